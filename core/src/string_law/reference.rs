//! The f64 reference of the string law: the base winding law
//! ([`payout_f64`]), the context an effect term reads ([`EffectContext`],
//! [`StringHome`]), each effect's contribution and gradient
//! ([`Effect::contribution_f64`], [`Effect::gradient_f64`]) and the string
//! lengths they sum to ([`string_lengths_f64`]). What the host fits, and the
//! yardstick of the fixed-point error.

use core::f64::consts::TAU;

use super::{
    cos2_inclination_q16, creep_mm, creep_variable, guide_elevation_q32, guide_elevation_rad,
    guide_mm, guide_slope, latency::payout_rate_at_mm_s, sag_home_variable, sag_mm, sag_variable,
    stretch_mm, MAX_SAG_MM,
};
use crate::model::{Effect, EffectTerm, Frame, StringInputs, StringLaw, WINDING_ORDER};
use crate::STRINGS;

/// Pulley angle `theta = 2 pi counts / counts_per_rev` (rad). Not finite when
/// `counts_per_rev` is 0.
pub fn pulley_angle(law: &StringLaw, counts: i32) -> f64 {
    TAU * f64::from(counts) / f64::from(law.counts_per_rev)
}

/// Base winding law: length paid out since home (mm) at `counts`,
/// `sum_k winding_mm[k-1] theta^k` (Horner) plus the law's layer table
/// ([`LayerTable::departure_mm`](crate::model::LayerTable::departure_mm)).
pub fn payout_f64(law: &StringLaw, counts: i32) -> f64 {
    payout_at_f64(law, counts, pulley_angle(law, counts))
}

/// [`payout_f64`] at `counts` whose pulley angle `theta` ([`pulley_angle`])
/// the caller has already.
fn payout_at_f64(law: &StringLaw, counts: i32, theta: f64) -> f64 {
    polynomial_payout_at_f64(law, theta) + law.layers.departure_mm(counts)
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
    /// [`payout_rate_mm_s`](super::payout_rate_mm_s): what a latency term scales with.
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
        // The angle once: the payout and its rate read it too.
        let theta = pulley_angle(law, counts);
        Some(Self {
            theta,
            payout_mm: payout_at_f64(law, counts, theta),
            home_length_mm: home.length_mm,
            tension_n: f64::from(*inputs.tension_mn.get(string)?) / 1000.0,
            total_tension_n,
            direction: *inputs.direction.get(string)?,
            time_s: f64::from(inputs.time_ms) / 1000.0,
            cos2_inclination: f64::from(*inputs.cos2_inclination_q16.get(string)?) / 65536.0,
            home_cos2_inclination: home.cos2_inclination,
            payout_rate_mm_s: payout_rate_at_mm_s(law, theta, *inputs.count_rate_cps.get(string)?),
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
///
/// [`StringLayout::active`]: crate::model::StringLayout::active
pub fn total_tension_mn(active: u8, tension_mn: &[u16; STRINGS]) -> u32 {
    (0..STRINGS)
        .filter(|&i| active >> i & 1 == 1)
        .map(|i| u32::from(tension_mn[i]))
        .sum()
}

fn direction_sign(direction: i8) -> f64 {
    f64::from(direction.signum())
}

pub(super) fn powi_f64(x: f64, power: u8) -> f64 {
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
///
/// [`string_lengths`]: super::string_lengths
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
