//! RBF epsilon-SVR, one regressor per output axis (paper section 5.3), solved
//! by our own SMO.
//!
//! Why our own solver: the notes measured the Rust crates against libsvm on
//! this very problem. linfa-svm 0.8.1 panics (index out of bounds in its SMO)
//! with shrinking on and takes 7.3 s with it off; smartcore 0.7.0 stops
//! silently at a hard-coded iteration cap and returned an unconverged model at
//! epsilon = 0.003 (1.76 mm against libsvm's 0.94 mm). What we need is
//! libsvm's algorithm: SMO with second-order working-set selection (WSS2, Fan,
//! Chen and Lin 2005), shrinking, and a stop on the KKT gap (tolerance 1e-3).
//! This module follows libsvm's `Solver` (C-SVC/epsilon-SVR, not nu) step for
//! step when [`SolverConfig::conjugate`] is off, so that its results can be
//! checked against libsvm's (`host/tests/fixtures/svr_libsvm.json`, written by
//! `scripts/reference/svr_reference.py`).
//!
//! By default each step is a conjugate SMO step (the idea of Torres-Barran,
//! Alaiz and Dorronsoro's "conjugate SMO"; our own formulation, see
//! `Solver::conjugate_step`): the WSS2 pair's direction plus the multiple of
//! the previous direction that makes the two Q-conjugate, with an exact line
//! search clipped to the box, and libsvm's plain step whenever that is not a
//! descent step. The selection, the shrinking and the stopping rule (KKT gap
//! below `tol`) are libsvm's. On the black-box grid it halves the iterations
//! (decision record 0018, `docs/decisions/0018-blackbox-conjugate-smo.md`),
//! and on the fixture it ends at least as close to the optimum as libsvm.
//!
//! By default ([`SolverConfig::per_point`]) the dual is solved in one variable
//! per point, `alpha_i - alpha*_i` (`svr/point.rs`): the same selection,
//! steps and stopping rule on values that libsvm's 2n variables give, one
//! gradient of n entries, each solver's own contiguous copy of its kernel
//! block, and the hot passes on AVX2 where the CPU has it (bit for bit the
//! scalar passes' results). On the black-box grid it is 2 times faster per
//! SMO iteration than the 2n solver, on the same iteration counts.
//!
//! The kernel cache is the whole dense kernel matrix, computed once (in
//! parallel) and shared by the three axes: every SMO iteration then reads two
//! rows with no kernel evaluation at all. Entries are stored in f32, as
//! libsvm's cache (`Qfloat`) does, with the gradient, alphas and the diagonal
//! in f64: 2197 points take 19 MB, rows stream through the caches twice as
//! fast, and the solver follows libsvm's path closely enough that the fixture
//! test can compare solutions tightly (with an f64 kernel the two solvers
//! drift apart on ill-conditioned problems by the f32 rounding of libsvm's
//! cache, 1e-4 in predictions at tol 1e-6). Predictions use f64 throughout.
//!
//! The dual, as in libsvm: 2n variables `beta = (alpha, alpha*)`, signs
//! `y = (+1.., -1..)`, `Q_st = y_s y_t K(s mod n, t mod n)`,
//! `p = (eps - z, eps + z)` for targets z; minimize `beta^T Q beta / 2 + p^T beta`
//! subject to `y^T beta = 0`, `0 <= beta <= C`. The regressor is
//! `f(x) = sum_j (alpha_j - alpha*_j) K(x_j, x) - rho`.

use std::time::{Duration, Instant};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

mod libsvm_dual;
mod point;
mod smo;

use libsvm_dual::Solver;
// What the per-point solver (`point`) takes from here.
use smo::{run_smo, Direction, Smo, MAX_DIRECTION_SUPPORT, TAU};

use super::standardize::{self, apply, mode_targets, output_position};
use super::{
    check_range, validate_pairs, validate_points, Deadline, ErrorStats, LearnError, OutputMode,
    SvrModel,
};

/// Default cap on points for the dense kernel: 16000^2 f32 is 1 GB.
pub const DEFAULT_MAX_DENSE_POINTS: usize = 16_000;

