//! The fixed-point form of one effect term ([`CompiledEffect`]), what it
//! reads of its string ([`FixedContext`]), how an [`EffectTerm`] is
//! compiled to it ([`compile_effect`]) and its contribution to the string
//! length, integer only. The families with more to them than a line live in
//! their own modules (`creep`, `frame_flex`, `guide`, `latency`, `sag`,
//! `stretch`); this is where they meet.

use serde::{Deserialize, Serialize};

use super::{
    check_counts_per_rev, creep, finite, frame_flex, guide, latency, mul_i32_shr, mul_u32_shr,
    powi_f64, q16_to_q32, rad_per_x, sag, sin_q30, stretch, to_fixed, to_fixed_i32,
    StringLawCompileError, COUNTS_SHIFT, MAX_EFFECT_WINDING_POWER, MAX_GUIDE_RADIUS_MM,
    MAX_LATENCY_S,
};
use crate::model::{Effect, EffectTerm, Frame, StringLaw, EVERY_STRING};
use crate::STRINGS;

/// The fixed-point form of one [`EffectTerm`]: one variant per [`Effect`],
/// `string` is the encoder index (`0..STRINGS`). Formats in the field docs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum CompiledEffect {
    /// `+ mm_q16` (Q47.16 mm).
    Offset { string: u8, mm_q16: i64 },
    /// `+ relative_q30 * payout` (Q1.30).
    Scale { string: u8, relative_q30: i32 },
    /// `+ coeff_q32 * x^power`, `x = counts / 2^18`; Q31.32 mm,
    /// `round(mm_per_rad_pow (2 pi 2^18 / counts_per_rev)^power 2^32)`.
    /// `power` in `1..=MAX_EFFECT_WINDING_POWER` (larger values evaluate as
    /// that maximum).
    Winding {
        string: u8,
        power: u8,
        coeff_q32: i64,
    },
    /// `+ sin_q16 sin(theta) + cos_q16 (cos(theta) - 1)` (amplitudes Q47.16
    /// mm); the phase is `(counts mod counts_per_rev) * turns_per_count_q48 /
    /// 2^16` in Q0.32 turns, `turns_per_count_q48 = round(2^48 / counts_per_rev)`.
    Eccentricity {
        string: u8,
        sin_q16: i64,
        cos_q16: i64,
        counts_per_rev: u32,
        turns_per_count_q48: u64,
    },
    /// `+ strain * (home_length + payout) - home_strain_q31 * home_length +
    /// mm_per_mn_q47 * tension_mn - home_lead_q32`, strain = `per_mn_q47 *
    /// tension_mn` rounded to Q0.31 and saturated (Q16.47 per millinewton),
    /// `home_strain_q31 = per_newton * T_home` (Q0.31), the lead part
    /// Q16.47 mm per millinewton and `home_lead_q32 = mm_per_newton *
    /// T_home` (Q31.32 mm).
    Elasticity {
        string: u8,
        per_mn_q47: i64,
        mm_per_mn_q47: i64,
        home_strain_q31: i32,
        home_lead_q32: i64,
    },
    /// `+ half_width_q16 * sign(direction)` (Q47.16 mm).
    Backlash { string: u8, half_width_q16: i64 },
    /// `+ mm_per_ms_q48 * time_ms` (Q15.48 mm per ms).
    Drift { string: u8, mm_per_ms_q48: i64 },
    /// `+ strain * (home_length + payout)`, strain = `per_ms_q63 * time_ms`
    /// rounded to Q0.31 and saturated (Q0.63 per millisecond; module
    /// `creep`).
    Creep { string: u8, per_ms_q63: i64 },
    /// `+ mm_q16` when `time_ms >= at_ms` (Q47.16 mm, ms since home).
    Slip { string: u8, at_ms: u32, mm_q16: i64 },
    /// `+ coeff_q32 * cos^2 * a^3 / tau^2 + home_coeff_q32 * home_sag`
    /// (Q31.32 mm) with `a = l / 4096 mm` and `tau = tension_mn / 1024`: `a`
    /// is the free length `l = home_length + payout` read as Q·30 (its Q·18
    /// mm bits), clamped to `0..2^31` (8192 mm); `tau^2` is
    /// `max(tension_mn, 250)^2` in Q·20; `a^2`, `a^3` in Q·30, `r = (a^3 <<
    /// 20) / tau^2` in Q·30, `cos^2` the input's Q0.16; `home_sag` the
    /// string law's [`CompiledStringLaw::home_sag_q30`]; each product
    /// through i128, rounded, each part clamped to `+-`[`MAX_SAG_MM`].
    /// `coeff = -mm_at_1m_1n * 4.096^3 / 1.024^2 = -mm_at_1m_1n * 65.536`,
    /// `home_coeff = home_mm_at_1m * 4.096^3`.
    ///
    /// [`CompiledStringLaw::home_sag_q30`]: super::CompiledStringLaw::home_sag_q30
    /// [`MAX_SAG_MM`]: super::MAX_SAG_MM
    Sag {
        string: u8,
        coeff_q32: i64,
        home_coeff_q32: i64,
    },
    /// `+ per_mn_q48 * total_tension_mn - home_q32`: Q15.48 mm per mN
    /// (`mm_per_newton / 1000`, clamped to `+-2^44` so that the product
    /// with the total of eight `u16` tensions fits `i64`), rounded to Q31.32;
    /// `home_q32` Q31.32 mm.
    FrameFlex {
        string: u8,
        per_mn_q48: i64,
        home_q32: i64,
    },
    /// `+ latency_q31 * payout_rate` (Q0.31 s times the context's
    /// [`FixedContext::payout_rate_q14`], Q17.14 mm/s; module `latency`).
    Latency { string: u8, latency_q31: i32 },
    /// `+ home_q20[string] - radius_q24 * bracket(elevation, radius / free
    /// length)`: the path's excess over the chord at home (Q11.20 mm per
    /// string, computed when compiled: 0 on the strings the term is not
    /// on), less the series of module `guide` (radius Q7.24 mm) at the
    /// context's [`FixedContext::guide_elevation_q32`].
    Guide {
        string: u8,
        radius_q24: i32,
        home_q20: [i32; STRINGS],
    },
}

