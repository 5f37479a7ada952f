//! Runtime recalibration (paper, section 5.5; `spidar monitor`).
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
//!    dataset [`Sample`]s (counts, device time since home, tracker,
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
//!    ([`MonitorConfig::drift_families`]; slip, offset, drift, scale by
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
//!    before anything that happened at run time: time since home 0; left
//!    out when the model has a time drift term). The learned position
//!    correction, if any, is kept. The new calibration is compiled
//!    ([`crate::model::compile::compile_checked`]), the device disarmed and
//!    flashed ([`Client::flash`], verified with `info`), and monitoring goes
//!    on: the first full window after the reflash is the error *after*, the
//!    window at detection the error *before*, both with the same statistic.
//!
//! The monitor never arms the device. Device time since home is device
//! time since boot (a device with a stored model homes at boot) unless a
//! `Homed` event is seen, after which it counts from that state on.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use spidar_core::model::{Calibration, Effect, EffectTerm, EVERY_STRING, WINDING_ORDER};
use spidar_core::STRINGS;
use spidar_protocol::messages::q16_to_mm;
use spidar_protocol::Event;

use crate::data::dataset::{DatasetError, Geometry, Sample, Session};
use crate::data::observe::{observations, Observation};
use crate::data::stats::{position_error, ErrorStats};
use crate::device::link::{Client, LinkError};
use crate::device::tracker::{ClockSync, HostClock, StateHistory};
use crate::device::tracker::{Next, TrackerError, TrackerFrame, TrackerSource};
use crate::model::compile::{compile_checked, model_id_of, CompileCmdError};
use crate::model::diagnose::{
    cross_validated_error, diagnose, family_name, gross_tracker_threshold_mm, model_errors, Change,
    Family, Finding, LoopConfig, GROSS_TRACKER_MAX_SHARE,
};
use crate::model::identify::{
    identify, Identification, IdentifyError, Start, Structure, WindingPhysics,
};

/// What to do when drift is found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RefitPolicy {
    /// Ask the operator (the `confirm` callback of [`monitor`]).
    Ask,
    /// Refit and reflash automatically.
    Yes,
    /// Report only.
    No,
}

/// Settings of the monitor.
#[derive(Clone, Debug)]
pub struct MonitorConfig {
    /// DTrack body id of the marker.
    pub body_id: u32,
    /// Pairs in the rolling window (and in the baseline).
    pub window: usize,
    /// Run the drift check every this many new pairs.
    pub check_every: usize,
    /// A tracker frame is paired with the device state at its capture time,
    /// interpolated between two states at most this far apart in device
    /// time; it waits at most this long (host time) for the state after it.
    pub max_pair_gap: Duration,
    /// Drift when the window's mean error exceeds the baseline mean by this
    /// factor ...
    pub error_factor: f64,
    /// ... and by at least this much, mm.
    pub min_error_rise_mm: f64,
    /// Families of the diagnosis that count as drift (effects that can
    /// appear while the device runs).
    pub drift_families: Vec<Family>,
    /// Smallest effect (its largest contribution over the window, mm) that
    /// counts as drift.
    pub min_amplitude_mm: f64,
    /// Smallest share of the window's residual sum of squares a diagnosed
    /// effect must explain to count as drift. The residual is not white
    /// noise (the calibration leaves position-dependent error, and over a
    /// short window the operator's path ties time to position), so the
    /// chi-square alone over-rates weak time-like terms: on clean runs they
    /// explain a few to 17 %, a slipped string most of the residual.
    pub min_explained: f64,
    /// Require both a diagnosed effect and the error rise (instead of
    /// either).
    pub require_both: bool,
    /// Significance thresholds of the diagnosis (and the refit's rule).
    pub loop_config: LoopConfig,
    pub refit: RefitPolicy,
    /// At most this many refits in one run.
    pub max_refits: usize,
    /// Fail when the tracker sends nothing for this long.
    pub tracker_timeout: Duration,
    /// Fail when the device streams no state for this long.
    pub device_timeout: Duration,
    /// Stop after this long of tracker time (from the first frame; None:
    /// until the tracker ends).
    pub duration: Option<Duration>,
    /// Device state frames per control-loop iterations.
    pub decimation: u16,
    /// The calibration's anchors may lie this far from the geometry's, mm.
    pub anchor_tolerance_mm: f64,
    /// Model id the device must run (default: the calibration's,
    /// [`model_id_of`], as `spidar compile` gives it).
    pub expected_model_id: Option<u32>,
    /// The clock arrivals are stamped with for the clock map (the wall
    /// clock; a simulated rig's own, [`crate::sim::operator::SimulatedRig::host_clock`]).
    pub host_clock: HostClock,
    /// Keep every pair in [`MonitorReport::recorded`] (a test compares them
    /// with a simulated truth; a long run would grow without bound).
    pub record_pairs: bool,
    /// Where the tracked body's origin sits from the strings' meeting point
    /// (body frame, mm), as the calibration found it (its report's
    /// `identification.marker_body_mm`): the tracker is then read at the
    /// meeting point, `p - R_body d`, as the calibration read it, and a
    /// frame without the body's rotation is not paired
    /// ([`MonitorReport::unoriented`]).
    pub marker_body_mm: Option<[f64; 3]>,
}

