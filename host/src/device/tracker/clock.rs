//! Pairing by timestamps: the map between the device's clock and the
//! tracker's, fitted online, and the device state interpolated at a tracker
//! frame's capture time.
//!
//! Each stream stamps its samples with its own clock: the device's state
//! frames with the control loop's timer (`State::time_us`), the tracker's
//! frames with the camera time (DTrack `ts`). The host sees when each
//! arrives; an arrival is its stamp plus a constant (the clocks' offset to
//! the host's, and the least transport delay) plus a delay that is never
//! negative (the link, the reader's scheduling). The least delayed samples
//! therefore lie on a line in (stamp, arrival - stamp): [`ClockSync`] keeps
//! the smallest `arrival - stamp` of each stream per [`ClockSync::BUCKET_S`]
//! of its clock and fits a line through those minima (offset and drift)
//! over the last [`ClockSync::HORIZON_S`]; the device-to-tracker map is the
//! difference of the two lines. However late the host reads, a sample's
//! stamp does not change, so the pairs do not depend on how the host is
//! scheduled; the host's delays only have to leave a few prompt samples per
//! bucket.
//!
//! What the arrival times cannot see is a constant latency inside a stream
//! before its stamp reaches the host (a tracker's processing time between
//! the exposure and `ts` being sent is not one: `ts` is the exposure). On a
//! rig with such a latency, [`super::sync::estimate_time_shift`] on the
//! motion of both streams measures it.

use std::collections::VecDeque;
use std::time::Instant;

use spidar_protocol::State;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// The simulated world's clock: how far it has been computed, µs of
/// simulated time (device time since the virtual device's first boot; it
/// does not restart at a power cycle). The virtual device moves it at each
/// tick of a plant with a hand ([`crate::sim::plant::Hand`]) before that tick's outputs are written,
/// so no sample is read before the instant it is stamped. In a simulated rig it
/// is also the host's clock: where a procedure reads the time it stamps
/// arrivals with ([`crate::device::tracker::HostClock::Simulated`]), so that how
/// the machine schedules the host's threads plays no part. Clones share
/// the clock.
#[derive(Clone, Debug, Default)]
pub struct SimClock {
    now: Arc<AtomicU64>,
    sent: Arc<AtomicU64>,
}

impl SimClock {
    /// Simulated time computed so far, µs.
    pub fn now_us(&self) -> u64 {
        self.now.load(Ordering::SeqCst)
    }

    /// Simulated time at which the device last sent a state, µs: when
    /// the newest state a host reads arrived (the simulated link has no
    /// delay, and this is its receive timestamp, not the reader's).
    pub fn last_sent_us(&self) -> u64 {
        self.sent.load(Ordering::SeqCst)
    }

    /// The world has been computed up to `t_us` (it never goes back).
    pub(crate) fn set(&self, t_us: u64) {
        self.now.fetch_max(t_us, Ordering::SeqCst);
    }

    /// The device sent a state stamped `t_us`.
    pub(crate) fn note_sent(&self, t_us: u64) {
        self.sent.fetch_max(t_us, Ordering::SeqCst);
    }
}

impl PartialEq for SimClock {
    /// The same clock (shared handle).
    fn eq(&self, other: &SimClock) -> bool {
        Arc::ptr_eq(&self.now, &other.now)
    }
}

/// The clock a procedure stamps arrivals with (the host's clock in
/// [`ClockSync`]'s terms).
#[derive(Clone, Debug, Default, PartialEq)]
pub enum HostClock {
    /// The wall clock: a real rig.
    #[default]
    Wall,
    /// A simulated rig's clock ([`SimClock`]): the host is part of the
    /// simulated world, and a sample is read at the simulated instant the
    /// world has reached, however late the machine ran the host's thread.
    Simulated(SimClock),
}

impl HostClock {
    /// Now, s since `base` (wall) or since the simulated world's start.
    pub fn now_s(&self, base: Instant) -> f64 {
        match self {
            HostClock::Wall => Instant::now().saturating_duration_since(base).as_secs_f64(),
            HostClock::Simulated(c) => c.now_us() as f64 / 1e6,
        }
    }

    /// When the device states just read arrived: now on the wall clock; on
    /// a simulated one, when the newest of them was sent (the simulated
    /// link's receive stamp: the reader may look later than the world it
    /// waits on has gone).
    pub fn states_arrival_s(&self, base: Instant) -> f64 {
        match self {
            HostClock::Wall => self.now_s(base),
            HostClock::Simulated(c) => c.last_sent_us() as f64 / 1e6,
        }
    }