/// What a compiled effect of one string depends on, in device units.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FixedContext {
    /// Counts since home.
    pub counts: i32,
    /// Direction of the last motion (only the sign is used).
    pub direction: i8,
    /// Commanded tension, mN.
    pub tension_mn: u16,
    /// Time since home, ms.
    pub time_ms: u32,
    /// Q47.16 mm.
    pub home_length_q16: i64,
    /// Q31.32 mm, [`CompiledStringLaw::payout_q32`].
    ///
    /// [`CompiledStringLaw::payout_q32`]: super::CompiledStringLaw::payout_q32
    pub payout_q32: i64,
    /// `cos^2` of the inclination, Q0.16 ([`StringInputs::cos2_inclination_q16`]).
    ///
    /// [`StringInputs::cos2_inclination_q16`]: crate::model::StringInputs::cos2_inclination_q16
    pub cos2_inclination_q16: u16,
    /// The law's [`CompiledStringLaw::home_sag_q30`].
    ///
    /// [`CompiledStringLaw::home_sag_q30`]: super::CompiledStringLaw::home_sag_q30
    pub home_sag_q30: i64,
    /// Sum of the active strings' commanded tensions, mN ([`total_tension_mn`]).
    ///
    /// [`total_tension_mn`]: super::total_tension_mn
    pub total_tension_mn: u32,
    /// The payout's rate of change, Q17.14 mm/s
    /// ([`CompiledStringLaw::payout_rate_q14`] at the string's count rate;
    /// 0 at a rate of 0).
    ///
    /// [`CompiledStringLaw::payout_rate_q14`]: super::CompiledStringLaw::payout_rate_q14
    pub payout_rate_q14: i32,
    /// The elevation of the string's chord, Q0.32 turns
    /// ([`StringInputs::guide_elevation_q32`]).
    ///
    /// [`StringInputs::guide_elevation_q32`]: crate::model::StringInputs::guide_elevation_q32
    pub guide_elevation_q32: i32,
    /// The string's encoder index (a shared term's per-string constants).
    pub string: u8,
}

