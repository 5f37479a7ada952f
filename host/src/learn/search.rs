//! Model selection: the hidden-size sweep of the paper's figure 13 and the SVR
//! hyperparameter search (C, epsilon, gamma), both parallel (rayon), seeded
//! and bounded in time.
//!
//! Budget: a full calibration (identification + NN + SVR) must fit in 10 s on
//! 2 cores. An LM epoch at H = 20 costs ~5 ms here, so the sweep trains every
//! size for a few tens of epochs only (enough to rank sizes: LM converges
//! fast at first), then trains the chosen size longer, warm-started from the
//! sweep's network plus fresh restarts.

use std::time::{Duration, Instant};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::nn::{self, best_run, check_lm, Init, LmConfig, NnFit, Prepared, StopReason};
use super::svr::{
    self, assemble, check_params, solve_axes, KernelMatrix, SolverConfig, SvrFit, SvrParams,
};
use super::{
    check_range, progress, split_indices, standardize, validate_pairs, Deadline, ErrorStats,
    LearnError, OutputMode, Rng,
};

/// Settings of the hidden-size sweep and the final training.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepConfig {
    /// Hidden sizes to try (the paper: 3..=24).
    pub sizes: Vec<usize>,
    /// LM settings for each sweep run (few epochs).
    pub sweep_lm: LmConfig,
    pub sweep_restarts: usize,
    /// LM settings for the final training of the chosen size.
    pub final_lm: LmConfig,
    /// Final candidates: the sweep winner continued, plus `final_restarts - 1`
    /// fresh initializations.
    pub final_restarts: usize,
    pub mode: OutputMode,
    pub validation_fraction: f64,
    pub seed: u64,
    pub sweep_time_limit: Option<Duration>,
    pub final_time_limit: Option<Duration>,
    pub quiet: bool,
    /// The progress bars say "black-box" (the paper's procedure, not the
    /// residual correction).
    #[serde(default)]
    pub blackbox: bool,
}

impl Default for SweepConfig {
    fn default() -> Self {
        SweepConfig {
            sizes: (3..=24).collect(),
            sweep_lm: LmConfig {
                max_epochs: 40,
                ..LmConfig::default()
            },
            sweep_restarts: 1,
            final_lm: LmConfig {
                max_epochs: 200,
                ..LmConfig::default()
            },
            final_restarts: 2,
            mode: OutputMode::Absolute,
            validation_fraction: 0.15,
            seed: 1,
            sweep_time_limit: None,
            final_time_limit: None,
            quiet: true,
            blackbox: false,
        }
    }
}

/// One point of the figure-13 curve.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepPoint {
    pub hidden: usize,
    /// Mean position error on the validation split, mm (best restart).
    pub validation_mean_mm: f64,
    pub train_mean_mm: f64,
    pub epochs: usize,
    pub stop: StopReason,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepResult {
    /// Hidden size -> validation mean error, ascending size. Sizes whose runs
    /// the time limit cut before any epoch are missing.
    pub curve: Vec<SweepPoint>,
    pub best_hidden: usize,
    /// The final network (of `best_hidden` neurons).
    pub fit: NnFit,
    pub sweep_seconds: f64,
    pub final_seconds: f64,
}

