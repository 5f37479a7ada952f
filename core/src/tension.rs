//! Tension distribution: which 8 string tensions render a desired force on the
//! end-effector.
//!
//! # Model
//!
//! String `i` pulls the end-effector at `p` (mm) toward its anchor `a_i` (mm)
//! with tension `T_i` (N) along the unit vector `u_i = (a_i - p) / |a_i - p|`.
//! The force on the end-effector is the resultant `A T = sum_i T_i u_i` (N),
//! `A = [u_1 .. u_8]` (3 x 8). Strings can only pull, and motors have a
//! limited torque, so every tension must stay in `[t_min, t_max]`
//! ([`TensionLimits`]).
//!
//! # Problem solved by [`distribute`]
//!
//! ```text
//! minimize   ||T - T_ref||^2
//! subject to A T = alpha F,  t_min <= T_i <= t_max,
//! ```
//!
//! with `alpha = 1` when `F` is feasible, otherwise the largest feasible
//! `alpha` in `[0, 1]` (times a tiny back-off, [`TensionConfig::scale_back_off`]):
//! the force is scaled down with its direction preserved. `T_ref` is the
//! reference tension ([`TensionReference`]): the closest-to-reference choice
//! keeps tensions smooth as the force and position change.
//!
//! # Method (bounded time, no allocation)
//!
//! 1. **Geometry and feasible force set, exact.** The set of forces the
//!    strings can render is the zonotope `Z = {A T : t_min <= T <= t_max}`
//!    `= c + sum_i [-r, r] u_i` with `c = t_mid sum_i u_i`, `r = (t_max - t_min) / 2`.
//!    In 3-D the facet normals of a zonotope are the cross products
//!    `n_ij = u_i x u_j` of pairs of generators, so
//!    `x in Z  <=>  |n_ij . (x - c)| <= r sum_k |n_ij . u_k|` for all 28 pairs.
//!    One pass over the 28 pairs gives: whether the end-effector is strictly
//!    inside the anchors' convex hull (some string on each side of every
//!    plane `n_ij`), whether zero force is feasible, and the exact largest
//!    `alpha` (a minimum of 28 ratios; no bisection).
//! 2. **QP by its dual, semismooth Newton.** For a fixed multiplier
//!    `lambda` (3-vector, N) the inner minimizer is
//!    `T_i(lambda) = clamp(T_ref + u_i . lambda, t_min, t_max)`; the concave,
//!    piecewise-quadratic dual `g(lambda)` has gradient `alpha F - A T(lambda)`
//!    (the force residual). Newton directions use the generalized Hessian
//!    `sum_{i free} u_i u_i^T`, solved by a modified `L D L^T` whose pivots
//!    are floored (fewer than 3 free strings: a long step along the null
//!    space, where the dual is linear). The step length is the **exact**
//!    maximizer of `g` along the direction: `g` is piecewise quadratic along
//!    a line with at most 16 breakpoints (a string reaching a limit), which
//!    are sorted and walked. So any step scale is safe, and once the set of
//!    clamped strings is right one full step solves the problem.
//! 3. **Primal refinement.** With the final set of free strings, at most
//!    [`MAX_REFINEMENTS`] minimum-norm corrections of the free tensions
//!    themselves. When the free strings are nearly coplanar (end-effector
//!    within a millimetre of a plane through 3 or 4 anchors) the multiplier
//!    grows to ~1e4 N and its f32 resolution, not the method, would limit the
//!    residual; this pass does not depend on it.
//!
//! Worst case: [`MAX_ITERATIONS`] = [`MAX_NEWTON_ITERATIONS`] (24) Newton
//! iterations + [`MAX_REFINEMENTS`] (3) refinements = 27, reported in
//! [`TensionSolution::iterations`]. Each Newton iteration is one 3x3 solve,
//! one evaluation of `T(lambda)` (8 dot products and clamps) and one line
//! search (16 divisions, an insertion sort of at most 16 values). Measured
//! over 20 000 random cases (positions in the central 1 m cube of a 2.2 m
//! frame, t in [0.5, 20] N): feasible forces (|F_i| <= 3 N) take 1 to 3
//! iterations; scaled forces (|F_i| <= 300 N) 2 to 7 in 99.7 % of cases,
//! 8 to 12 in 12 of 9 987, and the cap (25 = 24 + 1 refinement) once, with
//! the end-effector 0.26 mm from a plane through 4 anchors (it still
//! converged, through the refinement). Max resultant error 1.0e-4 N, max
//! direction error of a scaled force 5e-6 rad (`sweep_records_iterations_and_errors`).
//!
//! # Devices with 3 to 8 strings ([`StringLayout`])
//!
//! Inactive channels get a zero direction (a zero generator of the
//! zonotope: no facet, no reach; in the dual they pull nothing) and tension
//! 0; the method above then runs unchanged on the active strings. A planar
//! layout works in the `x, y` plane: directions and force are projected on
//! it (the force's `z` is dropped) and the 2-D zonotope's facets, one normal
//! `(-u_y, u_x)` per string, replace the 3-D pairs. Pulling in every
//! direction needs at least `dof + 1` strings
//! ([`TensionStatus::TooFewStrings`]) whose directions positively span
//! (else [`TensionStatus::OutsideAnchorHull`]; [`force_closure`]). With
//! exactly `dof + 1` strings the tensions of a force are unique, and a
//! scaled force at the zonotope's vertex may end `NotConverged` with a
//! residual near the tolerance (1 in 1,000 cases for a planar triangle;
//! rarely with 8 strings too, when the vertex leaves fewer free strings
//! than the last refinement needs). The controller renders such a solution
//! when its residual is below `control::USABLE_RESIDUAL_N`.
//! [`StringLayout::ALL`] takes the 8-string path itself: same results, same
//! cost.
//!
//! Only `+ - * /`, `sqrt`, `abs` and comparisons, in a fixed order: in `f32`
//! the host and the Cortex-M7 compute the same bits. Generic over
//! [`num_traits::Float`] so the host can also run it in `f64`.
#![allow(clippy::needless_range_loop)]

