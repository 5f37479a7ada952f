//! The guide-pulley family ([`Effect::Guide`](crate::model::Effect::Guide)):
//! a string that leaves the frame over a guide pulley of radius `r` whose
//! plane swivels about an axis toward the end-effector (the standard pulley
//! kinematics of cable robots). The model's anchor is the guide's entry
//! point `A` on the swivel axis `e`; from there the string wraps `r beta`
//! on the pulley and leaves along the tangent, so its length to the
//! end-effector `P` is
//!
//! ```text
//! x = D cos(a) - r,  y = D sin(a),  m = |(x, y)|
//! beta = pi - atan2(y, x) - acos(r / m)
//! length = r beta + sqrt(m^2 - r^2)
//! ```
//!
//! with `D = |P - A|` the chord and `a` its elevation: the angle of `P - A`
//! out of the plane across `e`, positive along `e`
//! ([`StringInputs::guide_elevation_q32`](crate::model::StringInputs::guide_elevation_q32)).
//! The encoders count the path from the home capture, where the string
//! already wrapped its home share, and the model's length is the chord, so
//! the term is the path's excess over the chord at home less the one now,
//!
//! ```text
//! + (length - D)(home) - (length - D)(now)
//! ```
//!
//! and `r = 0` is the model without it. The chord is read as the string's
//! free length `l = home_length + payout` (the model's length before its
//! effect terms: the two differ by the term, which moves it by `(r / l)^2`
//! of that), clamped to at least [`GUIDE_MIN_RADII`] radii; the home part
//! reads the home length and the home's elevation (quantized as the
//! device's input), a constant of each string the compiler computes in f64
//! (exact) and the compiled term carries.
//!
//! # The swivel axis
//!
//! The frame edge: vertical (device `z`), pointing away from the home
//! height (up for an anchor at or above the home's `z`, down below it), as
//! a SPIDAR's corner guides are mounted. The elevation is then the chord's
//! angle from the horizontal, negative toward the home height.
//!
//! # Fixed point
//!
//! The exact length needs an arctangent; the device evaluates its series
//! in `eps = r / l` instead (exact to `r 1e-6` at `eps <= 1/16`, the
//! clamp: 1e-5 mm for a 12 mm guide, `docs/fixed-point.md`, "Guide"):
//!
//! ```text
//! length - l = r [ (pi/2 - a - cos a)
//!                  + eps u^2 / 2 + eps^2 cos(a) u^2 / 2
//!                  + eps^3 u^3 (15 sin a + 13) / 24 + eps^4 u^3 (7 sin a + 5) cos(a) / 8 ],
//! u = 1 - sin a
//! ```
//!
//! | quantity | type | format |
//! |---|---|---|
//! | elevation `a` (input) | `i32` | Q0.32 turns, clamped to `+-1/4` turn |
//! | radius `r` | `i32` | Q7.24 mm (`|r| <=` [`MAX_GUIDE_RADIUS_MM`]) |
//! | `sin a`, `cos a` | `i32` | Q1.30, the sine table ([`super::sin_q30`]) |
//! | `a` in radians, the bracket and its parts | `i64` | Q·30, each product of two below `2^63` (rounded, shifted) |
//! | free length | `i64` | Q·16 mm, clamped to at least `16 r` (and 2^-16 mm) |
//! | `eps` | `i64` | Q·30: `(r << 22) / l`, one 64-bit division a string |
//! | home part | `[i32; 8]` | Q11.20 mm per string, the exact path's excess at home, rounded when compiled |
//! | contribution | `i64` | Q31.32 mm: the home part less the bracket now times `r` (rounded), saturated |

use core::f64::consts::{FRAC_PI_2, PI, TAU};

use super::{home_length_f64, in_range, mul_i32_shr, q16_to_q32, sin_q30, to_fixed_i32};
use super::{CompiledEffect, EffectContext, FixedContext, StringLawCompileError};
use crate::model::{Frame, Vec3, EVERY_STRING};
use crate::real::Real;
use crate::STRINGS;

/// Largest `|radius_mm|` of a guide term (mm): a 100 mm pulley is a wheel.
pub const MAX_GUIDE_RADIUS_MM: f64 = 50.0;

/// The least free length a guide term reads, in radii: the device's series
/// is exact to `r 1e-6` there (`l` shorter is the end-effector at the
/// pulley, which no string reaches).
pub const GUIDE_MIN_RADII: f64 = 16.0;

