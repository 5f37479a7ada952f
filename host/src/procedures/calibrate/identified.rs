//! Stages 0-3 of a calibration: the tracker's clock aligned with the
//! device's, the raw (nominal) model, the identification and the diagnosis
//! loop, the plain least-squares reference, the kinematics' rule, and the
//! final identified model on both sessions.

use std::path::Path;
use std::time::Instant;

use spidar_core::geometry::room_from_device;
use spidar_core::kinematics::{FkStatus, KinematicsRule};
use spidar_core::model::{Effect, EffectTerm, EVERY_STRING};

use crate::data::dataset::{Geometry, Session};
use crate::data::home::{LaterHome, TrainingHome};
use crate::data::observe::{observations_skipping, Observation};
use crate::data::stats::{ErrorStats, StatsError};
use crate::model::diagnose::{close_loop, Family, Finding, LoopConfig, LoopResult};
use crate::model::identify::{effect_parameter_names, identify, Identification, Start, Structure};
use crate::model::predict::{predict, KinematicModel, UNMEASURED_SCALES};
use crate::model::reference;
use crate::model::rule::RuleChoice;

use super::checks::{
    anchor_departure_warnings, check_alignment, check_enough_tracked_rows, check_tracker_scale,
    planar_session_warnings, radius_warnings, test_outlier_warning, tracker_outlier_warning,
    unfitted_warning, unpaired_rows_warnings, Regime,
};
use super::evaluate::{room_positions, stage, PerSession, StageErrors, StageList};
use super::loop_rows::LoopRows;
use super::{align, report, spinner, CalibrateConfig, CalibrateError, NamedSession, Run};

/// The observations of both sessions but their rows set aside whole
/// (`skipped`, ascending), the test rows after a new home capture marked
/// (`test_home`); on a planar device the tracker's z set to the anchors'
/// plane.
fn session_observations(
    nominal: &spidar_core::model::Frame<f64>,
    train: &Session,
    test: &Session,
    skipped: [&[usize]; 2],
    test_home: Option<&LaterHome>,
) -> (Vec<Observation>, Vec<Observation>) {
    let mut tr = observations_skipping(&train.samples, skipped[0]);
    let mut te = observations_skipping(&test.samples, skipped[1]);
    if let Some(home) = test_home {
        home.mark(&mut te);
    }
    if nominal.layout.planar {
        // A planar device's tracker gives the position in the plane; its z
        // (absent, or the marker's height) is not used: the errors are in
        // the plane.
        let plane_z = room_from_device(nominal, [0.0, 0.0, nominal.anchors[0][2]])[2];
        for o in tr.iter_mut().chain(te.iter_mut()) {
            if let Some(t) = o.tracker.as_mut() {
                t[2] = plane_z;
            }
        }
    }
    (tr, te)
}

/// The room positions of `predictions` where the kinematics placed the
/// row at all (what the alignment compares the tracker with).
fn placed(predictions: &[crate::model::predict::Prediction]) -> Vec<Option<[f64; 3]>> {
    predictions
        .iter()
        .map(|p| {
            matches!(
                p.status,
                FkStatus::Ok | FkStatus::FaultyStringExcluded | FkStatus::Inconsistent
            )
            .then_some(p.room)
        })
        .collect()
}

/// [`placed`] of `model`'s predictions of `obs`.
fn placed_positions(model: KinematicModel<'_>, obs: &[Observation]) -> Vec<Option<[f64; 3]>> {
    placed(&predict(model, obs))
}

/// Most rows the alignment's quick model is identified from (a 13^3
/// lattice has 2,197): a longer session is read one row in every few.
/// The model only places the end-effector for the speed profiles, whose
/// correlation every row still enters; the offsets of a 30,000-row stream
/// came out within 0.01 ms of those from every row (record 0051).
const ALIGNMENT_MODEL_ROWS: usize = 3000;

/// The sessions with their clocks aligned, and the nominal geometry's room
/// positions of the training rows when the alignment worked them out (the
/// raw stage's: the kinematics read the strings alone, which re-pairing the
/// tracker leaves as they were).
type Aligned = (
    Vec<Observation>,
    Vec<Observation>,
    report::Timing,
    Option<Vec<[f64; 3]>>,
);