use crate::real::Real;
use serde::{Deserialize, Serialize};

use crate::geometry::{cross, dot, norm, sub};
use crate::model::{StringLayout, Vec3};
use crate::STRINGS;

/// Most Newton iterations [`distribute`] takes (the worst case).
pub const MAX_NEWTON_ITERATIONS: u16 = 24;

/// Smallest pivot of the modified `L D L^T` solve of the Newton system
/// (dimensionless; the Hessian's entries are at most 8, f32 rounding about 1e-6).
const PIVOT_FLOOR: f64 = 2e-6;

/// Most primal refinement passes after the Newton iterations (each one
/// 3x3 solve and 8 multiply-adds); counted in [`TensionSolution::iterations`].
pub const MAX_REFINEMENTS: u16 = 3;

/// Worst case of [`TensionSolution::iterations`].
pub const MAX_ITERATIONS: u16 = MAX_NEWTON_ITERATIONS + MAX_REFINEMENTS;

/// Bounds every string tension must respect, in newtons, `0 < t_min < t_max`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TensionLimits<F> {
    /// Lowest tension (N): strings must stay taut.
    pub t_min: F,
    /// Highest tension (N): motor torque limit over pulley radius.
    pub t_max: F,
}

impl<F: Real> TensionLimits<F> {
    /// Whether `0 < t_min < t_max` and both are finite.
    pub fn is_valid(&self) -> bool {
        self.t_min.is_finite()
            && self.t_max.is_finite()
            && self.t_min > F::zero()
            && self.t_min < self.t_max
    }

    /// Mid tension `(t_min + t_max) / 2` (N).
    pub fn mid(&self) -> F {
        (self.t_min + self.t_max) * lit(0.5)
    }
}

/// The tension the distribution stays closest to (among all tension sets
/// rendering the force).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum TensionReference<F> {
    /// `(t_min + t_max) / 2` on every string: the most margin both ways.
    Mid,
    /// A preferred tension (N) on every string, e.g. a low pre-tension to
    /// spare the motors; clamped into the limits.
    Preferred(F),
}

/// Tuning of [`distribute`]. `Default` gives the values documented per field.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TensionConfig<F> {
    /// Reference tension (default [`TensionReference::Mid`]).
    pub reference: TensionReference<F>,
    /// Largest accepted `|A T - alpha F|` (N) (default 1e-4 N).
    pub force_tolerance_n: F,
    /// A string shorter than this (mm) has no defined direction: degenerate
    /// geometry (default 1 mm).
    pub min_string_length_mm: F,
    /// Margin of the "inside the anchors' hull" test, as the sine of the angle
    /// by which some string must lie on each side of every plane spanned by two
    /// strings (default 1e-3, about 0.06 degrees).
    pub hull_margin: F,
    /// Relative back-off of a scaled force below the exact feasibility limit,
    /// to stay clear of rounding at the boundary (default 1e-4).
    pub scale_back_off: F,
}

impl<F: Real> Default for TensionConfig<F> {
    fn default() -> Self {
        Self {
            reference: TensionReference::Mid,
            force_tolerance_n: lit(1e-4),
            min_string_length_mm: lit(1.0),
            hull_margin: lit(1e-3),
            scale_back_off: lit(1e-4),
        }
    }
}

/// Outcome of [`distribute`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum TensionStatus {
    /// The desired force is rendered exactly (to the force tolerance).
    Exact,
    /// The desired force is not feasible: `rendered_fraction` times it is
    /// rendered exactly, same direction.
    Scaled,
    /// The iteration limit was reached (or the Newton system broke down)
    /// before the residual met the tolerance. Tensions are within limits, but
    /// the resultant misses `rendered_fraction * F` by `residual_n`.
    NotConverged,
    /// `t_min`/`t_max` not finite or not `0 < t_min < t_max`; tensions are 0.
    InvalidLimits,
    /// A non-finite anchor, position, force or configuration value.
    NonFiniteInput,
    /// String `string` is shorter than `min_string_length_mm`: no direction.
    StringTooShort { string: u8 },
    /// The end-effector is not strictly inside the anchors' convex hull (or the
    /// strings do not span space): some direction cannot be pulled at all.
    OutsideAnchorHull,
    /// Inside the hull, but not even zero force can be held with every
    /// tension within the limits (limits too narrow for this position).
    NoFeasibleTension,
    /// The layout has fewer than `dof + 1` strings: strings only pull, so
    /// at least one more string than degrees of freedom is needed to pull in
    /// every direction, wherever the end-effector is.
    TooFewStrings { strings: u8, dof: u8 },
}

