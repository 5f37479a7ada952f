//! The calibration report: the JSON document `spidar calibrate --json` writes
//! (schema in `docs/json-schema.md`) and the readable summary printed on
//! stdout.

use serde::Serialize;

use crate::data::stats::ErrorStats;
use crate::model::diagnose::Finding;
use crate::model::identify::{Identification, ParameterEstimate};
use crate::model::learn::outliers::OutlierReport;
use crate::model::learn::search::{SvrCandidate, SvrSearchResult, SweepPoint, SweepResult};
use crate::model::learn::svr::SvrParams;
use spidar_core::model::EffectTerm;

mod device_slips;
mod strings;
mod summary;

pub use device_slips::DeviceSlips;
pub use strings::{Rejections, SessionRejections, StringWeight, StringsReport};

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
    pub anchor_tolerance: AnchorTolerance,
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
    /// From the choice (on the folds, or unjudged: its candidates empty).
    pub fn of(c: crate::model::rule::RuleChoice) -> KinematicsReport {
        KinematicsReport {
            rule: c.candidate().rule,
            weighted: c.candidate().weighted,
            reason: c.reason.clone(),
            disagreement_q99_mm: Some(c.disagreement_q99_mm),
            candidates: c.scores,
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
    /// The device's control-loop tick, estimated (`spidar_core::tick_cost`);
    /// `null` when the model does not compile (`spidar compile` says why).
    pub device_tick: Option<DeviceTick>,
}

/// What the device's control loop takes a tick with the calibration, and
/// what it left the learned correction (decision record 0068).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct DeviceTick {
    /// The identified model without a correction, with the most training
    /// slips a blob takes, and the room it left: the correction was learned
    /// within `support_vectors` and `neurons`.
    #[serde(flatten)]
    pub room: crate::model::compile::TickRoom,
    /// The final calibration with its correction and slips, estimated
    /// instructions; `null` when it does not compile.
    pub final_instructions: Option<u32>,
}

impl DeviceTick {
    pub fn of(
        room: crate::model::compile::TickRoom,
        calibration: &spidar_core::model::Calibration,
    ) -> DeviceTick {
        DeviceTick {
            room,
            final_instructions: crate::model::compile::tick_instructions(calibration),
        }
    }
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
    /// The fit part's points the SVR's search learned from: at most the
    /// support vectors the device evaluates within its tick
    /// (`spidar_core::correction::MAX_SUPPORT_VECTORS`), thinned evenly like
    /// the learning points; the final refit thins the fit part and the
    /// selection split together the same way.
    pub svr_learning_points: LearningPoints,
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
    /// Why the diagnosis loop did not run (`null` when it ran): the
    /// training session is too small for it, and the reason says how many
    /// more tracked rows enable it. No effect was then tried.
    pub loop_not_run: Option<String>,
    /// Each string's mechanical advantage, in the device's channel order
    /// (`device.channels`): a `string{k}.r_home` is the effective radius,
    /// the spool's radius over it.
    pub mechanical_advantage: Vec<f64>,
    /// The plain least-squares reference's parameters, each with its sd
    /// from the data alone (no prior holds it): the final model's when the
    /// selection holds to the reference (`selection.choice` `reference`),
    /// which the device then runs.
    pub reference_parameters: Vec<ParameterEstimate>,
}

impl IdentificationReport {
    /// The report of the loop's model (its final identification, its base,
    /// layer tables, marker offset and tracker outliers), on `loop_rows`,
    /// and of the plain least-squares `reference`.
    pub fn of(
        loop_result: &crate::model::diagnose::LoopResult,
        loop_rows: super::loop_rows::LoopRows,
        loop_not_run: Option<String>,
        reference: &Identification,
    ) -> IdentificationReport {
        let fin = &loop_result.identification;
        IdentificationReport {
            parameters: fin.parameters.clone(),
            warnings: fin.warnings.clone(),
            residual_scale_mm: fin.residual_scale_mm,
            rejected_fraction: fin.rejected_fraction,
            evaluations: fin.evaluations,
            effect_terms: fin.effects.clone(),
            base_residual_scale_mm: loop_result.base.residual_scale_mm,
            layer_tables: loop_result.layers.clone(),
            marker_body_mm: loop_result.structure.marker_body_mm,
            tracker_outliers: loop_result.tracker_outliers.clone(),
            loop_rows,
            loop_not_run,
            mechanical_advantage: fin
                .frame
                .layout
                .indices()
                .map(|c| fin.winding.mechanical_advantage[c])
                .collect(),
            reference_parameters: reference.parameters.clone(),
        }
    }

    /// String `channel`'s mechanical advantage when it is not 1 (its
    /// `r_home` is then the spool's radius over it).
    pub fn advantage_of(&self, channels: &[usize], channel: usize) -> Option<f64> {
        let k = channels.iter().position(|&c| c == channel)?;
        self.mechanical_advantage
            .get(k)
            .copied()
            .filter(|ma| *ma != 1.0)
    }
}

/// The anchors' tolerance as the report gives it: the choice
/// ([`crate::model::tolerance::ToleranceChoice`]) with one sd per anchor of
/// the device, in channel order (the choice holds one per channel the
/// firmware has, the unused ones padded).
#[derive(Clone, Debug, Serialize)]
pub struct AnchorTolerance {
    /// The tolerance the calibration used, mm, one per anchor.
    pub anchor_sd_mm: Vec<f64>,
    pub scores: Vec<crate::model::tolerance::ToleranceScore>,
    pub folds: String,
    pub reason: String,
    pub robust: bool,
    pub unweighted: Option<ErrorStats>,
}

impl AnchorTolerance {
    /// `choice` for the anchors of `layout`.
    pub fn of(
        choice: crate::model::tolerance::ToleranceChoice,
        layout: spidar_core::model::StringLayout,
    ) -> AnchorTolerance {
        AnchorTolerance {
            anchor_sd_mm: layout.indices().map(|c| choice.anchor_sd_mm[c]).collect(),
            scores: choice.scores,
            folds: choice.folds,
            reason: choice.reason,
            robust: choice.robust,
            unweighted: choice.unweighted,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The report gives one anchor sd per anchor of the device: 4 for a
    /// 4-string device, not the firmware's 8 channels padded (a survey's
    /// `anchor_sd_mm = [30, 30, 30, 100]` came back with 8 entries).
    #[test]
    fn the_anchors_tolerance_has_one_sd_per_anchor_of_the_device() {
        let choice = crate::model::tolerance::ToleranceChoice {
            anchor_sd_mm: [30.0, 30.0, 30.0, 100.0, 100.0, 100.0, 100.0, 100.0],
            scores: Vec::new(),
            folds: String::new(),
            reason: "the geometry's `anchor_sd_mm`".into(),
            robust: true,
            unweighted: None,
        };
        let layout = spidar_core::model::StringLayout::first(4, false);
        let t = AnchorTolerance::of(choice, layout);
        assert_eq!(t.anchor_sd_mm, vec![30.0, 30.0, 30.0, 100.0]);
        let json = serde_json::to_value(&t).unwrap();
        assert_eq!(
            json["anchor_sd_mm"],
            serde_json::json!([30.0, 30.0, 30.0, 100.0])
        );
    }
}
