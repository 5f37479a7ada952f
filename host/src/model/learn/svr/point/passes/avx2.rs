//! The three passes on 16 f64 lanes (four AVX2 vectors), for whole chunks
//! of 16 (the callers do the rest). Each operation is the scalar code's, in
//! its order, lane for lane.

use super::{Best, Top, CONJUGATE_CURVATURE_FLOOR, LANES, TAU};
use std::arch::x86_64::*;

const V: usize = LANES / 4;

#[inline(always)]
unsafe fn k4(k: &[f32], r: usize) -> __m256d {
    _mm256_cvtps_pd(_mm_loadu_ps(k.as_ptr().add(r)))
}

#[inline(always)]
unsafe fn load(a: &[f64; LANES]) -> [__m256d; V] {
    [0, 1, 2, 3].map(|v| _mm256_loadu_pd(a.as_ptr().add(4 * v)))
}

#[inline(always)]
unsafe fn store(a: &mut [f64; LANES], x: [__m256d; V]) {
    for (v, x) in x.iter().enumerate() {
        _mm256_storeu_pd(a.as_mut_ptr().add(4 * v), *x);
    }
}

/// Positions of the first chunk's lanes.
#[inline(always)]
unsafe fn first_positions() -> [__m256d; V] {
    [0, 1, 2, 3].map(|v| {
        let b = (4 * v) as f64;
        _mm256_setr_pd(b, b + 1.0, b + 2.0, b + 3.0)
    })
}

/// `Top::add` on four lanes: u = up - g, w = g + low.
#[inline(always)]
unsafe fn add_top(
    best: &mut __m256d,
    at: &mut __m256d,
    low_best: &mut __m256d,
    pos: __m256d,
    u: __m256d,
    w: __m256d,
) {
    let take = _mm256_cmp_pd::<_CMP_GE_OQ>(u, *best);
    *best = _mm256_blendv_pd(*best, u, take);
    *at = _mm256_blendv_pd(*at, pos, take);
    // `if w > low { w } else { low }`
    *low_best = _mm256_max_pd(w, *low_best);
}

/// Returns the first position not processed.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn plain(
    ki: &[f32],
    kj: &[f32],
    di: f64,
    dj: f64,
    g: &mut [f64],
    up: &[f64],
    low: &[f64],
    top: &mut Top,
) -> usize {
    let act = g.len();
    let (di4, dj4) = (_mm256_set1_pd(di), _mm256_set1_pd(dj));
    let (mut best, mut at, mut low_best) = (load(&top.up), load(&top.at), load(&top.low));
    let mut pos = first_positions();
    let step = _mm256_set1_pd(LANES as f64);
    let gp = g.as_mut_ptr();
    let mut t = 0;
    while t + LANES <= act {
        for v in 0..V {
            let r = t + 4 * v;
            let d = _mm256_add_pd(_mm256_mul_pd(k4(ki, r), di4), _mm256_mul_pd(k4(kj, r), dj4));
            let gr = _mm256_add_pd(_mm256_loadu_pd(gp.add(r)), d);
            _mm256_storeu_pd(gp.add(r), gr);
            let u = _mm256_sub_pd(_mm256_loadu_pd(up.as_ptr().add(r)), gr);
            let w = _mm256_add_pd(gr, _mm256_loadu_pd(low.as_ptr().add(r)));
            add_top(&mut best[v], &mut at[v], &mut low_best[v], pos[v], u, w);
            pos[v] = _mm256_add_pd(pos[v], step);
        }
        t += LANES;
    }
    store(&mut top.up, best);
    store(&mut top.at, at);
    store(&mut top.low, low_best);
    t
}

/// Returns the first position not processed.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn conjugate(
    ki: &[f32],
    kj: &[f32],
    bc: f64,
    step: f64,
    q: &mut [f64],
    g: &mut [f64],
    up: &[f64],
    low: &[f64],
    top: &mut Top,
) -> usize {
    let act = g.len();
    let (bc4, step4) = (_mm256_set1_pd(bc), _mm256_set1_pd(step));
    let (mut best, mut at, mut low_best) = (load(&top.up), load(&top.at), load(&top.low));
    let mut pos = first_positions();
    let advance = _mm256_set1_pd(LANES as f64);
    let (gp, qp) = (g.as_mut_ptr(), q.as_mut_ptr());
    let mut t = 0;
    while t + LANES <= act {
        for v in 0..V {
            let r = t + 4 * v;
            let w = _mm256_add_pd(
                _mm256_sub_pd(k4(ki, r), k4(kj, r)),
                _mm256_mul_pd(bc4, _mm256_loadu_pd(qp.add(r))),
            );
            _mm256_storeu_pd(qp.add(r), w);
            let gr = _mm256_add_pd(_mm256_loadu_pd(gp.add(r)), _mm256_mul_pd(step4, w));
            _mm256_storeu_pd(gp.add(r), gr);
            let u = _mm256_sub_pd(_mm256_loadu_pd(up.as_ptr().add(r)), gr);
            let lw = _mm256_add_pd(gr, _mm256_loadu_pd(low.as_ptr().add(r)));
            add_top(&mut best[v], &mut at[v], &mut low_best[v], pos[v], u, lw);
            pos[v] = _mm256_add_pd(pos[v], advance);
        }
        t += LANES;
    }
    store(&mut top.up, best);
    store(&mut top.at, at);
    store(&mut top.low, low_best);
    t
}