/// Train every hidden size briefly, pick the lowest validation error, train
/// that size longer.
pub fn nn_sweep(
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    cfg: &SweepConfig,
) -> Result<SweepResult, LearnError> {
    if cfg.sizes.is_empty() {
        return Err(LearnError::InvalidParameter {
            name: "sizes",
            value: 0.0,
            expected: "at least one hidden size",
        });
    }
    for &h in &cfg.sizes {
        check_range("sizes", h as f64, 1.0, 4096.0, "1..=4096 neurons")?;
    }
    check_lm(&cfg.sweep_lm)?;
    check_lm(&cfg.final_lm)?;
    check_range(
        "sweep_restarts",
        cfg.sweep_restarts as f64,
        1.0,
        1e6,
        ">= 1",
    )?;
    check_range(
        "final_restarts",
        cfg.final_restarts as f64,
        1.0,
        1e6,
        ">= 1",
    )?;
    check_range(
        "validation_fraction",
        cfg.validation_fraction,
        0.0,
        0.9,
        "0 <= fraction <= 0.9",
    )?;
    let t0 = Instant::now();
    let data = Prepared::new(inputs, targets, cfg.mode, cfg.validation_fraction, cfg.seed)?;

    // Largest networks first: the longest jobs start early, which balances
    // the two cores better. Results are keyed, so order does not matter.
    let mut jobs: Vec<(usize, usize)> = cfg
        .sizes
        .iter()
        .flat_map(|&h| (0..cfg.sweep_restarts).map(move |r| (h, r)))
        .collect();
    jobs.sort_by_key(|&(h, r)| (std::cmp::Reverse(h), r));
    let deadline = Deadline::after(cfg.sweep_time_limit);
    let pb = progress(
        jobs.len() as u64,
        if cfg.blackbox {
            "black-box NN sweep"
        } else {
            "NN sweep"
        },
        cfg.quiet,
    );
    let runs: Vec<(usize, usize, nn::Run)> = jobs
        .par_iter()
        .map(|&(h, r)| {
            let init = Init::Random(Rng::derive(cfg.seed, (h as u64) << 32 | r as u64));
            let run = nn::train_run(&data, h, init, &cfg.sweep_lm, deadline, &|| {});
            pb.inc(1);
            (h, r, run)
        })
        .collect();
    pb.finish_and_clear();

    let mut sizes = cfg.sizes.clone();
    sizes.sort_unstable();
    sizes.dedup();
    let mut curve = Vec::new();
    let mut best: Option<(f64, nn::Run)> = None;
    for &h in &sizes {
        let mut of_h: Vec<(usize, nn::Run)> = runs
            .iter()
            .filter(|(hh, _, run)| *hh == h && run.epochs > 0)
            .map(|(_, r, run)| (*r, run.clone()))
            .collect();
        of_h.sort_by_key(|(r, _)| *r);
        let Some(run) = best_run(of_h.into_iter().map(|(_, run)| run).collect()) else {
            continue;
        };
        let model = data.model(h, &run.w);
        let (train, val) = data.stats(&model);
        // Without a validation split the training error ranks the sizes.
        let score = if val.n > 0 { val.mean } else { train.mean };
        curve.push(SweepPoint {
            hidden: h,
            validation_mean_mm: val.mean,
            train_mean_mm: train.mean,
            epochs: run.epochs,
            stop: run.stop,
        });
        if best.as_ref().is_none_or(|(s, _)| score < *s) {
            best = Some((score, run));
        }
    }
    let sweep_seconds = t0.elapsed().as_secs_f64();
    let Some((_, winner)) = best else {
        return Err(LearnError::OutOfTime {
            what: "NN hidden-size sweep",
            budget_s: cfg.sweep_time_limit.map_or(0.0, |d| d.as_secs_f64()),
        });
    };
    let best_hidden = winner.h;

    let t1 = Instant::now();
    let deadline = Deadline::after(cfg.final_time_limit);
    let pb = progress(
        (cfg.final_restarts * cfg.final_lm.max_epochs) as u64,
        if cfg.blackbox {
            "black-box NN final"
        } else {
            "NN final"
        },
        cfg.quiet,
    );
    let finals: Vec<nn::Run> = (0..cfg.final_restarts)
        .into_par_iter()
        .map(|r| {
            let init = if r == 0 {
                Init::Warm(winner.w.clone())
            } else {
                // Streams distinct from the sweep's (h << 32 | r).
                Init::Random(Rng::derive(
                    cfg.seed ^ 0xF1A1,
                    (best_hidden as u64) << 32 | r as u64,
                ))
            };
            nn::train_run(&data, best_hidden, init, &cfg.final_lm, deadline, &|| {
                pb.inc(1)
            })
        })
        .collect();
    pb.finish_and_clear();
    // The sweep winner itself stays a candidate: if the final budget ran out
    // before any epoch, we still return it.
    let mut all = vec![winner];
    all.extend(finals.into_iter().filter(|r| r.epochs > 0));
    let chosen = best_run(all).ok_or(LearnError::OutOfTime {
        what: "NN final training",
        budget_s: cfg.final_time_limit.map_or(0.0, |d| d.as_secs_f64()),
    })?;
    let final_seconds = t1.elapsed().as_secs_f64();
    let fit = data.fit_of(chosen, cfg.final_restarts, final_seconds);
    Ok(SweepResult {
        curve,
        best_hidden,
        fit,
        sweep_seconds,
        final_seconds,
    })
}

/// How candidates are scored.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Validation {
    /// One seeded split; `fraction` of the points are held out.
    HoldOut { fraction: f64 },
    /// Seeded k-fold cross-validation.
    KFold { k: usize },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SvrSearchConfig {
    pub c: Vec<f64>,
    /// Standardized output units.
    pub epsilon: Vec<f64>,
    pub gamma: Vec<f64>,
    pub validation: Validation,
    pub solver: SolverConfig,
    pub mode: OutputMode,
    pub seed: u64,
    /// Candidates not started by then are skipped; running ones stop and are
    /// marked unconverged (and not selected).
    pub time_limit: Option<Duration>,
    /// Dense-kernel size cap (see `svr::DEFAULT_MAX_DENSE_POINTS`).
    pub max_dense_points: usize,
    pub quiet: bool,
    /// The progress bar says "black-box" (see [`SweepConfig::blackbox`]).
    #[serde(default)]
    pub blackbox: bool,
}