/// Tensions chosen by [`distribute`] and how well they render the force.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TensionSolution<F> {
    /// Tension of each string (N), index = encoder index. Always within the
    /// limits; `t_min` on every string when no distribution exists (status
    /// other than `Exact`, `Scaled`, `NotConverged`), 0 if the limits are
    /// invalid. 0 on the channels the layout marks inactive.
    pub tensions: [F; STRINGS],
    /// Whether the desired force itself is rendered (status `Exact`).
    pub feasible: bool,
    /// Fraction `alpha` in `[0, 1]` of the desired force that is rendered
    /// (1 when `Exact`, 0 when no distribution exists).
    pub rendered_fraction: F,
    /// Newton iterations plus refinement passes used, at most [`MAX_ITERATIONS`].
    pub iterations: u16,
    pub status: TensionStatus,
    /// `|A T - alpha F|` (N) of the returned tensions.
    pub residual_n: F,
    /// Final dual multiplier `lambda` (N); pass it to [`distribute_warm`] in
    /// the next control-loop iteration to start near the solution.
    pub multiplier: Vec3<F>,
}

/// Resultant force (N) of `tensions` (N) on the end-effector at `position`
/// (mm): `sum_i tensions_i u_i`, `u_i` the unit vector from the end-effector
/// toward `anchors[i]` (mm). A string of zero length (or with non-finite
/// geometry) contributes nothing.
pub fn resultant_force<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    position: Vec3<F>,
    tensions: &[F; STRINGS],
) -> Vec3<F> {
    let mut f = [F::zero(); 3];
    for i in 0..STRINGS {
        let d = sub(anchors[i], position);
        let len = norm(d);
        if len > F::zero() && len.is_finite() {
            for k in 0..3 {
                f[k] = f[k] + tensions[i] * (d[k] / len);
            }
        }
    }
    f
}

/// String directions: unit vectors from the end-effector at `position` (mm)
/// toward each anchor (mm), or the status naming the first string shorter
/// than `min_string_length_mm` (or with non-finite geometry).
pub fn string_directions<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    position: Vec3<F>,
    min_string_length_mm: F,
) -> Result<[Vec3<F>; STRINGS], TensionStatus> {
    let mut u = [[F::zero(); 3]; STRINGS];
    for i in 0..STRINGS {
        let d = sub(anchors[i], position);
        let len = norm(d);
        if !len.is_finite() {
            return Err(TensionStatus::NonFiniteInput);
        }
        if len < min_string_length_mm || len == F::zero() {
            return Err(TensionStatus::StringTooShort { string: i as u8 });
        }
        u[i] = [d[0] / len, d[1] / len, d[2] / len];
    }
    Ok(u)
}

/// Distributes the desired `force` (N, on the end-effector) over the
/// strings of `layout`, starting the dual iteration from zero. See
/// [`distribute_warm`].
pub fn distribute<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    position: Vec3<F>,
    force: Vec3<F>,
    limits: TensionLimits<F>,
    config: &TensionConfig<F>,
) -> TensionSolution<F> {
    distribute_warm(
        anchors,
        layout,
        position,
        force,
        limits,
        config,
        [F::zero(); 3],
    )
}

/// Whether the strings of `layout`, from the end-effector at `position`
/// (mm), can pull it in every direction (every direction of the plane, for a
/// planar layout) with tensions within `limits`: the condition for rendering
/// forces at all ("force closure"). `Err` says why not:
/// [`TensionStatus::TooFewStrings`] (fewer than `dof + 1` strings: never),
/// [`TensionStatus::OutsideAnchorHull`] (the string directions do not
/// positively span: the end-effector is outside the active anchors' convex
/// hull, e.g. below every anchor of a hanging design, which can only pull up
/// and relies on gravity), or another failure status of [`distribute`].
pub fn force_closure<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    position: Vec3<F>,
    limits: TensionLimits<F>,
    config: &TensionConfig<F>,
) -> Result<(), TensionStatus> {
    let s = distribute(anchors, layout, position, [F::zero(); 3], limits, config);
    match s.status {
        TensionStatus::Exact | TensionStatus::Scaled | TensionStatus::NotConverged => Ok(()),
        other => Err(other),
    }
}

