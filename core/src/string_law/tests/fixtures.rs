//! What the tests share: a reproducible random source, realistic
//! calibrations and random inputs, and compiling a calibration whole.

use crate::model::{Effect, EffectTerm, Frame, Knots, StringLaw, LAYER_KNOTS};
use crate::string_law::*;
use crate::test_fixtures::cube_frame;
use core::f64::consts::TAU;

/// Deterministic xorshift64* so that the measured error is reproducible.
pub(super) struct Rng(pub(super) u64);
impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    /// Uniform in [lo, hi).
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        let u = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        lo + (hi - lo) * u
    }
    fn int(&mut self, lo: i64, hi: i64) -> i64 {
        lo + (self.next_u64() % ((hi - lo + 1) as u64)) as i64
    }
}

pub(super) fn compile_all(
    frame: &Frame<f64>,
    laws: &[StringLaw; STRINGS],
    effects: &[EffectTerm],
) -> ([CompiledStringLaw; STRINGS], Vec<CompiledEffect>) {
    let mut cl = [CompiledStringLaw::default(); STRINGS];
    for i in 0..STRINGS {
        cl[i] = compile_string_law(frame, i, &laws[i]).expect("law compiles");
    }
    let ce = effects
        .iter()
        .map(|e| compile_effect(e, frame, laws).expect("effect compiles"))
        .collect();
    (cl, ce)
}

/// A realistic calibration: anchors at the corners of a 2.2 m frame, every
/// effect family on some string with realistic amplitudes.
pub(super) fn realistic(rng: &mut Rng) -> (Frame<f64>, [StringLaw; STRINGS], Vec<EffectTerm>) {
    let f = cube_frame([
        rng.uniform(-300.0, 300.0),
        rng.uniform(-300.0, 300.0),
        rng.uniform(-300.0, 300.0),
    ]);
    let mut laws = [StringLaw::polynomial(1, [0.0; 4]); STRINGS];
    let mut effects = Vec::new();
    for (i, law) in laws.iter_mut().enumerate() {
        let n = rng.int(2000, 20000) as u32;
        let theta_max = TAU * 250_000.0 / f64::from(n);
        *law = StringLaw::polynomial(
            n,
            [
                rng.uniform(7.5, 20.0),
                rng.uniform(-0.03, -0.01),
                rng.uniform(-10.0, 10.0) / theta_max.powi(3),
                rng.uniform(-10.0, 10.0) / theta_max.powi(4),
            ],
        );
        let step_log2 = rng.int(10, 14) as u8;
        // Non-decreasing knots: the random polynomials above are not
        // all monotone, and a falling table on a barely rising one is
        // (rightly) refused by the compiler.
        let mut knots: Vec<f64> = (0..rng.int(0, LAYER_KNOTS as i64))
            .map(|_| rng.uniform(-3.0, 3.0))
            .collect();
        knots.sort_by(f64::total_cmp);
        law.layers = crate::model::LayerTable {
            start_counts: rng.int(-250_000, 0) as i32,
            step_log2,
            knots_mm: Knots::from_slice(&knots).expect("at most LAYER_KNOTS"),
        };
        let s = i as u8;
        let mut push = |effect| effects.push(EffectTerm { string: s, effect });
        push(Effect::Offset {
            mm: rng.uniform(-50.0, 50.0),
        });
        push(Effect::Scale {
            relative: rng.uniform(-0.05, 0.05),
        });
        let power = rng.int(5, 8) as u8;
        push(Effect::Winding {
            power,
            mm_per_rad_pow: rng.uniform(-5.0, 5.0) / theta_max.powi(i32::from(power)),
        });
        push(Effect::Eccentricity {
            sin_mm: rng.uniform(-2.0, 2.0),
            cos_mm: rng.uniform(-2.0, 2.0),
        });
        push(Effect::Elasticity {
            per_newton: rng.uniform(0.0, 2e-4),
        });
        push(Effect::Backlash {
            half_width_mm: rng.uniform(-3.0, 3.0),
        });
        push(Effect::Drift {
            mm_per_s: rng.uniform(-0.01, 0.01),
        });
        push(Effect::Slip {
            at_s: rng.uniform(0.0, 7200.0),
            mm: rng.uniform(-30.0, 30.0),
        });
        push(Effect::Sag {
            mm_at_1m_1n: rng.uniform(-5.0, 5.0),
            home_mm_at_1m: rng.uniform(-5.0, 5.0),
        });
        push(Effect::Latency {
            latency_s: rng.uniform(-0.05, 0.05),
        });
        push(Effect::Guide {
            radius_mm: rng.uniform(0.0, 15.0),
        });
    }
    // Terms shared by every string.
    effects.push(EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Drift {
            mm_per_s: rng.uniform(-0.01, 0.01),
        },
    });
    effects.push(EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Scale {
            relative: rng.uniform(-0.01, 0.01),
        },
    });
    effects.push(EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Stretch {
            per_newton: rng.uniform(0.0, 2e-4),
            mm_per_newton: rng.uniform(0.0, 0.03),
            home_tension_n: rng.uniform(0.5, 2.0),
        },
    });
    effects.push(EffectTerm {
        string: EVERY_STRING,
        effect: Effect::FrameFlex {
            mm_per_newton: rng.uniform(-0.5, 0.5),
            home_mm: rng.uniform(-5.0, 5.0),
        },
    });
    effects.push(EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Latency {
            latency_s: rng.uniform(-0.02, 0.02),
        },
    });
    effects.push(EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Guide {
            radius_mm: rng.uniform(-5.0, 15.0),
        },
    });
    push_creeps(rng, &mut effects);
    push_stretches(rng, &mut effects);
    (f, laws, effects)
}