/// SVR hyperparameters (on standardized inputs and outputs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SvrParams {
    pub c: f64,
    /// Half-width of the insensitive tube, standardized output units.
    pub epsilon: f64,
    /// RBF `exp(-gamma |x - x'|^2)` on standardized inputs.
    pub gamma: f64,
}

/// Solver settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SolverConfig {
    /// Stop when the maximal KKT violation `m(beta) - M(beta)` is below this
    /// (libsvm's `-e`, default 1e-3).
    pub tol: f64,
    pub shrinking: bool,
    /// Iteration cap; `None` uses libsvm's `max(10^7, 100 n)`. Reaching it is
    /// reported (`converged = false`), never silent.
    pub max_iter: Option<usize>,
    /// Conjugate SMO: each step goes along the SMO pair's direction made
    /// Q-conjugate to the previous step's (see `Solver::conjugate_step`).
    #[serde(default)]
    pub conjugate: bool,
    /// Solve the dual in one variable per point (`alpha_i - alpha*_i`, see
    /// `svr/point.rs`) instead of libsvm's 2n: one gradient of n entries
    /// per iteration instead of 2n. Off, or above 6000 training points
    /// (each solver then keeps its own n^2 kernel block): libsvm's own
    /// formulation (with `conjugate` off, libsvm's path step for step).
    #[serde(default = "per_point_default")]
    pub per_point: bool,
}

fn per_point_default() -> bool {
    true
}

impl Default for SolverConfig {
    fn default() -> Self {
        SolverConfig {
            tol: 1e-3,
            shrinking: true,
            max_iter: None,
            conjugate: true,
            per_point: true,
        }
    }
}

/// Settings of a three-axis fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SvrConfig {
    pub params: SvrParams,
    pub solver: SolverConfig,
    pub mode: OutputMode,
    pub time_limit: Option<Duration>,
    pub max_dense_points: usize,
    /// Hide the progress spinner.
    pub quiet: bool,
}

impl Default for SvrConfig {
    fn default() -> Self {
        SvrConfig {
            params: SvrParams {
                c: 100.0,
                epsilon: 0.01,
                gamma: 1.0 / 3.0,
            },
            solver: SolverConfig::default(),
            mode: OutputMode::Absolute,
            time_limit: None,
            max_dense_points: DEFAULT_MAX_DENSE_POINTS,
            quiet: true,
        }
    }
}

/// The dense RBF kernel matrix of a point set (row-major, symmetric).
#[derive(Clone, Debug)]
pub struct KernelMatrix {
    n: usize,
    gamma: f64,
    data: Vec<f32>,
}

impl KernelMatrix {
    /// `K_ij = exp(-gamma |x_i - x_j|^2)`, rows computed in parallel.
    pub fn rbf(x: &[[f64; 3]], gamma: f64, max_points: usize) -> Result<Self, LearnError> {
        check_range("gamma", gamma, 1e-12, 1e12, "0 < gamma <= 1e12")?;
        validate_points("SVR kernel", x, 2)?;
        let n = x.len();
        if n > max_points {
            return Err(LearnError::TooLarge {
                what: "SVR kernel matrix",
                points: n,
                max: max_points,
            });
        }
        // libsvm's formula, |x|^2 + |x'|^2 - 2 x.x', rounded as libsvm rounds
        // it: entries then agree with its cache bit for bit and both solvers
        // take the same path (the fixture test sees 1e-15 agreement where the
        // problem is well conditioned). The cancellation it suffers is far
        // below the f32 storage rounding.
        let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let sq: Vec<f64> = x.iter().map(|p| dot(p, p)).collect();
        let mut data = vec![0.0f32; n * n];
        data.par_chunks_mut(n).enumerate().for_each(|(i, row)| {
            let xi = &x[i];
            for ((v, xj), sqj) in row.iter_mut().zip(x).zip(&sq) {
                *v = (-gamma * (sq[i] + sqj - 2.0 * dot(xi, xj))).exp() as f32;
            }
        });
        Ok(KernelMatrix { n, gamma, data })
    }

    pub fn len(&self) -> usize {
        self.n
    }
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }
    pub fn gamma(&self) -> f64 {
        self.gamma
    }
    fn row(&self, i: usize) -> &[f32] {
        &self.data[i * self.n..(i + 1) * self.n]
    }
}