/// `2^32 / 2 pi`: Q0.32 turns per radian.
const Q32_TURNS_PER_RAD: f32 = 683_565_275.576_431_6;

/// The elevation of the chord from `anchor` to `position` out of the plane
/// across the anchor's swivel axis (device `z`, pointing away from the
/// `home` height), positive along the axis, Q0.32 turns (`+-2^30` at the
/// poles); 0 for a chord of no length or a non-finite input. What
/// [`StringInputs::guide_elevation_q32`](crate::model::StringInputs::guide_elevation_q32)
/// carries: taken where the inclination of a sag is
/// ([`cos2_inclination_q16`](super::cos2_inclination_q16)). In `f32` on
/// both sides (the device's type), with `+ - * /` and the correctly rounded
/// square root only, so that host and device compute the same bits.
pub fn guide_elevation_q32<F: Real>(anchor: &Vec3<F>, home: &Vec3<F>, position: &Vec3<F>) -> i32 {
    let f = |v: F| v.to_f32().unwrap_or(f32::NAN);
    let (dx, dy, dz) = (
        f(position[0] - anchor[0]),
        f(position[1] - anchor[1]),
        f(position[2] - anchor[2]),
    );
    let along = if anchor[2] >= home[2] { dz } else { -dz };
    let perp = (dx * dx + dy * dy).sqrt_rounded();
    if !along.is_finite() || !perp.is_finite() || (along == 0.0 && perp == 0.0) {
        return 0;
    }
    // The `as` cast saturates (+-2^30 never reaches it) and rounds toward 0.
    (atan2_f32(along, perp) * Q32_TURNS_PER_RAD) as i32
}

/// [`guide_elevation_q32`] of every string of `anchors` at `position`.
pub fn guide_elevations<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    home: &Vec3<F>,
    position: &Vec3<F>,
) -> [i32; STRINGS] {
    core::array::from_fn(|i| guide_elevation_q32(&anchors[i], home, position))
}

/// `atan2(y, x)` for `x >= 0` (rad, `-pi/2..=pi/2`), `+ - * /` only.
fn atan2_f32(y: f32, x: f32) -> f32 {
    if y.abs() <= x {
        atan_f32(y / x)
    } else {
        let half_pi = if y > 0.0 {
            core::f32::consts::FRAC_PI_2
        } else {
            -core::f32::consts::FRAC_PI_2
        };
        half_pi - atan_f32(x / y)
    }
}

/// `atan(t)` for `|t| <= 1`: Abramowitz and Stegun 4.4.49, an odd
/// polynomial of degree 17 within 2e-8 rad (f32 rounding adds about 1e-7).
fn atan_f32(t: f32) -> f32 {
    const C: [f32; 9] = [
        1.0,
        -0.333_331_45,
        0.199_935_51,
        -0.142_089,
        0.106_562_64,
        -0.075_289_64,
        0.042_909_614,
        -0.016_165_737,
        0.002_866_225_7,
    ];
    let t2 = t * t;
    let mut acc = C[8];
    for k in (0..8).rev() {
        acc = acc * t2 + C[k];
    }
    acc * t
}

/// The elevation (rad) of a [`guide_elevation_q32`], clamped to `+-pi/2`.
pub fn guide_elevation_rad(elevation_q32: i32) -> f64 {
    (f64::from(elevation_q32) * TAU / 4_294_967_296.0).clamp(-FRAC_PI_2, FRAC_PI_2)
}

/// The string's length over a guide of radius `radius_mm` less its chord
/// (mm), for a chord of `chord_mm` at `elevation_rad` (exact, f64): what a
/// guide term adds ([`guide_mm`] reads the chord as the free length). 0 for
/// `radius_mm == 0`; the chord is clamped to at least [`GUIDE_MIN_RADII`]
/// radii.
pub fn guide_path_mm(radius_mm: f64, chord_mm: f64, elevation_rad: f64) -> f64 {
    if radius_mm == 0.0 {
        return 0.0;
    }
    let (l, beta, _, m2) = guide_geometry(radius_mm, chord_mm, elevation_rad);
    let free = libm::sqrt(m2 - radius_mm * radius_mm);
    radius_mm * beta + free - l
}

