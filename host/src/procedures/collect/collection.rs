//! One lattice collection under way: [`collect`] opens or resumes the
//! session file, starts the device and fills the cells not done, one
//! capture per cell, then disarms the device whatever happened. The device's
//! states are kept by their own sample time and mapped to the host's clock
//! with the tracker's frames; each capture pairs a tracker frame whose
//! marker lies in the target cell with the state nearest to it.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use spidar_protocol::State;

use super::{disarm_advice, done_cells, CollectConfig, CollectError, CollectReport, Lattice, Stop};
use crate::data::dataset::{Sample, SessionAppender};
use crate::data::observe::orientation_of_rotation;
use crate::device::cues::{CueSink, Cues, Progress};
use crate::device::link::{Client, LinkError};
use crate::device::tracker::{
    ClockSync, HostClock, Next, StateHistory, TrackerFrame, TrackerSource,
};
use crate::procedures::arm_watch::{ArmWatch, ArmWatchError};
use spidar_core::geometry::distance;

/// Device states by their own sample time, and the clock map fed by
/// every state's and tracker frame's arrival.
struct States {
    history: StateHistory,
    sync: ClockSync,
    clock: HostClock,
    base: Instant,
    last_at: Instant,
    first: Option<State>,
    /// (newest before, first after), s of device time: a state stamped
    /// before the newest one (the device rebooted; its home is lost).
    went_back: Option<(f64, f64)>,
    /// When the device was last asked its uptime.
    last_probe: Instant,
}

impl States {
    fn new(clock: HostClock) -> States {
        States {
            history: StateHistory::new(),
            sync: ClockSync::new(),
            clock,
            base: Instant::now(),
            last_at: Instant::now(),
            first: None,
            went_back: None,
            last_probe: Instant::now(),
        }
    }

    fn poll(&mut self, client: &mut Client) -> Result<usize, LinkError> {
        let states = client.poll_states()?;
        let now = Instant::now();
        let n = states.len();
        if n > 0 {
            self.last_at = now;
        }
        let arrival_s = self.clock.states_arrival_s(self.base);
        for s in states {
            self.first.get_or_insert(s);
            if let Some(newest) = self.history.newest().filter(|n| s.time_us < n.time_us) {
                self.went_back
                    .get_or_insert((newest.time_us as f64 / 1e6, s.time_us as f64 / 1e6));
            }
            self.sync.device_state(s.time_us, arrival_s);
            self.history.push(s);
        }
        Ok(n)
    }

    /// Sends a heartbeat when one is due. A stream silent for that long is
    /// asked (as often) the device's uptime: a device that rebooted
    /// answers with its stream off and an uptime behind its last state
    /// (`went_back`).
    fn keep_alive(
        &mut self,
        client: &mut Client,
        last_request: &mut Instant,
        every: Duration,
    ) -> Result<(), LinkError> {
        if last_request.elapsed() >= every {
            client.heartbeat()?;
            *last_request = Instant::now();
        }
        if self.last_at.elapsed() >= every && self.last_probe.elapsed() >= every {
            self.last_probe = Instant::now();
            let uptime_us = client.stats()?.uptime_us;
            if let Some(newest) = self.history.newest().filter(|n| uptime_us < n.time_us) {
                self.went_back
                    .get_or_insert((newest.time_us as f64 / 1e6, uptime_us as f64 / 1e6));
            }
        }
        Ok(())
    }

    fn tracker_frame(&mut self, ts_s: f64, received_at: Instant) {
        let arrival_s = self.clock.frame_arrival_s(received_at, self.base);
        self.sync.tracker_frame(ts_s, arrival_s);
    }

    fn latest(&self) -> Option<&State> {
        self.history.newest()
    }
}

/// `t_s` as written: whole microseconds, so that a value read back and
/// written again (a resumed file) carries no float noise.
fn t_s_of(us: f64) -> f64 {
    (us.round()) / 1e6
}

