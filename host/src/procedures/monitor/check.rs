//! The drift check: the residual diagnosis of the current calibration on
//! the window ([`crate::model::diagnose::diagnose`]), and the error of the
//! window against the baseline.

use spidar_core::correction::CorrectionModel;
use spidar_core::kinematics::FkConfig;

use crate::data::dataset::Sample;
use crate::data::observe::{observations, Observation};
use crate::data::stats::{position_errors, ErrorStats};
use crate::model::diagnose::{diagnose, Family, Finding};
use crate::model::identify::Identification;
use crate::model::predict::{corrected_positions, paired_with_tracker, predict_with};

use super::Monitor;

/// What a window's strings show beside the error of the position the
/// device reports. The device's kinematics leave a string out of the
/// position once the strings' RMS residual passes 1 mm and the others
/// agree without it (decision record 0030,
/// `docs/decisions/0030-faulty-string-from-1mm.md`): a slipped string then
/// does not move the device's position, and its error stays at the
/// baseline through the slip. The position every string gives does move:
/// it shows the slip until a refit puts it in the model.
#[derive(Clone, Debug, PartialEq)]
pub struct StringsSeen {
    /// Error of the position with every string in (the model the window is
    /// judged with, on the host; no string left out, however far it
    /// disagrees; the learned correction applied as on the device) against
    /// the tracker, mm.
    pub every_string: ErrorStats,
    /// (string, pairs): the strings the device left out of its position,
    /// and on how many of the window's pairs; most first.
    pub left_out: Vec<(u8, usize)>,
}

/// Position errors of `id` (then `correction`) with every string in the
/// position, on the tracked `observations`, mm.
pub(super) fn every_string_errors(
    id: &Identification,
    correction: &CorrectionModel,
    observations: &[Observation],
) -> Vec<f64> {
    let every_string = FkConfig {
        exclusion_threshold_mm: f64::INFINITY,
        fault_threshold_mm: f64::INFINITY,
        ..id.kinematics.apply(&FkConfig::default())
    };
    let rooms: Vec<[f64; 3]> = predict_with(id.kinematic_model(), observations, &every_string)
        .iter()
        .map(|p| p.room)
        .collect();
    let (p, t) = paired_with_tracker(&corrected_positions(correction, &rooms), observations);
    position_errors(&p, &t)
}

/// What one drift check found.
#[derive(Clone, Debug)]
pub struct Check {
    /// Pairs so far when it ran.
    pub at_pair: usize,
    /// Device time since home of the newest pair in the window, s.
    pub device_time_s: f64,
    /// The error of the position the device reported on the window's pairs.
    pub window: ErrorStats,
    /// What the window's strings show (the position with every string in,
    /// the strings the device left out).
    pub strings: StringsSeen,
    /// `window.mean / baseline.mean`.
    pub error_ratio: f64,
    /// The error rule fired.
    pub error_exceeded: bool,
    /// Significant effects of the drift families the model lacks,
    /// strongest first.
    pub findings: Vec<Finding>,
    /// Significant effects of the drift families, large enough, that explain
    /// less than
    /// [`MonitorConfig::min_explained`](super::MonitorConfig::min_explained)
    /// of the window's residual: not drift by themselves, but what a refit
    /// tries after `findings` when the error rule fired. Over a short window
    /// the model's own parameters take up much of a step (the operator's
    /// path ties time to position), so a slip that explains most of one
    /// window can explain a fraction of the window 1 s later while its
    /// chi-square stays far above the threshold; the refit's
    /// cross-validation, on the training lattice and the window, decides
    /// whether it helps.
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
/// straddles it less cleanly, so the slip explains less of it.
pub(super) fn confirmed_by_name(mut check: Check, settling_on: &[(Family, Vec<u8>)]) -> Check {
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

impl Monitor<'_> {
    pub(super) fn window_stats(&self) -> ErrorStats {
        let e: Vec<f64> = self.window.iter().map(|p| p.error_mm).collect();
        ErrorStats::of(&e)
    }

    /// The window's [`StringsSeen`] under the model it is judged with.
    pub(super) fn strings_seen(&self) -> StringsSeen {
        let every_string = ErrorStats::of(&every_string_errors(
            &self.identification,
            &self.calibration.correction,
            &self.window_observations(),
        ));
        let mut left_out: Vec<(u8, usize)> = Vec::new();
        for s in self.window.iter().filter_map(|p| p.excluded) {
            match left_out.iter_mut().find(|(string, _)| *string == s) {
                Some((_, n)) => *n += 1,
                None => left_out.push((s, 1)),
            }
        }
        left_out.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        StringsSeen {
            every_string,
            left_out,
        }
    }

    pub(super) fn window_observations(&self) -> Vec<Observation> {
        let samples: Vec<Sample> = self.window.iter().map(|p| p.sample.clone()).collect();
        observations(&samples)
    }

    pub(super) fn check(&self) -> Check {
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
            strings: self.strings_seen(),
            error_ratio: ratio,
            error_exceeded,
            findings,
            weaker,
            all_findings,
            drift,
        }
    }
}
