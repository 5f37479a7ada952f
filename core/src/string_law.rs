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

use core::f64::consts::TAU;
use core::fmt;

use serde::{Deserialize, Serialize};

use crate::model::{
    locate_knot, Effect, EffectTerm, Frame, Knots, StringInputs, StringLaw, StringLayout,
    EVERY_STRING, LAYER_KNOTS, MAX_LAYER_MM, MAX_LAYER_STEP_LOG2, WINDING_ORDER,
};
use crate::STRINGS;

mod creep;
mod frame_flex;
mod guide;
mod latency;
mod sag;
mod stretch;

pub use creep::{creep_mm, creep_variable, MAX_CREEP_PER_S};
pub use frame_flex::{MAX_FRAME_FLEX_HOME_MM, MAX_FRAME_FLEX_MM_PER_NEWTON};
pub use guide::{
    guide_elevation_q32, guide_elevation_rad, guide_elevations, guide_mm, guide_path_mm,
    guide_slope, GUIDE_MIN_RADII, MAX_GUIDE_RADIUS_MM,
};
pub use latency::{payout_rate_mm_s, MAX_LATENCY_S};
pub use sag::{
    cos2_inclination_q16, cos2_inclinations, sag_home_slope, sag_home_variable, sag_mm, sag_slope,
    sag_variable, MAX_SAG_LENGTH_MM, MAX_SAG_MM, MAX_SAG_MM_AT_1M_1N, SAG_MIN_TENSION_N,
};
pub use stretch::stretch_mm;

/// The winding polynomial is evaluated in `x = counts / 2^COUNTS_SHIFT`, so
/// `|x| <= 1` for `|counts| <= 262144`.
pub const COUNTS_SHIFT: u32 = 18;

/// Highest power of an extra winding effect term ([`Effect::Winding`]).
pub const MAX_EFFECT_WINDING_POWER: u8 = 8;

/// Largest `|per_newton|` of an elasticity term: the strain at the largest
/// commanded tension (65.535 N) must fit Q0.31.
pub const MAX_ELASTICITY_PER_NEWTON: f64 = 0.015;

/// Largest `|mm_per_newton|` of an elasticity term (mm/N): 1 m of lead on a
/// string of 1 kN stiffness.
pub const MAX_ELASTICITY_MM_PER_NEWTON: f64 = 1.0;

// ---------------------------------------------------------------------------
// f64 reference
// ---------------------------------------------------------------------------

/// Pulley angle `theta = 2 pi counts / counts_per_rev` (rad). Not finite when
/// `counts_per_rev` is 0.
pub fn pulley_angle(law: &StringLaw, counts: i32) -> f64 {
    TAU * f64::from(counts) / f64::from(law.counts_per_rev)
}

/// Base winding law: length paid out since home (mm) at `counts`,
/// `sum_k winding_mm[k-1] theta^k` (Horner) plus the law's layer table
/// ([`LayerTable::departure_mm`](crate::model::LayerTable::departure_mm)).
pub fn payout_f64(law: &StringLaw, counts: i32) -> f64 {
    polynomial_payout_f64(law, counts) + law.layers.departure_mm(counts)
}

/// The winding polynomial alone (mm), without the layer table.
pub fn polynomial_payout_f64(law: &StringLaw, counts: i32) -> f64 {
    polynomial_payout_at_f64(law, pulley_angle(law, counts))
}

/// The winding polynomial (mm) at pulley angle `theta` (rad from home).
pub fn polynomial_payout_at_f64(law: &StringLaw, theta: f64) -> f64 {
    let w = &law.winding_mm;
    let mut acc = 0.0;
    for k in (0..WINDING_ORDER).rev() {
        acc = (acc + w[k]) * theta;
    }
    acc
}

/// `d payout / d theta` of the winding polynomial at `theta` (mm/rad).
pub fn polynomial_slope_f64(law: &StringLaw, theta: f64) -> f64 {
    let w = &law.winding_mm;
    let mut acc = 0.0;
    for k in (0..WINDING_ORDER).rev() {
        acc = acc * theta + (k + 1) as f64 * w[k];
    }
    acc
}

/// `|home - anchor_string|` (mm); `None` when `string >= STRINGS`.
pub fn home_length_f64(frame: &Frame<f64>, string: usize) -> Option<f64> {
    let a = frame.anchors.get(string)?;
    let d = [
        frame.home[0] - a[0],
        frame.home[1] - a[1],
        frame.home[2] - a[2],
    ];
    Some(libm::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
}

/// What an effect term of one string depends on, in physical units (f64).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EffectContext {
    /// Pulley angle (rad), [`pulley_angle`].
    pub theta: f64,
    /// Base winding law output (mm), [`payout_f64`].
    pub payout_mm: f64,
    /// `|home - anchor|` (mm).
    pub home_length_mm: f64,
    /// Commanded tension (N) = `tension_mn / 1000`.
    pub tension_n: f64,
    /// Sum of the active strings' commanded tensions (N), [`total_tension_mn`] / 1000.
    pub total_tension_n: f64,
    /// Direction of the last motion; only its sign is used (+1, -1, 0).
    pub direction: i8,
    /// Time since home (s) = `time_ms / 1000`.
    pub time_s: f64,
    /// `cos^2` of the string's inclination = `cos2_inclination_q16 / 65536`.
    pub cos2_inclination: f64,
    /// `cos^2` of the string's inclination at home, from the frame,
    /// quantized as the device's ([`cos2_inclination_q16`]) / 65536.
    pub home_cos2_inclination: f64,
    /// The payout's rate of change (mm/s) at the string's count rate,
    /// [`payout_rate_mm_s`]: what a latency term scales with.
    pub payout_rate_mm_s: f64,
    /// The elevation of the string's chord out of the plane across its
    /// guide's swivel axis (rad), [`guide_elevation_rad`] of
    /// [`StringInputs::guide_elevation_q32`]: what a guide term reads.
    pub guide_elevation_rad: f64,
    /// The elevation of the string's chord at home (rad), from the frame,
    /// quantized as the device's ([`guide_elevation_q32`] at the frame's home).
    pub home_guide_elevation_rad: f64,
}

