//! String length from what the device knows: the base winding law of each
//! string plus its effect terms (see `docs/design.md`, [`StringLaw`],
//! [`Effect`]):
//!
//! ```text
//! L_i = |home - anchor_i| + payout_i(theta_i) + sum of the effect terms of string i
//! theta_i = 2 pi counts_i / counts_per_rev_i
//! payout_i = winding polynomial(theta_i) + layer table(counts_i)
//! ```
//!
//! Two implementations of the same law:
//! - **f64 reference** ([`string_lengths_f64`], [`payout_f64`],
//!   [`Effect::contribution_f64`], [`Effect::gradient_f64`]): what the host
//!   fits and the yardstick of the fixed-point error;
//! - **fixed point** ([`CompiledStringLaw`], [`CompiledEffect`],
//!   [`string_lengths`]): integer only, what the device runs every control-loop
//!   iteration, bit-identical on host and MCU by construction.
//!
//! # Fixed-point formats (also in `docs/fixed-point.md`, "String law")
//!
//! | quantity | type | format |
//! |---|---|---|
//! | counts since home | `i32` | integer counts; the polynomial variable is `x = counts / 2^COUNTS_SHIFT` ([`COUNTS_SHIFT`] = 18) |
//! | winding coefficient `k` (of `x^k`) | `i64` | Q31.32 mm: `round(winding_mm[k-1] (2 pi 2^18 / counts_per_rev)^k 2^32)` |
//! | internal sums (home + payout + effects) | `i64` | Q31.32 mm, saturating |
//! | home length, effect amplitudes (offset, eccentricity, backlash, slip) | `i64` | Q47.16 mm |
//! | output string length | `i64` | Q47.16 mm (`round(Q31.32 / 2^16)`) |
//! | scale | `i32` | Q1.30 (relative, `|relative| < 2`) |
//! | extra winding term | `i64` | Q31.32 mm per `x^power`, like the base law |
//! | elasticity | `i64` | Q16.47 per millinewton; strain `per_mn * tension_mn` in Q0.31 |
//! | drift | `i64` | Q15.48 mm per millisecond |
//! | creep | `i64` | Q0.63 per millisecond; strain `per_ms * time_ms` in Q0.31 (module `creep`) |
//! | slip time | `u32` | ms since home |
//! | pulley phase (eccentricity) | `u32` | Q0.32 turns, from `counts mod counts_per_rev` |
//! | sine table | `i32` | Q1.30, 512 segments per quarter turn, linear interpolation |
//! | inclination of a string (sag) | `u16` | Q0.16 `cos^2`, 65535 level |
//! | layer table knots | `i64` | Q47.16 mm (`|v| <= MAX_LAYER_MM`), knots `2^step_log2` counts apart; added to the payout |
//! | count rate (latency) | `i32` | counts per second; latency Q0.31 s, slope Q2.30 mm per count, payout rate Q17.14 mm/s (module `latency`, [`CompiledStringLaw::payout_rate_q14`]) |
//! | elevation of a string's chord (guide) | `i32` | Q0.32 turns; radius Q7.24 mm, the series in `r / l` in Q·30 (module `guide`) |
//!
//! Every product is `i64 x i32 -> 96 bits`, rounded (half up) and shifted back
//! to `i64`, saturating; every sum saturates. No input or compiled parameter
//! can make [`string_lengths`] panic.
//!
//! [`Effect`]: crate::model::Effect
//! [`Effect::contribution_f64`]: crate::model::Effect::contribution_f64
//! [`Effect::gradient_f64`]: crate::model::Effect::gradient_f64
//! [`StringLaw`]: crate::model::StringLaw

use crate::model::{StringInputs, StringLayout, EVERY_STRING};
use crate::STRINGS;

mod compile_error;
mod compiled_effect;
mod compiled_law;
mod creep;
mod frame_flex;
mod guide;
mod kernels;
mod latency;
mod reference;
mod sag;
mod stretch;

pub use compile_error::StringLawCompileError;
pub use compiled_effect::{compile_effect, CompiledEffect, FixedContext};
pub use compiled_law::{compile_string_law, CompiledLayerTable, CompiledStringLaw};
pub use creep::{creep_mm, creep_variable, MAX_CREEP_PER_S};
pub use frame_flex::{MAX_FRAME_FLEX_HOME_MM, MAX_FRAME_FLEX_MM_PER_NEWTON};
pub use guide::{
    guide_elevation_q32, guide_elevation_rad, guide_elevations, guide_mm, guide_path_mm,
    guide_slope, GUIDE_MIN_RADII, MAX_GUIDE_RADIUS_MM,
};
pub use latency::{payout_rate_mm_s, MAX_LATENCY_S};
pub use reference::{
    home_length_f64, payout_f64, polynomial_payout_at_f64, polynomial_payout_f64,
    polynomial_slope_f64, pulley_angle, string_lengths_at_homes, string_lengths_f64,
    total_tension_mn, total_tension_n, EffectContext, StringHome,
};
pub use sag::{
    cos2_inclination_q16, cos2_inclinations, sag_home_slope, sag_home_variable, sag_mm, sag_slope,
    sag_variable, MAX_SAG_LENGTH_MM, MAX_SAG_MM, MAX_SAG_MM_AT_1M_1N, SAG_MIN_TENSION_N,
};
pub use stretch::stretch_mm;