/// Aligns the tracker's clock of dynamic sessions (see [`align`]): twice
/// for the training session (nominal model, then a model identified from
/// the first alignment), once for the test session with that model.
fn align_clocks(
    (tr, tr_path): (Vec<Observation>, &Path),
    (te, te_path): (Vec<Observation>, &Path),
    geometry: &Geometry,
    nominal: &spidar_core::model::Frame<f64>,
    nominal_laws: &[spidar_core::model::StringLaw; spidar_core::STRINGS],
    clock_offset_s: f64,
) -> Result<Aligned, CalibrateError> {
    let nominal_model = KinematicModel {
        frame: nominal,
        laws: nominal_laws,
        effects: &[],
        length_scale_mm: &UNMEASURED_SCALES,
        kinematics: KinematicsRule::default(),
    };
    let mut id = None;
    let mut raw_train = None;
    let (tr, train_timing) = match align::static_timing(&tr) {
        Some(s) => (tr, s),
        None => {
            let nominal_tr = predict(nominal_model, &tr);
            // The model identified on rows paired a little off takes up part
            // of the offset, and the next pass with it finds the rest: the
            // two are alternated until the offset holds.
            let (mut a, mut rows) = align::align(
                &tr,
                &placed(&nominal_tr),
                clock_offset_s,
                align::ClockRate::Same,
            )
            .map_err(|e| alignment_failed(tr_path, &tr, e))?;
            raw_train = Some(nominal_tr.iter().map(|p| p.room).collect());
            let mut quick;
            let mut rounds = 0;
            loop {
                // The quick model places the end-effector for the speed
                // profiles only: a long session's rows, thinned in time,
                // identify it as well.
                let thinned = LoopRows::of(rows.len(), ALIGNMENT_MODEL_ROWS).pick(&rows);
                quick = identify(
                    &thinned,
                    nominal,
                    &Start::from_geometry(geometry),
                    &Structure::default(),
                )?;
                let (next, next_rows) = align::align(
                    &tr,
                    &placed_positions(quick.kinematic_model(), &tr),
                    a.offset_s,
                    align::ClockRate::Fitted,
                )
                .map_err(|e| alignment_failed(tr_path, &tr, e))?;
                let step = (next.offset_s - a.offset_s).abs();
                (a, rows) = (next, next_rows);
                rounds += 1;
                if step <= align::OFFSET_SETTLED_S.max(2.0 * a.offset_sd_s)
                    || rounds >= align::MAX_ALIGN_ROUNDS
                {
                    break;
                }
            }
            id = Some(quick);
            (rows, align::SessionTiming::Aligned(a))
        }
    };
    let (te, test_timing) = match align::static_timing(&te) {
        Some(s) => (te, s),
        None => {
            let model = match &id {
                Some(q) => q.kinematic_model(),
                None => nominal_model,
            };
            // The rig that recorded the training stream most likely kept its
            // clocks: the search is centred on the training session's
            // offset first (its +-5 s window then holds it whole, where a
            // window centred on 0 can find an edge of itself instead of the
            // offset); a tracker restarted between the two recordings has
            // another offset, searched around the user's hint and 0.
            let mut priors = vec![clock_offset_s, 0.0];
            if let align::SessionTiming::Aligned(a) = &train_timing {
                priors.insert(0, a.offset_s);
            }
            priors.dedup();
            // The clocks' rate: the test stream's own where it is long
            // enough to tell it from the model's errors, else the training
            // stream's (two oscillators keep their rate; a short stream
            // paired without it drifted 100 ppm x its length off).
            let rate = match align::ClockRate::of(&train_timing) {
                known @ align::ClockRate::Known { .. } if !align::tells_a_rate(&te) => known,
                _ => align::ClockRate::Fitted,
            };
            // The first search whose fine fit confirms its peak; with none,
            // the first search's result, which the checks then refuse.
            let positions = placed_positions(model, &te);
            let mut tried = priors
                .iter()
                .map(|&prior| align::align(&te, &positions, prior, rate));
            let first = tried.next().expect("one prior at least");
            let (a, te1) = match first {
                Ok(found) if found.0.refined => found,
                first => match tried.find_map(|r| r.ok().filter(|found| found.0.refined)) {
                    Some(found) => found,
                    None => first.map_err(|e| alignment_failed(te_path, &te, e))?,
                },
            };
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
        raw_train,
    ))
}

