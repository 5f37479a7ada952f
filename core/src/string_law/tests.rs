use super::*;
use crate::model::{Effect, EffectTerm, Frame, Knots, StringLaw, LAYER_KNOTS, WINDING_ORDER};
use crate::test_fixtures::cube_frame;
use core::f64::consts::TAU;
use proptest::prelude::*;

/// Deterministic xorshift64* so that the measured error is reproducible.
struct Rng(u64);
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

fn compile_all(
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

#[test]
fn sine_table_accuracy() {
    let mut max = 0.0f64;
    let mut phase: u32 = 0;
    for _ in 0..200_000 {
        let exact = libm::sin(TAU * f64::from(phase) / 4_294_967_296.0);
        let got = f64::from(sin_q30(phase)) / f64::from(1u32 << 30);
        max = max.max((got - exact).abs());
        phase = phase.wrapping_add(21_474_853); // ~1/200000 turn, not a divisor
    }
    for p in [0u32, 1 << 30, 2 << 30, 3 << 30, u32::MAX] {
        let exact = libm::sin(TAU * f64::from(p) / 4_294_967_296.0);
        max = max.max((f64::from(sin_q30(p)) / f64::from(1u32 << 30) - exact).abs());
    }
    assert!(max < 1.3e-6, "sine table error {max}");
    assert_eq!(sin_q30(1 << 30), 1 << 30);
    assert_eq!(sin_q30(0), 0);
}

proptest! {
    #[test]
    fn mul_i32_shr_matches_i128(a in any::<i64>(), b in any::<i32>(), s in 1u32..=32) {
        let exact = (i128::from(a) * i128::from(b) + (1i128 << (s - 1))) >> s;
        let want = exact.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
        prop_assert_eq!(mul_i32_shr(a, b, s), want);
    }

    #[test]
    fn mul_u32_shr_matches_i128(a in any::<i64>(), b in any::<u32>(), s in 1u32..=32) {
        let exact = (i128::from(a) * i128::from(b) + (1i128 << (s - 1))) >> s;
        let want = exact.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
        prop_assert_eq!(mul_u32_shr(a, b, s), want);
    }
}

#[test]
fn quadratic_law_at_known_points() {
    // r = 10 mm, 4096 counts/rev, d^2/(4 pi) = 0.02: one turn pays out
    // 2 pi 10 - 0.02 (2 pi)^2 mm.
    let law = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    let want = TAU * 10.0 - 0.02 * TAU * TAU;
    assert!((payout_f64(&law, 4096) - want).abs() < 1e-12);
    let f = cube_frame([0.0; 3]);
    let c = compile_string_law(&f, 0, &law).unwrap();
    let got = c.payout_q32(4096) as f64 / 4_294_967_296.0;
    assert!((got - want).abs() < 1e-8, "{got} vs {want}");
    assert_eq!(
        c.home_length_q16,
        (libm::sqrt(3.0) * 1100.0 * 65536.0).round() as i64
    );
}

/// A term shared by every string adds its contribution to each active
/// string with that string's inputs, as one term per string would; the
/// families that need one string's law cannot be shared.
#[test]
fn a_shared_term_is_one_term_on_every_string() {
    let f = cube_frame([10.0, -20.0, 30.0]);
    let laws = [StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]); STRINGS];
    let shared = [
        EffectTerm {
            string: EVERY_STRING,
            effect: Effect::Drift { mm_per_s: 2e-4 },
        },
        EffectTerm {
            string: EVERY_STRING,
            effect: Effect::Scale { relative: 0.003 },
        },
    ];
    let each: Vec<EffectTerm> = shared
        .iter()
        .flat_map(|t| (0..STRINGS as u8).map(move |s| EffectTerm { string: s, ..*t }))
        .collect();
    let mut rng = Rng(7);
    let (cl, ce_shared) = compile_all(&f, &laws, &shared);
    let (_, ce_each) = compile_all(&f, &laws, &each);
    for _ in 0..50 {
        let inputs = random_inputs(&mut rng);
        assert_eq!(
            string_lengths_f64(&f, &laws, &shared, &inputs),
            string_lengths_f64(&f, &laws, &each, &inputs)
        );
        assert_eq!(
            string_lengths(StringLayout::ALL, &cl, &ce_shared, &inputs),
            string_lengths(StringLayout::ALL, &cl, &ce_each, &inputs)
        );
        // Inactive channels stay 0.
        let four = StringLayout::first(4, false);
        let got = string_lengths(four, &cl, &ce_shared, &inputs);
        assert!(got[4..].iter().all(|&v| v == 0));
    }
    for c in &ce_shared {
        c.validate().expect("a shared drift or scale is valid");
    }
    for effect in [
        Effect::Winding {
            power: 3,
            mm_per_rad_pow: 1e-6,
        },
        Effect::Eccentricity {
            sin_mm: 0.1,
            cos_mm: 0.0,
        },
    ] {
        let term = EffectTerm {
            string: EVERY_STRING,
            effect,
        };
        assert_eq!(
            compile_effect(&term, &f, &laws),
            Err(StringLawCompileError::StringOutOfRange { string: 255 })
        );
    }
}

