//! The sag family ([`Effect::Sag`](crate::model::Effect::Sag)): a heavy
//! string's span is longer than its chord by `w^2 cos^2(a) l^3 / (24 T^2)`
//! (parabolic catenary), less its sag at the home capture; the input the
//! device reads for it (the inclination, [`cos2_inclination_q16`]), the f64
//! term, its compiler and its fixed-point kernel (formats in the parent
//! module's table and `docs/fixed-point.md`, "Sag").

use super::StringLawCompileError;
use super::{in_range, q16_to_q32, to_fixed, CompiledEffect, EffectContext, FixedContext};
use crate::model::Vec3;
use crate::real::Real;
use crate::STRINGS;

/// Least tension a sag term takes (N): below it the string is not a
/// catenary and `1 / T^2` would grow without bound.
pub const SAG_MIN_TENSION_N: f64 = 0.25;

/// [`MAX_SAG_MM`] in Q31.32 mm.
const MAX_SAG_Q32: i128 = (MAX_SAG_MM as i128) << 32;

/// [`SAG_MIN_TENSION_N`] in the device's unit (mN).
const SAG_MIN_TENSION_MN: u16 = (SAG_MIN_TENSION_N * 1000.0) as u16;

/// Longest free length a sag term takes (mm): the fixed-point cube is taken
/// of `l / 4096 mm < 2` ([`CompiledEffect::Sag`]).
pub const MAX_SAG_LENGTH_MM: f64 = 8192.0 - 1.0 / 65536.0;

/// Largest `|mm_at_1m_1n|` of a sag term: 1.6 mm is a 20 g/m string, 100 mm a
/// 160 g/m one; beyond it the compiled coefficient could overflow.
pub const MAX_SAG_MM_AT_1M_1N: f64 = 100.0;

/// Largest sag a term gives (mm): a string sagging more is not taut, the
/// parabolic law does not hold, and its slope (`3 sag / l`) would amplify
/// any error of the length it is evaluated at.
pub const MAX_SAG_MM: f64 = 100.0;

/// A sag term's contribution (mm): `- mm_at_1m_1n * sag_variable +
/// home_mm_at_1m * sag_home_variable`, each part clamped to
/// `+-`[`MAX_SAG_MM`] ([`Effect::Sag`](crate::model::Effect::Sag)).
pub fn sag_mm(mm_at_1m_1n: f64, home_mm_at_1m: f64, ctx: &EffectContext) -> f64 {
    let now = (mm_at_1m_1n * sag_variable(ctx)).clamp(-MAX_SAG_MM, MAX_SAG_MM);
    let home = (home_mm_at_1m * sag_home_variable(ctx)).clamp(-MAX_SAG_MM, MAX_SAG_MM);
    home - now
}

/// d(contribution)/d(free length) of a sag term: `-3 sag / l`, 0 where the
/// length or the sag is clamped (what the identification's payout and home
/// length derivatives carry).
pub fn sag_slope(mm_at_1m_1n: f64, ctx: &EffectContext) -> f64 {
    -cube_slope(
        mm_at_1m_1n * sag_variable(ctx),
        ctx.home_length_mm + ctx.payout_mm,
    )
}

/// d(contribution)/d(home length) of a sag term's home part: `3 home_sag /
/// home_length`, 0 where clamped (the identification adds it to the home
/// length's derivative, beside [`sag_slope`]).
pub fn sag_home_slope(home_mm_at_1m: f64, ctx: &EffectContext) -> f64 {
    cube_slope(home_mm_at_1m * sag_home_variable(ctx), ctx.home_length_mm)
}

/// d(sag)/d(l) of a sag in `l^3`: `3 sag / l`, 0 where the length or the
/// sag is clamped.
fn cube_slope(sag: f64, l: f64) -> f64 {
    if l <= 0.0 || l >= MAX_SAG_LENGTH_MM || sag.abs() >= MAX_SAG_MM {
        0.0
    } else {
        3.0 * sag / l
    }
}

/// `cos^2(a_home) (home_length / 1 m)^3` of a sag term: the home capture's
/// sag variable without its tension ([`Effect::Sag`](crate::model::Effect::Sag)).
pub fn sag_home_variable(ctx: &EffectContext) -> f64 {
    let l = ctx.home_length_mm.clamp(0.0, MAX_SAG_LENGTH_MM) / 1000.0;
    ctx.home_cos2_inclination * l * l * l
}

/// `cos^2(a) (l / 1 m)^3 / (T / 1 N)^2` of a sag term, with `l` and `T`
/// clamped as [`Effect::Sag`](crate::model::Effect::Sag) says.
pub fn sag_variable(ctx: &EffectContext) -> f64 {
    let l = (ctx.home_length_mm + ctx.payout_mm).clamp(0.0, MAX_SAG_LENGTH_MM) / 1000.0;
    let t = ctx.tension_n.max(SAG_MIN_TENSION_N);
    ctx.cos2_inclination * l * l * l / (t * t)
}

