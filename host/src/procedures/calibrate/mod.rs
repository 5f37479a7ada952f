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

pub mod align;
mod figures;
mod plots;
pub mod report;
pub mod trust;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::progress::Step;
use spidar_core::correction::CorrectionModel;
use spidar_core::model::Calibration;

use crate::data::dataset::{DatasetError, Geometry, Session};
use crate::data::observe::{observations, Observation};
use crate::data::stats::{error_stats_checked, ErrorStats, StatsError};
use crate::model::diagnose::{close_loop, tail_noise, LoopConfig, LoopResult};
use crate::model::identify::{identify, IdentifyError, Start, Structure};
use crate::model::learn::nn::{self, NnConfig};
use crate::model::learn::outliers;
use crate::model::learn::search::{self, SvrSearchConfig, SweepConfig};
use crate::model::learn::svr::{self, SvrConfig};
use crate::model::learn::{split_indices, LearnError, OutputMode};
use crate::model::predict::{predict, StringModel};
use spidar_core::geometry::{device_from_room, room_from_device};
use spidar_core::kinematics::FkStatus;

pub use report::{Report, SCHEMA};

/// Any failure of a calibration; each names the file, stage or step.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
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
    Simulate(#[from] crate::sim::SimError),
    #[error("{0}")]
    Compile(#[from] crate::model::compile::CompileCmdError),
    #[error("model blob of {what}: {message}")]
    Blob { what: &'static str, message: String },
    #[error("{0}")]
    Device(#[from] crate::device::measure::DeviceRunError),
    #[error("{0}")]
    Align(#[from] align::AlignError),
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
}

impl CalibrateConfig {
    /// The paper's procedure: NN sweep over 3..=24 hidden neurons with LM and
    /// restarts; RBF epsilon-SVR with a C x epsilon x gamma search. The
    /// residual SVR grid is centred where residual targets need it (epsilon
    /// about 0.05 in standardized units: the residual is mostly tracker noise,
    /// and a narrower tube only buys support vectors). Time limits are guards
    /// against pathological data, not part of the normal run: they do not
    /// trigger on the reference sessions (see `docs/benchmarks.md`).
    pub fn full() -> Self {
        let nn = SweepConfig {
            sizes: (3..=24).collect(),
            mode: OutputMode::Residual,
            sweep_time_limit: Some(Duration::from_secs(6)),
            final_time_limit: Some(Duration::from_secs(4)),
            ..SweepConfig::default()
        };
        let svr = SvrSearchConfig {
            c: vec![1.0, 10.0],
            epsilon: vec![0.1, 0.05],
            gamma: vec![0.3, 1.0],
            mode: OutputMode::Residual,
            time_limit: Some(Duration::from_secs(8)),
            ..SvrSearchConfig::default()
        };
        CalibrateConfig {
            seed: 1,
            loop_config: LoopConfig::default(),
            nn,
            svr,
            selection_fraction: 0.2,
            min_correction_gain: 0.01,
            blackbox: false,
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

/// Per-point errors of one stage on one session, for the figures.
#[derive(Clone, Debug, Default)]
pub struct PointErrors {
    /// Session row of each point (CSV line = row + 2).
    pub rows: Vec<usize>,
    /// Tracker position (room frame, mm).
    pub tracker: Vec<[f64; 3]>,
    /// Distance of the tracker position to the device origin, mm (figs. 15, 17).
    pub distance_mm: Vec<f64>,
    /// Eq. 7 error, mm.
    pub errors: Vec<f64>,
}

/// Stage errors kept for the figures (train and test).
#[derive(Clone, Debug)]
pub struct StagePoints {
    pub name: String,
    pub train: PointErrors,
    pub test: PointErrors,
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
}

/// (input, tracker) pairs in mm: the training pairs after Tukey's outlier
/// removal (what the learners train on), the test pairs all tracked rows.
#[derive(Clone, Debug, Default)]
pub struct PairSet {
    pub train_inputs: Vec<[f64; 3]>,
    pub train_targets: Vec<[f64; 3]>,
    pub test_inputs: Vec<[f64; 3]>,
    pub test_targets: Vec<[f64; 3]>,
}

impl PairSet {
    /// Write `DIR/{stem}_train.csv` and `DIR/{stem}_test.csv` in the layout
    /// `scripts/reference/reference.py` reads (`x,y,z,tx,ty,tz`).
    pub fn write(&self, dir: &Path, stem: &str) -> Result<[PathBuf; 2], CalibrateError> {
        std::fs::create_dir_all(dir).map_err(|source| CalibrateError::Io {
            file: dir.to_path_buf(),
            action: "cannot create the directory",
            source,
        })?;
        let write = |name: String, x: &[[f64; 3]], t: &[[f64; 3]]| {
            let path = dir.join(name);
            let mut text = String::from("x,y,z,tx,ty,tz\n");
            for (a, b) in x.iter().zip(t) {
                text.push_str(&format!(
                    "{},{},{},{},{},{}\n",
                    a[0], a[1], a[2], b[0], b[1], b[2]
                ));
            }
            std::fs::write(&path, text).map_err(|source| CalibrateError::Io {
                file: path.clone(),
                action: "cannot write",
                source,
            })?;
            Ok::<PathBuf, CalibrateError>(path)
        };
        Ok([
            write(
                format!("{stem}_train.csv"),
                &self.train_inputs,
                &self.train_targets,
            )?,
            write(
                format!("{stem}_test.csv"),
                &self.test_inputs,
                &self.test_targets,
            )?,
        ])
    }
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

/// The tracked rows of a session's observations, with positions from `f`.
fn point_errors(
    what: &str,
    obs: &[Observation],
    positions: &[[f64; 3]],
    frame: &spidar_core::model::Frame<f64>,
) -> Result<(PointErrors, ErrorStats), StatsError> {
    let mut pe = PointErrors::default();
    for (o, p) in obs.iter().zip(positions) {
        if let Some(t) = o.tracker {
            pe.rows.push(o.row);
            pe.tracker.push(t);
            let d = device_from_room(frame, t);
            pe.distance_mm
                .push((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt());
            pe.errors.push(crate::data::stats::position_error(*p, t));
        }
    }
    let stats = error_stats_checked(what, &pe.errors)?;
    Ok((pe, stats))
}

fn room_positions(model: StringModel<'_>, obs: &[Observation]) -> Vec<[f64; 3]> {
    predict(model, obs).iter().map(|p| p.room).collect()
}

fn subset(points: &[[f64; 3]], idx: &[usize]) -> Vec<[f64; 3]> {
    idx.iter().filter_map(|&i| points.get(i).copied()).collect()
}

/// Eq. 7 errors of corrected positions `x` against the tracker `t`.
fn point_error_list(
    correct: impl Fn([f64; 3]) -> [f64; 3],
    x: &[[f64; 3]],
    t: &[[f64; 3]],
) -> Vec<f64> {
    x.iter()
        .zip(t)
        .map(|(p, r)| crate::data::stats::position_error(correct(*p), *r))
        .collect()
}

/// Tracked pairs (model room position, tracker) of the training session.
fn tracked_pairs(obs: &[Observation], positions: &[[f64; 3]]) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    obs.iter()
        .zip(positions)
        .filter_map(|(o, p)| o.tracker.map(|t| (*p, t)))
        .unzip()
}

/// Aligns the tracker's clock of dynamic sessions (see [`align`]): twice
/// for the training session (nominal model, then a model identified from
/// the first alignment), once for the test session with that model.
fn align_clocks(
    tr: Vec<Observation>,
    te: Vec<Observation>,
    geometry: &Geometry,
    nominal: &spidar_core::model::Frame<f64>,
    nominal_laws: &[spidar_core::model::StringLaw; spidar_core::STRINGS],
) -> Result<(Vec<Observation>, Vec<Observation>, report::Timing), CalibrateError> {
    let positions = |model: StringModel<'_>, obs: &[Observation]| -> Vec<Option<[f64; 3]>> {
        predict(model, obs)
            .iter()
            .map(|p| {
                matches!(
                    p.status,
                    FkStatus::Ok | FkStatus::FaultyStringExcluded | FkStatus::Inconsistent
                )
                .then_some(p.room)
            })
            .collect()
    };
    let nominal_model = StringModel {
        frame: nominal,
        laws: nominal_laws,
        effects: &[],
    };
    let mut id = None;
    let (tr, train_timing) = match align::static_timing(&tr) {
        Some(s) => (tr, s),
        None => {
            let (first, tr1) = align::align(&tr, &positions(nominal_model, &tr), 0.0)?;
            let quick = identify(
                &tr1,
                nominal,
                &Start::from_geometry(geometry),
                &Structure::default(),
            )?;
            let model = StringModel {
                frame: &quick.frame,
                laws: &quick.laws,
                effects: &quick.effects,
            };
            let (a, tr2) = align::align(&tr, &positions(model, &tr), first.offset_s)?;
            id = Some(quick);
            (tr2, align::SessionTiming::Aligned(a))
        }
    };
    let (te, test_timing) = match align::static_timing(&te) {
        Some(s) => (te, s),
        None => {
            let (frame, laws, effects) = match &id {
                Some(q) => (&q.frame, &q.laws, q.effects.as_slice()),
                None => (nominal, nominal_laws, &[][..]),
            };
            let model = StringModel {
                frame,
                laws,
                effects,
            };
            let (a, te1) = align::align(&te, &positions(model, &te), 0.0)?;
            (te1, align::SessionTiming::Aligned(a))
        }
    };
    Ok((
        tr,
        te,
        report::Timing {
            train: train_timing,
            test: test_timing,
        },
    ))
}

/// Session facts for the report; refuses a session the tracker never saw.
fn session_info(s: NamedSession<'_>) -> Result<report::SessionInfo, CalibrateError> {
    let rows = s.session.samples.len();
    let tracked = s
        .session
        .samples
        .iter()
        .filter(|r| r.tracker.is_some())
        .count();
    if tracked == 0 {
        return Err(CalibrateError::Session {
            file: s.path.to_path_buf(),
            problem: format!(
                "none of its {rows} rows has a tracker position (ots_x, ots_y, ots_z): \
                 nothing to calibrate or evaluate against"
            ),
        });
    }
    Ok(report::SessionInfo {
        path: s.path.display().to_string(),
        rows,
        tracked,
        occluded: rows - tracked,
        has_legacy: s.session.has_legacy(),
        has_tension: s.session.has_tension(),
        ignored_columns: s.session.ignored_columns.clone(),
    })
}

fn stage(
    name: &str,
    kind: report::StageKind,
    train: ErrorStats,
    test: ErrorStats,
) -> report::Stage {
    report::Stage {
        name: name.to_string(),
        kind,
        train,
        test,
    }
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
    let mut timings = report::Timings::default();
    let mut warnings: Vec<String> = Vec::new();
    for s in [&train, &test] {
        s.session.check_strings(s.path, geometry, geometry_path)?;
    }
    let train_info = session_info(train)?;
    let test_info = session_info(test)?;
    match trust::shared_rows(train.session, test.session) {
        (0, _) => {}
        (shared, rows) if shared == rows => warnings.push(format!(
            "the test session {} holds only rows of the training session {}: the held-out \
             figures are training errors, not a test; record a separate test session",
            test.path.display(),
            train.path.display()
        )),
        (shared, rows) => warnings.push(format!(
            "{shared} of the {rows} test rows also appear in the training session: the \
             held-out figures are partly training errors; remove them from one of the files"
        )),
    }
    for (info, s) in [(&train_info, &train), (&test_info, &test)] {
        if !info.ignored_columns.is_empty() {
            warnings.push(format!(
                "{}: ignored unknown columns {}",
                s.path.display(),
                info.ignored_columns.join(", ")
            ));
        }
    }
    let nominal = geometry.nominal_frame();
    let mut tr = observations(&train.session.samples);
    let mut te = observations(&test.session.samples);
    if nominal.layout.planar {
        // A planar device's tracker gives the position in the plane; its z
        // (absent, or the marker's height) is not used: the errors are in
        // the plane.
        let plane_z = room_from_device(&nominal, [0.0, 0.0, nominal.anchors[0][2]])[2];
        for o in tr.iter_mut().chain(te.iter_mut()) {
            if let Some(t) = o.tracker.as_mut() {
                t[2] = plane_z;
            }
        }
    }
    let nominal_laws = geometry.nominal_string_laws();

    // 0. The tracker's clock against the device's (dynamic sessions only).
    let t = Instant::now();
    let (tr, te, timing) = align_clocks(tr, te, geometry, &nominal, &nominal_laws)?;
    timings.alignment_s = t.elapsed().as_secs_f64();
    for (name, t) in [("training", &timing.train), ("test", &timing.test)] {
        if let align::SessionTiming::Aligned(a) = t {
            if a.rows_unpaired > 0 {
                warnings.push(format!(
                    "{name} session: {} rows lost their tracker position when re-paired by the \
                     {:+.4} s clock offset (before the tracker's first or after its last frame, \
                     or across a gap)",
                    a.rows_unpaired, a.offset_s
                ));
            }
        }
    }

    // 1. Raw: nominal geometry through the device pipeline.
    let t = Instant::now();
    let raw_model = StringModel {
        frame: &nominal,
        laws: &nominal_laws,
        effects: &[],
    };
    let raw_tr = room_positions(raw_model, &tr);
    let raw_te = room_positions(raw_model, &te);
    let (raw_tr_pe, raw_tr_s) = point_errors("raw, training session", &tr, &raw_tr, &nominal)?;
    let (raw_te_pe, raw_te_s) = point_errors("raw, test session", &te, &raw_te, &nominal)?;
    timings.raw_s = t.elapsed().as_secs_f64();
    let mut stages = vec![stage("raw", report::StageKind::Raw, raw_tr_s, raw_te_s)];

    // 2-3. Identification and the diagnosis loop. Said in the user's terms
    // before it fails in a fold: every change is judged on two halves.
    let needed = crate::model::identify::rows_needed_for(&Structure::default(), nominal.layout);
    let tracked = tr.iter().filter(|o| o.tracker.is_some()).count();
    if tracked < 2 * needed {
        return Err(CalibrateError::Session {
            file: train.path.to_path_buf(),
            problem: format!(
                "{tracked} rows with tracker positions; a calibration needs at least {} ({needed} \
                 to identify the model's parameters, in each half of the 2-fold cross-validation \
                 that decides which effects to add): collect a larger lattice (e.g. `spidar \
                 collect --cells 4`, 64 cells)",
                2 * needed
            ),
        });
    }
    let t = Instant::now();
    let pb = spinner("identification and diagnosis", cfg.quiet);
    let start = Start::from_geometry(geometry);
    let loop_config = LoopConfig {
        home_tension_n: geometry.home_tension_n.or(cfg.loop_config.home_tension_n),
        ..cfg.loop_config
    };
    let loop_result = close_loop(&tr, Some(&te), &nominal, &start, &loop_config);
    pb.finish_and_clear();
    let loop_result = loop_result?;
    timings.identification_s = t.elapsed().as_secs_f64();
    let base = &loop_result.base;
    let base_model = base.string_model();
    let id_tr = room_positions(base_model, &tr);
    let id_te = room_positions(base_model, &te);
    let (id_tr_pe, id_tr_s) =
        point_errors("identified, training session", &tr, &id_tr, &base.frame)?;
    let (id_te_pe, id_te_s) = point_errors("identified, test session", &te, &id_te, &base.frame)?;
    stages.push(stage(
        "identified",
        report::StageKind::Identified,
        id_tr_s,
        id_te_s,
    ));

    // From here on the sessions are read at the strings' meeting point when
    // the loop found the tracked body's origin off it (the errors are then
    // those of the tracker's position predicted with its orientation).
    let marker = loop_result.structure.marker_body_mm;
    let tr = crate::data::observe::at_meeting_points(&tr, marker).into_owned();
    let te = crate::data::observe::at_meeting_points(&te, marker).into_owned();

    // The final identified model (the base when no effect was added); on
    // the test session, and in the calibration the device runs from its
    // next home capture, without the training session's slips.
    let fin = &loop_result.identification;
    let fin_new = fin.for_a_new_session();
    let fin_tr_pred = predict(fin.string_model(), &tr);
    let fin_te_pred = predict(fin_new.string_model(), &te);
    let rejections = report::SessionRejections {
        train: report::Rejections::of(&fin_tr_pred),
        test: report::Rejections::of(&fin_te_pred),
    };
    let room = |p: Vec<crate::model::predict::Prediction>| -> Vec<[f64; 3]> {
        p.iter().map(|p| p.room).collect()
    };
    let (fin_tr, fin_te) = (room(fin_tr_pred), room(fin_te_pred));
    let (fin_tr_pe, fin_tr_s) = point_errors(
        "identified with effects, training session",
        &tr,
        &fin_tr,
        &fin.frame,
    )?;
    let (fin_te_pe, fin_te_s) = point_errors(
        "identified with effects, test session",
        &te,
        &fin_te,
        &fin.frame,
    )?;
    let n_effects = loop_result.stages.len();
    for (k, s) in loop_result.stages.iter().enumerate() {
        // The last effect stage is the final identified model: its statistics
        // are recomputed here so that they match the corrections' base exactly.
        let (train_s, test_s) = if k + 1 == n_effects {
            (fin_tr_s, fin_te_s)
        } else {
            (s.train, s.test.unwrap_or_else(|| ErrorStats::of(&[])))
        };
        stages.push(stage(&s.name, report::StageKind::Effect, train_s, test_s));
    }

    // 4. Residual corrections on top of the final identified model.
    let (x_all, t_all) = tracked_pairs(&tr, &fin_tr);
    let outl = outliers::tukey(&x_all, &t_all).map_err(learn("outliers (Tukey box plot)"))?;
    let (x_kept, t_kept) = outliers::select(&outl, &x_all, &t_all);
    let (xt_all, tt_all) = tracked_pairs(&te, &fin_te);
    let mut pairs = Pairs {
        residual: PairSet {
            train_inputs: x_kept.clone(),
            train_targets: t_kept.clone(),
            test_inputs: xt_all,
            test_targets: tt_all,
        },
        blackbox: None,
    };
    let (fit_idx, sel_idx) = split_indices(x_kept.len(), cfg.selection_fraction, cfg.seed);
    let (x_fit, t_fit) = (subset(&x_kept, &fit_idx), subset(&t_kept, &fit_idx));
    let (x_sel, t_sel) = (subset(&x_kept, &sel_idx), subset(&t_kept, &sel_idx));

    let t = Instant::now();
    let sweep = search::nn_sweep(&x_fit, &t_fit, &cfg.nn).map_err(learn("NN hidden-size sweep"))?;
    timings.nn_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let svr_search = search::svr_search(&x_fit, &t_fit, &cfg.svr).map_err(learn("SVR search"))?;
    timings.svr_s = t.elapsed().as_secs_f64();
    let nn_corr = CorrectionModel::Nn(sweep.fit.model.clone());
    let svr_corr = CorrectionModel::Svr(svr_search.fit.model.clone());

    // 5. The choice, on the selection split.
    let t = Instant::now();
    let e_id = point_error_list(|p| p, &x_sel, &t_sel);
    let s_id = ErrorStats::of(&e_id);
    let s_nn = ErrorStats::of(&point_error_list(|p| nn_corr.evaluate(p), &x_sel, &t_sel));
    let s_svr = ErrorStats::of(&point_error_list(|p| svr_corr.evaluate(p), &x_sel, &t_sel));
    // Noise of the identified model's p95 and max on the selection split.
    let (noise_p95, noise_max) = tail_noise(&e_id);
    let enough_to_choose = x_sel.len() >= MIN_SELECTION_POINTS;
    if !enough_to_choose {
        warnings.push(format!(
            "the NN and SVR corrections are reported but not chosen: the selection split of the \
             training session has {} points, at least {MIN_SELECTION_POINTS} are needed to tell a \
             correction from noise (the final model is the identified one; collect a larger \
             training session to use a learned correction)",
            x_sel.len()
        ));
    }
    // A correction is eligible when it lowers the mean by the configured gain
    // without raising the p95 or the max beyond their noise; the eligible one
    // with the lower mean is chosen.
    let verdict = |name: &str, c: &ErrorStats| -> Result<(), String> {
        if !c.mean_mm.is_finite() || c.mean_mm >= s_id.mean_mm * (1.0 - cfg.min_correction_gain) {
            Err(format!(
                "{name} does not lower the mean by {:.0} % ({:.3} vs {:.3} mm)",
                100.0 * cfg.min_correction_gain,
                c.mean_mm,
                s_id.mean_mm
            ))
        } else if c.p95_mm > s_id.p95_mm + noise_p95 {
            Err(format!(
                "{name} raises the p95 beyond its noise ({:.3} vs {:.3} + {:.3} mm)",
                c.p95_mm, s_id.p95_mm, noise_p95
            ))
        } else if c.max_mm > s_id.max_mm + noise_max {
            Err(format!(
                "{name} raises the max beyond its noise ({:.2} vs {:.2} + {:.2} mm)",
                c.max_mm, s_id.max_mm, noise_max
            ))
        } else {
            Ok(())
        }
    };
    let judged = [
        (report::Choice::Nn, &s_nn, verdict("nn", &s_nn)),
        (report::Choice::Svr, &s_svr, verdict("svr", &s_svr)),
    ];
    let best = judged
        .iter()
        .filter(|j| j.2.is_ok())
        .min_by(|a, b| a.1.mean_mm.total_cmp(&b.1.mean_mm));
    let refused: Vec<String> = judged.iter().filter_map(|j| j.2.clone().err()).collect();
    let (choice, choice_reason) = match best {
        _ if !enough_to_choose => (
            report::Choice::Identified,
            format!(
                "the selection split has {} points, fewer than {MIN_SELECTION_POINTS}",
                x_sel.len()
            ),
        ),
        Some(b) => (
            b.0,
            format!(
                "{} lowers the mean {:.3} -> {:.3} mm with p95 {:.3} -> {:.3} and max {:.2} -> {:.2} \
                 within their noise ({:.3}, {:.2} mm){}",
                b.0.name(),
                s_id.mean_mm,
                b.1.mean_mm,
                s_id.p95_mm,
                b.1.p95_mm,
                s_id.max_mm,
                b.1.max_mm,
                noise_p95,
                noise_max,
                if refused.is_empty() {
                    String::new()
                } else {
                    format!("; {}", refused.join("; "))
                }
            ),
        ),
        None => (report::Choice::Identified, refused.join("; ")),
    };
    let (v_id, v_nn, v_svr) = (s_id.mean_mm, s_nn.mean_mm, s_svr.mean_mm);
    let pb = spinner("refitting the chosen correction", cfg.quiet);
    let final_corr = match choice {
        report::Choice::Identified => CorrectionModel::None,
        report::Choice::Nn => {
            let fit = nn::train(
                &x_kept,
                &t_kept,
                &NnConfig {
                    hidden: sweep.best_hidden,
                    mode: OutputMode::Residual,
                    lm: cfg.nn.final_lm.clone(),
                    restarts: cfg.nn.final_restarts,
                    validation_fraction: cfg.nn.validation_fraction,
                    seed: cfg.seed,
                    time_limit: cfg.nn.final_time_limit,
                    quiet: true,
                },
            )
            .map_err(learn("NN final training"));
            CorrectionModel::Nn(fit?.model)
        }
        report::Choice::Svr => {
            let fit = svr::train(
                &x_kept,
                &t_kept,
                &SvrConfig {
                    params: svr_search.best,
                    solver: cfg.svr.solver,
                    mode: OutputMode::Residual,
                    time_limit: cfg.svr.time_limit,
                    max_dense_points: cfg.svr.max_dense_points,
                    quiet: true,
                },
            )
            .map_err(learn("SVR final training"));
            CorrectionModel::Svr(fit?.model)
        }
    };
    pb.finish_and_clear();
    timings.selection_s = t.elapsed().as_secs_f64();

    let mut points = vec![
        StagePoints {
            name: "raw".into(),
            train: raw_tr_pe,
            test: raw_te_pe,
        },
        StagePoints {
            name: "identified".into(),
            train: id_tr_pe,
            test: id_te_pe,
        },
    ];
    if n_effects > 0 {
        points.push(StagePoints {
            name: "identified with effects".into(),
            train: fin_tr_pe,
            test: fin_te_pe,
        });
    }
    let mut correction_stage =
        |name: String, corr: &CorrectionModel, kind| -> Result<(), CalibrateError> {
            let ptr: Vec<[f64; 3]> = fin_tr.iter().map(|p| corr.evaluate(*p)).collect();
            let pte: Vec<[f64; 3]> = fin_te.iter().map(|p| corr.evaluate(*p)).collect();
            let (a, sa) =
                point_errors(&format!("{name}, training session"), &tr, &ptr, &fin.frame)?;
            let (b, sb) = point_errors(&format!("{name}, test session"), &te, &pte, &fin.frame)?;
            stages.push(stage(&name, kind, sa, sb));
            points.push(StagePoints {
                name,
                train: a,
                test: b,
            });
            Ok(())
        };
    correction_stage("nn".into(), &nn_corr, report::StageKind::Correction)?;
    correction_stage("svr".into(), &svr_corr, report::StageKind::Correction)?;
    let final_name = format!("final ({})", choice.name());
    correction_stage(final_name.clone(), &final_corr, report::StageKind::Final)?;

    // Where the held-out figure is not what it seems.
    let train_room: Vec<[f64; 3]> = tr.iter().filter_map(|o| o.tracker).collect();
    const BOX_MARGIN_MM: f64 = 1.0;
    if let (Some(bx), Some(fp)) = (
        trust::TrainingBox::of(&fin.frame, &train_room, BOX_MARGIN_MM),
        points.iter().find(|p| p.name == final_name),
    ) {
        let x = trust::extrapolation(&fin.frame, &bx, &fp.test.tracker, &fp.test.errors);
        if x.outside.n > 0 {
            warnings.push(format!(
                "{} of {} test points lie outside the volume the training session covers (its \
                 box, {BOX_MARGIN_MM} mm margin): the model extrapolates there; final error \
                 outside {:.3} mm mean, {:.3} max, inside {:.3} mean, {:.3} max",
                x.outside.n,
                x.outside.n + x.inside.n,
                x.outside.mean_mm,
                x.outside.max_mm,
                x.inside.mean_mm,
                x.inside.max_mm
            ));
        }
    }
    let train_device: Vec<[f64; 3]> = train_room
        .iter()
        .map(|r| device_from_room(&fin.frame, *r))
        .collect();
    if let Some(d) = trust::determination(&fin.frame, &train_device) {
        if d.gain > trust::POOR_DETERMINATION_GAIN {
            warnings.push(format!(
                "the anchors determine the position poorly along ({:+.2}, {:+.2}, {:+.2}) \
                 (device frame): there a string-length error moves the position {:.1} times as \
                 much (median over the training points; a cube SPIDAR: ~0.6). Anchors nearly in \
                 one plane or line? Spread them, or expect errors along that direction",
                d.direction[0], d.direction[1], d.direction[2], d.gain
            ));
        }
    }

    let selection = report::Selection {
        stage: final_name,
        choice,
        correction: match &final_corr {
            CorrectionModel::None => "none",
            CorrectionModel::Nn(_) => "nn",
            CorrectionModel::Svr(_) => "svr",
        },
        selection_points: x_sel.len(),
        fit_points: x_fit.len(),
        min_correction_gain: cfg.min_correction_gain,
        validation_mean_mm: report::Candidates {
            identified: v_id,
            nn: v_nn,
            svr: v_svr,
        },
        validation_p95_mm: report::Candidates {
            identified: s_id.p95_mm,
            nn: s_nn.p95_mm,
            svr: s_svr.p95_mm,
        },
        validation_max_mm: report::Candidates {
            identified: s_id.max_mm,
            nn: s_nn.max_mm,
            svr: s_svr.max_mm,
        },
        noise_p95_mm: noise_p95,
        noise_max_mm: noise_max,
        reason: choice_reason,
        final_support_vectors: match &final_corr {
            CorrectionModel::Svr(m) => Some(m.support.len()),
            _ => None,
        },
        final_hidden: match &final_corr {
            CorrectionModel::Nn(m) => Some(m.w1.len()),
            _ => None,
        },
    };
    let residual = report::Corrections {
        mode: "residual",
        input: "final identified model, room position (mm)",
        outliers: report::Outliers::of(
            &outl,
            "final identified model vs tracker, training session",
        ),
        nn: report::NnReport::of(&sweep),
        svr: report::SvrReport::of(&svr_search),
    };

    // Black-box comparison.
    let legacy = (train_info.has_legacy && test_info.has_legacy)
        .then(|| blackbox_pairs(geometry, train.session, test.session))
        .transpose()?;
    let blackbox = if cfg.blackbox {
        if let Some(lp) = &legacy {
            let t = Instant::now();
            let bb = blackbox(lp, &cfg, &mut points)?;
            timings.blackbox_s = Some(t.elapsed().as_secs_f64());
            Some(bb)
        } else {
            warnings.push(
                "black-box comparison skipped: it needs the legacy controller's dev_x, dev_y, \
                 dev_z columns in both sessions"
                    .into(),
            );
            None
        }
    } else {
        None
    };

    for w in &fin.warnings {
        warnings.push(format!("identification: {w}"));
    }
    if sweep.curve.len() < cfg.nn.sizes.len() {
        warnings.push(format!(
            "NN sweep: the time limit cut {} of {} hidden sizes",
            cfg.nn.sizes.len() - sweep.curve.len(),
            cfg.nn.sizes.len()
        ));
    }
    let cut = svr_search
        .candidates
        .iter()
        .filter(|c| c.validation_mean_mm.is_none())
        .count();
    if cut > 0 {
        warnings.push(format!(
            "SVR search: {cut} of {} candidates were not scored (time limit or no convergence)",
            svr_search.candidates.len()
        ));
    }

    let calibration = Calibration {
        frame: fin_new.frame,
        strings: fin_new.laws,
        effects: fin_new.effects.clone(),
        correction: final_corr,
    };
    timings.calibration_s = t_start.elapsed().as_secs_f64();
    let report = Report {
        schema: SCHEMA,
        tool: report::Tool::current(),
        timing,
        device: report::DeviceReport::of(
            geometry.layout,
            train_info.tracked,
            fin.residual_scale_mm,
            cfg.loop_config.chi2_threshold,
            rejections,
        ),
        inputs: report::Inputs {
            geometry: geometry_path.display().to_string(),
            train: train_info,
            test: test_info,
        },
        stages,
        effects: loop_result.findings.clone(),
        identification: report::IdentificationReport::of(
            base,
            fin,
            &loop_result.layers,
            loop_result.structure.marker_body_mm,
        ),
        selection,
        corrections: residual,
        blackbox,
        warnings,
        notes: Vec::new(),
        timings_s: timings,
        figures: Vec::new(),
        files: report::Files::default(),
    };
    pairs.blackbox = legacy.map(|l| l.kept);
    Ok(Calibrated {
        report,
        calibration,
        points,
        loop_result,
        pairs,
    })
}

/// Legacy position in the room (eq. 6: `p_room = p_device + t`), paired with
/// the tracker, over the rows that have both.
fn legacy_pairs(
    geometry: &Geometry,
    session: &Session,
) -> (Vec<usize>, Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let t = geometry.room_from_device_translation_mm;
    let mut rows = Vec::new();
    let mut x = Vec::new();
    let mut y = Vec::new();
    for (row, s) in session.samples.iter().enumerate() {
        if let (Some(d), Some(o)) = (s.legacy, s.tracker) {
            rows.push(row);
            x.push([d[0] + t[0], d[1] + t[1], d[2] + t[2]]);
            y.push(o);
        }
    }
    (rows, x, y)
}

/// The black-box data: all legacy pairs of both sessions (with their rows),
/// Tukey's box plot on the training ones, and the kept training pairs.
struct LegacyPairs {
    rows_tr: Vec<usize>,
    x_tr: Vec<[f64; 3]>,
    y_tr: Vec<[f64; 3]>,
    rows_te: Vec<usize>,
    outliers: outliers::OutlierReport,
    kept: PairSet,
    nominal: spidar_core::model::Frame<f64>,
}

fn blackbox_pairs(
    geometry: &Geometry,
    train: &Session,
    test: &Session,
) -> Result<LegacyPairs, CalibrateError> {
    let (rows_tr, x_tr, y_tr) = legacy_pairs(geometry, train);
    let (rows_te, x_te, y_te) = legacy_pairs(geometry, test);
    let outl =
        outliers::tukey(&x_tr, &y_tr).map_err(learn("black-box outliers (Tukey box plot)"))?;
    let (xk, yk) = outliers::select(&outl, &x_tr, &y_tr);
    Ok(LegacyPairs {
        rows_tr,
        x_tr,
        y_tr,
        rows_te,
        outliers: outl,
        kept: PairSet {
            train_inputs: xk,
            train_targets: yk,
            test_inputs: x_te,
            test_targets: y_te,
        },
        nominal: geometry.nominal_frame(),
    })
}

fn blackbox(
    lp: &LegacyPairs,
    cfg: &CalibrateConfig,
    points: &mut Vec<StagePoints>,
) -> Result<report::Blackbox, CalibrateError> {
    let (xk, yk) = (&lp.kept.train_inputs, &lp.kept.train_targets);
    let sweep = search::nn_sweep(xk, yk, &cfg.blackbox_nn).map_err(learn("black-box NN sweep"))?;
    let svr_search =
        search::svr_search(xk, yk, &cfg.blackbox_svr).map_err(learn("black-box SVR search"))?;
    let nn_corr = CorrectionModel::Nn(sweep.fit.model.clone());
    let svr_corr = CorrectionModel::Svr(svr_search.fit.model.clone());
    let mut stages = Vec::new();
    let pe =
        |rows: &[usize], x: &[[f64; 3]], y: &[[f64; 3]], corr: &CorrectionModel, what: &str| {
            let mut p = PointErrors::default();
            for ((row, xi), yi) in rows.iter().zip(x).zip(y) {
                p.rows.push(*row);
                p.tracker.push(*yi);
                let d = device_from_room(&lp.nominal, *yi);
                p.distance_mm
                    .push((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt());
                p.errors
                    .push(crate::data::stats::position_error(corr.evaluate(*xi), *yi));
            }
            error_stats_checked(what, &p.errors).map(|s| (p, s))
        };
    let (x_te, y_te) = (&lp.kept.test_inputs, &lp.kept.test_targets);
    for (name, corr) in [
        ("legacy", &CorrectionModel::None),
        ("blackbox nn", &nn_corr),
        ("blackbox svr", &svr_corr),
    ] {
        let (a, sa) = pe(
            &lp.rows_tr,
            &lp.x_tr,
            &lp.y_tr,
            corr,
            &format!("{name}, training session"),
        )?;
        let (b, sb) = pe(
            &lp.rows_te,
            x_te,
            y_te,
            corr,
            &format!("{name}, test session"),
        )?;
        let kind = if name == "legacy" {
            report::StageKind::Raw
        } else {
            report::StageKind::Correction
        };
        stages.push(stage(name, kind, sa, sb));
        points.push(StagePoints {
            name: name.to_string(),
            train: a,
            test: b,
        });
    }
    Ok(report::Blackbox {
        mode: "absolute",
        input: "legacy controller position dev_x, dev_y, dev_z + eq. 6 translation (mm)",
        stages,
        outliers: report::Outliers::of(
            &lp.outliers,
            "legacy position vs tracker, training session",
        ),
        nn: report::NnReport::of(&sweep),
        svr: report::SvrReport::of(&svr_search),
    })
}

/// Where [`write_outputs`] put things.
#[derive(Clone, Debug)]
pub struct Written {
    pub calibration: PathBuf,
    pub report: Vec<PathBuf>,
    pub figures: Vec<PathBuf>,
}

/// Write the figures (unless `figures` is false), `DIR/calibration.json`,
/// `DIR/report.json` and, when given, the JSON report at `json` too (`-` is
/// stdout, written by the caller). Fills the report's file paths.
pub fn write_outputs(
    calibrated: &mut Calibrated,
    out: &Path,
    json: Option<&Path>,
    figures: bool,
    quiet: bool,
) -> Result<Written, CalibrateError> {
    std::fs::create_dir_all(out).map_err(|source| CalibrateError::Io {
        file: out.to_path_buf(),
        action: "cannot create the output directory",
        source,
    })?;
    let t = Instant::now();
    if figures {
        let pb = spinner("figures", quiet);
        let drawn = plots::draw_all(calibrated, &out.join("figures"));
        pb.finish_and_clear();
        calibrated.report.figures = drawn?;
    }
    calibrated.report.timings_s.figures_s = Some(t.elapsed().as_secs_f64());
    let calibration_path = out.join("calibration.json");
    write_json(&calibration_path, &calibrated.calibration)?;
    let report_path = out.join("report.json");
    let mut reports = vec![report_path.clone()];
    if let Some(j) = json {
        if j != Path::new("-") && j != report_path {
            reports.push(j.to_path_buf());
        }
    }
    calibrated.report.files = report::Files {
        calibration: calibration_path.display().to_string(),
        reports: reports.iter().map(|p| p.display().to_string()).collect(),
        out_dir: out.display().to_string(),
    };
    for r in &reports {
        if let Some(parent) = r.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|source| CalibrateError::Io {
                file: parent.to_path_buf(),
                action: "cannot create the directory",
                source,
            })?;
        }
        write_json(r, &calibrated.report)?;
    }
    Ok(Written {
        calibration: calibration_path,
        report: reports,
        figures: calibrated
            .report
            .figures
            .iter()
            .map(|f| PathBuf::from(&f.path))
            .collect(),
    })
}

fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), CalibrateError> {
    let mut text = serde_json::to_string_pretty(value).map_err(|source| CalibrateError::Json {
        file: path.to_path_buf(),
        source,
    })?;
    text.push('\n');
    std::fs::write(path, text).map_err(|source| CalibrateError::Io {
        file: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}
