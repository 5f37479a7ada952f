//! The frame-flex family ([`Effect::FrameFlex`](crate::model::Effect::FrameFlex)):
//! the guides move with the strings' total pull, less the flex at the home
//! capture; its bounds, compiler and fixed-point kernel.

use super::{in_range, to_fixed, CompiledEffect, FixedContext, StringLawCompileError};

/// Largest `|mm_per_newton|` of a frame-flex term (mm/N): a frame that
/// gives 10 mm per newton of total pull is no frame.
pub const MAX_FRAME_FLEX_MM_PER_NEWTON: f64 = 10.0;

/// Largest `|home_mm|` of a frame-flex term (mm).
pub const MAX_FRAME_FLEX_HOME_MM: f64 = 100.0;

/// A frame-flex term: compliance within `+-`[`MAX_FRAME_FLEX_MM_PER_NEWTON`]
/// (per millinewton on the device), home part within
/// `+-`[`MAX_FRAME_FLEX_HOME_MM`].
pub(super) fn compile_frame_flex(
    s: usize,
    string: u8,
    mm_per_newton: f64,
    home_mm: f64,
) -> Result<CompiledEffect, StringLawCompileError> {
    let k = in_range(
        s,
        "mm_per_newton",
        mm_per_newton,
        -MAX_FRAME_FLEX_MM_PER_NEWTON,
        MAX_FRAME_FLEX_MM_PER_NEWTON,
    )?;
    let h = in_range(
        s,
        "home_mm",
        home_mm,
        -MAX_FRAME_FLEX_HOME_MM,
        MAX_FRAME_FLEX_HOME_MM,
    )?;
    Ok(CompiledEffect::FrameFlex {
        string,
        per_mn_q48: to_fixed(s, "mm_per_newton", k / 1000.0, 48, "Q15.48 mm per mN")?,
        home_q32: to_fixed(s, "home_mm", h, 32, "Q31.32 mm")?,
    })
}

/// [`CompiledEffect::FrameFlex`]'s contribution (Q31.32 mm). Always
/// inlined, as [`CompiledEffect::contribution_q32`].
#[inline(always)]
pub(super) fn frame_flex_q32(per_mn_q48: i64, home_q32: i64, ctx: &FixedContext) -> i64 {
    // |per| <= 2^44 and total < 2^19: the product fits i64.
    let per = per_mn_q48.clamp(-(1 << 44), 1 << 44);
    let flex = (per * i64::from(ctx.total_tension_mn) + (1 << 15)) >> 16;
    flex.saturating_sub(home_q32)
}