/// The refusal of a stream (`rows`, read from `path`) whose tracker clock
/// the alignment could not find: what failed, on how many tracked rows
/// over how long, and what to record instead.
fn alignment_failed(path: &Path, rows: &[Observation], e: align::AlignError) -> CalibrateError {
    let tracked: Vec<f64> = rows
        .iter()
        .filter(|o| o.tracker.is_some())
        .map(|o| o.t_s)
        .collect();
    let span_s = match (tracked.first(), tracked.last()) {
        (Some(a), Some(b)) => b - a,
        _ => 0.0,
    };
    CalibrateError::Session {
        file: path.to_path_buf(),
        problem: format!(
            "a stream (rows {:.3} s apart): its tracker's clock must be found from the motion \
             before the rows can be paired, and that failed on its {} tracked rows over {:.1} s \
             ({e}). Record a longer stream that moves the end-effector, or pair the device's \
             and the tracker's rows by a common clock and say so (`--clocks-paired`; a clock \
             more than 5 s off: `--clock-offset-s`)",
            align::median_interval_s(rows).unwrap_or(f64::NAN),
            tracked.len(),
            span_s
        ),
    }
}

/// The nominal model's room positions of each session's rows.
type RawPositions = PerSession<Vec<[f64; 3]>>;

/// Stage 1, raw: the nominal geometry through the device pipeline (the
/// training rows' positions `raw_train` when the alignment worked them out).
fn raw_errors(
    obs: PerSession<&[Observation]>,
    nominal: &spidar_core::model::Frame<f64>,
    nominal_laws: &[spidar_core::model::StringLaw; spidar_core::STRINGS],
    raw_train: Option<Vec<[f64; 3]>>,
) -> Result<(StageErrors, RawPositions), StatsError> {
    let raw_model = KinematicModel {
        frame: nominal,
        laws: nominal_laws,
        effects: &[],
        length_scale_mm: &UNMEASURED_SCALES,
        kinematics: KinematicsRule::default(),
    };
    let raw_tr = raw_train.unwrap_or_else(|| room_positions(raw_model, obs.train));
    let raw_te = room_positions(raw_model, obs.test);
    let errors = StageErrors::of(
        "raw",
        obs,
        PerSession {
            train: &raw_tr,
            test: &raw_te,
        },
        nominal,
    )?;
    Ok((
        errors,
        PerSession {
            train: raw_tr,
            test: raw_te,
        },
    ))
}

/// The latency every string shares that `t` is, s.
fn shared_latency_of(t: &EffectTerm) -> Option<f64> {
    match t.effect {
        Effect::Latency { latency_s } if t.string == EVERY_STRING => Some(latency_s),
        _ => None,
    }
}

/// The latency every string shares in `id` (s), if it holds one.
fn shared_latency_s(id: &Identification) -> Option<f64> {
    id.effects.iter().find_map(shared_latency_of)
}

/// `loop_result` without its latency every string shares. Moving the
/// clocks' pairing by the latency changes every row as the term did, to
/// first order in the motion, so the model's other parameters and the
/// loop's figures stand: refitted on the rows paired anew, the model held
/// out worse (decision record 0064).
fn fold_shared_latency(loop_result: &mut LoopResult) {
    let shared = |t: &EffectTerm| shared_latency_of(t).is_some();
    loop_result.structure.effects.retain(|t| !shared(t));
    let id = &mut loop_result.identification;
    let names: Vec<String> = id
        .effects
        .iter()
        .filter(|t| shared(t))
        .flat_map(effect_parameter_names)
        .collect();
    id.effects.retain(|t| !shared(t));
    id.parameters.retain(|p| !names.contains(&p.name));
}

/// The stage and finding of the latency every string shares, once the
/// clocks' offsets (`timing`) hold it, named for what they are.
fn name_the_clock_stage(loop_result: &mut LoopResult, timing: &report::Timing) {
    let offsets = |t: &align::SessionTiming| match t {
        align::SessionTiming::Aligned(a) => format!(
            "{:+.2} -> {:+.2} ms",
            a.first_offset_s.unwrap_or(a.offset_s) * 1e3,
            a.offset_s * 1e3
        ),
        align::SessionTiming::Static { .. } => "static".into(),
        align::SessionTiming::Paired { .. } => "paired".into(),
    };
    let note = format!(
        "; moved into the tracker clocks' offsets (training {}, test {}): the model holds no \
         latency every string shares, which the device would apply in use",
        offsets(&timing.train),
        offsets(&timing.test)
    );
    let is_it = |f: &Finding| f.family == Family::Latency && f.strings.is_empty() && f.added;
    for stage in loop_result.stages.iter_mut().filter(|s| is_it(&s.finding)) {
        stage.name = CLOCK_STAGE.into();
        stage.finding.description += &note;
    }
    for f in loop_result.findings.iter_mut().filter(|f| is_it(f)) {
        f.description += &note;
    }
}

