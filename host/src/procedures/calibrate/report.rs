//! The calibration report: the JSON document `spidar calibrate --json` writes
//! (schema in `docs/json-schema.md`) and the readable summary printed on
//! stdout.

use std::fmt::Write as _;

use serde::Serialize;

use crate::data::stats::ErrorStats;
use crate::model::diagnose::Finding;
use crate::model::identify::{Identification, ParameterEstimate};
use crate::model::learn::outliers::OutlierReport;
use crate::model::learn::search::{SvrCandidate, SvrSearchResult, SweepPoint, SweepResult};
use crate::model::learn::svr::SvrParams;
use spidar_core::model::EffectTerm;

/// Version of the report's JSON layout. The major number changes when a key
/// is removed or changes meaning; new keys do not change it.
pub const SCHEMA: &str = "spidar-calibrate-report/1";

/// The whole report.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub tool: Tool,
    pub inputs: Inputs,
    /// The device's strings and what their number allows.
    pub device: StringsReport,
    /// The tracker's clock against the device's, per session.
    pub timing: Timing,
    /// Pipeline order; the last stage is the final model.
    pub stages: Vec<Stage>,
    /// Everything the diagnosis loop reported (added or not).
    pub effects: Vec<Finding>,
    pub identification: IdentificationReport,
    /// How the final model was chosen.
    pub selection: Selection,
    /// Residual-mode corrections (the `nn` and `svr` stages); `null` when
    /// the training session is too small to learn them (see `warnings`).
    pub corrections: Option<Corrections>,
    /// The forward kinematics' rule the final model runs, and the
    /// candidates' held-out errors.
    pub kinematics: KinematicsReport,
    /// The anchors' tolerance (the identification's prior), given by the
    /// geometry or chosen on held-out rows ([`crate::model::tolerance`]).
    pub anchor_tolerance: crate::model::tolerance::ToleranceChoice,
    /// Whether the flashed model applies the training session's slips, and
    /// under which home capture.
    pub device_slips: DeviceSlips,
    /// The paper's black-box procedure, when run (`null` otherwise).
    pub blackbox: Option<Blackbox>,
    pub warnings: Vec<String>,
    /// What else the run could do, for information (not a problem with the
    /// result: e.g. that `--blackbox` would add the paper's procedure).
    #[serde(default)]
    pub notes: Vec<String>,
    pub timings_s: Timings,
    pub figures: Vec<Figure>,
    pub files: Files,
}

/// What the calibration did about the tracker's clock, per session.
#[derive(Clone, Debug, Serialize)]
pub struct Timing {
    pub train: super::align::SessionTiming,
    pub test: super::align::SessionTiming,
}

/// The strings of the calibrated device and what their number means for
/// what calibration and tracking can check.
#[derive(Clone, Debug, Serialize)]
pub struct StringsReport {
    /// Number of strings (anchors), 3..=8.
    pub strings: usize,
    /// Encoder channels that carry them.
    pub channels: Vec<usize>,
    /// The end-effector moves in the anchors' plane.
    pub planar: bool,
    /// Degrees of freedom of the position (2 or 3).
    pub dof: usize,
    /// Strings beyond the degrees of freedom.
    pub redundancy: usize,
    /// Whether forward kinematics can exclude a faulty string (needs 2 spare
    /// strings).
    pub fault_rejection: bool,
    /// Smallest constant error of one string that diagnosis would find on
    /// this training session (mm; `sigma * sqrt(chi2 threshold / rows)`,
    /// before the loss of power to what the model already absorbs).
    pub smallest_detectable_offset_mm: f64,
    /// What the number of strings and rows leaves unchecked, in words.
    pub limits: Vec<String>,
    /// What forward kinematics did with each row of the final identified
    /// model, per session: strings excluded as faulty, rows whose strings
    /// disagree with no single culprit.
    pub rejections: SessionRejections,
    /// Each string's measured scale and its weight in forward kinematics,
    /// in channel order.
    pub string_weights: Vec<StringWeight>,
    /// The typical string's scale, which the others are weighed against
    /// (mm; 0 when not measured).
    pub typical_scale_mm: f64,
}

/// How much forward kinematics trusts one string
/// ([`spidar_core::kinematics::residual_weights`]).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StringWeight {
    pub channel: usize,
    /// Robust scale of the part of its length residual that changes from
    /// row to row on the training session, mm.
    pub scale_mm: f64,
    /// Its residual's weight in forward kinematics (1: as the typical
    /// string; at least `MIN_RESIDUAL_WEIGHT`).
    pub weight: f64,
}

/// Below this weight the report names the string: it pulls the position
/// noticeably less than the others.
const NOTABLE_WEIGHT: f64 = 0.8;

/// [`Rejections`] of the training and the test session.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SessionRejections {
    pub train: Rejections,
    pub test: Rejections,
}

/// How forward kinematics treated the rows of one session.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Rejections {
    /// Rows predicted.
    pub rows: usize,
    /// Rows where this channel's string was excluded as faulty, per
    /// channel (0..8; channels without a string stay 0).
    pub excluded_by_channel: [usize; spidar_core::STRINGS],
    /// Rows whose strings disagree and no single exclusion is trusted (the
    /// device turns force off there), `inconsistent_excluded_by_channel`
    /// among them.
    pub inconsistent: usize,
    /// Of the inconsistent rows, those whose position leaves this channel's
    /// string out (the exclusion that fits clearly best, not trusted), per
    /// channel; the others are the all-string compromise.
    pub inconsistent_excluded_by_channel: [usize; spidar_core::STRINGS],
    /// Rows where the solve did not converge.
    pub not_converged: usize,
    /// Rows with an invalid length (NaN, negative).
    pub invalid: usize,
}