    /// Whether the device has sent a state at or after host time `t_s`
    /// (this clock's seconds) that may not have been read yet: a simulated
    /// link knows when the device last sent one; a real one cannot
    /// (false), and the reader waits its gap in host time.
    pub fn state_sent_since(&self, t_s: f64) -> bool {
        match self {
            HostClock::Wall => false,
            HostClock::Simulated(c) => c.last_sent_us() as f64 / 1e6 >= t_s,
        }
    }

    /// When a tracker frame the receiver stamped `received_at` (wall) was
    /// read: that stamp on the wall clock, now on a simulated one (the
    /// frame is taken as it is read).
    pub fn frame_arrival_s(&self, received_at: Instant, base: Instant) -> f64 {
        match self {
            HostClock::Wall => received_at.saturating_duration_since(base).as_secs_f64(),
            HostClock::Simulated(_) => self.now_s(base),
        }
    }
}

/// Arrival-time minima of one stream, per bucket of its own clock.
#[derive(Clone, Debug, Default)]
struct Envelope {
    /// (bucket index, stamp at the minimum, smallest arrival - stamp), in
    /// bucket order.
    minima: VecDeque<(i64, f64, f64)>,
    last_stamp_s: Option<f64>,
}

impl Envelope {
    fn add(&mut self, stamp_s: f64, arrival_s: f64) {
        if self.last_stamp_s.is_some_and(|l| stamp_s < l - 1e-6) {
            // The clock went back (a reboot): a new clock.
            self.minima.clear();
        }
        self.last_stamp_s = Some(stamp_s);
        let bucket = (stamp_s / ClockSync::BUCKET_S).floor() as i64;
        let d = arrival_s - stamp_s;
        match self.minima.back_mut() {
            Some(b) if b.0 == bucket => {
                if d < b.2 {
                    *b = (bucket, stamp_s, d);
                }
            }
            _ => self.minima.push_back((bucket, stamp_s, d)),
        }
        let keep = (ClockSync::HORIZON_S / ClockSync::BUCKET_S).ceil() as i64;
        while self.minima.front().is_some_and(|f| f.0 < bucket - keep) {
            self.minima.pop_front();
        }
    }

    /// `arrival - stamp` of a prompt sample at `stamp_s`: the line through
    /// the complete buckets' minima (the newest bucket is still filling;
    /// alone it is used as it stands), or `None` without data.
    fn delay_at(&self, stamp_s: f64) -> Option<f64> {
        let n = self.minima.len();
        let complete: Vec<(f64, f64)> = if n >= 2 {
            self.minima
                .iter()
                .take(n - 1)
                .map(|&(_, s, d)| (s, d))
                .collect()
        } else {
            self.minima.iter().map(|&(_, s, d)| (s, d)).collect()
        };
        match complete.len() {
            0 => None,
            1 | 2 => complete.iter().map(|p| p.1).reduce(f64::min),
            m => {
                // Least squares line d = a + b (s - s0).
                let s0 = complete.iter().map(|p| p.0).sum::<f64>() / m as f64;
                let d0 = complete.iter().map(|p| p.1).sum::<f64>() / m as f64;
                let sxx: f64 = complete.iter().map(|p| (p.0 - s0).powi(2)).sum();
                let sxy: f64 = complete.iter().map(|p| (p.0 - s0) * (p.1 - d0)).sum();
                // Two crystals drift by parts per million; a steeper line is
                // a backlog draining (a host that read late for a while, and
                // then caught up), not the clocks: keep the slope physical
                // and let the floor below find the prompt samples.
                let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
                let b = b.clamp(-ClockSync::MAX_DRIFT, ClockSync::MAX_DRIFT);
                // A line through minima of a noisy delay sits above the
                // floor by the minima's own scatter: pin it to the floor
                // (the smallest residual), keeping the slope.
                let floor = complete
                    .iter()
                    .map(|p| p.1 - (d0 + b * (p.0 - s0)))
                    .fold(f64::INFINITY, f64::min);
                Some(d0 + floor + b * (stamp_s - s0))
            }
        }
    }
}

/// The online map between device time and tracker time (see the module
/// documentation).
#[derive(Clone, Debug, Default)]
pub struct ClockSync {
    device: Envelope,
    tracker: Envelope,
}