/// The stage of a latency every string shares once it is in the clocks'
/// offsets.
const CLOCK_STAGE: &str = "tracker clock offset refined";

/// Stages 2-3: the base identification and the diagnosis loop, from the
/// geometry file's start (and its home tension when it gives one);
/// `clock_aligned`: the training's tracker clock was found from its rows.
fn identify_and_diagnose(
    geometry: &Geometry,
    obs: PerSession<&[Observation]>,
    nominal: &spidar_core::model::Frame<f64>,
    cfg: &CalibrateConfig,
    regime: &Regime,
    clock_aligned: bool,
) -> Result<(LoopResult, crate::model::tolerance::ToleranceChoice), CalibrateError> {
    let pb = spinner("identification and diagnosis", cfg.quiet);
    let start = Start::from_geometry(geometry);
    let loop_config = LoopConfig {
        diagnose: cfg.loop_config.diagnose && regime.full,
        clock_aligned,
        ..cfg.loop_config.with_geometry(geometry)
    };
    let tolerance = crate::model::tolerance::choose(obs.train, nominal, &start, &loop_config);
    let loop_config = LoopConfig {
        anchor_sd_mm: Some(tolerance.anchor_sd_mm),
        robust: tolerance.robust,
        ..loop_config
    };
    let loop_result = close_loop(obs.train, Some(obs.test), nominal, &start, &loop_config);
    pb.finish_and_clear();
    Ok((loop_result?, tolerance))
}

/// The base identification's errors (stage `identified`).
fn identified_errors(
    base: &crate::model::identify::Identification,
    obs: PerSession<&[Observation]>,
) -> Result<StageErrors, StatsError> {
    let base_model = base.kinematic_model();
    let id_tr = room_positions(base_model, obs.train);
    let id_te = room_positions(base_model, obs.test);
    StageErrors::of(
        "identified",
        obs,
        PerSession {
            train: &id_tr,
            test: &id_te,
        },
        &base.frame,
    )
}

/// The final identified model (the base when no effect was added) on both
/// sessions: on the test session's rows after a new home capture, and in
/// the calibration the device runs from its next home capture, without the
/// training session's slips.
pub(super) struct FinalIdentified {
    /// The model for a new session (the calibration's).
    pub(super) new_session: crate::model::identify::Identification,
    /// Room positions on each session.
    pub(super) positions: PerSession<Vec<[f64; 3]>>,
    pub(super) rejections: report::SessionRejections,
}

impl FinalIdentified {
    /// The model's predictions on both sessions, and their errors: `fin` on
    /// the training rows, `later` (`fin` with the slips the training's last
    /// home capture still has, [`under_the_training_home`]) on the test rows.
    pub(super) fn of(
        fin: &crate::model::identify::Identification,
        later: &crate::model::identify::Identification,
        obs: PerSession<&[Observation]>,
    ) -> Result<(FinalIdentified, StageErrors), StatsError> {
        let fin_new = fin.for_a_new_session();
        let fin_tr_pred = predict(fin.kinematic_model(), obs.train);
        // Test rows under the training's home capture keep its slips.
        let fin_te_pred = crate::model::validate::predict_later(later, obs.test);
        let rejections = report::SessionRejections {
            train: report::Rejections::of(&fin_tr_pred),
            test: report::Rejections::of(&fin_te_pred),
        };
        let room = |p: Vec<crate::model::predict::Prediction>| -> Vec<[f64; 3]> {
            p.iter().map(|p| p.room).collect()
        };
        let (fin_tr, fin_te) = (room(fin_tr_pred), room(fin_te_pred));
        let errors = StageErrors::of(
            "identified with effects",
            obs,
            PerSession {
                train: &fin_tr,
                test: &fin_te,
            },
            &fin.frame,
        )?;
        let final_identified = FinalIdentified {
            new_session: fin_new,
            positions: PerSession {
                train: fin_tr,
                test: fin_te,
            },
            rejections,
        };
        Ok((final_identified, errors))
    }
}

/// One stage per effect the diagnosis loop added.
fn effect_stages(loop_result: &LoopResult, fin: &StageErrors) -> Vec<report::Stage> {
    let n_effects = loop_result.stages.len();
    let mut stages = Vec::new();
    for (k, s) in loop_result.stages.iter().enumerate() {
        // The last effect stage is the final identified model: its statistics
        // are recomputed here so that they match the corrections' base exactly.
        let (train_s, test_s) = if k + 1 == n_effects {
            (fin.train_stats, fin.test_stats)
        } else {
            (s.train, s.test.unwrap_or_else(|| ErrorStats::of(&[])))
        };
        stages.push(stage(&s.name, report::StageKind::Effect, train_s, test_s));
    }
    stages
}

