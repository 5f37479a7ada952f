//! The latency family ([`Effect::Latency`]): a string whose encoder is read
//! `tau` late is short of its length by what it moved meanwhile,
//! `L(t) = L(t - tau) + tau dL/dt`. The term is
//!
//! ```text
//! + tau * d payout/d counts (counts) * count_rate
//! ```
//!
//! with the winding polynomial's slope (the layer table's is left out: its
//! knots change the slope by a few parts per thousand, see
//! `docs/fixed-point.md`, "Latency") and the string's count rate
//! ([`StringInputs::count_rate_cps`](crate::model::StringInputs::count_rate_cps)).
//!
//! # Fixed point
//!
//! | quantity | type | format |
//! |---|---|---|
//! | count rate | `i32` | counts per second |
//! | latency `tau` | `i32` | Q0.31 s (`|tau| <=` [`MAX_LATENCY_S`]) |
//! | polynomial slope in `x = counts / 2^18` | `i64` | Q31.32 mm per unit of `x`, by Horner on the law's coefficients (`k c_k x^(k-1)`, from the highest that is not 0), saturating |
//! | slope per count | `i32` | Q2.30 mm per count: the slope over 2^18, rounded, saturated (a spool paying out 2 mm a count is none) |
//! | payout rate | `i32` | Q17.14 mm/s: slope per count times the rate (one 32 x 32 -> 64 bit product) over 2^16, rounded, saturated at `+-131 m/s` |
//! | contribution | `i64` | Q31.32 mm: `rate_q14 * tau_q31 / 2^13`, one 32 x 32 -> 64 bit product, rounded |
//!
//! The slope per count is rounded at 2^-31 mm (1e-7 of a 12 mm spool's
//! 0.018 mm), the rate at 2^-15 mm/s (8e-6 mm times a quarter of a second):
//! the compiled term is the f64 term to a few 1e-6 mm
//! (`fixed_point_error_budget`). Two products of 32-bit values a string
//! and one a term: a model with a latency term shared by every string costs
//! the tick about 1,000 instructions (`docs/benchmarks.md`).

use core::f64::consts::TAU;

use super::{
    in_range, mul_i32_shr, polynomial_slope_f64, pulley_angle, shl_sat, CompiledEffect,
    CompiledStringLaw, FixedContext, StringLawCompileError, COUNTS_SHIFT,
};
use crate::model::{StringLaw, WINDING_ORDER};

/// Largest `|latency_s|` of a latency term (s): an encoder a quarter of a
/// second late is no encoder; a fit beyond it stands in for something else.
pub const MAX_LATENCY_S: f64 = 0.25;

/// The rate at which string `law`'s payout changes (mm/s) at `counts`
/// moving at `count_rate_cps`: the winding polynomial's slope per count
/// times the count rate (f64 reference of
/// [`CompiledStringLaw::payout_rate_q14`]).
pub fn payout_rate_mm_s(law: &StringLaw, counts: i32, count_rate_cps: i32) -> f64 {
    payout_rate_at_mm_s(law, pulley_angle(law, counts), count_rate_cps)
}

/// [`payout_rate_mm_s`] at the pulley angle `theta` of the counts
/// ([`pulley_angle`]), for a caller that has it already.
pub(crate) fn payout_rate_at_mm_s(law: &StringLaw, theta: f64, count_rate_cps: i32) -> f64 {
    if law.counts_per_rev == 0 {
        return 0.0;
    }
    let per_count = TAU / f64::from(law.counts_per_rev);
    polynomial_slope_f64(law, theta) * per_count * f64::from(count_rate_cps)
}

impl CompiledStringLaw {
    /// The payout's rate of change (Q17.14 mm/s) at `counts` moving at
    /// `count_rate_cps`: the winding polynomial's slope in `x` (Horner on
    /// `k c_k`, Q31.32 mm per x, from the highest coefficient that is not 0:
    /// an identified law is quadratic, one product instead of three; `k c_k`
    /// by shifts), per count in Q2.30 (rounded, saturated), times the rate,
    /// rounded to Q17.14 and saturated.
    #[inline]
    pub fn payout_rate_q14(&self, counts: i32, count_rate_cps: i32) -> i32 {
        if count_rate_cps == 0 {
            return 0;
        }
        let w = &self.winding_q32;
        let mut k = WINDING_ORDER;
        while k > 1 && w[k - 1] == 0 {
            k -= 1;
        }
        let mut slope = times(w[k - 1], k);
        for j in (1..k).rev() {
            slope = mul_i32_shr(slope, counts, COUNTS_SHIFT).saturating_add(times(w[j - 1], j));
        }
        // Q31.32 per x to Q2.30 per count: 2 + COUNTS_SHIFT bits.
        let per_count = ((slope >> (COUNTS_SHIFT + 1)) + 1) >> 1;
        let per_count = per_count.clamp(i64::from(i32::MIN), i64::from(i32::MAX));
        let rate_q30 = per_count * i64::from(count_rate_cps);
        ((rate_q30 + (1 << 15)) >> 16).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32
    }
}

/// `k c` (`k` in `1..=4`), saturating, by shifts.
#[inline(always)]
fn times(c: i64, k: usize) -> i64 {
    match k {
        1 => c,
        2 => shl_sat(c, 1),
        3 => c.saturating_add(shl_sat(c, 1)),
        _ => shl_sat(c, 2),
    }
}

/// A latency term: `latency_s` within `+-`[`MAX_LATENCY_S`], Q0.31 s.
pub(super) fn compile_latency(
    s: usize,
    string: u8,
    latency_s: f64,
) -> Result<CompiledEffect, StringLawCompileError> {
    let tau = in_range(s, "latency_s", latency_s, -MAX_LATENCY_S, MAX_LATENCY_S)?;
    Ok(CompiledEffect::Latency {
        string,
        latency_q31: libm::round(tau * libm::exp2(31.0)) as i32,
    })
}

/// Largest `|latency_q31|` a blob may carry ([`MAX_LATENCY_S`] in Q0.31).
pub(super) const MAX_LATENCY_Q31: i32 = (MAX_LATENCY_S * 2_147_483_648.0) as i32;

/// [`CompiledEffect::Latency`]'s contribution (Q31.32 mm): the context's
/// payout rate times the latency. Always inlined, as
/// [`CompiledEffect::contribution_q32`].
#[inline(always)]
pub(super) fn latency_q32(latency_q31: i32, ctx: &FixedContext) -> i64 {
    (i64::from(ctx.payout_rate_q14) * i64::from(latency_q31) + (1 << 12)) >> 13
}
