//! Closing the loop: find what the identified model still misses in the
//! residual, trace it to a physical effect, add the effect, refit, and keep it
//! only if it helps on data it was not fitted on ([`crate::model::validate`]).
//!
//! This file holds the loop ([`close_loop`]) and the diagnosis it runs at
//! each step ([`diagnose`]); beside it:
//! - `vocabulary`: the families, variables, changes and findings, the
//!   loop's settings and what it reports;
//! - `outliers`: the training rows whose tracker the loop sets aside;
//! - `order`: the order of the steps (rates, tables, effects), a term on
//!   time of every string tried before the tables, a term of the whole
//!   device before one string's;
//! - `rejudge`: spool rates and tables judged again once a term on time
//!   came after them;
//! - `trials`: each spool's own thinning rate and the layer tables, tried
//!   before the effect families;
//! - `evidence`: the residual rows and the model's span diagnosis reads;
//! - `candidates`: the effect families' columns, tested on the residual;
//! - `slips`: where a string slipped, whether it jumps there, and slips of
//!   several strings together;
//! - `unexplained`: structure no family explains;
//! - `describe`: the report's words for all of these.

mod candidates;
mod describe;
mod diagnosis;
mod evidence;
mod kinds;
mod order;
mod outliers;
mod rejudge;
mod revisits;
mod slips;
mod together;
mod trials;
mod unexplained;
mod vocabulary;

#[cfg(test)]
mod tests;

use kinds::{
    adds_a_drift, adds_a_motion_term, drifts_with_time, held_to_one_string_gain, one_string_term,
    same_term, steps_of, Proposals,
};
use order::FirstStep;

use std::borrow::Cow;

use spidar_core::correction::CorrectionModel;
use spidar_core::model::{Frame, MAX_EFFECTS};
use spidar_core::STRINGS;

use crate::data::observe::{at_meeting_points, Observation};
use crate::data::stats::ErrorStats;
use crate::model::identify::{
    effect_parameter_info, identify, Identification, IdentifyError, Start, Structure,
};
use crate::model::layers::{self, StringLayers, TableLevel};
use crate::model::validate::{
    held_out_error_list, interleaved_fold_errors, judge, judge_step, judgeable_folds,
    refuse_a_fold_repair, refuse_on_fold_rise, refused, stability, validate, validate_fits,
    validate_forward, FoldScope, IN_SAMPLE_SHARE_OF_GAIN,
};

use candidates::latency_not_tested;
use describe::{fitted_in_physical_terms, stage_name};
use together::{latencies_together, slips_together};
use trials::{add_layer_tables, free_spool_rates};

/// The held-out validation's figures and verdict, which the loop's findings
/// carry ([`Finding::validation`]), and the error figures its users report
/// beside the loop's.
pub use crate::model::validate::{
    cross_validated_error, model_errors, tail_noise, Check, Validation,
};
pub use describe::{family_name, variable_name};
pub use diagnosis::diagnose;
pub use outliers::{
    gross_tracker_threshold_mm, TrackerOutliers, GROSS_TRACKER_FLOOR_MM, GROSS_TRACKER_MAX_SHARE,
    GROSS_TRACKER_MEDIANS,
};
pub use unexplained::unexplained;
pub use vocabulary::{
    Change, Family, Finding, LoopConfig, LoopResult, LoopStage, Variable, RELEASED_ANCHOR_SD_MM,
};

