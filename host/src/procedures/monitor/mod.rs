//! `spidar monitor`: runtime recalibration (paper, section 5.5).
//!
//! While someone uses the device and the optical tracker sees the marker,
//! the host watches the calibration the device runs:
//!
//! 1. **Pairs.** The device streams its state, the tracker its frames. Each
//!    visible tracker frame is paired with the device state *at its capture
//!    time*: the frame's `ts` mapped to device time by the clock map fitted
//!    online from both streams' least delayed arrivals
//!    ([`crate::device::tracker::ClockSync`], offset and drift), the state there
//!    interpolated between the two streamed around it
//!    ([`crate::device::tracker::StateHistory`]). How late the host reads either
//!    stream does not move a pair. A frame whose instant falls in a gap of
//!    the stream wider than [`MonitorConfig::max_pair_gap`] is not paired
//!    (counted as
//!    `unpaired`); occluded frames are counted and skipped. A rolling
//!    window of the last [`MonitorConfig::window`] pairs is kept as
//!    dataset [`Sample`](crate::data::dataset::Sample)s (counts, device time since home, tracker,
//!    commanded tensions): the same data identification and diagnosis read
//!    from a session file.
//! 2. **Error.** Each pair carries the error of the position the device
//!    itself reports (`State::corrected_mm`, its fixed-point pipeline)
//!    against the tracker ([`crate::data::stats::position_error`]); the baseline
//!    is the first full window after the start.
//! 3. **Drift.** Every [`MonitorConfig::check_every`] new pairs, the
//!    residual diagnosis of the *current* calibration runs on the window
//!    ([`crate::model::diagnose::diagnose`]: score tests of every effect family
//!    the model lacks, with the slip's time search). Drift is reported when
//!    it finds a significant effect of a family that can appear at run time
//!    ([`MonitorConfig::drift_families`]; slip, offset, drift by
//!    default) at least [`MonitorConfig::min_amplitude_mm`] large, and/or
//!    the window error exceeds the baseline by
//!    [`MonitorConfig::error_factor`] (and by at least
//!    [`MonitorConfig::min_error_rise_mm`]). The effect must also explain a
//!    share of the residual ([`MonitorConfig::min_explained`]): the window's
//!    residual is not white, and chi-square alone over-rates weak terms.
//! 4. **Refit and reflash** ([`RefitPolicy`]: ask, yes, no). The found
//!    effects are added to the calibration's structure one at a time, each
//!    kept only if the cross-validated error on the pairs falls (the
//!    diagnosis loop's rule, [`crate::model::diagnose::cross_validated_error`]);
//!    the model is identified again (warm, from the current calibration) on
//!    the window, plus the training session when given (its rows count as
//!    before anything that happened at run time: at their own time since
//!    home when they are of the window's home capture, else at time since
//!    home 0; left out when the model has a time drift term). The learned position
//!    correction, if any, is kept. The new calibration is compiled
//!    ([`crate::model::compile::compile_checked`]), the device disarmed and
//!    flashed ([`Client::flash`], verified with `info`), and monitoring goes
//!    on: the first full window after the reflash is the error *after*, the
//!    window at detection the error *before*, both with the same statistic.
//!
//! The model the window is judged and refitted with is the calibration as
//! the device runs it under its current home capture ([`under_home`]):
//! with the training session's slips while the states' `home_id` is the
//! calibration's (`home`), without them after a new `Home` or a reboot. A
//! refit writes the slips back under the capture the states are under: the
//! training's (refitted) while it is theirs, and every slip it found at run
//! time, so that the next `Home` ends them on the device and here alike;
//! `effects` stays the model for the next home capture.
//!
//! The monitor never arms the device. Device time since home is device
//! time since boot (a device with a stored model homes at boot) unless a
//! `Homed` event is seen, after which it counts from that state on.
//!
//! The state machine is here; the pairs are made in `pairing.rs`, the
//! drift check runs in `check.rs`, the refit and reflash in `refit.rs`, on
//! the calibration as `calibration.rs` reads it; `simulated.rs` is a rig to
//! run it on, `text.rs` the lines a run prints.

mod calibration;
mod check;
mod config;
mod pairing;
mod refit;
mod simulated;
mod text;

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use spidar_core::model::Calibration;

