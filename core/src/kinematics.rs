//! Kinematics of an 8-string SPIDAR: string lengths from a position (inverse)
//! and a position from string lengths (forward, damped Gauss-Newton /
//! Levenberg-Marquardt) with faulty-string rejection.
//!
//! Generic over [`Real`]: the device runs `f32`, the host `f64`.
//! Only `+ - * /` and `sqrt` are used, always in the same order, so `f32`
//! results are bit-identical on x86_64 (SSE) and on the Cortex-M7 FPU: all
//! five are correctly rounded IEEE 754 operations on both, Rust never
//! contracts `a * b + c` into an FMA, and `sqrt` is [`Real::sqrt_rounded`]
//! (`VSQRT.F32` on the Cortex-M7, `libm::sqrtf`/`sqrt` elsewhere), all
//! correctly rounded.
//! Comparisons and `abs`/`is_finite` are exact.
//!
//! Units: millimetres, device frame.

use crate::real::Real;

use crate::model::{StringInputs, StringLayout, Vec3};
use crate::string_law::cos2_inclinations;
use crate::STRINGS;

/// `x` as `F` (constants only; every `f64` converts to `f32`/`f64`).
#[inline]
fn lit<F: Real>(x: f64) -> F {
    F::from(x).unwrap_or_else(F::zero)
}

/// Geometric string lengths `|position - anchor_i|` (mm), computed as
/// `sqrt(dx*dx + dy*dy + dz*dz)` in that order.
pub fn inverse_kinematics<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    position: Vec3<F>,
) -> [F; STRINGS] {
    let mut out = [F::zero(); STRINGS];
    for (o, a) in out.iter_mut().zip(anchors.iter()) {
        let dx = position[0] - a[0];
        let dy = position[1] - a[1];
        let dz = position[2] - a[2];
        *o = (dx * dx + dy * dy + dz * dz).sqrt_rounded();
    }
    out
}

/// Tuning of [`forward_kinematics`].
///
/// Worst case, the solver runs `max_iterations + STRINGS *
/// exclusion_max_iterations` iterations (110 with the defaults); each
/// iteration is one pass over the strings (8 `sqrt`, 8 divisions, ~120 other
/// flops) and one 3x3 solve (~40 flops, 3 divisions).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FkConfig<F> {
    /// Iteration limit of the solve with all strings (default 30).
    pub max_iterations: u32,
    /// Iteration limit of each leave-one-string-out solve (default 10; these
    /// start next to the solution).
    pub exclusion_max_iterations: u32,
    /// Converged when the proposed step is shorter than this (mm, default 1e-3).
    pub step_tolerance_mm: F,
    /// Steps shorter than this (mm, default 0.5) are accepted without
    /// checking that the cost decreased: within it the residuals are linear
    /// in the position to ~step^2 / (2 string length) < 1e-4 mm, while in f32
    /// the cost near the minimum is only known to ~1e-4 mm^2, so a cost test
    /// would reject good steps and stall. Larger steps must decrease the cost.
    pub trusted_step_mm: F,
    /// RMS string-length residual (mm) above which the strings are considered
    /// inconsistent and a faulty string is looked for (default 2 mm: a
    /// calibrated device with 0.1-0.5 mm length noise stays well below; a
    /// 10 mm error on one string typically raises the RMS to ~3 mm).
    pub fault_threshold_mm: F,
    /// Initial Levenberg-Marquardt damping (dimensionless, relative to
    /// `J^T J` whose eigenvalues are ~1-4 for unit Jacobian rows; default 1e-3).
    pub initial_damping: F,
}

impl<F: Real> Default for FkConfig<F> {
    /// Sensible for a ~2.2 m frame in millimetres.
    fn default() -> Self {
        Self {
            max_iterations: 30,
            exclusion_max_iterations: 10,
            step_tolerance_mm: lit(1e-3),
            trusted_step_mm: lit(0.5),
            fault_threshold_mm: lit(2.0),
            initial_damping: lit(1e-3),
        }
    }
}

impl<F: Real> FkConfig<F> {
    /// Worst-case iteration count of [`forward_kinematics`] with this config.
    pub fn worst_case_iterations(&self) -> u32 {
        self.max_iterations
            .saturating_add(self.exclusion_max_iterations.saturating_mul(STRINGS as u32))
    }
}

/// Outcome of [`forward_kinematics`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FkStatus {
    /// All strings agree (RMS residual <= `fault_threshold_mm`), converged.
    Ok,
    /// One string disagreed with the others; the position is solved from the
    /// other 7 and `excluded` names it.
    FaultyStringExcluded,
    /// The strings disagree and no single exclusion explains it (two or more
    /// faulty strings, or a bad calibration). The position is the all-string
    /// least-squares compromise or, with 4 or more spare strings, when
    /// leaving one string out lowers the RMS residual [`DOMINANT_EXCLUSION`]
    /// times or more, that solve's (`excluded` names the string): do not
    /// trust it either way.
    Inconsistent,
    /// The iteration limit was reached before convergence; the position is
    /// the best found.
    NotConverged,
    /// A string length is NaN, infinite or negative, or an anchor is not
    /// finite. The position is `start` (or the anchors' centroid, or 0).
    InvalidInput,
}