/// Runs the loop: identify, diagnose, add the strongest significant effect,
/// refit, repeat until nothing significant that helps on held-out data
/// remains; then report the structure no family explains. "Helps" is
/// [`judge`] on [`validate`]: folds blocked in time and space, so that a
/// change that only interpolates (a drift standing in for position on a
/// lattice collected plane by plane) is refused; every tested finding carries
/// its check.
pub fn close_loop(
    train: &[Observation],
    test: Option<&[Observation]>,
    nominal: &Frame<f64>,
    start: &Start,
    config: &LoopConfig,
) -> Result<LoopResult, IdentifyError> {
    let structure = config.base_structure();
    let first = identify(train, nominal, start, &structure)?;
    let tracker_outliers = TrackerOutliers::of(&first, train);
    let cleaned = tracker_outliers.without(train);
    let (train, base) = match &cleaned {
        None => (train, first),
        Some(cleaned) => (&cleaned[..], identify(cleaned, nominal, start, &structure)?),
    };
    let base_train = model_errors(&base, train);
    let base_test = test.map(|t| model_errors(&base, t));
    if !config.diagnose {
        return Ok(LoopResult {
            identification: base.clone(),
            base,
            base_train,
            base_test,
            structure,
            stages: Vec::new(),
            findings: Vec::new(),
            layers: Vec::new(),
            tracker_outliers,
            speed_counted_again_mm: [0.0; STRINGS],
        });
    }
    let validation = validate(train, nominal, &base, &structure, FoldScope::Judged)?;
    let fresh = LoopState {
        train,
        test,
        nominal,
        config,
        validated_from: base.clone(),
        id: base.clone(),
        structure,
        validation,
        stages: Vec::new(),
        findings: Vec::new(),
        seen_train: Cow::Borrowed(train),
        seen_test: test.map(Cow::Borrowed),
    };
    let mut state = fresh.clone();
    let sequence = state.rates_tables_and_effects()?;
    let mut layers = sequence.layers;
    if config.time_terms_before_tables && sequence.took_before_effects && !state.keeps_time_term() {
        if let Some(first) = fresh.clone().time_terms_first()? {
            layers = state.the_better_order(first, layers, FirstStep::TimeTerms);
        }
    }
    if config.motion_terms_before_tables && state.refused_a_motion_term_on_a_table(&layers) {
        if let Some(first) = fresh.motion_terms_first()? {
            layers = state.the_better_order(first, layers, FirstStep::MotionTerms);
        }
    }
    let LoopState {
        mut id,
        structure,
        mut stages,
        mut findings,
        seen_train,
        seen_test,
        ..
    } = state;
    findings.extend(unexplained(&id, &seen_train, nominal, &structure, config));
    findings.extend(latency_not_tested(&seen_train));
    let speed_counted_again_mm = weigh_what_follows_speed(&mut id, &findings);
    if speed_counted_again_mm.iter().any(|a| *a > 0.0) {
        // The last stage is the final model: its errors with the weights it
        // now has.
        if let Some(last) = stages.last_mut() {
            *last = LoopStage::of(
                last.name.clone(),
                &last.finding,
                &id,
                &seen_train,
                seen_test.as_deref(),
            );
        }
    }
    Ok(LoopResult {
        layers,
        base,
        base_train,
        base_test,
        identification: id,
        structure,
        stages,
        findings,
        tracker_outliers,
        speed_counted_again_mm,
    })
}

