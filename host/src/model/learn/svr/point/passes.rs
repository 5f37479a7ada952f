//! The hot passes of the per-point solver, which an SMO iteration is made
//! of: the gradient update after a plain or a conjugate step (each also
//! finding the next iteration's maximal violations) and the choice of j,
//! with the lane accumulators they share. Each pass runs on 16 lanes, on
//! AVX2 when the CPU has it (`avx2`) and in scalar code otherwise, with the
//! same operations in the same order, so both give the same bits.

use super::TAU;

#[cfg(target_arch = "x86_64")]
mod avx2;

/// The choice of j with a conjugate direction uses the pair's curvature
/// made conjugate to it, unless that is below this fraction of the pair's
/// own (then it is mostly rounding: the f32 kernel's, and the cancellation
/// in `u^T K u - (u^T K d)^2 / d^T K d`) and the pair's is used. Measured on
/// the black-box grid (C 300, four fits): 1e-3 saves 18 to 25 % of the
/// iterations, 0.05 to 0.15 save 25 to 29 %, 0.5 saves 0 to 14 %; 0.1 kept.
const CONJUGATE_CURVATURE_FLOOR: f64 = 0.1;

/// Lanes of the branch-free reductions: four vectors of 4 f64, so that four
/// independent compare-and-blend chains hide each other's latency.
pub(super) const LANES: usize = 16;

/// The largest value of the lanes and, among equal ones, the last position
/// (libsvm's tie rule: the last of equal candidates wins).
pub(super) fn reduce_max(best: [f64; LANES], at: [usize; LANES]) -> (f64, usize) {
    let mut v = f64::NEG_INFINITY;
    let mut p = 0;
    for k in 0..LANES {
        if best[k] > v || (best[k] == v && at[k] >= p) {
            v = best[k];
            p = at[k];
        }
    }
    (v, p)
}

/// Lane accumulators of the largest up violation (with the last position
/// reaching it) and the largest down violation. Positions are kept as f64
/// (exact below 2^53) so that the selects are the same vector blends as the
/// values'.
#[derive(Clone, Copy)]
struct Top {
    up: [f64; LANES],
    at: [f64; LANES],
    low: [f64; LANES],
}

impl Top {
    fn new() -> Self {
        Top {
            up: [f64::NEG_INFINITY; LANES],
            at: [0.0; LANES],
            low: [f64::NEG_INFINITY; LANES],
        }
    }
    #[inline(always)]
    fn add(&mut self, k: usize, r: f64, u: f64, w: f64) {
        let take = u >= self.up[k];
        self.up[k] = if take { u } else { self.up[k] };
        self.at[k] = if take { r } else { self.at[k] };
        self.low[k] = if w > self.low[k] { w } else { self.low[k] };
    }
    fn finish(self) -> (f64, usize, f64) {
        let (gmax, i) = reduce_max(self.up, self.at.map(|p| p as usize));
        let gmax2 = self
            .low
            .iter()
            .fold(f64::NEG_INFINITY, |m, &v| if v > m { v } else { m });
        (gmax, i, gmax2)
    }
}

/// Lane accumulators of WSS2's j: the best decrease as a fraction
/// `num / den` and its position (-1: none yet). A candidate of decrease 0
/// may be held until a positive one replaces it; `finish` never returns it.
#[derive(Clone, Copy)]
struct Best {
    num: [f64; LANES],
    den: [f64; LANES],
    at: [f64; LANES],
}

impl Best {
    fn new() -> Self {
        Best {
            num: [0.0; LANES],
            den: [1.0; LANES],
            at: [-1.0; LANES],
        }
    }
    #[inline(always)]
    fn add(&mut self, k: usize, r: f64, a: f64, b: f64) {
        let take = a * self.den[k] >= self.num[k] * b;
        self.num[k] = if take { a } else { self.num[k] };
        self.den[k] = if take { b } else { self.den[k] };
        self.at[k] = if take { r } else { self.at[k] };
    }
    fn finish(self) -> Option<usize> {
        let (mut bn, mut bd, mut j) = (0.0, 1.0, -1.0);
        for k in 0..LANES {
            if self.at[k] < 0.0 {
                continue;
            }
            let (l, r) = (self.num[k] * bd, bn * self.den[k]);
            if j < 0.0 || l > r || (l == r && self.at[k] > j) {
                bn = self.num[k];
                bd = self.den[k];
                j = self.at[k];
            }
        }
        (j >= 0.0 && bn > 0.0).then_some(j as usize)
    }
}

/// One candidate j: `(grad_diff^2, quad)`, or `(0, quad)` when r has no room
/// to go down or the pair would not decrease the objective (`Best` never
/// chooses those).
#[inline(always)]
fn candidate(gmax: f64, g: f64, low: f64, k: f32) -> (f64, f64) {
    let grad_diff = gmax + g + low;
    // K_ii + K_jj - 2 K_ij with K(x, x) = 1 (libsvm's double diagonal);
    // libsvm's `quad > 0 ? quad : TAU`, as a max: from an f32 K, quad is 0,
    // negative or above 1e-7, never in (0, TAU].
    let quad = (2.0 - 2.0 * f64::from(k)).max(TAU);
    // max(grad_diff, 0): -inf (no room) and negatives give 0.
    let gd = if grad_diff > 0.0 { grad_diff } else { 0.0 };
    (gd * gd, quad)
}