/// Runs lattice collection on an open device session, appending to the
/// session CSV at `path` (created, or resumed: see the module
/// documentation).
pub fn collect(
    client: &mut Client,
    tracker: &mut dyn TrackerSource,
    lattice: &Lattice,
    config: &CollectConfig,
    path: &Path,
    sink: &mut dyn CueSink,
) -> Result<CollectReport, CollectError> {
    config.validate()?;
    // Before the file is touched or the device armed.
    config.check_reach(lattice)?;
    // The session has the device's strings (enc0..enc{N-1}): those of the
    // nominal string model it is given, else a Scalable-SPIDAR's 8.
    let strings = config.string_model.map_or(spidar_core::STRINGS, |m| {
        m.active_strings.count_ones() as usize
    });
    let opened = SessionAppender::open_for(path, strings)?;
    let done = done_cells(lattice, &opened.existing, path)?;
    let rows = opened.existing.samples.len();
    let last_home = opened.existing.samples.last().and_then(|s| {
        Some(LastHome {
            line: rows as u64 + 1,
            home: s.home?,
            since_home_s: s.since_home_s?,
        })
    });
    let mut report = CollectReport {
        path: path.to_path_buf(),
        total: lattice.len(),
        resumed_from: done.iter().filter(|d| d.is_some()).count(),
        captured: 0,
        done: 0,
        stop: Stop::Complete,
        elapsed: Duration::ZERO,
        torn: opened.torn,
        clock_offset_s: 0.0,
        frames: 0,
        occluded: 0,
        unpaired: 0,
        rearms: 0,
        oriented: 0,
        improper_rotations: 0,
        orientation_columns: opened.appender.has_orientation_columns(),
        orientations_not_recorded: 0,
    };
    report.done = report.resumed_from;
    if report.done == report.total {
        sink.show(&Cues {
            message: format!("all {} cells are already done", report.total),
            ..Cues::default()
        });
        return Ok(report);
    }
    let start = Instant::now();
    let mut appender = opened.appender;
    let result = run(
        Rig {
            client: &mut *client,
            tracker,
            sink: &mut *sink,
        },
        Plan {
            lattice,
            config,
            appender: &mut appender,
            done,
            last_home,
        },
        &mut report,
    );
    // Whatever happened, leave the motors off and the stream closed.
    let _ = client.disarm();
    let _ = client.stream_off();
    report.elapsed = start.elapsed();
    sink.show(&Cues {
        progress: Some(Progress {
            done: report.done,
            total: report.total,
            time_left: None,
        }),
        message: match &result {
            Ok(()) => format!(
                "{} cells captured, {}/{} done; motors off",
                report.captured, report.done, report.total
            ),
            Err(e) => format!("stopped: {e}"),
        },
        ..Cues::default()
    });
    result.map(|()| report)
}

/// What a collection talks to: the device, the tracker and the operator's
/// view.
struct Rig<'a> {
    client: &'a mut Client,
    tracker: &'a mut dyn TrackerSource,
    sink: &'a mut dyn CueSink,
}

/// What a collection fills: the lattice's cells not done, in order, into
/// the session file.
struct Plan<'a> {
    lattice: &'a Lattice,
    config: &'a CollectConfig,
    appender: &'a mut SessionAppender,
    /// The line of the row that captured each cell, by position in
    /// [`Lattice::order`] (see [`done_cells`]).
    done: Vec<Option<u64>>,
    /// The file's last row's home capture, when it records one.
    last_home: Option<LastHome>,
}

/// The home capture of a file's last row, and the time since it there.
struct LastHome {
    line: u64,
    home: u64,
    since_home_s: f64,
}

/// One collection under way: the rig, the plan, and what the steps share.
struct Collection<'r, 'p> {
    rig: Rig<'r>,
    plan: Plan<'p>,
    report: &'p mut CollectReport,
    /// The device's serial port (for errors).
    port: String,
    states: States,
    /// When the device last heard from this host.
    last_request: Instant,
    last_frame_at: Instant,
    arm_watch: ArmWatch,
}

fn run(rig: Rig<'_>, mut plan: Plan<'_>, report: &mut CollectReport) -> Result<(), CollectError> {
    let port = rig.client.port_name().to_string();
    let last_request = start_device(rig.client, plan.config)?;
    let path = plan.appender.path().to_path_buf();
    let last_home = plan.last_home.take();
    let mut c = Collection {
        states: States::new(plan.config.host_clock.clone()),
        arm_watch: ArmWatch::new(plan.config.max_rearms),
        rig,
        plan,
        report,
        port,
        last_request,
        last_frame_at: Instant::now(),
    };
    c.wait_for_first_state()?;
    c.check_the_file_home(&path, last_home)?;
    c.continue_the_file_clock();
    c.last_frame_at = Instant::now();
    c.fill_cells()
}