impl EffectContext {
    /// The context of `string` for `inputs`; `None` when `string >= STRINGS`.
    pub fn for_string(
        frame: &Frame<f64>,
        laws: &[StringLaw; STRINGS],
        inputs: &StringInputs,
        string: usize,
    ) -> Option<Self> {
        let total_tension_n = total_tension_n(frame.layout.active, &inputs.tension_mn);
        Self::at_home(
            &StringHome::of(frame, string)?,
            laws,
            inputs,
            string,
            total_tension_n,
        )
    }

    /// [`for_string`](Self::for_string) with the string's home terms
    /// already worked out ([`StringHome::of`], once per frame) and the
    /// active strings' total tension already summed (once per row): the
    /// same context.
    pub fn at_home(
        home: &StringHome,
        laws: &[StringLaw; STRINGS],
        inputs: &StringInputs,
        string: usize,
        total_tension_n: f64,
    ) -> Option<Self> {
        let law = laws.get(string)?;
        let counts = *inputs.counts.get(string)?;
        Some(Self {
            theta: pulley_angle(law, counts),
            payout_mm: payout_f64(law, counts),
            home_length_mm: home.length_mm,
            tension_n: f64::from(*inputs.tension_mn.get(string)?) / 1000.0,
            total_tension_n,
            direction: *inputs.direction.get(string)?,
            time_s: f64::from(inputs.time_ms) / 1000.0,
            cos2_inclination: f64::from(*inputs.cos2_inclination_q16.get(string)?) / 65536.0,
            home_cos2_inclination: home.cos2_inclination,
            payout_rate_mm_s: payout_rate_mm_s(law, counts, *inputs.count_rate_cps.get(string)?),
            guide_elevation_rad: guide_elevation_rad(*inputs.guide_elevation_q32.get(string)?),
            home_guide_elevation_rad: home.guide_elevation_rad,
        })
    }
}

/// What a string's [`EffectContext`] takes from the frame alone: the
/// string's length at home and its chord's inclination and elevation there
/// (quantized as the device's). The same for every row of a frame: worked
/// out once per frame instead of once per row and string.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StringHome {
    /// [`EffectContext::home_length_mm`].
    pub length_mm: f64,
    /// [`EffectContext::home_cos2_inclination`].
    pub cos2_inclination: f64,
    /// [`EffectContext::home_guide_elevation_rad`].
    pub guide_elevation_rad: f64,
}

impl StringHome {
    /// String `string`'s home terms in `frame`; `None` when `string >=
    /// STRINGS`.
    pub fn of(frame: &Frame<f64>, string: usize) -> Option<StringHome> {
        let anchor = frame.anchors.get(string)?;
        Some(StringHome {
            length_mm: home_length_f64(frame, string)?,
            cos2_inclination: f64::from(cos2_inclination_q16(anchor, &frame.home)) / 65536.0,
            guide_elevation_rad: guide_elevation_rad(guide_elevation_q32(
                anchor,
                &frame.home,
                &frame.home,
            )),
        })
    }

    /// Every channel's home terms in `frame`.
    pub fn of_every_string(frame: &Frame<f64>) -> [Option<StringHome>; STRINGS] {
        core::array::from_fn(|i| StringHome::of(frame, i))
    }
}

/// [`total_tension_mn`] in N: what an [`EffectContext`] holds as
/// `total_tension_n`.
pub fn total_tension_n(active: u8, tension_mn: &[u16; STRINGS]) -> f64 {
    f64::from(total_tension_mn(active, tension_mn)) / 1000.0
}

/// Sum of the commanded tensions (mN) of the strings whose bit is set in
/// `active` ([`StringLayout::active`]): what a frame-flex term reads
/// ([`Effect::FrameFlex`]). Eight `u16` fit a `u32`.
pub fn total_tension_mn(active: u8, tension_mn: &[u16; STRINGS]) -> u32 {
    (0..STRINGS)
        .filter(|&i| active >> i & 1 == 1)
        .map(|i| u32::from(tension_mn[i]))
        .sum()
}

fn direction_sign(direction: i8) -> f64 {
    f64::from(direction.signum())
}