impl Rejections {
    pub fn of(predictions: &[crate::model::predict::Prediction]) -> Rejections {
        use spidar_core::kinematics::FkStatus;
        let mut r = Rejections {
            rows: predictions.len(),
            ..Rejections::default()
        };
        for p in predictions {
            match p.status {
                FkStatus::Ok => {}
                FkStatus::FaultyStringExcluded => {
                    if let Some(c) = p
                        .excluded
                        .and_then(|s| r.excluded_by_channel.get_mut(usize::from(s)))
                    {
                        *c += 1;
                    }
                }
                FkStatus::Inconsistent => {
                    r.inconsistent += 1;
                    if let Some(c) = p
                        .excluded
                        .and_then(|s| r.inconsistent_excluded_by_channel.get_mut(usize::from(s)))
                    {
                        *c += 1;
                    }
                }
                FkStatus::NotConverged => r.not_converged += 1,
                FkStatus::InvalidInput => r.invalid += 1,
            }
        }
        r
    }

    /// Rows not solved from all strings in agreement.
    pub fn flagged(&self) -> usize {
        self.excluded_by_channel.iter().sum::<usize>()
            + self.inconsistent
            + self.not_converged
            + self.invalid
    }

    /// One line in words, e.g. `3 of 2197 rows: string 2 excluded 3 times`.
    pub fn describe(&self) -> String {
        let mut parts: Vec<String> = self
            .excluded_by_channel
            .iter()
            .enumerate()
            .filter(|(_, &n)| n > 0)
            .map(|(s, &n)| {
                format!(
                    "string {s} excluded {n} time{}",
                    if n == 1 { "" } else { "s" }
                )
            })
            .collect();
        let placed: usize = self.inconsistent_excluded_by_channel.iter().sum();
        if self.inconsistent > 0 {
            let mut line = format!(
                "{} inconsistent (strings disagreeing, no exclusion trusted",
                self.inconsistent
            );
            let without: Vec<String> = self
                .inconsistent_excluded_by_channel
                .iter()
                .enumerate()
                .filter(|(_, &n)| n > 0)
                .map(|(s, &n)| format!("{n} without string {s}"))
                .collect();
            if !without.is_empty() {
                line += &format!(
                    "; placed {}, {} by all strings",
                    without.join(", "),
                    self.inconsistent - placed
                );
            }
            parts.push(line + ")");
        }
        for (n, what) in [
            (self.not_converged, "not converged"),
            (self.invalid, "invalid lengths"),
        ] {
            if n > 0 {
                parts.push(format!("{n} {what}"));
            }
        }
        if parts.is_empty() {
            format!("all {} rows solved with every string", self.rows)
        } else {
            format!(
                "{} of {} rows: {}",
                self.flagged(),
                self.rows,
                parts.join(", ")
            )
        }
    }
}

impl StringsReport {
    /// The report of `layout` calibrated from `tracked_rows` rows whose
    /// string residuals scatter by `residual_scale_mm` (each string's own
    /// scale `length_scale_mm`).
    pub fn of(
        layout: spidar_core::model::StringLayout,
        tracked_rows: usize,
        residual_scale_mm: f64,
        length_scale_mm: &[f64; spidar_core::STRINGS],
        chi2_threshold: f64,
        rejections: SessionRejections,
    ) -> StringsReport {
        let weights = spidar_core::kinematics::residual_weights(layout, length_scale_mm);
        let typical_scale_mm =
            spidar_core::kinematics::typical_scale(layout, length_scale_mm).unwrap_or(0.0);
        let string_weights = layout
            .indices()
            .map(|channel| StringWeight {
                channel,
                scale_mm: length_scale_mm[channel],
                weight: weights[channel],
            })
            .collect();
        let redundancy = layout.redundancy();
        let mut limits = Vec::new();
        match redundancy {
            0 => limits.push(
                "no spare string: the strings always agree on a position, so neither tracking \
                 nor calibration can see a string that reads wrong; string errors show only \
                 against the tracker"
                    .to_string(),
            ),
            1 => limits.push(
                "one spare string: the device sees when its strings disagree, but cannot tell \
                 which one is faulty (excluding a string needs 2 spare); a faulty string makes \
                 the position the least-squares compromise, flagged inconsistent"
                    .to_string(),
            ),
            2 => limits.push(
                "two spare strings: a faulty string is left out where its exclusion is the one \
                 set of strings that fits; where another fits by chance too, the row is flagged \
                 inconsistent (force off) and placed by the exclusion that fits clearly best, \
                 else by the least-squares compromise"
                    .to_string(),
            ),
            _ => {}
        }
        let smallest = residual_scale_mm * (chi2_threshold / tracked_rows.max(1) as f64).sqrt();
        if tracked_rows < 200 {
            limits.push(format!(
                "{tracked_rows} tracked rows: diagnosis sees a constant error of one string only \
                 above ~{smallest:.2} mm, and effects that depend on time, direction or speed \
                 are only testable with many rows spread over them"
            ));
        }
        StringsReport {
            strings: layout.count(),
            channels: layout.indices().collect(),
            planar: layout.planar,
            dof: layout.dof(),
            redundancy,
            fault_rejection: redundancy >= 2,
            smallest_detectable_offset_mm: smallest,
            limits,
            rejections,
            string_weights,
            typical_scale_mm,
        }
    }

