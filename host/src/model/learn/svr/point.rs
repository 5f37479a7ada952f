//! The epsilon-SVR dual in one variable per training point
//! (decision record 0019, `docs/decisions/0019-blackbox-per-point-dual.md`):
//! `beta_i = alpha_i - alpha*_i` in `[-C, C]`,
//!
//! ```text
//! minimize  beta^T K beta / 2 - z^T beta + eps sum |beta_i|   s.t.  sum beta_i = 0,
//! ```
//!
//! libsvm's 2n-variable dual with `alpha_i alpha*_i = 0` (which holds at every
//! SMO iterate that starts from such a point). The two gradients of a point
//! in the 2n form are `g_i + eps` and `eps - g_i` for `g = K beta - z`, so one
//! gradient of n entries carries them both: each SMO iteration updates n
//! entries instead of 2n, and the selection scans n.
//!
//! Everything else is libsvm's, translated: the violations of a point are its
//! one-sided derivatives (up: `-g_i - eps` for `beta_i >= 0`, `-g_i + eps`
//! below 0; down: `g_i + eps` above 0, `g_i - eps` at or below 0), which are
//! the largest of its two variables' libsvm violations, so the maximal
//! violation and the stopping rule (`m - M < tol`) are libsvm's to the
//! rounding of `g`. Steps stop at the kink `beta_i = 0` exactly as libsvm's
//! stop at `alpha_i = 0`. WSS2, shrinking (a point is shrunk when both its
//! variables would be), the unshrinking near the end, `rho` and the objective
//! are libsvm's formulas on the same values. The conjugate step is the 2n
//! solver's (`Solver::conjugate_step`) on points.
//!
//! The halving alone gained nothing measurable (after shrinking the active
//! sets are small either way); the speed (2.5 times the 2n solver's per
//! iteration on the black-box grid) comes from what this layout allows:
//! each solver keeps a contiguous copy of its kernel block, permuted with
//! the active set, so the passes read rows without gathers; each gradient
//! pass also computes the next iteration's maximal violation (the first half
//! of the selection), so an iteration is two passes over the active points,
//! the gradient update and the choice of j; that choice compares fractions
//! instead of dividing; and both passes run on AVX2 when the CPU has it,
//! with the scalar passes' operations in the same order on the same 16 lanes
//! (no FMA), so the path does not depend on the CPU.
//!
//! The solver's state and steps are here; the passes, scalar and AVX2, are
//! in `passes`.

mod passes;

use super::{run_smo, Direction, KernelMatrix, Smo, MAX_DIRECTION_SUPPORT, TAU};
use crate::model::learn::Deadline;
use passes::{choose_j, conjugate_pass, have_avx2, plain_pass, reduce_max, Conjugate, LANES};

/// Largest problem solved here: each solver keeps its own n^2 f32 kernel
/// block (144 MB at 6000 points, three at once in a three-axis fit); larger
/// problems go to the 2n solver, which reads the shared kernel.
pub(super) const MAX_BLOCK_POINTS: usize = 6000;

pub(super) struct PointSolver<'a> {
    k: &'a KernelMatrix,
    n: usize,
    /// Kernel row of the point at each (shrinking-permuted) position.
    index: Vec<usize>,
    z: Vec<f64>,
    pub(super) beta: Vec<f64>,
    /// `K beta - z` (exact on the active set, rebuilt on demand elsewhere).
    g: Vec<f64>,
    /// `sum_{|beta_j| = C} beta_j K_tj` over every point (for unshrinking).
    g_bar: Vec<f64>,
    /// The up violation is `-g + up_off` (`-inf` at `beta = C`), the down
    /// violation `g + low_off` (`-inf` at `beta = -C`).
    up_off: Vec<f64>,
    low_off: Vec<f64>,
    /// The kernel between positions, row-major with stride n, consistent
    /// for positions below `block_len` (>= `active_size`): the hot passes
    /// read contiguous rows instead of gathering from the shared kernel.
    block: Vec<f32>,
    block_len: usize,
    /// Position swaps not yet applied to the block.
    swaps: Vec<(usize, usize)>,
    /// Run the hot passes on AVX2 (same results as without).
    avx2: bool,
    /// Conjugate steps (set by `solve`).
    conjugate: bool,
    /// Original position of the point at each position.
    pub(super) active_set: Vec<usize>,
    active_size: usize,
    c: f64,
    eps: f64,
    tol: f64,
    unshrink: bool,
    /// The maximal up violation and its point, and the maximal down
    /// violation, as the last gradient pass left them (None: recompute).
    top: Option<(f64, usize, f64)>,
    /// Conjugate SMO's previous direction, as in the 2n solver.
    direction: Direction,
}