fn layered(start_counts: i32, step_log2: u8, knots: &[f64]) -> StringLaw {
    let mut law = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    law.layers = crate::model::LayerTable {
        start_counts,
        step_log2,
        knots_mm: Knots::from_slice(knots).expect("at most LAYER_KNOTS"),
    };
    law
}

/// The table interpolates between its knots and holds the end values
/// outside them, in f64 and in fixed point alike.
#[test]
fn layer_table_interpolates_and_holds_its_ends() {
    let law = layered(-1000, 10, &[1.0, -1.0, 2.0]); // knots at -1000, 24, 1048
    let t = &law.layers;
    let cases = [
        (i32::MIN, 1.0),
        (-5000, 1.0),
        (-1000, 1.0),
        (-488, 0.0),
        (24, -1.0),
        (536, 0.5),
        (1048, 2.0),
        (1049, 2.0),
        (i32::MAX, 2.0),
    ];
    let f = cube_frame([0.0; 3]);
    let c = compile_string_law(&f, 0, &law).expect("compiles");
    for (counts, want) in cases {
        assert!((t.departure_mm(counts) - want).abs() < 1e-12, "{counts}");
        let got = c.layers.departure_q16(counts) as f64 / 65536.0;
        assert!((got - want).abs() < 2e-5, "{counts}: fixed {got}");
        let whole = polynomial_payout_f64(&law, counts) + want;
        assert!((payout_f64(&law, counts) - whole).abs() < 1e-9);
    }
    // No table: nothing added, and the compiled law is the polynomial's.
    let plain = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    assert_eq!(plain.layers.departure_mm(12345), 0.0);
    let cp = compile_string_law(&f, 0, &plain).expect("compiles");
    assert_eq!(cp.layers, CompiledLayerTable::NONE);
    assert_eq!(
        cp.payout_q32(5000) + q16_to_q32(c.layers.departure_q16(5000)),
        c.payout_q32(5000)
    );
}