    /// The strings forward kinematics trusts noticeably less than the
    /// typical one, in words (None when there is none).
    fn describe_weights(&self) -> Option<String> {
        let notable: Vec<String> = self
            .string_weights
            .iter()
            .filter(|w| w.weight < NOTABLE_WEIGHT)
            .map(|w| {
                format!(
                    "string {} by {:.2} (its length scatters {:.2} mm)",
                    w.channel, w.weight, w.scale_mm
                )
            })
            .collect();
        if notable.is_empty() {
            return None;
        }
        Some(format!(
            "forward kinematics weighs {} against the typical string's {:.2} mm: \
             a string noisier than the others pulls the position less",
            notable.join(", "),
            self.typical_scale_mm
        ))
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct Tool {
    pub name: &'static str,
    pub version: &'static str,
}

impl Tool {
    pub fn current() -> Tool {
        Tool {
            name: "spidar",
            version: env!("CARGO_PKG_VERSION"),
        }
    }
}

/// Whether the model flashed from the calibration applies the training
/// session's slips (`calibration.json`'s `home`), and under which home
/// capture: while the device's `State::home_id` is `home_id`, until its
/// next `Home` or a reboot (decision record 0049, "Device side").
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DeviceSlips {
    /// The home capture the slips apply under; `null` when the model
    /// carries none.
    pub home_id: Option<u64>,
    /// The slips carried (each on one string, `at_s` since the capture).
    pub slips: Vec<EffectTerm>,
    /// The final model's slips not carried (of a capture that is over,
    /// fitted across captures, or none carried at all: `reason` says why).
    pub not_carried: Vec<EffectTerm>,
    /// Why, in a sentence (the summary prints it).
    pub reason: String,
}

/// A slip as the report lists it.
fn describe_slip(t: &EffectTerm) -> String {
    match t.effect {
        spidar_core::model::Effect::Slip { at_s, mm } => {
            format!("string {} {mm:+.2} mm from {at_s:.1} s", t.string)
        }
        _ => String::new(),
    }
}

impl DeviceSlips {
    /// The slips among the final identified model's `effects` that the
    /// device can apply under `training`'s home capture: those of its last
    /// capture ([`crate::data::home::TrainingHome::slip_is_of_last_capture`]),
    /// each on one string, at most [`spidar_core::model::MAX_HOME_SLIPS`].
    pub fn of(training: &crate::data::home::TrainingHome, effects: &[EffectTerm]) -> DeviceSlips {
        use crate::data::home::SlipRows;
        use spidar_core::model::{Effect, MAX_HOME_SLIPS};
        let all: Vec<EffectTerm> = effects
            .iter()
            .filter(|t| matches!(t.effect, Effect::Slip { .. }))
            .copied()
            .collect();
        let listed = |slips: &[EffectTerm]| {
            slips
                .iter()
                .map(describe_slip)
                .collect::<Vec<_>>()
                .join(", ")
        };
        let not_carried = |why: &str| DeviceSlips {
            home_id: None,
            slips: Vec::new(),
            not_carried: all.clone(),
            reason: format!(
                "the training session's slips ({}) are not carried to the device: {why}; it runs \
                 the model for its next home capture",
                listed(&all)
            ),
        };
        if all.is_empty() {
            return DeviceSlips {
                home_id: None,
                slips: Vec::new(),
                not_carried: Vec::new(),
                reason: "the training session has no slip to carry".into(),
            };
        }
        let Some(home_id) = training.home_id else {
            return not_carried(&training.reason);
        };
        if all
            .iter()
            .any(|t| usize::from(t.string) >= spidar_core::STRINGS)
        {
            return not_carried("a slip shared by every string is not a slip of one string");
        }
        let (slips, earlier): (Vec<EffectTerm>, Vec<EffectTerm>) =
            all.iter().partition(|t| match t.effect {
                Effect::Slip { at_s, .. } => training.slip_is_of_last_capture(at_s),
                _ => false,
            });
        // Why each slip left out is not the last capture's.
        let why_left = || {
            earlier
                .iter()
                .map(|t| {
                    let at_s = match t.effect {
                        Effect::Slip { at_s, .. } => at_s,
                        _ => 0.0,
                    };
                    let why = match training.rows_of_slip(at_s) {
                        SlipRows::Earlier => {
                            "a slip of an earlier capture, over with it (only rows of the earlier \
                             captures are that long after their own)"
                        }
                        _ => {
                            "fitted across captures (it shifted rows of the earlier captures and \
                             of the last alike, each that long after its own)"
                        }
                    };
                    format!("{} is {why}", describe_slip(t))
                })
                .collect::<Vec<_>>()
                .join("; ")
        };
        if slips.is_empty() {
            return not_carried(&format!("{}; {}", training.reason, why_left()));
        }
        if slips.len() > MAX_HOME_SLIPS {
            return not_carried(&format!("a blob carries at most {MAX_HOME_SLIPS}"));
        }
        let whose = if training.captures > 1 {
            format!(
                "the last of the training session's {} (from line {} on)",
                training.captures,
                training.first_row + 2
            )
        } else {
            "the training session's".into()
        };
        let left = if earlier.is_empty() {
            String::new()
        } else {
            format!("; not carried: {}", why_left())
        };
        DeviceSlips {
            home_id: Some(home_id),
            reason: format!(
                "the flashed model applies {} of the training session's slips ({}) while the \
                 device stays under home capture {home_id}, {whose}; from its next `Home` or a \
                 reboot it runs without them{left}",
                slips.len(),
                listed(&slips)
            ),
            slips,
            not_carried: earlier,
        }
    }

    /// What `calibration.json` carries: the slips and their capture, or
    /// nothing.
    pub fn home_slips(&self) -> Option<spidar_core::model::HomeSlips> {
        self.home_id.map(|home_id| spidar_core::model::HomeSlips {
            home_id,
            slips: self.slips.clone(),
        })
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct Inputs {
    pub geometry: String,
    pub train: SessionInfo,
    pub test: SessionInfo,
}

#[derive(Clone, Debug, Serialize)]
pub struct SessionInfo {
    pub path: String,
    pub rows: usize,
    /// Rows with a tracker position (the rows every statistic is over),
    /// after the rows set aside.
    pub tracked: usize,
    /// Rows without a tracker position (after the rows set aside).
    pub occluded: usize,
    pub has_legacy: bool,
    pub has_tension: bool,
    pub ignored_columns: Vec<String>,
    /// Known columns left unread (the legacy controller's `dev_*` without
    /// `--blackbox` or `--export-pairs`): not checked, not used.
    pub unread_columns: Vec<String>,
    /// Values no device of the geometry could produce, by line: a row
    /// whose counts cannot be is out of every figure; a position that cannot
    /// be is emptied (the row reads as occluded, or without its legacy
    /// position).
    pub set_aside: Vec<crate::data::impossible::ImpossibleValue>,
    /// The test session only: which home capture its rows count from, the
    /// training session's (its slips and drifts go on) or a new one, and
    /// what told it ([`crate::data::home`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub home: Option<crate::data::home::LaterHome>,
}

impl SessionInfo {
    /// The rows set aside whole (their counts cannot be), ascending.
    pub fn rows_set_aside(&self) -> Vec<usize> {
        self.set_aside
            .iter()
            .filter(|v| v.part == crate::data::impossible::SetAsidePart::Row)
            .map(|v| v.row)
            .collect()
    }
}

/// What a stage is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StageKind {
    /// No calibration: nominal geometry (or the legacy controller).
    Raw,
    /// The plain least-squares reference ([`crate::model::reference`]).
    Reference,
    /// The base kinematic identification.
    Identified,
    /// The identification with one more effect added by diagnosis.
    Effect,
    /// A learned correction (residual or black-box).
    Correction,
    /// The chosen model (always the last stage).
    Final,
}

/// One stage: eq. 7 error statistics on the training and test sessions.
#[derive(Clone, Debug, Serialize)]
pub struct Stage {
    pub name: String,
    pub kind: StageKind,
    pub train: ErrorStats,
    pub test: ErrorStats,
}

/// The chosen model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Choice {
    /// No correction helped: the identified model alone.
    Identified,
    Nn,
    Svr,
    /// The plain least-squares reference: the chosen model was not better
    /// on the selection split.
    Reference,
}

impl Choice {
    pub fn name(self) -> &'static str {
        match self {
            // Not "identified": that is the stage before diagnosis, and the
            // final model without a correction carries the loop's effects
            // and layer tables too (issue 13, point 5).
            Choice::Identified => "string model",
            Choice::Nn => "nn",
            Choice::Svr => "svr",
            Choice::Reference => "plain least squares",
        }
    }
}

/// The forward kinematics' rule ([`crate::model::rule`]).
#[derive(Clone, Debug, Serialize)]
pub struct KinematicsReport {
    /// The rule the final model runs.
    pub rule: spidar_core::kinematics::KinematicsRule,
    /// The strings weigh by their measured scales (else alike).
    pub weighted: bool,
    /// Why this rule.
    pub reason: String,
    /// The candidates and their held-out errors (empty when not chosen on
    /// folds).
    pub candidates: Vec<crate::model::rule::RuleScore>,
    /// The training rows' string disagreement (RMS) at its 99th
    /// percentile, mm (`null` when not measured).
    pub disagreement_q99_mm: Option<f64>,
}

impl KinematicsReport {
    /// From the choice on the folds, or why there was none (the device's
    /// rule then stays).
    pub fn of(choice: Result<crate::model::rule::RuleChoice, String>) -> KinematicsReport {
        match choice {
            Ok(c) => KinematicsReport {
                rule: c.candidate().rule,
                weighted: c.candidate().weighted,
                reason: c.reason.clone(),
                disagreement_q99_mm: Some(c.disagreement_q99_mm),
                candidates: c.scores,
            },
            Err(reason) => KinematicsReport {
                rule: Default::default(),
                weighted: true,
                reason,
                candidates: Vec::new(),
                disagreement_q99_mm: None,
            },
        }
    }
}

impl KinematicsReport {
    /// The same account of another rule.
    pub fn with_rule(
        self,
        rule: spidar_core::kinematics::KinematicsRule,
        weighted: bool,
    ) -> KinematicsReport {
        KinematicsReport {
            rule,
            weighted,
            ..self
        }
    }
}

/// Mean eq. 7 error of each candidate on the selection split, mm.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Candidates {
    pub identified: f64,
    pub nn: f64,
    pub svr: f64,
    /// The plain least-squares reference, on the same points.
    pub reference: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct Selection {
    /// Name of the final stage (the last of `stages`).
    pub stage: String,
    pub choice: Choice,
    /// Correction stored in `calibration.json`: "none", "nn" or "svr".
    pub correction: &'static str,
    /// Points the candidates were trained on / scored on (training session,
    /// after outlier removal).
    pub fit_points: usize,
    pub selection_points: usize,
    pub min_correction_gain: f64,
    pub validation_mean_mm: Candidates,
    pub validation_p95_mm: Candidates,
    pub validation_max_mm: Candidates,
    /// Sampling noise (two standard errors, `diagnose::tail_noise`) of the
    /// identified model's p95 and max on the selection split: a correction
    /// may not raise them by more.
    pub noise_p95_mm: f64,
    pub noise_max_mm: f64,
    /// Why the final model was chosen (and the corrections refused).
    pub reason: String,
    /// Of the final correction refitted on all kept training points.
    pub final_support_vectors: Option<usize>,
    pub final_hidden: Option<usize>,
}

/// Tukey's box plot on the absolute position errors of the training pairs.
#[derive(Clone, Debug, Serialize)]
pub struct Outliers {
    /// What the errors are of.
    pub on: &'static str,
    pub points: usize,
    pub removed: usize,
    pub removed_high: usize,
    pub removed_low: usize,
    pub whisker: f64,
    pub q1_mm: f64,
    pub q3_mm: f64,
    pub iqr_mm: f64,
    pub lower_fence_mm: f64,
    pub upper_fence_mm: f64,
}

impl Outliers {
    pub fn of(r: &OutlierReport, on: &'static str) -> Outliers {
        Outliers {
            on,
            points: r.errors.len(),
            removed: r.removed.len(),
            removed_high: r.removed_high(),
            removed_low: r.removed_low(),
            whisker: r.whisker,
            q1_mm: r.q1,
            q3_mm: r.q3,
            iqr_mm: r.iqr,
            lower_fence_mm: r.lower_fence,
            upper_fence_mm: r.upper_fence,
        }
    }
}

/// The hidden-size sweep (fig. 13) and the chosen network.
#[derive(Clone, Debug, Serialize)]
pub struct NnReport {
    pub best_hidden: usize,
    /// One point per hidden size: validation and training mean error, mm.
    pub sweep: Vec<SweepPoint>,
    pub epochs: usize,
    pub stop: crate::model::learn::nn::StopReason,
    pub restarts: usize,
    pub sweep_seconds: f64,
    pub final_seconds: f64,
}

impl NnReport {
    pub fn of(s: &SweepResult) -> NnReport {
        NnReport {
            best_hidden: s.best_hidden,
            sweep: s.curve.clone(),
            epochs: s.fit.epochs,
            stop: s.fit.stop,
            restarts: s.fit.restarts,
            sweep_seconds: s.sweep_seconds,
            final_seconds: s.final_seconds,
        }
    }
}

/// The SVR hyperparameter search and the chosen parameters.
#[derive(Clone, Debug, Serialize)]
pub struct SvrReport {
    /// C, epsilon (standardized output units), gamma (standardized inputs).
    pub best: SvrParams,
    /// Support vectors of the model (union over the three axes).
    pub support_vectors: usize,
    pub support_vectors_per_axis: [usize; 3],
    pub converged: [bool; 3],
    pub candidates: Vec<SvrCandidate>,
    pub search_seconds: f64,
    pub refit_seconds: f64,
}

impl SvrReport {
    pub fn of(s: &SvrSearchResult) -> SvrReport {
        SvrReport {
            best: s.best,
            support_vectors: s.fit.model.support.len(),
            support_vectors_per_axis: s.fit.axes.map(|a| a.support_vectors),
            converged: s.fit.axes.map(|a| a.converged),
            candidates: s.candidates.clone(),
            search_seconds: s.search_seconds,
            refit_seconds: s.refit_seconds,
        }
    }
}

/// The residual-mode corrections.
#[derive(Clone, Debug, Serialize)]
pub struct Corrections {
    pub mode: &'static str,
    pub input: &'static str,
    pub outliers: Outliers,
    /// The kept training points the corrections learn from.
    pub learning_points: LearningPoints,
    pub nn: NnReport,
    pub svr: SvrReport,
}

/// How many of the kept training points a correction learns from: all of
/// them up to the calibration's `max_learning_points`, one per cell of a
/// cubic grid beyond ([`crate::model::learn::thin`]).
#[derive(Clone, Debug, Serialize)]
pub struct LearningPoints {
    pub used: usize,
    pub kept: usize,
    /// Edge of the grid's cells, mm; `null` when every kept point is used.
    pub cell_mm: Option<f64>,
}

impl LearningPoints {
    pub fn of(thinning: &crate::model::learn::thin::Thinning, kept: usize) -> LearningPoints {
        LearningPoints {
            used: thinning.indices.len(),
            kept,
            cell_mm: thinning.cell_mm,
        }
    }
}

/// The paper's black-box procedure.
#[derive(Clone, Debug, Serialize)]
pub struct Blackbox {
    pub mode: &'static str,
    pub input: &'static str,
    /// `legacy`, `blackbox nn`, `blackbox svr`: over the rows with both a
    /// legacy and a tracker position.
    pub stages: Vec<Stage>,
    pub outliers: Outliers,
    pub learning_points: LearningPoints,
    pub nn: NnReport,
    pub svr: SvrReport,
}

/// The identified kinematic model.
#[derive(Clone, Debug, Serialize)]
pub struct IdentificationReport {
    /// Parameters of the final identification (with the added effects), each
    /// with its posterior standard deviation.
    pub parameters: Vec<ParameterEstimate>,
    pub warnings: Vec<String>,
    /// Robust scale of the string-space residuals, mm.
    pub residual_scale_mm: f64,
    pub rejected_fraction: f64,
    pub evaluations: usize,
    pub effect_terms: Vec<EffectTerm>,
    /// The base identification's residual scale, before any effect, mm.
    pub base_residual_scale_mm: f64,
    /// The layer-table spacing chosen for each string on the blocked folds
    /// (every spacing tried with its held-out string rms); whether the
    /// tables were kept is the `layers` finding's validation.
    pub layer_tables: Vec<crate::model::layers::StringLayers>,
    /// Where the tracked body's origin sits from the strings' meeting point
    /// (body frame, mm) when the loop found it through the tracker's
    /// orientation (`null` otherwise): the stages after it, the corrections
    /// and the final errors read the tracker at the meeting point. A tool
    /// that compares the device with the tracker must do the same.
    pub marker_body_mm: Option<[f64; 3]>,
    /// Training rows whose tracker the loop set aside as a glitch.
    pub tracker_outliers: crate::model::diagnose::TrackerOutliers,
    /// The training rows the loop decided on (the anchors' tolerance, the
    /// effects, the kinematics' rule): one in every `stride` of a session
    /// longer than the calibration's `max_loop_rows`; the parameters above
    /// are then identified on those rows (their sds say so).
    pub loop_rows: super::loop_rows::LoopRows,
}

impl IdentificationReport {
    pub fn of(
        base: &Identification,
        fin: &Identification,
        layer_tables: &[crate::model::layers::StringLayers],
        marker_body_mm: Option<[f64; 3]>,
        outliers: &crate::model::diagnose::TrackerOutliers,
        loop_rows: super::loop_rows::LoopRows,
    ) -> IdentificationReport {
        IdentificationReport {
            parameters: fin.parameters.clone(),
            warnings: fin.warnings.clone(),
            residual_scale_mm: fin.residual_scale_mm,
            rejected_fraction: fin.rejected_fraction,
            evaluations: fin.evaluations,
            effect_terms: fin.effects.clone(),
            base_residual_scale_mm: base.residual_scale_mm,
            layer_tables: layer_tables.to_vec(),
            marker_body_mm,
            tracker_outliers: outliers.clone(),
            loop_rows,
        }
    }
}

/// Wall-clock seconds of each step.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Timings {
    /// Finding the tracker's clock offset (dynamic sessions).
    pub alignment_s: f64,
    pub raw_s: f64,
    /// Identification and the diagnosis loop.
    pub identification_s: f64,
    /// The plain least-squares reference.
    pub reference_s: f64,
    /// The kinematics' rule on the held-out folds.
    pub rule_s: f64,
    /// Residual NN sweep and final training.
    pub nn_s: f64,
    /// Residual SVR search and refit.
    pub svr_s: f64,
    /// Choice of the final model and its refit on all the points it learns from.
    pub selection_s: f64,
    pub blackbox_s: Option<f64>,
    /// Everything [`super::calibrate`] did (black-box included when run).
    pub calibration_s: f64,
    pub figures_s: Option<f64>,
}

