//! Model selection: the hidden-size sweep of the paper's figure 13 and the SVR
//! hyperparameter search (C, epsilon, gamma), both parallel (rayon), seeded
//! and bounded in time.
//!
//! Budget: a full calibration (identification + NN + SVR) must fit in 10 s on
//! 2 cores. An LM epoch at H = 20 costs ~5 ms here, so the sweep trains every
//! size for a few tens of epochs only (enough to rank sizes: LM converges
//! fast at first), then trains the chosen size longer, warm-started from the
//! sweep's network plus fresh restarts.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use crate::progress::Step;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::nn::{self, best_run, check_lm, Init, LmConfig, NnFit, Prepared, StopReason};
use super::svr::{
    self, assemble, check_params, AxisSolution, KernelMatrix, Problem, SolverConfig, SvrFit,
    SvrParams,
};
use super::{
    check_range, progress, split_indices, standardize, validate_pairs, Deadline, ErrorStats,
    LearnError, OutputMode, Rng, Standardization,
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
    check_sweep(cfg)?;
    let t0 = Instant::now();
    let data = Prepared::new(inputs, targets, cfg.mode, cfg.validation_fraction, cfg.seed)?;
    let runs = sweep_runs(&data, cfg);
    let (curve, best) = sweep_curve(&data, cfg, &runs);
    let sweep_seconds = t0.elapsed().as_secs_f64();
    let Some((_, winner)) = best else {
        return Err(LearnError::OutOfTime {
            what: "NN hidden-size sweep",
            budget_s: cfg.sweep_time_limit.map_or(0.0, |d| d.as_secs_f64()),
        });
    };
    let best_hidden = winner.h;

    let t1 = Instant::now();
    let chosen = final_training(&data, cfg, winner)?;
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

/// The sweep's settings in range.
fn check_sweep(cfg: &SweepConfig) -> Result<(), LearnError> {
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
    )
}

/// The short training of every (hidden size, restart), in parallel:
/// (hidden size, restart, run).
fn sweep_runs(data: &Prepared, cfg: &SweepConfig) -> Vec<(usize, usize, nn::Run)> {
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
            let run = nn::train_run(data, h, init, &cfg.sweep_lm, deadline, &|| {});
            pb.inc(1);
            (h, r, run)
        })
        .collect();
    pb.finish_and_clear();
    runs
}

/// The figure-13 curve (ascending size; sizes the time limit cut before any
/// epoch left out) and the best run with its score.
fn sweep_curve(
    data: &Prepared,
    cfg: &SweepConfig,
    runs: &[(usize, usize, nn::Run)],
) -> (Vec<SweepPoint>, Option<(f64, nn::Run)>) {
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
        let Some(run) = best_run(data, of_h.into_iter().map(|(_, run)| run).collect()) else {
            continue;
        };
        let model = data.model(h, &run.w);
        let (train, val) = data.stats(&model);
        // Without a validation split the training error ranks the sizes.
        let score = if val.n > 0 {
            val.mean_mm
        } else {
            train.mean_mm
        };
        curve.push(SweepPoint {
            hidden: h,
            validation_mean_mm: val.mean_mm,
            train_mean_mm: train.mean_mm,
            epochs: run.epochs,
            stop: run.stop,
        });
        if best.as_ref().is_none_or(|(s, _)| score < *s) {
            best = Some((score, run));
        }
    }
    (curve, best)
}

/// The longer training of the sweep winner's size: the winner continued
/// and fresh restarts; the best of them (the winner included).
fn final_training(
    data: &Prepared,
    cfg: &SweepConfig,
    winner: nn::Run,
) -> Result<nn::Run, LearnError> {
    let best_hidden = winner.h;
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
            nn::train_run(data, best_hidden, init, &cfg.final_lm, deadline, &|| {
                pb.inc(1)
            })
        })
        .collect();
    pb.finish_and_clear();
    // The sweep winner itself stays a candidate: if the final budget ran out
    // before any epoch, we still return it.
    let mut all = vec![winner];
    all.extend(finals.into_iter().filter(|r| r.epochs > 0));
    best_run(data, all).ok_or(LearnError::OutOfTime {
        what: "NN final training",
        budget_s: cfg.final_time_limit.map_or(0.0, |d| d.as_secs_f64()),
    })
}

