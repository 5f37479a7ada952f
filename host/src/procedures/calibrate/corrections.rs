//! Stages 4-5 of a calibration: the residual NN and SVR on top of the final
//! identified model (Tukey's outlier removal, even thinning, the fit part and
//! the selection split), the choice of the final model on the selection
//! split, and the chosen correction refitted.

use std::time::Instant;

use spidar_core::correction::CorrectionModel;

use crate::data::observe::Observation;
use crate::data::stats::ErrorStats;
use crate::model::compile::TickRoom;
use crate::model::diagnose::tail_noise;
use crate::model::identify::{value_with_sd, Identification, ParameterEstimate};
use crate::model::learn::nn::{self, NnConfig};
use crate::model::learn::outliers;
use crate::model::learn::search;
use crate::model::learn::svr::{self, SvrConfig};
use crate::model::learn::thin::{thin_evenly, Thinning};
use crate::model::learn::{split_indices, OutputMode};

use super::evaluate::{point_error_list, subset, tracked_pairs, PerSession};
use super::{
    learn, report, spinner, CalibrateConfig, CalibrateError, PairSet, Run, MIN_SELECTION_POINTS,
};

/// The residual learners' data: the final identified model's tracked pairs,
/// Tukey's box plot on the training ones, the kept training pairs thinned
/// evenly through the volume ([`CalibrateConfig::max_learning_points`]),
/// and the thinned pairs split into a fit part and the selection split.
pub(super) struct ResidualData {
    outliers: outliers::OutlierReport,
    /// Kept training pairs and all tracked test pairs.
    pub(super) pairs: PairSet,
    /// Which kept training pairs the corrections learn from.
    thinning: Thinning,
    /// The thinned pairs: what the chosen correction is refitted on.
    x_learn: Vec<[f64; 3]>,
    t_learn: Vec<[f64; 3]>,
    x_fit: Vec<[f64; 3]>,
    t_fit: Vec<[f64; 3]>,
    x_sel: Vec<[f64; 3]>,
    t_sel: Vec<[f64; 3]>,
    /// The training session's row of each selection point.
    sel_rows: Vec<usize>,
}

impl ResidualData {
    /// The points of the selection split.
    pub(super) fn selection_points(&self) -> usize {
        self.x_sel.len()
    }

    pub(super) fn of(
        obs: PerSession<&[Observation]>,
        positions: PerSession<&[[f64; 3]]>,
        cfg: &CalibrateConfig,
    ) -> Result<ResidualData, CalibrateError> {
        let (x_all, t_all) = tracked_pairs(obs.train, positions.train);
        let outl = outliers::tukey(&x_all, &t_all).map_err(learn("outliers (Tukey box plot)"))?;
        let (x_kept, t_kept) = outliers::select(&outl, &x_all, &t_all);
        let (xt_all, tt_all) = tracked_pairs(obs.test, positions.test);
        let thinning = thin_evenly(&x_kept, cfg.max_learning_points);
        let x_learn = subset(&x_kept, &thinning.indices);
        let t_learn = subset(&t_kept, &thinning.indices);
        let (fit_idx, sel_idx) = split_indices(x_learn.len(), cfg.selection_fraction, cfg.seed);
        let (x_fit, t_fit) = (subset(&x_learn, &fit_idx), subset(&t_learn, &fit_idx));
        let (x_sel, t_sel) = (subset(&x_learn, &sel_idx), subset(&t_learn, &sel_idx));
        let tracked_rows: Vec<usize> = (0..obs.train.len())
            .filter(|&k| obs.train[k].tracker.is_some())
            .collect();
        let sel_rows = sel_idx
            .iter()
            .map(|&k| tracked_rows[outl.kept[thinning.indices[k]]])
            .collect();
        Ok(ResidualData {
            outliers: outl,
            pairs: PairSet {
                train_inputs: x_kept,
                train_targets: t_kept,
                test_inputs: xt_all,
                test_targets: tt_all,
            },
            thinning,
            x_learn,
            t_learn,
            x_fit,
            t_fit,
            x_sel,
            t_sel,
            sel_rows,
        })
    }
}

/// How large the learned corrections may be: what the device's tick leaves
/// beside the identified model ([`TickRoom`]), and at most
/// [`CalibrateConfig::max_support_vectors`] support vectors.
#[derive(Clone, Copy, Debug)]
pub(super) struct CorrectionLimits {
    /// Most points the SVR learns from (its support vectors are among them).
    pub(super) support_vectors: usize,
    /// Largest hidden size the NN sweep tries.
    pub(super) neurons: usize,
    pub(super) room: Option<TickRoom>,
}