/// Distributes the desired `force` (N) on the end-effector at `position` (mm)
/// over the strings leaving `anchors` (mm): tensions within `limits` whose
/// resultant is `force` (or, if infeasible, the largest feasible fraction of
/// it, same direction), closest to the reference tension. `warm_start` is an
/// initial dual multiplier (N), e.g. the previous solution's `multiplier`;
/// non-finite values are replaced by zero.
///
/// Only the strings `layout` marks active pull (the others get tension 0,
/// their anchors are not read). A planar layout renders the force's `x, y`
/// components in the anchors' plane (`z` is dropped, string directions are
/// taken in the plane). A layout with fewer than `dof + 1` strings cannot
/// pull in every direction: [`TensionStatus::TooFewStrings`]. All 8 strings
/// ([`StringLayout::ALL`]) run exactly the 8-string method of the module doc.
///
/// At most [`MAX_ITERATIONS`] iterations (see the module doc). Never
/// panics; every failure is a [`TensionStatus`].
pub fn distribute_warm<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    position: Vec3<F>,
    force: Vec3<F>,
    limits: TensionLimits<F>,
    config: &TensionConfig<F>,
    warm_start: Vec3<F>,
) -> TensionSolution<F> {
    // All 8 strings in space: the layout's tests compile out.
    if layout == StringLayout::ALL {
        solve::<F, true>(anchors, layout, position, force, limits, config, warm_start)
    } else {
        solve::<F, false>(anchors, layout, position, force, limits, config, warm_start)
    }
}

/// [`distribute_warm`]; `ALL`: `layout` is [`StringLayout::ALL`].
///
/// One piece (a numerical kernel of the control loop): checks, the dual
/// Newton iteration and the primal refinement share their state, and every
/// split tried changes the code the device runs (the refinement in an
/// always-inlined helper: 12 more instructions per call for N = 4 under
/// `scripts/qemu-bench`; the Newton iteration too: 5 more for 8 strings).
#[inline(always)]
#[allow(
    clippy::too_many_lines,
    reason = "a numerical kernel of the control loop: splitting it changes the device's code"
)]
fn solve<F: Real, const ALL: bool>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    position: Vec3<F>,
    force: Vec3<F>,
    limits: TensionLimits<F>,
    config: &TensionConfig<F>,
    warm_start: Vec3<F>,
) -> TensionSolution<F> {
    if !limits.is_valid() {
        return failure(F::zero(), TensionStatus::InvalidLimits);
    }
    let fail = |status| {
        let mut f = failure(limits.t_min, status);
        if !ALL {
            mask_inactive(&mut f.tensions, layout);
        }
        f
    };

    let t_ref = match config.reference {
        TensionReference::Mid => limits.mid(),
        TensionReference::Preferred(t) => clamp(t, limits.t_min, limits.t_max),
    };
    let config_finite = t_ref.is_finite()
        && config.force_tolerance_n.is_finite()
        && config.min_string_length_mm.is_finite()
        && config.hull_margin.is_finite()
        && config.scale_back_off.is_finite();
    let input_finite = all_finite(&position)
        && all_finite(&force)
        && if ALL {
            anchors.iter().all(|a| all_finite(a))
        } else {
            layout.indices().all(|i| all_finite(&anchors[i]))
        };
    if !config_finite || !input_finite {
        return fail(TensionStatus::NonFiniteInput);
    }

    let (u, alpha_max, force) = if ALL {
        let u = match string_directions(anchors, position, config.min_string_length_mm) {
            Ok(u) => u,
            Err(status) => return fail(status),
        };
        match feasible_fraction(&u, limits, force, config.hull_margin) {
            Ok(a) => (u, a, force),
            Err(status) => return fail(status),
        }
    } else {
        match layout_geometry(anchors, layout, position, force, limits, config) {
            Ok(g) => g,
            Err(status) => return fail(status),
        }
    };
    let alpha = if alpha_max >= F::one() {
        F::one()
    } else {
        let a = alpha_max * (F::one() - config.scale_back_off);
        if a > F::zero() {
            a
        } else {
            F::zero()
        }
    };
    let target = [alpha * force[0], alpha * force[1], alpha * force[2]];

    let mut lambda = if all_finite(&warm_start) {
        warm_start
    } else {
        [F::zero(); 3]
    };
    let tol2 = config.force_tolerance_n * config.force_tolerance_n;
    let mut cur = evaluate(&u, t_ref, limits, target, lambda);
    let mut iterations: u16 = 0;
    let pivot_floor: F = lit(PIVOT_FLOOR);
    let full_step_tolerance: F = lit(1e-3);
    // Close enough for the primal refinement to finish: 100 tolerances.
    let near2 = tol2 * lit(1e4);

    while cur.residual2 > tol2 && iterations < MAX_NEWTON_ITERATIONS {
        iterations += 1;
        // Generalized Hessian of -g: sum over free strings of u u^T, damped.
        let r = cur.residual;
        // Newton direction by modified LDL^T (pivots floored: a singular
        // Hessian, fewer than 3 free strings, gives a long step along its null
        // space, where the dual is linear); the gradient if that fails.
        // The exact line search makes any ascent direction safe.
        let step = solve_spd3(free_hessian(&u, &cur.free), r, pivot_floor)
            .filter(|d| dot(r, *d) > F::zero())
            .unwrap_or(r);
        let slope = dot(r, step); // directional derivative of g at s = 0
        let length = exact_line_search(&u, t_ref, limits, lambda, step, slope);
        let next_lambda = [
            lambda[0] + length * step[0],
            lambda[1] + length * step[1],
            lambda[2] + length * step[2],
        ];
        if next_lambda == lambda || !all_finite(&next_lambda) {
            break; // step below the resolution of lambda: stagnation
        }
        lambda = next_lambda;
        let free_before = cur.free;
        cur = evaluate(&u, t_ref, limits, target, lambda);
        if cur.free == free_before
            && ((length - F::one()).abs() < full_step_tolerance || cur.residual2 < near2)
        {
            // A full Newton step within one quadratic piece of the dual: the
            // multiplier is exact up to its rounding; the primal refinement
            // below finishes without the multiplier's resolution limit.
            break;
        }
    }

    // Primal refinement with the final set of free strings: the minimum-norm
    // correction of the free tensions, applied to the tensions themselves.
    // When the free strings are nearly coplanar the multiplier is large and
    // its f32 resolution limits the dual iteration; this pass does not.
    let mut tensions = cur.tensions;
    let mut free = cur.free;
    let mut residual = cur.residual;
    let mut residual2 = cur.residual2;
    let mut refinements: u16 = 0;
    while residual2 > tol2 && refinements < MAX_REFINEMENTS {
        refinements += 1;
        let w = match solve_spd3(free_hessian(&u, &free), residual, pivot_floor) {
            Some(w) => w,
            None => break,
        };
        let mut resultant = [F::zero(); 3];
        for i in 0..STRINGS {
            if free[i] {
                let t = tensions[i] + dot(u[i], w);
                tensions[i] = if t < limits.t_min {
                    free[i] = false;
                    limits.t_min
                } else if t > limits.t_max {
                    free[i] = false;
                    limits.t_max
                } else {
                    t
                };
            }
            for k in 0..3 {
                resultant[k] = resultant[k] + tensions[i] * u[i][k];
            }
        }
        residual = sub(target, resultant);
        residual2 = dot(residual, residual);
    }
    let iterations = iterations + refinements;
    if !ALL {
        // Inactive channels took the reference tension along (free, with a
        // zero direction: no force); they carry no string.
        mask_inactive(&mut tensions, layout);
    }

    let converged = residual2 <= tol2;
    let status = match (converged, alpha >= F::one()) {
        (true, true) => TensionStatus::Exact,
        (true, false) => TensionStatus::Scaled,
        (false, _) => TensionStatus::NotConverged,
    };
    TensionSolution {
        tensions,
        feasible: status == TensionStatus::Exact,
        rendered_fraction: alpha,
        iterations,
        status,
        residual_n: residual2.sqrt_rounded(),
        multiplier: lambda,
    }
}

