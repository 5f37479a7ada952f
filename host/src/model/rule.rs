//! The forward kinematics' rule for a calibrated device, chosen on held-out
//! data: when it leaves a string out of a row, when it calls a row's
//! strings inconsistent, and whether the strings weigh by their measured
//! scales.
//!
//! The device's fixed rule (look for a faulty string from 1 mm RMS, call the
//! strings inconsistent from 2 mm, weigh each string by its scale) suits a
//! device whose strings agree to a fraction of a millimetre. On a rig whose
//! strings disagree by a few millimetres in a smooth, shared way (a planar
//! robot whose cables attach at the carriage's corners), it leaves a string
//! out of most rows and loses the balance the all-string least squares
//! keeps. So the thresholds scale with what the training rows measured
//! ([`scaled_thresholds`]), and the rule is one of a few candidates
//! ([`candidates`]) chosen by the held-out error of the blocked folds, as
//! the diagnosis loop chooses its changes: each fold's model, fitted on the
//! fold's rows, places its held-out rows under each candidate (a session
//! too small for the loop: ten interleaved folds that each hold out a
//! tenth, as its anchors' tolerance is chosen on). Every string alike
//! (the plain least-squares reference's rule) stays unless another lowers
//! the held-out mean by the loop's [`LoopConfig::min_relative_gain`]: a
//! rule set on our simulators must earn its place on the device's own
//! data, and where the folds cannot tell the rules apart the plain one is
//! the floor (decision record 0074).
//!
//! Where the loop counted a string's structure that follows speed once more
//! in its scale (a device in use moves faster than a lattice's captures,
//! [`LoopResult::speed_counted_again_mm`]) and the training rows observe
//! speed (a stream, which moves in training as in use), the folds see the
//! speeds of use: each weighed rule is tried with the scales the training
//! measured as well, and the device keeps the structure counted again
//! unless they gain as any other rule must (decision record 0066). On a
//! static session the folds hold out slow rows only, and the structure
//! stays counted.

use rayon::prelude::*;
use serde::Serialize;
use spidar_core::kinematics::KinematicsRule;

use crate::data::observe::{observes_speed, Observation};
use crate::data::stats::{position_errors, quantile, ErrorStats};
use crate::model::diagnose::{
    count_speed_again, uncount_speed, LoopConfig, LoopResult, FOLLOWS_SPEED,
};
use crate::model::identify::{identify, rows_needed_for, Identification, IdentifyError, Start};
use crate::model::predict::{paired_with_tracker, predict, KinematicModel, UNMEASURED_SCALES};
use crate::model::validate::{choice_folds, fold_fits, judged_fold_fits, preferred, Preferred};
use spidar_core::model::Frame;
use spidar_core::STRINGS;

/// The quantile of the training rows' string disagreement (the RMS of the
/// string-length residuals at the all-string position) that the scaled
/// exclusion threshold sits at: one row in a hundred of the device's own
/// rows disagrees more.
pub const DISAGREEMENT_QUANTILE: f64 = 0.99;

/// A row whose strings disagree this many times the quantile above is
/// unlike any training row: the scaled fault threshold.
pub const FAULT_OVER_QUANTILE: f64 = 2.0;

/// A rule forward kinematics may run with.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RuleCandidate {
    pub name: &'static str,
    pub rule: KinematicsRule,
    /// The strings weigh by their measured scales (else alike).
    pub weighted: bool,
    /// Weighed, the scales count the structure that follows speed once
    /// more ([`LoopResult::speed_counted_again_mm`]); false: the scales
    /// the training rows measured.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub speed_counted_again: bool,
}

/// A candidate and its held-out error.
#[derive(Clone, Debug, Serialize)]
pub struct RuleScore {
    #[serde(flatten)]
    pub candidate: RuleCandidate,
    /// Over the rows the judged folds hold out.
    pub held_out: ErrorStats,
}

/// What the folds said, and the choice.
#[derive(Clone, Debug, Serialize)]
pub struct RuleChoice {
    /// Index into `scores` of the chosen rule (0 when none was scored).
    pub chosen: usize,
    /// The rules tried and their held-out errors; empty when the session
    /// had no folds to judge them on ([`unjudged`]).
    pub scores: Vec<RuleScore>,
    /// The rule chosen ([`RuleChoice::candidate`]): `scores[chosen]`'s
    /// where the rules were scored, kept in step by [`RuleChoice::choosing`].
    #[serde(skip)]
    rule: RuleCandidate,
    /// The training rows' string disagreement at the quantile the scaled
    /// thresholds read, mm.
    pub disagreement_q99_mm: f64,
    pub reason: String,
    /// The structure that follows speed counted once more in each string's
    /// scale by the loop (the identification's scales hold it), mm.
    #[serde(skip)]
    pub speed_counted_again_mm: [f64; STRINGS],
}