/// Whether this CPU runs the AVX2 passes (same results as the scalar ones:
/// the same operations in the same order on the same lanes, no FMA).
pub(super) fn have_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `g += K_i di + K_j dj` over the active positions (`g.len()`), and the
/// next maximal violations.
#[allow(clippy::too_many_arguments)]
pub(super) fn plain_pass(
    avx2: bool,
    ki: &[f32],
    kj: &[f32],
    di: f64,
    dj: f64,
    g: &mut [f64],
    up: &[f64],
    low: &[f64],
) -> (f64, usize, f64) {
    let act = g.len();
    let (ki, kj, up, low) = (&ki[..act], &kj[..act], &up[..act], &low[..act]);
    let mut top = Top::new();
    let mut t = 0;
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: AVX2 is present (checked by `have_avx2`); the slices all
        // have `act` elements (sliced above) and the body reads and writes
        // only whole chunks of 4 below `act`.
        t = unsafe { avx2::plain(ki, kj, di, dj, g, up, low, &mut top) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = avx2;
    while t + LANES <= act {
        for k in 0..LANES {
            let r = t + k;
            let gr = g[r] + (f64::from(ki[r]) * di + f64::from(kj[r]) * dj);
            g[r] = gr;
            top.add(k, r as f64, up[r] - gr, gr + low[r]);
        }
        t += LANES;
    }
    for r in t..act {
        let gr = g[r] + (f64::from(ki[r]) * di + f64::from(kj[r]) * dj);
        g[r] = gr;
        top.add(0, r as f64, up[r] - gr, gr + low[r]);
    }
    top.finish()
}

/// `q = K_i - K_j + bc q; g += step q` over the active positions, and the
/// next maximal violations.
#[allow(clippy::too_many_arguments)]
pub(super) fn conjugate_pass(
    avx2: bool,
    ki: &[f32],
    kj: &[f32],
    bc: f64,
    step: f64,
    q: &mut [f64],
    g: &mut [f64],
    up: &[f64],
    low: &[f64],
) -> (f64, usize, f64) {
    let act = g.len();
    let (ki, kj, q, up, low) = (
        &ki[..act],
        &kj[..act],
        &mut q[..act],
        &up[..act],
        &low[..act],
    );
    let mut top = Top::new();
    let mut t = 0;
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: as in `plain_pass`.
        t = unsafe { avx2::conjugate(ki, kj, bc, step, q, g, up, low, &mut top) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = avx2;
    while t + LANES <= act {
        for k in 0..LANES {
            let r = t + k;
            let w = (f64::from(ki[r]) - f64::from(kj[r])) + bc * q[r];
            q[r] = w;
            let gr = g[r] + step * w;
            g[r] = gr;
            top.add(k, r as f64, up[r] - gr, gr + low[r]);
        }
        t += LANES;
    }
    for r in t..act {
        let w = (f64::from(ki[r]) - f64::from(kj[r])) + bc * q[r];
        q[r] = w;
        let gr = g[r] + step * w;
        g[r] = gr;
        top.add(0, r as f64, up[r] - gr, gr + low[r]);
    }
    top.finish()
}

/// The previous conjugate direction as the choice of j sees it: `K d` over
/// the active positions, `(K d)_i` and `1 / d^T K d`.
#[derive(Clone, Copy)]
pub(super) struct Conjugate<'a> {
    pub(super) q: &'a [f64],
    pub(super) qi: f64,
    pub(super) inv_curv: f64,
}

/// The curvature of the pair (i, r) made conjugate to d:
/// `u^T K u - (u^T K d)^2 / d^T K d` for `u = e_i - e_r`, or the pair's own
/// `quad` when that falls below [`CONJUGATE_CURVATURE_FLOOR`] of it.
#[inline(always)]
fn conjugate_curvature(quad: f64, q: f64, qi: f64, inv_curv: f64) -> f64 {
    let dq = qi - q;
    let den = quad - dq * dq * inv_curv;
    if den > CONJUGATE_CURVATURE_FLOOR * quad {
        den
    } else {
        quad
    }
}

/// WSS2's j for the up point i (kernel row `ki`) of violation `gmax`: the
/// point with room to go down whose pair decreases the objective most,
/// `grad_diff^2 / quad`, compared as fractions (`num_a den_b >= num_b den_a`)
/// so that the pass has no division; on equal decreases the last point wins.
///
/// With a previous direction d (`conj`), the step will go along the pair's
/// direction made conjugate to d, and the gradient is orthogonal to d (d's
/// line search was exact), so that step decreases the objective by
/// `grad_diff^2 / (quad - (u^T K d)^2 / d^T K d)`: j maximizes that instead.
pub(super) fn choose_j(
    avx2: bool,
    ki: &[f32],
    g: &[f64],
    low: &[f64],
    gmax: f64,
    conj: Option<Conjugate>,
) -> Option<usize> {
    let act = g.len();
    let (ki, low) = (&ki[..act], &low[..act]);
    let mut best = Best::new();
    let mut t = 0;
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: as in `plain_pass` (and `c.q` is sliced to `act` below).
        t = unsafe {
            match conj {
                None => avx2::choose(ki, g, low, gmax, &mut best),
                Some(c) => avx2::choose_conjugate(
                    ki,
                    g,
                    low,
                    &c.q[..act],
                    gmax,
                    c.qi,
                    c.inv_curv,
                    &mut best,
                ),
            }
        };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = avx2;
    let one = |r: usize| -> (f64, f64) {
        let (a, quad) = candidate(gmax, g[r], low[r], ki[r]);
        match conj {
            None => (a, quad),
            Some(c) => (a, conjugate_curvature(quad, c.q[r], c.qi, c.inv_curv)),
        }
    };
    while t + LANES <= act {
        for k in 0..LANES {
            let r = t + k;
            let (a, b) = one(r);
            best.add(k, r as f64, a, b);
        }
        t += LANES;
    }
    for r in t..act {
        let (a, b) = one(r);
        best.add(0, r as f64, a, b);
    }
    best.finish()
}
