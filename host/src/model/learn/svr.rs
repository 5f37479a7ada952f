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

mod point;

/// Conjugate SMO's previous direction (both solvers): `d` by position, its
/// support (listed, and flagged by position), `Q d` over the active set and
/// `d^T Q d`; `curvature` is `None` when there is no direction.
struct Direction {
    d: Vec<f64>,
    support: Vec<usize>,
    in_support: Vec<bool>,
    q: Vec<f64>,
    curvature: Option<f64>,
}

impl Direction {
    fn new(n: usize) -> Direction {
        Direction {
            d: vec![0.0; n],
            support: Vec::new(),
            in_support: vec![false; n],
            q: vec![0.0; n],
            curvature: None,
        }
    }

    /// Forgets the direction (clears only its support's positions).
    fn forget(&mut self) {
        for &t in &self.support {
            self.d[t] = 0.0;
            self.in_support[t] = false;
        }
        self.support.clear();
        self.curvature = None;
    }

    /// After shrinking moved positions: lists the support again among the
    /// `active` first positions; forgets the direction if part of it left
    /// the active set (its `Q d` is only kept there) or the active set grew
    /// from `before` (unshrinking), clearing every position the old support
    /// may occupy.
    fn relist(&mut self, active: usize, before: usize) {
        if self.curvature.is_none() {
            return;
        }
        let kept = self.support.len();
        self.support.clear();
        let in_support = &self.in_support;
        self.support.extend((0..active).filter(|&t| in_support[t]));
        if active > before || self.support.len() != kept {
            self.d.fill(0.0);
            self.in_support.fill(false);
            self.support.clear();
            self.curvature = None;
        }
    }
}

use super::standardize::{self, apply, mode_targets, output_position};
use super::{
    check_range, validate_pairs, validate_points, Deadline, ErrorStats, LearnError, OutputMode,
    SvrModel,
};

/// Variables a conjugate direction may span before it restarts: measured on
/// the black-box grid (C 300, epsilon 0.005), 64 keeps the iteration count of
/// unbounded directions (0.55 and 0.77 million on two axes) at 3/4 of the
/// time; 16 costs 10 % more iterations.
const MAX_DIRECTION_SUPPORT: usize = 64;

/// libsvm's `TAU`: the curvature used when a pair's `quad_coef` is not positive.
const TAU: f64 = 1e-12;

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

#[derive(Clone, Copy, PartialEq, Eq)]
enum Status {
    Lower,
    Upper,
    Free,
}

/// libsvm's `Solver` specialised to epsilon-SVR with `Cp = Cn = C`.
/// Arrays are indexed by the current (shrinking-permuted) position.
struct Solver<'a> {
    k: &'a KernelMatrix,
    l: usize,
    y: Vec<f64>,
    /// Training point behind each variable.
    index: Vec<usize>,
    qd: Vec<f64>,
    p: Vec<f64>,
    alpha: Vec<f64>,
    status: Vec<Status>,
    g: Vec<f64>,
    /// Gradient part from variables at the upper bound (for unshrinking).
    g_bar: Vec<f64>,
    active_set: Vec<usize>,
    active_size: usize,
    c: f64,
    tol: f64,
    unshrink: bool,
    buf_i: Vec<f64>,
    buf_j: Vec<f64>,
    /// Whether each variable may move up (`I_up`: `y beta` can grow) or down
    /// (`I_low`), kept with `status` so that the selection needs no branch.
    up_ok: Vec<bool>,
    low_ok: Vec<bool>,
    /// The second-order decrease of each candidate j (selection scratch).
    obj_buf: Vec<f64>,
    /// Conjugate SMO's previous direction.
    direction: Direction,
}

/// `out[t] = y_i y_t K(point_i, point_t)` for `t < out.len()`.
fn fill_q(krow: &[f32], yi: f64, y: &[f64], index: &[usize], out: &mut [f64]) {
    for ((o, &yt), &it) in out.iter_mut().zip(y).zip(index) {
        *o = yi * yt * f64::from(krow[it]);
    }
}