impl<'a> PointSolver<'a> {
    pub(super) fn new(
        k: &'a KernelMatrix,
        points: &[usize],
        z: &[f64],
        epsilon: f64,
        c: f64,
        tol: f64,
        warm: Option<&[f64]>,
    ) -> Self {
        let n = points.len();
        let mut s = PointSolver {
            k,
            n,
            index: points.to_vec(),
            z: z.to_vec(),
            beta: vec![0.0; n],
            g: z.iter().map(|v| -v).collect(),
            g_bar: vec![0.0; n],
            up_off: vec![0.0; n],
            low_off: vec![0.0; n],
            block: Vec::new(),
            block_len: 0,
            swaps: Vec::new(),
            avx2: have_avx2(),
            conjugate: false,
            active_set: (0..n).collect(),
            active_size: n,
            c,
            eps: epsilon,
            tol,
            unshrink: false,
            top: None,
            direction: Direction::new(n),
        };
        if let Some(coef) = warm {
            s.start_from(coef);
        }
        for t in 0..n {
            s.update_offsets(t);
        }
        s.build_block();
        s
    }

    /// The kernel block over every position (n^2 entries).
    fn build_block(&mut self) {
        let n = self.n;
        self.block.resize(n * n, 0.0);
        for (row, &ir) in self.block.chunks_exact_mut(n).zip(&self.index) {
            let krow = self.k.row(ir);
            for (v, &is) in row.iter_mut().zip(&self.index) {
                *v = krow[is];
            }
        }
        self.block_len = n;
    }

    /// Row `r` of the block over the active positions.
    fn brow(&self, r: usize) -> &[f32] {
        &self.block[r * self.n..r * self.n + self.active_size]
    }

    /// Every point active again (after reconstructing the gradient).
    fn activate_all(&mut self) {
        self.reconstruct_gradient();
        self.active_size = self.n;
        if self.block_len < self.n {
            self.build_block();
        }
        self.top = None;
    }

    /// Set beta from coefficients (within rounding of C counts as C) and
    /// compute g and G_bar with one pass over the support vectors' rows.
    fn start_from(&mut self, coef: &[f64]) {
        let c = self.c;
        for (b, &ci) in self.beta.iter_mut().zip(coef) {
            let a = ci.abs().min(c);
            let a = if a >= c * (1.0 - 1e-12) { c } else { a };
            *b = if ci > 0.0 {
                a
            } else if ci < 0.0 {
                -a
            } else {
                0.0
            };
        }
        let mut u = vec![0.0; self.n];
        let mut ub = vec![0.0; self.n];
        for i in 0..self.n {
            let bi = self.beta[i];
            if bi == 0.0 {
                continue;
            }
            let at_bound = bi.abs() >= c;
            let row = self.k.row(self.index[i]);
            for ((ut, ubt), &pt) in u.iter_mut().zip(ub.iter_mut()).zip(&self.index) {
                let kv = f64::from(row[pt]);
                *ut += bi * kv;
                if at_bound {
                    *ubt += bi * kv;
                }
            }
        }
        for ((g, u), z) in self.g.iter_mut().zip(&u).zip(&self.z) {
            *g = u - z;
        }
        self.g_bar = ub;
    }

    fn update_offsets(&mut self, t: usize) {
        let (b, c, e) = (self.beta[t], self.c, self.eps);
        self.up_off[t] = if b >= c {
            f64::NEG_INFINITY
        } else if b < 0.0 {
            e
        } else {
            -e
        };
        self.low_off[t] = if b <= -c {
            f64::NEG_INFINITY
        } else if b > 0.0 {
            e
        } else {
            -e
        };
    }

    fn is_free(&self, t: usize) -> bool {
        let b = self.beta[t];
        b != 0.0 && b.abs() < self.c
    }

    fn swap_index(&mut self, i: usize, j: usize) {
        self.index.swap(i, j);
        self.z.swap(i, j);
        self.beta.swap(i, j);
        self.g.swap(i, j);
        self.g_bar.swap(i, j);
        self.up_off.swap(i, j);
        self.low_off.swap(i, j);
        self.active_set.swap(i, j);
        self.direction.d.swap(i, j);
        self.direction.in_support.swap(i, j);
        self.direction.q.swap(i, j);
        self.swaps.push((i, j));
    }