/// How candidates are scored.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Scoring {
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
    pub validation: Scoring,
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
            validation: Scoring::HoldOut { fraction: 0.2 },
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

/// Grid search over C x epsilon x gamma, scored by held-out or k-fold mean
/// position error (mm), then a refit of the best on all points.
///
/// How the work is shared: one kernel matrix per gamma
/// over all points serves every fold, axis and (C, epsilon) (a fold trains on
/// some of its rows) and then the refit. For each (gamma, fold, axis) the
/// (C, epsilon) pairs are solved in one chain, each from the previous
/// solution: a wider tube's solution for the next epsilon of the same C, the
/// previous C's solution scaled by the ratio of the C's for the next C. The
/// chains run in parallel; the refit on all points starts from the chosen
/// candidate's solution (held-out points at 0). Each solve still stops on
/// the same KKT gap as from 0 (decision record 0018,
/// `docs/decisions/0018-blackbox-conjugate-smo.md`).
pub fn svr_search(
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    cfg: &SvrSearchConfig,
) -> Result<SvrSearchResult, LearnError> {
    let t0 = Instant::now();
    check_search(inputs, targets, cfg)?;
    let search = SvrSearch::new(inputs, targets, cfg)?;
    let (sols, kept_kernel) = search.solve_grid()?;
    let candidates = search.candidates(&search.score(&sols));
    let best_idx = best_candidate(&candidates, cfg)?;
    let best = candidates[best_idx].params;
    let search_seconds = t0.elapsed().as_secs_f64();
    check_params(&best)?;
    let fit = search.refit(best_idx, best, kept_kernel, &sols)?;
    let refit_seconds = fit.seconds;
    Ok(SvrSearchResult {
        candidates,
        best,
        fit,
        search_seconds,
        refit_seconds,
    })
}

/// Fewest points the SVR search takes.
pub const MIN_SEARCH_POINTS: usize = 10;

/// The grid, the solver tolerance and the data in range; the kernel within
/// its size cap.
fn check_search(
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    cfg: &SvrSearchConfig,
) -> Result<(), LearnError> {
    check_grid("C", &cfg.c, 1e-12, "0 < C <= 1e12")?;
    check_grid("epsilon", &cfg.epsilon, 0.0, "0 <= epsilon <= 1e12")?;
    check_grid("gamma", &cfg.gamma, 1e-12, "0 < gamma <= 1e12")?;
    check_range("tol", cfg.solver.tol, 1e-15, 1e3, "0 < tol <= 1000")?;
    validate_pairs("SVR search data", inputs, targets, MIN_SEARCH_POINTS)?;
    let n = inputs.len();
    if n > cfg.max_dense_points {
        return Err(LearnError::TooLarge {
            what: "SVR kernel matrix",
            points: n,
            max: cfg.max_dense_points,
        });
    }
    Ok(())
}

/// A fold's (training, held-out) point indices.
type Fold = (Vec<usize>, Vec<usize>);

/// The (training, held-out) point indices of each fold.
fn validation_folds(n: usize, cfg: &SvrSearchConfig) -> Result<Vec<Fold>, LearnError> {
    Ok(match cfg.validation {
        Scoring::HoldOut { fraction } => {
            check_range("fraction", fraction, 0.01, 0.9, "0.01 <= fraction <= 0.9")?;
            vec![split_indices(n, fraction, cfg.seed)]
        }
        Scoring::KFold { k } => {
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
    })
}

/// What every step of one SVR search shares: the settings, the folds and
/// the standardized points.
struct SvrSearch<'a> {
    cfg: &'a SvrSearchConfig,
    inputs: &'a [[f64; 3]],
    targets: &'a [[f64; 3]],
    folds: Vec<Fold>,
    input: Standardization,
    output: Standardization,
    /// Standardized inputs and (mode) targets.
    x: Vec<[f64; 3]>,
    y: Vec<[f64; 3]>,
}