fn powi_f64(x: f64, power: u8) -> f64 {
    let mut r = 1.0;
    for _ in 0..power {
        r *= x;
    }
    r
}

/// An effect's parameters or gradient (at most three).
fn values(v: &[f64]) -> heapless::Vec<f64, 3> {
    heapless::Vec::from_slice(v).unwrap_or_default()
}

impl Effect {
    /// Whether the term reads the string's direction from the position (a
    /// sag its inclination, a guide its elevation): forward kinematics over
    /// sparse rows then solves twice, the second time at the direction of
    /// the first solution (`spidar::predict`).
    pub fn reads_inclination(&self) -> bool {
        matches!(self, Effect::Sag { .. } | Effect::Guide { .. })
    }

    /// Whether the term reads the strings' count rate (a latency).
    pub fn reads_speed(&self) -> bool {
        matches!(self, Effect::Latency { .. })
    }

    /// Contribution of this term to the string length (mm), f64 reference.
    pub fn contribution_f64(&self, ctx: &EffectContext) -> f64 {
        match *self {
            Effect::Offset { mm } => mm,
            Effect::Scale { relative } => relative * ctx.payout_mm,
            Effect::Winding {
                power,
                mm_per_rad_pow,
            } => mm_per_rad_pow * powi_f64(ctx.theta, power),
            Effect::Eccentricity { sin_mm, cos_mm } => {
                sin_mm * libm::sin(ctx.theta) + cos_mm * (libm::cos(ctx.theta) - 1.0)
            }
            Effect::Elasticity { per_newton } => {
                per_newton * ctx.tension_n * (ctx.home_length_mm + ctx.payout_mm)
            }
            Effect::Stretch {
                per_newton,
                mm_per_newton,
                home_tension_n,
            } => stretch_mm(per_newton, mm_per_newton, home_tension_n, ctx),
            Effect::FrameFlex {
                mm_per_newton,
                home_mm,
            } => mm_per_newton * ctx.total_tension_n - home_mm,
            Effect::Backlash { half_width_mm } => half_width_mm * direction_sign(ctx.direction),
            Effect::Drift { mm_per_s } => mm_per_s * ctx.time_s,
            Effect::Creep { per_s } => creep_mm(per_s, ctx),
            Effect::Slip { at_s, mm } => {
                if ctx.time_s >= at_s {
                    mm
                } else {
                    0.0
                }
            }
            Effect::Sag {
                mm_at_1m_1n,
                home_mm_at_1m,
            } => sag_mm(mm_at_1m_1n, home_mm_at_1m, ctx),
            Effect::Latency { latency_s } => latency_s * ctx.payout_rate_mm_s,
            Effect::Guide { radius_mm } => guide_mm(radius_mm, ctx),
        }
    }

    /// Derivative of [`contribution_f64`](Self::contribution_f64) with respect
    /// to each free parameter, in the order of [`parameters`](Self::parameters):
    ///
    /// | effect | free parameters | gradient |
    /// |---|---|---|
    /// | Offset | `mm` | `[1]` |
    /// | Scale | `relative` | `[payout]` |
    /// | Winding | `mm_per_rad_pow` (`power` is structural) | `[theta^power]` |
    /// | Eccentricity | `sin_mm, cos_mm` | `[sin theta, cos theta - 1]` |
    /// | Elasticity | `per_newton` | `[tension_N (home_length + payout)]` |
    /// | Backlash | `half_width_mm` | `[sign(direction)]` |
    /// | Drift | `mm_per_s` | `[t]` |
    /// | Creep | `per_s` | `[t (home_length + payout)]` |
    /// | Slip | `mm` (`at_s` is held fixed: a step is not differentiable in its time; search it separately) | `[t >= at_s ? 1 : 0]` |
    /// | Sag | `mm_at_1m_1n, home_mm_at_1m` | `[-cos^2(a) (l / 1 m)^3 / (T / 1 N)^2, cos^2(a_home) (home_length / 1 m)^3]` (0 where a part is clamped) |
    /// | FrameFlex | `mm_per_newton, home_mm` | `[sum_j T_j, -1]` |
    /// | Stretch | `per_newton, mm_per_newton, home_tension_n` | `[T (home_length + payout) - T_home home_length, T - T_home, -(per_newton home_length + mm_per_newton)]` |
    /// | Latency | `latency_s` | `[payout rate]` |
    /// | Guide | `radius_mm` | `[(beta - sin(beta))(home) - (beta - sin(beta))(now)]` (the wrap angle) |
    pub fn gradient_f64(&self, ctx: &EffectContext) -> heapless::Vec<f64, 3> {
        match *self {
            Effect::Offset { .. } => values(&[1.0]),
            Effect::Scale { .. } => values(&[ctx.payout_mm]),
            Effect::Winding { power, .. } => values(&[powi_f64(ctx.theta, power)]),
            Effect::Eccentricity { .. } => {
                values(&[libm::sin(ctx.theta), libm::cos(ctx.theta) - 1.0])
            }
            Effect::Elasticity { .. } => {
                values(&[ctx.tension_n * (ctx.home_length_mm + ctx.payout_mm)])
            }
            Effect::Stretch {
                per_newton,
                mm_per_newton,
                home_tension_n,
            } => values(&[
                ctx.tension_n * (ctx.home_length_mm + ctx.payout_mm)
                    - home_tension_n * ctx.home_length_mm,
                ctx.tension_n - home_tension_n,
                -(per_newton * ctx.home_length_mm + mm_per_newton),
            ]),
            Effect::FrameFlex { .. } => values(&[ctx.total_tension_n, -1.0]),
            Effect::Backlash { .. } => values(&[direction_sign(ctx.direction)]),
            Effect::Drift { .. } => values(&[ctx.time_s]),
            Effect::Creep { .. } => values(&[creep_variable(ctx)]),
            Effect::Slip { at_s, .. } => values(&[if ctx.time_s >= at_s { 1.0 } else { 0.0 }]),
            Effect::Sag {
                mm_at_1m_1n,
                home_mm_at_1m,
            } => {
                let v = sag_variable(ctx);
                let h = sag_home_variable(ctx);
                values(&[
                    if (mm_at_1m_1n * v).abs() < MAX_SAG_MM {
                        -v
                    } else {
                        0.0
                    },
                    if (home_mm_at_1m * h).abs() < MAX_SAG_MM {
                        h
                    } else {
                        0.0
                    },
                ])
            }
            Effect::Latency { .. } => values(&[ctx.payout_rate_mm_s]),
            Effect::Guide { radius_mm } => values(&[guide_slope(radius_mm, ctx)]),
        }
    }

