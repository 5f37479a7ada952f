//! The stretch family ([`Effect::Stretch`](crate::model::Effect::Stretch),
//! and the elasticity of one string, [`Effect::Elasticity`](crate::model::Effect::Elasticity),
//! its form without lead and home parts): the f64 contribution, the
//! compiler and the fixed-point kernel of their one compiled form
//! ([`CompiledEffect::Elasticity`]).

use super::{
    finite, in_range, q32_to_q16, to_fixed, to_fixed_i32, CompiledEffect, EffectContext,
    FixedContext, StringLawCompileError, MAX_ELASTICITY_MM_PER_NEWTON, MAX_ELASTICITY_PER_NEWTON,
};

/// A stretch term's contribution (mm): `per_newton * (T (home_length +
/// payout) - T_home home_length) + mm_per_newton (T - T_home)`
/// ([`Effect::Stretch`](crate::model::Effect::Stretch)).
pub fn stretch_mm(
    per_newton: f64,
    mm_per_newton: f64,
    home_tension_n: f64,
    ctx: &EffectContext,
) -> f64 {
    per_newton
        * (ctx.tension_n * (ctx.home_length_mm + ctx.payout_mm)
            - home_tension_n * ctx.home_length_mm)
        + mm_per_newton * (ctx.tension_n - home_tension_n)
}

/// An elasticity or stretch term in its one compiled form (an elasticity is
/// a stretch without lead and home parts).
pub(super) fn compile_stretch(
    s: usize,
    string: u8,
    per_newton: f64,
    mm_per_newton: f64,
    home_tension_n: f64,
) -> Result<CompiledEffect, StringLawCompileError> {
    let e = finite(s, "per_newton", per_newton)?;
    if e.abs() > MAX_ELASTICITY_PER_NEWTON {
        return Err(StringLawCompileError::DoesNotFit {
            string: s,
            field: "per_newton",
            value: e,
            format: "strain Q0.31 at 65.535 N",
        });
    }
    let m = in_range(
        s,
        "mm_per_newton",
        mm_per_newton,
        -MAX_ELASTICITY_MM_PER_NEWTON,
        MAX_ELASTICITY_MM_PER_NEWTON,
    )?;
    // A commanded tension is at most 65.535 N (u16 mN). The home tension
    // is a fitted parameter: where the data make it negative (its home
    // part then also takes a constant length of the string, decision
    // record 0061) the device runs it as fitted; it is stored only as the
    // products below, signed, which fit at either sign.
    let th = in_range(s, "home_tension_n", home_tension_n, -65.535, 65.535)?;
    Ok(CompiledEffect::Elasticity {
        string,
        per_mn_q47: to_fixed(s, "per_newton", e / 1000.0, 47, "Q16.47 per mN")?,
        mm_per_mn_q47: to_fixed(s, "mm_per_newton", m / 1000.0, 47, "Q16.47 mm per mN")?,
        home_strain_q31: to_fixed_i32(s, "home_tension_n", e * th, 31, "strain Q0.31")?,
        home_lead_q32: to_fixed(s, "home_tension_n", m * th, 32, "Q31.32 mm")?,
    })
}

/// [`CompiledEffect::Elasticity`]'s contribution (Q31.32 mm): the strain
/// of the commanded tension over the free length, less the home strain over
/// the home length, plus the lead part. Always inlined, as
/// [`CompiledEffect::contribution_q32`].
#[inline(always)]
pub(super) fn elasticity_q32(
    per_mn_q47: i64,
    mm_per_mn_q47: i64,
    home_strain_q31: i32,
    home_lead_q32: i64,
    ctx: &FixedContext,
) -> i64 {
    // |per_mn_q47| <= 2^47 (a compiled model's is below 2^31):
    // the product fits i64 without a checked multiply, which
    // the M7 does in a library call.
    let strain_q47 = per_mn_q47.clamp(-(1 << 47), 1 << 47) * i64::from(ctx.tension_mn);
    let strain_q31 = ((strain_q47 >> 16) + ((strain_q47 >> 15) & 1))
        .clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32;
    // Lengths in Q16 (below 2^15 mm: clamped to i32) times
    // Q0.31 strains: one 32 x 32 -> 64 bit product each, in
    // Q.47 (the payout rounded to Q16 first: 8e-6 mm times the
    // strain). The home part is skipped by an elasticity of one
    // string, which has none.
    let mut stretch_q47 = free_length_q16(ctx) * i64::from(strain_q31);
    if home_strain_q31 != 0 {
        stretch_q47 -= to_i32(ctx.home_length_q16) * i64::from(home_strain_q31);
    }
    let stretch = (stretch_q47 + (1 << 14)) >> 15;
    // The lead part: |mm_per_mn_q47| <= 2^47 (a compiled
    // model's is below 2^37) times a u16 fits i64.
    if mm_per_mn_q47 == 0 {
        stretch
    } else {
        let m = mm_per_mn_q47.clamp(-(1 << 47), 1 << 47);
        let lead = (m * i64::from(ctx.tension_mn) + (1 << 14)) >> 15;
        stretch.saturating_add(lead.saturating_sub(home_lead_q32))
    }
}

/// `v` clamped to the `i32` range (kept as `i64`).
#[inline(always)]
fn to_i32(v: i64) -> i64 {
    v.clamp(i64::from(i32::MIN), i64::from(i32::MAX))
}

/// The string's free length `home_length + payout` in Q15.16 mm (the
/// payout rounded from Q31.32), clamped to the `i32` range: what an
/// elasticity's and a creep's strain multiply (one 32 x 32 -> 64 bit
/// product each).
#[inline(always)]
pub(super) fn free_length_q16(ctx: &FixedContext) -> i64 {
    let home_q16 = to_i32(ctx.home_length_q16);
    to_i32(home_q16 + q32_to_q16(ctx.payout_q32).clamp(-(1 << 40), 1 << 40))
}
