//! The monitor's settings: its window, when a check runs, what counts as
//! drift, what a refit may do, and the clocks and timeouts of the streams.

use std::time::Duration;

use crate::device::tracker::HostClock;
use crate::model::diagnose::{Family, LoopConfig};

use super::MonitorError;

/// What to do when drift is found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RefitPolicy {
    /// Ask the operator (the `confirm` callback of [`monitor`](super::monitor)).
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
    /// [`model_id_of`](crate::model::compile::model_id_of), as `spidar
    /// compile` gives it).
    pub expected_model_id: Option<u32>,
    /// The clock arrivals are stamped with for the clock map (the wall
    /// clock; a simulated rig's own, [`crate::sim::operator::SimulatedRig::host_clock`]).
    pub host_clock: HostClock,
    /// Keep every pair in
    /// [`MonitorReport::recorded`](super::MonitorReport::recorded) (a test
    /// compares them with a simulated truth; a long run would grow without
    /// bound).
    pub record_pairs: bool,
    /// Where the tracked body's origin sits from the strings' meeting point
    /// (body frame, mm), as the calibration found it (its report's
    /// `identification.marker_body_mm`): the tracker is then read at the
    /// meeting point, `p - R_body d`, as the calibration read it, and a
    /// frame without the body's rotation is not paired
    /// ([`MonitorReport::unoriented`](super::MonitorReport::unoriented)).
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
            drift_families: vec![Family::Slip, Family::Offset, Family::Drift],
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
    pub(super) fn validate(&self) -> Result<(), MonitorError> {
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

#[cfg(test)]
mod tests;