/// The clamped chord, the wrap angle `beta`, `sin(phi_T) = sin(beta)` and
/// `m^2` of a guide (module docs).
fn guide_geometry(r: f64, chord_mm: f64, elevation_rad: f64) -> (f64, f64, f64, f64) {
    let l = chord_mm.max(GUIDE_MIN_RADII * r.abs());
    let (s, c) = (libm::sin(elevation_rad), libm::cos(elevation_rad));
    let (x, y) = (l * c - r, l * s);
    let m2 = x * x + y * y;
    let m = libm::sqrt(m2);
    let free = libm::sqrt(m2 - r * r);
    let beta = PI - libm::atan2(y, x) - libm::acos(r / m);
    (l, beta, (r * y + x * free) / m2, m2)
}

/// A guide term's contribution (mm): [`guide_path_mm`] at the home length
/// and the home's elevation less the one at the context's free length and
/// elevation.
pub fn guide_mm(radius_mm: f64, ctx: &EffectContext) -> f64 {
    at_home_less_now(ctx, |chord, elevation| {
        guide_path_mm(radius_mm, chord, elevation)
    })
}

/// `d(contribution)/d(radius)` of a guide term: the path's slope in `r`
/// at home less the one now (`(pi/2 - a - cos a)` at home less now at `r = 0`, the
/// column the loop tests).
pub fn guide_slope(radius_mm: f64, ctx: &EffectContext) -> f64 {
    at_home_less_now(ctx, |chord, elevation| {
        path_slope(radius_mm, chord, elevation)
    })
}

/// `f(chord, elevation)` at the home capture (the home length, the home's
/// elevation) less at the context (its free length and elevation): what
/// the encoders, zeroed at home, read of a path term.
fn at_home_less_now(ctx: &EffectContext, f: impl Fn(f64, f64) -> f64) -> f64 {
    f(ctx.home_length_mm, ctx.home_guide_elevation_rad)
        - f(ctx.home_length_mm + ctx.payout_mm, ctx.guide_elevation_rad)
}

/// `d(guide_path_mm)/d(radius)`: `beta - sin(beta)` (the wrap angle less
/// its sine; `pi/2 - a - cos a` at `r = 0`); where the chord is clamped,
/// the path over `r` (it is `r` times a function of the elevation alone).
fn path_slope(radius_mm: f64, chord_mm: f64, elevation_rad: f64) -> f64 {
    let a = elevation_rad;
    if radius_mm == 0.0 {
        return FRAC_PI_2 - a - libm::cos(a);
    }
    if chord_mm < GUIDE_MIN_RADII * radius_mm.abs() {
        return guide_path_mm(radius_mm, chord_mm, a) / radius_mm;
    }
    let (_, beta, sin_beta, _) = guide_geometry(radius_mm, chord_mm, a);
    beta - sin_beta
}

/// [`MAX_GUIDE_RADIUS_MM`] in Q7.24.
pub(super) const MAX_GUIDE_RADIUS_Q24: i32 = (MAX_GUIDE_RADIUS_MM * 16_777_216.0) as i32;

/// A guide term: `radius_mm` within `+-`[`MAX_GUIDE_RADIUS_MM`], Q7.24 mm,
/// and its home part on each string it is on (every string of `frame` for
/// a shared term), Q11.20 mm: the exact path's excess over the chord from
/// the anchor to home, at the home's elevation as the device quantizes it.
pub(super) fn compile_guide(
    s: usize,
    string: u8,
    radius_mm: f64,
    frame: &Frame<f64>,
) -> Result<CompiledEffect, StringLawCompileError> {
    let r = in_range(
        s,
        "radius_mm",
        radius_mm,
        -MAX_GUIDE_RADIUS_MM,
        MAX_GUIDE_RADIUS_MM,
    )?;
    let mut home_q20 = [0; STRINGS];
    for (i, h) in home_q20.iter_mut().enumerate() {
        if string != EVERY_STRING && usize::from(string) != i {
            continue;
        }
        let (Some(anchor), Some(length)) = (frame.anchors.get(i), home_length_f64(frame, i)) else {
            continue;
        };
        let elevation = guide_elevation_rad(guide_elevation_q32(anchor, &frame.home, &frame.home));
        let home = guide_path_mm(r, length, elevation);
        // A channel without a string may hold any anchor: its part is never read.
        *h = if home.is_finite() || string != EVERY_STRING {
            to_fixed_i32(i, "anchor (guide's home part)", home, 20, "Q11.20 mm")?
        } else {
            0
        };
    }
    Ok(CompiledEffect::Guide {
        string,
        radius_q24: libm::round(r * 16_777_216.0) as i32,
        home_q20,
    })
}