    /// The free parameters, in the order of [`gradient_f64`](Self::gradient_f64).
    pub fn parameters(&self) -> heapless::Vec<f64, 3> {
        match *self {
            Effect::Offset { mm } => values(&[mm]),
            Effect::Scale { relative } => values(&[relative]),
            Effect::Winding { mm_per_rad_pow, .. } => values(&[mm_per_rad_pow]),
            Effect::Eccentricity { sin_mm, cos_mm } => values(&[sin_mm, cos_mm]),
            Effect::Elasticity { per_newton } => values(&[per_newton]),
            Effect::Stretch {
                per_newton,
                mm_per_newton,
                home_tension_n,
            } => values(&[per_newton, mm_per_newton, home_tension_n]),
            Effect::FrameFlex {
                mm_per_newton,
                home_mm,
            } => values(&[mm_per_newton, home_mm]),
            Effect::Backlash { half_width_mm } => values(&[half_width_mm]),
            Effect::Drift { mm_per_s } => values(&[mm_per_s]),
            Effect::Creep { per_s } => values(&[per_s]),
            Effect::Slip { mm, .. } => values(&[mm]),
            Effect::Sag {
                mm_at_1m_1n,
                home_mm_at_1m,
            } => values(&[mm_at_1m_1n, home_mm_at_1m]),
            Effect::Latency { latency_s } => values(&[latency_s]),
            Effect::Guide { radius_mm } => values(&[radius_mm]),
        }
    }

    /// This effect with its free parameters replaced by `p` (order of
    /// [`parameters`](Self::parameters)); `None` when `p` has the wrong length.
    pub fn with_parameters(&self, p: &[f64]) -> Option<Effect> {
        let n = self.parameters().len();
        if p.len() != n {
            return None;
        }
        Some(match *self {
            Effect::Offset { .. } => Effect::Offset { mm: p[0] },
            Effect::Scale { .. } => Effect::Scale { relative: p[0] },
            Effect::Winding { power, .. } => Effect::Winding {
                power,
                mm_per_rad_pow: p[0],
            },
            Effect::Eccentricity { .. } => Effect::Eccentricity {
                sin_mm: p[0],
                cos_mm: p[1],
            },
            Effect::Elasticity { .. } => Effect::Elasticity { per_newton: p[0] },
            Effect::Stretch { .. } => Effect::Stretch {
                per_newton: p[0],
                mm_per_newton: p[1],
                home_tension_n: p[2],
            },
            Effect::FrameFlex { .. } => Effect::FrameFlex {
                mm_per_newton: p[0],
                home_mm: p[1],
            },
            Effect::Backlash { .. } => Effect::Backlash {
                half_width_mm: p[0],
            },
            Effect::Drift { .. } => Effect::Drift { mm_per_s: p[0] },
            Effect::Creep { .. } => Effect::Creep { per_s: p[0] },
            Effect::Slip { at_s, .. } => Effect::Slip { at_s, mm: p[0] },
            Effect::Sag { .. } => Effect::Sag {
                mm_at_1m_1n: p[0],
                home_mm_at_1m: p[1],
            },
            Effect::Latency { .. } => Effect::Latency { latency_s: p[0] },
            Effect::Guide { .. } => Effect::Guide { radius_mm: p[0] },
        })
    }
}

/// String lengths (mm), f64 reference of [`string_lengths`]. Effect terms whose
/// `string` is out of range are ignored (compiling them is an error).
pub fn string_lengths_f64(
    frame: &Frame<f64>,
    laws: &[StringLaw; STRINGS],
    effects: &[EffectTerm],
    inputs: &StringInputs,
) -> [f64; STRINGS] {
    string_lengths_at_homes(
        &StringHome::of_every_string(frame),
        frame.layout.active,
        laws,
        effects,
        inputs,
    )
}

