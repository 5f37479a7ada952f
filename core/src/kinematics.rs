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

use crate::model::{Frame, StringInputs, StringLayout, Vec3};
use crate::string_law::{cos2_inclinations, guide_elevations};
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
    /// RMS string-length residual (mm) above which a faulty string is looked
    /// for while the strings still count as agreeing (default 1 mm, at most
    /// `fault_threshold_mm`): an exclusion that brings the others within it
    /// gives the position ([`FkStatus::FaultyStringExcluded`]); without one,
    /// the all-string solution stands ([`FkStatus::Ok`]) up to
    /// `fault_threshold_mm`. A string that slipped a few mm on its spool, or
    /// the paper's abnormal motor riding out of its groove, raises the RMS
    /// of 8 strings by ~1 mm, under the 2 mm at which the strings are
    /// inconsistent, and pulls the all-string position by that much; a
    /// calibrated device's strings agree to 0.15 mm RMS (p99 0.4 mm) on
    /// independent physics (decision record 0030,
    /// `docs/decisions/0030-faulty-string-from-1mm.md`).
    pub exclusion_threshold_mm: F,
    /// Initial Levenberg-Marquardt damping (dimensionless, relative to
    /// `J^T J` whose eigenvalues are ~1-4 for unit Jacobian rows; default 1e-3).
    pub initial_damping: F,
    /// Weight of each string's residual (default 1 for every string): the
    /// solve minimises `sum_i (w_i (|p - anchor_i| - length_i))^2`, and the
    /// thresholds above, the RMS and the choice of the string to leave out
    /// read the weighted residuals, so a string of weight `w` counts as
    /// faulty only at `1/w` times the length error of a string of weight 1.
    /// [`residual_weights`] sets them from each string's measured residual
    /// scale. A weight of exactly 1 multiplies exactly: the unweighted solve
    /// is bit for bit what it was.
    pub residual_weight: [F; STRINGS],
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
            exclusion_threshold_mm: lit(1.0),
            initial_damping: lit(1e-3),
            residual_weight: [F::one(); STRINGS],
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

/// When forward kinematics looks for a faulty string and when it calls the
/// strings inconsistent: the two thresholds of [`FkConfig`] a calibration
/// chooses for its device and the blob carries (format 9). The defaults are
/// [`FkConfig::default`]'s. A rule whose `exclusion_threshold_mm` equals its
/// `fault_threshold_mm` never leaves a string out of an agreeing row: the
/// position is the all-string least squares until the strings are
/// inconsistent.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct KinematicsRule {
    /// [`FkConfig::exclusion_threshold_mm`], mm.
    pub exclusion_threshold_mm: f64,
    /// [`FkConfig::fault_threshold_mm`], mm.
    pub fault_threshold_mm: f64,
}

impl Default for KinematicsRule {
    fn default() -> Self {
        let fk = FkConfig::<f64>::default();
        KinematicsRule {
            exclusion_threshold_mm: fk.exclusion_threshold_mm,
            fault_threshold_mm: fk.fault_threshold_mm,
        }
    }
}

impl KinematicsRule {
    /// Whether both thresholds are positive numbers and the exclusion's is
    /// not above the fault's (what a device can run).
    pub fn is_valid(&self) -> bool {
        let ok = |t: f64| t.is_finite() && t > 0.0;
        ok(self.exclusion_threshold_mm)
            && ok(self.fault_threshold_mm)
            && self.exclusion_threshold_mm <= self.fault_threshold_mm
    }

    /// `config` with this rule's thresholds.
    pub fn apply<F: Real>(&self, config: &FkConfig<F>) -> FkConfig<F> {
        FkConfig {
            exclusion_threshold_mm: lit(self.exclusion_threshold_mm),
            fault_threshold_mm: lit(self.fault_threshold_mm),
            ..*config
        }
    }
}