impl<'a> Solver<'a> {
    /// The dual over the kernel rows `points` (targets `z[i]` at
    /// `points[i]`), from `warm` coefficients `alpha_i - alpha*_i` (feasible:
    /// `|c_i| <= C`, summing to 0) or from 0.
    fn new(
        k: &'a KernelMatrix,
        points: &[usize],
        z: &[f64],
        epsilon: f64,
        c: f64,
        tol: f64,
        warm: Option<&[f64]>,
    ) -> Self {
        let n = points.len();
        let l = 2 * n;
        let mut y = vec![1.0; l];
        let mut index = vec![0; l];
        let mut p = vec![0.0; l];
        let mut qd = vec![0.0; l];
        for i in 0..n {
            y[i + n] = -1.0;
            index[i] = points[i];
            index[i + n] = points[i];
            p[i] = epsilon - z[i];
            p[i + n] = epsilon + z[i];
            // libsvm keeps the diagonal in double: K(x, x) = 1 for the RBF.
            qd[i] = 1.0;
            qd[i + n] = qd[i];
        }
        let mut s = Solver {
            k,
            l,
            y,
            index,
            qd,
            // All alphas start at 0, so the gradient starts at p and G_bar at 0.
            g: p.clone(),
            p,
            alpha: vec![0.0; l],
            status: vec![Status::Lower; l],
            g_bar: vec![0.0; l],
            active_set: (0..l).collect(),
            active_size: l,
            c,
            tol,
            unshrink: false,
            buf_i: vec![0.0; l],
            buf_j: vec![0.0; l],
            up_ok: vec![false; l],
            low_ok: vec![false; l],
            obj_buf: vec![0.0; l],
            direction: Direction::new(l),
        };
        for t in 0..l {
            s.update_status(t);
        }
        if let Some(coef) = warm {
            s.start_from(points, coef);
        }
        s
    }

    /// Set `beta` from coefficients and compute the gradient and G_bar with
    /// one pass over the kernel rows of the support vectors.
    fn start_from(&mut self, points: &[usize], coef: &[f64]) {
        let n = points.len();
        let c = self.c;
        for (i, &ci) in coef.iter().enumerate() {
            // Exactly at the bound when within rounding of it (a warm start
            // scaled from another C).
            let a = ci.abs().min(c);
            let a = if a >= c * (1.0 - 1e-12) { c } else { a };
            if ci > 0.0 {
                self.alpha[i] = a;
            } else if ci < 0.0 {
                self.alpha[i + n] = a;
            }
        }
        for t in 0..self.l {
            self.update_status(t);
        }
        // u_t = sum_i c_i K(i, t), ub_t = C sum_{|c_i| = C} sign(c_i) K(i, t).
        let mut u = vec![0.0; n];
        let mut ub = vec![0.0; n];
        for i in 0..n {
            let ci = self.alpha[i] - self.alpha[i + n];
            if ci == 0.0 {
                continue;
            }
            let at_bound = self.is_upper(i) || self.is_upper(i + n);
            let row = self.k.row(points[i]);
            for ((ut, ubt), &pt) in u.iter_mut().zip(ub.iter_mut()).zip(points) {
                let kv = f64::from(row[pt]);
                *ut += ci * kv;
                if at_bound {
                    *ubt += ci * kv;
                }
            }
        }
        for t in 0..n {
            self.g[t] = u[t] + self.p[t];
            self.g[t + n] = -u[t] + self.p[t + n];
            self.g_bar[t] = ub[t];
            self.g_bar[t + n] = -ub[t];
        }
    }

    fn update_status(&mut self, i: usize) {
        let st = if self.alpha[i] >= self.c {
            Status::Upper
        } else if self.alpha[i] <= 0.0 {
            Status::Lower
        } else {
            Status::Free
        };
        self.status[i] = st;
        let (not_upper, not_lower) = (st != Status::Upper, st != Status::Lower);
        if self.y[i] > 0.0 {
            self.up_ok[i] = not_upper;
            self.low_ok[i] = not_lower;
        } else {
            self.up_ok[i] = not_lower;
            self.low_ok[i] = not_upper;
        }
    }

    fn is_upper(&self, i: usize) -> bool {
        self.status[i] == Status::Upper
    }
    fn is_lower(&self, i: usize) -> bool {
        self.status[i] == Status::Lower
    }