/// One figure file.
#[derive(Clone, Debug, Serialize)]
pub struct Figure {
    pub name: String,
    /// The paper's figure it corresponds to, e.g. "9".
    pub paper_figure: Option<&'static str>,
    pub path: String,
    pub title: String,
    /// What it shows: axis ranges, colour scale, marks, from the data drawn.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drawn: Option<super::figures::Drawn>,
}

#[derive(Clone, Debug, Default, Serialize)]
pub struct Files {
    pub out_dir: String,
    /// `spidar_core::model::Calibration` as JSON (frame, string laws,
    /// effects, correction): what later commands read.
    pub calibration: String,
    pub reports: Vec<String>,
    /// The report as one page for people (`report.html`, beside
    /// `report.json`).
    pub page: String,
}

fn stage_table(out: &mut String, stages: &[Stage]) {
    let width = stages
        .iter()
        .map(|s| s.name.chars().count())
        .max()
        .unwrap_or(5)
        .max(5);
    let (ntr, nte) = stages.first().map_or((0, 0), |s| (s.train.n, s.test.n));
    let _ = writeln!(
        out,
        "  {:width$}  {:>27}  {:>27}",
        "",
        format!("training session (n = {ntr})"),
        format!("test session (n = {nte})"),
    );
    let _ = writeln!(
        out,
        "  {:width$}  {:>8} {:>8} {:>9}  {:>8} {:>8} {:>9}",
        "stage", "mean", "sd", "max", "mean", "sd", "max"
    );
    for s in stages {
        let _ = writeln!(
            out,
            "  {:width$}  {:>8} {:>8} {:>9}  {:>8} {:>8} {:>9}",
            s.name,
            num(s.train.mean_mm),
            num(s.train.sd_mm),
            num(s.train.max_mm),
            num(s.test.mean_mm),
            num(s.test.sd_mm),
            num(s.test.max_mm),
        );
    }
}

