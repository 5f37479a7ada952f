//! The creep family ([`Effect::Creep`](crate::model::Effect::Creep)): a
//! string whose natural length grows by `per_s * t` of itself (thermal or
//! plastic creep, `t` the time since home) is counted short by that much
//! of its whole length, so
//!
//! ```text
//! + per_s * t * (home_length + payout)
//! ```
//!
//! the time analogue of an elasticity (`per_newton * tension * (home_length
//! + payout)`, module `stretch`), whose free length it shares.
//!
//! # Fixed point
//!
//! | quantity | type | format |
//! |---|---|---|
//! | time since home | `u32` | ms ([`FixedContext::time_ms`]; 49 days) |
//! | rate `per_s / 1000` | `i64` | Q0.63 per millisecond (`|per_s| <=` [`MAX_CREEP_PER_S`]: below 2^37) |
//! | strain `per_ms * time_ms` | `i32` | Q0.31: one 64 x 32 bit product over 2^32, rounded, saturated at `+-1` |
//! | free length `home_length + payout` | `i32` | Q15.16 mm, clamped (as an elasticity's) |
//! | contribution | `i64` | Q31.32 mm: free length times strain (one 32 x 32 -> 64 bit product, Q.47) over 2^15, rounded |
//!
//! At the largest rate the strain is 0.36 after 10 h and saturates only
//! after 27 h; at a thermal creep's size (300 ppm/h) it is 0.003 after
//! 10 h. The rate is rounded at 2^-63 per ms (4e-12 of strain after 10 h),
//! the strain at 2^-32 (2e-7 mm on 1 m): the compiled term is the f64 term
//! to a few 1e-7 mm (`fixed_point_error_budget`).

use super::{
    finite, mul_u32_shr, stretch::free_length_q16, to_fixed, CompiledEffect, EffectContext,
    FixedContext, StringLawCompileError,
};

/// Largest `|per_s|` of a creep term (relative length per second): 3.6 %
/// an hour, a hundred times a nylon string's thermal creep; a fit beyond
/// it stands in for something else. Its strain stays within Q0.31 for 27 h.
pub const MAX_CREEP_PER_S: f64 = 1e-5;

/// A creep term's contribution (mm): `per_s * t * (home_length + payout)`
/// (f64 reference of the compiled term, `creep_q32`).
pub fn creep_mm(per_s: f64, ctx: &EffectContext) -> f64 {
    per_s * creep_variable(ctx)
}

/// What a creep term multiplies its rate by: the time since home (s) times
/// the string's whole length (mm).
pub fn creep_variable(ctx: &EffectContext) -> f64 {
    ctx.time_s * (ctx.home_length_mm + ctx.payout_mm)
}

/// A creep term of `per_s`: its rate per millisecond in Q0.63.
pub(super) fn compile_creep(
    s: usize,
    string: u8,
    per_s: f64,
) -> Result<CompiledEffect, StringLawCompileError> {
    let r = finite(s, "per_s", per_s)?;
    if r.abs() > MAX_CREEP_PER_S {
        return Err(StringLawCompileError::OutOfRange {
            string: s,
            field: "per_s",
            value: r,
            min: -MAX_CREEP_PER_S,
            max: MAX_CREEP_PER_S,
        });
    }
    Ok(CompiledEffect::Creep {
        string,
        per_ms_q63: to_fixed(s, "per_s", r / 1000.0, 63, "Q0.63 per ms")?,
    })
}

/// [`CompiledEffect::Creep`]'s contribution (Q31.32 mm): the strain since
/// home over the string's free length. Any rate (a blob's from another
/// tool too) saturates, never overflows. Always inlined, as
/// [`CompiledEffect::contribution_q32`].
#[inline(always)]
pub(super) fn creep_q32(per_ms_q63: i64, ctx: &FixedContext) -> i64 {
    let strain_q31 =
        mul_u32_shr(per_ms_q63, ctx.time_ms, 32).clamp(i64::from(i32::MIN), i64::from(i32::MAX));
    // |free_q16| < 2^31, |strain_q31| <= 2^31: the product fits i64.
    (free_length_q16(ctx) * strain_q31 + (1 << 14)) >> 15
}