    fn q_into_i(&mut self, i: usize, len: usize) {
        let krow = self.k.row(self.index[i]);
        fill_q(
            krow,
            self.y[i],
            &self.y[..len],
            &self.index[..len],
            &mut self.buf_i[..len],
        );
    }
    fn q_into_j(&mut self, j: usize, len: usize) {
        let krow = self.k.row(self.index[j]);
        fill_q(
            krow,
            self.y[j],
            &self.y[..len],
            &self.index[..len],
            &mut self.buf_j[..len],
        );
    }

    fn swap_index(&mut self, i: usize, j: usize) {
        self.y.swap(i, j);
        self.index.swap(i, j);
        self.qd.swap(i, j);
        self.p.swap(i, j);
        self.alpha.swap(i, j);
        self.status.swap(i, j);
        self.g.swap(i, j);
        self.g_bar.swap(i, j);
        self.active_set.swap(i, j);
        self.up_ok.swap(i, j);
        self.low_ok.swap(i, j);
        self.direction.d.swap(i, j);
        self.direction.in_support.swap(i, j);
        self.direction.q.swap(i, j);
    }

    /// Recompute the gradient of the shrunk variables from G_bar and the free
    /// variables (libsvm's `reconstruct_gradient`).
    fn reconstruct_gradient(&mut self) {
        let (act, l) = (self.active_size, self.l);
        if act == l {
            return;
        }
        for j in act..l {
            self.g[j] = self.g_bar[j] + self.p[j];
        }
        let nr_free = (0..act).filter(|&j| self.status[j] == Status::Free).count();
        // Pick the cheaper loop order, as libsvm does.
        if nr_free * l > 2 * act * (l - act) {
            for i in act..l {
                self.q_into_i(i, act);
                let mut acc = 0.0;
                for j in 0..act {
                    if self.status[j] == Status::Free {
                        acc += self.alpha[j] * self.buf_i[j];
                    }
                }
                self.g[i] += acc;
            }
        } else {
            for i in 0..act {
                if self.status[i] == Status::Free {
                    self.q_into_i(i, l);
                    let ai = self.alpha[i];
                    for j in act..l {
                        self.g[j] += ai * self.buf_i[j];
                    }
                }
            }
        }
    }

    /// WSS2: i maximizes the violation, j maximizes the second-order decrease.
    ///
    /// libsvm's selection, value for value and with its tie rules (the last
    /// of equal candidates wins), written as branch-free passes over the
    /// active set: the branchy loop spent two thirds of the solver's time on
    /// mispredicted branches.
    fn select_working_set(&mut self) -> Option<(usize, usize)> {
        let act = self.active_size;
        let (y, g) = (&self.y[..act], &self.g[..act]);
        let (up_ok, low_ok) = (&self.up_ok[..act], &self.low_ok[..act]);
        // gmax = max over I_up of -y G; gmax2 = max over I_low of y G (it
        // does not depend on i).
        let mut gmax = [f64::NEG_INFINITY; 4];
        let mut gmax2 = [f64::NEG_INFINITY; 4];
        let mut t = 0;
        while t + 4 <= act {
            for k in 0..4 {
                let yg = y[t + k] * g[t + k];
                let up = if up_ok[t + k] { -yg } else { f64::NEG_INFINITY };
                let low = if low_ok[t + k] { yg } else { f64::NEG_INFINITY };
                gmax[k] = if up > gmax[k] { up } else { gmax[k] };
                gmax2[k] = if low > gmax2[k] { low } else { gmax2[k] };
            }
            t += 4;
        }
        for r in t..act {
            let yg = y[r] * g[r];
            if up_ok[r] && -yg > gmax[0] {
                gmax[0] = -yg;
            }
            if low_ok[r] && yg > gmax2[0] {
                gmax2[0] = yg;
            }
        }
        let gmax = gmax
            .iter()
            .fold(f64::NEG_INFINITY, |m, &v| if v > m { v } else { m });
        let gmax2 = gmax2
            .iter()
            .fold(f64::NEG_INFINITY, |m, &v| if v > m { v } else { m });
        if gmax == f64::NEG_INFINITY {
            return None;
        }
        // i: the last variable of I_up reaching gmax.
        let i = (0..act)
            .rev()
            .find(|&r| up_ok[r] && -(y[r] * g[r]) == gmax)?;
        let (krow, index) = (self.k.row(self.index[i]), &self.index[..act]);
        let qdi = self.qd[i];
        let qd = &self.qd[..act];
        let obj = &mut self.obj_buf[..act];
        let mut best = [f64::INFINITY; 4];
        let mut t = 0;
        let cand = |r: usize| -> f64 {
            let grad_diff = gmax + y[r] * g[r];
            // quad = Q_ii + Q_jj - 2 y_i y_j Q_ij = K_ii + K_jj - 2 K_ij.
            let quad = qdi + qd[r] - 2.0 * f64::from(krow[index[r]]);
            let quad = if quad > 0.0 { quad } else { TAU };
            let od = -(grad_diff * grad_diff) / quad;
            if low_ok[r] && grad_diff > 0.0 {
                od
            } else {
                f64::INFINITY
            }
        };
        while t + 4 <= act {
            for k in 0..4 {
                let v = cand(t + k);
                obj[t + k] = v;
                best[k] = if v < best[k] { v } else { best[k] };
            }
            t += 4;
        }
        for (r, o) in obj.iter_mut().enumerate().skip(t) {
            let v = cand(r);
            *o = v;
            if v < best[0] {
                best[0] = v;
            }
        }
        if gmax + gmax2 < self.tol {
            return None;
        }
        let best = best
            .iter()
            .fold(f64::INFINITY, |m, &v| if v < m { v } else { m });
        if best == f64::INFINITY {
            return None;
        }
        let j = (0..act).rev().find(|&r| obj[r] == best)?;
        Some((i, j))
    }