/// Tension 0 on the channels `layout` marks inactive.
fn mask_inactive<F: Real>(tensions: &mut [F; STRINGS], layout: StringLayout) {
    for (i, t) in tensions.iter_mut().enumerate() {
        if !layout.is_active(i) {
            *t = F::zero();
        }
    }
}

/// String directions, the force to render and its largest feasible fraction.
type Geometry<F> = ([Vec3<F>; STRINGS], F, Vec3<F>);

/// String directions, force and largest feasible fraction for a layout other
/// than all 8 strings in space. Inactive channels get a zero direction: in
/// the zonotope they are zero generators (no facet, no reach), in the dual
/// they pull nothing; the 8-string method then runs unchanged on the active
/// strings. Planar: directions and force in the `x, y` plane, and the 2-D
/// facets (one per string) replace the 3-D pairs, whose normals would all be
/// `z`.
fn layout_geometry<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    position: Vec3<F>,
    force: Vec3<F>,
    limits: TensionLimits<F>,
    config: &TensionConfig<F>,
) -> Result<Geometry<F>, TensionStatus> {
    let (count, dof) = (layout.count(), layout.dof());
    if count < dof + 1 {
        return Err(TensionStatus::TooFewStrings {
            strings: count as u8,
            dof: dof as u8,
        });
    }
    let mut u = [[F::zero(); 3]; STRINGS];
    for i in layout.indices() {
        let mut d = sub(anchors[i], position);
        if layout.planar {
            d[2] = F::zero();
        }
        let len = norm(d);
        if !len.is_finite() {
            return Err(TensionStatus::NonFiniteInput);
        }
        if len < config.min_string_length_mm || len == F::zero() {
            return Err(TensionStatus::StringTooShort { string: i as u8 });
        }
        u[i] = [d[0] / len, d[1] / len, d[2] / len];
    }
    if layout.planar {
        let force = renderable_force(layout, force);
        let alpha = feasible_fraction_planar(&u, layout, limits, force, config.hull_margin)?;
        Ok((u, alpha, force))
    } else {
        let alpha = feasible_fraction(&u, limits, force, config.hull_margin)?;
        Ok((u, alpha, force))
    }
}

