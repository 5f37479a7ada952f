use super::*;
use crate::model::{Effect, EffectTerm, StringInputs, StringLaw, StringLayout, EVERY_STRING};
use crate::string_law::{compile_effect, compile_string_law, string_lengths, string_lengths_f64};
use crate::test_fixtures::cube_frame;

/// The elevation is the chord's angle from the plane across the swivel
/// axis, which points away from the home height: 0 level, `-1/4` turn
/// toward the home height straight along the axis, the same in f32 and
/// f64 (to f32's rounding), and 0 for no chord or a non-finite position.
#[test]
fn the_elevation_is_signed_along_the_axis_away_from_home() {
    let home = [0.0f64, 0.0, 0.0];
    let top = [1000.0f64, 1000.0, 1000.0];
    let bottom = [1000.0f64, 1000.0, -1000.0];
    let q = |a: &[f64; 3], p: [f64; 3]| guide_elevation_q32(a, &home, &p);
    assert_eq!(q(&top, [0.0, 1000.0, 1000.0]), 0); // level
    assert_eq!(q(&top, [1000.0, 1000.0, 0.0]), -(1 << 30)); // below a top guide
    assert_eq!(q(&bottom, [1000.0, 1000.0, 0.0]), -(1 << 30)); // above a bottom guide
    assert_eq!(q(&bottom, [1000.0, 1000.0, -2000.0]), 1 << 30); // beyond it
    assert_eq!(q(&top, top), 0);
    assert_eq!(q(&top, [f64::NAN, 0.0, 0.0]), 0);
    let mut worst = 0.0f64;
    for k in 0..2000 {
        let t = f64::from(k) * 0.37;
        let p = [
            900.0 * libm::sin(t),
            700.0 * libm::cos(1.3 * t),
            1100.0 * libm::sin(0.7 * t),
        ];
        for a in [top, bottom] {
            let d = [p[0] - a[0], p[1] - a[1], p[2] - a[2]];
            let along = if a[2] >= home[2] { d[2] } else { -d[2] };
            let want = libm::atan2(along, libm::hypot(d[0], d[1]));
            worst = worst.max((guide_elevation_rad(q(&a, p)) - want).abs());
            let (a32, p32, h32) = (a.map(|x| x as f32), p.map(|x| x as f32), [0.0f32; 3]);
            let device = guide_elevation_q32(&a32, &h32, &p32);
            assert!((device - q(&a, p)).abs() < 400, "{device} vs {}", q(&a, p));
        }
    }
    assert!(worst < 3e-7, "{worst} rad");
}

/// The exact path, built another way: the tangent point `T` on the pulley
/// (centre `M` at `r` from the entry point across the axis) with `T - M`
/// square to `P - T`, the arc from the entry point to `T` and the free
/// span `|P - T|`.
#[test]
fn the_exact_path_is_the_arc_to_the_tangent_point_and_the_span() {
    for r in [6.0, 12.0, 30.0] {
        for chord in [300.0, 800.0, 2500.0] {
            for deg in [-89.0f64, -60.0, -30.0, -5.0, 0.0, 20.0, 70.0] {
                if chord < GUIDE_MIN_RADII * r {
                    continue; // clamped
                }
                let a = deg.to_radians();
                // Plane coordinates (across, along), entry point at 0.
                let p = [chord * libm::cos(a), chord * libm::sin(a)];
                let m = [r, 0.0];
                let (dx, dy) = (p[0] - m[0], p[1] - m[1]);
                let dm = libm::hypot(dx, dy);
                // T = M + r (cos t, sin t) with cos(t - atan2(dy, dx)) = r / dm,
                // on the side the string wraps (from the entry point at angle pi,
                // turning through the far side of the pulley).
                let t = libm::atan2(dy, dx) + libm::acos(r / dm);
                let tp = [m[0] + r * libm::cos(t), m[1] + r * libm::sin(t)];
                let radial = [tp[0] - m[0], tp[1] - m[1]];
                let span = [p[0] - tp[0], p[1] - tp[1]];
                assert!((radial[0] * span[0] + radial[1] * span[1]).abs() < 1e-6);
                let wrap = (PI - t).rem_euclid(TAU);
                let want = r * wrap + libm::hypot(span[0], span[1]) - chord;
                let got = guide_path_mm(r, chord, a);
                assert!(
                    (got - want).abs() < 1e-9,
                    "r {r} chord {chord} a {deg}: {got} vs {want}"
                );
            }
        }
    }
    assert_eq!(guide_path_mm(0.0, 500.0, 0.3), 0.0);
}

