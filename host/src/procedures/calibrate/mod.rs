//! `spidar calibrate`: the whole calibration of a device from a training
//! session (the paper's lattice) and a separate test session, with the
//! paper's error statistics (eq. 7, tables 1-6) for every stage, figures
//! (figs. 9-17) and a JSON report (`docs/json-schema.md`).
//!
//! ## Pipeline (the report's `stages`, in this order)
//!
//! 1. `raw`: the nominal geometry and nominal pulley radius of the geometry
//!    file through the device pipeline in f64 ([`crate::model::predict`]).
//! 2. `identified`: the base kinematic identification
//!    ([`crate::model::diagnose::LoopResult::base`]).
//! 3. One stage per effect the diagnosis loop added
//!    ([`crate::model::diagnose::close_loop`]), named after it.
//! 4. `nn` and `svr`: model-less corrections trained in residual mode on top
//!    of the final identified model's room positions (what the kinematic model
//!    leaves), after Tukey's box plot removed the outliers of the training
//!    errors, as the paper (section 5.1). Both are trained on a fit part of
//!    the training session (80 %); the rest (the *selection split*) scores
//!    them, never the test session.
//! 5. `final (<choice>)`: the chosen model, always last. The choice is the
//!    lowest mean error on the selection split among the identified model
//!    alone, `nn` and `svr`; a correction must beat the identified model by
//!    [`CalibrateConfig::min_correction_gain`] to be chosen (a correction that
//!    does not help only adds noise and device time). The chosen correction is
//!    then refitted on all kept training points with the hyperparameters the
//!    search found (hidden size; C, epsilon, gamma).
//!
//! Black-box stages (`legacy`, `blackbox nn`, `blackbox svr`, the paper's own
//! procedure: the legacy controller's `dev_*` position plus the eq. 6
//! translation in, the tracker out, absolute mode) are a separate list, run
//! with [`CalibrateConfig::blackbox`] when both sessions have `dev_*` columns.
//!
//! Every error statistic comes from [`crate::data::stats`] (eq. 7 against the
//! tracker, room frame, over the rows the tracker saw).
//!
//! ## Where each part lives
//!
//! This file holds the pipeline ([`calibrate`], its settings and its error).
//! Beside it: `checks.rs` (what a calibration refuses and warns about),
//! `evaluate.rs` (a stage's errors on both sessions), `identified.rs`
//! (stages 0-3), `corrections.rs` (stages 4-5), `blackbox.rs` (the paper's
//! procedure), `outputs.rs` (the files written), `request.rs` (files in,
//! files out: [`run_calibrate`]); [`align`] (the tracker's clock), [`report`]
//! (the JSON report), [`trust`] (where the held-out figure is not what it
//! seems), `figures.rs` and `plots.rs` (the figures).

pub mod align;
mod blackbox;
mod checks;
mod corrections;
mod evaluate;
mod figures;
mod identified;
pub mod loop_rows;
mod outputs;
mod plots;
pub mod report;
mod request;
pub mod trust;

use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::progress::Step;
use spidar_core::correction::CorrectionModel;
use spidar_core::model::Calibration;

use crate::data::dataset::{DatasetError, Geometry, Session};
use crate::data::impossible::SetAside;
use crate::data::observe::Observation;
use crate::data::stats::{ErrorStats, StatsError};
use crate::model::compile::TickRoom;
use crate::model::diagnose::{LoopConfig, LoopResult};
use crate::model::identify::IdentifyError;
use crate::model::learn::search::{SvrSearchConfig, SweepConfig};
use crate::model::learn::{LearnError, OutputMode};
use crate::model::predict::predict;

use checks::{checked_sessions, declared_tolerance_warning, reference_warning, trust_warnings};
use corrections::{
    hold_to_reference, identification_only, learner_warnings, loose_reference_warning,
    residual_report, selection_report, train_corrections, unchosen_corrections_warning,
    CorrectionLimits, Learned, ResidualData,
};
use evaluate::{correction_errors, point_error_list, tracked_pairs, PerSession};
use identified::{FinalIdentified, IdentifiedModel, ReferenceModel};