    fn be_shrunk(&self, i: usize, gmax1: f64, gmax2: f64) -> bool {
        if self.is_upper(i) {
            if self.y[i] > 0.0 {
                -self.g[i] > gmax1
            } else {
                -self.g[i] > gmax2
            }
        } else if self.is_lower(i) {
            if self.y[i] > 0.0 {
                self.g[i] > gmax2
            } else {
                self.g[i] > gmax1
            }
        } else {
            false
        }
    }

    fn do_shrinking(&mut self) {
        let mut gmax1 = f64::NEG_INFINITY; // max { -y_i grad_i | i in I_up }
        let mut gmax2 = f64::NEG_INFINITY; // max { y_i grad_i | i in I_low }
        for i in 0..self.active_size {
            let g = self.g[i];
            if self.y[i] > 0.0 {
                if !self.is_upper(i) && -g >= gmax1 {
                    gmax1 = -g;
                }
                if !self.is_lower(i) && g >= gmax2 {
                    gmax2 = g;
                }
            } else {
                if !self.is_upper(i) && -g >= gmax2 {
                    gmax2 = -g;
                }
                if !self.is_lower(i) && g >= gmax1 {
                    gmax1 = g;
                }
            }
        }
        // Close to the optimum: unshrink once, so that variables shrunk early
        // on a poor gradient estimate get another look.
        if !self.unshrink && gmax1 + gmax2 <= self.tol * 10.0 {
            self.unshrink = true;
            self.reconstruct_gradient();
            self.active_size = self.l;
        }
        let mut i = 0;
        while i < self.active_size {
            if self.be_shrunk(i, gmax1, gmax2) {
                self.active_size -= 1;
                while self.active_size > i {
                    if !self.be_shrunk(self.active_size, gmax1, gmax2) {
                        self.swap_index(i, self.active_size);
                        break;
                    }
                    self.active_size -= 1;
                }
            }
            i += 1;
        }
    }

    fn calculate_rho(&self) -> f64 {
        let mut nr_free = 0usize;
        let mut ub = f64::INFINITY;
        let mut lb = f64::NEG_INFINITY;
        let mut sum_free = 0.0;
        for i in 0..self.active_size {
            let yg = self.y[i] * self.g[i];
            if self.is_upper(i) {
                if self.y[i] < 0.0 {
                    ub = ub.min(yg);
                } else {
                    lb = lb.max(yg);
                }
            } else if self.is_lower(i) {
                if self.y[i] > 0.0 {
                    ub = ub.min(yg);
                } else {
                    lb = lb.max(yg);
                }
            } else {
                nr_free += 1;
                sum_free += yg;
            }
        }
        if nr_free > 0 {
            sum_free / nr_free as f64
        } else {
            (ub + lb) / 2.0
        }
    }