/// [`string_lengths_f64`] with the frame's home terms already worked out
/// ([`StringHome::of_every_string`]) and its active strings
/// ([`StringLayout::active`](crate::model::StringLayout::active)): the same
/// lengths, for a caller that evaluates many rows of one frame.
pub fn string_lengths_at_homes(
    homes: &[Option<StringHome>; STRINGS],
    active: u8,
    laws: &[StringLaw; STRINGS],
    effects: &[EffectTerm],
    inputs: &StringInputs,
) -> [f64; STRINGS] {
    let mut ctx = [None; STRINGS];
    let mut out = [0.0; STRINGS];
    let total_tension_n = total_tension_n(active, &inputs.tension_mn);
    for i in 0..STRINGS {
        ctx[i] = homes[i]
            .as_ref()
            .and_then(|home| EffectContext::at_home(home, laws, inputs, i, total_tension_n));
        if let Some(c) = &ctx[i] {
            out[i] = c.home_length_mm + c.payout_mm;
        }
    }
    for term in effects {
        for (i, c) in ctx.iter().enumerate() {
            if let Some(c) = c.as_ref().filter(|_| term.applies_to(i)) {
                out[i] += term.effect.contribution_f64(c);
            }
        }
    }
    out
}

// ---------------------------------------------------------------------------
// Compilation errors
// ---------------------------------------------------------------------------

/// Why a string law or an effect term cannot be compiled to fixed point (or a
/// compiled one is invalid). Fields are named as in [`StringLaw`], [`Effect`]
/// and [`Frame`].
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StringLawCompileError {
    /// The string index is not in `0..STRINGS`.
    StringOutOfRange { string: usize },
    /// A parameter is NaN or infinite.
    NotFinite { string: usize, field: &'static str },
    /// A parameter, scaled to its fixed-point format, does not fit it.
    DoesNotFit {
        string: usize,
        field: &'static str,
        value: f64,
        format: &'static str,
    },
    /// A parameter is outside its allowed range.
    OutOfRange {
        string: usize,
        field: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
}

impl fmt::Display for StringLawCompileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            StringLawCompileError::StringOutOfRange { string } => {
                write!(f, "string {string} is out of range 0..{STRINGS}")
            }
            StringLawCompileError::NotFinite { string, field } => {
                write!(f, "string {string}: {field} is not finite")
            }
            StringLawCompileError::DoesNotFit {
                string,
                field,
                value,
                format,
            } => write!(
                f,
                "string {string}: {field} = {value} does not fit {format}"
            ),
            StringLawCompileError::OutOfRange {
                string,
                field,
                value,
                min,
                max,
            } => write!(
                f,
                "string {string}: {field} = {value} is outside [{min}, {max}]"
            ),
        }
    }
}

impl core::error::Error for StringLawCompileError {}

const WINDING_FIELDS: [&str; WINDING_ORDER] = [
    "winding_mm[0]",
    "winding_mm[1]",
    "winding_mm[2]",
    "winding_mm[3]",
];

fn finite(string: usize, field: &'static str, v: f64) -> Result<f64, StringLawCompileError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(StringLawCompileError::NotFinite { string, field })
    }
}

/// `v` when finite and within `min..=max`, else the error naming `field`.
fn in_range(
    string: usize,
    field: &'static str,
    v: f64,
    min: f64,
    max: f64,
) -> Result<f64, StringLawCompileError> {
    let v = finite(string, field, v)?;
    if (min..=max).contains(&v) {
        Ok(v)
    } else {
        Err(StringLawCompileError::OutOfRange {
            string,
            field,
            value: v,
            min,
            max,
        })
    }
}

/// `round(v * 2^frac)` as i64, or an error naming `field`.
fn to_fixed(
    string: usize,
    field: &'static str,
    v: f64,
    frac: i32,
    format: &'static str,
) -> Result<i64, StringLawCompileError> {
    let v = finite(string, field, v)?;
    let scaled = libm::round(v * libm::exp2(f64::from(frac)));
    // 2^63 is exactly representable; i64::MAX is not.
    const TWO_63: f64 = 9_223_372_036_854_775_808.0;
    if !(-TWO_63..TWO_63).contains(&scaled) {
        return Err(StringLawCompileError::DoesNotFit {
            string,
            field,
            value: v,
            format,
        });
    }
    Ok(scaled as i64)
}

fn to_fixed_i32(
    string: usize,
    field: &'static str,
    v: f64,
    frac: i32,
    format: &'static str,
) -> Result<i32, StringLawCompileError> {
    let q = to_fixed(string, field, v, frac, format)?;
    i32::try_from(q).map_err(|_| StringLawCompileError::DoesNotFit {
        string,
        field,
        value: v,
        format,
    })
}

fn check_counts_per_rev(string: usize, counts_per_rev: u32) -> Result<(), StringLawCompileError> {
    if counts_per_rev == 0 || counts_per_rev > i32::MAX as u32 {
        return Err(StringLawCompileError::OutOfRange {
            string,
            field: "counts_per_rev",
            value: f64::from(counts_per_rev),
            min: 1.0,
            max: f64::from(i32::MAX),
        });
    }
    Ok(())
}