/// The part of `force` a device of `layout` renders: a planar device's
/// strings pull in the anchors' plane, so its `x, y` only; the whole force
/// otherwise. What [`distribute_warm`] renders, and what the controller
/// reports as asked of it.
pub fn renderable_force<F: Real>(layout: StringLayout, force: Vec3<F>) -> Vec3<F> {
    if layout.planar {
        [force[0], force[1], F::zero()]
    } else {
        force
    }
}

/// [`feasible_fraction`] in the plane: the facets of a 2-D zonotope are
/// parallel to its generators, so each active string `i` gives the normal
/// `n_i = (-u_i.y, u_i.x)` (unit). Hull test: some other string beyond
/// `hull_margin` on each side of the line along `u_i` (the directions then
/// positively span the plane). Directions `u` have `z = 0`; inactive ones
/// are zero.
fn feasible_fraction_planar<F: Real>(
    u: &[Vec3<F>; STRINGS],
    layout: StringLayout,
    limits: TensionLimits<F>,
    force: Vec3<F>,
    hull_margin: F,
) -> Result<F, TensionStatus> {
    let mid = limits.mid();
    let radius = (limits.t_max - limits.t_min) * lit(0.5);
    let mut alpha = F::one();
    for i in layout.indices() {
        let n = [-u[i][1], u[i][0], F::zero()];
        let (mut sum, mut sum_abs) = (F::zero(), F::zero());
        let (mut above, mut below) = (false, false);
        for k in layout.indices() {
            if k == i {
                continue;
            }
            let s = dot(n, u[k]);
            sum = sum + s;
            sum_abs = sum_abs + s.abs();
            above |= s > hull_margin;
            below |= -s > hull_margin;
        }
        if !(above && below) {
            return Err(TensionStatus::OutsideAnchorHull);
        }
        alpha = facet_limit(alpha, radius * sum_abs, mid * sum, dot(n, force))?;
    }
    Ok(alpha)
}

/// The feasible fraction `alpha` after one facet pair of the tension
/// zonotope: `|alpha n.F - n.c| <= reach`, with `centre = n.c` and
/// `a = n.F`; the shared step of the 3-D and planar searches.
#[inline(always)]
fn facet_limit<F: Real>(alpha: F, reach: F, centre: F, a: F) -> Result<F, TensionStatus> {
    if centre.abs() > reach {
        return Err(TensionStatus::NoFeasibleTension);
    }
    let (slack, a_abs) = if a >= F::zero() {
        (reach + centre, a)
    } else {
        (reach - centre, -a)
    };
    Ok(if slack < alpha * a_abs {
        slack / a_abs
    } else {
        alpha
    })
}

/// `x > hm * sqrt(n2)` without the square root (`n2 >= 0`).
#[inline(always)]
fn beyond_margin<F: Real>(x: F, hm: F, n2: F) -> bool {
    let hm2n2 = hm * hm * n2;
    if hm >= F::zero() {
        x > F::zero() && x * x > hm2n2
    } else {
        x >= F::zero() || x * x < hm2n2
    }
}

/// Index of the pair `(i, j)`, `i < j`, in lexicographic order (`0..28`):
/// `PAIR_BASE[i] + j - i - 1`.
const PAIR_BASE: [usize; STRINGS] = [0, 7, 13, 18, 22, 25, 27, 28];

/// Per-pair arrays are 32 long and indexed modulo 32 (no bounds checks).
const PAIR_SLOTS: usize = 32;