/// A stretch on each string, each its own stiffness, lead and home
/// tension (the loop's stretches of each string, decision record 0061),
/// drawn after every other term so that the others' draws are as they
/// were; home tensions -5 to 5 N, as those terms' free home tensions reach.
fn push_stretches(rng: &mut Rng, effects: &mut Vec<EffectTerm>) {
    for i in 0..STRINGS {
        effects.push(EffectTerm {
            string: i as u8,
            effect: Effect::Stretch {
                per_newton: rng.uniform(0.0, 2e-4),
                mm_per_newton: rng.uniform(0.0, 0.03),
                home_tension_n: rng.uniform(-5.0, 5.0),
            },
        });
    }
}

/// Creep terms, drawn after every other term so that the others' draws
/// are as they were: one string's on each and a shared one, up to 7,200
/// ppm/h (24 times the independent simulator's thermal creep).
fn push_creeps(rng: &mut Rng, effects: &mut Vec<EffectTerm>) {
    for i in 0..STRINGS {
        effects.push(EffectTerm {
            string: i as u8,
            effect: Effect::Creep {
                per_s: rng.uniform(-2e-6, 2e-6),
            },
        });
    }
    effects.push(EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Creep {
            per_s: rng.uniform(-2e-6, 2e-6),
        },
    });
}

pub(super) fn random_inputs(rng: &mut Rng) -> StringInputs {
    let mut inputs = StringInputs::default();
    for i in 0..STRINGS {
        inputs.counts[i] = rng.int(-250_000, 250_000) as i32;
        inputs.direction[i] = rng.int(-1, 1) as i8;
        inputs.tension_mn[i] = rng.int(0, 20_000) as u16;
        inputs.cos2_inclination_q16[i] = rng.int(0, 65535) as u16;
        // Up to 0.5 to 12 m/s of string (the pulleys' 2.4e-3 to 6.3e-2
        // mm per count).
        inputs.count_rate_cps[i] = rng.int(-200_000, 200_000) as i32;
        // Any elevation, the poles and beyond them (clamped) included.
        inputs.guide_elevation_q32[i] = rng.int(-(1 << 30) - 1000, (1 << 30) + 1000) as i32;
    }
    inputs.time_ms = rng.int(0, 7_200_000) as u32;
    inputs
}