/// Compiles one effect term; `laws` gives the counts per revolution of its
/// string (winding and eccentricity terms), `frame` the anchors and home
/// (a guide's home part).
pub fn compile_effect(
    term: &EffectTerm,
    frame: &Frame<f64>,
    laws: &[StringLaw; STRINGS],
) -> Result<CompiledEffect, StringLawCompileError> {
    let s = usize::from(term.string);
    let law = law_of_term(term, laws)?;
    let string = term.string;
    Ok(match term.effect {
        Effect::Offset { mm } => CompiledEffect::Offset {
            string,
            mm_q16: to_fixed(s, "mm", mm, 16, "Q47.16 mm")?,
        },
        Effect::Scale { relative } => CompiledEffect::Scale {
            string,
            relative_q30: to_fixed_i32(s, "relative", relative, 30, "Q1.30")?,
        },
        Effect::Winding {
            power,
            mm_per_rad_pow,
        } => compile_winding(s, string, power, mm_per_rad_pow, law)?,
        Effect::Eccentricity { sin_mm, cos_mm } => {
            check_counts_per_rev(s, law.counts_per_rev)?;
            CompiledEffect::Eccentricity {
                string,
                sin_q16: to_fixed(s, "sin_mm", sin_mm, 16, "Q47.16 mm")?,
                cos_q16: to_fixed(s, "cos_mm", cos_mm, 16, "Q47.16 mm")?,
                counts_per_rev: law.counts_per_rev,
                turns_per_count_q48: turns_per_count_q48(law.counts_per_rev),
            }
        }
        Effect::Elasticity { per_newton } => {
            stretch::compile_stretch(s, string, per_newton, 0.0, 0.0)?
        }
        Effect::Stretch {
            per_newton,
            mm_per_newton,
            home_tension_n,
        } => stretch::compile_stretch(s, string, per_newton, mm_per_newton, home_tension_n)?,
        Effect::Sag {
            mm_at_1m_1n,
            home_mm_at_1m,
        } => sag::compile_sag(s, string, mm_at_1m_1n, home_mm_at_1m)?,
        Effect::FrameFlex {
            mm_per_newton,
            home_mm,
        } => frame_flex::compile_frame_flex(s, string, mm_per_newton, home_mm)?,
        Effect::Backlash { half_width_mm } => CompiledEffect::Backlash {
            string,
            half_width_q16: to_fixed(s, "half_width_mm", half_width_mm, 16, "Q47.16 mm")?,
        },
        Effect::Drift { mm_per_s } => CompiledEffect::Drift {
            string,
            mm_per_ms_q48: to_fixed(s, "mm_per_s", mm_per_s / 1000.0, 48, "Q15.48 mm per ms")?,
        },
        Effect::Creep { per_s } => creep::compile_creep(s, string, per_s)?,
        Effect::Slip { at_s, mm } => compile_slip(s, string, at_s, mm)?,
        Effect::Latency { latency_s } => latency::compile_latency(s, string, latency_s)?,
        Effect::Guide { radius_mm } => guide::compile_guide(s, string, radius_mm, frame)?,
    })
}

/// The law a term compiles against: its string's. A shared term of a family
/// that does not read the law compiles against any law; winding and
/// eccentricity need their string's.
fn law_of_term<'a>(
    term: &EffectTerm,
    laws: &'a [StringLaw; STRINGS],
) -> Result<&'a StringLaw, StringLawCompileError> {
    let s = usize::from(term.string);
    let shared = term.string == EVERY_STRING;
    match laws.get(s) {
        Some(law) => Ok(law),
        None if shared
            && !matches!(
                term.effect,
                Effect::Winding { .. } | Effect::Eccentricity { .. }
            ) =>
        {
            Ok(&laws[0])
        }
        None => Err(StringLawCompileError::StringOutOfRange { string: s }),
    }
}

/// A winding term: power in `1..=`[`MAX_EFFECT_WINDING_POWER`], the
/// coefficient per radian^power turned into one per `x^power` of the
/// string's counts per revolution.
fn compile_winding(
    s: usize,
    string: u8,
    power: u8,
    mm_per_rad_pow: f64,
    law: &StringLaw,
) -> Result<CompiledEffect, StringLawCompileError> {
    if power == 0 || power > MAX_EFFECT_WINDING_POWER {
        return Err(StringLawCompileError::OutOfRange {
            string: s,
            field: "power",
            value: f64::from(power),
            min: 1.0,
            max: f64::from(MAX_EFFECT_WINDING_POWER),
        });
    }
    check_counts_per_rev(s, law.counts_per_rev)?;
    let c = finite(s, "mm_per_rad_pow", mm_per_rad_pow)?;
    let scaled = c * powi_f64(rad_per_x(law.counts_per_rev), power);
    Ok(CompiledEffect::Winding {
        string,
        power,
        coeff_q32: to_fixed(s, "mm_per_rad_pow", scaled, 32, "Q31.32 mm per x^power")?,
    })
}

/// A slip term: its time rounded up to whole milliseconds since home (a
/// `u32`).
fn compile_slip(
    s: usize,
    string: u8,
    at_s: f64,
    mm: f64,
) -> Result<CompiledEffect, StringLawCompileError> {
    let at = finite(s, "at_s", at_s)?;
    let at_ms = libm::ceil(at * 1000.0);
    if !(0.0..=f64::from(u32::MAX)).contains(&at_ms) {
        return Err(StringLawCompileError::OutOfRange {
            string: s,
            field: "at_s",
            value: at,
            min: 0.0,
            max: f64::from(u32::MAX) / 1000.0,
        });
    }
    Ok(CompiledEffect::Slip {
        string,
        at_ms: at_ms as u32,
        mm_q16: to_fixed(s, "mm", mm, 16, "Q47.16 mm")?,
    })
}