/// Outcome of [`forward_kinematics`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FkStatus {
    /// All strings agree (RMS residual <= `fault_threshold_mm`), converged.
    Ok,
    /// One string disagreed with the others; the position is solved from the
    /// other active strings and `excluded` names it.
    FaultyStringExcluded,
    /// The strings disagree and no single exclusion explains it (two or more
    /// faulty strings, or a bad calibration). The position is the all-string
    /// least-squares compromise or, with 4 or more spare strings (2 or 3
    /// when that exclusion fits [`DOMINANT_EXCLUSION`] times better than any
    /// other), when leaving one string out lowers the RMS residual
    /// [`DOMINANT_EXCLUSION`] times or more, that solve's (`excluded` names
    /// the string): do not trust it either way.
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
    /// RMS of `w_i (|position - anchor_i| - length_i)` over the strings used
    /// (mm, weights [`FkConfig::residual_weight`]);
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
    weights: &[F; STRINGS],
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
        let w = weights[i];
        let r = (dist - lengths[i]) * w;
        e.cost = e.cost + r * r;
        // At an anchor the residual has no direction: no Jacobian row.
        if dist > F::zero() {
            let ux = dx / dist * w;
            let uy = dy / dist * w;
            let uz = dz / dist * w;
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
    let mut cur = evaluate(anchors, layout, lengths, &config.residual_weight, skip, p);
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
        let next = evaluate(anchors, layout, lengths, &config.residual_weight, skip, q);
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
    weights: &[F; STRINGS],
    p: Vec3<F>,
) -> usize {
    let mut worst = layout.indices().next().unwrap_or(0);
    let mut worst_r = F::neg_infinity();
    for i in layout.indices() {
        let a = anchors[i];
        let dx = p[0] - a[0];
        let dy = p[1] - a[1];
        let dz = p[2] - a[2];
        let r = (((dx * dx + dy * dy + dz * dz).sqrt_rounded() - lengths[i]) * weights[i]).abs();
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
/// strings' direction from the position (a sag its inclination, a guide
/// its elevation, [`crate::model::Effect::reads_inclination`]), for the
/// host's replays of a session (f64 reference and device bits): the
/// lengths at the directions at `start`, then, when `inclined`, at those of
/// the first solution, solved again from it (the anchors, home and layout
/// of `frame`). The device's loop needs no second solve: the position it
/// holds is a tick old. `lengths` gives the string lengths of `inputs`.
pub fn forward_kinematics_inclined<F: Real>(
    frame: &Frame<F>,
    inputs: &StringInputs,
    start: Vec3<F>,
    config: &FkConfig<F>,
    inclined: bool,
    lengths: impl Fn(&StringInputs) -> [F; STRINGS],
) -> FkSolution<F> {
    let (anchors, home, layout) = (&frame.anchors, &frame.home, frame.layout);
    if !inclined {
        // No term reads the directions: the lengths are the inputs' own.
        return forward_kinematics(anchors, layout, &lengths(inputs), start, config);
    }
    let mut inputs = *inputs;
    inputs.cos2_inclination_q16 = cos2_inclinations(anchors, &start);
    inputs.guide_elevation_q32 = guide_elevations(anchors, home, &start);
    let fk = forward_kinematics(anchors, layout, &lengths(&inputs), start, config);
    if !finite3(&fk.position) {
        return fk;
    }
    inputs.cos2_inclination_q16 = cos2_inclinations(anchors, &fk.position);
    inputs.guide_elevation_q32 = guide_elevations(anchors, home, &fk.position);
    forward_kinematics(anchors, layout, &lengths(&inputs), fk.position, config)
}

/// Position (mm, device frame) from the string lengths of the channels
/// `layout` marks active, warm-started from `start` (the previous position;
/// the frame centre on a cold start). Inactive channels' anchors and lengths
/// are not read.
///
/// 1. Damped Gauss-Newton (Levenberg-Marquardt) on the weighted residuals
///    `w_i (|p - anchor_i| - length_i)` of the `n` active strings
///    ([`FkConfig::residual_weight`]; every RMS below is of them), at most
///    `config.max_iterations` iterations (planar layouts keep `z`).
/// 2. If the RMS residual exceeds `config.exclusion_threshold_mm` and the layout
///    has at least 2 spare strings ([`StringLayout::redundancy`]; with one
///    spare a disagreement is seen but no string can be blamed), solves
///    leaving one string out (`n - 1` strings) are run, each from the better
///    of `start` and the all-string solution, at most
///    `config.exclusion_max_iterations` iterations each. The string with the
///    largest residual at the all-string solution goes first; if leaving it
///    out converges within the threshold it is the answer
///    ([`FkStatus::FaultyStringExcluded`]). Otherwise the others are run too
///    and the one with the lowest RMS is kept if it is converged and below
///    the threshold. The threshold is `exclusion_threshold_mm` while the
///    all-string RMS is within `config.fault_threshold_mm` (without such an
///    exclusion the all-string solution is [`FkStatus::Ok`]), and
///    `fault_threshold_mm` beyond it (without one: [`FkStatus::Inconsistent`]).
///
/// Fewer active strings than degrees of freedom is [`FkStatus::InvalidInput`].
/// Never panics; never returns a NaN position or RMS (a non-finite `start`
/// is replaced by the active anchors' centroid).
///
/// One piece (a numerical kernel of the control loop): the exclusion search
/// of step 2 as a function of its own changes the code the device runs
/// (out of line: 1 % more instructions with a faulty string; always inlined:
/// a few instructions more or fewer per call, under `scripts/qemu-bench`).
#[allow(
    clippy::too_many_lines,
    reason = "a numerical kernel of the control loop: splitting it changes the device's code"
)]
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
    let fault_mm = config.fault_threshold_mm;
    let look_mm = if config.exclusion_threshold_mm < fault_mm {
        config.exclusion_threshold_mm
    } else {
        fault_mm
    };
    // Within the fault threshold the strings agree: the all-string solution
    // stands unless an exclusion brings the others within `look_mm`. An
    // infinite RMS (overflow) is not below either threshold.
    let agree = all_rms <= fault_mm;
    let all_strings = FkSolution {
        position: all.position,
        status: match (all.converged, agree) {
            (false, _) => FkStatus::NotConverged,
            (true, true) => FkStatus::Ok,
            (true, false) => FkStatus::Inconsistent,
        },
        excluded: None,
        rms_residual_mm: all_rms,
        iterations,
    };
    if all_rms <= look_mm || layout.redundancy() < 2 {
        // (With fewer than 2 spares, leaving one string out would leave no
        // spare to check the rest: any exclusion fits exactly, so none can
        // be trusted.)
        return all_strings;
    }

    // The string with the largest residual at the all-string solution is the
    // likeliest culprit: its exclusion is tried first and kept at once if it
    // explains the lengths (converged, RMS within the threshold), which
    // spares the other solves in the common single-fault case. Otherwise
    // every exclusion is tried and the best one kept.
    let first = largest_residual(
        anchors,
        layout,
        lengths,
        &config.residual_weight,
        all.position,
    );
    let exclude = |k: usize| {
        let skip = Some(k);
        // Start from whichever of the previous position and the all-string
        // solution fits the remaining strings better.
        let c_start = evaluate(
            anchors,
            layout,
            lengths,
            &config.residual_weight,
            skip,
            start,
        )
        .cost;
        let c_all = evaluate(
            anchors,
            layout,
            lengths,
            &config.residual_weight,
            skip,
            all.position,
        )
        .cost;
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
    // Strings that agree to within the fault threshold: an exclusion must
    // bring the others within the tighter one to be believed.
    let fit_mm = if agree { look_mm } else { fault_mm };
    if !unique_required && s.converged && r <= fit_mm {
        return FkSolution {
            position: s.position,
            status: FkStatus::FaultyStringExcluded,
            excluded: Some(first as u8),
            rms_residual_mm: r,
            iterations,
        };
    }
    let fits = |s: &Solve<F>| s.converged && rms(s.cost, n_strings - 1) <= fit_mm;
    let mut fitting = usize::from(fits(&s));
    let mut best: Option<(usize, Solve<F>)> = Some((first, s));
    // The lowest cost of the other exclusions.
    let mut runner_up = F::infinity();
    for k in layout.indices().filter(|&k| k != first) {
        let s = exclude(k);
        iterations = iterations.saturating_add(s.iterations);
        fitting += usize::from(fits(&s));
        match &best {
            Some((_, b)) if s.cost >= b.cost => {
                if s.cost < runner_up {
                    runner_up = s.cost;
                }
            }
            Some((_, b)) => {
                runner_up = b.cost;
                best = Some((k, s));
            }
            None => best = Some((k, s)),
        }
    }
    if let Some((k, s)) = best {
        let r = rms(s.cost, n_strings - 1);
        // With few spares a good string left out can leave a set that fits
        // too (the fault absorbed by the position), but it fits worse: with
        // 3 spares (six strings in 3-D) the faulty string's exclusion is
        // still trusted when every other one leaves DOMINANT_EXCLUSION times
        // its RMS residual or more (the all-string compromise spreads the
        // faulty string's error over the position). With 2 spares, a wrong
        // exclusion leaves one spare, which can fit by chance: only the one
        // set that fits is trusted (the clearly best one there raises a
        // planar 4-string device's test error; decision record 0011,
        // `docs/decisions/0011-devices-3-to-8-strings.md`).
        let clearly_best = rms(runner_up, n_strings - 1) >= r * lit(DOMINANT_EXCLUSION);
        let trusted =
            !unique_required || fitting == 1 || (clearly_best && layout.redundancy() >= 3);
        if s.converged && r <= fit_mm && trusted {
            return FkSolution {
                position: s.position,
                status: FkStatus::FaultyStringExcluded,
                excluded: Some(k as u8),
                rms_residual_mm: r,
                iterations,
            };
        }
        // No exclusion is trusted, but one explains most of the
        // disagreement (a faulty string on a device whose other strings
        // disagree a little too, or, with 2 spares, a second exclusion that
        // fits by chance): its position is a better estimate than the
        // compromise that spreads the faulty string's error over all of
        // them (a 4-string planar device's string 127 mm off: the compromise
        // 66 mm off the tracker, the exclusion 1 mm). Still inconsistent:
        // not to be trusted for force.
        //
        // With 2 spares, where a string weighed below 1 stays in, it must
        // also be the string the compromise blames most: the noisy string's
        // residual, weighed low, let a wrong exclusion fit by chance (24 mm
        // off on a planar 4-string device's test session whose string 1
        // weighs 0.23). With every string weighed alike, the compromise
        // often blames another string most, and the right exclusion would
        // be lost (29 of 29 named on a 5-string device, 16 with this rule).
        let blamed = layout.redundancy() >= 3
            || k == first
            || layout
                .indices()
                .all(|i| i == k || config.residual_weight[i] >= F::one());
        if !agree
            && (!unique_required || (clearly_best && blamed))
            && s.converged
            && r * lit(DOMINANT_EXCLUSION) <= all_rms
        {
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
        ..all_strings
    }
}

/// The lowest weight [`residual_weights`] gives a string: one ten times
/// noisier than the device's typical string still counts (1 % of a typical
/// string's share of the fit, in variance), so that a fault on it can still
/// be seen and a device's redundancy is not silently lost.
pub const MIN_RESIDUAL_WEIGHT: f64 = 0.1;

/// Weights of the strings' residuals in [`forward_kinematics`]
/// ([`FkConfig::residual_weight`]) from each string's measured length
/// residual scale (mm, the robust standard deviation of its length against
/// the tracker on the training session): `w_i = s_ref / s_i`, at most 1 and
/// at least [`MIN_RESIDUAL_WEIGHT`], with `s_ref` the median scale of the
/// active strings (the lower one of the middle two). This is weighted least
/// squares with each string's measured variance, that is, down-weighting
/// only the strings noisier than the device's typical one: a string whose
/// reading carries an error the model lacks (an encoder that lags, a spool
/// that winds unevenly) pulls the position less, and its fault threshold
/// follows its own scale.
///
/// Without a measured scale for every active string (any of them zero,
/// negative or not finite: a calibration that did not measure them), every
/// weight is 1.
pub fn residual_weights<F: Real>(layout: StringLayout, scale_mm: &[F; STRINGS]) -> [F; STRINGS] {
    let mut w = [F::one(); STRINGS];
    let Some(reference) = typical_scale(layout, scale_mm) else {
        return w;
    };
    let floor: F = lit(MIN_RESIDUAL_WEIGHT);
    for i in layout.indices() {
        let ratio = reference / scale_mm[i];
        w[i] = if ratio >= F::one() {
            F::one()
        } else if ratio > floor {
            ratio
        } else {
            floor
        };
    }
    w
}

/// The scale of the device's typical string, which [`residual_weights`]
/// weighs the others against: the median of the active strings' scales
/// (the lower one of the middle two). `None` when a scale is not measured
/// (an active string's is zero, negative or not finite) or no string is
/// active.
pub fn typical_scale<F: Real>(layout: StringLayout, scale_mm: &[F; STRINGS]) -> Option<F> {
    let mut sorted = [F::zero(); STRINGS];
    let mut n = 0;
    for i in layout.indices() {
        let s = scale_mm[i];
        if !(s.is_finite() && s > F::zero()) {
            return None;
        }
        // Insertion sort of at most 8 values.
        let mut k = n;
        while k > 0 && sorted[k - 1] > s {
            sorted[k] = sorted[k - 1];
            k -= 1;
        }
        sorted[k] = s;
        n += 1;
    }
    (n > 0).then(|| sorted[(n - 1) / 2])
}

/// An exclusion that does not bring the RMS residual within the threshold
/// but lowers it this many times gives the position of an inconsistent solve
/// (see [`FkStatus::Inconsistent`]).
pub const DOMINANT_EXCLUSION: f64 = 3.0;

#[cfg(test)]
mod tests;