    /// Apply the swaps since the last call to the block (rows, then the
    /// columns of each row in one go: a column swap at a time would stride
    /// through every row), keeping it consistent over the first `len`
    /// positions.
    fn permute_block(&mut self, len: usize) {
        let (n, old) = (self.n, self.block_len);
        if self.swaps.iter().any(|&(i, j)| i.max(j) >= old) {
            self.swaps.clear();
            self.build_block();
            return;
        }
        for &(i, j) in &self.swaps {
            let (a, b) = (i.min(j), i.max(j));
            let (head, tail) = self.block.split_at_mut(b * n);
            head[a * n..a * n + old].swap_with_slice(&mut tail[..old]);
        }
        if !self.swaps.is_empty() {
            for row in self.block.chunks_exact_mut(n).take(len) {
                for &(i, j) in &self.swaps {
                    row.swap(i, j);
                }
            }
        }
        self.swaps.clear();
        self.block_len = len.min(old);
    }

    /// `g_t = G_bar_t - z_t + sum_{free j} beta_j K_tj` for the shrunk
    /// points (libsvm's `reconstruct_gradient`, its loop-order choice).
    fn reconstruct_gradient(&mut self) {
        let (act, n) = (self.active_size, self.n);
        if act == n {
            return;
        }
        for t in act..n {
            self.g[t] = self.g_bar[t] - self.z[t];
        }
        let nr_free = (0..act).filter(|&j| self.is_free(j)).count();
        if nr_free * n > 2 * act * (n - act) {
            for t in act..n {
                let row = self.k.row(self.index[t]);
                let mut acc = 0.0;
                for j in 0..act {
                    if self.is_free(j) {
                        acc += self.beta[j] * f64::from(row[self.index[j]]);
                    }
                }
                self.g[t] += acc;
            }
        } else {
            for j in 0..act {
                if self.is_free(j) {
                    let row = self.k.row(self.index[j]);
                    let bj = self.beta[j];
                    for t in act..n {
                        self.g[t] += bj * f64::from(row[self.index[t]]);
                    }
                }
            }
        }
        self.top = None;
    }

    /// The maximal up violation (and its point) and the maximal down
    /// violation over the active set.
    fn scan_top(&self) -> (f64, usize, f64) {
        let act = self.active_size;
        let (g, up, low) = (&self.g[..act], &self.up_off[..act], &self.low_off[..act]);
        let mut best = [f64::NEG_INFINITY; LANES];
        let mut at = [0usize; LANES];
        let mut best2 = [f64::NEG_INFINITY; LANES];
        let mut t = 0;
        while t + LANES <= act {
            for k in 0..LANES {
                let u = up[t + k] - g[t + k];
                let w = g[t + k] + low[t + k];
                let take = u >= best[k];
                best[k] = if take { u } else { best[k] };
                at[k] = if take { t + k } else { at[k] };
                best2[k] = if w > best2[k] { w } else { best2[k] };
            }
            t += LANES;
        }
        for r in t..act {
            let u = up[r] - g[r];
            let w = g[r] + low[r];
            if u >= best[0] {
                best[0] = u;
                at[0] = r;
            }
            if w > best2[0] {
                best2[0] = w;
            }
        }
        let (gmax, i) = reduce_max(best, at);
        let gmax2 = best2
            .iter()
            .fold(f64::NEG_INFINITY, |m, &v| if v > m { v } else { m });
        (gmax, i, gmax2)
    }

    /// WSS2 on points: i maximizes the up violation, j (with room to go
    /// down) the second-order decrease of the pair.
    fn select_working_set(&mut self) -> Option<(usize, usize)> {
        let (gmax, i, gmax2) = match self.top {
            Some(top) => top,
            None => self.scan_top(),
        };
        self.top = None;
        if gmax == f64::NEG_INFINITY || gmax + gmax2 < self.tol {
            return None;
        }
        let act = self.active_size;
        // The direction the conjugate step will use (the same conditions).
        let conj = match self.direction.curvature {
            Some(curv)
                if self.conjugate && self.direction.support.len() < MAX_DIRECTION_SUPPORT =>
            {
                Some(Conjugate {
                    q: &self.direction.q[..act],
                    qi: self.direction.q[i],
                    inv_curv: 1.0 / curv,
                })
            }
            _ => None,
        };
        let j = choose_j(
            self.avx2,
            self.brow(i),
            &self.g[..act],
            &self.low_off[..act],
            gmax,
            conj.filter(|c| c.inv_curv.is_finite() && c.inv_curv > 0.0),
        )?;
        Some((i, j))
    }