impl Default for MonitorConfig {
    fn default() -> Self {
        MonitorConfig {
            body_id: 0,
            window: 600,
            check_every: 200,
            max_pair_gap: Duration::from_millis(15),
            error_factor: 1.5,
            min_error_rise_mm: 1.0,
            drift_families: vec![Family::Slip, Family::Offset, Family::Drift, Family::Scale],
            min_amplitude_mm: 1.0,
            min_explained: 0.4,
            require_both: false,
            loop_config: LoopConfig::default(),
            refit: RefitPolicy::Ask,
            max_refits: 3,
            tracker_timeout: Duration::from_secs(2),
            device_timeout: Duration::from_secs(2),
            duration: None,
            decimation: 10,
            anchor_tolerance_mm: 100.0,
            expected_model_id: None,
            host_clock: HostClock::Wall,
            record_pairs: false,
            marker_body_mm: None,
        }
    }
}

impl MonitorConfig {
    fn validate(&self) -> Result<(), MonitorError> {
        let bad = |field: &'static str, problem: String| {
            Err(MonitorError::Config(crate::ConfigError::new(
                field, problem,
            )))
        };
        if let Some(d) = self.marker_body_mm {
            if !d.iter().all(|v| v.is_finite() && v.abs() <= 1000.0) {
                return bad(
                    "marker_body_mm",
                    format!("{d:?} is not an offset of finite mm (at most 1 m per axis)"),
                );
            }
        }
        if self.window < 100 {
            return bad(
                "window",
                format!(
                    "{} pairs is too few (at least 100: the slip search needs 20 on each side)",
                    self.window
                ),
            );
        }
        if self.check_every == 0 || self.check_every > self.window {
            return bad(
                "check_every",
                format!("{} is not within 1..={}", self.check_every, self.window),
            );
        }
        if !(self.error_factor.is_finite() && self.error_factor > 1.0) {
            return bad(
                "error_factor",
                format!("{} is not a factor > 1", self.error_factor),
            );
        }
        for (field, v) in [
            ("min_error_rise_mm", self.min_error_rise_mm),
            ("min_amplitude_mm", self.min_amplitude_mm),
            ("anchor_tolerance_mm", self.anchor_tolerance_mm),
            ("min_explained", self.min_explained),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, format!("{v} is not a distance >= 0"));
            }
        }
        if self.max_pair_gap.is_zero() {
            return bad("max_pair_gap", "must be positive".into());
        }
        Ok(())
    }
}

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

/// One tracker frame paired with a device state.
#[derive(Clone, Debug, PartialEq)]
pub struct Pair {
    /// As a session row: `t_s` = device time since home, counts, tracker
    /// (room frame), commanded tensions.
    pub sample: Sample,
    /// Device time since boot, s.
    pub device_time_s: f64,
    /// The device's corrected position, room frame, mm.
    pub device_room_mm: [f64; 3],
    /// Its error against the tracker, mm.
    pub error_mm: f64,
    /// Device time from the capture instant to the nearest state streamed, ms
    /// (the state is interpolated across it).
    pub gap_ms: f64,
}

/// What one drift check found.
#[derive(Clone, Debug)]
pub struct Check {
    /// Pairs so far when it ran.
    pub at_pair: usize,
    /// Device time since home of the newest pair in the window, s.
    pub device_time_s: f64,
    pub window: ErrorStats,
    /// `window.mean / baseline.mean`.
    pub error_ratio: f64,
    /// The error rule fired.
    pub error_exceeded: bool,
    /// Significant effects of the drift families the model lacks,
    /// strongest first.
    pub findings: Vec<Finding>,
    /// Significant effects of the drift families, large enough, that explain
    /// less than [`MonitorConfig::min_explained`] of the window's residual:
    /// not drift by themselves, but what a refit tries after `findings` when
    /// the error rule fired. Over a short window the model's own parameters
    /// take up much of a step (the operator's path ties time to position),
    /// so a slip that explained 76 % of one window explains 23 % of the
    /// window 1 s later while its chi-square stays far above the threshold;
    /// the refit's cross-validation, on the training lattice and the window,
    /// decides whether it helps.
    pub weaker: Vec<Finding>,
    /// All that the diagnosis found significant (for the log).
    pub all_findings: usize,
    pub drift: bool,
}

/// `check`, taken as drift when the window no longer shows the error rise
/// or a change that explains enough of it, but still names a change (family
/// and strings, large enough: among [`Check::weaker`]) that the check which
/// began the settling found: that change, first, is what the refit tries.
/// The device's kinematics leave a slipped string out (from 1 mm RMS), so
/// its position error need not rise; and the window 1 s after a slip
/// straddles it less cleanly (76 % of the residual explained, then 23 %).
fn confirmed_by_name(mut check: Check, settling_on: &[(Family, Vec<u8>)]) -> Check {
    let named = |f: &Finding| {
        settling_on
            .iter()
            .any(|(family, strings)| *family == f.family && *strings == f.strings)
    };
    let (again, rest): (Vec<Finding>, Vec<Finding>) =
        check.weaker.drain(..).partition(|f| named(f));
    if !again.is_empty() {
        check.drift = true;
        check.findings.splice(0..0, again);
    }
    check.weaker = rest;
    check
}