/// `id` as it holds for the test rows under the training's last home
/// capture (and for the device under it): the slips of that capture, not
/// those of an earlier one or fitted across captures.
pub(super) fn under_the_training_home(
    id: &crate::model::identify::Identification,
    training_home: &TrainingHome,
) -> crate::model::identify::Identification {
    id.with_slips_where(|at_s| training_home.slip_is_of_last_capture(at_s))
}

/// Stages 0-3: the identified model and its stages, with the sessions'
/// observations it leaves for the corrections.
pub(super) struct IdentifiedModel {
    /// The tracker's clock against the device's.
    pub(super) timing: report::Timing,
    /// The sessions' observations, read at the strings' meeting point.
    pub(super) tr: Vec<Observation>,
    pub(super) te: Vec<Observation>,
    pub(super) loop_result: LoopResult,
    pub(super) final_identified: FinalIdentified,
    /// `raw`, the reference, `identified` and one stage per added effect.
    pub(super) list: StageList,
    pub(super) regime: Regime,
    pub(super) reference: ReferenceModel,
    pub(super) rule: report::KinematicsReport,
    /// The anchors' tolerance the identification used.
    pub(super) tolerance: crate::model::tolerance::ToleranceChoice,
    /// The training rows the loop decided on.
    pub(super) loop_rows: LoopRows,
    /// The home capture the training session ends under: which of its
    /// slips a later session under it, and the device, still have.
    pub(super) training_home: TrainingHome,
}

/// The plain least-squares reference ([`crate::model::reference`]) and its
/// positions on both sessions (read as the loop's base reads them).
pub(super) struct ReferenceModel {
    pub(super) id: crate::model::identify::Identification,
    positions: PerSession<Vec<[f64; 3]>>,
    /// Its error on each training row (`None`: not tracked).
    pub(super) train_errors_by_row: Vec<Option<f64>>,
}

impl ReferenceModel {
    /// The reference identified on `fit_rows` (the loop's training rows),
    /// its positions on both sessions `obs`.
    pub(super) fn of(
        geometry: &Geometry,
        nominal: &spidar_core::model::Frame<f64>,
        fit_rows: &[Observation],
        obs: PerSession<&[Observation]>,
    ) -> Result<ReferenceModel, CalibrateError> {
        let id = reference::identify_reference(fit_rows, nominal, &Start::from_geometry(geometry))?;
        let positions = PerSession {
            train: room_positions(id.kinematic_model(), obs.train),
            test: room_positions(id.kinematic_model(), obs.test),
        };
        let train_errors_by_row = obs
            .train
            .iter()
            .zip(&positions.train)
            .map(|(o, p)| o.tracker.map(|t| crate::data::stats::position_error(*p, t)))
            .collect();
        Ok(ReferenceModel {
            id,
            positions,
            train_errors_by_row,
        })
    }

    pub(super) fn errors(
        &self,
        obs: PerSession<&[Observation]>,
        frame: &spidar_core::model::Frame<f64>,
    ) -> Result<StageErrors, StatsError> {
        StageErrors::of(
            reference::STAGE_NAME,
            obs,
            PerSession {
                train: &self.positions.train,
                test: &self.positions.test,
            },
            frame,
        )
    }
}