impl RuleChoice {
    /// The chosen candidate.
    pub fn candidate(&self) -> RuleCandidate {
        self.rule
    }

    /// The same choice with `scores[k]`'s rule chosen instead.
    pub fn choosing(&self, k: usize) -> RuleChoice {
        RuleChoice {
            chosen: k,
            rule: self.scores[k].candidate,
            ..self.clone()
        }
    }

    /// `id` (whose scales hold the structure counted again) running the
    /// chosen rule: its thresholds, and its scales zeroed when the strings
    /// weigh alike, or without the structure counted again when the rule
    /// weighs by the scales the training measured.
    pub fn apply(&self, id: &Identification) -> Identification {
        let candidate = self.candidate();
        let mut out = with_rule(id, &candidate);
        let counted = self.speed_counted_again_mm.iter().any(|c| *c > 0.0);
        if counted && candidate.weighted && !candidate.speed_counted_again {
            uncount_speed(&mut out.length_scale_mm, &self.speed_counted_again_mm);
            out.warnings.retain(|w| !w.contains(FOLLOWS_SPEED));
            out.warnings.push(format!(
                "the structure that follows speed is not counted again in the strings' scales: \
                 {}",
                self.reason
            ));
        }
        out
    }
}

/// `id` with `candidate`'s thresholds, and its scales zeroed (every string
/// weighs alike on the device too) when the candidate does not weigh.
pub fn with_rule(id: &Identification, candidate: &RuleCandidate) -> Identification {
    let mut out = id.clone();
    out.kinematics = candidate.rule;
    if !candidate.weighted {
        out.length_scale_mm = UNMEASURED_SCALES;
    }
    out
}

/// The thresholds scaled to how well the training rows' strings agree
/// under `id` (all strings, alike): the exclusion at the disagreement's
/// [`DISAGREEMENT_QUANTILE`], the fault at [`FAULT_OVER_QUANTILE`] times it,
/// neither below the device's defaults (a well-calibrated device's strings
/// agree far within them, and its safety rule stays). Also the quantile.
pub fn scaled_thresholds(id: &Identification, train: &[Observation]) -> (KinematicsRule, f64) {
    let all_strings = all_strings_model(id, f64::MAX);
    let disagreement: Vec<f64> = predict(all_strings.kinematic_model(), train)
        .iter()
        .zip(train)
        .filter(|(p, o)| o.tracker.is_some() && p.rms_residual_mm.is_finite())
        .map(|(p, _)| p.rms_residual_mm)
        .collect();
    let q = quantile(&disagreement, DISAGREEMENT_QUANTILE);
    let device = KinematicsRule::default();
    let q_ok = if q.is_finite() { q } else { 0.0 };
    let rule = KinematicsRule {
        exclusion_threshold_mm: device.exclusion_threshold_mm.max(q_ok),
        fault_threshold_mm: device.fault_threshold_mm.max(FAULT_OVER_QUANTILE * q_ok),
    };
    (rule, q)
}

/// Every string in every row whose strings agree within `fault_mm`, each
/// weighing alike: the plain least-squares placement.
pub fn all_strings_alike(fault_mm: f64) -> RuleCandidate {
    RuleCandidate {
        name: "all strings, alike",
        rule: KinematicsRule {
            exclusion_threshold_mm: fault_mm,
            fault_threshold_mm: fault_mm,
        },
        weighted: false,
        speed_counted_again: false,
    }
}

/// `id` placing every row with all its strings, alike, up to `fault_mm`.
fn all_strings_model(id: &Identification, fault_mm: f64) -> Identification {
    with_rule(id, &all_strings_alike(fault_mm))
}