    /// Optimize the pair (i, j).
    fn step(&mut self, i: usize, j: usize) {
        let act = self.active_size;
        let c = self.c;
        let (old_ai, old_aj) = (self.alpha[i], self.alpha[j]);
        let (ki, cols) = (self.k.row(self.index[i]), &self.index[..act]);
        let qij = self.y[i] * self.y[j] * f64::from(ki[cols[j]]);
        let (mut ai, mut aj) = (old_ai, old_aj);
        if self.y[i] != self.y[j] {
            let mut quad = self.qd[i] + self.qd[j] + 2.0 * qij;
            if quad <= 0.0 {
                quad = TAU;
            }
            let delta = (-self.g[i] - self.g[j]) / quad;
            let diff = ai - aj;
            ai += delta;
            aj += delta;
            if diff > 0.0 {
                if aj < 0.0 {
                    aj = 0.0;
                    ai = diff;
                }
            } else if ai < 0.0 {
                ai = 0.0;
                aj = -diff;
            }
            // Cp = Cn = C, so libsvm's `diff > C_i - C_j` is `diff > 0`.
            if diff > 0.0 {
                if ai > c {
                    ai = c;
                    aj = c - diff;
                }
            } else if aj > c {
                aj = c;
                ai = c + diff;
            }
        } else {
            let mut quad = self.qd[i] + self.qd[j] - 2.0 * qij;
            if quad <= 0.0 {
                quad = TAU;
            }
            let delta = (self.g[i] - self.g[j]) / quad;
            let sum = ai + aj;
            ai -= delta;
            aj += delta;
            if sum > c {
                if ai > c {
                    ai = c;
                    aj = sum - c;
                }
            } else if aj < 0.0 {
                aj = 0.0;
                ai = sum;
            }
            if sum > c {
                if aj > c {
                    aj = c;
                    ai = sum - c;
                }
            } else if ai < 0.0 {
                ai = 0.0;
                aj = sum;
            }
        }
        self.alpha[i] = ai;
        self.alpha[j] = aj;
        let dai = ai - old_ai;
        let daj = aj - old_aj;
        // G_t += Q_ti dai + Q_tj daj = y_t (y_i K_ti dai + y_j K_tj daj),
        // the same rounding as with the signed Q rows.
        let (yi, yj) = (self.y[i], self.y[j]);
        let (kj, _) = (self.k.row(self.index[j]), &self.index[..act]);
        for ((g, &yt), &it) in self.g[..act].iter_mut().zip(&self.y[..act]).zip(cols) {
            *g += yt * (yi * (f64::from(ki[it]) * dai) + yj * (f64::from(kj[it]) * daj));
        }
        let (ui, uj) = (self.is_upper(i), self.is_upper(j));
        self.update_status(i);
        self.update_status(j);
        let l = self.l;
        if ui != self.is_upper(i) {
            self.q_into_i(i, l);
            let s = if ui { -c } else { c };
            for (gb, q) in self.g_bar.iter_mut().zip(&self.buf_i) {
                *gb += s * q;
            }
        }
        if uj != self.is_upper(j) {
            self.q_into_j(j, l);
            let s = if uj { -c } else { c };
            for (gb, q) in self.g_bar.iter_mut().zip(&self.buf_j) {
                *gb += s * q;
            }
        }
    }

    fn reset_direction(&mut self) {
        self.direction.forget();
    }