    fn be_shrunk(&self, t: usize, gmax1: f64, gmax2: f64) -> bool {
        if self.is_free(t) {
            return false;
        }
        // Up (if allowed) and down (if allowed) both not violating.
        let u = self.up_off[t] - self.g[t];
        let w = self.g[t] + self.low_off[t];
        (u == f64::NEG_INFINITY || u < -gmax2) && (w == f64::NEG_INFINITY || w < -gmax1)
    }

    fn do_shrinking(&mut self) {
        let (gmax1, _, gmax2) = self.scan_top();
        if !self.unshrink && gmax1 + gmax2 <= self.tol * 10.0 {
            self.unshrink = true;
            self.activate_all();
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
        self.permute_block(self.active_size);
        self.top = None;
    }

    /// libsvm's `calculate_rho` on the two variables of every point.
    pub(super) fn calculate_rho(&self) -> f64 {
        let (c, e) = (self.c, self.eps);
        let mut nr_free = 0usize;
        let mut ub = f64::INFINITY;
        let mut lb = f64::NEG_INFINITY;
        let mut sum_free = 0.0;
        for t in 0..self.active_size {
            let (b, g) = (self.beta[t], self.g[t]);
            if b >= c {
                lb = lb.max(g + e);
            } else if b <= -c {
                ub = ub.min(g - e);
            } else if b == 0.0 {
                ub = ub.min(g + e);
                lb = lb.max(g - e);
            } else if b > 0.0 {
                nr_free += 1;
                sum_free += g + e;
            } else {
                nr_free += 1;
                sum_free += g - e;
            }
        }
        if nr_free > 0 {
            sum_free / nr_free as f64
        } else {
            (ub + lb) / 2.0
        }
    }

    /// `beta^T K beta / 2 - z^T beta + eps |beta|_1` from the gradient.
    pub(super) fn objective(&self) -> f64 {
        (0..self.n)
            .map(|t| self.beta[t] * (self.g[t] - self.z[t]) / 2.0 + self.eps * self.beta[t].abs())
            .sum()
    }

    /// Room to move beta_t by `d` before the next kink or bound.
    fn room(&self, t: usize, up: bool) -> f64 {
        let (b, c) = (self.beta[t], self.c);
        if up {
            if b < 0.0 {
                -b
            } else {
                c - b
            }
        } else if b > 0.0 {
            b
        } else {
            b + c
        }
    }

    /// Move beta_t to `b` and keep the offsets and G_bar in step (G_bar over
    /// every point when t reaches or leaves a bound).
    fn set_beta(&mut self, t: usize, b: f64) {
        let old = self.beta[t];
        let was = old.abs() >= self.c;
        self.beta[t] = b;
        self.update_offsets(t);
        let now = b.abs() >= self.c;
        if was || now {
            let s = if now { b } else { 0.0 } - if was { old } else { 0.0 };
            if s != 0.0 {
                let row = self.k.row(self.index[t]);
                for (gb, &it) in self.g_bar.iter_mut().zip(&self.index) {
                    *gb += s * f64::from(row[it]);
                }
            }
        }
    }

    /// The plain SMO step on (i up, j down), clipped at the first kink or
    /// bound like libsvm's.
    fn step(&mut self, i: usize, j: usize) {
        let act = self.active_size;
        let kij = f64::from(self.block[i * self.n + j]);
        let quad = 2.0 - 2.0 * kij;
        let quad = if quad > 0.0 { quad } else { TAU };
        let viol = (self.up_off[i] - self.g[i]) + (self.g[j] + self.low_off[j]);
        let (ri, rj) = (self.room(i, true), self.room(j, false));
        let mut delta = viol / quad;
        let (old_i, old_j) = (self.beta[i], self.beta[j]);
        let (mut bi, mut bj) = (old_i + delta, old_j - delta);
        if delta >= ri || delta >= rj {
            if ri <= rj {
                delta = ri;
                bi = if old_i < 0.0 { 0.0 } else { self.c };
                bj = old_j - delta;
                if delta == rj {
                    bj = if old_j > 0.0 { 0.0 } else { -self.c };
                }
            } else {
                delta = rj;
                bj = if old_j > 0.0 { 0.0 } else { -self.c };
                bi = old_i + delta;
            }
        }
        self.set_beta(i, bi);
        self.set_beta(j, bj);
        let di = self.beta[i] - old_i;
        let dj = self.beta[j] - old_j;
        let n = self.n;
        let (ki, kj) = (
            &self.block[i * n..i * n + act],
            &self.block[j * n..j * n + act],
        );
        self.top = Some(plain_pass(
            self.avx2,
            ki,
            kj,
            di,
            dj,
            &mut self.g[..act],
            &self.up_off[..act],
            &self.low_off[..act],
        ));
    }

    fn reset_direction(&mut self) {
        self.direction.forget();
    }

    /// After a plain step on (i, j): its direction `e_i - e_j` and `K d`.
    fn start_direction(&mut self, i: usize, j: usize) {
        let free = self.is_free(i) && self.is_free(j);
        if !free {
            self.reset_direction();
            return;
        }
        let (act, n) = (self.active_size, self.n);
        let (ki, kj) = (
            &self.block[i * n..i * n + act],
            &self.block[j * n..j * n + act],
        );
        for ((w, &a), &b) in self.direction.q[..act].iter_mut().zip(ki).zip(kj) {
            *w = f64::from(a) - f64::from(b);
        }
        self.direction.d[i] = 1.0;
        self.direction.d[j] = -1.0;
        self.direction.in_support[i] = true;
        self.direction.in_support[j] = true;
        self.direction.support.push(i);
        self.direction.support.push(j);
        self.direction.curvature = Some(2.0 - 2.0 * f64::from(self.block[i * n + j]));
    }

    fn plain(&mut self, i: usize, j: usize) {
        self.reset_direction();
        self.step(i, j);
        self.start_direction(i, j);
    }

    /// The conjugate step of the 2n solver on points: `u = e_i - e_j` plus
    /// the multiple of the previous direction that makes the two
    /// K-conjugate, an exact line search clipped at the first kink or bound.
    fn conjugate_step(&mut self, i: usize, j: usize) {
        let act = self.active_size;
        let bc = match self.direction.curvature {
            Some(curv) if self.direction.support.len() < MAX_DIRECTION_SUPPORT => {
                -(self.direction.q[i] - self.direction.q[j]) / curv
            }
            _ => 0.0,
        };
        if bc == 0.0 || !bc.is_finite() {
            return self.plain(i, j);
        }
        for &t in &self.direction.support {
            self.direction.d[t] *= bc;
        }
        for (v, add) in [(i, 1.0), (j, -1.0)] {
            self.direction.d[v] += add;
            if !self.direction.in_support[v] {
                self.direction.in_support[v] = true;
                self.direction.support.push(v);
            }
        }
        let n = self.n;
        let e = self.eps;
        let mut gd = 0.0;
        let mut dqd = 0.0;
        for &t in &self.direction.support {
            let d = self.direction.d[t];
            let (ki, kj) = (&self.block[i * n..], &self.block[j * n..]);
            let it = t;
            let b = self.beta[t];
            // The one-sided slope of eps |beta_t| along d.
            let s = if b > 0.0 || (b == 0.0 && d > 0.0) {
                e
            } else {
                -e
            };
            gd += (self.g[t] + s) * d;
            dqd += d * ((f64::from(ki[it]) - f64::from(kj[it])) + bc * self.direction.q[t]);
        }
        let t_opt = -gd / dqd;
        if !(gd < 0.0 && dqd > 0.0 && t_opt.is_finite()) {
            return self.plain(i, j);
        }
        let (t_max, blocking) = self.first_block(t_opt);
        if t_max.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return self.plain(i, j);
        }
        let clipped = t_max < t_opt;
        let step = if clipped { t_max } else { t_opt };
        self.move_along(step, clipped.then_some(blocking));
        // K d and the gradient in one pass, with the next maximal violations.
        let (ki, kj) = (
            &self.block[i * n..i * n + act],
            &self.block[j * n..j * n + act],
        );
        self.top = Some(conjugate_pass(
            self.avx2,
            ki,
            kj,
            bc,
            step,
            &mut self.direction.q[..act],
            &mut self.g[..act],
            &self.up_off[..act],
            &self.low_off[..act],
        ));
        if clipped {
            self.reset_direction();
        } else {
            self.direction.curvature = Some(dqd);
        }
    }