/// Gives a device without a calibration blob the nominal string model,
/// sets the limits, arms it at pre-tension and starts its stream. Returns
/// when the device last heard from the host.
fn start_device(client: &mut Client, config: &CollectConfig) -> Result<Instant, CollectError> {
    if let Some(model) = config.string_model {
        if client.info()?.is_none() {
            client.set_string_model(model)?;
        }
    }
    client.set_limits(config.limits)?;
    client.clear_faults()?;
    client.arm()?;
    let last_request = Instant::now();
    client.stream_on(config.decimation)?;
    Ok(last_request)
}

/// The time per cell of the last captures times the cells left; `None`
/// before two captures.
fn time_left(captures: &VecDeque<Instant>, report: &CollectReport) -> Option<Duration> {
    match (captures.front(), captures.back()) {
        (Some(a), Some(b)) if captures.len() >= 2 => {
            let per_cell = b.duration_since(*a).as_secs_f64() / (captures.len() - 1) as f64;
            let left = (report.total - report.done) as f64;
            Some(Duration::from_secs_f64(per_cell * left))
        }
        _ => None,
    }
}

impl Collection<'_, '_> {
    /// Waits for the first state, which gives the device clock (sending
    /// heartbeats meanwhile).
    fn wait_for_first_state(&mut self) -> Result<(), CollectError> {
        let config = self.plan.config;
        let waiting_since = Instant::now();
        while self.states.first.is_none() {
            self.states.poll(self.rig.client)?;
            // Frames read meanwhile feed the clock map (and a simulated
            // tracker in step with this procedure waits for them).
            if let Next::Frame(f) = self.rig.tracker.next_frame(Duration::from_millis(1))? {
                self.states.tracker_frame(f.ts_s, f.received_at);
            }
            if waiting_since.elapsed() > config.device_timeout {
                return Err(CollectError::DeviceSilent {
                    port: self.port.clone(),
                    seconds: waiting_since.elapsed().as_secs_f64(),
                });
            }
            if self.last_request.elapsed() >= config.heartbeat_every {
                self.rig.client.heartbeat()?;
                self.last_request = Instant::now();
            }
        }
        Ok(())
    }

    /// A device under the file's last home capture (the same id) must be
    /// at least as long after it as that row was: else the id names two
    /// captures (a boot id drawn twice) and the new rows would read as the
    /// old capture's time going back. Refused before the first capture.
    fn check_the_file_home(&self, file: &Path, last: Option<LastHome>) -> Result<(), CollectError> {
        let (Some(last), Some(first)) = (last, self.states.first) else {
            return Ok(());
        };
        let device_s = first.since_home_us as f64 / 1e6;
        if first.home_id == last.home && device_s < last.since_home_s {
            return Err(CollectError::HomeIdReused {
                file: file.to_path_buf(),
                line: last.line,
                home: last.home,
                file_s: last.since_home_s,
                device_s,
            });
        }
        Ok(())
    }

    /// A first state behind the file's last row means a reboot: `t_s`
    /// continues from that row.
    fn continue_the_file_clock(&mut self) {
        let first_s = self.states.first.map_or(0.0, |s| s.time_us as f64 / 1e6);
        if let Some(last) = self.plan.appender.last_t_s() {
            if first_s < last {
                self.report.clock_offset_s = t_s_of((last - first_s) * 1e6);
            }
        }
    }

    fn cancelled(&self) -> bool {
        self.plan
            .config
            .cancel
            .as_ref()
            .is_some_and(|c| c.load(Ordering::SeqCst))
    }

    /// Shows the cells not done in order, and captures each, until every
    /// cell is done, `max_cells` were captured or the run is cancelled.
    fn fill_cells(&mut self) -> Result<(), CollectError> {
        let order = self.plan.lattice.order();
        let mut captures: VecDeque<Instant> = VecDeque::new();
        while let Some(index) = self.plan.done.iter().position(Option::is_none) {
            if self
                .plan
                .config
                .max_cells
                .is_some_and(|m| self.report.captured >= m)
            {
                self.report.stop = Stop::MaxCells;
                return Ok(());
            }
            let progress = Some(Progress {
                done: self.report.done,
                total: self.report.total,
                time_left: time_left(&captures, self.report),
            });
            let Some(row) = self.capture(order[index], progress)? else {
                self.report.stop = Stop::Cancelled;
                return Ok(());
            };
            let line = self.plan.appender.append(&row)?;
            self.plan.done[index] = Some(line);
            self.report.captured += 1;
            self.report.done += 1;
            self.arm_watch.progress();
            captures.push_back(Instant::now());
            while captures.len() > self.plan.config.eta_window {
                captures.pop_front();
            }
        }
        self.report.stop = Stop::Complete;
        Ok(())
    }