    /// Conjugate SMO step for the WSS2 pair (i, j): the pair's direction
    /// `u = y_i e_i - y_j e_j` plus a multiple of the previous direction that
    /// makes the two Q-conjugate, then an exact line search clipped to the
    /// box. Falls back to the plain SMO step (and forgets the direction) when
    /// that would not be a useful descent step.
    fn conjugate_step(&mut self, i: usize, j: usize) {
        let act = self.active_size;
        let (yi, yj) = (self.y[i], self.y[j]);
        // Restart (a plain step) once the direction spans MAX_DIRECTION_SUPPORT
        // variables: its upkeep grows with the support, its benefit does not.
        let beta = match self.direction.curvature {
            Some(curv) if self.direction.support.len() < MAX_DIRECTION_SUPPORT => {
                -(yi * self.direction.q[i] - yj * self.direction.q[j]) / curv
            }
            _ => 0.0,
        };
        if beta == 0.0 || !beta.is_finite() {
            self.reset_direction();
            self.step(i, j);
            self.start_direction(i, j);
            return;
        }
        // Candidate direction d = u + beta d_prev; Q d is needed on the
        // support for the line search, over the active set for the gradient.
        let (ki, cols) = (self.k.row(self.index[i]), &self.index[..act]);
        let (kj, _) = (self.k.row(self.index[j]), &self.index[..act]);
        for &t in &self.direction.support {
            self.direction.d[t] *= beta;
        }
        for (v, add) in [(i, yi), (j, -yj)] {
            self.direction.d[v] += add;
            if !self.direction.in_support[v] {
                self.direction.in_support[v] = true;
                self.direction.support.push(v);
            }
        }
        let q_dir_at = |t: usize| {
            let it = cols[t];
            self.y[t] * (f64::from(ki[it]) - f64::from(kj[it])) + beta * self.direction.q[t]
        };
        let mut gd = 0.0;
        let mut dqd = 0.0;
        for &t in &self.direction.support {
            let d = self.direction.d[t];
            gd += self.g[t] * d;
            dqd += d * q_dir_at(t);
        }
        let t_opt = -gd / dqd;
        if !(gd < 0.0 && dqd > 0.0 && t_opt.is_finite()) {
            self.reset_direction();
            self.step(i, j);
            self.start_direction(i, j);
            return;
        }
        // The box: the full step usually fits (a division only for the
        // variables it would push out).
        let c = self.c;
        let mut t_max = f64::INFINITY;
        let mut blocking = 0;
        for &t in &self.direction.support {
            let d = self.direction.d[t];
            let a = self.alpha[t] + t_opt * d;
            if a < 0.0 || a > c {
                let room = if d > 0.0 {
                    (c - self.alpha[t]) / d
                } else {
                    -self.alpha[t] / d
                };
                if room < t_max {
                    t_max = room;
                    blocking = t;
                }
            }
        }
        // (Also false for NaN.)
        if t_max.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            self.reset_direction();
            self.step(i, j);
            self.start_direction(i, j);
            return;
        }
        let clipped = t_max < t_opt;
        let t = if clipped { t_max } else { t_opt };
        // Q d and the gradient in one pass.
        for (((w, g), &yt), &it) in self.direction.q[..act]
            .iter_mut()
            .zip(self.g[..act].iter_mut())
            .zip(&self.y[..act])
            .zip(cols)
        {
            *w = yt * (f64::from(ki[it]) - f64::from(kj[it])) + beta * *w;
            *g += t * *w;
        }
        let l = self.l;
        for k in 0..self.direction.support.len() {
            let v = self.direction.support[k];
            let was_upper = self.is_upper(v);
            let mut a = (self.alpha[v] + t * self.direction.d[v]).clamp(0.0, c);
            if clipped && v == blocking {
                a = if self.direction.d[v] > 0.0 { c } else { 0.0 };
            }
            self.alpha[v] = a;
            if a <= 0.0 || a >= c || self.status[v] != Status::Free {
                self.update_status(v);
            }
            if was_upper != self.is_upper(v) {
                self.q_into_i(v, l);
                let s = if was_upper { -c } else { c };
                for (gb, q) in self.g_bar.iter_mut().zip(&self.buf_i) {
                    *gb += s * q;
                }
            }
        }
        if clipped {
            self.reset_direction();
        } else {
            self.direction.curvature = Some(dqd);
        }
    }

    /// After a plain SMO step on (i, j): remember its direction and Q d so
    /// that the next step can be made conjugate to it.
    fn start_direction(&mut self, i: usize, j: usize) {
        let act = self.active_size;
        let (yi, yj) = (self.y[i], self.y[j]);
        let (ki, cols) = (self.k.row(self.index[i]), &self.index[..act]);
        let (kj, _) = (self.k.row(self.index[j]), &self.index[..act]);
        for ((w, &yt), &it) in self.direction.q[..act]
            .iter_mut()
            .zip(&self.y[..act])
            .zip(cols)
        {
            *w = yt * (f64::from(ki[it]) - f64::from(kj[it]));
        }
        self.direction.d[i] = yi;
        self.direction.d[j] = -yj;
        self.direction.in_support[i] = true;
        self.direction.in_support[j] = true;
        self.direction.support.push(i);
        self.direction.support.push(j);
        // The plain step is exact along u unless it was clipped: keep the
        // direction only when both variables stayed strictly inside.
        let free = |v: usize| self.status[v] == Status::Free;
        self.direction.curvature = if free(i) && free(j) {
            Some(self.qd[i] + self.qd[j] - 2.0 * f64::from(ki[cols[j]]))
        } else {
            None
        };
        if self.direction.curvature.is_none() {
            self.reset_direction();
        }
    }

    /// Run SMO; returns (iterations, converged).
    fn solve(&mut self, cfg: &SolverConfig, max_iter: usize, deadline: Deadline) -> (usize, bool) {
        run_smo(self, cfg.shrinking, cfg.conjugate, max_iter, deadline)
    }
}