impl Default for SvrSearchConfig {
    fn default() -> Self {
        SvrSearchConfig {
            // Around the paper's choice (C 30-100, epsilon 0.01); eight fits
            // on 80 % of 2197 points took ~4 s on 2 cores (learn_bench).
            c: vec![30.0, 300.0],
            epsilon: vec![0.01, 0.005],
            gamma: vec![0.3, 1.0],
            validation: Validation::HoldOut { fraction: 0.2 },
            solver: SolverConfig::default(),
            mode: OutputMode::Absolute,
            seed: 1,
            time_limit: None,
            max_dense_points: svr::DEFAULT_MAX_DENSE_POINTS,
            quiet: true,
            blackbox: false,
        }
    }
}

/// How one parameter set did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SvrCandidate {
    pub params: SvrParams,
    /// Mean position error over the held-out points, mm; `None` if the time
    /// limit skipped or cut it.
    pub validation_mean_mm: Option<f64>,
    /// Largest per-axis support-vector count (last fold).
    pub support_vectors: usize,
    /// Solver seconds summed over folds.
    pub seconds: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SvrSearchResult {
    /// Every candidate, in grid order (gamma, C, epsilon).
    pub candidates: Vec<SvrCandidate>,
    pub best: SvrParams,
    /// The best parameters refit on all points.
    pub fit: SvrFit,
    pub search_seconds: f64,
    pub refit_seconds: f64,
}

fn check_grid(
    name: &'static str,
    v: &[f64],
    lo: f64,
    expected: &'static str,
) -> Result<(), LearnError> {
    if v.is_empty() {
        return Err(LearnError::InvalidParameter {
            name,
            value: 0.0,
            expected: "a non-empty list",
        });
    }
    v.iter()
        .try_for_each(|&x| check_range(name, x, lo, 1e12, expected))
}

/// (candidate index, summed validation distance, seconds, support vectors,
/// converged) of one candidate on one fold.
type Scored = (usize, f64, f64, usize, bool);