/// The largest `alpha` in `[0, 1]` such that `alpha * force` is renderable
/// with tensions in `limits` along directions `u`, after checking that the
/// end-effector is strictly inside the anchors' hull and that zero force is
/// renderable. Exact up to rounding: 28 zonotope facet pairs.
///
/// For the pair `(i, j)` each other string `k` enters through the triple
/// product `s = (u_i x u_j) . u_k`, which is shared by the three pairs of its
/// strings (`det(u_i, u_j, u_k)` is `s` for `(i, j)` and `(j, k)`, `-s` for
/// `(i, k)`): one pass over the 56 triples `i < j < k` gives every pair's sum
/// and sum of magnitudes of `s` (the direct form takes 168 dot products).
///
/// Hull test (some string beyond `hull_margin |n|` on each side of every
/// pair's plane): with 6 other strings, `sum max(s, 0) > 6 margin` implies
/// that one of them is beyond the margin, and `sum max(s, 0) = (sum_abs +
/// sum) / 2`; only a pair failing this sufficient test (near the hull
/// boundary) is checked string by string. Margins are compared on squares:
/// no square root.
fn feasible_fraction<F: Real>(
    u: &[Vec3<F>; STRINGS],
    limits: TensionLimits<F>,
    force: Vec3<F>,
    hull_margin: F,
) -> Result<F, TensionStatus> {
    let mid = limits.mid();
    let radius = (limits.t_max - limits.t_min) * lit(0.5);
    // Pairs of (nearly) parallel strings span no plane: skipped (|n|^2 below).
    let min_pair2: F = lit(1e-8);
    let others: F = lit(2.0 * (STRINGS - 2) as f64);
    let mut sum = [F::zero(); PAIR_SLOTS];
    let mut sum_abs = [F::zero(); PAIR_SLOTS];
    let mut alpha = F::one();
    let mut pairs_used = 0u8;
    for i in 0..STRINGS {
        for j in (i + 1)..STRINGS {
            let pij = (PAIR_BASE[i] + j - i - 1) % PAIR_SLOTS;
            let n = cross(u[i], u[j]);
            // Triples (i, j, k > j): this pair's sums are complete after
            // this loop (k < j came from earlier pairs).
            let mut s_ij = sum[pij];
            let mut a_ij = sum_abs[pij];
            for k in (j + 1)..STRINGS {
                let d = dot(n, u[k]);
                let a = d.abs();
                let pik = (PAIR_BASE[i] + k - i - 1) % PAIR_SLOTS;
                let pjk = (PAIR_BASE[j] + k - j - 1) % PAIR_SLOTS;
                s_ij = s_ij + d;
                a_ij = a_ij + a;
                sum[pik] = sum[pik] - d;
                sum_abs[pik] = sum_abs[pik] + a;
                sum[pjk] = sum[pjk] + d;
                sum_abs[pjk] = sum_abs[pjk] + a;
            }
            let n2 = dot(n, n);
            if n2.is_nan() || n2 <= min_pair2 {
                continue;
            }
            pairs_used += 1;
            let sufficient = beyond_margin(a_ij + s_ij, others * hull_margin, n2)
                && beyond_margin(a_ij - s_ij, others * hull_margin, n2);
            if !sufficient && !strings_on_both_sides(u, i, j, n, hull_margin, n2) {
                return Err(TensionStatus::OutsideAnchorHull);
            }
            // Facet pair: |alpha n.F - n.c| <= r sum_k |n.u_k|, c = mid sum_k u_k.
            alpha = facet_limit(alpha, radius * a_ij, mid * s_ij, dot(n, force))?;
        }
    }
    if pairs_used == 0 {
        return Err(TensionStatus::OutsideAnchorHull);
    }
    Ok(alpha)
}

/// Whether some string other than `i`, `j` lies beyond `hull_margin |n|` on
/// each side of the plane with normal `n = u_i x u_j` (`|n|^2 = n2`).
#[inline(never)]
fn strings_on_both_sides<F: Real>(
    u: &[Vec3<F>; STRINGS],
    i: usize,
    j: usize,
    n: Vec3<F>,
    hull_margin: F,
    n2: F,
) -> bool {
    let mut above = false;
    let mut below = false;
    for k in 0..STRINGS {
        if k == i || k == j {
            continue;
        }
        let s = dot(n, u[k]);
        above |= beyond_margin(s, hull_margin, n2);
        below |= beyond_margin(-s, hull_margin, n2);
    }
    above && below
}

/// One evaluation of the inner minimizer at `lambda`.
#[derive(Clone, Copy)]
struct Evaluation<F> {
    tensions: [F; STRINGS],
    /// Strings whose unclamped tension lies within the limits.
    free: [bool; STRINGS],
    /// `target - A T` (N), the dual gradient.
    residual: Vec3<F>,
    residual2: F,
}

/// `T_i = clamp(t_ref + u_i . lambda)` and the residual `target - A T` (the
/// gradient of the dual `g = sum_i (T_i - t_ref)^2 / 2 - (u_i . lambda) T_i + lambda . target`).
fn evaluate<F: Real>(
    u: &[Vec3<F>; STRINGS],
    t_ref: F,
    limits: TensionLimits<F>,
    target: Vec3<F>,
    lambda: Vec3<F>,
) -> Evaluation<F> {
    let mut tensions = [F::zero(); STRINGS];
    let mut free = [false; STRINGS];
    let mut resultant = [F::zero(); 3];
    for i in 0..STRINGS {
        let z = t_ref + dot(u[i], lambda);
        let t = if z < limits.t_min {
            limits.t_min
        } else if z > limits.t_max {
            limits.t_max
        } else {
            free[i] = true;
            z
        };
        tensions[i] = t;
        for k in 0..3 {
            resultant[k] = resultant[k] + t * u[i][k];
        }
    }
    let residual = sub(target, resultant);
    Evaluation {
        tensions,
        free,
        residual,
        residual2: dot(residual, residual),
    }
}