/// `2 pi 2^COUNTS_SHIFT / counts_per_rev`: rad per unit of `x`.
fn rad_per_x(counts_per_rev: u32) -> f64 {
    TAU * libm::exp2(f64::from(COUNTS_SHIFT)) / f64::from(counts_per_rev)
}

// ---------------------------------------------------------------------------
// Fixed-point kernels
// ---------------------------------------------------------------------------

/// `v * 2^k`, saturated to i64.
#[inline]
fn shl_sat(v: i64, k: u32) -> i64 {
    if k == 0 {
        return v;
    }
    let lim = i64::MAX >> k;
    if v > lim {
        i64::MAX
    } else if v < -lim - 1 {
        i64::MIN
    } else {
        v << k
    }
}

#[inline]
fn clamp_i128(v: i128) -> i64 {
    if v > i128::from(i64::MAX) {
        i64::MAX
    } else if v < i128::from(i64::MIN) {
        i64::MIN
    } else {
        v as i64
    }
}

/// `round_half_up(a * b / 2^s)` saturated to i64, for `1 <= s <= 32`
/// (`s` outside is clamped into it). Two 32x32->64 multiplies, no 128-bit
/// multiply (which is a library call on Cortex-M).
#[inline]
pub(crate) fn mul_i32_shr(a: i64, b: i32, s: u32) -> i64 {
    let s = s.clamp(1, 32);
    let lo = (a as u64 & 0xFFFF_FFFF) as i64; // 0 ..= 2^32 - 1
    let hi = a >> 32; // i32 range
    let b = i64::from(b);
    // |lo * b| <= (2^32 - 1) 2^31 < 2^63 - 2^31: room for the rounding half.
    let low = (lo * b + (1i64 << (s - 1))) >> s;
    let high = hi * b; // |.| <= 2^62
    clamp_i128((i128::from(high) << (32 - s)) + i128::from(low))
}

/// `round_half_up(a * b / 2^s)` saturated to i64, for `1 <= s <= 32`.
#[inline]
pub(crate) fn mul_u32_shr(a: i64, b: u32, s: u32) -> i64 {
    let s = s.clamp(1, 32);
    let lo = a as u64 & 0xFFFF_FFFF;
    let hi = a >> 32;
    // lo * b <= (2^32 - 1)^2 = 2^64 - 2^33 + 1: room for the rounding half.
    let low = (lo * u64::from(b) + (1u64 << (s - 1))) >> s;
    let high = hi * i64::from(b); // |.| < 2^63
    clamp_i128((i128::from(high) << (32 - s)) + i128::from(low))
}

/// Q47.16 -> Q31.32, saturating.
#[inline]
fn q16_to_q32(v: i64) -> i64 {
    shl_sat(v, 16)
}

/// Q31.32 -> Q47.16, rounding half up (never overflows).
#[inline]
fn q32_to_q16(v: i64) -> i64 {
    (v >> 16) + ((v >> 15) & 1)
}

/// Segments of the sine table per quarter turn (power of two).
const SIN_SEGMENTS_LOG2: u32 = 9;
const SIN_SEGMENTS: usize = 1 << SIN_SEGMENTS_LOG2;
/// round(pi/2 * 2^62).
const HALF_PI_Q62: i128 = 7_244_019_458_077_122_842;

/// `sin(k pi / (2 SIN_SEGMENTS))` in Q1.30 for `k = 0..=SIN_SEGMENTS + 1`
/// (one entry past the quarter so that interpolation never reads out of
/// bounds), computed at compile time with an integer Taylor series in Q62:
/// the same bits on every target.
static SIN_TABLE_Q30: [i32; SIN_SEGMENTS + 2] = build_sin_table();

const fn build_sin_table() -> [i32; SIN_SEGMENTS + 2] {
    let mut table = [0i32; SIN_SEGMENTS + 2];
    let mut k = 0;
    while k < SIN_SEGMENTS + 2 {
        let x = HALF_PI_Q62 * (k as i128) / (SIN_SEGMENTS as i128); // Q62, <= 1.58
        let x2 = (x * x) >> 62;
        let mut term = x;
        let mut sum = x;
        let mut n: i128 = 1;
        while n < 16 {
            term = -((term * x2) >> 62) / ((2 * n) * (2 * n + 1));
            sum += term;
            n += 1;
        }
        table[k] = ((sum + (1i128 << 31)) >> 32) as i32;
        k += 1;
    }
    table
}

/// `sin(2 pi phase / 2^32)` in Q1.30, `phase` in Q0.32 turns. Linear
/// interpolation in a quarter-wave table: max error 1.2e-6 (measured in tests).
#[inline]
pub(crate) fn sin_q30(phase: u32) -> i32 {
    let quadrant = phase >> 30;
    let f = phase & 0x3FFF_FFFF; // Q0.30 of a quarter turn
    let g = if quadrant & 1 == 1 {
        (1u32 << 30) - f
    } else {
        f
    }; // 0..=2^30
    const FRAC_BITS: u32 = 30 - SIN_SEGMENTS_LOG2;
    let idx = (g >> FRAC_BITS) as usize; // 0..=SIN_SEGMENTS
    let frac = i64::from(g & ((1 << FRAC_BITS) - 1));
    let (y0, y1) = match (SIN_TABLE_Q30.get(idx), SIN_TABLE_Q30.get(idx + 1)) {
        (Some(&a), Some(&b)) => (i64::from(a), i64::from(b)),
        _ => (1 << 30, 1 << 30),
    };
    let y = y0 + (((y1 - y0) * frac + (1 << (FRAC_BITS - 1))) >> FRAC_BITS);
    let y = if quadrant >= 2 { -y } else { y };
    y as i32
}