/// The rules tried, the one that stays first: every string in every row
/// that agrees within the scaled fault threshold, alike; then the device's
/// thresholds, the thresholds scaled to the training rows and every string
/// up to the scaled fault threshold, each weighed by the strings' scales.
/// Weighed, the scales count the structure that follows speed once more
/// where the loop `counted` it; with `speed_twins` (and `counted`), each
/// weighed rule also by the scales the training measured, after it.
pub fn candidates(scaled: KinematicsRule, counted: bool, speed_twins: bool) -> Vec<RuleCandidate> {
    let alike = all_strings_alike(scaled.fault_threshold_mm);
    // Each weighed rule: its name, its twin's, its thresholds.
    let mut weighed = vec![(
        "device thresholds, strings weighed",
        "device thresholds, strings weighed, speed not counted again",
        KinematicsRule::default(),
    )];
    if scaled != KinematicsRule::default() {
        weighed.push((
            "scaled thresholds, strings weighed",
            "scaled thresholds, strings weighed, speed not counted again",
            scaled,
        ));
    }
    weighed.push((
        "all strings, weighed",
        "all strings, weighed, speed not counted again",
        alike.rule,
    ));
    let mut out = vec![alike];
    for (name, twin, rule) in weighed {
        let candidate = RuleCandidate {
            name,
            rule,
            weighted: true,
            speed_counted_again: counted,
        };
        out.push(candidate);
        if counted && speed_twins {
            out.push(RuleCandidate {
                name: twin,
                speed_counted_again: false,
                ..candidate
            });
        }
    }
    out
}

/// Held-out position errors of `model` on `rows`.
fn held_out(model: KinematicModel<'_>, rows: &[&Observation]) -> Vec<f64> {
    let room: Vec<[f64; 3]> = predict(model, rows).iter().map(|p| p.room).collect();
    let (p, t) = paired_with_tracker(&room, rows);
    position_errors(&p, &t)
}

/// The folds a rule is chosen on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RuleFolds {
    /// The folds the diagnosis loop judges by (blocked, or two interleaved
    /// ones).
    Judged,
    /// A session too small for those (each half cannot identify the model):
    /// ten interleaved folds that each hold out a tenth, as the anchors'
    /// tolerance is chosen on (`validate::choice_folds`).
    SmallSession,
}

/// Chooses the rule for the loop's model (its identification, of its
/// structure, identified on `train`) on the held-out rows of `folds`;
/// `None` when the session has no such folds (a small session without a
/// row to spare).
pub fn choose(
    train: &[Observation],
    nominal: &Frame<f64>,
    loop_result: &LoopResult,
    config: &LoopConfig,
    folds: RuleFolds,
) -> Result<Option<RuleChoice>, IdentifyError> {
    let id = &loop_result.identification;
    let counted = loop_result.speed_counted_again_mm;
    let (scaled, q99) = scaled_thresholds(id, train);
    let any_counted = counted.iter().any(|c| *c > 0.0);
    let tried = candidates(scaled, any_counted, observes_speed(train));
    let start = Start::from_identification(id);
    let structure = &loop_result.structure;
    let fit = |rows: &[&Observation]| identify(rows, nominal, &start, structure);
    let (fits, folds_name) = match folds {
        RuleFolds::Judged => (judged_fold_fits(train, fit)?, None),
        RuleFolds::SmallSession => {
            let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
            let (name, small) = choice_folds(&tracked, rows_needed_for(structure, nominal.layout));
            if small.is_empty() {
                return Ok(None);
            }
            (fold_fits(&tracked, &small, fit)?, Some(name))
        }
    };
    // Each rule's kinematics over the held-out rows on its own core; the
    // folds' scales are those their rows measured.
    let scores: Vec<RuleScore> = tried
        .par_iter()
        .map(|c| {
            let errors: Vec<f64> = fits
                .iter()
                .flat_map(|(fold, held)| {
                    let mut fold = with_rule(fold, c);
                    if c.weighted && c.speed_counted_again {
                        count_speed_again(&mut fold.length_scale_mm, &counted);
                    }
                    held_out(fold.kinematic_model(), held)
                })
                .collect();
            RuleScore {
                candidate: *c,
                held_out: ErrorStats::of(&errors),
            }
        })
        .collect();
    let mut choice = decide(scores, q99, config.min_relative_gain);
    choice.speed_counted_again_mm = counted;
    if let Some(name) = folds_name {
        choice.reason += &format!(" ({name})");
    }
    Ok(Some(choice))
}

