//! The epsilon-SVR dual in libsvm's 2n variables `beta = (alpha, alpha*)`:
//! libsvm's `Solver` specialised to epsilon-SVR ([`Solver`]), its WSS2
//! selection, shrinking, plain SMO step and `rho`, plus the conjugate step.
//! With `conjugate` off it follows libsvm step for step; `solve` uses it
//! when `per_point` is off or the problem is too large for the per-point
//! solver's kernel block.

use super::smo::{run_smo, Direction, Smo, MAX_DIRECTION_SUPPORT, TAU};
use super::{KernelMatrix, SolverConfig};
use crate::model::learn::Deadline;

#[derive(Clone, Copy, PartialEq, Eq)]
enum Status {
    Lower,
    Upper,
    Free,
}

/// libsvm's `Solver` specialised to epsilon-SVR with `Cp = Cn = C`.
/// Arrays are indexed by the current (shrinking-permuted) position.
pub(super) struct Solver<'a> {
    k: &'a KernelMatrix,
    l: usize,
    y: Vec<f64>,
    /// Training point behind each variable.
    index: Vec<usize>,
    qd: Vec<f64>,
    pub(super) p: Vec<f64>,
    pub(super) alpha: Vec<f64>,
    status: Vec<Status>,
    pub(super) g: Vec<f64>,
    /// Gradient part from variables at the upper bound (for unshrinking).
    g_bar: Vec<f64>,
    pub(super) active_set: Vec<usize>,
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

    pub(super) fn calculate_rho(&self) -> f64 {
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
    pub(super) fn solve(
        &mut self,
        cfg: &SolverConfig,
        max_iter: usize,
        deadline: Deadline,
    ) -> (usize, bool) {
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