// ---------------------------------------------------------------------------
// Compiled string law
// ---------------------------------------------------------------------------

/// The fixed-point form of one string's base law: home length plus the
/// winding polynomial in `x = counts / 2^COUNTS_SHIFT`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompiledStringLaw {
    /// `|home - anchor|`, Q47.16 mm.
    pub home_length_q16: i64,
    /// Quadrature counts per pulley revolution (for reference; the
    /// coefficients already include it).
    pub counts_per_rev: u32,
    /// Coefficient of `x^k` at index `k-1`, Q31.32 mm:
    /// `round(winding_mm[k-1] (2 pi 2^18 / counts_per_rev)^k 2^32)`.
    pub winding_q32: [i64; WINDING_ORDER],
    /// The layer table ([`LayerTable`](crate::model::LayerTable)), knots in Q47.16 mm.
    pub layers: CompiledLayerTable,
    /// What a sag term's home part scales with: `cos^2(a_home) (home_length
    /// / 4096 mm)^3` in Q·30 (`cos^2` quantized to Q0.16 as the device's,
    /// the length clamped to [`MAX_SAG_LENGTH_MM`]: below 2^33).
    pub home_sag_q30: i64,
}

/// The fixed-point form of a [`LayerTable`](crate::model::LayerTable): the same knots (counts), their
/// values in Q47.16 mm, `|value| <= MAX_LAYER_MM`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompiledLayerTable {
    pub start_counts: i32,
    pub step_log2: u8,
    pub knots_q16: Knots<i64>,
}

impl Eq for Knots<i64> {}

impl Default for CompiledLayerTable {
    fn default() -> Self {
        Self::NONE
    }
}

impl CompiledLayerTable {
    /// No table.
    pub const NONE: CompiledLayerTable = CompiledLayerTable {
        start_counts: 0,
        step_log2: 0,
        knots_q16: Knots::EMPTY_I64,
    };

    /// Departure at `counts`, Q47.16 mm: linear interpolation between the
    /// two knots around `counts`, `v_k + round_half_up((v_{k+1} - v_k)
    /// along / 2^step_log2)`, held at the end knots outside them. With
    /// `|v| <= MAX_LAYER_MM` (checked when compiled and when read) the
    /// product is below `2^25 2^30`: no overflow.
    #[inline]
    pub fn departure_q16(&self, counts: i32) -> i64 {
        let Some((k, along)) = self.locate(counts) else {
            return 0;
        };
        let v = self.knots_q16.as_slice();
        let (Some(&a), Some(&b)) = (v.get(k), v.get(k + 1)) else {
            return v.get(k).copied().unwrap_or(0);
        };
        if along == 0 {
            return a;
        }
        let s = u32::from(self.step_log2.min(MAX_LAYER_STEP_LOG2));
        let product = b.saturating_sub(a).saturating_mul(i64::from(along));
        a.saturating_add(product.saturating_add(1i64 << (s - 1)) >> s)
    }

    #[inline]
    fn locate(&self, counts: i32) -> Option<(usize, u32)> {
        locate_knot(
            self.start_counts,
            self.step_log2,
            self.knots_q16.len(),
            counts,
        )
    }
}

/// Compiles string `string`'s base law (home length from `frame`).
pub fn compile_string_law(
    frame: &Frame<f64>,
    string: usize,
    law: &StringLaw,
) -> Result<CompiledStringLaw, StringLawCompileError> {
    let anchor = frame
        .anchors
        .get(string)
        .ok_or(StringLawCompileError::StringOutOfRange { string })?;
    for v in anchor {
        finite(string, "anchor", *v)?;
    }
    for v in &frame.home {
        finite(string, "home", *v)?;
    }
    let home =
        home_length_f64(frame, string).ok_or(StringLawCompileError::StringOutOfRange { string })?;
    let home_length_q16 = to_fixed(string, "home", home, 16, "Q47.16 mm")?;
    check_counts_per_rev(string, law.counts_per_rev)?;
    let r = rad_per_x(law.counts_per_rev);
    let mut winding_q32 = [0i64; WINDING_ORDER];
    let mut scale = 1.0;
    for k in 0..WINDING_ORDER {
        scale *= r;
        let a = finite(string, WINDING_FIELDS[k], law.winding_mm[k])?;
        winding_q32[k] = to_fixed(
            string,
            WINDING_FIELDS[k],
            a * scale,
            32,
            "Q31.32 mm per x^k",
        )?;
    }
    let home_cos2 = f64::from(cos2_inclination_q16(anchor, &frame.home)) / 65536.0;
    let a = home.clamp(0.0, MAX_SAG_LENGTH_MM) / 4096.0;
    Ok(CompiledStringLaw {
        home_length_q16,
        counts_per_rev: law.counts_per_rev,
        winding_q32,
        layers: compile_layer_table(string, law)?,
        home_sag_q30: libm::round(home_cos2 * a * a * a * (1u64 << 30) as f64) as i64,
    })
}