/// For the four points at `r`: the second-order choice's numerator
/// `a = max(gmax + g_t + low_t, 0)^2` and the pair's curvature
/// `quad = max(2 - 2 K_it, tau)`, which [`choose`] and
/// [`choose_conjugate`] share (the same operations in the same order as
/// the scalar pass).
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn gap_and_curvature(
    ki: &[f32],
    g: &[f64],
    low: &[f64],
    gmax4: __m256d,
    r: usize,
) -> (__m256d, __m256d) {
    let two = _mm256_set1_pd(2.0);
    let gd = _mm256_add_pd(
        _mm256_add_pd(gmax4, _mm256_loadu_pd(g.as_ptr().add(r))),
        _mm256_loadu_pd(low.as_ptr().add(r)),
    );
    // `x.max(y)` is `_mm256_max_pd(x, y)` for non-NaN x and y.
    let quad = _mm256_max_pd(
        _mm256_sub_pd(two, _mm256_mul_pd(two, k4(ki, r))),
        _mm256_set1_pd(TAU),
    );
    let gd = _mm256_max_pd(gd, _mm256_setzero_pd());
    (_mm256_mul_pd(gd, gd), quad)
}

/// Returns the first position not processed.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn choose(
    ki: &[f32],
    g: &[f64],
    low: &[f64],
    gmax: f64,
    best: &mut Best,
) -> usize {
    let act = g.len();
    let gmax4 = _mm256_set1_pd(gmax);
    let (mut num, mut den, mut at) = (load(&best.num), load(&best.den), load(&best.at));
    let mut pos = first_positions();
    let advance = _mm256_set1_pd(LANES as f64);
    let mut t = 0;
    while t + LANES <= act {
        for v in 0..V {
            let r = t + 4 * v;
            let (a, quad) = gap_and_curvature(ki, g, low, gmax4, r);
            let take =
                _mm256_cmp_pd::<_CMP_GE_OQ>(_mm256_mul_pd(a, den[v]), _mm256_mul_pd(num[v], quad));
            num[v] = _mm256_blendv_pd(num[v], a, take);
            den[v] = _mm256_blendv_pd(den[v], quad, take);
            at[v] = _mm256_blendv_pd(at[v], pos[v], take);
            pos[v] = _mm256_add_pd(pos[v], advance);
        }
        t += LANES;
    }
    store(&mut best.num, num);
    store(&mut best.den, den);
    store(&mut best.at, at);
    t
}

/// `choose` with the conjugate curvature (`super::conjugate_curvature`).
/// Returns the first position not processed.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn choose_conjugate(
    ki: &[f32],
    g: &[f64],
    low: &[f64],
    q: &[f64],
    gmax: f64,
    qi: f64,
    inv_curv: f64,
    best: &mut Best,
) -> usize {
    let act = g.len();
    let gmax4 = _mm256_set1_pd(gmax);
    let (qi4, inv4) = (_mm256_set1_pd(qi), _mm256_set1_pd(inv_curv));
    let floor = _mm256_set1_pd(CONJUGATE_CURVATURE_FLOOR);
    let (mut num, mut den, mut at) = (load(&best.num), load(&best.den), load(&best.at));
    let mut pos = first_positions();
    let advance = _mm256_set1_pd(LANES as f64);
    let mut t = 0;
    while t + LANES <= act {
        for v in 0..V {
            let r = t + 4 * v;
            let (a, quad) = gap_and_curvature(ki, g, low, gmax4, r);
            let dq = _mm256_sub_pd(qi4, _mm256_loadu_pd(q.as_ptr().add(r)));
            let cd = _mm256_sub_pd(quad, _mm256_mul_pd(_mm256_mul_pd(dq, dq), inv4));
            let b = _mm256_blendv_pd(
                quad,
                cd,
                _mm256_cmp_pd::<_CMP_GT_OQ>(cd, _mm256_mul_pd(floor, quad)),
            );
            let take =
                _mm256_cmp_pd::<_CMP_GE_OQ>(_mm256_mul_pd(a, den[v]), _mm256_mul_pd(num[v], b));
            num[v] = _mm256_blendv_pd(num[v], a, take);
            den[v] = _mm256_blendv_pd(den[v], b, take);
            at[v] = _mm256_blendv_pd(at[v], pos[v], take);
            pos[v] = _mm256_add_pd(pos[v], advance);
        }
        t += LANES;
    }
    store(&mut best.num, num);
    store(&mut best.den, den);
    store(&mut best.at, at);
    t
}