    /// The first kink or bound along the direction, and the variable that
    /// sets it: `(t_max, blocking)`. Only a variable whose room is within
    /// twice the full step `t_opt` can block it (or set `t_max <= 0`): the
    /// division is done for those only (most steps are not clipped), and
    /// `t_max` and `blocking` are what dividing for every one gives.
    #[inline]
    fn first_block(&self, t_opt: f64) -> (f64, usize) {
        let mut t_max = f64::INFINITY;
        let mut blocking = usize::MAX;
        for &t in &self.direction.support {
            let d = self.direction.d[t];
            if d == 0.0 {
                continue;
            }
            let room = self.room(t, d > 0.0);
            if room > 2.0 * t_opt * d.abs() {
                continue;
            }
            let ratio = room / d.abs();
            if ratio < t_max {
                t_max = ratio;
                blocking = t;
            }
        }
        (t_max, blocking)
    }

    /// Moves every variable of the direction by `step` along it; the
    /// `blocking` variable of a clipped step lands exactly on its kink or
    /// bound.
    #[inline]
    fn move_along(&mut self, step: f64, blocking: Option<usize>) {
        let c = self.c;
        for k in 0..self.direction.support.len() {
            let v = self.direction.support[k];
            let (b, d) = (self.beta[v], self.direction.d[v]);
            let nb = if blocking == Some(v) {
                if d > 0.0 {
                    if b < 0.0 {
                        0.0
                    } else {
                        c
                    }
                } else if b > 0.0 {
                    0.0
                } else {
                    -c
                }
            } else {
                // Never across a kink or out of the box by rounding.
                let x = (b + step * d).clamp(-c, c);
                if b > 0.0 {
                    x.max(0.0)
                } else if b < 0.0 {
                    x.min(0.0)
                } else if d > 0.0 {
                    x.max(0.0)
                } else {
                    x.min(0.0)
                }
            };
            if nb != b {
                self.set_beta(v, nb);
            }
        }
    }

