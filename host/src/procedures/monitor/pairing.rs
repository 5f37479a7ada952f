//! Pairs: each visible tracker frame with the device state at its capture
//! time (the clock map, the state history), and the gate that sets the
//! tracker's glitches aside.

use std::collections::VecDeque;
use std::time::Instant;

use spidar_protocol::messages::q16_to_mm;
use spidar_protocol::Event;

use crate::data::dataset::Sample;
use crate::data::stats::position_error;
use crate::device::link::Client;
use crate::device::tracker::TrackerFrame;
use crate::model::diagnose::{gross_tracker_threshold_mm, GROSS_TRACKER_MAX_SHARE};

use super::{Monitor, MonitorError, MonitorEvent};

/// One tracker frame paired with a device state.
#[derive(Clone, Debug, PartialEq)]
pub struct Pair {
    /// As a session row: `t_s` = `since_home_s` = device time since home,
    /// its capture (`home`), counts, tracker (room frame), commanded
    /// tensions.
    pub sample: Sample,
    /// Device time since boot, s.
    pub device_time_s: f64,
    /// The device's corrected position, room frame, mm.
    pub device_room_mm: [f64; 3],
    /// Its error against the tracker, mm.
    pub error_mm: f64,
    /// The string the device's kinematics left out (`State::excluded` of
    /// the state after the instant): one whose modelled length disagrees
    /// with the others.
    pub excluded: Option<u8>,
    /// Device time from the capture instant to the nearest state streamed, ms
    /// (the state is interpolated across it).
    pub gap_ms: f64,
}

/// Where the tracker sees the strings' meeting point in a frame of `body`:
/// its origin, or with a marker offset `p - R_body d` (`None` when the frame
/// has no rotation then: its meeting point is unknown).
pub fn tracked_point(
    body: &crate::device::tracker::BodyPose,
    marker_body_mm: Option<[f64; 3]>,
) -> Option<[f64; 3]> {
    match marker_body_mm {
        None => Some(body.position_mm),
        Some(d) => body
            .rotation
            .map(|r| crate::data::observe::meeting_point(&body.position_mm, &r, &d)),
    }
}

/// Host arrival time of a stream's frames from the stream's own clock: the
/// clock plus the smallest arrival offset seen over the last
/// [`ArrivalClock::HORIZON_S`] of that clock (the least delayed frame), so
/// that read jitter and a backlog read at once do not move it, while a
/// clock that steps or runs at another rate is followed within the
/// horizon. A clock going backwards (a reboot) starts over.
#[derive(Clone, Debug, Default)]
pub struct ArrivalClock {
    /// (clock, observed offset), offsets increasing: the front is the
    /// minimum over the horizon.
    offsets: VecDeque<(f64, f64)>,
    last_clock_s: f64,
}

impl ArrivalClock {
    /// Span of the sliding minimum, s of the stream's clock.
    pub const HORIZON_S: f64 = 2.0;

    /// The estimated arrival (host seconds) of a frame stamped `clock_s`
    /// that was read at `read_s` (host seconds, at or after its arrival).
    pub fn arrival(&mut self, clock_s: f64, read_s: f64) -> f64 {
        if clock_s < self.last_clock_s {
            self.offsets.clear();
        }
        self.last_clock_s = clock_s;
        let observed = read_s - clock_s;
        while self.offsets.back().is_some_and(|b| b.1 >= observed) {
            self.offsets.pop_back();
        }
        self.offsets.push_back((clock_s, observed));
        while self
            .offsets
            .front()
            .is_some_and(|f| f.0 < clock_s - Self::HORIZON_S)
        {
            self.offsets.pop_front();
        }
        clock_s + self.offsets.front().map_or(observed, |f| f.1)
    }
}

/// Sets aside the pairs whose tracker is a glitch (a reflection, a swapped
/// marker): an error beyond [`gross_tracker_threshold_mm`] of the baseline
/// window's median, as the calibration's
/// loop sets such training rows aside
/// ([`crate::model::diagnose::TrackerOutliers`]). One glitch of 200 mm
/// raises a 400-pair window's mean by half a millimetre, more than the
/// baseline: a tracker glitching on a few of its frames makes a device
/// that does not drift report drift. Pairs that far off in more
/// than [`GROSS_TRACKER_MAX_SHARE`] of a window are not glitches (the
/// device's position changed: a large slip on a device that cannot exclude
/// the string): they go into the window, for the drift check to see.
#[derive(Clone, Debug)]
pub struct GlitchGate {
    /// The error beyond which a pair is far, mm; `None` before the
    /// baseline (every pair is admitted).
    threshold_mm: Option<f64>,
    /// Whether each of the last `capacity` pairs was far.
    recent: VecDeque<bool>,
    capacity: usize,
}

impl GlitchGate {
    /// A gate judging over the last `capacity` pairs (the window's size).
    pub fn new(capacity: usize) -> GlitchGate {
        GlitchGate {
            threshold_mm: None,
            recent: VecDeque::with_capacity(capacity + 1),
            capacity: capacity.max(1),
        }
    }

    /// Sets the threshold from the baseline window's median error (mm);
    /// returns it.
    pub fn set_baseline(&mut self, median_mm: f64) -> f64 {
        let t = gross_tracker_threshold_mm(median_mm);
        self.threshold_mm = Some(t);
        t
    }