impl CorrectionLimits {
    /// The limits beside the model `room` describes (`None`: a model that
    /// does not compile, which `spidar compile` will name; only the
    /// configured cap then).
    pub(super) fn of(room: Option<TickRoom>, cfg: &CalibrateConfig) -> CorrectionLimits {
        CorrectionLimits {
            support_vectors: room.map_or(cfg.max_support_vectors, |r| {
                cfg.max_support_vectors.min(r.support_vectors as usize)
            }),
            neurons: room.map_or(usize::MAX, |r| usize::from(r.neurons)),
            room,
        }
    }

    /// Why no correction can be learned beside this model: the tick has no
    /// room for the smallest NN of the sweep or for an SVR.
    pub(super) fn no_room(&self, cfg: &CalibrateConfig) -> Option<String> {
        let room = self.room?;
        let smallest = cfg.nn.sizes.iter().copied().min().unwrap_or(1);
        let fewest = search::MIN_SEARCH_POINTS;
        (smallest > self.neurons || self.support_vectors < fewest).then(|| {
            format!(
                "identification only: the model's tick is estimated at {} of the device's {} \
                 instructions, which leaves room for {} hidden neurons and {} support vectors, \
                 too few for a correction (the smallest NN has {smallest} neurons, an SVR needs \
                 {fewest} points)",
                room.model_instructions, room.budget, room.neurons, room.support_vectors
            )
        })
    }
}

/// The points of `inputs` (and their `targets`) the SVR learns from: at
/// most `limits.support_vectors`, spread evenly through the volume, so that
/// its support vectors (a subset of them) fit the device's tick.
fn svr_points(
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    limits: &CorrectionLimits,
) -> (Thinning, Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let thinning = thin_evenly(inputs, limits.support_vectors);
    let x = subset(inputs, &thinning.indices);
    let t = subset(targets, &thinning.indices);
    (thinning, x, t)
}

/// The residual NN and SVR, searched and trained on the fit part within
/// the [`CorrectionLimits`] (the SVR on at most their support vectors of
/// its points, the NN's sweep up to their neurons).
pub(super) struct Learned {
    sweep: search::SweepResult,
    svr_search: search::SvrSearchResult,
    /// The fit part's points the SVR learned from.
    svr_thinning: Thinning,
    limits: CorrectionLimits,
    pub(super) nn: CorrectionModel,
    pub(super) svr: CorrectionModel,
}

/// Stage 4: the NN hidden-size sweep and the SVR search on the fit part
/// (their times into `timings`), within `limits` (which
/// [`CorrectionLimits::no_room`] found room in).
pub(super) fn train_corrections(
    data: &ResidualData,
    cfg: &CalibrateConfig,
    limits: CorrectionLimits,
    timings: &mut report::Timings,
) -> Result<Learned, CalibrateError> {
    let t = Instant::now();
    let mut nn_cfg = cfg.nn.clone();
    nn_cfg.sizes.retain(|&h| h <= limits.neurons);
    let sweep = search::nn_sweep(&data.x_fit, &data.t_fit, &nn_cfg)
        .map_err(learn("NN hidden-size sweep"))?;
    timings.nn_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (svr_thinning, x_svr, t_svr) = svr_points(&data.x_fit, &data.t_fit, &limits);
    let svr_search = search::svr_search(&x_svr, &t_svr, &cfg.svr).map_err(learn("SVR search"))?;
    timings.svr_s = t.elapsed().as_secs_f64();
    let nn = CorrectionModel::Nn(sweep.fit.model.clone());
    let svr = CorrectionModel::Svr(svr_search.fit.model.clone());
    Ok(Learned {
        sweep,
        svr_search,
        svr_thinning,
        limits,
        nn,
        svr,
    })
}

/// What the selection split said of the identified model and the two
/// corrections, and the choice it made.
pub(super) struct Judgement {
    identified: ErrorStats,
    nn: ErrorStats,
    svr: ErrorStats,
    /// The plain least-squares reference on the same points.
    reference: ErrorStats,
    /// Noise of the identified model's p95 and max on the selection split.
    noise_p95: f64,
    noise_max: f64,
    /// The selection split has enough points to choose a correction.
    enough_to_choose: bool,
    pub(super) choice: report::Choice,
    reason: String,
}