/// A string whose residual follows the speed of motion (an encoder that
/// lags its string), which no term of the model reads, keeps that error in
/// use, and a device in use moves faster than a lattice's captures (the
/// hand slows at each point): its scale counts the unexplained structure's
/// amplitude once more, in quadrature, so that forward kinematics weighs
/// it less ([`Identification::length_scale_mm`]); the identification's
/// warnings say so. Without it such a string takes a stand-in (a
/// `backlash`) and scatters in use (decision record 0036,
/// `docs/decisions/0036-strings-weighed-by-scale.md`). Other variables are
/// read by a term or do not range wider in use than on the lattice (time
/// restarts at home, positions stay in the frame). Whether the device runs
/// with these scales is the kinematics' rule's to choose on the held-out
/// folds (a stream moves in training as in use; decision record 0066).
/// The amplitude counted again on each string (0 where none).
fn weigh_what_follows_speed(id: &mut Identification, findings: &[Finding]) -> [f64; STRINGS] {
    let mut counted = [0.0f64; STRINGS];
    for f in findings
        .iter()
        .filter(|f| f.family == Family::Unexplained && f.variable == Variable::Speed)
    {
        for &k in &f.strings {
            let k = usize::from(k);
            if id.length_scale_mm[k] > 0.0 && f.amplitude_mm.is_finite() {
                counted[k] = counted[k].hypot(f.amplitude_mm);
            }
        }
    }
    let before = id.length_scale_mm;
    count_speed_again(&mut id.length_scale_mm, &counted);
    for k in (0..STRINGS).filter(|&k| counted[k] > 0.0) {
        id.warnings.push(format!(
            "string {k}'s {FOLLOWS_SPEED}, which no term of the model reads (an encoder that \
             lags its string?), and the device moves faster in use than at the lattice's \
             captures: its scale counts that structure's {:.2} mm once more ({:.2} -> {:.2} \
             mm), so forward kinematics weighs it less",
            counted[k], before[k], id.length_scale_mm[k]
        ));
    }
    counted
}

/// What the warning of a string whose scale counts the structure that
/// follows speed says of it ([`weigh_what_follows_speed`]).
pub(crate) const FOLLOWS_SPEED: &str = "residual follows speed";

/// Each measured scale with the structure that follows speed (`counted`,
/// mm) counted once more, in quadrature; a scale of 0 (not measured) stays.
pub(crate) fn count_speed_again(scales: &mut [f64; STRINGS], counted: &[f64; STRINGS]) {
    for (scale, c) in scales.iter_mut().zip(counted) {
        if *c > 0.0 && *scale > 0.0 {
            *scale = scale.hypot(*c);
        }
    }
}

/// [`count_speed_again`] undone: the scales the training rows measured.
pub(crate) fn uncount_speed(scales: &mut [f64; STRINGS], counted: &[f64; STRINGS]) {
    for (scale, c) in scales.iter_mut().zip(counted) {
        if *c > 0.0 && *scale > 0.0 {
            *scale = (*scale * *scale - c * c).max(0.0).sqrt();
        }
    }
}

/// A validation, and the model its folds' fits started from.
struct Validated {
    validation: Validation,
    from: Identification,
}

/// What [`close_loop`] carries from step to step: the model so far, its
/// validation, the stages and findings reported, and the sessions.
#[derive(Clone)]
struct LoopState<'a> {
    train: &'a [Observation],
    test: Option<&'a [Observation]>,
    nominal: &'a Frame<f64>,
    config: &'a LoopConfig,
    id: Identification,
    structure: Structure,
    validation: Validation,
    /// The model `validation`'s fold fits started from: its interleaved
    /// folds are fitted from it when a step in time is judged.
    validated_from: Identification,
    stages: Vec<LoopStage>,
    findings: Vec<Finding>,
    /// The sessions as the model reads them: at the strings' meeting point
    /// once a marker offset is found (the tracker sees the body's origin).
    seen_train: Cow<'a, [Observation]>,
    seen_test: Option<Cow<'a, [Observation]>>,
}