impl ClockSync {
    /// Span of one bucket of a stream's clock, s.
    pub const BUCKET_S: f64 = 0.25;
    /// Span of the fit, s of a stream's clock.
    pub const HORIZON_S: f64 = 8.0;
    /// Largest drift of a stream's clock against the host's that the fit
    /// believes (1000 ppm; crystals are within 100).
    pub const MAX_DRIFT: f64 = 1e-3;

    pub fn new() -> ClockSync {
        ClockSync::default()
    }

    /// A device state stamped `time_us` read at `arrival_s` (host seconds,
    /// any fixed origin shared with [`ClockSync::tracker_frame`]).
    pub fn device_state(&mut self, time_us: u64, arrival_s: f64) {
        self.device.add(time_us as f64 / 1e6, arrival_s);
    }

    /// A tracker frame stamped `ts_s` read at `arrival_s`.
    pub fn tracker_frame(&mut self, ts_s: f64, arrival_s: f64) {
        self.tracker.add(ts_s, arrival_s);
    }

    /// Both streams have a complete bucket: the map is usable.
    pub fn ready(&self) -> bool {
        self.device.minima.len() >= 2 && self.tracker.minima.len() >= 2
    }

    /// `tracker_ts - device_t` at tracker time `ts_s` (s), if known.
    pub fn offset_at_tracker_s(&self, ts_s: f64) -> Option<f64> {
        // host = ts + dt(ts) = t + dd(t): solve for t by fixed point,
        // starting from the device line where it has data (the two clocks
        // may be hours apart: a line's slope, noise, extrapolated that far
        // would throw the first guess off by seconds). Each step shrinks
        // the error by the slope of the device line (well below 1).
        let host = ts_s + self.tracker.delay_at(ts_s)?;
        let newest = self.device.minima.back().map(|m| m.1)?;
        let mut t = host - self.device.delay_at(newest)?;
        for _ in 0..8 {
            let next = host - self.device.delay_at(t)?;
            let done = (next - t).abs() < 1e-9;
            t = next;
            if done {
                break;
            }
        }
        Some(ts_s - t)
    }

    /// The device time (µs, fractional) of the instant the tracker stamped
    /// `ts_s`.
    pub fn device_time_us(&self, ts_s: f64) -> Option<f64> {
        let offset = self.offset_at_tracker_s(ts_s)?;
        Some((ts_s - offset) * 1e6)
    }
}

/// Recent device states in stream order, to read the state at any instant
/// between two of them.
#[derive(Clone, Debug, Default)]
pub struct StateHistory {
    states: VecDeque<State>,
}

impl StateHistory {
    /// States older than this behind the newest are dropped, µs.
    pub const KEEP_US: u64 = 2_000_000;

    pub fn new() -> StateHistory {
        StateHistory::default()
    }

    /// Adds the next state; a state older than the newest (a reboot) starts
    /// the history over.
    pub fn push(&mut self, state: State) {
        if self
            .states
            .back()
            .is_some_and(|b| state.time_us < b.time_us)
        {
            self.states.clear();
        }
        self.states.push_back(state);
        while self
            .states
            .front()
            .is_some_and(|f| f.time_us + Self::KEEP_US < state.time_us)
        {
            self.states.pop_front();
        }
    }

    pub fn clear(&mut self) {
        self.states.clear();
    }

    pub fn newest(&self) -> Option<&State> {
        self.states.back()
    }

    pub fn is_empty(&self) -> bool {
        self.states.is_empty()
    }

    /// Device time from `t_us` to the nearest state held, µs.
    pub fn nearest_gap_us(&self, t_us: f64) -> Option<f64> {
        self.states
            .iter()
            .map(|s| (s.time_us as f64 - t_us).abs())
            .reduce(f64::min)
    }