/// Result of [`forward_kinematics`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FkSolution<F> {
    /// Device-frame position (mm). Finite whenever the inputs are finite.
    pub position: Vec3<F>,
    pub status: FkStatus,
    /// Encoder index of the string left out, with [`FkStatus::FaultyStringExcluded`]
    /// (and with [`FkStatus::Inconsistent`] when one exclusion dominates).
    pub excluded: Option<u8>,
    /// RMS of `|position - anchor_i| - length_i` over the strings used (mm);
    /// infinite with [`FkStatus::InvalidInput`] or when it overflows.
    pub rms_residual_mm: F,
    /// Iterations run in total, fault handling included (see
    /// [`FkConfig::worst_case_iterations`]).
    pub iterations: u32,
}

/// Sum of squared residuals, normal matrix `J^T J` (upper triangle
/// `[00, 01, 02, 11, 12, 22]`) and gradient `J^T r` at `p`, skipping string
/// `skip`.
struct Eval<F> {
    cost: F,
    jtj: [F; 6],
    jtr: [F; 3],
}

fn evaluate<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    lengths: &[F; STRINGS],
    skip: Option<usize>,
    p: Vec3<F>,
) -> Eval<F> {
    let mut e = Eval {
        cost: F::zero(),
        jtj: [F::zero(); 6],
        jtr: [F::zero(); 3],
    };
    for i in 0..STRINGS {
        if skip == Some(i) || !layout.is_active(i) {
            continue;
        }
        let a = anchors[i];
        let dx = p[0] - a[0];
        let dy = p[1] - a[1];
        let dz = p[2] - a[2];
        let dist = (dx * dx + dy * dy + dz * dz).sqrt_rounded();
        let r = dist - lengths[i];
        e.cost = e.cost + r * r;
        // At an anchor the residual has no direction: no Jacobian row.
        if dist > F::zero() {
            let ux = dx / dist;
            let uy = dy / dist;
            let uz = dz / dist;
            e.jtj[0] = e.jtj[0] + ux * ux;
            e.jtj[1] = e.jtj[1] + ux * uy;
            e.jtj[2] = e.jtj[2] + ux * uz;
            e.jtj[3] = e.jtj[3] + uy * uy;
            e.jtj[4] = e.jtj[4] + uy * uz;
            e.jtj[5] = e.jtj[5] + uz * uz;
            e.jtr[0] = e.jtr[0] + ux * r;
            e.jtr[1] = e.jtr[1] + uy * r;
            e.jtr[2] = e.jtr[2] + uz * r;
        }
    }
    if layout.planar {
        // The end-effector stays in the anchors' plane: no step along z.
        e.jtj[2] = F::zero();
        e.jtj[4] = F::zero();
        e.jtj[5] = F::one();
        e.jtr[2] = F::zero();
    }
    e
}

/// Solves `(J^T J + lambda I) delta = -J^T r` by cofactors; `None` when the
/// matrix is singular or something is not finite.
fn damped_step<F: Real>(e: &Eval<F>, lambda: F) -> Option<Vec3<F>> {
    let m00 = e.jtj[0] + lambda;
    let m01 = e.jtj[1];
    let m02 = e.jtj[2];
    let m11 = e.jtj[3] + lambda;
    let m12 = e.jtj[4];
    let m22 = e.jtj[5] + lambda;
    let c00 = m11 * m22 - m12 * m12;
    let c01 = m02 * m12 - m01 * m22;
    let c02 = m01 * m12 - m02 * m11;
    let c11 = m00 * m22 - m02 * m02;
    let c12 = m01 * m02 - m00 * m12;
    let c22 = m00 * m11 - m01 * m01;
    let det = m00 * c00 + m01 * c01 + m02 * c02;
    if det <= F::zero() || !det.is_finite() {
        return None;
    }
    let b0 = -e.jtr[0];
    let b1 = -e.jtr[1];
    let b2 = -e.jtr[2];
    let d = [
        (c00 * b0 + c01 * b1 + c02 * b2) / det,
        (c01 * b0 + c11 * b1 + c12 * b2) / det,
        (c02 * b0 + c12 * b1 + c22 * b2) / det,
    ];
    if d[0].is_finite() && d[1].is_finite() && d[2].is_finite() {
        Some(d)
    } else {
        None
    }
}

struct Solve<F> {
    position: Vec3<F>,
    cost: F,
    iterations: u32,
    converged: bool,
}