/// The dual solution for one output axis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisSolution {
    /// `alpha_i - alpha*_i` for every training point (0 for non-support).
    pub coef: Vec<f64>,
    /// `-rho`.
    pub bias: f64,
    /// Dual objective `beta^T Q beta / 2 + p^T beta` as the solver sees it,
    /// i.e. with the f32 kernel (libsvm's `obj` is computed the same way).
    pub objective: f64,
    pub iterations: usize,
    /// False when the iteration cap or the time limit stopped the solver.
    pub converged: bool,
    pub support_vectors: usize,
    /// Support vectors at the bound C (outside the tube).
    pub bounded_support_vectors: usize,
    /// Wall seconds of the solve (set by callers that time it).
    #[serde(default)]
    pub seconds: f64,
}

/// Solve one epsilon-SVR dual on a precomputed kernel for targets `z`
/// (standardized, one per kernel point), from 0. Returns an error only for
/// bad input; an unconverged run is flagged in the result.
pub fn solve_epsilon_svr(
    kernel: &KernelMatrix,
    z: &[f64],
    c: f64,
    epsilon: f64,
    solver: &SolverConfig,
    deadline: Deadline,
) -> Result<AxisSolution, LearnError> {
    let points: Vec<usize> = (0..kernel.len()).collect();
    solve(
        &Problem {
            kernel,
            points: &points,
            z,
            c,
            epsilon,
            warm: None,
        },
        solver,
        deadline,
    )
}

/// One epsilon-SVR dual on some rows of a precomputed kernel.
#[derive(Clone, Copy, Debug)]
pub struct Problem<'a> {
    pub kernel: &'a KernelMatrix,
    /// The kernel rows (points) that train; the solution's coefficients are
    /// in this order.
    pub points: &'a [usize],
    /// Standardized target of each training point.
    pub z: &'a [f64],
    pub c: f64,
    pub epsilon: f64,
    /// Start from these coefficients `alpha_i - alpha*_i` (one per training
    /// point, summing to 0), e.g. the solution for a smaller C or a wider
    /// tube, instead of from 0. Scaled down if some exceed C. The optimum
    /// and the stopping rule are the same; only the path is shorter.
    pub warm: Option<&'a [f64]>,
}

/// Solve a [`Problem`]. Returns an error only for bad input; an unconverged
/// run is flagged in the result.
pub fn solve(
    problem: &Problem,
    solver: &SolverConfig,
    deadline: Deadline,
) -> Result<AxisSolution, LearnError> {
    let &Problem {
        kernel,
        points,
        z,
        c,
        epsilon,
        warm,
    } = problem;
    let n = points.len();
    if z.len() != n {
        return Err(LearnError::LengthMismatch {
            inputs: n,
            targets: z.len(),
        });
    }
    if n == 0 || points.iter().any(|&p| p >= kernel.len()) {
        return Err(LearnError::InvalidParameter {
            name: "points",
            value: n as f64,
            expected: "at least one training point, each a row of the kernel matrix",
        });
    }
    if let Some(index) = z.iter().position(|v| !v.is_finite()) {
        return Err(LearnError::NonFinite {
            what: "SVR targets",
            index,
            axis: 0,
        });
    }
    check_range("C", c, 1e-12, 1e12, "0 < C <= 1e12")?;
    check_range("epsilon", epsilon, 0.0, 1e12, "epsilon >= 0")?;
    check_range("tol", solver.tol, 1e-15, 1e3, "0 < tol <= 1000")?;
    let warm = match warm {
        None => None,
        Some(w) => Some(feasible_start(w, n, c)?),
    };
    let max_iter = solver.max_iter.unwrap_or((100 * n).max(10_000_000));
    let (coef, bias, objective, iterations, converged) =
        if solver.per_point && n <= point::MAX_BLOCK_POINTS {
            let mut s =
                point::PointSolver::new(kernel, points, z, epsilon, c, solver.tol, warm.as_deref());
            let (iterations, converged) =
                s.solve(solver.shrinking, solver.conjugate, max_iter, deadline);
            let rho = s.calculate_rho();
            let objective = s.objective();
            let mut coef = vec![0.0; n];
            for (t, &orig) in s.active_set.iter().enumerate() {
                coef[orig] = s.beta[t];
            }
            (coef, -rho, objective, iterations, converged)
        } else {
            let mut s = Solver::new(kernel, points, z, epsilon, c, solver.tol, warm.as_deref());
            let (iterations, converged) = s.solve(solver, max_iter, deadline);
            let rho = s.calculate_rho();
            let objective = s
                .alpha
                .iter()
                .zip(&s.g)
                .zip(&s.p)
                .map(|((a, g), p)| a * (g + p))
                .sum::<f64>()
                / 2.0;
            let mut beta = vec![0.0; 2 * n];
            for (t, &orig) in s.active_set.iter().enumerate() {
                beta[orig] = s.alpha[t];
            }
            let coef: Vec<f64> = (0..n).map(|i| beta[i] - beta[i + n]).collect();
            (coef, -rho, objective, iterations, converged)
        };
    let support_vectors = coef.iter().filter(|v| **v != 0.0).count();
    let bounded_support_vectors = coef.iter().filter(|v| v.abs() >= c).count();
    Ok(AxisSolution {
        coef,
        bias,
        objective,
        iterations,
        converged,
        support_vectors,
        bounded_support_vectors,
        seconds: 0.0,
    })
}