pub(crate) use kernels::{mul_i32_shr, mul_u32_shr, sin_q30};

use compile_error::{
    check_counts_per_rev, finite, in_range, rad_per_x, to_fixed, to_fixed_i32, WINDING_FIELDS,
};
use kernels::{q16_to_q32, q32_to_q16, shl_sat};
use reference::powi_f64;

/// The winding polynomial is evaluated in `x = counts / 2^COUNTS_SHIFT`, so
/// `|x| <= 1` for `|counts| <= 262144`.
pub const COUNTS_SHIFT: u32 = 18;

/// Highest power of an extra winding effect term ([`Effect::Winding`]).
///
/// [`Effect::Winding`]: crate::model::Effect::Winding
pub const MAX_EFFECT_WINDING_POWER: u8 = 8;

/// Largest `|per_newton|` of an elasticity term: the strain at the largest
/// commanded tension (65.535 N) must fit Q0.31.
pub const MAX_ELASTICITY_PER_NEWTON: f64 = 0.015;

/// Largest `|mm_per_newton|` of an elasticity term (mm/N): 1 m of lead on a
/// string of 1 kN stiffness.
pub const MAX_ELASTICITY_MM_PER_NEWTON: f64 = 1.0;

/// String lengths (Q47.16 mm) from the compiled laws and effect terms: what
/// the device runs every control-loop iteration. Integer only, saturating,
/// never panics. Only the channels `layout` marks active are evaluated; the
/// others (and terms on them, or whose `string` is out of range) are skipped
/// and their length is 0, which nothing reads.
pub fn string_lengths(
    layout: StringLayout,
    laws: &[CompiledStringLaw; STRINGS],
    effects: &[CompiledEffect],
    inputs: &StringInputs,
) -> [i64; STRINGS] {
    // All 8 channels: the masks compile out (the 8-string cost as it was).
    if layout.active == u8::MAX {
        lengths_of::<true>(u8::MAX, laws, effects, inputs)
    } else {
        lengths_of::<false>(layout.active, laws, effects, inputs)
    }
}

/// [`string_lengths`] on the channels of `active` (`ALL`: every channel).
#[inline(always)]
fn lengths_of<const ALL: bool>(
    active: u8,
    laws: &[CompiledStringLaw; STRINGS],
    effects: &[CompiledEffect],
    inputs: &StringInputs,
) -> [i64; STRINGS] {
    let mut payout = [0i64; STRINGS];
    let mut acc = [0i64; STRINGS];
    for i in 0..STRINGS {
        if !ALL && active >> i & 1 == 0 {
            continue;
        }
        payout[i] = laws[i].payout_q32(inputs.counts[i]);
        acc[i] = q16_to_q32(laws[i].home_length_q16).saturating_add(payout[i]);
    }
    let total_tension_mn = total_tension_mn(if ALL { u8::MAX } else { active }, &inputs.tension_mn);
    // Each string's context built once, not once per term that reads it
    // (a shared term reads all eight).
    let contexts: [FixedContext; STRINGS] = core::array::from_fn(|s| FixedContext {
        counts: inputs.counts[s],
        direction: inputs.direction[s],
        tension_mn: inputs.tension_mn[s],
        time_ms: inputs.time_ms,
        home_length_q16: laws[s].home_length_q16,
        payout_q32: payout[s],
        cos2_inclination_q16: inputs.cos2_inclination_q16[s],
        home_sag_q30: laws[s].home_sag_q30,
        total_tension_mn,
        // 0 at once where the string's count rate is 0: the device's loop
        // gives a rate only to a model with a term that reads it.
        payout_rate_q14: laws[s].payout_rate_q14(inputs.counts[s], inputs.count_rate_cps[s]),
        guide_elevation_q32: inputs.guide_elevation_q32[s],
        string: s as u8,
    });
    for e in effects {
        let s = usize::from(e.string());
        if e.string() == EVERY_STRING {
            for (i, a) in acc.iter_mut().enumerate() {
                if ALL || active >> i & 1 == 1 {
                    *a = a.saturating_add(e.contribution_q32(&contexts[i]));
                }
            }
            continue;
        }
        if s >= STRINGS || (!ALL && active >> s & 1 == 0) {
            continue;
        }
        acc[s] = acc[s].saturating_add(e.contribution_q32(&contexts[s]));
    }
    let mut out = [0i64; STRINGS];
    for i in 0..STRINGS {
        out[i] = q32_to_q16(acc[i]);
    }
    out
}

#[cfg(test)]
mod tests;