/// How the chains of one group of kernels run: the (C, epsilon) order of
/// each chain, the search's deadline and its progress bar.
struct Chains {
    c_order: Vec<usize>,
    e_order: Vec<usize>,
    deadline: Deadline,
    pb: Step,
}

/// A group's kernels: (gamma index, kernel, seconds to build it).
type Kernels = Vec<(usize, KernelMatrix, f64)>;

/// Per (candidate, fold, axis): the solution; per gamma: the kernel kept for
/// the refit, with its build seconds.
type GridSolutions = (Vec<Option<AxisSolution>>, Vec<Option<(KernelMatrix, f64)>>);

impl<'a> SvrSearch<'a> {
    fn new(
        inputs: &'a [[f64; 3]],
        targets: &'a [[f64; 3]],
        cfg: &'a SvrSearchConfig,
    ) -> Result<SvrSearch<'a>, LearnError> {
        let folds = validation_folds(inputs.len(), cfg)?;
        // One standardization for all folds (as the NN): folds then differ only
        // in which points train, and the refit model uses the same scales.
        let outs = standardize::mode_targets(cfg.mode, inputs, targets);
        let input = standardize::fit("SVR inputs", inputs)?;
        let output = standardize::fit("SVR targets", &outs)?;
        let x = standardize::apply_all(&input, inputs);
        let y = standardize::apply_all(&output, &outs);
        Ok(SvrSearch {
            cfg,
            inputs,
            targets,
            folds,
            input,
            output,
            x,
            y,
        })
    }

    fn n_cand(&self) -> usize {
        self.cfg.gamma.len() * self.cfg.c.len() * self.cfg.epsilon.len()
    }

    fn cand_index(&self, gi: usize, ci: usize, ei: usize) -> usize {
        (gi * self.cfg.c.len() + ci) * self.cfg.epsilon.len() + ei
    }

    fn slot(&self, idx: usize, f: usize, a: usize) -> usize {
        (idx * self.folds.len() + f) * 3 + a
    }

    /// Every candidate on every fold and axis, one group of kernels at a
    /// time, until the deadline.
    fn solve_grid(&self) -> Result<GridSolutions, LearnError> {
        let cfg = self.cfg;
        // Chain order within one (gamma, fold, axis): C ascending, and for each
        // C the widest tube first (cheap candidates first, so that a tight
        // budget still scores some, and each warm start comes from an easier
        // problem).
        let mut c_order: Vec<usize> = (0..cfg.c.len()).collect();
        c_order.sort_by(|&a, &b| cfg.c[a].total_cmp(&cfg.c[b]));
        let mut e_order: Vec<usize> = (0..cfg.epsilon.len()).collect();
        e_order.sort_by(|&a, &b| cfg.epsilon[b].total_cmp(&cfg.epsilon[a]));
        let n_cand = self.n_cand();
        let deadline = Deadline::after(cfg.time_limit);
        let pb = progress(
            (n_cand * self.folds.len() * 3) as u64,
            if cfg.blackbox {
                "black-box SVR search"
            } else {
                "SVR search"
            },
            cfg.quiet,
        );
        let chains = Chains {
            c_order,
            e_order,
            deadline,
            pb,
        };

        // Kernels: all at once when they fit in 1 GiB (every chain can then run
        // in parallel), otherwise one gamma at a time.
        let n = self.inputs.len();
        let bytes_per_kernel = n * n * std::mem::size_of::<f32>();
        let at_once = (1usize << 30) / bytes_per_kernel.max(1);
        let groups: Vec<Vec<usize>> = (0..cfg.gamma.len())
            .collect::<Vec<_>>()
            .chunks(at_once.max(1))
            .map(|c| c.to_vec())
            .collect();
        let mut sols: Vec<Option<AxisSolution>> = vec![None; n_cand * self.folds.len() * 3];
        let mut kept_kernel: Vec<Option<(KernelMatrix, f64)>> =
            (0..cfg.gamma.len()).map(|_| None).collect();
        for group in &groups {
            if deadline.passed() {
                break;
            }
            let kernels = self.kernels_of(group)?;
            let jobs = self.chain_jobs(&kernels);
            let done = run_queue(&jobs, |job| self.solve_chain(&kernels, job, &chains));
            for (_, r) in done {
                for (k, sol) in r? {
                    sols[k] = Some(sol);
                }
            }
            for (gi, k, secs) in kernels {
                kept_kernel[gi] = Some((k, secs));
            }
            // The refit reuses the kernel of the chosen gamma when all kernels
            // fit in memory at once; otherwise it builds it again.
            if groups.len() > 1 {
                for k in kept_kernel.iter_mut() {
                    *k = None;
                }
            }
        }
        chains.pb.finish_and_clear();
        Ok((sols, kept_kernel))
    }

    /// The kernel matrix of each gamma of `group`, timed.
    fn kernels_of(&self, group: &[usize]) -> Result<Kernels, LearnError> {
        group
            .iter()
            .map(|&gi| {
                let t = Instant::now();
                KernelMatrix::rbf(&self.x, self.cfg.gamma[gi], self.cfg.max_dense_points)
                    .map(|k| (gi, k, t.elapsed().as_secs_f64()))
            })
            .collect::<Result<_, _>>()
    }

    /// The (kernel, fold, axis) chains, longest first: larger gamma (more
    /// support vectors) first.
    fn chain_jobs(&self, kernels: &Kernels) -> Vec<(usize, usize, usize)> {
        let mut jobs: Vec<(usize, usize, usize)> = Vec::new();
        for ki in 0..kernels.len() {
            for f in 0..self.folds.len() {
                for a in 0..3 {
                    jobs.push((ki, f, a));
                }
            }
        }
        let gamma = &self.cfg.gamma;
        jobs.sort_by(|p, q| gamma[kernels[q.0].0].total_cmp(&gamma[kernels[p.0].0]));
        jobs
    }

    /// One (gamma, fold, axis) chain: every (C, epsilon) in chain order, each
    /// warm-started from the one before.
    fn solve_chain(
        &self,
        kernels: &Kernels,
        &(ki, f, a): &(usize, usize, usize),
        chains: &Chains,
    ) -> ChainResult {
        let cfg = self.cfg;
        let (gi, kernel, _) = &kernels[ki];
        let tr = &self.folds[f].0;
        let z: Vec<f64> = tr.iter().map(|&i| self.y[i][a]).collect();
        let mut out = Vec::new();
        let mut prev_c: Option<(f64, Vec<f64>)> = None;
        for &ci in &chains.c_order {
            let c = cfg.c[ci];
            let mut prev_e: Option<Vec<f64>> = None;
            for &ei in &chains.e_order {
                if chains.deadline.passed() {
                    chains.pb.inc(1);
                    continue;
                }
                let warm: Option<Vec<f64>> = match (&prev_e, &prev_c) {
                    (Some(w), _) => Some(w.clone()),
                    (None, Some((c0, w))) => Some(w.iter().map(|v| v * (c / c0)).collect()),
                    (None, None) => None,
                };
                let t = Instant::now();
                let mut sol = svr::solve(
                    &Problem {
                        kernel,
                        points: tr,
                        z: &z,
                        c,
                        epsilon: cfg.epsilon[ei],
                        warm: warm.as_deref(),
                    },
                    &cfg.solver,
                    chains.deadline,
                )?;
                sol.seconds = t.elapsed().as_secs_f64();
                if prev_e.is_none() {
                    prev_c = Some((c, sol.coef.clone()));
                }
                prev_e = Some(sol.coef.clone());
                out.push((self.slot(self.cand_index(*gi, ci, ei), f, a), sol));
                chains.pb.inc(1);
            }
        }
        Ok(out)
    }

    /// Every candidate's score: the three axes of each fold as one model.
    /// (mean held-out error if every fold converged, largest support-vector
    /// count, solver seconds), by candidate index.
    fn score(&self, sols: &[Option<AxisSolution>]) -> Vec<(Option<f64>, usize, f64)> {
        let cfg = self.cfg;
        (0..self.n_cand())
            .into_par_iter()
            .map(|idx| {
                let gi = idx / (cfg.c.len() * cfg.epsilon.len());
                let gamma = cfg.gamma[gi];
                let mut sum = 0.0;
                let mut count = 0usize;
                let mut ok = true;
                let mut secs = 0.0;
                let mut sv = 0;
                for (f, (tr, va)) in self.folds.iter().enumerate() {
                    let axes: Option<Vec<&AxisSolution>> = (0..3)
                        .map(|a| sols[self.slot(idx, f, a)].as_ref())
                        .collect();
                    let Some(axes) = axes else {
                        ok = false;
                        continue;
                    };
                    ok &= axes.iter().all(|s| s.converged);
                    secs += axes.iter().map(|s| s.seconds).sum::<f64>();
                    sv = axes.iter().map(|s| s.support_vectors).max().unwrap_or(0);
                    let xt: Vec<[f64; 3]> = tr.iter().map(|&i| self.x[i]).collect();
                    let owned: Vec<AxisSolution> = axes.into_iter().cloned().collect();
                    let model = assemble(self.input, self.output, gamma, cfg.mode, &xt, &owned);
                    sum += va
                        .iter()
                        .map(|&i| {
                            super::dist(&svr::predict(&model, &self.inputs[i]), &self.targets[i])
                        })
                        .sum::<f64>();
                    count += va.len();
                }
                ((ok && count > 0).then(|| sum / count as f64), sv, secs)
            })
            .collect()
    }

    /// The candidates in grid order (gamma, C, epsilon) with their scores.
    fn candidates(&self, scored: &[(Option<f64>, usize, f64)]) -> Vec<SvrCandidate> {
        let cfg = self.cfg;
        let mut candidates = Vec::with_capacity(self.n_cand());
        for (gi, &gamma) in cfg.gamma.iter().enumerate() {
            for (ci, &c) in cfg.c.iter().enumerate() {
                for (ei, &epsilon) in cfg.epsilon.iter().enumerate() {
                    let (val, sv, secs) = scored[self.cand_index(gi, ci, ei)];
                    candidates.push(SvrCandidate {
                        params: SvrParams { c, epsilon, gamma },
                        validation_mean_mm: val,
                        support_vectors: sv,
                        seconds: secs,
                    });
                }
            }
        }
        candidates
    }

    /// Refit on all points, from the chosen candidate's solution on the last
    /// fold (its held-out points start at 0).
    fn refit(
        &self,
        best_idx: usize,
        best: SvrParams,
        mut kept_kernel: Vec<Option<(KernelMatrix, f64)>>,
        sols: &[Option<AxisSolution>],
    ) -> Result<SvrFit, LearnError> {
        let cfg = self.cfg;
        let n = self.inputs.len();
        let t1 = Instant::now();
        let gi = best_idx / (cfg.c.len() * cfg.epsilon.len());
        let (kernel, kernel_seconds) = match kept_kernel[gi].take() {
            Some(k) => k,
            None => {
                let t = Instant::now();
                let k = KernelMatrix::rbf(&self.x, best.gamma, cfg.max_dense_points)?;
                (k, t.elapsed().as_secs_f64())
            }
        };
        drop(kept_kernel);
        let last = self.folds.len() - 1;
        let all: Vec<usize> = (0..n).collect();
        let pb = progress(3, "SVR refit", cfg.quiet);
        let refit: Result<Vec<AxisSolution>, LearnError> = (0..3)
            .into_par_iter()
            .map(|a| {
                let mut warm = vec![0.0; n];
                if let Some(s) = &sols[self.slot(best_idx, last, a)] {
                    for (&i, &c) in self.folds[last].0.iter().zip(&s.coef) {
                        warm[i] = c;
                    }
                }
                let z: Vec<f64> = self.y.iter().map(|p| p[a]).collect();
                let r = svr::solve(
                    &Problem {
                        kernel: &kernel,
                        points: &all,
                        z: &z,
                        c: best.c,
                        epsilon: best.epsilon,
                        warm: Some(&warm),
                    },
                    &cfg.solver,
                    Deadline::none(),
                );
                pb.inc(1);
                r
            })
            .collect();
        pb.finish_and_clear();
        let refit = refit?;
        let model = assemble(
            self.input,
            self.output,
            best.gamma,
            cfg.mode,
            &self.x,
            &refit,
        );
        let pred = svr::predict_all(&model, self.inputs);
        let refit_seconds = t1.elapsed().as_secs_f64();
        Ok(SvrFit {
            train: ErrorStats::between(&pred, self.targets),
            axes: [0, 1, 2].map(|a| svr::summary(&refit[a])),
            model,
            seconds: refit_seconds,
            kernel_seconds,
        })
    }
}