pub use evaluate::{PointErrors, StagePoints};
pub use figures::robust_colour_max;
pub use outputs::{write_outputs, PairSet, Written};
pub use report::{Report, SCHEMA};
pub use request::{run_calibrate, CalibrateRequest};

/// Any failure of a calibration; each names the file, stage or step.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    #[error("{0}")]
    OutputOverInput(#[from] crate::data::output::OutputOverInput),
    #[error("{0}")]
    Dataset(#[from] DatasetError),
    #[error("{}: {problem}", file.display())]
    Session { file: PathBuf, problem: String },
    #[error("identification: {0}")]
    Identify(#[from] IdentifyError),
    #[error("{step}: {source}")]
    Learn {
        step: &'static str,
        source: LearnError,
    },
    #[error("{0}")]
    Stats(#[from] StatsError),
    #[error("{0}")]
    Figure(#[from] figures::FigureError),
    #[error("{}: {action}: {source}", file.display())]
    Io {
        file: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
    #[error("{}: cannot encode JSON: {source}", file.display())]
    Json {
        file: PathBuf,
        source: serde_json::Error,
    },
    #[error("{0}")]
    Align(#[from] align::AlignError),
    #[error("{0}")]
    Page(#[from] crate::procedures::report_page::PageError),
}

fn learn(step: &'static str) -> impl FnOnce(LearnError) -> CalibrateError {
    move |source| CalibrateError::Learn { step, source }
}

/// Settings of a calibration.
#[derive(Clone, Debug)]
pub struct CalibrateConfig {
    /// Seeds the selection split, the NN initializations and the SVR folds.
    pub seed: u64,
    pub loop_config: LoopConfig,
    /// Residual-mode NN: hidden-size sweep and final training.
    pub nn: SweepConfig,
    /// Residual-mode SVR: hyperparameter grid.
    pub svr: SvrSearchConfig,
    /// Most training points the corrections learn from (fit part and
    /// selection split together): a larger session is thinned evenly
    /// through its volume
    /// ([`thin_evenly`](crate::model::learn::thin::thin_evenly)); every row
    /// still counts in the identification and in the error figures. 2500
    /// keeps a 13^3 lattice (2197 points) whole, so the SVR's kernel and
    /// the NN's steps stay as measured on it, and the learners' time stays
    /// bounded however long the session.
    pub max_learning_points: usize,
    /// Most points the SVR learns from, of the fit part in the search and of
    /// the fit part and the selection split together in the final refit,
    /// thinned evenly like the learning points: its support vectors are
    /// among them, and the device evaluates at most
    /// [`MAX_SUPPORT_VECTORS`](spidar_core::correction::MAX_SUPPORT_VECTORS)
    /// within its control loop's tick (the default).
    pub max_support_vectors: usize,
    /// Most training rows the identification loop decides on (the anchors'
    /// tolerance, which effects to add, the kinematics' rule): a longer
    /// session is read one row in every k, in time order
    /// ([`LoopRows`](loop_rows::LoopRows)), and the model is the loop's,
    /// identified on those rows. Every error figure counts every row but
    /// the training figures of the effect stages before the last (the
    /// loop's, over its rows: their `n` says so). 0: every row. The
    /// default, 4000, leaves a 13^3 lattice (2,197 rows) and sessions up to
    /// 4,000 rows whole and bounds what the loop costs on a longer one (a
    /// 30,000-row stream: 12-14 s on 2 cores, 104 s on every row); on the
    /// 30,000-row sessions and the 6,000-row wall
    /// robot it was measured held out within 3 % of every row (record
    /// 0051, docs/benchmarks.md "Speed of a calibration").
    pub max_loop_rows: usize,
    /// Share of the kept training points held out to choose the final model.
    pub selection_fraction: f64,
    /// Relative gain over the identified model a correction needs, on the
    /// selection split, to be chosen.
    pub min_correction_gain: f64,
    /// Run the black-box comparison (when both sessions have `dev_*`).
    pub blackbox: bool,
    pub blackbox_nn: SweepConfig,
    pub blackbox_svr: SvrSearchConfig,
    /// Hide progress bars.
    pub quiet: bool,
    /// Where the alignment of a stream's clocks starts its search (s,
    /// tracker minus device; it reaches [`align::MAX_OFFSET_S`] around
    /// it): 0, unless the rig's tracker clock is known to be further off.
    pub clock_offset_s: f64,
    /// The sessions' tracker and device rows were paired by one clock when
    /// logged: a stream is read as written, no offset searched
    /// ([`align::SessionTiming::Paired`]).
    pub clocks_paired: bool,
}

impl CalibrateConfig {
    /// The paper's procedure: NN sweep over 3..=24 hidden neurons with LM and
    /// restarts; RBF epsilon-SVR with a C x epsilon x gamma search. The
    /// residual SVR grid is centred where residual targets need it (epsilon
    /// about 0.05 in standardized units: the residual is mostly tracker noise,
    /// and a narrower tube only buys support vectors). No wall-clock limit:
    /// a calibration's result never depends on how fast or how busy the
    /// machine is. The learners' work is bounded by the data instead: at
    /// most [`CalibrateConfig::max_learning_points`] points, LM epochs and
    /// SMO iterations capped.
    pub fn full() -> Self {
        let nn = SweepConfig {
            sizes: (3..=24).collect(),
            mode: OutputMode::Residual,
            ..SweepConfig::default()
        };
        let svr = SvrSearchConfig {
            c: vec![1.0, 10.0],
            epsilon: vec![0.1, 0.05],
            gamma: vec![0.3, 1.0],
            mode: OutputMode::Residual,
            ..SvrSearchConfig::default()
        };
        CalibrateConfig {
            seed: 1,
            loop_config: LoopConfig::default(),
            nn,
            svr,
            max_learning_points: 2500,
            max_support_vectors: spidar_core::correction::MAX_SUPPORT_VECTORS as usize,
            max_loop_rows: 4000,
            selection_fraction: 0.2,
            min_correction_gain: 0.01,
            blackbox: false,
            clock_offset_s: 0.0,
            clocks_paired: false,
            // The paper's grid (C 30..100, epsilon 0.01), as
            // `scripts/reference/reference.py --grid paper` searches it.
            blackbox_nn: SweepConfig {
                sizes: (3..=24).collect(),
                mode: OutputMode::Absolute,
                blackbox: true,
                ..SweepConfig::default()
            },
            blackbox_svr: SvrSearchConfig {
                mode: OutputMode::Absolute,
                blackbox: true,
                ..SvrSearchConfig::default()
            },
            quiet: false,
        }
    }

    /// A reduced procedure for tests and smoke runs: every fourth hidden
    /// size, shorter LM runs, a two-point SVR grid.
    pub fn quick() -> Self {
        let mut c = CalibrateConfig::full();
        c.nn.sizes = vec![3, 6, 10, 16];
        c.nn.sweep_lm.max_epochs = 25;
        c.nn.final_lm.max_epochs = 60;
        c.svr.c = vec![1.0];
        c.svr.gamma = vec![0.3];
        c.blackbox_nn.sizes = vec![8, 16];
        c.blackbox_nn.final_lm.max_epochs = 100;
        c.blackbox_svr.c = vec![30.0];
        c.blackbox_svr.epsilon = vec![0.01];
        c.blackbox_svr.gamma = vec![0.3];
        c
    }

    fn with_seed_and_quiet(&self) -> CalibrateConfig {
        let mut c = self.clone();
        for s in [&mut c.nn, &mut c.blackbox_nn] {
            s.seed = self.seed;
            s.quiet = self.quiet;
        }
        for s in [&mut c.svr, &mut c.blackbox_svr] {
            s.seed = self.seed;
            s.quiet = self.quiet;
        }
        c
    }
}

impl Default for CalibrateConfig {
    fn default() -> Self {
        CalibrateConfig::full()
    }
}

/// Fewest points of the selection split on which a learned correction may
/// be chosen over the identified model: below it, a 1% gain is noise.
pub const MIN_SELECTION_POINTS: usize = 30;

/// A session with the name it is reported under.
#[derive(Clone, Copy, Debug)]
pub struct NamedSession<'a> {
    pub path: &'a Path,
    pub session: &'a Session,
}

/// What [`calibrate`] computed: the report (without file paths), the
/// calibration, and the per-point errors the figures need.
#[derive(Clone, Debug)]
pub struct Calibrated {
    pub report: Report,
    pub calibration: Calibration,
    /// Per-point errors of the stages with figures (raw, identified, nn, svr,
    /// final; black-box legacy, nn, svr).
    pub points: Vec<StagePoints>,
    pub loop_result: LoopResult,
    /// The learners' data: residual pairs, and black-box pairs when both
    /// sessions have `dev_*` columns (whether or not the black-box ran).
    pub pairs: Pairs,
    /// The sessions' rows as every stage after the raw one read them (rows
    /// set aside, the tracker's clock aligned, its glitches occluded, at the
    /// strings' meeting point): what the report page's evidence figures and
    /// its fixed-point error read.
    pub train_rows: Vec<Observation>,
    pub test_rows: Vec<Observation>,
}

#[derive(Clone, Debug, Default)]
pub struct Pairs {
    /// Final identified model's room position -> tracker.
    pub residual: PairSet,
    /// Legacy `dev_*` + eq. 6 translation -> tracker.
    pub blackbox: Option<PairSet>,
}

impl Calibrated {
    /// Per-point errors of a stage, by name.
    pub fn points_of(&self, name: &str) -> Option<&StagePoints> {
        self.points.iter().find(|p| p.name == name)
    }
}

/// A spinner for a step that may take over a second, shown by the installed
/// [`crate::progress`] reporter unless `quiet`.
pub(crate) fn spinner(message: &'static str, quiet: bool) -> Step {
    Step::spinner(message, quiet)
}

/// What the stages of one calibration share: its inputs and settings, and
/// the times and warnings they add to.
struct Run<'a> {
    geometry: &'a Geometry,
    geometry_path: &'a Path,
    train_info: report::SessionInfo,
    test_info: report::SessionInfo,
    cfg: CalibrateConfig,
    timings: report::Timings,
    warnings: Vec<String>,
}

/// What the stages found, for the report.
struct Findings<'a> {
    timing: report::Timing,
    stages: Vec<report::Stage>,
    loop_result: &'a LoopResult,
    rejections: report::SessionRejections,
    selection: report::Selection,
    corrections: Option<report::Corrections>,
    kinematics: report::KinematicsReport,
    anchor_tolerance: crate::model::tolerance::ToleranceChoice,
    loop_rows: loop_rows::LoopRows,
    blackbox: Option<report::Blackbox>,
    device_slips: report::DeviceSlips,
    /// Why the diagnosis loop did not run (the session too small for it).
    loop_not_run: Option<String>,
    /// The plain least-squares reference.
    reference: &'a crate::model::identify::Identification,
}

/// What stages 4-5 left: the learners' data, the learned corrections (none
/// for a session too small for them), the final model's correction, and the
/// report's account of them.
struct Corrected {
    data: ResidualData,
    learned: Option<Learned>,
    final_corr: CorrectionModel,
    /// The plain least-squares reference is the final model.
    fall_back: bool,
    selection: report::Selection,
    corrections: Option<report::Corrections>,
    /// What the device's tick left a correction beside the identified model.
    room: Option<TickRoom>,
}

impl Run<'_> {
    /// Stages 4-5: the residual corrections on top of the final identified
    /// model, the choice on the selection split held to the reference, and
    /// their stages in `model.list`.
    fn correct(&mut self, model: &mut IdentifiedModel) -> Result<Corrected, CalibrateError> {
        let obs = PerSession {
            train: &model.tr[..],
            test: &model.te[..],
        };
        let positions = PerSession {
            train: &model.final_identified.positions.train[..],
            test: &model.final_identified.positions.test[..],
        };

        // 4. Residual corrections on top of the final identified model (a
        // session too small for the loop is too small for them).
        // No larger than the device's tick leaves them beside the model.
        let data = ResidualData::of(obs, positions, &self.cfg)?;
        let room = TickRoom::beside(
            &model
                .final_identified
                .new_session
                .calibration(CorrectionModel::None),
        );
        let limits = CorrectionLimits::of(room, &self.cfg);
        let no_room = limits.no_room(&self.cfg);
        if let Some(r) = room.filter(|r| r.model_instructions > r.budget) {
            self.warnings.push(format!(
                "the device's control loop would take an estimated {} instructions a tick with \
                 this model's effect terms alone, over the {} it has: `spidar compile` will \
                 refuse it (fewer terms: a simpler model)",
                r.model_instructions, r.budget
            ));
        }
        let learned = if model.regime.full && no_room.is_none() {
            Some(train_corrections(
                &data,
                &self.cfg,
                limits,
                &mut self.timings,
            )?)
        } else {
            None
        };

        // 5. The choice, on the selection split, held to the reference there.
        let (mut judgement, mut final_corr) = match &learned {
            Some(learned) => self.choose_final_model(&data, learned)?,
            None => (
                identification_only(
                    &data,
                    model.regime.reason.clone().or(no_room).unwrap_or_default(),
                ),
                CorrectionModel::None,
            ),
        };
        let fall_back = hold_to_reference(
            &mut judgement,
            &mut final_corr,
            &data,
            &model.reference.train_errors_by_row,
            &model.reference.id,
        );
        if fall_back {
            self.warnings.extend(loose_reference_warning(
                &model.reference.id,
                &model.loop_result.identification,
            ));
        }
        if learned.is_some() {
            self.warnings.extend(unchosen_corrections_warning(
                &judgement,
                data.selection_points(),
            ));
        }
        let final_name = format!("final ({})", judgement.choice.name());
        self.final_stages(model, learned.as_ref(), &final_name, &final_corr, fall_back)?;
        let selection = selection_report(final_name, judgement, &final_corr, &data, &self.cfg);
        let corrections = learned.as_ref().map(|l| residual_report(&data, l));
        Ok(Corrected {
            data,
            learned,
            final_corr,
            fall_back,
            selection,
            corrections,
            room,
        })
    }

    /// The stages of the learned corrections and of the final model (the
    /// reference's errors when it is the final model) into `model.list`, and
    /// the warnings on the final model's held-out figure.
    fn final_stages(
        &mut self,
        model: &mut IdentifiedModel,
        learned: Option<&Learned>,
        final_name: &str,
        final_corr: &CorrectionModel,
        fall_back: bool,
    ) -> Result<(), CalibrateError> {
        let fin = &model.loop_result.identification;
        let (tr, te) = (&model.tr, &model.te);
        let obs = PerSession {
            train: &tr[..],
            test: &te[..],
        };
        let positions = PerSession {
            train: &model.final_identified.positions.train[..],
            test: &model.final_identified.positions.test[..],
        };
        let (list, reference) = (&mut model.list, &model.reference);
        if let Some(learned) = learned {
            for (name, corr) in [("nn", &learned.nn), ("svr", &learned.svr)] {
                let errors = correction_errors(name, corr, obs, positions, &fin.frame)?;
                list.push(name.into(), report::StageKind::Correction, errors);
            }
        }
        let final_errors = if fall_back {
            reference.errors(obs, &reference.id.frame)?
        } else {
            correction_errors(final_name, final_corr, obs, positions, &fin.frame)?
        };
        list.push(final_name.into(), report::StageKind::Final, final_errors);
        let plain_rule = crate::model::rule::with_rule(
            &identified::under_the_training_home(fin, &model.training_home),
            &crate::model::rule::all_strings_alike(reference.id.kinematics.fault_threshold_mm),
        );
        let plain_rule_te: Vec<[f64; 3]> = crate::model::validate::predict_later(&plain_rule, te)
            .iter()
            .map(|p| p.room)
            .collect();
        let (x, t) = tracked_pairs(te, &plain_rule_te);
        let plain_rule_test = ErrorStats::of(&point_error_list(|p| p, &x, &t));
        self.warnings
            .extend(reference_warning(&list.stages, plain_rule_test.mean_mm));
        self.warnings.extend(declared_tolerance_warning(
            self.geometry.anchor_sd_mm.as_ref(),
            &self.geometry.nominal_frame(),
            &reference.id.frame,
            &list.stages,
        ));
        let final_points = list.points.iter().find(|p| p.name == final_name);
        let reference_points = list
            .points
            .iter()
            .find(|p| p.name == crate::model::reference::STAGE_NAME);
        self.warnings.extend(trust_warnings(
            &fin.frame,
            tr,
            final_points,
            reference_points,
        ));
        Ok(())
    }

    /// The report of the run, from what its stages found.
    fn report(self, f: Findings<'_>) -> Report {
        let fin = &f.loop_result.identification;
        let notes = align::rate_not_fitted_note(&f.timing.train)
            .into_iter()
            .collect();
        Report {
            schema: SCHEMA,
            tool: report::Tool::current(),
            timing: f.timing,
            device: report::StringsReport::of(
                self.geometry.layout,
                self.train_info.tracked,
                fin.residual_scale_mm,
                &fin.length_scale_mm,
                self.cfg.loop_config.chi2_threshold,
                f.rejections,
            ),
            inputs: report::Inputs {
                geometry: self.geometry_path.display().to_string(),
                train: self.train_info,
                test: self.test_info,
            },
            stages: f.stages,
            effects: f.loop_result.findings.clone(),
            identification: report::IdentificationReport::of(
                f.loop_result,
                f.loop_rows,
                f.loop_not_run,
                f.reference,
            ),
            selection: f.selection,
            corrections: f.corrections,
            kinematics: f.kinematics,
            anchor_tolerance: report::AnchorTolerance::of(f.anchor_tolerance, self.geometry.layout),
            device_slips: f.device_slips,
            blackbox: f.blackbox,
            warnings: self.warnings,
            notes,
            timings_s: self.timings,
            figures: Vec::new(),
            files: report::Files::default(),
        }
    }
}

/// The final identified model's slips, which go to the device under the
/// training's home capture: none when the plain least-squares reference is
/// the final model (`fall_back`).
fn device_slips(
    training_home: &crate::data::home::TrainingHome,
    loop_result: &LoopResult,
    fall_back: bool,
) -> report::DeviceSlips {
    let effects: &[spidar_core::model::EffectTerm] = if fall_back {
        &[]
    } else {
        &loop_result.identification.effects
    };
    report::DeviceSlips::of(training_home, effects)
}

/// Calibrate a device: identification and the diagnosis loop, residual NN
/// and SVR, the choice of the final model, and the black-box comparison when
/// asked for. No file is written (see [`write_outputs`]).
pub fn calibrate(
    geometry: &Geometry,
    geometry_path: &Path,
    train: NamedSession<'_>,
    test: NamedSession<'_>,
    config: &CalibrateConfig,
) -> Result<Calibrated, CalibrateError> {
    let cfg = config.with_seed_and_quiet();
    let t_start = Instant::now();
    // Rows no device of the geometry could produce are set aside before
    // anything reads the sessions: their positions emptied here, their
    // whole rows skipped where the sessions become observations.
    let set_aside = [train, test].map(|s| SetAside::find(s.session, geometry));
    let as_read = [train.session, test.session];
    let kept = [(train, &set_aside[0]), (test, &set_aside[1])].map(|(s, found)| {
        if found.is_empty() {
            Cow::Borrowed(s.session)
        } else {
            Cow::Owned(found.without_positions(s.session))
        }
    });
    let train = NamedSession {
        path: train.path,
        session: &kept[0],
    };
    let test = NamedSession {
        path: test.path,
        session: &kept[1],
    };
    let (train_info, test_info, warnings) = checked_sessions(
        geometry,
        geometry_path,
        train,
        test,
        [&set_aside[0], &set_aside[1]],
        as_read,
    )?;
    let mut run = Run {
        geometry,
        geometry_path,
        train_info,
        test_info,
        cfg,
        timings: report::Timings::default(),
        warnings,
    };
    let mut model = run.identify_model(train, test)?;
    let corrected = run.correct(&mut model)?;

    // Black-box comparison.
    let (legacy, blackbox) = run.blackbox_comparison(
        train.session,
        test.session,
        model.loop_result.structure.marker_body_mm,
        &mut model.list.points,
    )?;
    run.warnings.extend(learner_warnings(
        &model.loop_result.identification,
        corrected.learned.as_ref(),
        &run.cfg,
    ));
    let IdentifiedModel {
        timing,
        tr,
        te,
        loop_result,
        final_identified,
        list,
        regime,
        reference,
        rule,
        tolerance,
        loop_rows,
        training_home,
    } = model;
    let obs = PerSession {
        train: &tr[..],
        test: &te[..],
    };
    let device_slips = device_slips(&training_home, &loop_result, corrected.fall_back);
    let FinalModel {
        mut calibration,
        rejections,
        rule,
    } = final_model(
        final_identified,
        &reference,
        obs,
        rule,
        corrected.final_corr,
        corrected.fall_back,
    );
    calibration.home = device_slips.home_slips();
    let mut selection = corrected.selection;
    selection.device_tick = corrected
        .room
        .map(|room| report::DeviceTick::of(room, &calibration));
    run.timings.calibration_s = t_start.elapsed().as_secs_f64();
    let report = run.report(Findings {
        timing,
        stages: list.stages,
        loop_result: &loop_result,
        rejections,
        selection,
        corrections: corrected.corrections,
        kinematics: rule,
        anchor_tolerance: tolerance,
        loop_rows,
        blackbox,
        device_slips,
        loop_not_run: (!regime.full).then_some(regime.reason).flatten(),
        reference: &reference.id,
    });
    let pairs = Pairs {
        residual: corrected.data.pairs,
        blackbox: legacy.map(|l| l.kept),
    };
    Ok(Calibrated {
        report,
        calibration,
        points: list.points,
        loop_result,
        pairs,
        train_rows: tr,
        test_rows: te,
    })
}

/// The calibration the device runs from its next home capture (the
/// training's slips, for its home capture, are added beside it), the rows
/// its kinematics flag on each session, and the report's account of its
/// rule.
struct FinalModel {
    calibration: Calibration,
    rejections: report::SessionRejections,
    rule: report::KinematicsReport,
}

/// The final model: the final identified model (for a new session) with the
/// chosen correction or, when the plain least-squares reference is the final
/// model, the reference, with the rows its kinematics flag.
fn final_model(
    final_identified: FinalIdentified,
    reference: &ReferenceModel,
    obs: PerSession<&[Observation]>,
    rule: report::KinematicsReport,
    final_corr: CorrectionModel,
    fall_back: bool,
) -> FinalModel {
    // The rows the final model's kinematics flagged: the reference's when
    // it is the final model.
    let (fin_new, rejections) = if fall_back {
        let flagged = |rows: &[Observation]| {
            report::Rejections::of(&predict(reference.id.kinematic_model(), rows))
        };
        let rejections = report::SessionRejections {
            train: flagged(obs.train),
            test: flagged(obs.test),
        };
        (reference.id.clone(), rejections)
    } else {
        (final_identified.new_session, final_identified.rejections)
    };
    let calibration = fin_new.calibration(final_corr);
    let rule = if fall_back {
        report::KinematicsReport {
            rule: fin_new.kinematics,
            weighted: false,
            reason: format!(
                "the plain least-squares reference's: every string alike, up to {:.2} mm RMS",
                fin_new.kinematics.fault_threshold_mm
            ),
            candidates: Vec::new(),
            disagreement_q99_mm: None,
        }
    } else {
        rule
    };
    FinalModel {
        calibration,
        rejections,
        rule,
    }
}