/// Levenberg-Marquardt from `start` with at most `max_iterations` trials
/// (each trial = one evaluation and one 3x3 solve).
fn solve<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    lengths: &[F; STRINGS],
    skip: Option<usize>,
    start: Vec3<F>,
    max_iterations: u32,
    config: &FkConfig<F>,
) -> Solve<F> {
    let ten: F = lit(10.0);
    let tol2 = config.step_tolerance_mm * config.step_tolerance_mm;
    let trust2 = config.trusted_step_mm * config.trusted_step_mm;
    let mut p = start;
    let mut cur = evaluate(anchors, layout, lengths, skip, p);
    let mut lambda = config.initial_damping;
    let mut iterations = 0;
    let mut converged = false;
    while iterations < max_iterations {
        iterations += 1;
        let Some(d) = damped_step(&cur, lambda) else {
            lambda = lambda * ten;
            continue;
        };
        let step2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        let q = [p[0] + d[0], p[1] + d[1], p[2] + d[2]];
        let next = evaluate(anchors, layout, lengths, skip, q);
        // Short steps are taken without the cost test: there the model is
        // linear far below float resolution, while the cost difference of a
        // millimetre-scale step drowns in f32 rounding near the minimum.
        if next.cost < cur.cost || step2 <= trust2 {
            p = q;
            cur = next;
            lambda = lambda / ten;
            if step2 <= tol2 {
                converged = true;
                break;
            }
        } else {
            lambda = lambda * ten;
        }
    }
    Solve {
        position: p,
        cost: cur.cost,
        iterations,
        converged,
    }
}

/// Index of the string with the largest `| |p - anchor_i| - length_i |` (the
/// first one on ties; 0 if every residual is NaN).
fn largest_residual<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    lengths: &[F; STRINGS],
    p: Vec3<F>,
) -> usize {
    let mut worst = layout.indices().next().unwrap_or(0);
    let mut worst_r = F::neg_infinity();
    for i in layout.indices() {
        let a = anchors[i];
        let dx = p[0] - a[0];
        let dy = p[1] - a[1];
        let dz = p[2] - a[2];
        let r = ((dx * dx + dy * dy + dz * dz).sqrt_rounded() - lengths[i]).abs();
        if r > worst_r {
            worst = i;
            worst_r = r;
        }
    }
    worst
}

fn rms<F: Real>(cost: F, n: usize) -> F {
    let r = (cost / lit(n as f64)).sqrt_rounded();
    if r.is_finite() {
        r
    } else {
        F::infinity()
    }
}

fn finite3<F: Real>(v: &Vec3<F>) -> bool {
    v[0].is_finite() && v[1].is_finite() && v[2].is_finite()
}

/// Forward kinematics of one session row whose string lengths read the
/// strings' inclination (a sag, [`crate::model::Effect::reads_inclination`]),
/// for the host's replays of a session (f64 reference and device bits): the
/// lengths at the inclinations at `start`, then, when `inclined`, at those of
/// the first solution, solved again from it. The device's loop needs no
/// second solve: the position it holds is a tick old. `lengths` gives the
/// string lengths of `inputs`.
pub fn forward_kinematics_inclined<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    inputs: &StringInputs,
    start: Vec3<F>,
    config: &FkConfig<F>,
    inclined: bool,
    lengths: impl Fn(&StringInputs) -> [F; STRINGS],
) -> FkSolution<F> {
    let mut inputs = *inputs;
    inputs.cos2_inclination_q16 = cos2_inclinations(anchors, &start);
    let fk = forward_kinematics(anchors, layout, &lengths(&inputs), start, config);
    if !inclined || !finite3(&fk.position) {
        return fk;
    }
    inputs.cos2_inclination_q16 = cos2_inclinations(anchors, &fk.position);
    forward_kinematics(anchors, layout, &lengths(&inputs), fk.position, config)
}