/// `round(2^48 / counts_per_rev)` (0 for 0).
fn turns_per_count_q48(counts_per_rev: u32) -> u64 {
    if counts_per_rev == 0 {
        return 0;
    }
    let n = u64::from(counts_per_rev);
    ((1u64 << 48) + n / 2) / n
}

impl CompiledEffect {
    /// Encoder index of the string this term applies to.
    pub fn string(&self) -> u8 {
        match *self {
            CompiledEffect::Offset { string, .. }
            | CompiledEffect::Scale { string, .. }
            | CompiledEffect::Winding { string, .. }
            | CompiledEffect::Eccentricity { string, .. }
            | CompiledEffect::Elasticity { string, .. }
            | CompiledEffect::Backlash { string, .. }
            | CompiledEffect::Drift { string, .. }
            | CompiledEffect::Creep { string, .. }
            | CompiledEffect::Slip { string, .. }
            | CompiledEffect::Sag { string, .. }
            | CompiledEffect::FrameFlex { string, .. }
            | CompiledEffect::Latency { string, .. }
            | CompiledEffect::Guide { string, .. } => string,
        }
    }

    /// Checks a compiled term read from a blob: string in range, winding
    /// power in range, eccentricity counts per revolution consistent.
    pub fn validate(&self) -> Result<(), StringLawCompileError> {
        let s = usize::from(self.string());
        let law_free = !matches!(
            self,
            CompiledEffect::Winding { .. } | CompiledEffect::Eccentricity { .. }
        );
        if s >= STRINGS && !(self.string() == EVERY_STRING && law_free) {
            return Err(StringLawCompileError::StringOutOfRange { string: s });
        }
        match *self {
            CompiledEffect::Winding { power, .. }
                if power == 0 || power > MAX_EFFECT_WINDING_POWER =>
            {
                Err(StringLawCompileError::OutOfRange {
                    string: s,
                    field: "power",
                    value: f64::from(power),
                    min: 1.0,
                    max: f64::from(MAX_EFFECT_WINDING_POWER),
                })
            }
            CompiledEffect::Eccentricity {
                counts_per_rev,
                turns_per_count_q48: t,
                ..
            } => {
                check_counts_per_rev(s, counts_per_rev)?;
                if t != turns_per_count_q48(counts_per_rev) {
                    return Err(StringLawCompileError::OutOfRange {
                        string: s,
                        field: "turns_per_count_q48",
                        value: t as f64,
                        min: turns_per_count_q48(counts_per_rev) as f64,
                        max: turns_per_count_q48(counts_per_rev) as f64,
                    });
                }
                Ok(())
            }
            CompiledEffect::Latency { latency_q31, .. }
                if !(-latency::MAX_LATENCY_Q31..=latency::MAX_LATENCY_Q31)
                    .contains(&latency_q31) =>
            {
                Err(StringLawCompileError::OutOfRange {
                    string: s,
                    field: "latency_s",
                    value: f64::from(latency_q31) / 2_147_483_648.0,
                    min: -MAX_LATENCY_S,
                    max: MAX_LATENCY_S,
                })
            }
            CompiledEffect::Guide { radius_q24, .. }
                if !(-guide::MAX_GUIDE_RADIUS_Q24..=guide::MAX_GUIDE_RADIUS_Q24)
                    .contains(&radius_q24) =>
            {
                Err(StringLawCompileError::OutOfRange {
                    string: s,
                    field: "radius_mm",
                    value: f64::from(radius_q24) / 16_777_216.0,
                    min: -MAX_GUIDE_RADIUS_MM,
                    max: MAX_GUIDE_RADIUS_MM,
                })
            }
            _ => Ok(()),
        }
    }

    /// Whether the term reads the string's inclination ([`Effect::reads_inclination`]).
    pub fn reads_inclination(&self) -> bool {
        matches!(
            self,
            CompiledEffect::Sag { .. } | CompiledEffect::Guide { .. }
        )
    }

    /// Whether the term reads the strings' count rate ([`Effect::reads_speed`]).
    pub fn reads_speed(&self) -> bool {
        matches!(self, CompiledEffect::Latency { .. })
    }