/// The rule that stays unless held-out data choose another (the first of
/// [`candidates`]: every string, alike, up to the fault threshold the
/// training rows' own disagreement scales), where no folds could judge
/// the rules (`why`): a session with no row to spare. The device's
/// thresholds and the strings' weights are rules set on our simulators,
/// which such a session cannot judge (decision record 0083).
pub fn unjudged(id: &Identification, train: &[Observation], why: &str) -> RuleChoice {
    let (scaled, q99) = scaled_thresholds(id, train);
    let rule = all_strings_alike(scaled.fault_threshold_mm);
    RuleChoice {
        chosen: 0,
        scores: Vec::new(),
        rule,
        disagreement_q99_mm: q99,
        reason: format!(
            "{}: the rule that stays unless held-out data choose another; {why}",
            rule.name
        ),
        speed_counted_again_mm: [0.0; STRINGS],
    }
}

/// The first score's rule (every string alike) unless another lowers the
/// held-out mean by `min_gain` (relative); then the lowest.
fn decide(scores: Vec<RuleScore>, q99: f64, min_gain: f64) -> RuleChoice {
    let means: Vec<f64> = scores.iter().map(|s| s.held_out.mean_mm).collect();
    let first = means[0];
    let Preferred { best, chosen } = preferred(&means, min_gain);
    let best = best.unwrap_or(0);
    let reason = if chosen == 0 {
        format!(
            "{}: no other lowers the held-out mean {:.3} mm by {:.0} %{}",
            scores[0].candidate.name,
            first,
            100.0 * min_gain,
            if best != 0 {
                format!(
                    " (best: {}, {:.3} mm)",
                    scores[best].candidate.name, scores[best].held_out.mean_mm
                )
            } else {
                String::new()
            }
        )
    } else {
        format!(
            "{} lowers the held-out mean {:.3} -> {:.3} mm (strings disagree up to {:.2} mm RMS \
             on 99 % of the training rows)",
            scores[chosen].candidate.name, first, scores[chosen].held_out.mean_mm, q99
        )
    };
    RuleChoice {
        chosen,
        rule: scores[chosen].candidate,
        scores,
        disagreement_q99_mm: q99,
        reason,
        speed_counted_again_mm: [0.0; STRINGS],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn score(name: &'static str, mean: f64) -> RuleScore {
        let mut held_out = ErrorStats::of(&[mean]);
        held_out.mean_mm = mean;
        RuleScore {
            candidate: RuleCandidate {
                name,
                rule: KinematicsRule::default(),
                weighted: true,
                speed_counted_again: true,
            },
            held_out,
        }
    }

    #[test]
    fn the_first_rule_stays_unless_another_gains_the_loops_margin() {
        let kept = decide(vec![score("device", 1.0), score("other", 0.99)], 0.5, 0.02);
        assert_eq!(kept.chosen, 0, "{}", kept.reason);
        let taken = decide(vec![score("device", 1.0), score("other", 0.9)], 0.5, 0.02);
        assert_eq!(taken.chosen, 1, "{}", taken.reason);
        assert!(taken.reason.contains("other"), "{}", taken.reason);
    }

    #[test]
    fn a_first_rule_that_places_nothing_gives_way() {
        let taken = decide(
            vec![score("device", f64::NAN), score("other", 3.0)],
            0.5,
            0.02,
        );
        assert_eq!(taken.chosen, 1);
    }

    #[test]
    fn scaled_candidates_never_exclude_below_the_devices_thresholds() {
        let scaled = KinematicsRule {
            exclusion_threshold_mm: 3.0,
            fault_threshold_mm: 6.0,
        };
        for c in candidates(scaled, true, true) {
            assert!(c.rule.is_valid(), "{c:?}");
            assert!(c.rule.exclusion_threshold_mm >= 1.0, "{c:?}");
        }
        let same = candidates(KinematicsRule::default(), false, true);
        assert_eq!(same.len(), 3, "no scaled duplicate of the device's rule");
        assert_eq!(same[0].name, "all strings, alike", "the plain rule first");
        assert!(!same[0].weighted);
        assert!(
            same.iter().all(|c| !c.speed_counted_again),
            "nothing counted"
        );
        let twins = candidates(KinematicsRule::default(), true, true);
        assert_eq!(
            twins.len(),
            5,
            "each weighed rule without the speed counted again"
        );
        assert_eq!(
            candidates(scaled, true, false).len(),
            4,
            "a static session: no twin"
        );
    }
}