fn check_layer_step(string: usize, step_log2: u8) -> Result<(), StringLawCompileError> {
    if step_log2 > MAX_LAYER_STEP_LOG2 {
        return Err(StringLawCompileError::OutOfRange {
            string,
            field: "layers.step_log2",
            value: f64::from(step_log2),
            min: 0.0,
            max: f64::from(MAX_LAYER_STEP_LOG2),
        });
    }
    Ok(())
}

/// Compiles a law's layer table, refusing one that would make the payout
/// decrease where the polynomial's increases (the law must stay monotone: a
/// non-monotone law has one string length for two counts, and the fit that
/// made it followed noise). Checked on every segment at both ends against
/// the polynomial's slope there.
fn compile_layer_table(
    string: usize,
    law: &StringLaw,
) -> Result<CompiledLayerTable, StringLawCompileError> {
    let table = &law.layers;
    check_layer_step(string, table.step_log2)?;
    let values = table.knots_mm.as_slice();
    let mut knots_q16 = [0i64; LAYER_KNOTS];
    for (k, &v) in values.iter().enumerate() {
        let v = finite(string, "layers.knots_mm", v)?;
        if v.abs() > MAX_LAYER_MM {
            return Err(StringLawCompileError::OutOfRange {
                string,
                field: "layers.knots_mm",
                value: v,
                min: -MAX_LAYER_MM,
                max: MAX_LAYER_MM,
            });
        }
        knots_q16[k] = to_fixed(string, "layers.knots_mm", v, 16, "Q47.16 mm")?;
    }
    let rad_per_count = TAU / f64::from(law.counts_per_rev);
    let step_rad = libm::exp2(f64::from(table.step_log2)) * rad_per_count;
    for k in 1..values.len() {
        let slope = (values[k] - values[k - 1]) / step_rad;
        for end in [k - 1, k] {
            let theta = table.knot_counts(end) as f64 * rad_per_count;
            let polynomial = polynomial_slope_f64(law, theta);
            let total = polynomial + slope;
            if polynomial > 0.0 && total <= 0.0 {
                return Err(StringLawCompileError::OutOfRange {
                    string,
                    field: "layers (payout slope, mm/rad)",
                    value: total,
                    min: 0.0,
                    max: f64::INFINITY,
                });
            }
        }
    }
    Ok(CompiledLayerTable {
        start_counts: table.start_counts,
        step_log2: table.step_log2,
        knots_q16: Knots::from_slice(&knots_q16[..values.len()]).unwrap_or(Knots::EMPTY_I64),
    })
}

impl CompiledStringLaw {
    /// Base winding law output (payout since home) at `counts`, Q31.32 mm,
    /// by Horner in `x = counts / 2^18`, saturating.
    #[inline]
    pub fn payout_q32(&self, counts: i32) -> i64 {
        let mut acc: i64 = 0;
        for k in (0..WINDING_ORDER).rev() {
            acc = acc.saturating_add(self.winding_q32[k]);
            acc = mul_i32_shr(acc, counts, COUNTS_SHIFT);
        }
        acc.saturating_add(q16_to_q32(self.layers.departure_q16(counts)))
    }

    /// Checks a compiled law read from a blob.
    pub fn validate(&self, string: usize) -> Result<(), StringLawCompileError> {
        if string >= STRINGS {
            return Err(StringLawCompileError::StringOutOfRange { string });
        }
        check_counts_per_rev(string, self.counts_per_rev)?;
        check_layer_step(string, self.layers.step_log2)?;
        let limit = (MAX_LAYER_MM * 65536.0) as i64;
        for &v in self.layers.knots_q16.as_slice() {
            if !(-limit..=limit).contains(&v) {
                return Err(StringLawCompileError::OutOfRange {
                    string,
                    field: "layers.knots_mm",
                    value: v as f64 / 65536.0,
                    min: -MAX_LAYER_MM,
                    max: MAX_LAYER_MM,
                });
            }
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------
// Compiled effects
// ---------------------------------------------------------------------------

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
    pub payout_q32: i64,
    /// `cos^2` of the inclination, Q0.16 ([`StringInputs::cos2_inclination_q16`]).
    pub cos2_inclination_q16: u16,
    /// The law's [`CompiledStringLaw::home_sag_q30`].
    pub home_sag_q30: i64,
    /// Sum of the active strings' commanded tensions, mN ([`total_tension_mn`]).
    pub total_tension_mn: u32,
    /// The payout's rate of change, Q17.14 mm/s
    /// ([`CompiledStringLaw::payout_rate_q14`] at the string's count rate;
    /// 0 at a rate of 0).
    pub payout_rate_q14: i32,
    /// The elevation of the string's chord, Q0.32 turns
    /// ([`StringInputs::guide_elevation_q32`]).
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