/// Exact maximizer `s >= 0` of the dual along `lambda + s step`.
///
/// The dual's derivative along the step, `phi'(s) = step . target - sum_i w_i T_i(s)`
/// with `w_i = u_i . step`, is piecewise linear and non-increasing: string
/// `i` contributes curvature `w_i^2` while it is free. The at most 16 points
/// where a string enters or leaves its limits are sorted (insertion sort,
/// ties by string index) and walked until `phi'` crosses zero. `slope` is
/// `phi'(0) > 0`. Returns 0 if no ascent is possible.
fn exact_line_search<F: Real>(
    u: &[Vec3<F>; STRINGS],
    t_ref: F,
    limits: TensionLimits<F>,
    lambda: Vec3<F>,
    step: Vec3<F>,
    slope: F,
) -> F {
    if slope.is_nan() || slope <= F::zero() {
        return F::zero();
    }
    let mut events = [(F::zero(), F::zero()); 2 * STRINGS]; // (s, curvature change)
    let mut count = 0usize;
    let mut curvature = F::zero();
    for i in 0..STRINGS {
        let z = t_ref + dot(u[i], lambda);
        let w = dot(u[i], step);
        if w == F::zero() {
            continue;
        }
        let w2 = w * w;
        // Free for s in [enter, leave].
        let (enter, leave) = if w > F::zero() {
            ((limits.t_min - z) / w, (limits.t_max - z) / w)
        } else {
            ((limits.t_max - z) / w, (limits.t_min - z) / w)
        };
        if leave <= F::zero() {
            continue; // clamped for every s > 0
        }
        if enter <= F::zero() {
            curvature = curvature + w2;
        } else {
            events[count] = (enter, w2);
            count += 1;
        }
        events[count] = (leave, -w2);
        count += 1;
    }
    // Insertion sort by s (stable: ties keep string order).
    for k in 1..count {
        let mut j = k;
        while j > 0 && events[j - 1].0 > events[j].0 {
            events.swap(j - 1, j);
            j -= 1;
        }
    }
    let mut s = F::zero();
    let mut d = slope;
    for &(at, change) in events.iter().take(count) {
        let c = if curvature > F::zero() {
            curvature
        } else {
            F::zero()
        };
        let d_at = d - c * (at - s);
        if d_at <= F::zero() {
            return s + d / c;
        }
        d = d_at;
        s = at;
        curvature = curvature + change;
    }
    if curvature > F::zero() {
        s + d / curvature
    } else {
        s
    }
}

/// `sum_{i free} u_i u_i^T` as `[xx, xy, xz, yy, yz, zz]`.
fn free_hessian<F: Real>(u: &[Vec3<F>; STRINGS], free: &[bool; STRINGS]) -> [F; 6] {
    let mut h = [F::zero(); 6];
    for i in 0..STRINGS {
        if free[i] {
            let v = u[i];
            h[0] = h[0] + v[0] * v[0];
            h[1] = h[1] + v[0] * v[1];
            h[2] = h[2] + v[0] * v[2];
            h[3] = h[3] + v[1] * v[1];
            h[4] = h[4] + v[1] * v[2];
            h[5] = h[5] + v[2] * v[2];
        }
    }
    h
}

/// Solves `H x = b` for symmetric positive semi-definite `H`, given as
/// `[xx, xy, xz, yy, yz, zz]`, by a modified `L D L^T` factorization: every
/// pivot is raised to at least `pivot_floor`, so a singular `H` gives a
/// finite solution with a long component along its null space. `None` only
/// if the result is not finite.
fn solve_spd3<F: Real>(h: [F; 6], b: Vec3<F>, pivot_floor: F) -> Option<Vec3<F>> {
    let floor = |d: F| if d > pivot_floor { d } else { pivot_floor };
    let [a11, a21, a31, a22, a32, a33] = h;
    let d1 = floor(a11);
    let l21 = a21 / d1;
    let l31 = a31 / d1;
    let d2 = floor(a22 - l21 * l21 * d1);
    let l32 = (a32 - l31 * l21 * d1) / d2;
    let d3 = floor(a33 - l31 * l31 * d1 - l32 * l32 * d2);
    let y1 = b[0];
    let y2 = b[1] - l21 * y1;
    let y3 = b[2] - l31 * y1 - l32 * y2;
    let x3 = y3 / d3;
    let x2 = y2 / d2 - l32 * x3;
    let x1 = y1 / d1 - l21 * x2 - l31 * x3;
    let x = [x1, x2, x3];
    if all_finite(&x) {
        Some(x)
    } else {
        None
    }
}

fn failure<F: Real>(tension: F, status: TensionStatus) -> TensionSolution<F> {
    TensionSolution {
        tensions: [tension; STRINGS],
        feasible: false,
        rendered_fraction: F::zero(),
        iterations: 0,
        status,
        residual_n: F::zero(),
        multiplier: [F::zero(); 3],
    }
}

/// A literal in the float type (exact for every value used here in f32/f64).
#[inline(always)]
fn lit<F: Real>(x: f64) -> F {
    F::from(x).unwrap_or_else(F::nan)
}

#[inline(always)]
fn clamp<F: Real>(x: F, lo: F, hi: F) -> F {
    if x < lo {
        lo
    } else if x > hi {
        hi
    } else {
        x
    }
}

#[inline(always)]
fn all_finite<F: Real>(a: &[F]) -> bool {
    a.iter().all(|x| x.is_finite())
}

#[cfg(test)]
mod tests;