    /// Whether the term reads the strings' elevation from their guides'
    /// swivel planes (a guide; a sag reads `cos^2` of the inclination).
    pub fn reads_elevation(&self) -> bool {
        matches!(self, CompiledEffect::Guide { .. })
    }

    /// Contribution of this term (Q31.32 mm), integer only, saturating.
    /// Always inlined: `string_lengths` has a copy of its loop for all 8
    /// channels and one for a layout, and the call would cost each term ~70
    /// instructions.
    #[inline(always)]
    pub fn contribution_q32(&self, ctx: &FixedContext) -> i64 {
        match *self {
            CompiledEffect::Offset { mm_q16, .. } => q16_to_q32(mm_q16),
            CompiledEffect::Scale { relative_q30, .. } => {
                mul_i32_shr(ctx.payout_q32, relative_q30, 30)
            }
            CompiledEffect::Winding {
                power, coeff_q32, ..
            } => {
                let mut t = coeff_q32;
                for _ in 0..power.min(MAX_EFFECT_WINDING_POWER) {
                    t = mul_i32_shr(t, ctx.counts, COUNTS_SHIFT);
                }
                t
            }
            CompiledEffect::Eccentricity {
                sin_q16,
                cos_q16,
                counts_per_rev,
                turns_per_count_q48,
                ..
            } => eccentricity_q32(sin_q16, cos_q16, counts_per_rev, turns_per_count_q48, ctx),
            CompiledEffect::Elasticity {
                per_mn_q47,
                mm_per_mn_q47,
                home_strain_q31,
                home_lead_q32,
                ..
            } => stretch::elasticity_q32(
                per_mn_q47,
                mm_per_mn_q47,
                home_strain_q31,
                home_lead_q32,
                ctx,
            ),
            CompiledEffect::Backlash { half_width_q16, .. } => {
                let h = q16_to_q32(half_width_q16);
                match ctx.direction.signum() {
                    1 => h,
                    -1 => h.saturating_neg(),
                    _ => 0,
                }
            }
            CompiledEffect::Drift { mm_per_ms_q48, .. } => {
                mul_u32_shr(mm_per_ms_q48, ctx.time_ms, 16)
            }
            CompiledEffect::Creep { per_ms_q63, .. } => creep::creep_q32(per_ms_q63, ctx),
            CompiledEffect::Slip { at_ms, mm_q16, .. } => {
                if ctx.time_ms >= at_ms {
                    q16_to_q32(mm_q16)
                } else {
                    0
                }
            }
            CompiledEffect::Sag {
                coeff_q32,
                home_coeff_q32,
                ..
            } => sag::sag_q32(coeff_q32, home_coeff_q32, ctx),
            CompiledEffect::FrameFlex {
                per_mn_q48,
                home_q32,
                ..
            } => frame_flex::frame_flex_q32(per_mn_q48, home_q32, ctx),
            CompiledEffect::Latency { latency_q31, .. } => latency::latency_q32(latency_q31, ctx),
            CompiledEffect::Guide {
                radius_q24,
                ref home_q20,
                ..
            } => guide::guide_q32(radius_q24, home_q20, ctx),
        }
    }
}

/// [`CompiledEffect::Eccentricity`]'s contribution (Q31.32 mm) at the
/// pulley phase of `ctx.counts`. Always inlined, as
/// [`CompiledEffect::contribution_q32`].
#[inline(always)]
fn eccentricity_q32(
    sin_q16: i64,
    cos_q16: i64,
    counts_per_rev: u32,
    turns_per_count_q48: u64,
    ctx: &FixedContext,
) -> i64 {
    let phase = pulley_phase_q32(ctx.counts, counts_per_rev, turns_per_count_q48);
    let sin = sin_q30(phase);
    let cos = sin_q30(phase.wrapping_add(1 << 30));
    let cos_m1 = (i64::from(cos) - (1 << 30)).clamp(i64::from(i32::MIN), 0) as i32;
    mul_i32_shr(sin_q16, sin, 14).saturating_add(mul_i32_shr(cos_q16, cos_m1, 14))
}

/// Pulley phase in Q0.32 turns from `counts mod counts_per_rev` (exact for
/// any count); 0 when `counts_per_rev` is not in `1..=i32::MAX`.
#[inline]
fn pulley_phase_q32(counts: i32, counts_per_rev: u32, turns_per_count_q48: u64) -> u32 {
    let Ok(n) = i32::try_from(counts_per_rev) else {
        return 0;
    };
    if n == 0 {
        return 0;
    }
    let m = counts.rem_euclid(n) as u32 as u64; // 0..n
    (m.wrapping_mul(turns_per_count_q48) >> 16) as u32
}