/// Fixed point against the exact f64 term: within 3e-5 mm for guides up to
/// 15 mm at any elevation and free length (the series is exact to `r 1e-6`
/// at the clamp, 16 radii, the sine table to 1.2e-6), one string's term and
/// a shared one alike. Run with `--nocapture` for the measured maximum.
#[test]
fn the_series_in_fixed_point_follows_the_exact_path() {
    let f = cube_frame([0.0; 3]);
    let laws = [StringLaw::polynomial(4096, [12.0, -0.004, 0.0, 0.0]); STRINGS];
    let compiled: [_; STRINGS] =
        core::array::from_fn(|i| compile_string_law(&f, i, &laws[i]).unwrap());
    let mut worst = 0.0f64;
    for r in [-3.0, 0.0, 0.5, 6.0, 12.0, 15.0] {
        for string in [3u8, EVERY_STRING] {
            let terms = [EffectTerm {
                string,
                effect: Effect::Guide { radius_mm: r },
            }];
            let ce = [compile_effect(&terms[0], &f, &laws).unwrap()];
            for k in 0..400 {
                let mut inputs = StringInputs::default();
                for i in 0..STRINGS {
                    // From the clamp's length (home 1905 mm less up to 4000
                    // mm) to 2 m beyond home, elevations across the range.
                    inputs.counts[i] = (k * 997 + i as i32 * 7919) % 120_000 - 60_000;
                    inputs.guide_elevation_q32[i] =
                        ((k * 104_729 + i as i32 * 15_485_863) % (1 << 30)) * 2 - (1 << 30);
                }
                let want = string_lengths_f64(&f, &laws, &terms, &inputs);
                let got = string_lengths(StringLayout::ALL, &compiled, &ce, &inputs);
                for i in 0..STRINGS {
                    worst = worst.max((got[i] as f64 / 65536.0 - want[i]).abs());
                }
            }
        }
    }
    println!("guide: max |fixed - f64| = {worst:.3e} mm");
    assert!(worst < 3e-5, "{worst} mm");
}

/// A guide of 12 mm at a chord of 500 mm: the path's excess is the wrap
/// less what the anchor's move from the exit point to the entry point
/// saves, about `r (pi/2 - a - cos a)`; the term is its excess at home
/// less the one now, 0 at home, and its slope in `r` is the gradient.
#[test]
fn a_guide_adds_its_wrap_in_both_paths() {
    let ctx_for = |a: f64| EffectContext {
        theta: 0.0,
        payout_mm: 0.0,
        home_length_mm: 500.0,
        tension_n: 1.0,
        total_tension_n: 8.0,
        direction: 0,
        time_s: 0.0,
        cos2_inclination: 1.0,
        home_cos2_inclination: 1.0,
        payout_rate_mm_s: 0.0,
        guide_elevation_rad: a,
        home_guide_elevation_rad: -0.5,
    };
    let path =
        |r: f64, ctx: &EffectContext| guide_path_mm(r, ctx.home_length_mm, -0.5) - guide_mm(r, ctx);
    let level = path(12.0, &ctx_for(0.0));
    // pi/2 - 1 = 0.5708 of a radius, and (r / l) / 2 of one more.
    assert!(
        (level - 12.0 * (FRAC_PI_2 - 1.0 + 0.012)).abs() < 0.01,
        "{level}"
    );
    // Straight along the axis: half a turn, and u^2 / 2 = 2 of r^2 / l.
    let down = path(12.0, &ctx_for(-FRAC_PI_2));
    assert!(
        (down - 12.0 * PI - 2.0 * 144.0 / 500.0).abs() < 0.01,
        "{down}"
    );
    let h = 1e-6;
    let ctx = ctx_for(-0.7);
    let fd = (guide_mm(12.0 + h, &ctx) - guide_mm(12.0 - h, &ctx)) / (2.0 * h);
    assert!((fd - guide_slope(12.0, &ctx)).abs() < 1e-6);
    let at_zero = (guide_mm(h, &ctx) - guide_mm(-h, &ctx)) / (2.0 * h);
    assert!((at_zero - guide_slope(0.0, &ctx)).abs() < 1e-6);
    assert!(guide_mm(12.0, &ctx_for(-0.5)).abs() < 1e-12);
}