/// Three decimals below 1000 mm, one above; "-" for a missing value.
fn num(v: f64) -> String {
    if !v.is_finite() {
        "-".into()
    } else if v.abs() < 1000.0 {
        format!("{v:.3}")
    } else {
        format!("{v:.1}")
    }
}

/// The JSON name of an enum value (e.g. `pulley_angle`).
fn label<T: Serialize>(value: &T) -> String {
    match serde_json::to_value(value) {
        Ok(serde_json::Value::String(s)) => s,
        _ => "?".into(),
    }
}

fn pct(v: f64) -> String {
    format!("{:.0} %", 100.0 * v)
}

impl Report {
    /// The readable summary: the paper's tables (raw, identified, effects,
    /// NN, SVR, final; mean, sd, max; training and test), the effects found,
    /// the choice, warnings, and where the files went.
    pub fn summary(&self) -> String {
        let mut o = String::new();
        self.write_inputs(&mut o);
        self.write_error_tables(&mut o);
        self.write_effects(&mut o);
        self.write_corrections(&mut o);
        self.write_warnings(&mut o);
        self.write_time(&mut o);
        self.write_files(&mut o);
        o
    }

    /// The sessions, the device, its forward-kinematics rejections and the
    /// clock alignment.
    fn write_inputs(&self, o: &mut String) {
        let i = &self.inputs;
        let _ = writeln!(
            o,
            "training session {} ({} rows, {} tracked); test session {} ({} rows, {} tracked)",
            i.train.path, i.train.rows, i.train.tracked, i.test.path, i.test.rows, i.test.tracked
        );
        if let Some(h) = &i.test.home {
            let _ = writeln!(o, "test session's home capture: {}", h.reason);
        }
        let _ = writeln!(
            o,
            "training slips on the device: {}",
            self.device_slips.reason
        );
        let d = &self.device;
        let _ = writeln!(
            o,
            "device: {} strings (channels {:?}), {}, {} spare string{}",
            d.strings,
            d.channels,
            if d.planar { "planar" } else { "3-D" },
            d.redundancy,
            if d.redundancy == 1 { "" } else { "s" }
        );
        for l in &d.limits {
            let _ = writeln!(o, "  limit: {l}");
        }
        if let Some(w) = d.describe_weights() {
            let _ = writeln!(o, "  {w}");
        }
        for (name, r) in [
            ("training", &d.rejections.train),
            ("test", &d.rejections.test),
        ] {
            if r.flagged() > 0 {
                let _ = writeln!(o, "  forward kinematics, {name} session: {}", r.describe());
            }
        }
        for (name, t) in [
            ("training", &self.timing.train),
            ("test", &self.timing.test),
        ] {
            if let super::align::SessionTiming::Aligned(a) = t {
                let drift = if a.drift_ppm != 0.0 {
                    format!(
                        " at {:.1} s, running {:+.1} ppm fast (sd {:.1} ppm)",
                        a.reference_t_s, a.drift_ppm, a.drift_sd_ppm
                    )
                } else {
                    String::new()
                };
                let again = a.first_offset_s.map_or(String::new(), |first| {
                    format!(
                        ", moved by the latency every string shares that the loop found (the \
                         alignment's quick model, without one string's latencies, found {:+.2} \
                         ms)",
                        first * 1e3
                    )
                });
                let _ = writeln!(
                    o,
                    "{name} session: tracker clock {:+.2} ms (sd {:.3} ms){drift} from the \
                     device's, found from the motion ({} pairs, speed correlation {:.3}){again}; \
                     rows re-paired",
                    a.offset_s * 1e3,
                    a.offset_sd_s * 1e3,
                    a.pairs,
                    a.correlation
                );
            }
        }
    }