#[test]
fn layer_table_compile_errors_name_the_field() {
    let f = cube_frame([0.0; 3]);
    let err = compile_string_law(&f, 3, &layered(0, 31, &[0.0, 1.0])).unwrap_err();
    assert!(
        matches!(
            err,
            StringLawCompileError::OutOfRange {
                string: 3,
                field: "layers.step_log2",
                ..
            }
        ),
        "{err}"
    );
    let err = compile_string_law(&f, 2, &layered(0, 10, &[0.0, f64::NAN])).unwrap_err();
    assert_eq!(
        err,
        StringLawCompileError::NotFinite {
            string: 2,
            field: "layers.knots_mm"
        }
    );
    let err = compile_string_law(&f, 1, &layered(0, 10, &[0.0, 150.0])).unwrap_err();
    assert!(
        matches!(
            err,
            StringLawCompileError::OutOfRange {
                string: 1,
                field: "layers.knots_mm",
                ..
            }
        ),
        "{err}"
    );
    // 1024 counts = 1.57 rad; the polynomial rises by ~15.7 mm there: a
    // table falling by 20 mm over it would make the payout fall.
    let err = compile_string_law(&f, 0, &layered(0, 10, &[0.0, -20.0])).unwrap_err();
    assert!(
        matches!(
            err,
            StringLawCompileError::OutOfRange {
                string: 0,
                field: "layers (payout slope, mm/rad)",
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("layers"), "{err}");
    compile_string_law(&f, 0, &layered(0, 10, &[0.0, -10.0])).expect("still rising");
    // A compiled table read from a blob is checked too.
    let mut c = compile_string_law(&f, 0, &layered(0, 10, &[0.0, 1.0])).expect("compiles");
    c.validate(0).expect("valid");
    c.layers.knots_q16.as_mut_slice()[1] = 101 << 16;
    assert!(matches!(
        c.validate(0),
        Err(StringLawCompileError::OutOfRange {
            field: "layers.knots_mm",
            ..
        })
    ));
    c.layers.knots_q16.as_mut_slice()[1] = 0;
    c.layers.step_log2 = 40;
    assert!(matches!(
        c.validate(0),
        Err(StringLawCompileError::OutOfRange {
            field: "layers.step_log2",
            ..
        })
    ));
}

/// A law written before layer tables existed still reads (no table); a
/// table round-trips through JSON and postcard; more than LAYER_KNOTS
/// knots is an error, not a truncation.
#[test]
fn layer_tables_serialize_and_old_laws_still_read() {
    let old = r#"{"counts_per_rev":4096,"winding_mm":[10.0,-0.02,0.0,0.0]}"#;
    let law: StringLaw = serde_json::from_str(old).expect("old law reads");
    assert!(law.layers.is_empty());
    let law = layered(-300, 12, &[0.5, -0.25, 1.0]);
    let json = serde_json::to_string(&law).expect("serializes");
    assert!(json.contains("[0.5,-0.25,1.0]"), "{json}");
    assert_eq!(
        serde_json::from_str::<StringLaw>(&json).expect("reads"),
        law
    );
    let f = cube_frame([0.0; 3]);
    let c = compile_string_law(&f, 0, &law).expect("compiles");
    let bytes = postcard::to_allocvec(&c).expect("postcard");
    assert_eq!(
        postcard::from_bytes::<CompiledStringLaw>(&bytes).expect("reads"),
        c
    );
    let too_many = format!(
        r#"{{"start_counts":0,"step_log2":10,"knots_mm":[{}]}}"#,
        vec!["0.0"; LAYER_KNOTS + 1].join(",")
    );
    let err = serde_json::from_str::<crate::model::LayerTable>(&too_many).unwrap_err();
    assert!(err.to_string().contains("at most 32"), "{err}");
}

/// A realistic calibration: anchors at the corners of a 2.2 m frame, every
/// effect family on some string with realistic amplitudes.
fn realistic(rng: &mut Rng) -> (Frame<f64>, [StringLaw; STRINGS], Vec<EffectTerm>) {
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

fn random_inputs(rng: &mut Rng) -> StringInputs {
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

/// Largest |fixed - f64| (mm) over `sets` calibrations x `per_set` inputs,
/// keeping the effect terms for which `keep` holds.
fn measure(seed: u64, sets: usize, per_set: usize, keep: fn(&Effect) -> bool) -> f64 {
    let mut rng = Rng(seed);
    let mut max_err = 0.0f64;
    for _ in 0..sets {
        let (f, laws, mut effects) = realistic(&mut rng);
        effects.retain(|t| keep(&t.effect));
        let (cl, ce) = compile_all(&f, &laws, &effects);
        for k in 0..per_set {
            let mut inputs = random_inputs(&mut rng);
            if k < 4 {
                // The ends of the range, both ways.
                let c = [250_000, -250_000, 0, 1][k];
                inputs.counts = [c; STRINGS];
            }
            let want = string_lengths_f64(&f, &laws, &effects, &inputs);
            let got = string_lengths(StringLayout::ALL, &cl, &ce, &inputs);
            for i in 0..STRINGS {
                let err = (got[i] as f64 / 65536.0 - want[i]).abs();
                max_err = max_err.max(err);
            }
        }
    }
    max_err
}

/// The error budget: fixed point against the f64 reference over counts in
/// +-250,000 with every effect family at realistic amplitudes. Measured
/// maximum recorded in docs/fixed-point.md ("String law"); run with
/// `cargo test -p spidar-core --release fixed_point_error_budget -- --nocapture`.
#[test]
fn fixed_point_error_budget() {
    let max_err = measure(0x5EED_0001, 400, 500, |_| true);
    println!("string law: max |fixed - f64| = {max_err:.3e} mm (400 calibrations x 500 inputs x 8 strings)");
    type Keep = fn(&Effect) -> bool;
    let families: [(&str, Keep); 15] = [
        ("no effect", |_| false),
        ("offset", |e| matches!(e, Effect::Offset { .. })),
        ("scale", |e| matches!(e, Effect::Scale { .. })),
        ("winding", |e| matches!(e, Effect::Winding { .. })),
        ("eccentricity", |e| matches!(e, Effect::Eccentricity { .. })),
        ("elasticity", |e| matches!(e, Effect::Elasticity { .. })),
        ("backlash", |e| matches!(e, Effect::Backlash { .. })),
        ("drift", |e| matches!(e, Effect::Drift { .. })),
        ("slip", |e| matches!(e, Effect::Slip { .. })),
        ("sag", |e| matches!(e, Effect::Sag { .. })),
        ("stretch", |e| matches!(e, Effect::Stretch { .. })),
        ("frame flex", |e| matches!(e, Effect::FrameFlex { .. })),
        ("latency", |e| matches!(e, Effect::Latency { .. })),
        ("guide", |e| matches!(e, Effect::Guide { .. })),
        ("creep", |e| matches!(e, Effect::Creep { .. })),
    ];
    for (name, keep) in families {
        let e = measure(0x5EED_0002, 100, 200, keep);
        println!("  base law + {name}: {e:.3e} mm");
        assert!(e < 1e-4, "{name}: {e} mm");
    }
    assert!(max_err < 1e-4, "fixed-point error {max_err} mm");
}

#[test]
fn f64_gradients_match_finite_differences() {
    let mut rng = Rng(7);
    let (f, laws, effects) = realistic(&mut rng);
    let inputs = random_inputs(&mut rng);
    for term in effects.iter().filter(|t| t.string != EVERY_STRING) {
        let ctx = EffectContext::for_string(&f, &laws, &inputs, usize::from(term.string)).unwrap();
        let g = term.effect.gradient_f64(&ctx);
        let p = term.effect.parameters();
        assert_eq!(g.len(), p.len());
        for j in 0..p.len() {
            let h = 1e-6 * p[j].abs().max(1e-9);
            let mut plus = p.clone();
            plus[j] += h;
            let mut minus = p.clone();
            minus[j] -= h;
            let e_plus = term.effect.with_parameters(&plus).unwrap();
            let e_minus = term.effect.with_parameters(&minus).unwrap();
            let fd = (e_plus.contribution_f64(&ctx) - e_minus.contribution_f64(&ctx)) / (2.0 * h);
            assert!(
                (fd - g[j]).abs() <= 1e-6 * g[j].abs().max(1.0),
                "{:?} param {j}: fd {fd} vs {}",
                term.effect,
                g[j]
            );
        }
        assert!(term.effect.with_parameters(&[1.0, 2.0, 3.0, 4.0]).is_none());
    }
}

#[test]
fn string_law_compile_errors_name_the_field() {
    let f = cube_frame([0.0; 3]);
    let law = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    assert_eq!(
        compile_string_law(&f, 8, &law),
        Err(StringLawCompileError::StringOutOfRange { string: 8 })
    );
    let bad = StringLaw {
        counts_per_rev: 0,
        ..law
    };
    assert!(matches!(
        compile_string_law(&f, 1, &bad),
        Err(StringLawCompileError::OutOfRange {
            string: 1,
            field: "counts_per_rev",
            ..
        })
    ));
    let bad = StringLaw {
        winding_mm: [10.0, f64::NAN, 0.0, 0.0],
        ..law
    };
    assert_eq!(
        compile_string_law(&f, 2, &bad),
        Err(StringLawCompileError::NotFinite {
            string: 2,
            field: "winding_mm[1]"
        })
    );
    let bad = StringLaw {
        winding_mm: [10.0, 0.0, 0.0, 1e6],
        ..law
    };
    assert!(matches!(
        compile_string_law(&f, 3, &bad),
        Err(StringLawCompileError::DoesNotFit {
            string: 3,
            field: "winding_mm[3]",
            ..
        })
    ));
    let mut nf = f;
    nf.home[1] = f64::INFINITY;
    assert_eq!(
        compile_string_law(&nf, 0, &law),
        Err(StringLawCompileError::NotFinite {
            string: 0,
            field: "home"
        })
    );
    let mut nf = f;
    nf.anchors[5][2] = f64::NAN;
    assert_eq!(
        compile_string_law(&nf, 5, &law),
        Err(StringLawCompileError::NotFinite {
            string: 5,
            field: "anchor"
        })
    );

    let msg = format!(
        "{}",
        StringLawCompileError::NotFinite {
            string: 2,
            field: "winding_mm[1]"
        }
    );
    assert_eq!(msg, "string 2: winding_mm[1] is not finite");
}

/// Which kind of compile error, and for which field.
fn kind_and_field(e: StringLawCompileError) -> (&'static str, &'static str) {
    match e {
        StringLawCompileError::StringOutOfRange { .. } => ("StringOutOfRange", "string"),
        StringLawCompileError::NotFinite { field, .. } => ("NotFinite", field),
        StringLawCompileError::DoesNotFit { field, .. } => ("DoesNotFit", field),
        StringLawCompileError::OutOfRange { field, .. } => ("OutOfRange", field),
    }
}

#[test]
fn effect_compile_errors_name_the_field() {
    let f = cube_frame([0.0; 3]);
    let law = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    let laws = [law; STRINGS];
    let term = |string, effect| EffectTerm { string, effect };
    assert_eq!(
        compile_effect(&term(8, Effect::Offset { mm: 1.0 }), &f, &laws),
        Err(StringLawCompileError::StringOutOfRange { string: 8 })
    );
    let sag = |mm_at_1m_1n, home_mm_at_1m| Effect::Sag {
        mm_at_1m_1n,
        home_mm_at_1m,
    };
    let cases = [
        (Effect::Scale { relative: 2.5 }, "DoesNotFit", "relative"),
        (
            Effect::Winding {
                power: 0,
                mm_per_rad_pow: 1.0,
            },
            "OutOfRange",
            "power",
        ),
        (
            Effect::Elasticity { per_newton: 0.1 },
            "DoesNotFit",
            "per_newton",
        ),
        (
            Effect::Slip {
                at_s: -1.0,
                mm: 1.0,
            },
            "OutOfRange",
            "at_s",
        ),
        (
            Effect::Slip {
                at_s: 1.0,
                mm: f64::NAN,
            },
            "NotFinite",
            "mm",
        ),
        (sag(101.0, 1.0), "OutOfRange", "mm_at_1m_1n"),
        (sag(1.6, -101.0), "OutOfRange", "home_mm_at_1m"),
        (sag(f64::NAN, 0.0), "NotFinite", "mm_at_1m_1n"),
        (Effect::Drift { mm_per_s: 1e30 }, "DoesNotFit", "mm_per_s"),
        (
            Effect::Latency { latency_s: 0.3 },
            "OutOfRange",
            "latency_s",
        ),
        (
            Effect::Latency {
                latency_s: f64::INFINITY,
            },
            "NotFinite",
            "latency_s",
        ),
        (Effect::Guide { radius_mm: 51.0 }, "OutOfRange", "radius_mm"),
        (Effect::Creep { per_s: 2e-5 }, "OutOfRange", "per_s"),
        (Effect::Creep { per_s: f64::NAN }, "NotFinite", "per_s"),
        (
            Effect::Guide {
                radius_mm: f64::NAN,
            },
            "NotFinite",
            "radius_mm",
        ),
    ];
    for (effect, kind, field) in cases {
        let got = compile_effect(&term(0, effect), &f, &laws).map(|_| ());
        assert_eq!(
            got.map_err(kind_and_field),
            Err((kind, field)),
            "{effect:?}"
        );
    }
    let zero = [StringLaw {
        counts_per_rev: 0,
        ..law
    }; STRINGS];
    let eccentricity = Effect::Eccentricity {
        sin_mm: 1.0,
        cos_mm: 0.0,
    };
    assert_eq!(
        compile_effect(&term(0, eccentricity), &f, &zero)
            .map(|_| ())
            .map_err(kind_and_field),
        Err(("OutOfRange", "counts_per_rev"))
    );
}

#[test]
fn compiled_effects_validate() {
    let mut rng = Rng(11);
    let (f, laws, effects) = realistic(&mut rng);
    for e in &effects {
        compile_effect(e, &f, &laws).unwrap().validate().unwrap();
    }
    assert!(CompiledEffect::Offset {
        string: 9,
        mm_q16: 0
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Winding {
        string: 0,
        power: 9,
        coeff_q32: 0
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Eccentricity {
        string: 0,
        sin_q16: 0,
        cos_q16: 0,
        counts_per_rev: 4096,
        turns_per_count_q48: 3,
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Latency {
        string: EVERY_STRING,
        latency_q31: i32::MAX,
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Guide {
        string: EVERY_STRING,
        radius_q24: i32::MIN,
        home_q20: [0; STRINGS],
    }
    .validate()
    .is_err());
}

/// A latency term adds `tau` times the payout's rate at the string's count
/// rate, the same in both paths: nothing at rest, the string's motion over
/// `tau` when it moves (one string's term or one shared by every string,
/// each string at its own law's slope), and its sign with the motion's.
#[test]
fn a_latency_adds_the_motion_over_its_delay_in_both_paths() {
    let f = cube_frame([30.0, -20.0, 10.0]);
    let mut laws = [StringLaw::polynomial(4096, [12.0, -0.004, 0.0, 0.0]); STRINGS];
    laws[5] = StringLaw::polynomial(8192, [9.0, -0.002, 1e-6, 0.0]);
    let tau = 0.006;
    for string in [3, 5, EVERY_STRING] {
        let terms = [EffectTerm {
            string,
            effect: Effect::Latency { latency_s: tau },
        }];
        let (cl, ce) = compile_all(&f, &laws, &terms);
        for (counts, rate) in [(0, 0), (20_000, 0), (20_000, 30_000), (-50_000, -65_000)] {
            let inputs = StringInputs {
                counts: [counts; STRINGS],
                count_rate_cps: [rate; STRINGS],
                ..StringInputs::default()
            };
            let bare = string_lengths_f64(&f, &laws, &[], &inputs);
            let want = string_lengths_f64(&f, &laws, &terms, &inputs);
            let got = string_lengths(StringLayout::ALL, &cl, &ce, &inputs);
            for i in 0..STRINGS {
                let law = &laws[i];
                let theta = pulley_angle(law, counts);
                let mm_per_count =
                    polynomial_slope_f64(law, theta) * TAU / f64::from(law.counts_per_rev);
                let moved = if string == EVERY_STRING || usize::from(string) == i {
                    tau * mm_per_count * f64::from(rate)
                } else {
                    0.0
                };
                assert!((want[i] - bare[i] - moved).abs() < 1e-9, "string {i}");
                assert!(
                    (got[i] as f64 / 65536.0 - want[i]).abs() < 1e-4,
                    "string {i}"
                );
                if rate == 0 {
                    assert_eq!(want[i], bare[i]);
                } else if moved != 0.0 {
                    // Paying out: the late reading is short, the term adds.
                    assert_eq!(moved > 0.0, rate > 0, "string {i}");
                }
            }
        }
    }
}

/// A creep term adds `per_s t` of the string's whole length, the same in
/// both paths: nothing at the home capture, each string's own length times
/// the strain since (one string's term or one shared), its sign with the
/// rate's; at the largest rate the fixed point follows f64 over 10 h (the
/// strain 0.36, within Q0.31) and saturates, without overflow, past 27 h.
/// The term's own error (beside the base law's, both rounded to Q47.16)
/// is printed (`docs/fixed-point.md`, "Creep"):
/// `cargo test -p spidar-core --release creep_ -- --nocapture`.
#[test]
fn a_creep_adds_its_strain_of_the_whole_length_in_both_paths() {
    let f = cube_frame([30.0, -20.0, 10.0]);
    let laws = [StringLaw::polynomial(4096, [12.0, -0.004, 0.0, 0.0]); STRINGS];
    let mut worst = 0.0f64;
    for (string, per_s) in [
        (3, 8.3e-8),
        (EVERY_STRING, -8.3e-8),
        (5, MAX_CREEP_PER_S),
        (EVERY_STRING, -MAX_CREEP_PER_S),
    ] {
        let terms = [EffectTerm {
            string,
            effect: Effect::Creep { per_s },
        }];
        let (cl, ce) = compile_all(&f, &laws, &terms);
        for (counts, time_ms) in [
            (20_000, 0),
            (0, 60_000),
            (20_000, 4_800_000),
            (-50_000, 36_000_000),
            (90_000, 36_000_000),
        ] {
            let inputs = StringInputs {
                counts: [counts; STRINGS],
                time_ms,
                ..StringInputs::default()
            };
            let bare = string_lengths_f64(&f, &laws, &[], &inputs);
            let want = string_lengths_f64(&f, &laws, &terms, &inputs);
            let got = string_lengths(StringLayout::ALL, &cl, &ce, &inputs);
            let got_bare = string_lengths(StringLayout::ALL, &cl, &[], &inputs);
            for i in 0..STRINGS {
                let crept = if string == EVERY_STRING || usize::from(string) == i {
                    per_s * f64::from(time_ms) / 1000.0 * bare[i]
                } else {
                    0.0
                };
                assert!((want[i] - bare[i] - crept).abs() < 1e-9, "string {i}");
                // The term's own error, beside the base law's.
                let err = ((got[i] - got_bare[i]) as f64 / 65536.0 - (want[i] - bare[i])).abs();
                assert!(err < 2e-5, "string {i} at {time_ms} ms: {err} mm");
                worst = worst.max(err);
                if time_ms == 0 {
                    assert_eq!(want[i], bare[i]);
                } else if crept != 0.0 {
                    assert_eq!(crept > 0.0, per_s > 0.0, "string {i}");
                }
            }
        }
    }
    println!(
        "creep: the term's max |fixed - f64| = {worst:.3e} mm (up to 10 h, up to MAX_CREEP_PER_S)"
    );
    // Past 27 h at the largest rate the strain saturates at -1 (the string
    // is no string), and 49 days of a rate from another tool do not overflow.
    let at = |per_ms_q63: i64, time_ms: u32| {
        let inputs = StringInputs {
            counts: [0; STRINGS],
            time_ms,
            ..StringInputs::default()
        };
        let (cl, _) = compile_all(&f, &laws, &[]);
        let ce = [CompiledEffect::Creep {
            string: 0,
            per_ms_q63,
        }];
        string_lengths(StringLayout::ALL, &cl, &ce, &inputs)[0]
    };
    assert_eq!(at(i64::MIN, u32::MAX), 0);
    assert!((at(i64::MAX, u32::MAX) - 2 * at(0, 0)).abs() <= 1);
}

#[test]
fn inclination_is_level_plumb_or_between_and_never_panics() {
    let a = [100.0f32, -200.0, 300.0];
    let at = |p: [f32; 3]| cos2_inclination_q16(&a, &p);
    assert_eq!(at([1100.0, -200.0, 300.0]), u16::MAX); // level
    assert_eq!(at([100.0, -200.0, -700.0]), 0); // plumb
    assert_eq!(at([1100.0, -200.0, 1300.0]), 32768); // 45 degrees
    assert_eq!(at(a), 0); // no chord
    assert_eq!(at([f32::NAN, 0.0, 0.0]), 0);
    assert_eq!(at([f32::INFINITY, 0.0, 0.0]), 0);
    // f32 on the device, f64 on the host: the same Q0.16 away from ties.
    let p64 = [612.5f64, 48.25, -333.0];
    let p32 = p64.map(|x| x as f32);
    let a64 = a.map(f64::from);
    assert_eq!(
        cos2_inclination_q16(&a64, &p64),
        cos2_inclination_q16(&a, &p32)
    );
}

#[test]
fn sag_scales_with_the_inclination_in_both_paths() {
    let laws = [StringLaw::polynomial(4096, [10.0, 0.0, 0.0, 0.0]); STRINGS];
    let f = cube_frame([0.0; 3]);
    let terms = [EffectTerm {
        string: 2,
        effect: Effect::Sag {
            mm_at_1m_1n: 1.6,
            home_mm_at_1m: 0.0,
        },
    }];
    let (cl, ce) = compile_all(&f, &laws, &terms);
    let mut inputs = StringInputs {
        tension_mn: [1000; STRINGS],
        ..StringInputs::default()
    };
    inputs.counts[2] = 40_000;
    let base = string_lengths_f64(&f, &laws, &[], &inputs)[2];
    let mut sags = [0.0; 3];
    for (k, cos2) in [0u16, 32768, u16::MAX].into_iter().enumerate() {
        inputs.cos2_inclination_q16[2] = cos2;
        let want = string_lengths_f64(&f, &laws, &terms, &inputs)[2];
        let got = string_lengths(StringLayout::ALL, &cl, &ce, &inputs)[2] as f64 / 65536.0;
        assert!((want - got).abs() < 1e-4, "cos2 {cos2}: {want} vs {got}");
        sags[k] = want - base;
    }
    assert_eq!(sags[0], 0.0, "a plumb string does not sag");
    assert!(
        sags[2] < -1.0,
        "the chord is shorter than the string: {sags:?}"
    );
    assert!(
        (sags[1] - sags[2] / 2.0).abs() < 1e-4 * sags[2].abs(),
        "{sags:?}"
    );
}

#[test]
fn a_sag_term_is_zero_at_the_home_capture() {
    // The counts start from the string as it sagged at home (tension
    // T_home): with home_mm_at_1m = mm_at_1m_1n / T_home^2 the term
    // vanishes there, in both paths, and is the sag's change elsewhere.
    let laws = [StringLaw::polynomial(4096, [10.0, 0.0, 0.0, 0.0]); STRINGS];
    let f = cube_frame([100.0, -50.0, 200.0]);
    let t_home = 1.1;
    let terms = [EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Sag {
            mm_at_1m_1n: 1.6,
            home_mm_at_1m: 1.6 / (t_home * t_home),
        },
    }];
    let (cl, ce) = compile_all(&f, &laws, &terms);
    let at_home = StringInputs {
        tension_mn: [1100; STRINGS],
        cos2_inclination_q16: cos2_inclinations(&f.anchors, &f.home),
        ..StringInputs::default()
    };
    let want = string_lengths_f64(&f, &laws, &terms, &at_home);
    let bare = string_lengths_f64(&f, &laws, &[], &at_home);
    let got = string_lengths(StringLayout::ALL, &cl, &ce, &at_home);
    for i in 0..STRINGS {
        assert!(
            (want[i] - bare[i]).abs() < 1e-9,
            "string {i}: {} vs {}",
            want[i],
            bare[i]
        );
        assert!(
            (got[i] as f64 / 65536.0 - bare[i]).abs() < 1e-4,
            "string {i}"
        );
    }
    // Taut (4x the home tension) at home: the string sags less than at
    // the capture, so the chord is longer than the counts say.
    let taut = StringInputs {
        tension_mn: [4400; STRINGS],
        ..at_home
    };
    let want = string_lengths_f64(&f, &laws, &terms, &taut);
    let got = string_lengths(StringLayout::ALL, &cl, &ce, &taut);
    for i in 0..STRINGS {
        assert!(want[i] - bare[i] > 0.1, "string {i}: {}", want[i] - bare[i]);
        assert!(
            (got[i] as f64 / 65536.0 - want[i]).abs() < 1e-4,
            "string {i}"
        );
    }
}

#[test]
fn a_stretch_is_zero_at_the_home_capture_and_grows_with_the_tension() {
    // The counts start from the strings as they stretched at home
    // (tension T_home): the term vanishes there in both paths, and a
    // string pulled harder is longer by its whole length's strain.
    let laws = [StringLaw::polynomial(4096, [10.0, 0.0, 0.0, 0.0]); STRINGS];
    let f = cube_frame([100.0, -50.0, 200.0]);
    let (k, m, t_home) = (5e-5, 0.02, 1.1);
    let terms = [EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Stretch {
            per_newton: k,
            mm_per_newton: m,
            home_tension_n: t_home,
        },
    }];
    let (cl, ce) = compile_all(&f, &laws, &terms);
    let at_home = StringInputs {
        tension_mn: [1100; STRINGS],
        ..StringInputs::default()
    };
    let bare = string_lengths_f64(&f, &laws, &[], &at_home);
    let want = string_lengths_f64(&f, &laws, &terms, &at_home);
    let got = string_lengths(StringLayout::ALL, &cl, &ce, &at_home);
    for i in 0..STRINGS {
        assert!((want[i] - bare[i]).abs() < 1e-9, "string {i}");
        assert!(
            (got[i] as f64 / 65536.0 - bare[i]).abs() < 1e-4,
            "string {i}"
        );
    }
    let taut = StringInputs {
        tension_mn: [4100; STRINGS],
        counts: [2000; STRINGS],
        ..at_home
    };
    let bare = string_lengths_f64(&f, &laws, &[], &taut);
    let want = string_lengths_f64(&f, &laws, &terms, &taut);
    let got = string_lengths(StringLayout::ALL, &cl, &ce, &taut);
    for i in 0..STRINGS {
        let home_length = EffectContext::for_string(&f, &laws, &taut, i)
            .expect("string")
            .home_length_mm;
        let payout = bare[i] - home_length;
        let stretch = k * (4.1 * (home_length + payout) - t_home * home_length) + m * 3.0;
        assert!((want[i] - bare[i] - stretch).abs() < 1e-9, "string {i}");
        assert!(
            (got[i] as f64 / 65536.0 - want[i]).abs() < 1e-4,
            "string {i}"
        );
    }
    // Its gradient is its slope in each parameter.
    let ctx = EffectContext::for_string(&f, &laws, &taut, 2).expect("string 2");
    let effect = terms[0].effect;
    let p = effect.parameters();
    let g = effect.gradient_f64(&ctx);
    for j in 0..p.len() {
        let h = 1e-6 * p[j].abs().max(1e-6);
        let mut up = p.clone();
        up[j] += h;
        let moved = effect.with_parameters(&up).expect("three parameters");
        let slope = (moved.contribution_f64(&ctx) - effect.contribution_f64(&ctx)) / h;
        assert!(
            (slope - g[j]).abs() < 1e-4 * g[j].abs().max(1.0),
            "{j}: {slope} vs {}",
            g[j]
        );
    }
}

#[test]
fn a_frame_flex_reads_the_total_tension_of_the_active_strings() {
    let laws = [StringLaw::polynomial(4096, [10.0, 0.0, 0.0, 0.0]); STRINGS];
    let mut f = cube_frame([100.0, -50.0, 200.0]);
    let (k, home_mm) = (0.02, 0.176);
    let terms = [EffectTerm {
        string: EVERY_STRING,
        effect: Effect::FrameFlex {
            mm_per_newton: k,
            home_mm,
        },
    }];
    let inputs = StringInputs {
        tension_mn: [1000, 2000, 3000, 4000, 5000, 6000, 7000, 8000],
        counts: [1500; STRINGS],
        ..StringInputs::default()
    };
    for layout in [
        StringLayout::ALL,
        StringLayout {
            active: 0b0101_0101,
            planar: false,
        },
    ] {
        f.layout = layout;
        let total: f64 = layout.indices().map(|i| (i + 1) as f64).sum();
        let (cl, ce) = compile_all(&f, &laws, &terms);
        let bare = string_lengths_f64(&f, &laws, &[], &inputs);
        let want = string_lengths_f64(&f, &laws, &terms, &inputs);
        let got = string_lengths(layout, &cl, &ce, &inputs);
        for i in layout.indices() {
            assert!(
                (want[i] - bare[i] - (k * total - home_mm)).abs() < 1e-9,
                "string {i}"
            );
            assert!(
                (got[i] as f64 / 65536.0 - want[i]).abs() < 1e-4,
                "string {i}"
            );
        }
    }
    // A blob's coefficient of any size neither overflows nor panics.
    let worst = CompiledEffect::FrameFlex {
        string: EVERY_STRING,
        per_mn_q48: i64::MAX,
        home_q32: i64::MIN,
    };
    let ctx = FixedContext {
        counts: 0,
        direction: 0,
        tension_mn: u16::MAX,
        time_ms: 0,
        home_length_q16: 0,
        payout_q32: 0,
        cos2_inclination_q16: 0,
        home_sag_q30: 0,
        total_tension_mn: 8 * u32::from(u16::MAX),
        payout_rate_q14: 0,
        guide_elevation_q32: 0,
        string: 0,
    };
    assert_eq!(worst.contribution_q32(&ctx), i64::MAX);
}

#[test]
fn slip_step_time_is_consistent() {
    let laws = [StringLaw::polynomial(4096, [10.0, 0.0, 0.0, 0.0]); STRINGS];
    let f = cube_frame([0.0; 3]);
    for at_s in [0.0, 0.1, 0.3, 1.0005, 17.25, 3600.0001] {
        let terms = [EffectTerm {
            string: 3,
            effect: Effect::Slip { at_s, mm: 10.0 },
        }];
        let (cl, ce) = compile_all(&f, &laws, &terms);
        let at_ms = match ce[0] {
            CompiledEffect::Slip { at_ms, .. } => at_ms,
            _ => unreachable!(),
        };
        for t in [at_ms.saturating_sub(1), at_ms, at_ms + 1] {
            let inputs = StringInputs {
                time_ms: t,
                ..Default::default()
            };
            let want = string_lengths_f64(&f, &laws, &terms, &inputs)[3];
            let got = string_lengths(StringLayout::ALL, &cl, &ce, &inputs)[3] as f64 / 65536.0;
            assert!(
                (want - got).abs() < 1e-4,
                "at_s {at_s} t {t}: {want} vs {got}"
            );
        }
    }
}

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

/// The layer table's knot spacing, `2^step_log2` counts, is read as an
/// integer power of two: the value libm's `exp2` gives, to the bit.
#[test]
fn layer_step_is_exp2_of_its_log() {
    for n in 0..=crate::model::MAX_LAYER_STEP_LOG2 {
        assert_eq!(f64::from(1u32 << n), libm::exp2(f64::from(n)), "2^{n}");
    }
}