    /// Whether a pair of error `error_mm` goes into the window.
    pub fn admit(&mut self, error_mm: f64) -> bool {
        let Some(threshold) = self.threshold_mm else {
            return true;
        };
        let far = error_mm.is_nan() || error_mm > threshold;
        self.recent.push_back(far);
        while self.recent.len() > self.capacity {
            self.recent.pop_front();
        }
        if !far {
            return true;
        }
        let far_count = self.recent.iter().filter(|&&f| f).count();
        far_count as f64 > GROSS_TRACKER_MAX_SHARE * self.capacity as f64
    }
}

impl Monitor<'_> {
    /// A tracker frame: into the clock map, and its visible marker into the
    /// frames waiting for their state.
    pub(super) fn take_frame(&mut self, f: &TrackerFrame) {
        self.report.frames += 1;
        let read_s = self
            .config
            .host_clock
            .frame_arrival_s(f.received_at, self.base);
        self.sync.tracker_frame(f.ts_s, read_s);
        match f
            .body
            .as_ref()
            .filter(|b| b.id == self.config.body_id && b.is_visible())
        {
            Some(b) => match tracked_point(b, self.config.marker_body_mm) {
                Some(p) => self.pending.push_back((f.ts_s, read_s, p)),
                None => self.report.unoriented += 1,
            },
            None => self.report.occluded += 1,
        }
    }

    /// Reads the device's states into the history and the clock map (an
    /// error when it stayed silent too long; a new home restarts the
    /// window). Returns the host time now, s.
    pub(super) fn take_states(
        &mut self,
        client: &mut Client,
        last_state: &mut Instant,
        on_event: &mut dyn FnMut(&MonitorEvent),
    ) -> Result<f64, MonitorError> {
        let states = client.poll_states()?;
        let read_s = self.config.host_clock.states_arrival_s(self.base);
        let now_s = self.config.host_clock.now_s(self.base);
        if states.is_empty() {
            if last_state.elapsed() > self.config.device_timeout {
                return Err(MonitorError::DeviceSilent {
                    seconds: last_state.elapsed().as_secs_f64(),
                });
            }
        } else {
            *last_state = Instant::now();
        }
        if client
            .take_events()
            .iter()
            .any(|e| matches!(e, Event::Homed))
        {
            // The counts restart: the window no longer fits them (pairs
            // with states from before the home are not made).
            self.window.clear();
            on_event(&MonitorEvent::Note(
                "the device was homed again: the window restarts".into(),
            ));
        }
        for s in states {
            self.report.states += 1;
            self.home_us = s.time_us.saturating_sub(s.since_home_us);
            if self.home_id != Some(s.home_id) {
                self.home_id = Some(s.home_id);
                self.model_under_home();
            }
            self.sync.device_state(s.time_us, read_s);
            self.states.push(s);
        }
        Ok(now_s)
    }

    /// Pairs the pending tracker frames whose capture time the device
    /// stream has passed (or that waited longer than the gap): the device
    /// state at the frame's `ts` mapped to device time.
    pub(super) fn pair(&mut self, now_s: f64) {
        let gap = self.config.max_pair_gap;
        let gap_us = gap.as_micros() as u64;
        while let Some(&(ts_s, read_s, marker)) = self.pending.front() {
            let at_us = self.sync.device_time_us(ts_s);
            let newest = self
                .states
                .newest()
                .map_or(f64::NEG_INFINITY, |s| s.time_us as f64);
            let covered = at_us.is_some_and(|t| newest >= t);
            // Wait for the state after the frame: at most the gap in host
            // time, and on a simulated link as long as one sent after the
            // frame's instant is still on its way (the machine's pipe, not
            // the device, is late).
            let in_flight = self.config.host_clock.state_sent_since(read_s);
            if !covered && (now_s - read_s < gap.as_secs_f64() || in_flight) {
                break;
            }
            self.pending.pop_front();
            let Some((t, state)) = at_us.and_then(|t| self.states.at(t, gap_us).map(|s| (t, s)))
            else {
                self.report.unpaired += 1;
                continue;
            };
            if state.model_id != Some(self.model_id)
                || state.time_us.saturating_sub(state.since_home_us) != self.home_us
            {
                self.report.superseded += 1;
                continue;
            }
            let nearest_ms = self.states.nearest_gap_us(t).unwrap_or(0.0) / 1e3;
            let device_room_mm = state.corrected_mm.map(q16_to_mm);
            let pair = Pair {
                sample: Sample {
                    t_s: state.since_home_us as f64 / 1e6,
                    counts: state.counts,
                    tracker: Some(marker),
                    orientation: None,
                    legacy: None,
                    tension_n: Some(state.tensions_n.map(f64::from)),
                    since_home_s: Some(state.since_home_us as f64 / 1e6),
                    home: Some(state.home_id),
                },
                device_time_s: t.round() / 1e6,
                device_room_mm,
                error_mm: position_error(device_room_mm, marker),
                excluded: state.excluded,
                gap_ms: nearest_ms,
            };
            if !self.gate.admit(pair.error_mm) {
                self.report.glitches += 1;
                continue;
            }
            if self.config.record_pairs {
                self.report.recorded.push((ts_s, pair.clone()));
            }
            let first = self
                .report
                .device_span_s
                .map_or(pair.device_time_s, |(first, _)| first);
            self.report.device_span_s = Some((first, pair.device_time_s));
            self.window.push_back(pair);
            while self.window.len() > self.config.window {
                self.window.pop_front();
            }
            self.report.pairs += 1;
            self.since_check += 1;
        }
    }
}

#[cfg(test)]
mod tests;