    /// The error table of every stage, and the black-box one.
    fn write_error_tables(&self, o: &mut String) {
        let _ = writeln!(
            o,
            "\nAbsolute position error (eq. 7) against the tracker, room frame, mm:"
        );
        stage_table(o, &self.stages);

        if let Some(bb) = &self.blackbox {
            let _ = writeln!(
                o,
                "\nBlack-box, as the paper ({}; {} mode):",
                bb.input, bb.mode
            );
            stage_table(o, &bb.stages);
            let _ = writeln!(
                o,
                "  NN: {} hidden neurons; SVR: C = {}, epsilon = {}, gamma = {}, {} support vectors; \
                 outliers removed: {} of {} (fence {:.1} mm)",
                bb.nn.best_hidden,
                bb.svr.best.c,
                bb.svr.best.epsilon,
                bb.svr.best.gamma,
                bb.svr.support_vectors,
                bb.outliers.removed,
                bb.outliers.points,
                bb.outliers.upper_fence_mm
            );
        }
    }

    /// The effects diagnosis found (or the smallest it would have seen).
    fn write_effects(&self, o: &mut String) {
        let _ = writeln!(o, "\nEffects found by diagnosis:");
        if self.effects.is_empty() {
            let _ = writeln!(
                o,
                "  none significant: the identified model explains the residual (a constant \
                 error of one string above ~{:.2} mm would have been seen)",
                self.device.smallest_detectable_offset_mm
            );
        }
        for f in &self.effects {
            let strings = if f.strings.is_empty() {
                "all strings".to_string()
            } else {
                let s: Vec<String> = f.strings.iter().map(|s| s.to_string()).collect();
                format!("string {}", s.join(", "))
            };
            let _ = writeln!(
                o,
                "  {:9} {} ({strings}) against {}: amplitude {:.3} mm, explains {}{}",
                if f.added { "added" } else { "not added" },
                label(&f.family),
                label(&f.variable),
                f.amplitude_mm,
                pct(f.explained),
                if f.description.is_empty() {
                    String::new()
                } else {
                    format!(" - {}", f.description)
                }
            );
            if let Some(check) = &f.validation {
                let _ = writeln!(o, "            {}", check.reason);
            }
        }
    }