/// Grid search over C x epsilon x gamma, scored by held-out or k-fold mean
/// position error (mm), then a refit of the best on all points.
pub fn svr_search(
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    cfg: &SvrSearchConfig,
) -> Result<SvrSearchResult, LearnError> {
    let t0 = Instant::now();
    check_grid("C", &cfg.c, 1e-12, "0 < C <= 1e12")?;
    check_grid("epsilon", &cfg.epsilon, 0.0, "0 <= epsilon <= 1e12")?;
    check_grid("gamma", &cfg.gamma, 1e-12, "0 < gamma <= 1e12")?;
    validate_pairs("SVR search data", inputs, targets, 10)?;
    let n = inputs.len();
    let folds: Vec<(Vec<usize>, Vec<usize>)> = match cfg.validation {
        Validation::HoldOut { fraction } => {
            check_range("fraction", fraction, 0.01, 0.9, "0.01 <= fraction <= 0.9")?;
            vec![split_indices(n, fraction, cfg.seed)]
        }
        Validation::KFold { k } => {
            check_range("k", k as f64, 2.0, n as f64, "2 <= k <= points")?;
            let mut idx: Vec<usize> = (0..n).collect();
            Rng::derive(cfg.seed, 0xF01D).shuffle(&mut idx);
            (0..k)
                .map(|f| {
                    let mut val: Vec<usize> = idx.iter().copied().skip(f).step_by(k).collect();
                    let mut tr: Vec<usize> = idx
                        .iter()
                        .enumerate()
                        .filter(|(p, _)| p % k != f)
                        .map(|(_, &i)| i)
                        .collect();
                    val.sort_unstable();
                    tr.sort_unstable();
                    (tr, val)
                })
                .collect()
        }
    };
    // One standardization for all folds (as the NN): folds then differ only
    // in which points train, and the refit model uses the same scales.
    let outs = standardize::mode_targets(cfg.mode, inputs, targets);
    let input = standardize::fit("SVR inputs", inputs)?;
    let output = standardize::fit("SVR targets", &outs)?;
    let x = standardize::apply_all(&input, inputs);
    let y = standardize::apply_all(&output, &outs);

    // Grid order: gamma, C, epsilon. Within one kernel, cheap candidates
    // (small C, wide tube) first so a tight budget still scores some.
    let mut pairs: Vec<(usize, usize)> = (0..cfg.c.len())
        .flat_map(|ci| (0..cfg.epsilon.len()).map(move |ei| (ci, ei)))
        .collect();
    pairs.sort_by(|a, b| {
        cfg.c[a.0]
            .total_cmp(&cfg.c[b.0])
            .then(cfg.epsilon[b.1].total_cmp(&cfg.epsilon[a.1]))
    });
    let n_cand = cfg.gamma.len() * pairs.len();
    // Per candidate, over folds: summed validation distances and their count.
    let mut sum_err = vec![0.0; n_cand];
    let mut count = vec![0usize; n_cand];
    let mut ok = vec![true; n_cand];
    let mut secs = vec![0.0; n_cand];
    let mut svs = vec![0usize; n_cand];
    let cand_index =
        |gi: usize, ci: usize, ei: usize| (gi * cfg.c.len() + ci) * cfg.epsilon.len() + ei;
    let deadline = Deadline::after(cfg.time_limit);
    let pb = progress(
        (n_cand * folds.len()) as u64,
        if cfg.blackbox {
            "black-box SVR search"
        } else {
            "SVR search"
        },
        cfg.quiet,
    );
    for (tr, va) in &folds {
        let xt: Vec<[f64; 3]> = tr.iter().map(|&i| x[i]).collect();
        let yt: Vec<[f64; 3]> = tr.iter().map(|&i| y[i]).collect();
        for (gi, &gamma) in cfg.gamma.iter().enumerate() {
            if deadline.passed() {
                for &(ci, ei) in &pairs {
                    ok[cand_index(gi, ci, ei)] = false;
                }
                continue;
            }
            let kernel = KernelMatrix::rbf(&xt, gamma, cfg.max_dense_points)?;
            let results: Vec<Result<Scored, LearnError>> = pairs
                .par_iter()
                .map(|&(ci, ei)| {
                    let idx = cand_index(gi, ci, ei);
                    if deadline.passed() {
                        pb.inc(1);
                        return Ok((idx, 0.0, 0.0, 0, false));
                    }
                    let t = Instant::now();
                    let params = SvrParams {
                        c: cfg.c[ci],
                        epsilon: cfg.epsilon[ei],
                        gamma,
                    };
                    let sols = solve_axes(&kernel, &yt, &params, &cfg.solver, deadline)?;
                    let converged = sols.iter().all(|s| s.converged);
                    let model = assemble(input, output, gamma, cfg.mode, &xt, &sols);
                    let err: f64 = va
                        .iter()
                        .map(|&i| super::dist(&svr::predict(&model, &inputs[i]), &targets[i]))
                        .sum();
                    let sv = sols.iter().map(|s| s.support_vectors).max().unwrap_or(0);
                    pb.inc(1);
                    Ok((idx, err, t.elapsed().as_secs_f64(), sv, converged))
                })
                .collect();
            for r in results {
                let (idx, err, s, sv, converged) = r?;
                sum_err[idx] += err;
                count[idx] += va.len();
                secs[idx] += s;
                svs[idx] = sv;
                ok[idx] &= converged;
            }
        }
    }
    pb.finish_and_clear();
    let mut candidates = Vec::with_capacity(n_cand);
    for (gi, &gamma) in cfg.gamma.iter().enumerate() {
        for (ci, &c) in cfg.c.iter().enumerate() {
            for (ei, &epsilon) in cfg.epsilon.iter().enumerate() {
                let idx = cand_index(gi, ci, ei);
                candidates.push(SvrCandidate {
                    params: SvrParams { c, epsilon, gamma },
                    validation_mean_mm: (ok[idx] && count[idx] > 0)
                        .then(|| sum_err[idx] / count[idx] as f64),
                    support_vectors: svs[idx],
                    seconds: secs[idx],
                });
            }
        }
    }
    let best = candidates
        .iter()
        .filter_map(|c| c.validation_mean_mm.map(|e| (e, c.params)))
        .reduce(|a, b| if b.0 < a.0 { b } else { a })
        .map(|(_, p)| p)
        .ok_or(LearnError::OutOfTime {
            what: "SVR hyperparameter search",
            budget_s: cfg.time_limit.map_or(0.0, |d| d.as_secs_f64()),
        })?;
    let search_seconds = t0.elapsed().as_secs_f64();
    check_params(&best)?;
    let fit = svr::train(
        inputs,
        targets,
        &svr::SvrConfig {
            params: best,
            solver: cfg.solver,
            mode: cfg.mode,
            time_limit: None,
            max_dense_points: cfg.max_dense_points,
            quiet: cfg.quiet,
        },
    )?;
    let refit_seconds = fit.seconds;
    Ok(SvrSearchResult {
        candidates,
        best,
        fit,
        search_seconds,
        refit_seconds,
    })
}

/// Test-set statistics of any corrector, mm.
pub fn evaluate<F: Fn(&[f64; 3]) -> [f64; 3] + Sync>(
    correct: F,
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
) -> ErrorStats {
    let pred: Vec<[f64; 3]> = inputs.par_iter().map(&correct).collect();
    ErrorStats::between(&pred, targets)
}