/// A warm start checked and scaled into the box `|c_i| <= C`.
fn feasible_start(w: &[f64], n: usize, c: f64) -> Result<Vec<f64>, LearnError> {
    if w.len() != n {
        return Err(LearnError::LengthMismatch {
            inputs: n,
            targets: w.len(),
        });
    }
    if let Some(index) = w.iter().position(|v| !v.is_finite()) {
        return Err(LearnError::NonFinite {
            what: "SVR warm start",
            index,
            axis: 0,
        });
    }
    let sum: f64 = w.iter().sum();
    let size: f64 = w.iter().map(|v| v.abs()).sum();
    if sum.abs() > 1e-9 * size.max(1.0) {
        return Err(LearnError::InvalidParameter {
            name: "warm start",
            value: sum,
            expected: "coefficients alpha - alpha* summing to 0",
        });
    }
    let largest = w.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let scale = if largest > c { c / largest } else { 1.0 };
    Ok(w.iter().map(|v| v * scale).collect())
}

/// A trained three-axis SVR and how the solver did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SvrFit {
    pub model: SvrModel,
    /// Per-axis solver outcome (coefficients omitted: they are in the model).
    pub axes: [AxisSummary; 3],
    /// Position error on the training points, mm.
    pub train: ErrorStats,
    pub seconds: f64,
    pub kernel_seconds: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisSummary {
    pub objective: f64,
    pub iterations: usize,
    pub converged: bool,
    pub support_vectors: usize,
    pub bounded_support_vectors: usize,
}

/// Fit three SVRs (x, y, z outputs) on (device position, target position)
/// pairs in mm, sharing one kernel matrix; the axes are solved in parallel.
pub fn train(
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    cfg: &SvrConfig,
) -> Result<SvrFit, LearnError> {
    let start = Instant::now();
    validate_pairs("SVR training data", inputs, targets, 3)?;
    check_params(&cfg.params)?;
    let outs = mode_targets(cfg.mode, inputs, targets);
    let input = standardize::fit("SVR inputs", inputs)?;
    let output = standardize::fit("SVR targets", &outs)?;
    let x = standardize::apply_all(&input, inputs);
    let y = standardize::apply_all(&output, &outs);
    let kernel = KernelMatrix::rbf(&x, cfg.params.gamma, cfg.max_dense_points)?;
    let kernel_seconds = start.elapsed().as_secs_f64();
    let deadline = Deadline::after(cfg.time_limit);
    // Small epsilon can take the SMO from a fraction of a second to minutes:
    // show that it is working.
    let pb = super::progress(3, "SVR axes", cfg.quiet);
    let sols: Result<Vec<AxisSolution>, LearnError> = (0..3)
        .into_par_iter()
        .map(|a| {
            let z: Vec<f64> = y.iter().map(|p| p[a]).collect();
            let r = solve_epsilon_svr(
                &kernel,
                &z,
                cfg.params.c,
                cfg.params.epsilon,
                &cfg.solver,
                deadline,
            );
            pb.inc(1);
            r
        })
        .collect();
    pb.finish_and_clear();
    let sols = sols?;
    let model = assemble(input, output, cfg.params.gamma, cfg.mode, &x, &sols);
    let pred = predict_all(&model, inputs);
    Ok(SvrFit {
        train: ErrorStats::between(&pred, targets),
        axes: [0, 1, 2].map(|a| summary(&sols[a])),
        model,
        seconds: start.elapsed().as_secs_f64(),
        kernel_seconds,
    })
}