    /// The residual corrections and the choice of the final stage.
    fn write_corrections(&self, o: &mut String) {
        let s = &self.selection;
        let k = &self.kinematics;
        let _ = writeln!(
            o,
            "\nKinematics: leave a string out from {:.2} mm RMS, inconsistent from {:.2} mm, \
             strings {} - {}",
            k.rule.exclusion_threshold_mm,
            k.rule.fault_threshold_mm,
            if k.weighted {
                "weighed by their scales"
            } else {
                "weighing alike"
            },
            k.reason
        );
        for c in &k.candidates {
            let _ = writeln!(
                o,
                "  {:36} held out {} mm mean, {} p95",
                c.candidate.name,
                num(c.held_out.mean_mm),
                num(c.held_out.p95_mm)
            );
        }
        let r = &self.identification.loop_rows;
        if r.stride > 1 {
            let _ = writeln!(
                o,
                "Identification loop: decided on {} of the {} training rows (one in every {}, in time order); the model identified on those rows, every row in the figures",
                r.rows, r.of, r.stride
            );
        }
        let t = &self.anchor_tolerance;
        let _ = writeln!(
            o,
            "Anchors' tolerance: {} mm - {}",
            num(t.anchor_sd_mm[0]),
            t.reason
        );
        let Some(c) = &self.corrections else {
            let _ = writeln!(
                o,
                "\nFinal stage `{}` (no learned corrections): {} (selection split of {} points: \
                 identified {}, plain least squares {} mm)",
                s.stage,
                s.reason,
                s.selection_points,
                num(s.validation_mean_mm.identified),
                num(s.validation_mean_mm.reference)
            );
            return;
        };
        let _ = writeln!(
            o,
            "\nCorrections ({} mode, on top of the identified model):",
            c.mode
        );
        let _ = writeln!(
            o,
            "  outliers (Tukey box plot): {} of {} training points removed (fences {:.3} .. {:.3} mm)",
            c.outliers.removed, c.outliers.points, c.outliers.lower_fence_mm, c.outliers.upper_fence_mm
        );
        if let Some(cell) = c.learning_points.cell_mm {
            let _ = writeln!(
                o,
                "  learned from {} of the {} kept training points, one per {:.1} mm cell (a larger session is thinned evenly through its volume)",
                c.learning_points.used, c.learning_points.kept, cell
            );
        }
        let _ = writeln!(
            o,
            "  nn: sweep of {} hidden sizes, best {} neurons; svr: C = {}, epsilon = {}, gamma = {}, {} support vectors",
            c.nn.sweep.len(),
            c.nn.best_hidden,
            c.svr.best.c,
            c.svr.best.epsilon,
            c.svr.best.gamma,
            c.svr.support_vectors
        );
        let why = match s.choice {
            Choice::Identified if s.selection_points < super::MIN_SELECTION_POINTS => format!(
                "the identified model alone: corrections are not chosen on fewer than {} points, \
                 and there are",
                super::MIN_SELECTION_POINTS
            ),
            Choice::Identified => format!(
                "the identified model alone: no correction lowered its mean error by {} without \
                 raising its p95 or max beyond noise, on",
                pct(s.min_correction_gain)
            ),
            Choice::Nn => {
                "the NN correction, refitted on all the points it learns from; lowest error on"
                    .into()
            }
            Choice::Svr => {
                "the SVR correction, refitted on all the points it learns from; lowest error on"
                    .into()
            }
            Choice::Reference => {
                "the plain least-squares reference: the chosen model was not better on".into()
            }
        };
        let _ = writeln!(
            o,
            "  final stage `{}`: {why} a {}-point selection split of the training session \
             (identified {}, nn {}, svr {}, plain least squares {} mm)",
            s.stage,
            s.selection_points,
            num(s.validation_mean_mm.identified),
            num(s.validation_mean_mm.nn),
            num(s.validation_mean_mm.svr),
            num(s.validation_mean_mm.reference)
        );
        let _ = writeln!(o, "    why: {}", s.reason);
    }