/// The index of the candidate of least held-out error (the first of equal
/// ones); an error when the time limit left none scored.
fn best_candidate(candidates: &[SvrCandidate], cfg: &SvrSearchConfig) -> Result<usize, LearnError> {
    candidates
        .iter()
        .enumerate()
        .filter_map(|(i, c)| c.validation_mean_mm.map(|e| (e, i)))
        .reduce(|a, b| if b.0 < a.0 { b } else { a })
        .map(|(_, i)| i)
        .ok_or(LearnError::OutOfTime {
            what: "SVR hyperparameter search",
            budget_s: cfg.time_limit.map_or(0.0, |d| d.as_secs_f64()),
        })
}

/// Runs the chains from one queue, longest first: each worker takes the
/// next chain when it is free, so the cores end together as far as whole
/// chains allow. (Measured on the black-box grid, 2 threads: rayon's
/// halving of the list left one core idle for the last 1.9 s in two runs
/// out of two; 0.4 and 0.6 s with the queue.) A worker the pool never
/// starts leaves its share to the others. The results come back in job
/// order.
fn run_queue<J: Sync>(
    jobs: &[J],
    chain: impl Fn(&J) -> ChainResult + Sync,
) -> Vec<(usize, ChainResult)> {
    let next = AtomicUsize::new(0);
    let workers = rayon::current_num_threads().clamp(1, jobs.len().max(1));
    let mut done: Vec<(usize, ChainResult)> = (0..workers)
        .into_par_iter()
        .flat_map_iter(|_| {
            let mut mine = Vec::new();
            loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                let Some(job) = jobs.get(k) else { break };
                mine.push((k, chain(job)));
            }
            mine
        })
        .collect();
    done.sort_by_key(|(k, _)| *k);
    done
}

/// One (gamma, fold, axis) chain's solutions, by result slot.
type ChainResult = Result<Vec<(usize, AxisSolution)>, LearnError>;

/// Test-set statistics of any corrector, mm.
pub fn evaluate<F: Fn(&[f64; 3]) -> [f64; 3] + Sync>(
    correct: F,
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
) -> ErrorStats {
    let pred: Vec<[f64; 3]> = inputs.par_iter().map(&correct).collect();
    ErrorStats::between(&pred, targets)
}