impl Run<'_> {
    /// Stages 0-3: the clocks aligned, the raw model, the identification and
    /// the diagnosis loop, and the final identified model.
    pub(super) fn identify_model(
        &mut self,
        train: NamedSession<'_>,
        test: NamedSession<'_>,
    ) -> Result<IdentifiedModel, CalibrateError> {
        let geometry = self.geometry;
        let nominal = geometry.nominal_frame();
        let nominal_laws = geometry.nominal_string_laws();

        // 0. The tracker's clock against the device's (dynamic sessions only).
        let (mut tr, mut te, mut timing, raw_train) =
            self.aligned_observations(train, test, &nominal, &nominal_laws)?;
        let obs = PerSession {
            train: &tr[..],
            test: &te[..],
        };

        // 1. Raw: nominal geometry through the device pipeline.
        let t = Instant::now();
        let (mut raw, raw_positions) = raw_errors(obs, &nominal, &nominal_laws, raw_train)?;
        self.timings.raw_s = t.elapsed().as_secs_f64();
        self.check_tracker_units([(train.path, &tr), (test.path, &te)], &raw_positions)?;
        // 2-3. Identification and the diagnosis loop.
        let regime = check_enough_tracked_rows(train.path, &tr, &nominal)?;
        self.warnings.extend(regime.reason.clone());
        let loop_rows = LoopRows::of(tr.len(), self.cfg.max_loop_rows);
        let t = Instant::now();
        let clock_aligned = matches!(timing.train, align::SessionTiming::Aligned(_));
        let (mut loop_result, tolerance) = {
            let read = loop_rows.pick(&tr);
            let obs = PerSession {
                train: &read[..],
                test: obs.test,
            };
            identify_and_diagnose(geometry, obs, &nominal, &self.cfg, &regime, clock_aligned)?
        };
        // A latency every string shares, on clocks found from the rows, is
        // those clocks' offset refined (the alignment's quick model had no
        // latency of one string): it goes into the offsets, where the
        // device does not apply it in use (decision record 0064).
        if let Some(latency_s) =
            shared_latency_s(&loop_result.identification).filter(|_| clock_aligned)
        {
            let t = Instant::now();
            fold_shared_latency(&mut loop_result);
            let (tr_moved, te_moved, timing_moved) = self.clocks_without_the_shared_latency(
                latency_s,
                &loop_result.identification,
                [train, test],
                &nominal,
                &timing,
            )?;
            name_the_clock_stage(&mut loop_result, &timing_moved);
            let stale = unpaired_rows_warnings(&timing);
            self.warnings.retain(|w| !stale.contains(w));
            self.warnings.extend(unpaired_rows_warnings(&timing_moved));
            (tr, te, timing) = (tr_moved, te_moved, timing_moved);
            raw = raw_errors(
                PerSession {
                    train: &tr[..],
                    test: &te[..],
                },
                &nominal,
                &nominal_laws,
                None,
            )?
            .0;
            self.timings.alignment_s += t.elapsed().as_secs_f64();
        }
        let mut list = StageList::default();
        list.push("raw".into(), report::StageKind::Raw, raw);
        if loop_rows.thinned() {
            // The glitches the loop found are among the rows it read: every
            // row is judged by its base model, on the same threshold rule.
            loop_result.tracker_outliers =
                crate::model::diagnose::TrackerOutliers::of(&loop_result.base, &tr);
        }
        self.timings.identification_s = t.elapsed().as_secs_f64();
        // The rows whose tracker the loop set aside count as occluded from
        // here on (the raw stage above is the sessions as read).
        let tr = loop_result.tracker_outliers.without(&tr).unwrap_or(tr);
        self.warnings.extend(tracker_outlier_warning(
            train.path,
            &loop_result.tracker_outliers,
        ));
        let obs = PerSession {
            train: &tr[..],
            test: &te[..],
        };
        let identified = identified_errors(&loop_result.base, obs)?;
        list.push(
            "identified".into(),
            report::StageKind::Identified,
            identified,
        );
        let reference = self.reference(obs, &loop_rows.pick(obs.train), &nominal, &mut list)?;
        self.warnings
            .extend(unfitted_warning(train.path, &tr, &list.stages));
        self.warn_of_the_geometry(&loop_result.identification, train);

        // From here on the sessions are read at the strings' meeting point when
        // the loop found the tracked body's origin off it (the errors are then
        // those of the tracker's position predicted with its orientation).
        let marker = loop_result.structure.marker_body_mm;
        let tr = at_meeting_points_moved(tr, marker);
        let te = at_meeting_points_moved(te, marker);
        let obs = PerSession {
            train: &tr[..],
            test: &te[..],
        };
        let t = Instant::now();
        let rule = self.choose_rule(&loop_result, &loop_rows.pick(obs.train), &nominal, &regime);
        self.timings.rule_s = t.elapsed().as_secs_f64();
        let training_home = TrainingHome::of(train.session);
        let final_identified = self.final_identified(
            &mut loop_result,
            obs,
            &rule,
            &training_home,
            test.path,
            &mut list,
        )?;
        Ok(IdentifiedModel {
            timing,
            tr,
            te,
            loop_result,
            final_identified,
            list,
            regime,
            reference,
            rule: report::KinematicsReport::of(rule),
            tolerance,
            loop_rows,
            training_home,
        })
    }

    /// Each session's tracker in the geometry's unit (a test session in
    /// metres held out 670 mm, blamed on the priors): refused far off,
    /// warned of nearer.
    fn check_tracker_units(
        &mut self,
        [train, test]: [(&Path, &[Observation]); 2],
        raw: &RawPositions,
    ) -> Result<(), CalibrateError> {
        for ((path, rows), raw_rows) in [(train, &raw.train), (test, &raw.test)] {
            self.warnings.extend(check_tracker_scale(
                path,
                self.geometry_path,
                rows,
                raw_rows,
            )?);
        }
        Ok(())
    }

    /// What the loop's model `model` says of the geometry as written: a
    /// string's mechanical advantage or an anchor's coordinate that is
    /// another's or mistyped. The loop's model, whose parameters the
    /// report prints: the base identification's anchors take up the
    /// effects it lacks (a planar device's anchor 37 mm off in the base
    /// model and 12 in the printed one was named as a typo). A planar
    /// device's training session (`train`) tracked on a plane tilted from
    /// the tracker's.
    fn warn_of_the_geometry(&mut self, model: &Identification, train: NamedSession<'_>) {
        self.warnings.extend(radius_warnings(
            self.geometry_path,
            self.geometry,
            &model.laws,
        ));
        self.warnings.extend(anchor_departure_warnings(
            self.geometry_path,
            self.geometry,
            model,
        ));
        if self.geometry.layout.planar {
            self.warnings.extend(planar_session_warnings(
                train.path,
                &train.session.samples,
                model.residual_scale_mm,
            ));
        }
    }

    /// Both sessions, as recorded, paired anew once the loop's latency
    /// every string shares (`latency_s`) is out of `model`: the training
    /// session by its offset moved by the latency (the model was fitted
    /// on that pairing, [`align::shifted`]), the test session aligned
    /// again with the model (its own offset, which the alignment's quick
    /// model left off by its own amount). A static session as it is.
    fn clocks_without_the_shared_latency(
        &self,
        latency_s: f64,
        model: &Identification,
        [train, test]: [NamedSession<'_>; 2],
        nominal: &spidar_core::model::Frame<f64>,
        timing: &report::Timing,
    ) -> Result<(Vec<Observation>, Vec<Observation>, report::Timing), CalibrateError> {
        let (tr, te) = self.as_recorded(train, test, nominal);
        let (tr, train_timing) = match &timing.train {
            align::SessionTiming::Aligned(a) => {
                let (a, rows) = align::shifted(&tr, a, -latency_s);
                (rows, align::SessionTiming::Aligned(a))
            }
            first => (tr, first.clone()),
        };
        let (te, test_timing) = match &timing.test {
            align::SessionTiming::Aligned(first) => {
                let positions = placed_positions(model.kinematic_model(), &te);
                // The rate the first alignment took stays.
                let rate = if first.drift_ppm != 0.0 {
                    align::ClockRate::Known {
                        drift_ppm: first.drift_ppm,
                        drift_sd_ppm: first.drift_sd_ppm,
                    }
                } else {
                    align::ClockRate::Same
                };
                let (mut a, rows) =
                    align::align(&te, &positions, first.offset_s - latency_s, rate)?;
                a.first_offset_s = Some(first.offset_s);
                let a = align::SessionTiming::Aligned(a);
                check_alignment(test.path, &a)?;
                (rows, a)
            }
            first => (te, first.clone()),
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

    /// Both sessions' observations as recorded (their tracker as the
    /// rows pair it), but their rows set aside whole ([`session_observations`]).
    fn as_recorded(
        &self,
        train: NamedSession<'_>,
        test: NamedSession<'_>,
        nominal: &spidar_core::model::Frame<f64>,
    ) -> (Vec<Observation>, Vec<Observation>) {
        let skipped = [&self.train_info, &self.test_info].map(|info| info.rows_set_aside());
        session_observations(
            nominal,
            train.session,
            test.session,
            [&skipped[0], &skipped[1]],
            self.test_info.home.as_ref(),
        )
    }

    /// Stage 0: both sessions' observations, their tracker's clock aligned
    /// with the device's (its time into `alignment_s`); refuses a clock the
    /// motion could not align, warns of rows the alignment left unpaired.
    fn aligned_observations(
        &mut self,
        train: NamedSession<'_>,
        test: NamedSession<'_>,
        nominal: &spidar_core::model::Frame<f64>,
        nominal_laws: &[spidar_core::model::StringLaw; spidar_core::STRINGS],
    ) -> Result<Aligned, CalibrateError> {
        let (tr, te) = self.as_recorded(train, test, nominal);
        if self.cfg.clocks_paired {
            let timing = report::Timing {
                train: align::paired_timing(&tr),
                test: align::paired_timing(&te),
            };
            return Ok((tr, te, timing, None));
        }
        let t = Instant::now();
        let (tr, te, timing, raw_train) = align_clocks(
            (tr, train.path),
            (te, test.path),
            self.geometry,
            nominal,
            nominal_laws,
            self.cfg.clock_offset_s,
        )?;
        for (path, t) in [(train.path, &timing.train), (test.path, &timing.test)] {
            check_alignment(path, t)?;
        }
        self.timings.alignment_s = t.elapsed().as_secs_f64();
        self.warnings.extend(unpaired_rows_warnings(&timing));
        Ok((tr, te, timing, raw_train))
    }

    /// The plain least-squares reference, identified on the same rows as
    /// the base identification (`fit_rows`: the loop's), its figures on
    /// every row; its stage goes second in `list` (after `raw`).
    fn reference(
        &mut self,
        obs: PerSession<&[Observation]>,
        fit_rows: &[Observation],
        nominal: &spidar_core::model::Frame<f64>,
        list: &mut StageList,
    ) -> Result<ReferenceModel, CalibrateError> {
        let t = Instant::now();
        let reference = ReferenceModel::of(self.geometry, nominal, fit_rows, obs)?;
        self.timings.reference_s = t.elapsed().as_secs_f64();
        list.insert(
            1,
            reference::STAGE_NAME.into(),
            report::StageKind::Reference,
            reference.errors(obs, &reference.id.frame)?,
        );
        Ok(reference)
    }

    /// The kinematics' rule (chosen on the held-out folds) applied to the
    /// loop's model; the final identified model on both sessions, its effect
    /// stages in `list`, and the warning for the test rows whose tracker
    /// disagrees with it.
    fn final_identified(
        &mut self,
        loop_result: &mut LoopResult,
        obs: PerSession<&[Observation]>,
        rule: &RuleChoice,
        training_home: &TrainingHome,
        test_path: &Path,
        list: &mut StageList,
    ) -> Result<FinalIdentified, CalibrateError> {
        loop_result.identification = rule.apply(&loop_result.identification);
        let later = under_the_training_home(&loop_result.identification, training_home);
        let (final_identified, errors) =
            FinalIdentified::of(&loop_result.identification, &later, obs)?;
        self.warnings.extend(test_outlier_warning(
            test_path,
            &crate::model::diagnose::TrackerOutliers::of_session(
                &later,
                obs.test,
                loop_result.tracker_outliers.threshold_mm,
            ),
        ));
        list.stages.extend(effect_stages(loop_result, &errors));
        if !loop_result.stages.is_empty() {
            list.points
                .push(errors.points("identified with effects".into()));
        }
        Ok(final_identified)
    }

    /// The forward kinematics' rule for the final identified model, chosen
    /// on the held-out folds ([`crate::model::rule`]); every string alike,
    /// the rule that stays, with why not when the session is too small for
    /// them or they could not be fitted ([`crate::model::rule::unjudged`]).
    fn choose_rule(
        &self,
        loop_result: &LoopResult,
        train: &[Observation],
        nominal: &spidar_core::model::Frame<f64>,
        regime: &Regime,
    ) -> RuleChoice {
        use crate::model::rule::RuleFolds;
        // Below what the loop needs, the folds the anchors' tolerance is
        // chosen on: each holds out a tenth.
        let folds = if regime.full {
            RuleFolds::Judged
        } else {
            RuleFolds::SmallSession
        };
        let pb = spinner("choosing the kinematics' rule", self.cfg.quiet);
        let choice =
            crate::model::rule::choose(train, nominal, loop_result, &self.cfg.loop_config, folds)
                .map_err(|e| format!("the folds could not be fitted ({e})"));
        pb.finish_and_clear();
        let unjudged =
            |why: String| crate::model::rule::unjudged(&loop_result.identification, train, &why);
        match choice {
            Ok(Some(choice)) => choice,
            Ok(None) => {
                unjudged("the session is too small for held-out folds (no row to spare)".into())
            }
            Err(why) => unjudged(why),
        }
    }
}

/// `observations` read at the strings' meeting point
/// ([`at_meeting_points`](crate::data::observe::at_meeting_points)), moved
/// as they are without a marker offset (a copy of a long session is its
/// size again) and dropped once read anew.
fn at_meeting_points_moved(
    observations: Vec<Observation>,
    marker_body_mm: Option<[f64; 3]>,
) -> Vec<Observation> {
    if marker_body_mm.is_none() {
        return observations;
    }
    crate::data::observe::at_meeting_points(&observations, marker_body_mm).into_owned()
}