    /// Warnings and notes.
    fn write_warnings(&self, o: &mut String) {
        if !self.warnings.is_empty() {
            let _ = writeln!(o, "\nWarnings:");
            for w in &self.warnings {
                let _ = writeln!(o, "  - {w}");
            }
        }
        if !self.notes.is_empty() {
            let _ = writeln!(o, "\nNotes:");
            for n in &self.notes {
                let _ = writeln!(o, "  - {n}");
            }
        }
    }

    /// Where the time went.
    fn write_time(&self, o: &mut String) {
        let t = &self.timings_s;
        let _ = writeln!(
            o,
            "\nTime: calibration {:.1} s (identification and diagnosis {:.1}, NN {:.1}, SVR {:.1}, choice and refit {:.1}{}){}",
            t.calibration_s,
            t.identification_s,
            t.nn_s,
            t.svr_s,
            t.selection_s,
            t.blackbox_s
                .map_or(String::new(), |b| format!(", black-box {b:.1}")),
            t.figures_s
                .map_or(String::new(), |f| format!("; figures {f:.1} s")),
        );
    }

    /// Where the files went.
    fn write_files(&self, o: &mut String) {
        if !self.files.calibration.is_empty() {
            let _ = writeln!(o, "\nWrote:");
            let _ = writeln!(o, "  {} (the calibration)", self.files.calibration);
            for r in &self.files.reports {
                let _ = writeln!(o, "  {r} (JSON report)");
            }
            if !self.files.page.is_empty() {
                let _ = writeln!(
                    o,
                    "  {} (the report as a page: open it in a browser)",
                    self.files.page
                );
            }
            if let Some(first) = self.figures.first() {
                let dir = std::path::Path::new(&first.path)
                    .parent()
                    .map(|p| p.display().to_string())
                    .unwrap_or_default();
                let _ = writeln!(o, "  {dir}/ ({} figures, PNG)", self.figures.len());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::predict::Prediction;
    use spidar_core::kinematics::FkStatus;

    fn row(status: FkStatus, excluded: Option<u8>) -> Prediction {
        Prediction {
            device: [0.0; 3],
            room: [0.0; 3],
            status,
            excluded,
            rms_residual_mm: 0.0,
        }
    }

    fn slip(string: u8, at_s: f64) -> EffectTerm {
        EffectTerm {
            string,
            effect: spidar_core::model::Effect::Slip { at_s, mm: 5.0 },
        }
    }

    /// A training session homed again at row 2 (the earlier capture's rows
    /// 0 and 40 s after it): a slip from 60 s since home is the last
    /// capture's and carried under it; one from 30 s also shifted the
    /// earlier capture's row at 40 s, and is not.
    #[test]
    fn only_the_slips_of_the_training_s_last_home_capture_are_carried() {
        use crate::data::dataset::{Sample, Session};
        use crate::data::home::TrainingHome;
        let row = |t_s: f64, since_home_s: f64, home: u64| {
            Sample::at_home(t_s, Some(since_home_s), Some(home))
        };
        let training = TrainingHome::of(&Session {
            samples: vec![
                row(0.0, 0.0, 7),
                row(40.0, 40.0, 7),
                row(50.0, 1.0, 8),
                row(120.0, 71.0, 8),
            ],
            ..Session::default()
        });
        let d = DeviceSlips::of(&training, &[slip(2, 60.0), slip(5, 30.0)]);
        assert_eq!(d.home_id, Some(8), "{}", d.reason);
        assert_eq!(
            (d.slips.clone(), d.not_carried.clone()),
            (vec![slip(2, 60.0)], vec![slip(5, 30.0)])
        );
        for said in [
            "applies 1 of the training session's slips (string 2 +5.00 mm from 60.0 s)",
            "home capture 8, the last of the training session's 2 (from line 4 on)",
            "not carried: string 5 +5.00 mm from 30.0 s is fitted across captures",
        ] {
            assert!(d.reason.contains(said), "{said}: {}", d.reason);
        }
        let none = DeviceSlips::of(&training, &[slip(5, 30.0)]);
        assert_eq!((none.home_id, none.not_carried.len()), (None, 1));
        assert!(
            none.reason.contains("spans 2 home captures")
                && none.reason.contains("are not carried"),
            "{}",
            none.reason
        );
    }

    #[test]
    fn rejections_are_counted_per_string_and_kind() {
        let rows = [
            row(FkStatus::Ok, None),
            row(FkStatus::FaultyStringExcluded, Some(2)),
            row(FkStatus::FaultyStringExcluded, Some(2)),
            row(FkStatus::FaultyStringExcluded, Some(7)),
            row(FkStatus::Inconsistent, None),
            row(FkStatus::Inconsistent, Some(1)),
            row(FkStatus::NotConverged, None),
            row(FkStatus::InvalidInput, None),
            row(FkStatus::Ok, None),
        ];
        let r = Rejections::of(&rows);
        assert_eq!(r.rows, 9);
        assert_eq!(r.excluded_by_channel, [0, 0, 2, 0, 0, 0, 0, 1]);
        assert_eq!(r.inconsistent_excluded_by_channel, [0, 1, 0, 0, 0, 0, 0, 0]);
        assert_eq!((r.inconsistent, r.not_converged, r.invalid), (2, 1, 1));
        assert_eq!(r.flagged(), 7);
        assert_eq!(
            r.describe(),
            "7 of 9 rows: string 2 excluded 2 times, string 7 excluded 1 time, \
             2 inconsistent (strings disagreeing, no exclusion trusted; placed 1 without \
             string 1, 1 by all strings), 1 not converged, 1 invalid lengths"
        );
        assert_eq!(
            Rejections::of(&rows[4..5]).describe(),
            "1 of 1 rows: 1 inconsistent (strings disagreeing, no exclusion trusted)"
        );
        let clean = Rejections::of(&rows[..1]);
        assert_eq!(clean.describe(), "all 1 rows solved with every string");
    }
}