use crate::data::dataset::{DatasetError, Geometry, Session};
use crate::data::stats::ErrorStats;
use crate::device::link::{Client, LinkError};
use crate::device::tracker::{ClockSync, StateHistory};
use crate::device::tracker::{Next, TrackerError, TrackerSource};
use crate::model::compile::{model_id_of, CompileCmdError};
use crate::model::diagnose::{Family, GROSS_TRACKER_MAX_SHARE};
use crate::model::identify::{Identification, IdentifyError, Structure};

pub use calibration::{check_calibration, identification_of, structure_of, under_home};
pub use check::{Check, StringsSeen};
pub use config::{MonitorConfig, RefitPolicy};
pub use pairing::{tracked_point, ArrivalClock, GlitchGate, Pair};
pub use refit::Refit;
pub use simulated::{
    calibrate_simulated, calibrate_simulated_with, SimCalibration, SimRigConfig,
    SimulatedMonitorRig,
};
pub use text::{describe_finding, event_line, summary};

use check::confirmed_by_name;

/// Why monitoring stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum MonitorError {
    #[error("monitor: {0}")]
    Config(#[from] crate::ConfigError),
    #[error("{}: `{field}`: {problem}", file.display())]
    Calibration {
        file: PathBuf,
        field: String,
        problem: String,
    },
    #[error(
        "{}: the device runs {}, this calibration is model {calibration:#010x} (flash it first, or pass the calibration the device runs)",
        file.display(),
        match device { Some(id) => format!("model {id:#010x}"), None => "no model blob".to_string() }
    )]
    ModelMismatch {
        file: PathBuf,
        device: Option<u32>,
        calibration: u32,
    },
    #[error("monitor: {0}")]
    Link(#[from] LinkError),
    #[error("monitor: tracker: {0}")]
    Tracker(#[from] TrackerError),
    #[error("monitor: {0}")]
    Dataset(#[from] DatasetError),
    #[error("monitor: refit: {0}")]
    Identify(#[from] IdentifyError),
    #[error("monitor: refit: {0}")]
    Compile(#[from] CompileCmdError),
    #[error(
        "monitor: the tracker sent nothing for {seconds:.1} s (is DTrack sending to this host and port?)"
    )]
    TrackerSilent { seconds: f64 },
    #[error("monitor: the device streamed no state for {seconds:.1} s")]
    DeviceSilent { seconds: f64 },
    #[error("monitor: after the reflash the device reports {what}")]
    Verify { what: String },
    #[error("monitor: simulation: {0}")]
    Simulation(#[from] crate::sim::SimError),
    #[error("monitor: simulation: calibration: {0}")]
    SimulatedCalibration(#[source] Box<crate::procedures::calibrate::CalibrateError>),
    #[error("monitor: simulation: {0}")]
    SimulatedRig(#[from] crate::sim::operator::RigError),
    #[error("monitor: simulation: {0}")]
    VirtualDevice(#[from] crate::sim::virtual_device::VirtualDeviceError),
}

/// What the monitor reports as it goes.
#[derive(Clone, Debug)]
pub enum MonitorEvent {
    /// The first full window: the device's error, and what its strings
    /// show.
    Baseline(ErrorStats, StringsSeen),
    Check(Check),
    /// Drift found; `refit` says what the policy decided.
    Drift {
        check: Check,
        refit: bool,
    },
    Refitted(Box<Refit>),
    RefitFailed(String),
    /// The first full window after a reflash: the device's error and what
    /// the strings show, before (the window at detection) and after.
    After {
        before: ErrorStats,
        after: ErrorStats,
        strings_before: StringsSeen,
        strings_after: StringsSeen,
    },
    Note(String),
}

/// What a monitor run did.
#[derive(Clone, Debug, Default)]
pub struct MonitorReport {
    pub frames: usize,
    pub occluded: usize,
    pub unpaired: usize,
    /// Tracker frames whose instant the device spent under a model or a
    /// home the monitor no longer watches (before a reflash or a new home):
    /// not paired.
    pub superseded: usize,
    /// Tracker frames without the body's rotation while a marker offset is
    /// set: their meeting point is unknown, not paired.
    pub unoriented: usize,
    pub states: usize,
    /// Frames paired (the window's pairs are the last of them).
    pub pairs: usize,
    /// Visible frames still waiting for the state after their instant
    /// when the run stopped: not paired. With it, `frames` is `pairs +
    /// occluded + unoriented + unpaired + superseded + glitches + waiting`
    /// ([`MonitorReport::unaccounted_frames`]).
    pub waiting: usize,
    /// Pairs set aside as the tracker's glitches ([`GlitchGate`]): not in
    /// the window, nor in `pairs`.
    pub glitches: usize,
    /// The error beyond which a pair is a glitch (set with the baseline), mm.
    pub glitch_threshold_mm: Option<f64>,
    pub baseline: Option<ErrorStats>,
    /// What the baseline window's strings show.
    pub baseline_strings: Option<StringsSeen>,
    pub checks: Vec<Check>,
    pub refits: Vec<Refit>,
    /// The last full window.
    pub last_window: Option<ErrorStats>,
    /// The stamps (`ts`, s of the tracker's clock) of the first and the
    /// last tracker frame taken: the monitored span on the session's clock,
    /// the one [`MonitorConfig::duration`] counts.
    pub tracker_span_s: Option<(f64, f64)>,
    /// Device time since boot (s) of the first and the last pair.
    pub device_span_s: Option<(f64, f64)>,
    /// Wall-clock time the run took, s: on a simulated rig (virtual time)
    /// the machine's, not the session's.
    pub wall_seconds: f64,
    /// Every pair with its tracker frame's stamp (`ts`, s), in the order
    /// made, when [`MonitorConfig::record_pairs`].
    pub recorded: Vec<(f64, Pair)>,
}

impl MonitorReport {
    /// Checks that reported drift.
    pub fn drifts(&self) -> impl Iterator<Item = &Check> {
        self.checks.iter().filter(|c| c.drift)
    }

    /// Tracker frames in none of the counts that split `frames` (0: every
    /// frame was paired, or counted where it was not).
    pub fn unaccounted_frames(&self) -> isize {
        self.frames as isize
            - (self.pairs
                + self.occluded
                + self.unoriented
                + self.unpaired
                + self.superseded
                + self.glitches
                + self.waiting) as isize
    }

    /// Tracker time from the first frame taken to the last, s (0 before
    /// two frames).
    pub fn tracker_seconds(&self) -> f64 {
        self.tracker_span_s
            .map_or(0.0, |(first, last)| last - first)
    }
}

/// What the monitor is given besides the device and the tracker.
#[derive(Clone, Copy, Debug)]
pub struct MonitorInputs<'a> {
    pub geometry: &'a Geometry,
    /// The calibration the device runs.
    pub calibration: &'a Calibration,
    /// Its file (named in errors).
    pub calibration_file: &'a Path,
    /// The training session it was identified from, if at hand.
    pub training: Option<&'a Session>,
}

/// The monitor's loop state.
struct Monitor<'a> {
    config: &'a MonitorConfig,
    geometry: &'a Geometry,
    training: Option<&'a Session>,
    calibration: Calibration,
    identification: Identification,
    structure: Structure,
    base: Instant,
    /// Device-to-tracker clock map, fed by both streams' arrivals.
    sync: ClockSync,
    states: StateHistory,
    /// Visible tracker frames waiting for the state after them: (`ts`,
    /// host read time, marker).
    pending: VecDeque<(f64, f64, [f64; 3])>,
    window: VecDeque<Pair>,
    /// Sets aside the pairs whose tracker is a glitch.
    gate: GlitchGate,
    since_check: usize,
    /// Device time (since boot) of the newest home: `time_us -
    /// since_home_us` of the newest state.
    home_us: u64,
    /// The newest state's home capture (`State::home_id`): the
    /// calibration's training slips are part of the model the window is
    /// judged and refitted with while it is theirs ([`under_home`]).
    home_id: Option<u64>,
    report: MonitorReport,
    /// Index into `report.refits` waiting for its after-window.
    awaiting_after: Option<usize>,
    /// Drift was found and a refit is due once the window holds a quarter
    /// window of pairs after it (a change seen a fraction of a
    /// second ago is poorly determined: the slip's size is underestimated,
    /// and a refit on it can leave the device worse than it was;
    /// decision record 0042, `docs/decisions/0042-monitor-refits-once-settled.md`).
    settling: bool,
    /// The changes (family, strings) the drift check that began the
    /// settling found: the settled check confirms the drift when it names
    /// one of them again ([`confirmed_by_name`]).
    settling_on: Vec<(Family, Vec<u8>)>,
    /// The model the device runs: a state of another one (streamed before
    /// a reflash, read after it) is never paired.
    model_id: u32,
}

/// Runs the monitor on an open device session until `config.duration`
/// passes or the tracker ends. `confirm` answers [`RefitPolicy::Ask`];
/// `on_event` sees everything as it happens. The device is left disarmed,
/// its stream off.
pub fn monitor(
    client: &mut Client,
    tracker: &mut dyn TrackerSource,
    inputs: MonitorInputs<'_>,
    config: &MonitorConfig,
    on_event: &mut dyn FnMut(&MonitorEvent),
    confirm: &mut dyn FnMut(&Check) -> bool,
) -> Result<MonitorReport, MonitorError> {
    config.validate()?;
    check_calibration(
        inputs.calibration,
        inputs.geometry,
        config.anchor_tolerance_mm,
        inputs.calibration_file,
    )?;
    let expected = config
        .expected_model_id
        .unwrap_or_else(|| model_id_of(inputs.calibration));
    let device = client.info()?.map(|i| i.header.model_id);
    if device != Some(expected) {
        return Err(MonitorError::ModelMismatch {
            file: inputs.calibration_file.to_path_buf(),
            device,
            calibration: expected,
        });
    }
    let mut m = Monitor {
        config,
        geometry: inputs.geometry,
        training: inputs.training,
        calibration: inputs.calibration.clone(),
        identification: identification_of(
            inputs.calibration,
            &inputs.geometry.mechanical_advantage,
        ),
        structure: structure_of(inputs.calibration),
        base: Instant::now(),
        sync: ClockSync::new(),
        states: StateHistory::new(),
        pending: VecDeque::new(),
        window: VecDeque::new(),
        gate: GlitchGate::new(config.window),
        since_check: 0,
        home_us: 0,
        home_id: None,
        report: MonitorReport::default(),
        awaiting_after: None,
        settling: false,
        settling_on: Vec::new(),
        model_id: expected,
    };
    client.stream_on(config.decimation)?;
    let result = m.run(client, tracker, on_event, confirm);
    let _ = client.stream_off();
    let _ = client.disarm();
    result?;
    m.finish();
    Ok(m.report)
}

impl Monitor<'_> {
    /// The model to judge and refit with: the calibration as the device
    /// runs it under the newest state's home capture ([`under_home`]).
    fn model_under_home(&mut self) {
        let c = under_home(&self.calibration, self.home_id);
        self.identification = identification_of(&c, &self.geometry.mechanical_advantage);
        self.structure = structure_of(&c);
    }

    fn now_s(&self) -> f64 {
        self.base.elapsed().as_secs_f64()
    }

    fn run(
        &mut self,
        client: &mut Client,
        tracker: &mut dyn TrackerSource,
        on_event: &mut dyn FnMut(&MonitorEvent),
        confirm: &mut dyn FnMut(&Check) -> bool,
    ) -> Result<(), MonitorError> {
        let mut last_frame = Instant::now();
        let mut last_state = Instant::now();
        let mut first_ts: Option<f64> = None;
        loop {
            match tracker.next_frame(Duration::from_millis(5))? {
                Next::End => return Ok(()),
                Next::Timeout => {
                    if last_frame.elapsed() > self.config.tracker_timeout {
                        return Err(MonitorError::TrackerSilent {
                            seconds: last_frame.elapsed().as_secs_f64(),
                        });
                    }
                }
                Next::Frame(f) => {
                    last_frame = Instant::now();
                    let first = *first_ts.get_or_insert(f.ts_s);
                    if self
                        .config
                        .duration
                        .is_some_and(|d| f.ts_s - first >= d.as_secs_f64())
                    {
                        return Ok(());
                    }
                    self.report.tracker_span_s = Some((first, f.ts_s));
                    self.take_frame(&f);
                }
            }
            let now_s = self.take_states(client, &mut last_state, on_event)?;
            self.pair(now_s);
            self.note_windows(on_event);
            if self.check_and_refit(client, tracker, on_event, confirm)? {
                // What queued up meanwhile is paired as it comes, by its
                // stamps (a backlog's late arrivals do not move the clock
                // map, which keeps the least delayed ones); states of the
                // model before a reflash are not paired. The refit's own
                // time is no silence of either stream.
                last_frame = Instant::now();
                last_state = Instant::now();
            }
        }
    }

    /// The baseline from the first full window, and a refit's after-window
    /// once the window is full again.
    fn note_windows(&mut self, on_event: &mut dyn FnMut(&MonitorEvent)) {
        if self.report.baseline.is_none() && self.window.len() >= self.config.window {
            // The first window's glitches came before there was a
            // threshold: they leave it, and the baseline is the rest's.
            let threshold = self.gate.set_baseline(self.window_stats().median_mm);
            self.report.glitch_threshold_mm = Some(threshold);
            let before = self.window.len();
            let kept: VecDeque<Pair> = self
                .window
                .iter()
                .filter(|p| p.error_mm <= threshold)
                .cloned()
                .collect();
            if (before - kept.len()) as f64 <= GROSS_TRACKER_MAX_SHARE * before as f64 {
                self.report.glitches += before - kept.len();
                self.report.pairs -= before - kept.len();
                self.report
                    .recorded
                    .retain(|(_, p)| p.error_mm <= threshold);
                self.window = kept;
            }
            let b = self.window_stats();
            let strings = self.strings_seen();
            self.report.baseline = Some(b);
            self.report.baseline_strings = Some(strings.clone());
            self.since_check = 0;
            on_event(&MonitorEvent::Baseline(b, strings));
        }
        if let Some(k) = self.awaiting_after {
            if self.window.len() >= self.config.window {
                let after = self.window_stats();
                let strings_after = self.strings_seen();
                let refit = &mut self.report.refits[k];
                refit.after = Some(after);
                refit.after_strings = Some(strings_after.clone());
                self.awaiting_after = None;
                self.since_check = 0;
                on_event(&MonitorEvent::After {
                    before: refit.before,
                    after,
                    strings_before: refit.before_strings.clone(),
                    strings_after,
                });
            }
        }
    }

    /// Checks the window for drift when a check is due; on drift, waits for
    /// the window to settle, then refits and flashes as the policy says.
    /// True when it went as far as the refit decision (the streams'
    /// silence clocks restart then).
    fn check_and_refit(
        &mut self,
        client: &mut Client,
        tracker: &mut dyn TrackerSource,
        on_event: &mut dyn FnMut(&MonitorEvent),
        confirm: &mut dyn FnMut(&Check) -> bool,
    ) -> Result<bool, MonitorError> {
        let ready = self.report.baseline.is_some()
            && self.awaiting_after.is_none()
            && self.window.len() >= self.config.window
            && self.since_check
                >= if self.settling {
                    self.config.window / 4
                } else {
                    self.config.check_every
                };
        if !ready {
            return Ok(false);
        }
        self.since_check = 0;
        let mut check = self.check();
        if self.settling && !check.drift {
            check = confirmed_by_name(check, &self.settling_on);
        }
        self.report.checks.push(check.clone());
        if !check.drift {
            self.settling = false;
            on_event(&MonitorEvent::Check(check));
            return Ok(false);
        }
        if !self.settling
            && self.config.refit != RefitPolicy::No
            && self.report.refits.len() < self.config.max_refits
        {
            self.settling = true;
            self.settling_on = check
                .findings
                .iter()
                .map(|f| (f.family, f.strings.clone()))
                .collect();
            on_event(&MonitorEvent::Drift {
                check,
                refit: false,
            });
            on_event(&MonitorEvent::Note(format!(
                "collecting {} more pairs after the change before refitting",
                self.config.window / 4
            )));
            return Ok(false);
        }
        self.settling = false;
        let refit = self.report.refits.len() < self.config.max_refits
            && match self.config.refit {
                RefitPolicy::Yes => true,
                RefitPolicy::No => false,
                RefitPolicy::Ask => confirm(&check),
            };
        on_event(&MonitorEvent::Drift {
            check: check.clone(),
            refit,
        });
        if refit {
            // Busy: a simulated world waits for the refit (its
            // length is the machine's, not the rig's).
            tracker.busy();
            match self.refit_and_flash(client, &check) {
                Ok(r) => {
                    on_event(&MonitorEvent::Refitted(Box::new(r.clone())));
                    self.model_id = r.model_id;
                    self.report.refits.push(r);
                    self.awaiting_after = Some(self.report.refits.len() - 1);
                    self.window.clear();
                }
                Err(MonitorError::Identify(e)) => {
                    on_event(&MonitorEvent::RefitFailed(e.to_string()))
                }
                Err(e) => return Err(e),
            }
        }
        Ok(true)
    }

    fn finish(&mut self) {
        if self.window.len() >= self.config.window {
            self.report.last_window = Some(self.window_stats());
        }
        if let Some(k) = self.awaiting_after {
            if !self.window.is_empty() {
                self.report.refits[k].after_partial = Some(self.window_stats());
                self.report.refits[k].after_strings = Some(self.strings_seen());
            }
        }
        self.report.waiting = self.pending.len();
        self.report.wall_seconds = self.now_s();
    }
}