    /// Frames until one captures `cell`: its row; `None` when the run was
    /// cancelled.
    fn capture(
        &mut self,
        cell: [u32; 3],
        progress: Option<Progress>,
    ) -> Result<Option<Sample>, CollectError> {
        let centre = self.plan.lattice.cell_centre(cell);
        loop {
            if self.cancelled() {
                return Ok(None);
            }
            self.watch_device()?;
            let Some(frame) = self.next_frame()? else {
                continue;
            };
            if self.states.went_back.is_some() {
                continue;
            }
            let cues = Cues {
                target_room_mm: Some(centre),
                target_half_size_mm: self.plan.lattice.cell_mm() / 2.0,
                progress,
                ..Cues::default()
            };
            if let Some(row) = self.try_capture(&frame, cell, cues)? {
                return Ok(Some(row));
            }
        }
    }

    /// Reads the device's states and keeps it going: an error for a device
    /// that rebooted, keeps disarming itself or fell silent; re-arms one
    /// that disarmed itself; sends the heartbeat when due.
    fn watch_device(&mut self) -> Result<(), CollectError> {
        let config = self.plan.config;
        self.states.poll(self.rig.client)?;
        // A device that rebooted has lost its home: no rearm helps.
        if let Some((previous_s, now_s)) = self.states.went_back {
            return Err(CollectError::ClockWentBack {
                port: self.port.clone(),
                previous_s,
                now_s,
            });
        }
        // A device that disarmed itself is armed again, a few times.
        let latest = self.states.latest().map(|s| (s.armed, s.faults));
        match self.arm_watch.check(self.rig.client, latest) {
            Ok(true) => {
                self.report.rearms += 1;
                self.last_request = Instant::now();
            }
            Ok(false) => {}
            Err(ArmWatchError::Link(e)) => return Err(e.into()),
            Err(ArmWatchError::KeepsDisarming { events, last }) => {
                let faults = self.states.latest().map_or(0, |s| s.faults.0);
                let simulated = matches!(config.host_clock, HostClock::Simulated(_));
                return Err(CollectError::KeepsDisarming {
                    events,
                    last,
                    advice: disarm_advice(faults, simulated),
                });
            }
        }
        if self.states.last_at.elapsed() > config.device_timeout {
            return Err(CollectError::DeviceSilent {
                port: self.port.clone(),
                seconds: self.states.last_at.elapsed().as_secs_f64(),
            });
        }
        self.states.keep_alive(
            self.rig.client,
            &mut self.last_request,
            config.heartbeat_every,
        )?;
        Ok(())
    }

    /// The next tracker frame (fed to the clock map and answered with a
    /// heartbeat); `None` when none came yet. An error when the tracker
    /// ended or stayed silent too long.
    fn next_frame(&mut self) -> Result<Option<TrackerFrame>, CollectError> {
        let config = self.plan.config;
        // A short wait: states are read (and stamped) at least every
        // 2 ms, so some arrive promptly enough for the clock map.
        let frame = match self.rig.tracker.next_frame(Duration::from_millis(2))? {
            Next::Frame(f) => f,
            Next::End => {
                return Err(CollectError::TrackerEnded {
                    tracker: config.tracker_label.clone(),
                })
            }
            Next::Timeout => {
                if self.last_frame_at.elapsed() > config.tracker_timeout {
                    return Err(CollectError::TrackerSilent {
                        tracker: config.tracker_label.clone(),
                        seconds: self.last_frame_at.elapsed().as_secs_f64(),
                    });
                }
                return Ok(None);
            }
        };
        self.last_frame_at = Instant::now();
        self.report.frames += 1;
        self.states.tracker_frame(frame.ts_s, frame.received_at);
        // Every tracker frame is a heartbeat too: the device hears from
        // the host at the tracker's rate in its own time, however fast
        // or slow the host runs.
        self.rig.client.heartbeat()?;
        self.last_request = Instant::now();
        Ok(Some(frame))
    }

