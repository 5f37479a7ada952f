//! Arbitrary compiled parameters and inputs: the hot path never panics,
//! layouts, compiling arbitrary values.

use crate::model::{Effect, EffectTerm, Knots, StringLaw, LAYER_KNOTS, WINDING_ORDER};
use crate::string_law::*;
use crate::test_fixtures::cube_frame;
use proptest::prelude::*;

fn arb_effect() -> impl Strategy<Value = CompiledEffect> {
    let s = any::<u8>();
    prop_oneof![
        (s, any::<i64>()).prop_map(|(string, mm_q16)| CompiledEffect::Offset { string, mm_q16 }),
        (s, any::<i32>()).prop_map(|(string, relative_q30)| CompiledEffect::Scale {
            string,
            relative_q30
        }),
        (s, any::<u8>(), any::<i64>()).prop_map(|(string, power, coeff_q32)| {
            CompiledEffect::Winding {
                string,
                power,
                coeff_q32,
            }
        }),
        (s, any::<i64>(), any::<i64>(), any::<u32>(), any::<u64>()).prop_map(
            |(string, sin_q16, cos_q16, counts_per_rev, turns_per_count_q48)| {
                CompiledEffect::Eccentricity {
                    string,
                    sin_q16,
                    cos_q16,
                    counts_per_rev,
                    turns_per_count_q48,
                }
            }
        ),
        (s, any::<i64>()).prop_map(|(string, per_mn_q47)| CompiledEffect::Elasticity {
            string,
            per_mn_q47,
            mm_per_mn_q47: 0,
            home_strain_q31: 0,
            home_lead_q32: 0,
        }),
        (s, any::<i64>()).prop_map(|(string, half_width_q16)| CompiledEffect::Backlash {
            string,
            half_width_q16
        }),
        (s, any::<i64>()).prop_map(|(string, mm_per_ms_q48)| CompiledEffect::Drift {
            string,
            mm_per_ms_q48
        }),
        (s, any::<u32>(), any::<i64>()).prop_map(|(string, at_ms, mm_q16)| {
            CompiledEffect::Slip {
                string,
                at_ms,
                mm_q16,
            }
        }),
        (s, any::<i64>(), any::<i64>()).prop_map(|(string, coeff_q32, home_coeff_q32)| {
            CompiledEffect::Sag {
                string,
                coeff_q32,
                home_coeff_q32,
            }
        }),
        (s, any::<i32>()).prop_map(|(string, latency_q31)| CompiledEffect::Latency {
            string,
            latency_q31
        }),
        (s, any::<i64>())
            .prop_map(|(string, per_ms_q63)| CompiledEffect::Creep { string, per_ms_q63 }),
        (s, any::<i32>()).prop_map(|(string, radius_q24)| CompiledEffect::Guide {
            string,
            radius_q24,
            home_q20: [1 << 30; STRINGS],
        }),
    ]
}

fn arb_layers() -> impl Strategy<Value = CompiledLayerTable> {
    (
        any::<i32>(),
        any::<u8>(),
        proptest::collection::vec(any::<i64>(), 0..=LAYER_KNOTS),
    )
        .prop_map(|(start_counts, step_log2, knots)| CompiledLayerTable {
            start_counts,
            step_log2,
            knots_q16: Knots::from_slice(&knots).expect("at most LAYER_KNOTS"),
        })
}

fn arb_law() -> impl Strategy<Value = CompiledStringLaw> {
    (
        any::<i64>(),
        any::<u32>(),
        any::<[i64; WINDING_ORDER]>(),
        arb_layers(),
        any::<i64>(),
    )
        .prop_map(
            |(home_length_q16, counts_per_rev, winding_q32, layers, home_sag_q30)| {
                CompiledStringLaw {
                    home_length_q16,
                    counts_per_rev,
                    winding_q32,
                    home_sag_q30,
                    layers,
                }
            },
        )
}

fn arb_inputs() -> impl Strategy<Value = StringInputs> {
    (
        any::<[i32; STRINGS]>(),
        any::<[i8; STRINGS]>(),
        any::<[u16; STRINGS]>(),
        any::<u32>(),
        any::<[u16; STRINGS]>(),
        any::<[i32; STRINGS]>(),
        any::<[i32; STRINGS]>(),
    )
        .prop_map(
            |(
                counts,
                direction,
                tension_mn,
                time_ms,
                cos2_inclination_q16,
                count_rate_cps,
                guide_elevation_q32,
            )| {
                StringInputs {
                    counts,
                    direction,
                    tension_mn,
                    time_ms,
                    cos2_inclination_q16,
                    count_rate_cps,
                    guide_elevation_q32,
                }
            },
        )
}

proptest! {
    /// No input and no compiled parameter makes the hot path panic.
    #[test]
    fn string_lengths_never_panics(laws in proptest::array::uniform8(arb_law()),
                                   effects in proptest::collection::vec(arb_effect(), 0..40),
                                   inputs in arb_inputs()) {
        let a = string_lengths(StringLayout::ALL, &laws, &effects, &inputs);
        let b = string_lengths(StringLayout::ALL, &laws, &effects, &inputs);
        prop_assert_eq!(a, b);
    }

    /// A layout evaluates its active channels exactly as all 8 do and
    /// gives 0 on the others.
    #[test]
    fn inactive_channels_give_zero_and_active_ones_are_unchanged(
        laws in proptest::array::uniform8(arb_law()),
        effects in proptest::collection::vec(arb_effect(), 0..40),
        inputs in arb_inputs(),
        active in any::<u8>(),
        planar in any::<bool>(),
    ) {
        let all = string_lengths(StringLayout::ALL, &laws, &effects, &inputs);
        let some = string_lengths(StringLayout { active, planar }, &laws, &effects, &inputs);
        for i in 0..STRINGS {
            let want = if active >> i & 1 == 1 { all[i] } else { 0 };
            prop_assert_eq!(some[i], want, "channel {}", i);
        }
    }

    /// Compiling arbitrary f64 parameters either fails with a named field or
    /// gives a term that validates.
    #[test]
    fn compile_never_panics(v in any::<f64>(), w in any::<f64>(), string in any::<u8>(),
                            power in any::<u8>(), n in any::<u32>()) {
        let laws = [StringLaw::polynomial(n, [v, w, v, w]); STRINGS];
        let f = cube_frame([v, w, 0.0]);
        let _ = compile_string_law(&f, usize::from(string), &laws[0]);
        for effect in [
            Effect::Offset { mm: v },
            Effect::Scale { relative: v },
            Effect::Winding { power, mm_per_rad_pow: v },
            Effect::Eccentricity { sin_mm: v, cos_mm: w },
            Effect::Elasticity { per_newton: v },
            Effect::Backlash { half_width_mm: v },
            Effect::Drift { mm_per_s: v },
            Effect::Slip { at_s: v, mm: w },
            Effect::Sag {
                mm_at_1m_1n: v,
                home_mm_at_1m: w,
            },
            Effect::Latency { latency_s: v },
            Effect::Guide { radius_mm: v },
            Effect::Creep { per_s: v },
        ] {
            if let Ok(c) = compile_effect(&EffectTerm { string, effect }, &f, &laws) {
                prop_assert!(c.validate().is_ok());
            }
        }
    }
}