/// Position (mm, device frame) from the string lengths of the channels
/// `layout` marks active, warm-started from `start` (the previous position;
/// the frame centre on a cold start). Inactive channels' anchors and lengths
/// are not read.
///
/// 1. Damped Gauss-Newton (Levenberg-Marquardt) on the residuals
///    `|p - anchor_i| - length_i` of the `n` active strings, at most
///    `config.max_iterations` iterations (planar layouts keep `z`).
/// 2. If the RMS residual exceeds `config.fault_threshold_mm` and the layout
///    has at least 2 spare strings ([`StringLayout::redundancy`]; with one
///    spare a disagreement is seen but no string can be blamed), solves
///    leaving one string out (`n - 1` strings) are run, each from the better
///    of `start` and the all-string solution, at most
///    `config.exclusion_max_iterations` iterations each. The string with the
///    largest residual at the all-string solution goes first; if leaving it
///    out converges within the threshold it is the answer
///    ([`FkStatus::FaultyStringExcluded`]). Otherwise the others are run too
///    and the one with the lowest RMS is kept if it is converged and below
///    the threshold, else [`FkStatus::Inconsistent`].
///
/// Fewer active strings than degrees of freedom is [`FkStatus::InvalidInput`].
/// Never panics; never returns a NaN position or RMS (a non-finite `start`
/// is replaced by the active anchors' centroid).
///
/// One piece (a numerical kernel of the control loop): the exclusion search
/// of step 2 as a function of its own changes the code the device runs
/// (out of line: 1 % more instructions with a faulty string; always inlined:
/// a few instructions more or fewer per call, under `scripts/qemu-bench`).
pub fn forward_kinematics<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    lengths: &[F; STRINGS],
    start: Vec3<F>,
    config: &FkConfig<F>,
) -> FkSolution<F> {
    let n_strings = layout.count();
    let anchors_ok = layout.indices().all(|i| finite3(&anchors[i]));
    let start = if finite3(&start) {
        start
    } else if anchors_ok && n_strings > 0 {
        let mut c = [F::zero(); 3];
        for i in layout.indices() {
            let a = anchors[i];
            c = [c[0] + a[0], c[1] + a[1], c[2] + a[2]];
        }
        let n: F = lit(n_strings as f64);
        [c[0] / n, c[1] / n, c[2] / n]
    } else {
        [F::zero(); 3]
    };
    let lengths_ok = layout
        .indices()
        .all(|i| lengths[i].is_finite() && lengths[i] >= F::zero());
    if !anchors_ok || !lengths_ok || n_strings < layout.dof() {
        return FkSolution {
            position: start,
            status: FkStatus::InvalidInput,
            excluded: None,
            rms_residual_mm: F::infinity(),
            iterations: 0,
        };
    }

    let all = solve(
        anchors,
        layout,
        lengths,
        None,
        start,
        config.max_iterations,
        config,
    );
    let all_rms = rms(all.cost, n_strings);
    let mut iterations = all.iterations;
    // An infinite RMS (overflow) is not below the threshold: fault handling.
    if all_rms <= config.fault_threshold_mm {
        return FkSolution {
            position: all.position,
            status: if all.converged {
                FkStatus::Ok
            } else {
                FkStatus::NotConverged
            },
            excluded: None,
            rms_residual_mm: all_rms,
            iterations,
        };
    }
    let inconsistent = FkSolution {
        position: all.position,
        status: if all.converged {
            FkStatus::Inconsistent
        } else {
            FkStatus::NotConverged
        },
        excluded: None,
        rms_residual_mm: all_rms,
        iterations,
    };
    if layout.redundancy() < 2 {
        // Leaving one string out would leave no spare to check the rest:
        // any exclusion fits exactly, so none can be trusted.
        return inconsistent;
    }

    // The string with the largest residual at the all-string solution is the
    // likeliest culprit: its exclusion is tried first and kept at once if it
    // explains the lengths (converged, RMS within the threshold), which
    // spares the other solves in the common single-fault case. Otherwise
    // every exclusion is tried and the best one kept.
    let first = largest_residual(anchors, layout, lengths, all.position);
    let exclude = |k: usize| {
        let skip = Some(k);
        // Start from whichever of the previous position and the all-string
        // solution fits the remaining strings better.
        let c_start = evaluate(anchors, layout, lengths, skip, start).cost;
        let c_all = evaluate(anchors, layout, lengths, skip, all.position).cost;
        let from = if c_start < c_all { start } else { all.position };
        solve(
            anchors,
            layout,
            lengths,
            skip,
            from,
            config.exclusion_max_iterations,
            config,
        )
    };
    let s = exclude(first);
    iterations = iterations.saturating_add(s.iterations);
    let r = rms(s.cost, n_strings - 1);
    // With few spare strings, leaving a good string out can also leave a
    // set that fits within the threshold (the fault is absorbed by the
    // position): then an exclusion is only trusted when it is the one set
    // that fits. With 4 or more spares (7 or 8 strings in 3-D) the first
    // fit is taken at once.
    let unique_required = layout.redundancy() < 4;
    if !unique_required && s.converged && r <= config.fault_threshold_mm {
        return FkSolution {
            position: s.position,
            status: FkStatus::FaultyStringExcluded,
            excluded: Some(first as u8),
            rms_residual_mm: r,
            iterations,
        };
    }
    let fits =
        |s: &Solve<F>| s.converged && rms(s.cost, n_strings - 1) <= config.fault_threshold_mm;
    let mut fitting = usize::from(fits(&s));
    let mut best: Option<(usize, Solve<F>)> = Some((first, s));
    for k in layout.indices().filter(|&k| k != first) {
        let s = exclude(k);
        iterations = iterations.saturating_add(s.iterations);
        fitting += usize::from(fits(&s));
        let better = match &best {
            None => true,
            Some((_, b)) => s.cost < b.cost,
        };
        if better {
            best = Some((k, s));
        }
    }
    if let Some((k, s)) = best {
        let r = rms(s.cost, n_strings - 1);
        if s.converged && r <= config.fault_threshold_mm && (!unique_required || fitting == 1) {
            return FkSolution {
                position: s.position,
                status: FkStatus::FaultyStringExcluded,
                excluded: Some(k as u8),
                rms_residual_mm: r,
                iterations,
            };
        }
        // No exclusion fits, but one explains most of the disagreement (a
        // faulty string on a device whose other strings disagree a little
        // too): its position is a better estimate than the compromise that
        // spreads the faulty string's error over all of them. Still
        // inconsistent: not to be trusted for force.
        if !unique_required && s.converged && r * lit(DOMINANT_EXCLUSION) <= all_rms {
            return FkSolution {
                position: s.position,
                status: FkStatus::Inconsistent,
                excluded: Some(k as u8),
                rms_residual_mm: r,
                iterations,
            };
        }
    }
    FkSolution {
        iterations,
        ..inconsistent
    }
}