    /// Run SMO; returns (iterations, converged).
    pub(super) fn solve(
        &mut self,
        shrinking: bool,
        conjugate: bool,
        max_iter: usize,
        deadline: Deadline,
    ) -> (usize, bool) {
        self.conjugate = conjugate;
        run_smo(self, shrinking, conjugate, max_iter, deadline)
    }
}

impl Smo for PointSolver<'_> {
    fn shrink_period(&self) -> usize {
        // libsvm counts its 2n variables.
        (2 * self.n).min(1000)
    }
    fn shrunk(&self) -> bool {
        self.active_size < self.n
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
    fn unshrink(&mut self, resume: bool) {
        if resume {
            self.activate_all();
        } else {
            self.reconstruct_gradient();
            self.active_size = self.n;
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::learn::Rng;

    /// The AVX2 passes take the scalar passes' path to the last bit (same
    /// iterations, same coefficients), on a problem with ties (a lattice)
    /// and active sets that are not multiples of the lane count.
    #[test]
    fn avx2_and_scalar_passes_agree_bit_for_bit() {
        if !have_avx2() {
            return;
        }
        let mut rng = Rng::derive(7, 1);
        let mut x = Vec::new();
        for i in 0..7 {
            for j in 0..7 {
                for k in 0..5 {
                    x.push([i as f64 * 0.4, j as f64 * 0.4, k as f64 * 0.5]);
                }
            }
        }
        x.push([0.13, 0.71, 0.29]);
        let z: Vec<f64> = x
            .iter()
            .map(|p| {
                (p[0] * 1.3).sin()
                    + p[1] * p[2] * 0.2
                    + 0.05 * (rng.next_u64() % 100) as f64 / 100.0
            })
            .collect();
        let k = KernelMatrix::rbf(&x, 1.0, 10_000).unwrap();
        let points: Vec<usize> = (0..x.len()).collect();
        for conjugate in [false, true] {
            let run = |avx2: bool| {
                let mut s = PointSolver::new(&k, &points, &z, 0.01, 100.0, 1e-3, None);
                s.avx2 = avx2;
                let (iters, converged) = s.solve(true, conjugate, 1_000_000, Deadline::none());
                let mut coef = vec![0.0; points.len()];
                for (t, &o) in s.active_set.iter().enumerate() {
                    coef[o] = s.beta[t];
                }
                (iters, converged, coef, s.calculate_rho())
            };
            let (a, b) = (run(false), run(true));
            assert!(a.1 && b.1);
            assert!(a.0 > 100, "too easy a problem: {} iterations", a.0);
            assert_eq!(a.0, b.0, "iterations");
            assert!(a
                .2
                .iter()
                .zip(&b.2)
                .all(|(u, v)| u.to_bits() == v.to_bits()));
            assert_eq!(a.3.to_bits(), b.3.to_bits());
        }
    }
}