impl Judgement {
    /// The chosen candidate's statistics on the selection split.
    fn chosen_stats(&self) -> &ErrorStats {
        match self.choice {
            report::Choice::Identified => &self.identified,
            report::Choice::Nn => &self.nn,
            report::Choice::Svr => &self.svr,
            report::Choice::Reference => &self.reference,
        }
    }
}

/// Stage 5: the choice, on the selection split.
fn judge_on_selection_split(
    data: &ResidualData,
    learned: &Learned,
    cfg: &CalibrateConfig,
    not_held: &[(report::Choice, String)],
) -> Judgement {
    let (x_sel, t_sel) = (&data.x_sel, &data.t_sel);
    let e_id = point_error_list(|p| p, x_sel, t_sel);
    let s_id = ErrorStats::of(&e_id);
    let s_nn = ErrorStats::of(&point_error_list(|p| learned.nn.evaluate(p), x_sel, t_sel));
    let s_svr = ErrorStats::of(&point_error_list(|p| learned.svr.evaluate(p), x_sel, t_sel));
    // Noise of the identified model's p95 and max on the selection split.
    let (noise_p95, noise_max) = tail_noise(&e_id);
    let enough_to_choose = x_sel.len() >= MIN_SELECTION_POINTS;
    // A correction is eligible when it lowers the mean by the configured gain
    // without raising the p95 or the max beyond their noise; the eligible one
    // with the lower mean is chosen.
    let verdict = |choice: report::Choice, c: &ErrorStats| -> Result<(), String> {
        let name = choice.name();
        if let Some((_, why)) = not_held.iter().find(|held| held.0 == choice) {
            Err(format!(
                "{name}'s refit does not fit the device's fixed point ({why})"
            ))
        } else if !c.mean_mm.is_finite()
            || c.mean_mm >= s_id.mean_mm * (1.0 - cfg.min_correction_gain)
        {
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
        (
            report::Choice::Nn,
            &s_nn,
            verdict(report::Choice::Nn, &s_nn),
        ),
        (
            report::Choice::Svr,
            &s_svr,
            verdict(report::Choice::Svr, &s_svr),
        ),
    ];
    let best = judged
        .iter()
        .filter(|j| j.2.is_ok())
        .min_by(|a, b| a.1.mean_mm.total_cmp(&b.1.mean_mm));
    let refused: Vec<String> = judged.iter().filter_map(|j| j.2.clone().err()).collect();
    let (choice, reason) = match best {
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
    Judgement {
        identified: s_id,
        nn: s_nn,
        svr: s_svr,
        reference: ErrorStats::of(&[]),
        noise_p95,
        noise_max,
        enough_to_choose,
        choice,
        reason,
    }
}

/// The judgement of a session too small for the learners: the identified
/// model, for `reason`.
pub(super) fn identification_only(data: &ResidualData, reason: String) -> Judgement {
    let e_id = point_error_list(|p| p, &data.x_sel, &data.t_sel);
    let (noise_p95, noise_max) = tail_noise(&e_id);
    Judgement {
        identified: ErrorStats::of(&e_id),
        nn: ErrorStats::of(&[]),
        svr: ErrorStats::of(&[]),
        reference: ErrorStats::of(&[]),
        noise_p95,
        noise_max,
        enough_to_choose: false,
        choice: report::Choice::Identified,
        reason,
    }
}

/// Means closer than this (mm) are one figure: the report gives them to
/// the micrometre, and a selection split of tens of points under a tracker
/// of tenths of a millimetre cannot order them. The selection holds to the
/// reference by it, and the warnings that compare held-out means with the
/// reference's use it too ([`shows_above`]): a warning then names a
/// difference the report can show.
pub const SELECTION_TIE_MM: f64 = 0.0005;

/// Whether `mean_mm` is above `other_mm` as the report shows them: by more
/// than [`SELECTION_TIE_MM`]. A figure not finite is above nothing.
pub(super) fn shows_above(mean_mm: f64, other_mm: f64) -> bool {
    mean_mm > other_mm + SELECTION_TIE_MM
}

/// Holds the choice to the plain least-squares reference on the selection
/// split: the reference's statistics on the same rows go into `judgement`
/// (`reference_rows`: its error on each training row), and when its mean is
/// below the chosen candidate's by more than [`SELECTION_TIE_MM`] (as the
/// report gives them, the reference lower), the reference is the final
/// model (no correction). True then. At a tie the chosen model stays: with
/// the kinematics' rule the reference's, the two differ by fractions of a
/// micrometre on the split, and which is lower was a coin's toss between
/// models that hold out 0.50 and 0.92 mm (decision record 0074).
pub(super) fn hold_to_reference(
    judgement: &mut Judgement,
    final_corr: &mut CorrectionModel,
    data: &ResidualData,
    reference_rows: &[Option<f64>],
    reference: &Identification,
) -> bool {
    judgement.reference = ErrorStats::of(
        &data
            .sel_rows
            .iter()
            .filter_map(|&r| reference_rows[r])
            .collect::<Vec<f64>>(),
    );
    let chosen_mean = judgement.chosen_stats().mean_mm;
    let fall_back = shows_above(chosen_mean, judgement.reference.mean_mm);
    if let Some(why) = undetermined_reference(reference).filter(|_| fall_back) {
        judgement.reason = format!(
            "{}; the plain least-squares reference, lower on the split ({:.3} mm), is not a \
             candidate: {why}",
            judgement.reason, judgement.reference.mean_mm
        );
        return false;
    }
    if fall_back {
        judgement.reason = format!(
            "the plain least-squares reference: {} has {:.3} mm on the selection split, the \
             reference {:.3} mm (before: {})",
            judgement.choice.name(),
            chosen_mean,
            judgement.reference.mean_mm,
            judgement.reason
        );
        judgement.choice = report::Choice::Reference;
        *final_corr = CorrectionModel::None;
    }
    fall_back
}

/// Why the plain least-squares reference cannot be the final model, when
/// the training rows do not determine it: some of its parameters are
/// undetermined (an infinite or prior-sized sd), left where the fit began
/// or wherever the solver stopped. Such a fit is no floor: judged on the
/// selection split it was fitted on, it fits those rows and nothing beyond
/// them (a 12-row stream of 0.11 s: every parameter undetermined, 0.45 mm
/// on its split and 91 mm held out, against the identified model's 9.0).
/// `None` when every parameter is determined.
pub(super) fn undetermined_reference(reference: &Identification) -> Option<String> {
    let undetermined: Vec<&str> = reference
        .parameters
        .iter()
        .filter(|p| !p.determined)
        .map(|p| p.name.as_str())
        .collect();
    let first = undetermined.first()?;
    Some(format!(
        "the training rows do not determine {} of its {} parameters ({first}{})",
        undetermined.len(),
        reference.parameters.len(),
        if undetermined.len() > 1 { ", ..." } else { "" }
    ))
}

/// How many of the loosely determined parameters a warning names.
const LOOSE_PARAMETERS_NAMED: usize = 3;

/// A warning when the plain least-squares reference is the final model and
/// its training rows determine some of its parameters less well than the
/// geometry does: each whose sd from the data is above the sd the
/// identification's prior holds the same parameter of `identified` to (the
/// anchors' tolerance, the home's, the tracker frame's), the widest against
/// it first. Away from the training poses such a model places the
/// end-effector on values the rows hardly hold (poses on a printer's bed
/// leave its anchors' heights to hundreds of mm, decision record 0086),
/// which the selection split, whose rows lie among the training poses,
/// cannot show. `None` when every parameter with a prior is determined
/// within it.
pub(super) fn loose_reference_warning(
    reference: &Identification,
    identified: &Identification,
) -> Option<String> {
    let mut loose: Vec<(&ParameterEstimate, f64)> = reference
        .parameters
        .iter()
        .filter_map(|p| {
            let prior = identified
                .parameters
                .iter()
                .find(|q| q.name == p.name)?
                .prior_sd?;
            (p.sd > prior || p.sd.is_nan()).then_some((p, prior))
        })
        .collect();
    if loose.is_empty() {
        return None;
    }
    loose.sort_by(|a, b| (b.0.sd / b.1).total_cmp(&(a.0.sd / a.1)));
    let named: Vec<String> = loose
        .iter()
        .take(LOOSE_PARAMETERS_NAMED)
        .map(|(p, prior)| {
            let estimate = value_with_sd(p.value, p.sd).unwrap_or_else(|| format!("{}", p.value));
            format!(
                "{} {estimate} {unit} (the geometry: ± {prior} {unit})",
                p.name,
                unit = p.unit
            )
        })
        .collect();
    Some(format!(
        "the final model is the plain least-squares reference, and its training rows determine \
         {} of its parameters less well than the geometry does: {}{}; away from the training \
         poses it places the end-effector on values the rows hardly hold (the identified model \
         holds them to the geometry), which the selection split, among the training poses, \
         cannot show: poses spread over the volume the device works in determine them",
        loose.len(),
        named.join(", "),
        if loose.len() > LOOSE_PARAMETERS_NAMED {
            ", ..."
        } else {
            ""
        }
    ))
}

/// Why the learned corrections were reported but not chosen, when the
/// selection split was too small to choose one: it names the final model
/// as `judgement` has it after [`hold_to_reference`] (the string model, or
/// the plain least-squares reference when that beat it on the split).
/// `None` when the split (of `selection_points`) was large enough to choose.
pub(super) fn unchosen_corrections_warning(
    judgement: &Judgement,
    selection_points: usize,
) -> Option<String> {
    if judgement.enough_to_choose {
        return None;
    }
    let final_model = match judgement.choice {
        report::Choice::Reference => {
            "the plain least-squares reference, which beat the string model on that split"
        }
        report::Choice::Identified => "the string model without a learned correction",
        report::Choice::Nn => "the NN correction",
        report::Choice::Svr => "the SVR correction",
    };
    Some(format!(
        "the NN and SVR corrections are reported but not chosen: the selection split of the \
         training session has {selection_points} points, at least {MIN_SELECTION_POINTS} are \
         needed to tell a correction from noise (the final model is {final_model}, `final ({})`; \
         collect a larger training session to use a learned correction)",
        judgement.choice.name()
    ))
}

/// The chosen correction refitted on all the training points it learns
/// from (the kept ones, thinned when there are more than
/// [`CalibrateConfig::max_learning_points`]) with the hyperparameters the
/// search found (none for the identified model); the SVR on at most the
/// [`CorrectionLimits`]' support vectors of them.
fn refit_chosen(
    choice: report::Choice,
    data: &ResidualData,
    learned: &Learned,
    cfg: &CalibrateConfig,
) -> Result<CorrectionModel, CalibrateError> {
    let (x_kept, t_kept) = (&data.x_learn, &data.t_learn);
    let pb = spinner("refitting the chosen correction", cfg.quiet);
    let final_corr = match choice {
        report::Choice::Identified | report::Choice::Reference => CorrectionModel::None,
        report::Choice::Nn => {
            let fit = nn::train(
                x_kept,
                t_kept,
                &NnConfig {
                    hidden: learned.sweep.best_hidden,
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
            let (_, x_svr, t_svr) = svr_points(x_kept, t_kept, &learned.limits);
            let fit = svr::train(
                &x_svr,
                &t_svr,
                &SvrConfig {
                    params: learned.svr_search.best,
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
    Ok(final_corr)
}

/// The report's account of the choice of the final model.
pub(super) fn selection_report(
    final_name: String,
    judgement: Judgement,
    final_corr: &CorrectionModel,
    data: &ResidualData,
    cfg: &CalibrateConfig,
) -> report::Selection {
    let (s_id, s_nn, s_svr, s_ref) = (
        &judgement.identified,
        &judgement.nn,
        &judgement.svr,
        &judgement.reference,
    );
    report::Selection {
        stage: final_name,
        choice: judgement.choice,
        correction: match final_corr {
            CorrectionModel::None => "none",
            CorrectionModel::Nn(_) => "nn",
            CorrectionModel::Svr(_) => "svr",
        },
        selection_points: data.x_sel.len(),
        fit_points: data.x_fit.len(),
        min_correction_gain: cfg.min_correction_gain,
        validation_mean_mm: report::Candidates {
            identified: s_id.mean_mm,
            nn: s_nn.mean_mm,
            svr: s_svr.mean_mm,
            reference: s_ref.mean_mm,
        },
        validation_p95_mm: report::Candidates {
            identified: s_id.p95_mm,
            nn: s_nn.p95_mm,
            svr: s_svr.p95_mm,
            reference: s_ref.p95_mm,
        },
        validation_max_mm: report::Candidates {
            identified: s_id.max_mm,
            nn: s_nn.max_mm,
            svr: s_svr.max_mm,
            reference: s_ref.max_mm,
        },
        noise_p95_mm: judgement.noise_p95,
        noise_max_mm: judgement.noise_max,
        reason: judgement.reason,
        final_support_vectors: match final_corr {
            CorrectionModel::Svr(m) => Some(m.support.len()),
            _ => None,
        },
        final_hidden: match final_corr {
            CorrectionModel::Nn(m) => Some(m.w1.len()),
            _ => None,
        },
        device_tick: None,
    }
}

/// The report's account of the residual corrections.
pub(super) fn residual_report(data: &ResidualData, learned: &Learned) -> report::Corrections {
    report::Corrections {
        mode: "residual",
        input: "final identified model, room position (mm)",
        outliers: report::Outliers::of(
            &data.outliers,
            "final identified model vs tracker, training session",
        ),
        learning_points: report::LearningPoints::of(&data.thinning, data.pairs.train_inputs.len()),
        nn: report::NnReport::of(&learned.sweep),
        svr: report::SvrReport::of(&learned.svr_search),
        svr_learning_points: report::LearningPoints::of(&learned.svr_thinning, data.x_fit.len()),
    }
}

/// The identification's own warnings, and the learners' time limits that cut
/// their search.
pub(super) fn learner_warnings(
    fin: &crate::model::identify::Identification,
    learned: Option<&Learned>,
    cfg: &CalibrateConfig,
) -> Vec<String> {
    let mut warnings = Vec::new();
    for w in &fin.warnings {
        warnings.push(format!("identification: {w}"));
    }
    let Some(learned) = learned else {
        return warnings;
    };
    let (sweep, svr_search) = (&learned.sweep, &learned.svr_search);
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
    warnings
}

/// The choice `judge` makes and the correction `refit` makes of it, the
/// device holding it: a refit whose fixed-point form does not compile
/// (every restart of its training beyond the blob's ranges) is refused,
/// and the choice made again without it (`judge` is given the choices
/// refused and why). The string model alone always compiles.
fn choice_the_device_holds(
    judge: impl Fn(&[(report::Choice, String)]) -> Judgement,
    mut refit: impl FnMut(report::Choice) -> Result<CorrectionModel, CalibrateError>,
) -> Result<(Judgement, CorrectionModel), CalibrateError> {
    let mut not_held: Vec<(report::Choice, String)> = Vec::new();
    loop {
        let judgement = judge(&not_held);
        let correction = refit(judgement.choice)?;
        match correction.compile() {
            Err(e) if !not_held.iter().any(|held| held.0 == judgement.choice) => {
                not_held.push((judgement.choice, e.to_string()));
            }
            _ => return Ok((judgement, correction)),
        }
    }
}

impl Run<'_> {
    /// Stage 5: the choice on the selection split, and the chosen correction
    /// refitted (its time into `selection_s`).
    pub(super) fn choose_final_model(
        &mut self,
        data: &ResidualData,
        learned: &Learned,
    ) -> Result<(Judgement, CorrectionModel), CalibrateError> {
        let t = Instant::now();
        let chosen = choice_the_device_holds(
            |not_held| judge_on_selection_split(data, learned, &self.cfg, not_held),
            |choice| refit_chosen(choice, data, learned, &self.cfg),
        );
        self.timings.selection_s = t.elapsed().as_secs_f64();
        chosen
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A judgement on a selection split too small to choose a correction,
    /// whose final model is `choice`.
    fn too_small(choice: report::Choice) -> Judgement {
        Judgement {
            identified: ErrorStats::of(&[1.0, 2.0]),
            nn: ErrorStats::of(&[1.0, 2.0]),
            svr: ErrorStats::of(&[1.0, 2.0]),
            reference: ErrorStats::of(&[0.5, 1.0]),
            noise_p95: 0.1,
            noise_max: 0.1,
            enough_to_choose: false,
            choice,
            reason: String::new(),
        }
    }

    /// The warning that the learned corrections were not chosen names the
    /// final model the choice ended with: the plain least-squares reference
    /// when it beat the string model on the split (a survey's run said "the
    /// final model is the identified one" under a table whose final stage
    /// was the reference), and nothing when the split could choose.
    #[test]
    fn the_unchosen_corrections_warning_names_the_final_model() {
        let w = unchosen_corrections_warning(&too_small(report::Choice::Reference), 3).unwrap();
        assert!(
            w.contains("has 3 points")
                && w.contains("the final model is the plain least-squares reference")
                && w.contains("`final (plain least squares)`")
                && !w.contains("identified one"),
            "{w}"
        );
        let w = unchosen_corrections_warning(&too_small(report::Choice::Identified), 3).unwrap();
        assert!(
            w.contains("the final model is the string model without a learned correction")
                && w.contains("`final (string model)`"),
            "{w}"
        );
        let mut enough = too_small(report::Choice::Identified);
        enough.enough_to_choose = true;
        assert_eq!(unchosen_corrections_warning(&enough, 40), None);
    }

    /// A refit the device cannot hold (an NN whose first-layer bias, 20,
    /// is beyond Q4.27's +-16) is refused and the choice made again
    /// without it: the SVR when it is next, the string model when nothing
    /// else is left.
    #[test]
    fn a_refit_the_device_cannot_hold_is_not_the_final_model() {
        use spidar_core::correction::{NnModel, OutputMode, Standardization};
        let unit = Standardization {
            mean: [0.0; 3],
            std: [100.0; 3],
        };
        let nn = |bias: f64| {
            CorrectionModel::Nn(NnModel {
                input: unit,
                output: Standardization {
                    mean: [0.0; 3],
                    std: [1.0; 3],
                },
                w1: vec![[1.0, 0.0, 0.0]],
                b1: vec![bias],
                w2: [vec![0.1], vec![0.0], vec![0.0]],
                b2: [0.0; 3],
                mode: OutputMode::Residual,
            })
        };
        assert!(nn(20.0).compile().is_err() && nn(2.0).compile().is_ok());
        for (order, expected) in [
            (
                [
                    report::Choice::Nn,
                    report::Choice::Svr,
                    report::Choice::Identified,
                ],
                report::Choice::Svr,
            ),
            (
                [
                    report::Choice::Nn,
                    report::Choice::Identified,
                    report::Choice::Svr,
                ],
                report::Choice::Identified,
            ),
        ] {
            let mut refits = Vec::new();
            let (judgement, correction) = choice_the_device_holds(
                |not_held| {
                    let next = order
                        .iter()
                        .find(|c| !not_held.iter().any(|h| h.0 == **c))
                        .copied()
                        .unwrap();
                    if next != report::Choice::Nn {
                        assert!(not_held[0].1.contains("b1"), "{not_held:?}");
                    }
                    too_small(next)
                },
                |choice| {
                    refits.push(choice);
                    Ok(match choice {
                        report::Choice::Nn => nn(20.0),
                        report::Choice::Svr => nn(2.0),
                        _ => CorrectionModel::None,
                    })
                },
            )
            .unwrap();
            assert_eq!(judgement.choice, expected);
            assert_eq!(refits, [report::Choice::Nn, expected]);
            assert!(correction.compile().is_ok());
        }
    }

    fn room(model_instructions: u32) -> TickRoom {
        TickRoom {
            model_instructions,
            budget: spidar_core::tick_cost::TICK_BUDGET,
            support_vectors: spidar_core::tick_cost::support_vectors_left(model_instructions),
            neurons: spidar_core::tick_cost::neurons_left(model_instructions),
        }
    }

    /// The learned corrections are as large as the tick leaves them beside
    /// the model, and not learned at all where it leaves too little: the
    /// reason says how much there was.
    #[test]
    fn corrections_are_sized_to_the_room_the_tick_leaves() {
        let cfg = CalibrateConfig::full();
        let roomy = CorrectionLimits::of(Some(room(20_000)), &cfg);
        assert_eq!(roomy.support_vectors, cfg.max_support_vectors);
        assert_eq!(roomy.neurons, 400);
        assert_eq!(roomy.no_room(&cfg), None);
        let tight = CorrectionLimits::of(Some(room(50_000)), &cfg);
        assert_eq!(tight.support_vectors, 200);
        assert_eq!(tight.neurons, 75);
        assert_eq!(tight.no_room(&cfg), None);
        // Room for two neurons: the sweep's smallest has three.
        let full = CorrectionLimits::of(Some(room(54_700)), &cfg);
        let why = full.no_room(&cfg).expect("no room");
        assert!(
            why.contains("54700 of the device's 55000")
                && why.contains("room for 1 hidden neurons"),
            "{why}"
        );
        // A model that does not compile: only the configured cap.
        let unknown = CorrectionLimits::of(None, &cfg);
        assert_eq!(unknown.support_vectors, cfg.max_support_vectors);
        assert_eq!(unknown.no_room(&cfg), None);
    }
}