/// A refit and reflash.
#[derive(Clone, Debug)]
pub struct Refit {
    /// The window at detection (the error before).
    pub before: ErrorStats,
    /// The first full window after the reflash (the error after); `None`
    /// when the run ended first (see `after_partial`).
    pub after: Option<ErrorStats>,
    /// The pairs after the reflash when the run ended before a full window.
    pub after_partial: Option<ErrorStats>,
    /// What was added, in the device's terms.
    pub added: Vec<String>,
    /// Host (f64, before the learned correction) mean error on the window
    /// of the old and the new model, mm.
    pub host_before_mm: f64,
    pub host_after_mm: f64,
    pub model_id: u32,
    pub blob_len: u32,
    /// Pairs in the refit (window, plus training rows).
    pub rows: usize,
    pub calibration: Calibration,
    /// Refit, compile and flash, s.
    pub seconds: f64,
}

/// What the monitor reports as it goes.
#[derive(Clone, Debug)]
pub enum MonitorEvent {
    Baseline(ErrorStats),
    Check(Check),
    /// Drift found; `refit` says what the policy decided.
    Drift {
        check: Check,
        refit: bool,
    },
    Refitted(Box<Refit>),
    RefitFailed(String),
    /// The first full window after a reflash.
    After {
        before: ErrorStats,
        after: ErrorStats,
    },
    Note(String),
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
    pub pairs: usize,
    /// Pairs set aside as the tracker's glitches ([`GlitchGate`]): not in
    /// the window, nor in `pairs`.
    pub glitches: usize,
    /// The error beyond which a pair is a glitch (set with the baseline), mm.
    pub glitch_threshold_mm: Option<f64>,
    pub baseline: Option<ErrorStats>,
    pub checks: Vec<Check>,
    pub refits: Vec<Refit>,
    /// The last full window.
    pub last_window: Option<ErrorStats>,
    pub seconds: f64,
    /// Every pair with its tracker frame's stamp (`ts`, s), in the order
    /// made, when [`MonitorConfig::record_pairs`].
    pub recorded: Vec<(f64, Pair)>,
}