    /// The state at device time `t_us`: the two states around it, no more
    /// than `max_gap_us` apart, interpolated linearly (counts rounded to
    /// the nearest count, positions and tensions as `f32`); flags and ids
    /// from the later one. `None` if `t_us` is outside the history, falls
    /// in a gap, or between two states of different homes (their counts
    /// start from different zeros) or different models.
    pub fn at(&self, t_us: f64, max_gap_us: u64) -> Option<State> {
        let k = self.states.partition_point(|s| (s.time_us as f64) < t_us);
        let b = self.states.get(k)?;
        if (b.time_us as f64 - t_us).abs() < 0.5 {
            return Some(*b);
        }
        let a = self.states.get(k.checked_sub(1)?)?;
        let span = b.time_us.checked_sub(a.time_us)?;
        let home = |s: &State| s.time_us.saturating_sub(s.since_home_us);
        // Counts of two homes, or positions of two models, do not mix.
        if span == 0 || span > max_gap_us || a.model_id != b.model_id || home(a) != home(b) {
            return None;
        }
        let w = (t_us - a.time_us as f64) / span as f64;
        let mix = |x: f64, y: f64| x + w * (y - x);
        let mut s = *b;
        s.time_us = t_us.round() as u64;
        s.since_home_us = s.time_us - home(b);
        for i in 0..s.counts.len() {
            s.counts[i] = mix(f64::from(a.counts[i]), f64::from(b.counts[i])).round() as i32;
            s.tensions_n[i] = mix(f64::from(a.tensions_n[i]), f64::from(b.tensions_n[i])) as f32;
        }
        for k in 0..3 {
            s.position_mm[k] = mix(f64::from(a.position_mm[k]), f64::from(b.position_mm[k])) as f32;
            s.corrected_mm[k] =
                mix(f64::from(a.corrected_mm[k]), f64::from(b.corrected_mm[k])).round() as i32;
        }
        s.armed = a.armed && b.armed;
        s.motors_on = a.motors_on && b.motors_on;
        Some(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_map_comes_from_the_least_delayed_samples_whatever_the_delays() {
        // Tracker ts = device t + 36000 s + 40 ppm drift; the host's clock
        // is the device's + 5 s. Delays: 0.05..30 ms, mostly late.
        let mut sync = ClockSync::new();
        let mut seed = 1u64;
        let mut delay = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = (seed >> 11) as f64 / (1u64 << 53) as f64;
            5e-5 + 0.03 * u * u
        };
        for k in 0..4000u64 {
            let t = k as f64 * 0.002;
            sync.device_state(k * 2000, 5.0 + t + delay());
            if k % 5 == 0 {
                let ts = 36_000.0 + t * (1.0 + 40e-6);
                sync.tracker_frame(ts, 5.0 + t + delay());
            }
        }
        assert!(sync.ready());
        for t in [6.0, 7.5] {
            let ts = 36_000.0 + t * (1.0 + 40e-6);
            let got = sync.device_time_us(ts).unwrap() / 1e6;
            assert!((got - t).abs() < 1e-4, "{t}: {got}");
        }
    }

    fn state(t_us: u64, c: i32) -> State {
        State {
            time_us: t_us,
            since_home_us: t_us,
            home_id: 1,
            counts: [c; 8],
            position_mm: [c as f32; 3],
            corrected_mm: [c; 3],
            tensions_n: [1.0; 8],
            rendered_force_n: [0.0; 3],
            faults: Default::default(),
            slack: 0,
            excluded: None,
            loop_us: 0,
            loop_max_us: 0,
            armed: true,
            motors_on: true,
            model_id: None,
        }
    }

    #[test]
    fn a_state_between_two_is_interpolated_and_a_gap_is_not_bridged() {
        let mut h = StateHistory::new();
        h.push(state(1000, 0));
        h.push(state(3000, 100));
        h.push(state(20_000, 200));
        let s = h.at(1500.0, 5000).unwrap();
        assert_eq!(s.counts[0], 25);
        assert_eq!(s.time_us, 1500);
        assert_eq!(h.at(3000.0, 5000).unwrap().counts[0], 100);
        assert!(h.at(10_000.0, 5000).is_none(), "a gap");
        assert!(h.at(500.0, 5000).is_none(), "before the history");
        assert!(h.at(25_000.0, 5000).is_none(), "after it");
    }

    #[test]
    fn states_of_two_homes_or_two_models_are_not_mixed() {
        let mut h = StateHistory::new();
        h.push(state(1000, 0));
        // Homed at 1500 µs: counts restart.
        h.push(State {
            since_home_us: 500,
            ..state(2000, 7)
        });
        h.push(State {
            since_home_us: 1500,
            ..state(3000, 9)
        });
        // A new model from 4000 µs on.
        h.push(State {
            since_home_us: 2500,
            model_id: Some(5),
            ..state(4000, 11)
        });
        assert!(h.at(1200.0, 5000).is_none(), "across the home");
        let s = h.at(2500.0, 5000).unwrap();
        assert_eq!((s.counts[0], s.since_home_us), (8, 1000));
        assert!(h.at(3500.0, 5000).is_none(), "across the reflash");
        assert_eq!(h.at(4000.0, 5000).unwrap().model_id, Some(5));
    }
}
