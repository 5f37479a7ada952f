//! What both SMO solvers share (libsvm's 2n-variable one, `libsvm_dual`,
//! and the per-point one, `point`): libsvm's SMO loop ([`run_smo`]) and
//! what it asks of a solver ([`Smo`]), the previous direction a conjugate
//! step is made Q-conjugate to ([`Direction`]), and the two constants of
//! the step.

use crate::model::learn::Deadline;

/// Variables a conjugate direction may span before it restarts: measured on
/// the black-box grid (C 300, epsilon 0.005), 64 keeps the iteration count of
/// unbounded directions (0.55 and 0.77 million on two axes) at 3/4 of the
/// time; 16 costs 10 % more iterations.
pub(super) const MAX_DIRECTION_SUPPORT: usize = 64;

/// libsvm's `TAU`: the curvature used when a pair's `quad_coef` is not positive.
pub(super) const TAU: f64 = 1e-12;

/// Conjugate SMO's previous direction (both solvers): `d` by position, its
/// support (listed, and flagged by position), `Q d` over the active set and
/// `d^T Q d`; `curvature` is `None` when there is no direction.
pub(super) struct Direction {
    pub(super) d: Vec<f64>,
    pub(super) support: Vec<usize>,
    pub(super) in_support: Vec<bool>,
    pub(super) q: Vec<f64>,
    pub(super) curvature: Option<f64>,
}

impl Direction {
    pub(super) fn new(n: usize) -> Direction {
        Direction {
            d: vec![0.0; n],
            support: Vec::new(),
            in_support: vec![false; n],
            q: vec![0.0; n],
            curvature: None,
        }
    }

    /// Forgets the direction (clears only its support's positions).
    pub(super) fn forget(&mut self) {
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
    pub(super) fn relist(&mut self, active: usize, before: usize) {
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

/// What libsvm's SMO loop asks of a solver (the 2n-variable one and the
/// per-point one, [`run_smo`]).
pub(super) trait Smo {
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
pub(super) fn run_smo<S: Smo>(
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