impl MonitorReport {
    /// Checks that reported drift.
    pub fn drifts(&self) -> impl Iterator<Item = &Check> {
        self.checks.iter().filter(|c| c.drift)
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

/// A finding in the device's terms: string, mm, when.
pub fn describe_finding(f: &Finding) -> String {
    let term = match f.change {
        Some(Change::Effect(EffectTerm { string, effect })) => {
            let who = if string == EVERY_STRING {
                "every string".to_string()
            } else {
                format!("string {string}")
            };
            match effect {
                Effect::Slip { at_s, mm } => {
                    format!("{who} slipped by {mm:+.2} mm at {at_s:.2} s of device time since home")
                }
                Effect::Offset { mm } => format!("{who} reads {mm:+.2} mm off"),
                Effect::Drift { mm_per_s } => {
                    format!("{who} drifts {:+.3} mm/min", mm_per_s * 60.0)
                }
                Effect::Scale { relative } => {
                    format!("{who}'s payout is off by {:+.3} %", relative * 100.0)
                }
                other => format!("{who}: {other:?}"),
            }
        }
        _ => f.description.clone(),
    };
    format!(
        "{} ({}; {:.1} mm at most, explains {:.0} % of the residual, chi2 {:.0})",
        family_name(f.family),
        term,
        f.amplitude_mm,
        100.0 * f.explained,
        f.chi2
    )
}

/// Checks that `calibration` belongs to the device of `geometry`: the same
/// encoders, anchors within `tolerance_mm` of the design, and string laws of
/// the identified winding form (what diagnosis can test and refit).
pub fn check_calibration(
    calibration: &Calibration,
    geometry: &Geometry,
    tolerance_mm: f64,
    file: &Path,
) -> Result<(), MonitorError> {
    let bad = |field: String, problem: String| {
        Err(MonitorError::Calibration {
            file: file.to_path_buf(),
            field,
            problem,
        })
    };
    for i in geometry.layout.indices() {
        let law = &calibration.strings[i];
        if law.counts_per_rev != geometry.counts_per_rev[i] {
            return bad(
                format!("strings[{i}].counts_per_rev"),
                format!(
                    "{} counts per revolution, the geometry has {} (a calibration of another device?)",
                    law.counts_per_rev, geometry.counts_per_rev[i]
                ),
            );
        }
        // The identified form: [r_home_i, -(kappa + kappa_i) / m_i, 0, 0]
        // (m_i the string's mechanical advantage, 1 for a single line).
        if law.winding_mm[2..WINDING_ORDER].iter().any(|c| *c != 0.0) {
            return bad(
                format!("strings[{i}].winding_mm"),
                "not of the identified winding form [r_home, -kappa / mechanical_advantage, 0, \
                 0]: runtime diagnosis cannot test this model"
                    .into(),
            );
        }
    }
    if calibration.frame.layout != geometry.layout {
        return bad(
            "frame.layout".into(),
            format!(
                "strings on channels {:?}{}, the geometry has {:?}{}: the calibration and the \
                 geometry are of different devices",
                calibration.frame.layout.indices().collect::<Vec<_>>(),
                if calibration.frame.layout.planar {
                    " (planar)"
                } else {
                    ""
                },
                geometry.layout.indices().collect::<Vec<_>>(),
                if geometry.layout.planar {
                    " (planar)"
                } else {
                    ""
                },
            ),
        );
    }
    for i in geometry.layout.indices() {
        let a = calibration.frame.anchors[i];
        let n = geometry.anchors_mm[i];
        let d = ((a[0] - n[0]).powi(2) + (a[1] - n[1]).powi(2) + (a[2] - n[2]).powi(2)).sqrt();
        if !d.is_finite() || d > tolerance_mm {
            return bad(
                format!("frame.anchors[{i}]"),
                format!(
                    "{d:.1} mm from the geometry's anchor {i} (tolerance {tolerance_mm} mm): \
                     the calibration and the geometry are of different devices"
                ),
            );
        }
    }
    Ok(())
}

/// The calibration as an identification (its frame, winding and effects),
/// so that diagnosis can test it; `mechanical_advantage` is the geometry's
/// (each string's law carries the shared kappa over it, see
/// [`check_calibration`]).
pub fn identification_of(
    calibration: &Calibration,
    mechanical_advantage: &[f64; STRINGS],
) -> Identification {
    let laws = calibration.strings;
    let layout = calibration.frame.layout;
    // Each string's thinning rate, split into the shared mean and each
    // spool's departure (the identification's form).
    let kappa_of = |i: usize| -laws[i].winding_mm[1] * mechanical_advantage[i];
    let kappa_mm = layout.indices().map(kappa_of).sum::<f64>() / layout.count().max(1) as f64;
    Identification {
        frame: calibration.frame,
        winding: WindingPhysics {
            r_home_mm: core::array::from_fn(|i| laws[i].winding_mm[0]),
            kappa_mm,
            kappa_each_mm: core::array::from_fn(|i| {
                if layout.is_active(i) {
                    kappa_of(i) - kappa_mm
                } else {
                    0.0
                }
            }),
            counts_per_rev: laws.map(|l| l.counts_per_rev),
            mechanical_advantage: *mechanical_advantage,
            layers: laws.map(|l| l.layers),
        },
        laws,
        effects: calibration.effects.clone(),
        parameters: Vec::new(),
        warnings: Vec::new(),
        residual_scale_mm: 0.0,
        length_scale_mm: calibration.length_scale_mm,
        rejected_fraction: 0.0,
        evaluations: 0,
        kinematics: calibration.kinematics,
    }
}

/// The structure of a calibration: its effect terms, the tracker scale free
/// when it is not 1.
pub fn structure_of(calibration: &Calibration) -> Structure {
    Structure {
        fit_room_scale: (calibration.frame.room_scale - 1.0).abs() > 1e-12,
        effects: calibration.effects.clone(),
        // A window of a few seconds cannot tell a spool's thinning rate
        // from a step or a drift: the calibration's are held (the default).
        ..Structure::default()
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
/// baseline: a tracker glitching on 1 % of its frames made a device that
/// did not drift report drift at 3 of 9 checks. Pairs that far off in more
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
    report: MonitorReport,
    /// Index into `report.refits` waiting for its after-window.
    awaiting_after: Option<usize>,
    /// Drift was found and a refit is due once the window holds half a
    /// quarter window of pairs after it (a change seen a fraction of a second ago is
    /// poorly determined: a 7 mm slip 0.24 s before the check measured
    /// 5.5 mm, and a refit on it left the device worse than before).
    settling: bool,
    /// The changes (family, strings) the drift check that began the
    /// settling found: the settled check confirms the drift when it names
    /// one of them again ([`confirmed_by_name`]).
    settling_on: Vec<(Family, Vec<u8>)>,
    /// The model the device runs: a state of another one (streamed before
    /// a reflash, read after it) is never paired.
    model_id: u32,
}

/// A refit's model before it is flashed: the identification, its
/// structure, the data it was fitted on and the terms added (in words).
struct RefitModel {
    id: Identification,
    structure: Structure,
    data: Vec<Observation>,
    added: Vec<String>,
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

    /// A tracker frame: into the clock map, and its visible marker into the
    /// frames waiting for their state.
    fn take_frame(&mut self, f: &TrackerFrame) {
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
    fn take_states(
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
            self.sync.device_state(s.time_us, read_s);
            self.states.push(s);
        }
        Ok(now_s)
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
            self.report.baseline = Some(b);
            self.since_check = 0;
            on_event(&MonitorEvent::Baseline(b));
        }
        if let Some(k) = self.awaiting_after {
            if self.window.len() >= self.config.window {
                let after = self.window_stats();
                self.report.refits[k].after = Some(after);
                self.awaiting_after = None;
                self.since_check = 0;
                on_event(&MonitorEvent::After {
                    before: self.report.refits[k].before,
                    after,
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

    /// Pairs the pending tracker frames whose capture time the device
    /// stream has passed (or that waited longer than the gap): the device
    /// state at the frame's `ts` mapped to device time.
    fn pair(&mut self, now_s: f64) {
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
                },
                device_time_s: t.round() / 1e6,
                device_room_mm,
                error_mm: position_error(device_room_mm, marker),
                gap_ms: nearest_ms,
            };
            if !self.gate.admit(pair.error_mm) {
                self.report.glitches += 1;
                continue;
            }
            if self.config.record_pairs {
                self.report.recorded.push((ts_s, pair.clone()));
            }
            self.window.push_back(pair);
            while self.window.len() > self.config.window {
                self.window.pop_front();
            }
            self.report.pairs += 1;
            self.since_check += 1;
        }
    }

    fn window_stats(&self) -> ErrorStats {
        let e: Vec<f64> = self.window.iter().map(|p| p.error_mm).collect();
        ErrorStats::of(&e)
    }

    fn window_observations(&self) -> Vec<Observation> {
        let samples: Vec<Sample> = self.window.iter().map(|p| p.sample.clone()).collect();
        observations(&samples)
    }

    fn check(&self) -> Check {
        let window = self.window_stats();
        let baseline = self.report.baseline.unwrap_or(window);
        let ratio = window.mean_mm / baseline.mean_mm.max(1e-9);
        let error_exceeded = ratio > self.config.error_factor
            && window.mean_mm - baseline.mean_mm >= self.config.min_error_rise_mm;
        let obs = self.window_observations();
        let all = diagnose(
            &self.identification,
            &obs,
            &self.geometry.nominal_frame(),
            &self.structure,
            &self.config.loop_config,
        );
        let all_findings = all.len();
        let (findings, weaker): (Vec<Finding>, Vec<Finding>) = all
            .into_iter()
            .filter(|f| {
                self.config.drift_families.contains(&f.family)
                    && f.amplitude_mm >= self.config.min_amplitude_mm
                    && f.change.is_some()
            })
            .partition(|f| f.explained >= self.config.min_explained);
        let drift = if self.config.require_both {
            error_exceeded && !findings.is_empty()
        } else {
            error_exceeded || !findings.is_empty()
        };
        Check {
            at_pair: self.report.pairs,
            device_time_s: self.window.back().map_or(0.0, |p| p.sample.t_s),
            window,
            error_ratio: ratio,
            error_exceeded,
            findings,
            weaker,
            all_findings,
            drift,
        }
    }

    /// The refit's data: the window, plus the training session (time since
    /// home 0) when given and the model has no time drift term.
    fn refit_data(&self, structure: &Structure) -> Vec<Observation> {
        let has_drift = structure
            .effects
            .iter()
            .any(|t| matches!(t.effect, Effect::Drift { .. }));
        let mut samples: Vec<Sample> = Vec::new();
        if let (Some(train), false) = (self.training, has_drift) {
            samples.extend(train.samples.iter().map(|s| Sample {
                t_s: 0.0,
                ..s.clone()
            }));
        }
        samples.extend(self.window.iter().map(|p| p.sample.clone()));
        // The training rows as the calibration read them (the window's are
        // paired at the meeting point already and carry no orientation).
        crate::data::observe::at_meeting_points(&observations(&samples), self.config.marker_body_mm)
            .into_owned()
    }

    fn refit_and_flash(
        &mut self,
        client: &mut Client,
        check: &Check,
    ) -> Result<Refit, MonitorError> {
        let t0 = Instant::now();
        let window_obs = self.window_observations();
        let RefitModel {
            mut id,
            structure,
            data,
            added,
        } = self.refit_model(check)?;
        // A window of a few seconds does not measure each string's scale as
        // the calibration's session did: the strings keep their weights.
        id.length_scale_mm = self.calibration.length_scale_mm;
        let host_before_mm = model_errors(&self.identification, &window_obs).mean_mm;
        let host_after_mm = model_errors(&id, &window_obs).mean_mm;
        if host_after_mm.partial_cmp(&host_before_mm) != Some(std::cmp::Ordering::Less) {
            return Err(MonitorError::Identify(IdentifyError::Diverged(format!(
                "the refit does not lower the window error ({host_before_mm:.3} mm -> {host_after_mm:.3} mm); nothing flashed"
            ))));
        }
        let calibration = Calibration {
            frame: id.frame,
            strings: id.laws,
            effects: id.effects.clone(),
            correction: self.calibration.correction.clone(),
            // A calibration whose strings weigh alike (its rule, chosen on
            // held-out folds) keeps them alike.
            length_scale_mm: if self.calibration.length_scale_mm.iter().all(|&s| s == 0.0) {
                self.calibration.length_scale_mm
            } else {
                id.length_scale_mm
            },
            kinematics: self.calibration.kinematics,
        };
        let model_id = model_id_of(&calibration);
        let flashed = self.flash_calibration(client, &calibration, model_id)?;
        self.calibration = calibration.clone();
        self.identification = id;
        self.structure = structure;
        Ok(Refit {
            before: check.window,
            after: None,
            after_partial: None,
            added,
            host_before_mm,
            host_after_mm,
            model_id,
            blob_len: flashed.blob_len,
            rows: data.iter().filter(|o| o.tracker.is_some()).count(),
            calibration,
            seconds: t0.elapsed().as_secs_f64(),
        })
    }

    /// The refitted model: the check's findings added as terms where they
    /// lower the cross-validated error enough, else the model as it is
    /// refitted.
    fn refit_model(&self, check: &Check) -> Result<RefitModel, MonitorError> {
        let nominal = self.geometry.nominal_frame();
        let mut structure = self.structure.clone();
        let mut id = self.identification.clone();
        let mut data = self.refit_data(&structure);
        let mut validation = cross_validated_error(&data, &nominal, &id, &structure)?;
        let mut added = Vec::new();
        // One new term per string per refit, the strongest (findings come
        // strongest first): a step on a string also scores as an offset and
        // as a drift, and a drift fitted across a step inside a few seconds
        // of data extrapolates wildly (measured: `--simulate 5 --effect
        // slip:3:at_s=8,mm=7` added slip + drift on string 3, and the error
        // after the reflash rose from 0.66 to 2.5 mm).
        let mut strings_changed: Vec<u8> = Vec::new();
        let weaker = check.weaker.iter().filter(|_| check.error_exceeded);
        for f in check.findings.iter().chain(weaker) {
            if added.len() >= self.config.loop_config.max_effects {
                break;
            }
            let Some(change) = f.change else { continue };
            // A term shared by every string (no strings named) touches them
            // all.
            let touched: Vec<u8> = if f.strings.is_empty() {
                self.geometry.layout.indices().map(|i| i as u8).collect()
            } else {
                f.strings.clone()
            };
            if touched.iter().any(|s| strings_changed.contains(s)) {
                continue;
            }
            let candidate = structure.with(change);
            let candidate_data = self.refit_data(&candidate);
            let after = cross_validated_error(&candidate_data, &nominal, &id, &candidate)?;
            if after < validation * (1.0 - self.config.loop_config.min_relative_gain) {
                id = identify(
                    &candidate_data,
                    &nominal,
                    &Start::from_identification(&id),
                    &candidate,
                )?;
                structure = candidate;
                data = candidate_data;
                validation = after;
                strings_changed.extend(&touched);
                added.push(describe_finding(f));
            }
        }
        if added.is_empty() {
            // Nothing the diagnosis named helps: refit the model as it is
            // (the error rule fired, or the effect is already a term).
            id = identify(
                &data,
                &nominal,
                &Start::from_identification(&id),
                &structure,
            )?;
            added.push("no new term: the model's parameters refitted".into());
        }
        Ok(RefitModel {
            id,
            structure,
            data,
            added,
        })
    }

    /// Compiles `calibration` and flashes it with the motors off and the
    /// stream paused; checks that the device runs it, then streams again.
    fn flash_calibration(
        &self,
        client: &mut Client,
        calibration: &Calibration,
        model_id: u32,
    ) -> Result<crate::device::link::FlashReport, MonitorError> {
        let blob = compile_checked(
            calibration,
            model_id,
            crate::model::compile::created_now(),
            Path::new("(runtime refit)"),
        )?;
        // Flashing needs the motors off; the stream pauses meanwhile.
        client.stream_off()?;
        client.disarm()?;
        let flashed = client.flash(&blob, |_| {})?;
        match client.info()? {
            Some(info) if info.header.model_id == model_id => {}
            other => {
                return Err(MonitorError::Verify {
                    what: match other {
                        Some(i) => format!(
                            "model {:#010x}, flashed {model_id:#010x}",
                            i.header.model_id
                        ),
                        None => "no model".into(),
                    },
                })
            }
        }
        client.stream_on(self.config.decimation)?;
        Ok(flashed)
    }

    fn finish(&mut self) {
        if self.window.len() >= self.config.window {
            self.report.last_window = Some(self.window_stats());
        }
        if let Some(k) = self.awaiting_after {
            if !self.window.is_empty() {
                self.report.refits[k].after_partial = Some(self.window_stats());
            }
        }
        self.report.seconds = self.now_s();
    }
}

// ---------------------------------------------------------------------------
// Simulation: a calibrated virtual device in a simulated operator's hand.

/// A simulated device calibrated from its simulated lattice session.
#[derive(Clone, Debug)]
pub struct SimCalibration {
    /// The device seed.
    pub seed: u64,
    /// The simulator configuration of the device (effects aside).
    pub sim_config: crate::sim::SimConfig,
    pub geometry: Geometry,
    /// The lattice (training) session.
    pub training: Session,
    pub calibration: Calibration,
    /// The calibrate pipeline's summary.
    pub summary: String,
    pub seconds: f64,
}

/// Simulates the lattice and a test session of the built-in device of
/// `seed` (no injected effect: the device as calibrated) and runs the
/// calibrate pipeline on them in process (reduced NN/SVR search).
pub fn calibrate_simulated(seed: u64) -> Result<SimCalibration, MonitorError> {
    calibrate_simulated_with(seed, &crate::sim::SimConfig::default())
}

/// [`calibrate_simulated`] for the device of another simulator
/// configuration (`spidar monitor --simulate --sim-config`: e.g. a
/// 4-string rig); its injected effects are left out.
pub fn calibrate_simulated_with(
    seed: u64,
    sim_config: &crate::sim::SimConfig,
) -> Result<SimCalibration, MonitorError> {
    use crate::procedures::calibrate::{calibrate, CalibrateConfig, NamedSession};
    use crate::sim::{simulate_session, SessionKind, SimConfig, SimDevice};
    let t0 = Instant::now();
    let config = SimConfig {
        effects: Vec::new(),
        ..sim_config.clone()
    };
    let device = SimDevice::new(&config, seed)?;
    let training = simulate_session(&device, SessionKind::Lattice, seed.wrapping_add(100))?;
    let test = simulate_session(
        &device,
        SessionKind::Random { points: 300 },
        seed.wrapping_add(200),
    )?;
    let mut cc = CalibrateConfig::quick();
    cc.quiet = true;
    cc.seed = seed;
    let calibrated = calibrate(
        &device.nominal,
        Path::new("(simulated geometry)"),
        NamedSession {
            path: Path::new("(simulated lattice)"),
            session: &training,
        },
        NamedSession {
            path: Path::new("(simulated test session)"),
            session: &test,
        },
        &cc,
    )
    .map_err(|e| MonitorError::SimulatedCalibration(Box::new(e)))?;
    Ok(SimCalibration {
        seed,
        sim_config: config.clone(),
        geometry: device.nominal.clone(),
        training,
        calibration: calibrated.calibration,
        summary: calibrated.report.summary(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Settings of a [`SimulatedMonitorRig`].
#[derive(Clone, Debug, PartialEq)]
pub struct SimRigConfig {
    /// Injected effects of the device at run time (`--effect` syntax, e.g.
    /// `slip:2:at_s=8,mm=6`: `at_s` is device time since boot, and the
    /// device boots, and homes, when monitoring starts).
    pub effects: Vec<String>,
    /// The operator wanders in a cube of this half size around home, mm.
    pub wander_half_size_mm: f64,
    pub wander_speed_mm_s: f64,
    /// Probability that a tracker frame has the marker occluded.
    pub occlusion: f64,
    /// Probability that a tracker frame's position is a glitch, thrown 50
    /// to 300 mm ([`crate::sim::operator::SimOperatorConfig::glitch`]).
    pub glitch: f64,
    pub operator_seed: u64,
    /// The tracker's frame rate, Hz (the device streams at 100 Hz: another
    /// rate puts frames between its states).
    pub frame_rate_hz: f64,
    /// The operator (and the tracker) stop after this long.
    pub max_duration: Duration,
}

impl Default for SimRigConfig {
    fn default() -> Self {
        SimRigConfig {
            effects: Vec::new(),
            wander_half_size_mm: 120.0,
            wander_speed_mm_s: 60.0,
            occlusion: 0.02,
            glitch: 0.0,
            operator_seed: 1,
            frame_rate_hz: 100.0,
            max_duration: Duration::from_secs(600),
        }
    }
}

/// A calibrated virtual device (real time) whose end-effector is in the
/// hand of a simulated operator who wanders about, and the DTrack2 receiver
/// on loopback the operator's tracker sends to: a [`SimulatedRig`] with the
/// calibration flashed before the operator starts.
///
/// [`SimulatedRig`]: crate::sim::operator::SimulatedRig
pub struct SimulatedMonitorRig {
    pub rig: crate::sim::operator::SimulatedRig,
    /// The model flashed before the start.
    pub model_id: u32,
}

impl std::ops::Deref for SimulatedMonitorRig {
    type Target = crate::sim::operator::SimulatedRig;
    fn deref(&self) -> &Self::Target {
        &self.rig
    }
}

impl std::ops::DerefMut for SimulatedMonitorRig {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.rig
    }
}

impl SimulatedMonitorRig {
    /// Builds the run-time device (same seed, plus `config.effects`),
    /// spawns it with the end-effector at its true home, flashes the
    /// calibration, power-cycles it (it homes at boot, where the hand is:
    /// device time since home = since boot), then starts the operator.
    pub fn start(
        calibrated: &SimCalibration,
        config: &SimRigConfig,
    ) -> Result<SimulatedMonitorRig, MonitorError> {
        use crate::sim::operator::{FreeMotion, SimulatedRig};
        use crate::sim::{SimConfig, SimDevice};
        let sim_config = SimConfig {
            effects: config.effects.clone(),
            ..calibrated.sim_config.clone()
        };
        let device = SimDevice::new(&sim_config, calibrated.seed)?;
        let model_id = model_id_of(&calibrated.calibration);
        let blob = compile_checked(
            &calibrated.calibration,
            model_id,
            0,
            Path::new("(simulated calibration)"),
        )?;
        let home = device.frame.home;
        let rig = SimulatedRig::start_prepared(
            device,
            [0.0; 3],
            |virtual_device| -> Result<(), MonitorError> {
                {
                    let mut client = Client::open(virtual_device.port_path())?;
                    client.flash(&blob, |_| {})?;
                }
                Ok(virtual_device.power_cycle()?)
            },
            |op| {
                op.free_motion = FreeMotion::Wander {
                    centre_mm: home,
                    half_size_mm: config.wander_half_size_mm,
                    speed_mm_s: config.wander_speed_mm_s,
                };
                op.occlusion = config.occlusion;
                op.glitch = config.glitch;
                op.seed = config.operator_seed;
                op.frame_rate_hz = config.frame_rate_hz;
                op.max_duration = config.max_duration;
            },
        )?;
        Ok(SimulatedMonitorRig { rig, model_id })
    }
}

/// One line per monitor event.
pub fn event_line(e: &MonitorEvent) -> String {
    let stats = |s: &ErrorStats| {
        format!(
            "mean {:.3} mm, sd {:.3}, p95 {:.3}, max {:.3} (n {})",
            s.mean_mm, s.sd_mm, s.p95_mm, s.max_mm, s.n
        )
    };
    match e {
        MonitorEvent::Baseline(s) => format!("baseline window: {}", stats(s)),
        MonitorEvent::Check(c) => format!(
            "check at t = {:.1} s: window {} ({:.2} x baseline); no drift",
            c.device_time_s,
            stats(&c.window),
            c.error_ratio
        ),
        MonitorEvent::Drift { check: c, refit } => {
            let mut s = format!(
                "DRIFT at t = {:.1} s (device time since home): window {} ({:.2} x baseline{})",
                c.device_time_s,
                stats(&c.window),
                c.error_ratio,
                if c.error_exceeded { ", above the limit" } else { "" }
            );
            for f in &c.findings {
                s.push_str(&format!("\n  found: {}", describe_finding(f)));
            }
            s.push_str(if *refit {
                "\n  refitting and reflashing"
            } else {
                "\n  not refitted"
            });
            s
        }
        MonitorEvent::Refitted(r) => format!(
            "refit on {} pairs: {}; window error on the host {:.3} -> {:.3} mm; flashed model {:#010x} ({} bytes) in {:.1} s",
            r.rows,
            r.added.join("; "),
            r.host_before_mm,
            r.host_after_mm,
            r.model_id,
            r.blob_len,
            r.seconds
        ),
        MonitorEvent::RefitFailed(why) => format!("refit failed: {why}"),
        MonitorEvent::After { before, after } => format!(
            "after the reflash: window {} (before: mean {:.3} mm)",
            stats(after),
            before.mean_mm
        ),
        MonitorEvent::Note(n) => n.clone(),
    }
}

/// The run's summary.
pub fn summary(r: &MonitorReport) -> String {
    let mut s = format!(
        "monitored {:.1} s: {} tracker frames ({} occluded, {} unpaired, {} before a reflash or home, {} glitches set aside), {} device states, {} pairs, {} checks, {} drift reports, {} refits\n",
        r.seconds,
        r.frames,
        r.occluded,
        r.unpaired,
        r.superseded,
        r.glitches,
        r.states,
        r.pairs,
        r.checks.len(),
        r.drifts().count(),
        r.refits.len()
    );
    if let Some(b) = &r.baseline {
        s.push_str(&format!("baseline: mean {:.3} mm (n {})", b.mean_mm, b.n));
        if let Some(t) = r.glitch_threshold_mm {
            s.push_str(&format!(
                "; a pair more than {t:.1} mm off is the tracker's glitch"
            ));
        }
        s.push('\n');
    }
    for (k, f) in r.refits.iter().enumerate() {
        let after = f.after.or(f.after_partial);
        s.push_str(&format!(
            "refit {}: before mean {:.3} mm, after {}\n",
            k + 1,
            f.before.mean_mm,
            after.map_or("(no pairs)".into(), |a| format!(
                "mean {:.3} mm (n {})",
                a.mean_mm, a.n
            ))
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::tracker::BodyPose;

    /// Without a marker offset the tracker is read at the body's origin;
    /// with one, at the meeting point the body's rotation puts it; a frame
    /// without the rotation then has no meeting point.
    #[test]
    fn the_tracker_is_read_at_the_meeting_point_the_calibration_found() {
        let quarter_turn_about_z = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let body = BodyPose {
            rotation: Some(quarter_turn_about_z),
            ..BodyPose::at(0, [100.0, 200.0, 300.0])
        };
        assert_eq!(tracked_point(&body, None), Some([100.0, 200.0, 300.0]));
        assert_eq!(
            tracked_point(&body, Some([10.0, 0.0, 5.0])),
            Some([100.0, 190.0, 295.0])
        );
        let blind = BodyPose {
            rotation: None,
            ..body
        };
        assert_eq!(tracked_point(&blind, Some([10.0, 0.0, 5.0])), None);
        assert_eq!(tracked_point(&blind, None), Some([100.0, 200.0, 300.0]));
    }

    /// An offset of the tracked body that is not finite is refused by name.
    /// Before the baseline every pair is admitted; after it, a lone pair
    /// beyond the threshold is set aside, and far pairs in more than a
    /// quarter of the window are admitted (the position did change).
    #[test]
    fn the_glitch_gate_sets_lone_far_pairs_aside_and_admits_persistent_ones() {
        let mut gate = GlitchGate::new(40);
        assert!(gate.admit(500.0), "no threshold before the baseline");
        assert_eq!(gate.set_baseline(0.2), 10.0, "the floor");
        assert_eq!(GlitchGate::new(40).set_baseline(1.0), 20.0);
        for k in 0..100 {
            // One far pair in 20: set aside, the others admitted.
            let far = k % 20 == 0;
            let e = if far { 200.0 } else { 0.3 };
            assert_eq!(gate.admit(e), !far, "pair {k}");
        }
        assert!(!gate.admit(f64::NAN), "a pair the device cannot place");
        // From here on every pair is 30 mm off: set aside until far pairs
        // are more than a quarter of the last 40, admitted after.
        let admitted: Vec<bool> = (0..20).map(|_| gate.admit(30.0)).collect();
        let first = admitted.iter().position(|&a| a).expect("admitted at last");
        assert!(admitted[first..].iter().all(|&a| a), "{admitted:?}");
        assert!((7..=10).contains(&first), "{admitted:?}");
    }

    #[test]
    fn a_marker_offset_that_is_not_finite_is_refused() {
        let config = MonitorConfig {
            marker_body_mm: Some([f64::NAN, 0.0, 0.0]),
            ..MonitorConfig::default()
        };
        let e = config.validate().unwrap_err().to_string();
        assert!(e.contains("marker_body_mm"), "{e}");
    }
}