/// An exclusion that does not bring the RMS residual within the threshold
/// but lowers it this many times gives the position of an inconsistent solve
/// (see [`FkStatus::Inconsistent`]).
pub const DOMINANT_EXCLUSION: f64 = 3.0;

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn anchors<F: Real>() -> [Vec3<F>; STRINGS] {
        let h: F = lit(1100.0);
        let mut a = [[F::zero(); 3]; STRINGS];
        for (i, v) in a.iter_mut().enumerate() {
            *v = [
                if i & 1 == 0 { -h } else { h },
                if i & 2 == 0 { -h } else { h },
                if i & 4 == 0 { -h } else { h },
            ];
        }
        a
    }

    /// A row far from the previous one (a lattice's next point): lengths
    /// that read the inclination (a 20 mm sag-like term, exact at the true
    /// inclinations) solved once at the previous position's inclinations
    /// are off; solved again at the first solution's, they are not.
    #[test]
    fn a_row_whose_lengths_read_the_inclination_is_solved_at_its_own() {
        let a = anchors::<f64>();
        let config = FkConfig::<f64>::default();
        let truth = [300.0, -200.0, 150.0];
        let at_truth = cos2_inclinations(&a, &truth);
        let lengths = |inputs: &StringInputs| -> [f64; STRINGS] {
            let chords = inverse_kinematics(&a, truth);
            core::array::from_fn(|i| {
                let read = f64::from(inputs.cos2_inclination_q16[i]) / 65536.0;
                chords[i] + 20.0 * (read - f64::from(at_truth[i]) / 65536.0)
            })
        };
        let inputs = StringInputs::default();
        let solve = |inclined| {
            let fk = forward_kinematics_inclined(
                &a,
                StringLayout::ALL,
                &inputs,
                [0.0; 3],
                &config,
                inclined,
                lengths,
            );
            dist(fk.position, truth)
        };
        let (once, twice) = (solve(false), solve(true));
        assert!(once > 1.0, "{once}");
        assert!(twice < 0.1 * once && twice < 0.5, "{once} -> {twice}");
    }

    /// Points of a 1 m cube centred in the frame, `n` per axis.
    fn cube(n: usize) -> Vec<[f64; 3]> {
        let mut out = Vec::new();
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let c = |m: usize| -500.0 + 1000.0 * m as f64 / (n - 1) as f64;
                    out.push([c(i), c(j), c(k)]);
                }
            }
        }
        out
    }

    fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    }

    fn to_f64<F: Real>(p: Vec3<F>) -> [f64; 3] {
        [
            p[0].to_f64().unwrap(),
            p[1].to_f64().unwrap(),
            p[2].to_f64().unwrap(),
        ]
    }

    /// Round trip position -> lengths -> position; returns (max error mm, max iterations).
    fn round_trip<F: Real + core::fmt::Debug>(warm: bool) -> (f64, u32) {
        let a = anchors::<F>();
        let config = FkConfig::<F>::default();
        let mut max_err = 0.0f64;
        let mut max_it = 0;
        for p in cube(11) {
            let pf = [lit::<F>(p[0]), lit(p[1]), lit(p[2])];
            // Lengths from the exact f64 geometry, rounded to F once.
            let a64 = anchors::<f64>();
            let l64 = inverse_kinematics(&a64, p);
            let l: [F; STRINGS] = core::array::from_fn(|i| lit(l64[i]));
            let start = if warm {
                [pf[0] + lit(3.0), pf[1] - lit(2.0), pf[2] + lit(1.5)]
            } else {
                [F::zero(); 3]
            };
            let s = forward_kinematics(&a, StringLayout::ALL, &l, start, &config);
            assert_eq!(s.status, FkStatus::Ok, "{p:?}: {s:?}");
            max_err = max_err.max(dist(to_f64(s.position), p));
            max_it = max_it.max(s.iterations);
        }
        (max_err, max_it)
    }

    #[test]
    fn round_trip_f64_cold_and_warm() {
        let (e, it) = round_trip::<f64>(false);
        println!("f64 cold: max error {e:.2e} mm, max iterations {it}");
        assert!(e < 1e-6, "cold f64 error {e} mm");
        assert!(it <= 10, "cold f64 iterations {it}");
        let (e, it) = round_trip::<f64>(true);
        println!("f64 warm: max error {e:.2e} mm, max iterations {it}");
        assert!(e < 1e-6, "warm f64 error {e} mm");
        assert!(it <= 5, "warm f64 iterations {it}");
    }

    #[test]
    fn round_trip_f32_cold_and_warm() {
        let (e, it) = round_trip::<f32>(false);
        println!("f32 cold: max error {e:.2e} mm, max iterations {it}");
        assert!(e < 0.01, "cold f32 error {e} mm");
        assert!(it <= 12, "cold f32 iterations {it}");
        let (e, it) = round_trip::<f32>(true);
        println!("f32 warm: max error {e:.2e} mm, max iterations {it}");
        assert!(e < 0.01, "warm f32 error {e} mm");
        assert!(it <= 6, "warm f32 iterations {it}");
    }

    #[test]
    fn inverse_kinematics_at_centre() {
        let l = inverse_kinematics(&anchors::<f64>(), [0.0; 3]);
        for v in l {
            assert!((v - 1100.0 * 3f64.sqrt()).abs() < 1e-9);
        }
    }

    fn check_single_fault<F: Real + core::fmt::Debug>() -> (f64, u32) {
        let mut max_err = 0.0f64;
        let mut max_it = 0;
        let a = anchors::<F>();
        let a64 = anchors::<f64>();
        let config = FkConfig::<F>::default();
        for (n, p) in cube(5).into_iter().enumerate() {
            let bad = n % STRINGS;
            let mut l64 = inverse_kinematics(&a64, p);
            l64[bad] += 40.0;
            let l: [F; STRINGS] = core::array::from_fn(|i| lit(l64[i]));
            for start in [[F::zero(); 3], [lit(p[0]), lit(p[1]), lit(p[2])]] {
                let s = forward_kinematics(&a, StringLayout::ALL, &l, start, &config);
                assert_eq!(
                    s.status,
                    FkStatus::FaultyStringExcluded,
                    "{p:?} bad {bad}: {s:?}"
                );
                assert_eq!(s.excluded, Some(bad as u8));
                let err = dist(to_f64(s.position), p);
                assert!(err < 0.5, "{p:?}: error {err} mm");
                assert!(s.iterations <= config.worst_case_iterations());
                max_err = max_err.max(err);
                max_it = max_it.max(s.iterations);
            }
        }
        (max_err, max_it)
    }

    #[test]
    fn one_faulty_string_is_excluded() {
        let (e, it) = check_single_fault::<f64>();
        println!("+40 mm on one string, f64: max error {e:.2e} mm, max iterations {it}");
        let (e, it) = check_single_fault::<f32>();
        println!("+40 mm on one string, f32: max error {e:.2e} mm, max iterations {it}");
    }

    #[test]
    fn two_faulty_strings_are_inconsistent() {
        let a = anchors::<f64>();
        let config = FkConfig::default();
        for (n, p) in cube(5).into_iter().enumerate() {
            let b1 = n % STRINGS;
            let b2 = (n + 3) % STRINGS;
            let mut l = inverse_kinematics(&a, p);
            l[b1] += 40.0;
            l[b2] -= 30.0;
            let s = forward_kinematics(&a, StringLayout::ALL, &l, p, &config);
            assert_eq!(
                s.status,
                FkStatus::Inconsistent,
                "{p:?} bad {b1},{b2}: {s:?}"
            );
            assert_eq!(s.excluded, None);
            assert!(s.rms_residual_mm > config.fault_threshold_mm);
        }
    }

    /// Deterministic Gaussian-ish noise (sum of 12 uniforms - 6).
    struct Noise(u64);
    impl Noise {
        fn gauss(&mut self) -> f64 {
            let mut s = 0.0;
            for _ in 0..12 {
                self.0 ^= self.0 << 13;
                self.0 ^= self.0 >> 7;
                self.0 ^= self.0 << 17;
                s += (self.0 >> 11) as f64 / (1u64 << 53) as f64;
            }
            s - 6.0
        }
    }

    #[test]
    fn length_noise_gives_sub_mm_position_error() {
        let mut noise = Noise(0x1234_5678);
        let a = anchors::<f64>();
        let af = anchors::<f32>();
        let config = FkConfig::default();
        let configf = FkConfig::<f32>::default();
        let mut max64 = 0.0f64;
        let mut max32 = 0.0f64;
        for p in cube(7) {
            let mut l = inverse_kinematics(&a, p);
            for v in l.iter_mut() {
                *v += 0.1 * noise.gauss();
            }
            let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &config);
            assert_eq!(s.status, FkStatus::Ok, "{s:?}");
            max64 = max64.max(dist(s.position, p));
            let lf: [f32; STRINGS] = core::array::from_fn(|i| l[i] as f32);
            let s = forward_kinematics(&af, StringLayout::ALL, &lf, [0.0; 3], &configf);
            assert_eq!(s.status, FkStatus::Ok, "{s:?}");
            max32 = max32.max(dist(to_f64(s.position), p));
        }
        println!("0.1 mm length noise: max position error f64 {max64:.3} mm, f32 {max32:.3} mm");
        assert!(max64 < 1.0 && max32 < 1.0, "{max64} {max32}");
    }

    #[test]
    fn invalid_inputs() {
        let a = anchors::<f32>();
        let config = FkConfig::default();
        let good = inverse_kinematics(&a, [10.0, 20.0, 30.0]);
        for bad in [f32::NAN, f32::INFINITY, -1.0] {
            let mut l = good;
            l[4] = bad;
            let s = forward_kinematics(&a, StringLayout::ALL, &l, [1.0, 2.0, 3.0], &config);
            assert_eq!(s.status, FkStatus::InvalidInput);
            assert_eq!(s.position, [1.0, 2.0, 3.0]);
            assert!(!s.rms_residual_mm.is_nan());
        }
        let mut na = a;
        na[2][1] = f32::NAN;
        let s = forward_kinematics(&na, StringLayout::ALL, &good, [0.0; 3], &config);
        assert_eq!(s.status, FkStatus::InvalidInput);
        // A NaN start is replaced by the centroid and still solves.
        let s = forward_kinematics(&a, StringLayout::ALL, &good, [f32::NAN; 3], &config);
        assert_eq!(s.status, FkStatus::Ok);
        assert!((s.position[0] - 10.0).abs() < 0.01);
    }

    #[test]
    fn at_an_anchor_and_degenerate() {
        let a = anchors::<f64>();
        let config = FkConfig::default();
        // Start exactly on an anchor.
        let l = inverse_kinematics(&a, [100.0, 0.0, 0.0]);
        let s = forward_kinematics(&a, StringLayout::ALL, &l, a[0], &config);
        assert_eq!(s.status, FkStatus::Ok);
        // All anchors at one point: no position can be found, but no NaN.
        let same = [[0.0; 3]; STRINGS];
        let s = forward_kinematics(
            &same,
            StringLayout::ALL,
            &[100.0; STRINGS],
            [0.0; 3],
            &config,
        );
        assert!(s.position.iter().all(|v| v.is_finite()));
        assert!(!s.rms_residual_mm.is_nan());
    }

    /// A 4-line cable robot (Hangprinter-like: three low anchors, one high)
    /// on channels 0..4; channels 4..8 hold garbage that must not be read.
    fn four_line_anchors() -> ([Vec3<f64>; STRINGS], StringLayout) {
        let mut a = [[f64::NAN; 3]; STRINGS];
        a[0] = [0.0, -1620.0, -150.0];
        a[1] = [1272.8, 1272.8, -150.0];
        a[2] = [-1403.0, 810.0, -150.0];
        a[3] = [0.0, 0.0, 2350.0];
        (a, StringLayout::first(4, false))
    }

    #[test]
    fn four_strings_round_trip_and_ignore_inactive_channels() {
        let (a, layout) = four_line_anchors();
        for p in [
            [0.0, 0.0, 0.0],
            [300.0, -250.0, 400.0],
            [-400.0, 500.0, 1100.0],
        ] {
            let mut l = inverse_kinematics(&a, p);
            for v in l.iter_mut().skip(4) {
                *v = f64::NAN;
            }
            let s = forward_kinematics(&a, layout, &l, [0.0, 0.0, 100.0], &FkConfig::default());
            assert_eq!(s.status, FkStatus::Ok, "{s:?}");
            assert!(dist(s.position, p) < 1e-6, "{:?} vs {p:?}", s.position);
        }
    }

    #[test]
    fn one_spare_string_sees_a_fault_but_blames_no_string() {
        let (a, layout) = four_line_anchors();
        assert_eq!(layout.redundancy(), 1);
        let mut l = inverse_kinematics(&a, [100.0, 50.0, 300.0]);
        l[2] += 30.0;
        let s = forward_kinematics(&a, layout, &l, [0.0; 3], &FkConfig::default());
        assert_eq!(s.status, FkStatus::Inconsistent, "{s:?}");
        assert_eq!(s.excluded, None);
    }

    /// A faulty string on a device whose other strings disagree by more than
    /// the threshold too: no exclusion fits, but leaving the faulty string
    /// out explains most of it, and that position is kept (flagged
    /// inconsistent) instead of the compromise.
    #[test]
    fn a_dominant_exclusion_gives_the_position_of_an_inconsistent_solve() {
        let a = anchors::<f64>();
        let p = [150.0, -220.0, 90.0];
        let exact = inverse_kinematics(&a, p);
        for bad in 0..STRINGS {
            let mut l = exact;
            for (i, v) in l.iter_mut().enumerate() {
                // The sign of x y z at corner i: no position absorbs it.
                let sign = [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0][i];
                *v += if i == bad { 40.0 } else { 2.6 * sign };
            }
            let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &FkConfig::default());
            assert_eq!(s.status, FkStatus::Inconsistent, "bad {bad}: {s:?}");
            assert_eq!(s.excluded, Some(bad as u8), "bad {bad}");
            let compromise = forward_kinematics(
                &a,
                StringLayout::ALL,
                &l,
                [0.0; 3],
                &FkConfig {
                    fault_threshold_mm: f64::INFINITY,
                    ..FkConfig::default()
                },
            );
            let (kept, spread) = (dist(s.position, p), dist(compromise.position, p));
            assert!(
                kept < 6.0 && kept < spread / 3.0,
                "bad {bad}: {kept} vs {spread} mm"
            );
        }
        // Two faulty strings: no exclusion dominates, the compromise stays.
        let mut l = exact;
        l[1] += 40.0;
        l[5] -= 35.0;
        let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &FkConfig::default());
        assert_eq!(
            (s.status, s.excluded),
            (FkStatus::Inconsistent, None),
            "{s:?}"
        );
    }

    #[test]
    fn two_spare_strings_exclude_a_faulty_one() {
        let full = anchors::<f64>();
        // Channels 0, 1, 2, 4, 6, 7 of the cube: 6 strings, redundancy 3.
        let layout = StringLayout {
            active: 0b1101_0111,
            planar: false,
        };
        assert_eq!(layout.redundancy(), 3);
        let p = [120.0, -80.0, 60.0];
        let good = inverse_kinematics(&full, p);
        // A faulty string is excluded when it is the only one whose
        // exclusion fits; where leaving another string out fits too (the
        // fault absorbed by a different position) no string is blamed, never
        // the wrong one. At this point that happens for string 4 (and for
        // string 2 at 25 mm): leaving string 2 out fits within 0.3 mm.
        let mut excluded_right = 0;
        for bad in layout.indices() {
            for amount in [25.0, 150.0] {
                let mut l = good;
                l[bad] += amount;
                let s = forward_kinematics(&full, layout, &l, [0.0; 3], &FkConfig::default());
                match s.status {
                    FkStatus::FaultyStringExcluded => {
                        assert_eq!(s.excluded, Some(bad as u8), "+{amount} on {bad}: {s:?}");
                        assert!(dist(s.position, p) < 1e-3);
                        excluded_right += 1;
                    }
                    FkStatus::Inconsistent => assert_eq!(s.excluded, None),
                    _ => panic!("+{amount} on {bad}: {s:?}"),
                }
            }
        }
        assert!(excluded_right >= 9, "{excluded_right} of 12");
    }

    #[test]
    fn planar_layout_solves_in_the_anchors_plane() {
        let mut a = [[0.0; 3]; STRINGS];
        for (i, v) in a.iter_mut().take(4).enumerate() {
            let (x, y) = [
                (-800.0, -600.0),
                (800.0, -600.0),
                (800.0, 600.0),
                (-800.0, 600.0),
            ][i];
            *v = [x, y, 25.0];
        }
        for n in [3usize, 4] {
            let layout = StringLayout::first(n, true);
            assert_eq!(layout.dof(), 2);
            let p = [210.0, -130.0, 25.0];
            let l = inverse_kinematics(&a, p);
            // A start off the plane stays off by that offset in z: the
            // solve moves x, y only. Starts come from the plane (home).
            let s = forward_kinematics(&a, layout, &l, [0.0, 0.0, 25.0], &FkConfig::default());
            assert_eq!(s.status, FkStatus::Ok, "{n} strings: {s:?}");
            assert!(dist(s.position, p) < 1e-6, "{n}: {:?}", s.position);
        }
        // One string cannot fix a point in the plane.
        let s = forward_kinematics(
            &a,
            StringLayout::first(1, true),
            &[500.0; STRINGS],
            [0.0, 0.0, 25.0],
            &FkConfig::default(),
        );
        assert_eq!(s.status, FkStatus::InvalidInput);
    }

    #[test]
    fn layout_counts() {
        assert_eq!(StringLayout::ALL.count(), 8);
        assert_eq!(StringLayout::ALL.redundancy(), 5);
        assert_eq!(StringLayout::first(3, false).redundancy(), 0);
        assert_eq!(StringLayout::first(9, false), StringLayout::ALL);
        let l = StringLayout {
            active: 0b0101_0000,
            planar: true,
        };
        assert_eq!(l.indices().collect::<Vec<_>>(), [4, 6]);
    }

    proptest! {
        /// Finite inputs never give a NaN or a panic, whatever their values.
        #[test]
        fn finite_inputs_never_nan(l in proptest::array::uniform8(0.0f32..1e30),
                                   start in proptest::array::uniform3(-1e30f32..1e30),
                                   scale in prop_oneof![Just(1.0f32), Just(1e-30), Just(1e20)]) {
            let mut a = anchors::<f32>();
            for v in a.iter_mut() { for c in v.iter_mut() { *c *= scale; } }
            let s = forward_kinematics(&a, StringLayout::ALL, &l, start, &FkConfig::default());
            prop_assert!(s.position.iter().all(|v| v.is_finite()), "{:?}", s);
            prop_assert!(!s.rms_residual_mm.is_nan());
            prop_assert!(s.iterations <= FkConfig::<f32>::default().worst_case_iterations());
        }

        #[test]
        fn realistic_lengths_round_trip(p in proptest::array::uniform3(-500.0f64..500.0),
                                        s in proptest::array::uniform3(-600.0f64..600.0)) {
            let a = anchors::<f64>();
            let l = inverse_kinematics(&a, p);
            let sol = forward_kinematics(&a, StringLayout::ALL, &l, s, &FkConfig::default());
            prop_assert_eq!(sol.status, FkStatus::Ok);
            prop_assert!(dist(sol.position, p) < 1e-6);
        }
    }
}