impl LoopState<'_> {
    /// Each spool's own thinning rate ([`free_spool_rates`]): its finding,
    /// and the refit when accepted.
    fn try_spool_rates(&mut self) -> Result<(), IdentifyError> {
        let (finding, added) = free_spool_rates(
            &self.seen_train,
            self.nominal,
            &self.id,
            &self.structure,
            &self.validation,
            self.config,
        )?;
        match added {
            Some((refit, free, after)) => {
                let name = format!("spool rates strings {:?}", finding.strings);
                let validated = Validated {
                    validation: after,
                    from: self.id.clone(),
                };
                self.accept(name, finding, refit, free, validated, None);
            }
            None => self.findings.push(finding),
        }
        Ok(())
    }

    /// One try of the layer tables ([`add_layer_tables`]): `None` when no
    /// string wanted a table, else whether they were added; the strings'
    /// choices.
    fn try_layer_tables(&mut self) -> Result<(Option<bool>, Vec<StringLayers>), IdentifyError> {
        let tried = add_layer_tables(
            &self.seen_train,
            self.nominal,
            &self.id,
            &self.structure,
            &self.validation,
            self.config,
        )?;
        self.take_layer_try(tried)
    }

    /// A try of the layer tables into the model (accepted) or the report.
    fn take_layer_try(
        &mut self,
        tried: trials::LayerTry,
    ) -> Result<(Option<bool>, Vec<StringLayers>), IdentifyError> {
        let Some(mut finding) = tried.finding else {
            return Ok((None, tried.choice));
        };
        let added = tried.added.is_some();
        // A refused try's finding gives way to this one; tables added
        // earlier (judged again after a term on time) stay in the story.
        self.findings
            .retain(|f| f.family != Family::Layers || f.added);
        match tried.added {
            Some((refit, _)) => {
                // The tables' own check fits each fold's tables on the
                // fold's rows; every later change is validated with the
                // tables held (fitted on every row, the held-out ones
                // included), and must be judged against the same structure
                // validated the same way. The check's own figure as the
                // baseline would give the first change after the tables a
                // gain it does not make, and an offset or a drift would
                // stand in on that (decision record 0025,
                // `docs/decisions/0025-one-baseline-after-tables.md`).
                let held = validate(
                    &self.seen_train,
                    self.nominal,
                    &refit,
                    &self.structure,
                    FoldScope::Judged,
                )?;
                finding.description += &format!(
                    " (the changes after the tables are judged against {:.3} mm: the same \
                     held-out folds with the tables held, as those changes are validated)",
                    held.held.mean_mm
                );
                let name = stage_name(&finding);
                // The tables are the refit's string laws: the structure
                // stays.
                let structure = self.structure.clone();
                let validated = Validated {
                    validation: held,
                    from: refit.clone(),
                };
                self.accept(name, finding, refit, structure, validated, None);
            }
            None => self.findings.push(finding),
        }
        Ok((Some(added), tried.choice))
    }

    /// Diagnose, add the first of the three strongest proposals (then the
    /// slips of several strings together) that helps on held-out data,
    /// repeat until none helps or the loop holds its most effects; only
    /// the terms on time with [`Proposals::TimeTerms`].
    fn add_effects(&mut self, which: Proposals) -> Result<(), IdentifyError> {
        'outer: while self.stages.len() < self.config.max_effects {
            let proposals = diagnose(
                &self.id,
                &self.seen_train,
                self.nominal,
                &self.structure,
                self.config,
            );
            // Findings without a change (a term on time the revisits do not
            // show) are reported, and take no place among the strongest.
            let (proposals, reported): (Vec<Finding>, Vec<Finding>) = proposals
                .into_iter()
                .filter(|f| which.takes(f))
                .partition(|f| f.change.is_some());
            for finding in reported {
                self.report(finding);
            }
            let slips: Vec<&Finding> = proposals
                .iter()
                .filter(|f| f.family == Family::Slip && f.strings.len() == 1)
                .collect();
            let together = slips_together(&slips);
            let latencies: Vec<&Finding> = proposals
                .iter()
                .filter(|f| f.family == Family::Latency && f.strings.len() == 1)
                .collect();
            let lagging = latencies_together(&latencies);
            let frame_wide: Vec<Finding> = proposals
                .iter()
                .filter(|f| f.strings.is_empty() && f.change.is_some())
                .cloned()
                .collect();
            let each_string: Vec<Finding> = proposals
                .iter()
                .filter(|f| matches!(f.change, Some(Change::Stretches(..))))
                .cloned()
                .collect();
            let mut tried: Vec<Finding> = Vec::new();
            let mut frame_wide_below = Vec::new();
            let mut rank = 0;
            for finding in proposals {
                // Drifts of several strings are tried beside the strongest,
                // not in the place of one: where slips of several strings
                // are what changes with time, they stand in for them and
                // are refused, and must not push a slip out.
                let beside = matches!(finding.change, Some(Change::Drifts(_)));
                if rank >= STRONGEST_TRIED && !beside {
                    if finding.strings.is_empty() {
                        frame_wide_below.push(finding);
                    }
                    continue;
                }
                rank += usize::from(!beside);
                tried.push(finding.clone());
                let before = (finding.change.is_some_and(one_string_term)
                    || (finding.strings.is_empty() && !each_string.is_empty()))
                .then(|| self.clone());
                let shared = finding.strings.is_empty();
                if self.try_finding(finding)? {
                    match before {
                        Some(before) if shared => {
                            self.prefer_each_string(before, &each_string, &tried)?
                        }
                        Some(before) => self.prefer_frame_wide(before, &frame_wide, &tried)?,
                        None => {}
                    }
                    continue 'outer;
                }
            }
            // Several strings that slipped in one session: each step alone
            // leaves the others to the rest of the model (and the layer
            // tables, which a step in time bends, were refused), so none
            // helps alone. Tried together, as one change, when none of the
            // strongest helped alone.
            if let Some((finding, change)) = together.filter(|_| which == Proposals::All) {
                if self.try_change(finding, change)? {
                    continue 'outer;
                }
            }
            // Strings read late, each of whose latencies was refused alone:
            // tried together, before a latency every string shares stands
            // in for them (decision record 0067). Lags are the strings'
            // against the tracker's clock, whose offset the alignment found
            // from the motion of every string, late ones too: the strings on
            // time then read early alike. The latency every string shares,
            // proposed beside them, is tried from the model without the
            // group as a one-string term's frame-wide rivals are, and takes
            // its place when its blocked folds reach a lower mean
            // (decision record 0080).
            if let Some((finding, change)) = lagging.filter(|_| which == Proposals::All) {
                let shared_lag: Vec<Finding> = frame_wide
                    .iter()
                    .filter(|f| f.family == Family::Latency)
                    .cloned()
                    .collect();
                // The state (a session moved by a marker offset among it)
                // is kept only when there is a rival to try from it.
                let before = (!shared_lag.is_empty()).then(|| self.clone());
                if self.try_change(finding, change)? {
                    if let Some(before) = before {
                        self.prefer_frame_wide(before, &shared_lag, &tried)?;
                    }
                    continue 'outer;
                }
            }
            // A term of the whole frame or of the tracked body below them
            // (a marker offset can sit under three per-string proposals
            // that are refused): one parameter
            // set for every string, which the blocked folds judge as well as
            // the strongest; the per-string proposals below stay untried
            // (about 50 of them, the ones that stand in for other physics).
            for finding in frame_wide_below {
                let before = (!each_string.is_empty()).then(|| self.clone());
                if self.try_finding(finding)? {
                    if let Some(before) = before {
                        self.prefer_each_string(before, &each_string, &tried)?;
                    }
                    continue 'outer;
                }
            }
            break;
        }
        Ok(())
    }

    /// A finding not added, in the report in place of an earlier one of
    /// the same family and strings that was not added either (an added one
    /// is a stage of the model: a string's second slip must not take its
    /// first out of the report).
    fn report(&mut self, finding: Finding) {
        self.findings.retain(|f| f.added || !same_term(f, &finding));
        self.findings.push(finding);
    }

    /// [`try_change`](Self::try_change) with the finding's own change;
    /// `false` for a finding without one (an anchor to inspect).
    fn try_finding(&mut self, finding: Finding) -> Result<bool, IdentifyError> {
        self.try_rival(finding, f64::INFINITY)
    }

    /// [`try_finding`](Self::try_finding) for a rival of a term taken
    /// (the model it is tried on is dropped unless it wins): `false` as
    /// soon as its blocked folds' mean is above `most_mm`, before the
    /// checks and the refit on every row, which could only make a model
    /// that is dropped.
    fn try_rival(&mut self, finding: Finding, most_mm: f64) -> Result<bool, IdentifyError> {
        match finding.change {
            Some(change) => self.try_change_at_most(finding, change, most_mm),
            None => Ok(false),
        }
    }

    /// Validates the model with `finding`'s `change` and judges it; adds it
    /// (a stage, the refit) when accepted. The finding, with its check,
    /// replaces an earlier one of the same family and strings that was not
    /// added (an added one is a stage of the model: a string's second slip
    /// must not take its first out of the report). Whether the change was
    /// added.
    fn try_change(&mut self, finding: Finding, change: Change) -> Result<bool, IdentifyError> {
        self.try_change_at_most(finding, change, f64::INFINITY)
    }

    /// [`try_change`](Self::try_change), refused as soon as the blocked
    /// folds' mean is above `most_mm` ([`try_rival`](Self::try_rival)).
    fn try_change_at_most(
        &mut self,
        mut finding: Finding,
        change: Change,
        most_mm: f64,
    ) -> Result<bool, IdentifyError> {
        let candidate = self.structure.with(change);
        if let Some(reason) = beyond_the_device(&candidate) {
            finding.validation = Some(Check {
                before: self.validation.summary(),
                after: self.validation.summary(),
                stability_chi2: None,
                accepted: false,
                reason,
            });
            self.report(finding);
            return Ok(false);
        }
        let moved = (candidate.marker_body_mm != self.structure.marker_body_mm).then(|| {
            // The session as the current offset reads it is set down while
            // another offset is tried, and read again if that is refused:
            // each reading of a long session is its size again.
            self.seen_train = Cow::Borrowed(self.train);
            at_meeting_points(self.train, candidate.marker_body_mm).into_owned()
        });
        let train: &[Observation] = moved.as_deref().unwrap_or(&self.seen_train);
        let retabled = self.with_step_in_the_tables(change, train, &candidate)?;
        let from = retabled.as_ref().unwrap_or(&self.id);
        let scope = if steps_of(change).is_some() {
            // A step in time is judged on the interleaved folds too, the
            // model's as well as the candidate's.
            if self.validation.lacks_interleaved() {
                let (errors, inconsistent) = interleaved_fold_errors(
                    train,
                    self.nominal,
                    &self.validated_from,
                    &self.structure,
                )?;
                self.validation.add_interleaved(errors, inconsistent);
            }
            FoldScope::WithInterleaved
        } else {
            FoldScope::Judged
        };
        let (after, fits) = validate_fits(train, self.nominal, from, &candidate, scope)?;
        if after.held.mean_mm > most_mm {
            self.refuse(finding, moved.is_some());
            return Ok(false);
        }
        let mut check = self.judge_change(change, train, &after, &fits);
        if check.accepted && adds_a_drift(change) && self.config.time_terms_forward {
            check = self.judge_forward(check, train, from, &candidate)?;
        }
        // A term on one string that gains held out must also gain on every
        // row: the refit it would be is made now, and kept if accepted.
        let mut refit_now = None;
        if check.accepted && one_string_term(change) && retabled.is_none() {
            let refit = identify(
                train,
                self.nominal,
                &Start::from_identification(&self.id),
                &candidate,
            )?;
            let in_sample = |id: &Identification| ErrorStats::of(&held_out_error_list(id, train));
            // A drift need only not raise the error of the rows it is fitted
            // on: where time goes with position the fit on every row absorbs
            // it into position terms (which is why it must beat a position
            // error, its rival) and only a fold fitted on one half in time
            // shows its gain; a drift that raises it stands in for something
            // else (a string riding out of its groove) and raises the test
            // error.
            let share = if adds_a_drift(change) {
                0.0
            } else {
                IN_SAMPLE_SHARE_OF_GAIN
            };
            refuse_a_fold_repair(&mut check, in_sample(&self.id), in_sample(&refit), share);
            refit_now = Some(refit);
        }
        let accepted = check.accepted;
        finding.validation = Some(check.summarized());
        if !accepted {
            self.refuse(finding, moved.is_some());
            return Ok(false);
        }
        self.findings.retain(|f| f.added || !same_term(f, &finding));
        let validated = Validated {
            validation: after,
            from: from.clone(),
        };
        let refit = match retabled.or(refit_now) {
            Some(refit) => refit,
            None => identify(
                train,
                self.nominal,
                &Start::from_identification(&self.id),
                &candidate,
            )?,
        };
        if let Some(fitted) = fitted_in_physical_terms(change, &refit) {
            finding.description += &fitted;
        }
        // A term fitted beyond its fixed point's range would make a
        // calibration `spidar compile` refuses: a change must leave a model
        // the device can hold, where the model before it could
        // (decision record 0082).
        let cannot_hold = |id: &Identification| {
            crate::model::compile::device_cannot_hold(&id.calibration(CorrectionModel::None))
        };
        if let Some(why) = cannot_hold(&refit).filter(|_| cannot_hold(&self.id).is_none()) {
            if let Some(check) = finding.validation.as_mut() {
                check.accepted = false;
                check.reason = format!(
                    "not added: the device cannot hold it ({why}), though {}",
                    check.reason.trim_start_matches("added: ")
                );
            }
            self.refuse(finding, moved.is_some());
            return Ok(false);
        }
        let name = stage_name(&finding);
        self.accept(name, finding, refit, candidate, validated, moved);
        Ok(true)
    }

    /// A change not taken: its finding in the report, and the training
    /// session read again as the model's marker offset reads it when the
    /// change had `moved` it.
    fn refuse(&mut self, finding: Finding, moved: bool) {
        if moved {
            self.seen_train = at_meeting_points(self.train, self.structure.marker_body_mm);
        }
        self.report(finding);
    }

    /// Takes a change judged good into the model: the sessions as the new
    /// model reads them (`moved`: the training session at the strings'
    /// meeting point, when the change is a marker offset; the test session
    /// is moved alike), the stage `name` with the refit's errors on them,
    /// the finding (added), and the model (`refit`, its `structure` and
    /// `validated`) every later change is judged against.
    fn accept(
        &mut self,
        name: String,
        mut finding: Finding,
        refit: Identification,
        structure: Structure,
        validated: Validated,
        moved: Option<Vec<Observation>>,
    ) {
        if let Some(moved) = moved {
            self.seen_train = Cow::Owned(moved);
            self.seen_test = self
                .test
                .map(|t| at_meeting_points(t, structure.marker_body_mm));
        }
        finding.added = true;
        self.stages.push(LoopStage::of(
            name,
            &finding,
            &refit,
            &self.seen_train,
            self.seen_test.as_deref(),
        ));
        self.findings.push(finding);
        self.validation = validated.validation;
        self.validated_from = validated.from;
        self.structure = structure;
        self.id = refit;
    }

    /// `check` (an accepted drift's) refused when the drift, fitted on the
    /// earlier rows, predicts the later ones worse than the model without
    /// it ([`validate_forward`]): a term that reads time is used later than
    /// it was fitted, so it must predict forward, whatever the blocked folds
    /// (which also fit the later half and predict the earlier) say.
    fn judge_forward(
        &self,
        check: Check,
        train: &[Observation],
        from: &Identification,
        candidate: &Structure,
    ) -> Result<Check, IdentifyError> {
        let before = validate_forward(train, self.nominal, &self.id, &self.structure)?;
        let after = validate_forward(train, self.nominal, from, candidate)?;
        let (Some(before), Some(after)) = (before, after) else {
            return Ok(check);
        };
        if after.mean_mm <= before.mean_mm {
            return Ok(Check {
                reason: format!(
                    "{}; forward (fitted on the earlier rows, the later predicted) {:.3} -> {:.3} mm",
                    check.reason, before.mean_mm, after.mean_mm
                ),
                ..check
            });
        }
        let why = format!(
            "fitted on the earlier rows it predicts the later ones worse, {:.3} -> {:.3} mm \
             (forward chaining), though the blocked folds took it",
            before.mean_mm, after.mean_mm
        );
        Ok(refused(check, &why))
    }

    /// With a step (a slip) proposed on a model with layer tables: the
    /// model with the step, its tables refitted together with it
    /// ([`layers::fit_table_with_slips`]), which the step is validated from
    /// and, accepted, is the refit. `None` for other changes or without
    /// tables: they are validated from the current model, tables held.
    fn with_step_in_the_tables(
        &self,
        change: Change,
        train: &[Observation],
        candidate: &Structure,
    ) -> Result<Option<Identification>, IdentifyError> {
        if steps_of(change).is_none() {
            return Ok(None);
        }
        let steps = layers::steps_in(&self.id);
        if steps.iter().all(Option::is_none) {
            return Ok(None);
        }
        let sized = identify(
            train,
            self.nominal,
            &Start::from_identification(&self.id),
            candidate,
        )?;
        layers::identify_with_layers(
            train,
            self.nominal,
            &sized,
            candidate,
            &steps,
            TableLevel::Kept,
        )
        .map(Some)
    }

    /// The check of `change` validated on `train` (`after`, each fold's
    /// fit in `fits`): a slip on the folds that can judge a step, any other
    /// change on the blocked folds with its stability; an accepted drift is
    /// refused when it only moves error between folds.
    fn judge_change(
        &self,
        change: Change,
        train: &[Observation],
        after: &Validation,
        fits: &[Identification],
    ) -> Check {
        let min_gain = if held_to_one_string_gain(change) {
            self.config.min_relative_gain_one_string
        } else {
            self.config.min_relative_gain
        };
        let check = match steps_of(change) {
            None => {
                // The parameters of the terms the change adds (none: a
                // change of the geometry or the tracked body, no halves
                // test).
                let added: usize = change
                    .effect_terms()
                    .iter()
                    .map(|t| effect_parameter_info(&t.effect).len())
                    .sum();
                // A term of one string is held to white residuals' sds:
                // searched on every string, it stands in more often
                // (record 0032), and its halves are what refuse it
                // (record 0058).
                let held: &[f64] = if one_string_term(change) {
                    &[]
                } else {
                    &after.held_errors
                };
                let stable = (added > 0).then(|| stability(added, fits, held)).flatten();
                judge(&self.validation, after, stable, min_gain)
            }
            Some(steps_at_s) => {
                let (keep, left_out) = judgeable_folds(&steps_at_s, train);
                judge_step(
                    &self.validation,
                    after,
                    &keep,
                    &left_out,
                    self.config.min_relative_gain,
                )
            }
        };
        if check.accepted && adds_a_drift(change) {
            refuse_on_fold_rise(check)
        } else {
            check
        }
    }
}

/// How many of a diagnosis's strongest proposals the loop tries before
/// the slips of several strings together and the frame-wide terms below.
const STRONGEST_TRIED: usize = 3;

/// Why `structure` cannot run on the device, if it cannot: its blob holds at
/// most [`MAX_EFFECTS`] effect terms (several strings' slips added together
/// take one each, and a string may slip more than once).
fn beyond_the_device(structure: &Structure) -> Option<String> {
    (structure.effects.len() > MAX_EFFECTS).then(|| {
        format!(
            "not added: the model would hold {} effect terms, the device at most {MAX_EFFECTS}",
            structure.effects.len()
        )
    })
}