pub(crate) fn check_params(p: &SvrParams) -> Result<(), LearnError> {
    check_range("C", p.c, 1e-12, 1e12, "0 < C <= 1e12")?;
    check_range("epsilon", p.epsilon, 0.0, 1e12, "epsilon >= 0")?;
    check_range("gamma", p.gamma, 1e-12, 1e12, "0 < gamma <= 1e12")
}

pub(crate) fn summary(s: &AxisSolution) -> AxisSummary {
    AxisSummary {
        objective: s.objective,
        iterations: s.iterations,
        converged: s.converged,
        support_vectors: s.support_vectors,
        bounded_support_vectors: s.bounded_support_vectors,
    }
}

/// Build the model: support vectors are the union over axes, with zero
/// coefficients where an axis does not use a point.
pub(crate) fn assemble(
    input: super::Standardization,
    output: super::Standardization,
    gamma: f64,
    mode: OutputMode,
    x_std: &[[f64; 3]],
    sols: &[AxisSolution],
) -> SvrModel {
    let used: Vec<usize> = (0..x_std.len())
        .filter(|&i| sols.iter().any(|s| s.coef[i] != 0.0))
        .collect();
    SvrModel {
        input,
        output,
        gamma,
        support: used.iter().map(|&i| x_std[i]).collect(),
        coef: [0, 1, 2].map(|a| used.iter().map(|&i| sols[a].coef[i]).collect()),
        bias: [0, 1, 2].map(|a| sols[a].bias),
        mode,
    }
}

/// The standardized output of the three regressors at a standardized input.
pub fn decision(model: &SvrModel, x: &[f64; 3]) -> [f64; 3] {
    let mut y = model.bias;
    for (j, sv) in model.support.iter().enumerate() {
        let d0 = x[0] - sv[0];
        let d1 = x[1] - sv[1];
        let d2 = x[2] - sv[2];
        let k = (-model.gamma * (d0 * d0 + d1 * d1 + d2 * d2)).exp();
        for (a, ya) in y.iter_mut().enumerate() {
            *ya += model.coef[a].get(j).copied().unwrap_or(0.0) * k;
        }
    }
    y
}

/// Corrected position (mm) at a device position (mm), in either output mode.
pub fn predict(model: &SvrModel, p: &[f64; 3]) -> [f64; 3] {
    let y = decision(model, &apply(&model.input, p));
    output_position(model.mode, &model.output, p, &y)
}

pub fn predict_all(model: &SvrModel, points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    points.par_iter().map(|p| predict(model, p)).collect()
}

/// Check that a model's arrays agree with each other and are finite.
pub fn check_model(model: &SvrModel) -> Result<(), LearnError> {
    let m = model.support.len();
    if model.coef.iter().any(|c| c.len() != m) {
        return Err(LearnError::MalformedModel {
            what: "SvrModel: coef rows must match the number of support vectors",
        });
    }
    let finite = model.support.iter().flatten().all(|v| v.is_finite())
        && model.coef.iter().flatten().all(|v| v.is_finite())
        && model.bias.iter().all(|v| v.is_finite())
        && model.gamma.is_finite()
        && model.gamma > 0.0
        && model.input.std.iter().all(|s| s.is_finite() && *s > 0.0)
        && model.output.std.iter().all(|s| s.is_finite() && *s > 0.0);
    if finite {
        Ok(())
    } else {
        Err(LearnError::MalformedModel {
            what: "SvrModel: non-finite value, gamma <= 0 or std <= 0",
        })
    }
}