impl Smo for Solver<'_> {
    fn shrink_period(&self) -> usize {
        self.l.min(1000)
    }
    fn shrunk(&self) -> bool {
        self.active_size < self.l
    }
    fn shrink(&mut self) {
        let before = self.active_size;
        self.do_shrinking();
        // Positions moved: list the direction's support again.
        self.direction.relist(self.active_size, before);
    }
    fn working_set(&mut self) -> Option<(usize, usize)> {
        self.select_working_set()
    }
    fn unshrink(&mut self, _resume: bool) {
        self.reconstruct_gradient();
        self.active_size = self.l;
    }
    fn forget_direction(&mut self) {
        self.reset_direction();
    }
    fn smo_step(&mut self, i: usize, j: usize, conjugate: bool) {
        if conjugate {
            self.conjugate_step(i, j);
        } else {
            self.step(i, j);
        }
    }
}

/// What libsvm's SMO loop asks of a solver (the 2n-variable one and the
/// per-point one, [`run_smo`]).
trait Smo {
    /// Iterations between shrinkings: libsvm's `min(l, 1000)` with `l` its
    /// 2n variables.
    fn shrink_period(&self) -> usize;
    /// Whether some variables are out of the active set.
    fn shrunk(&self) -> bool;
    /// Shrink the active set (and re-list the conjugate direction).
    fn shrink(&mut self);
    /// The WSS2 pair, `None` when the active set is optimal.
    fn working_set(&mut self) -> Option<(usize, usize)>;
    /// Every variable active again, with its gradient rebuilt; `resume`:
    /// the loop goes on (rebuild what the steps read), else it has ended.
    fn unshrink(&mut self, resume: bool);
    /// Forget the conjugate direction.
    fn forget_direction(&mut self);
    /// One SMO step on the pair (conjugate or plain).
    fn smo_step(&mut self, i: usize, j: usize, conjugate: bool);
}

/// libsvm's SMO loop: shrink every [`Smo::shrink_period`] iterations,
/// check the deadline there, and when the active set is optimal unshrink
/// and look again; returns (iterations, converged).
fn run_smo<S: Smo>(
    s: &mut S,
    shrinking: bool,
    conjugate: bool,
    max_iter: usize,
    deadline: Deadline,
) -> (usize, bool) {
    let period = s.shrink_period();
    let mut iter = 0;
    let mut counter = period + 1;
    let mut converged = false;
    while iter < max_iter {
        counter -= 1;
        if counter == 0 {
            counter = period;
            if shrinking {
                s.shrink();
            }
            if deadline.passed() {
                break;
            }
        }
        let (i, j) = match s.working_set() {
            Some(pair) => pair,
            None => {
                // Optimal on the active set: check all variables.
                s.forget_direction();
                s.unshrink(true);
                match s.working_set() {
                    Some(pair) => {
                        counter = 1; // shrink again at the next iteration
                        pair
                    }
                    None => {
                        converged = true;
                        break;
                    }
                }
            }
        };
        iter += 1;
        s.smo_step(i, j, conjugate);
    }
    if s.shrunk() {
        s.unshrink(false);
    }
    (iter, converged)
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