/// `round(pi/2 2^32)`.
const HALF_PI_Q32: i64 = 6_746_518_852;
/// `round(pi/2 2^30)`.
const HALF_PI_Q30: i64 = 1_686_629_713;
/// `round(13/24 2^30)`.
const THIRTEEN_24THS_Q30: i64 = 581_610_837;
/// `5/8 2^30`.
const FIVE_8THS_Q30: i64 = 671_088_640;

/// `round_half_up(a b / 2^s)`; the callers keep `|a b| < 2^63`.
#[inline(always)]
fn mul_shr(a: i64, b: i64, s: u32) -> i64 {
    (a * b + (1 << (s - 1))) >> s
}

/// [`CompiledEffect::Guide`]'s contribution (Q31.32 mm): the string's home
/// part less the series of the module docs at the context's free length
/// and elevation. Always inlined, as [`CompiledEffect::contribution_q32`].
#[inline(always)]
pub(super) fn guide_q32(radius_q24: i32, home_q20: &[i32; STRINGS], ctx: &FixedContext) -> i64 {
    let home = home_q20
        .get(usize::from(ctx.string))
        .map_or(0, |&h| i64::from(h) << 12);
    if radius_q24 == 0 {
        return home;
    }
    let r = radius_q24.clamp(-MAX_GUIDE_RADIUS_Q24, MAX_GUIDE_RADIUS_Q24);
    let free = q16_to_q32(ctx.home_length_q16).saturating_add(ctx.payout_q32) >> 16;
    let now = bracket_q30(r, ctx.guide_elevation_q32, free);
    // Q.30 times Q7.24 to Q31.32 (the bracket below 2^33).
    home.saturating_sub(mul_i32_shr(now, r, 22))
}

/// The bracket of the module docs (Q.30) for a guide of `r` (Q7.24 mm) at
/// `elevation_q32` (Q0.32 turns) and the free length `l_q16` (Q.16 mm).
#[inline(always)]
fn bracket_q30(r: i32, elevation_q32: i32, l_q16: i64) -> i64 {
    let a = elevation_q32.clamp(-(1 << 30), 1 << 30);
    let s = i64::from(sin_q30(a as u32));
    let c = i64::from(sin_q30((a as u32).wrapping_add(1 << 30)));
    // pi/2 - a - cos a, Q.30 (a in rad: |a| 2^30 pi/2 < 2^63).
    let a_rad = mul_shr(i64::from(a), HALF_PI_Q32, 32);
    let first = HALF_PI_Q30 - a_rad - c;
    // eps = r / l, Q.30: l in Q.16 at least 16 |r| (r in Q.24 >> 4), so
    // |eps| <= 2^26; |r| 2^22 < 2^52.
    let l_min = (i64::from(r).abs() >> 4).max(1);
    let eps = (i64::from(r) << 22) / l_q16.max(l_min);
    // u = 1 - sin a in 0..=2 (Q.30: <= 2^31), u^2 <= 2^32, u^3 <= 2^33.
    let u = (1 << 30) - s;
    let u2 = mul_shr(u, u, 30);
    let k2 = (u2 + 1) >> 1;
    let k3 = mul_shr(c, u2, 31);
    let u3 = mul_shr(u2 >> 2, u, 28);
    // (15 s + 13) / 24 and (7 s + 5) / 8, Q.30, below 2^31.
    let w4 = ((5 * s + 4) >> 3) + THIRTEEN_24THS_Q30;
    let w5 = ((7 * s + 4) >> 3) + FIVE_8THS_Q30;
    let k4 = mul_shr(u3 >> 4, w4, 26);
    let k5 = mul_shr(mul_shr(u3 >> 4, c, 26) >> 4, w5, 26);
    // Horner in eps: each |eps h| <= 2^26 2^35.
    let mut h = k4 + mul_shr(eps, k5, 30);
    h = k3 + mul_shr(eps, h, 30);
    h = k2 + mul_shr(eps, h, 30);
    first + mul_shr(eps, h, 30)
}

#[cfg(test)]
mod tests;