    /// Shows `frame`'s cues (`cues` gives the target) and, when its visible
    /// marker lies inside `cell` and an armed device state pairs with it,
    /// the row it captures.
    fn try_capture(
        &mut self,
        frame: &TrackerFrame,
        cell: [u32; 3],
        mut cues: Cues,
    ) -> Result<Option<Sample>, CollectError> {
        let lattice = self.plan.lattice;
        let body = frame
            .body
            .as_ref()
            .filter(|b| b.id == self.plan.config.body_id && b.is_visible());
        let marker = body.map(|b| b.position_mm);
        let rotation = body.and_then(|b| b.rotation);
        cues.marker_room_mm = marker;
        let Some(marker) = marker else {
            self.report.occluded += 1;
            cues.message = "marker occluded: bring it back into the tracker's view".into();
            self.rig.sink.show(&cues);
            return Ok(None);
        };
        let d = lattice.distance_to(cell, &marker);
        cues.distance_mm = Some(d);
        if !lattice.contains(cell, &marker) {
            cues.message = format!(
                "move into the highlighted cell {}/{} {cell:?} ({:.0} mm from its centre)",
                self.report.done + 1,
                self.report.total,
                distance(marker, lattice.cell_centre(cell))
            );
            self.rig.sink.show(&cues);
            return Ok(None);
        }
        let (at_us, paired) = self.state_at(frame.ts_s)?;
        match paired {
            Some(s) if s.armed => {
                // Never before the last row.
                let t_s = t_s_of(s.time_us as f64 + self.report.clock_offset_s * 1e6)
                    .max(self.plan.appender.last_t_s().unwrap_or(0.0));
                cues.message = format!(
                    "captured cell {}/{}",
                    self.report.done + 1,
                    self.report.total
                );
                self.rig.sink.show(&cues);
                Ok(Some(self.row_of(&s, t_s, marker, rotation)))
            }
            other => {
                self.report.unpaired += 1;
                cues.message = match (other, at_us) {
                    (Some(s), _) => format!(
                        "inside: waiting for the device to arm (faults {:#06x})",
                        s.faults.0
                    ),
                    (None, None) => {
                        "inside: synchronizing the device's and the tracker's clocks".into()
                    }
                    (None, Some(_)) => {
                        "inside: no device state around the frame's time (a gap in the stream)"
                            .into()
                    }
                };
                self.rig.sink.show(&cues);
                Ok(None)
            }
        }
    }

    /// The device state at a frame's capture time (the tracker's stamp
    /// `ts_s` mapped to device time, `None` before the clock map is ready),
    /// interpolated between the two states around it; waits for the state
    /// after it.
    fn state_at(&mut self, ts_s: f64) -> Result<(Option<f64>, Option<State>), CollectError> {
        let config = self.plan.config;
        let states = &mut self.states;
        let at_us = if states.sync.ready() {
            states.sync.device_time_us(ts_s)
        } else {
            None
        };
        let wait_from = Instant::now();
        if let Some(t) = at_us {
            while states.latest().is_some_and(|s| (s.time_us as f64) < t)
                && states.went_back.is_none()
                && wait_from.elapsed() < config.device_timeout
            {
                states.poll(self.rig.client)?;
                states.keep_alive(
                    self.rig.client,
                    &mut self.last_request,
                    config.heartbeat_every,
                )?;
                std::thread::sleep(Duration::from_micros(200));
            }
        }
        let max_gap_us = config.max_pairing_gap.as_micros() as u64;
        Ok((at_us, at_us.and_then(|t| states.history.at(t, max_gap_us))))
    }

    /// The row of a capture: device state `s`, `t_s`, the tracker's marker
    /// and, when the file takes it, the body's orientation.
    fn row_of(
        &mut self,
        s: &State,
        t_s: f64,
        marker: [f64; 3],
        rotation: Option<[[f64; 3]; 3]>,
    ) -> Sample {
        let report = &mut *self.report;
        let orientation = rotation.and_then(|r| {
            let q = orientation_of_rotation(&r);
            report.improper_rotations += u64::from(q.is_none());
            q
        });
        let orientation = orientation.filter(|_| {
            let fits = self.plan.appender.has_orientation_columns();
            report.orientations_not_recorded += u64::from(!fits);
            fits
        });
        report.oriented += u64::from(orientation.is_some());
        // A file an older collect started has no home columns: its rows
        // go on without them (as its header says).
        let home_fits = self.plan.appender.has_home_columns();
        Sample {
            t_s,
            counts: s.counts,
            tracker: Some(marker),
            orientation,
            legacy: Some(s.position_mm.map(f64::from)),
            tension_n: Some(s.tensions_n.map(f64::from)),
            since_home_s: Some(s.since_home_us as f64 / 1e6).filter(|_| home_fits),
            home: Some(s.home_id).filter(|_| home_fits),
        }
    }
}
