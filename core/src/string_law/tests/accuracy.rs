//! The fixed point's accuracy: its arithmetic and sine table, a law at
//! known points, the error budget against the f64 reference, and the f64
//! gradients.

use super::fixtures::{compile_all, random_inputs, realistic, Rng};
use crate::model::{Effect, StringLaw};
use crate::string_law::*;
use crate::test_fixtures::cube_frame;
use core::f64::consts::TAU;
use proptest::prelude::*;

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
