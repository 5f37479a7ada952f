//! The effect terms in both paths (f64 and fixed point): shared terms,
//! latency, creep, inclination and sag, stretch, frame flex, slips.

use super::fixtures::{compile_all, random_inputs, Rng};
use crate::model::{Effect, EffectTerm, StringLaw};
use crate::string_law::*;
use crate::test_fixtures::cube_frame;
use core::f64::consts::TAU;

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