/// `cos^2` of the inclination from the horizontal of the chord from
/// `anchor` to `position` (device frame, z up), Q0.16, saturating at 65535
/// (a level chord); 0 for a plumb chord, a chord of no length or a non-finite
/// input. What
/// [`StringInputs::cos2_inclination_q16`](crate::model::StringInputs::cos2_inclination_q16)
/// carries: the device takes it at the position its loop holds (the last
/// forward kinematics, a tick old), the host at the tracker's position
/// (identification) or at the row's solved position (prediction).
pub fn cos2_inclination_q16<F: Real>(anchor: &Vec3<F>, position: &Vec3<F>) -> u16 {
    let d = [
        position[0] - anchor[0],
        position[1] - anchor[1],
        position[2] - anchor[2],
    ];
    let level = d[0] * d[0] + d[1] * d[1];
    let squared = level + d[2] * d[2];
    if squared.partial_cmp(&F::zero()) != Some(core::cmp::Ordering::Greater) {
        return 0; // no chord, or NaN
    }
    // In f32 on both sides (the device's type; a Q0.16 step is 1.5e-5): the
    // `as` cast truncates the non-negative value (so rounds half up),
    // saturates the level chord's 65536 and takes NaN (an infinite input) to 0.
    let ratio = (level / squared).to_f32().unwrap_or(f32::NAN);
    (ratio * 65536.0 + 0.5) as u16
}

/// [`cos2_inclination_q16`] of every string of `anchors` at `position`.
pub fn cos2_inclinations<F: Real>(
    anchors: &[Vec3<F>; STRINGS],
    position: &Vec3<F>,
) -> [u16; STRINGS] {
    core::array::from_fn(|i| cos2_inclination_q16(&anchors[i], position))
}

/// A sag term: both coefficients within `+-`[`MAX_SAG_MM_AT_1M_1N`], in
/// the units of [`CompiledEffect::Sag`].
pub(super) fn compile_sag(
    s: usize,
    string: u8,
    mm_at_1m_1n: f64,
    home_mm_at_1m: f64,
) -> Result<CompiledEffect, StringLawCompileError> {
    let bounded = |field, v| in_range(s, field, v, -MAX_SAG_MM_AT_1M_1N, MAX_SAG_MM_AT_1M_1N);
    let m = bounded("mm_at_1m_1n", mm_at_1m_1n)?;
    let h = bounded("home_mm_at_1m", home_mm_at_1m)?;
    Ok(CompiledEffect::Sag {
        string,
        coeff_q32: to_fixed(s, "mm_at_1m_1n", -m * 65.536, 32, "Q31.32 mm")?,
        home_coeff_q32: to_fixed(
            s,
            "home_mm_at_1m",
            h * 4.096 * 4.096 * 4.096,
            32,
            "Q31.32 mm",
        )?,
    })
}

/// [`CompiledEffect::Sag`]'s contribution (Q31.32 mm). Always inlined, as
/// [`CompiledEffect::contribution_q32`].
#[inline(always)]
pub(super) fn sag_q32(coeff_q32: i64, home_coeff_q32: i64, ctx: &FixedContext) -> i64 {
    // Where this is written moves the code of `string_lengths` by a percent
    // or two (`scripts/qemu-bench`), even always inlined; its bits do not
    // move (`scripts/qemu-test`).
    let free_q32 = q16_to_q32(ctx.home_length_q16).saturating_add(ctx.payout_q32);
    // a = l / 4096 mm in Q.30 is l in Q.18 mm; 0 <= a < 2, so
    // a^2 < 2^62 and a^2 a < 2^63 (rounded at each step).
    let round_q30 = |x: i64| (x + (1 << 29)) >> 30;
    let a_q30 = (free_q32 >> 14).clamp(0, (1 << 31) - 1);
    let a2_q30 = round_q30(a_q30 * a_q30);
    let a3_q30 = round_q30(a2_q30 * a_q30);
    let t = i64::from(ctx.tension_mn.max(SAG_MIN_TENSION_MN));
    let t2 = t * t;
    // a^3 / tau^2 in Q.30 (a^3 << 20 < 2^54), rounded.
    let r_q30 = ((a3_q30 << 20) + t2 / 2) / t2;
    // coeff cos^2 a^3 / tau^2 in Q.46: |coeff| < 2^45, r < 2^38
    // (tau >= 250 mN) and cos^2 < 2^16, so below 2^99.
    let scaled = i128::from(coeff_q32) * i128::from(r_q30);
    let now = (scaled * i128::from(ctx.cos2_inclination_q16) + (1 << 45)) >> 46;
    // |home_coeff| < 2^45, home_sag < 2^33.
    let home = (i128::from(home_coeff_q32) * i128::from(ctx.home_sag_q30) + (1 << 29)) >> 30;
    (now.clamp(-MAX_SAG_Q32, MAX_SAG_Q32) + home.clamp(-MAX_SAG_Q32, MAX_SAG_Q32)) as i64
}
