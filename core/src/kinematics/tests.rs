use super::*;
use proptest::prelude::*;

fn anchors<F: Real>() -> [Vec3<F>; STRINGS] {
    let h: F = lit(1100.0);
    let mut a = [[F::zero(); 3]; STRINGS];
    for (i, v) in a.iter_mut().enumerate() {
        *v = [
            if i & 1 == 0 { -h } else { h },
            if i & 2 == 0 { -h } else { h },
            if i & 4 == 0 { -h } else { h },
        ];
    }
    a
}

/// A row far from the previous one (a lattice's next point): lengths
/// that read the inclination (a 20 mm sag-like term, exact at the true
/// inclinations) solved once at the previous position's inclinations
/// are off; solved again at the first solution's, they are not.
#[test]
fn a_row_whose_lengths_read_the_inclination_is_solved_at_its_own() {
    let a = anchors::<f64>();
    let config = FkConfig::<f64>::default();
    let truth = [300.0, -200.0, 150.0];
    let at_truth = cos2_inclinations(&a, &truth);
    let lengths = |inputs: &StringInputs| -> [f64; STRINGS] {
        let chords = inverse_kinematics(&a, truth);
        core::array::from_fn(|i| {
            let read = f64::from(inputs.cos2_inclination_q16[i]) / 65536.0;
            chords[i] + 20.0 * (read - f64::from(at_truth[i]) / 65536.0)
        })
    };
    let inputs = StringInputs::default();
    let solve = |inclined| {
        let frame = Frame {
            anchors: a,
            layout: StringLayout::ALL,
            home: [0.0; 3],
            room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            room_translation: [0.0; 3],
            room_scale: 1.0,
        };
        let fk = forward_kinematics_inclined(&frame, &inputs, [0.0; 3], &config, inclined, lengths);
        dist(fk.position, truth)
    };
    let (once, twice) = (solve(false), solve(true));
    assert!(once > 1.0, "{once}");
    assert!(twice < 0.1 * once && twice < 0.5, "{once} -> {twice}");
}

/// Points of a 1 m cube centred in the frame, `n` per axis.
fn cube(n: usize) -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    for i in 0..n {
        for j in 0..n {
            for k in 0..n {
                let c = |m: usize| -500.0 + 1000.0 * m as f64 / (n - 1) as f64;
                out.push([c(i), c(j), c(k)]);
            }
        }
    }
    out
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn to_f64<F: Real>(p: Vec3<F>) -> [f64; 3] {
    [
        p[0].to_f64().unwrap(),
        p[1].to_f64().unwrap(),
        p[2].to_f64().unwrap(),
    ]
}

/// Round trip position -> lengths -> position; returns (max error mm, max iterations).
fn round_trip<F: Real + core::fmt::Debug>(warm: bool) -> (f64, u32) {
    let a = anchors::<F>();
    let config = FkConfig::<F>::default();
    let mut max_err = 0.0f64;
    let mut max_it = 0;
    for p in cube(11) {
        let pf = [lit::<F>(p[0]), lit(p[1]), lit(p[2])];
        // Lengths from the exact f64 geometry, rounded to F once.
        let a64 = anchors::<f64>();
        let l64 = inverse_kinematics(&a64, p);
        let l: [F; STRINGS] = core::array::from_fn(|i| lit(l64[i]));
        let start = if warm {
            [pf[0] + lit(3.0), pf[1] - lit(2.0), pf[2] + lit(1.5)]
        } else {
            [F::zero(); 3]
        };
        let s = forward_kinematics(&a, StringLayout::ALL, &l, start, &config);
        assert_eq!(s.status, FkStatus::Ok, "{p:?}: {s:?}");
        max_err = max_err.max(dist(to_f64(s.position), p));
        max_it = max_it.max(s.iterations);
    }
    (max_err, max_it)
}

#[test]
fn round_trip_f64_cold_and_warm() {
    let (e, it) = round_trip::<f64>(false);
    println!("f64 cold: max error {e:.2e} mm, max iterations {it}");
    assert!(e < 1e-6, "cold f64 error {e} mm");
    assert!(it <= 10, "cold f64 iterations {it}");
    let (e, it) = round_trip::<f64>(true);
    println!("f64 warm: max error {e:.2e} mm, max iterations {it}");
    assert!(e < 1e-6, "warm f64 error {e} mm");
    assert!(it <= 5, "warm f64 iterations {it}");
}

#[test]
fn round_trip_f32_cold_and_warm() {
    let (e, it) = round_trip::<f32>(false);
    println!("f32 cold: max error {e:.2e} mm, max iterations {it}");
    assert!(e < 0.01, "cold f32 error {e} mm");
    assert!(it <= 12, "cold f32 iterations {it}");
    let (e, it) = round_trip::<f32>(true);
    println!("f32 warm: max error {e:.2e} mm, max iterations {it}");
    assert!(e < 0.01, "warm f32 error {e} mm");
    assert!(it <= 6, "warm f32 iterations {it}");
}

#[test]
fn inverse_kinematics_at_centre() {
    let l = inverse_kinematics(&anchors::<f64>(), [0.0; 3]);
    for v in l {
        assert!((v - 1100.0 * 3f64.sqrt()).abs() < 1e-9);
    }
}

fn check_single_fault<F: Real + core::fmt::Debug>() -> (f64, u32) {
    let mut max_err = 0.0f64;
    let mut max_it = 0;
    let a = anchors::<F>();
    let a64 = anchors::<f64>();
    let config = FkConfig::<F>::default();
    for (n, p) in cube(5).into_iter().enumerate() {
        let bad = n % STRINGS;
        let mut l64 = inverse_kinematics(&a64, p);
        l64[bad] += 40.0;
        let l: [F; STRINGS] = core::array::from_fn(|i| lit(l64[i]));
        for start in [[F::zero(); 3], [lit(p[0]), lit(p[1]), lit(p[2])]] {
            let s = forward_kinematics(&a, StringLayout::ALL, &l, start, &config);
            assert_eq!(
                s.status,
                FkStatus::FaultyStringExcluded,
                "{p:?} bad {bad}: {s:?}"
            );
            assert_eq!(s.excluded, Some(bad as u8));
            let err = dist(to_f64(s.position), p);
            assert!(err < 0.5, "{p:?}: error {err} mm");
            assert!(s.iterations <= config.worst_case_iterations());
            max_err = max_err.max(err);
            max_it = max_it.max(s.iterations);
        }
    }
    (max_err, max_it)
}

#[test]
fn one_faulty_string_is_excluded() {
    let (e, it) = check_single_fault::<f64>();
    println!("+40 mm on one string, f64: max error {e:.2e} mm, max iterations {it}");
    let (e, it) = check_single_fault::<f32>();
    println!("+40 mm on one string, f32: max error {e:.2e} mm, max iterations {it}");
}

#[test]
fn two_faulty_strings_are_inconsistent() {
    let a = anchors::<f64>();
    let config = FkConfig::default();
    for (n, p) in cube(5).into_iter().enumerate() {
        let b1 = n % STRINGS;
        let b2 = (n + 3) % STRINGS;
        let mut l = inverse_kinematics(&a, p);
        l[b1] += 40.0;
        l[b2] -= 30.0;
        let s = forward_kinematics(&a, StringLayout::ALL, &l, p, &config);
        assert_eq!(
            s.status,
            FkStatus::Inconsistent,
            "{p:?} bad {b1},{b2}: {s:?}"
        );
        assert_eq!(s.excluded, None);
        assert!(s.rms_residual_mm > config.fault_threshold_mm);
    }
}

/// Deterministic Gaussian-ish noise (sum of 12 uniforms - 6).
struct Noise(u64);
impl Noise {
    fn gauss(&mut self) -> f64 {
        let mut s = 0.0;
        for _ in 0..12 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            s += (self.0 >> 11) as f64 / (1u64 << 53) as f64;
        }
        s - 6.0
    }
}

#[test]
fn length_noise_gives_sub_mm_position_error() {
    let mut noise = Noise(0x1234_5678);
    let a = anchors::<f64>();
    let af = anchors::<f32>();
    let config = FkConfig::default();
    let configf = FkConfig::<f32>::default();
    let mut max64 = 0.0f64;
    let mut max32 = 0.0f64;
    for p in cube(7) {
        let mut l = inverse_kinematics(&a, p);
        for v in l.iter_mut() {
            *v += 0.1 * noise.gauss();
        }
        let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &config);
        assert_eq!(s.status, FkStatus::Ok, "{s:?}");
        max64 = max64.max(dist(s.position, p));
        let lf: [f32; STRINGS] = core::array::from_fn(|i| l[i] as f32);
        let s = forward_kinematics(&af, StringLayout::ALL, &lf, [0.0; 3], &configf);
        assert_eq!(s.status, FkStatus::Ok, "{s:?}");
        max32 = max32.max(dist(to_f64(s.position), p));
    }
    println!("0.1 mm length noise: max position error f64 {max64:.3} mm, f32 {max32:.3} mm");
    assert!(max64 < 1.0 && max32 < 1.0, "{max64} {max32}");
}

/// A string a few mm off (a slip on its spool) raises the 8 strings' RMS
/// to about 1 mm, under the 2 mm at which they are inconsistent: the string
/// is still left out (the all-string solution is pulled by ~2 mm), while
/// strings that only disagree by their noise keep every string. With 0.4 mm
/// of noise (more than a calibrated device's 0.15 mm RMS) no string is left
/// out on a 7^3 cube.
#[test]
fn a_string_a_few_mm_off_is_left_out_below_the_fault_threshold() {
    let a = anchors::<f64>();
    let config = FkConfig::default();
    let mut noise = Noise(0x0bad_5119);
    let (mut excluded, mut worst_kept, mut worst_pulled) = (0, 0.0f64, 0.0f64);
    for (k, p) in cube(7).into_iter().enumerate() {
        let mut l = inverse_kinematics(&a, p);
        let bad = k % STRINGS;
        l[bad] += if k % 2 == 0 { 4.0 } else { -4.0 };
        let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &config);
        assert!(s.rms_residual_mm < config.fault_threshold_mm);
        assert_eq!(s.status, FkStatus::FaultyStringExcluded, "{p:?}: {s:?}");
        assert_eq!(s.excluded, Some(bad as u8));
        worst_kept = worst_kept.max(dist(s.position, p));
        let compromise = forward_kinematics(
            &a,
            StringLayout::ALL,
            &l,
            [0.0; 3],
            &FkConfig {
                exclusion_threshold_mm: config.fault_threshold_mm,
                ..config
            },
        );
        assert_eq!(compromise.status, FkStatus::Ok, "the old rule kept it");
        worst_pulled = worst_pulled.max(dist(compromise.position, p));

        let mut l = inverse_kinematics(&a, p);
        for v in l.iter_mut() {
            *v += 0.4 * noise.gauss();
        }
        let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &config);
        excluded += usize::from(s.status == FkStatus::FaultyStringExcluded);
        assert_ne!(s.status, FkStatus::Inconsistent);
    }
    assert!(worst_kept < 1e-6, "{worst_kept} mm");
    assert!(worst_pulled > 1.0, "{worst_pulled} mm");
    assert_eq!(excluded, 0, "noise left a string out");
}

#[test]
fn invalid_inputs() {
    let a = anchors::<f32>();
    let config = FkConfig::default();
    let good = inverse_kinematics(&a, [10.0, 20.0, 30.0]);
    for bad in [f32::NAN, f32::INFINITY, -1.0] {
        let mut l = good;
        l[4] = bad;
        let s = forward_kinematics(&a, StringLayout::ALL, &l, [1.0, 2.0, 3.0], &config);
        assert_eq!(s.status, FkStatus::InvalidInput);
        assert_eq!(s.position, [1.0, 2.0, 3.0]);
        assert!(!s.rms_residual_mm.is_nan());
    }
    let mut na = a;
    na[2][1] = f32::NAN;
    let s = forward_kinematics(&na, StringLayout::ALL, &good, [0.0; 3], &config);
    assert_eq!(s.status, FkStatus::InvalidInput);
    // A NaN start is replaced by the centroid and still solves.
    let s = forward_kinematics(&a, StringLayout::ALL, &good, [f32::NAN; 3], &config);
    assert_eq!(s.status, FkStatus::Ok);
    assert!((s.position[0] - 10.0).abs() < 0.01);
}

#[test]
fn at_an_anchor_and_degenerate() {
    let a = anchors::<f64>();
    let config = FkConfig::default();
    // Start exactly on an anchor.
    let l = inverse_kinematics(&a, [100.0, 0.0, 0.0]);
    let s = forward_kinematics(&a, StringLayout::ALL, &l, a[0], &config);
    assert_eq!(s.status, FkStatus::Ok);
    // All anchors at one point: no position can be found, but no NaN.
    let same = [[0.0; 3]; STRINGS];
    let s = forward_kinematics(
        &same,
        StringLayout::ALL,
        &[100.0; STRINGS],
        [0.0; 3],
        &config,
    );
    assert!(s.position.iter().all(|v| v.is_finite()));
    assert!(!s.rms_residual_mm.is_nan());
}

/// A 4-line cable robot (Hangprinter-like: three low anchors, one high)
/// on channels 0..4; channels 4..8 hold garbage that must not be read.
fn four_line_anchors() -> ([Vec3<f64>; STRINGS], StringLayout) {
    let mut a = [[f64::NAN; 3]; STRINGS];
    a[0] = [0.0, -1620.0, -150.0];
    a[1] = [1272.8, 1272.8, -150.0];
    a[2] = [-1403.0, 810.0, -150.0];
    a[3] = [0.0, 0.0, 2350.0];
    (a, StringLayout::first(4, false))
}

#[test]
fn four_strings_round_trip_and_ignore_inactive_channels() {
    let (a, layout) = four_line_anchors();
    for p in [
        [0.0, 0.0, 0.0],
        [300.0, -250.0, 400.0],
        [-400.0, 500.0, 1100.0],
    ] {
        let mut l = inverse_kinematics(&a, p);
        for v in l.iter_mut().skip(4) {
            *v = f64::NAN;
        }
        let s = forward_kinematics(&a, layout, &l, [0.0, 0.0, 100.0], &FkConfig::default());
        assert_eq!(s.status, FkStatus::Ok, "{s:?}");
        assert!(dist(s.position, p) < 1e-6, "{:?} vs {p:?}", s.position);
    }
}

#[test]
fn one_spare_string_sees_a_fault_but_blames_no_string() {
    let (a, layout) = four_line_anchors();
    assert_eq!(layout.redundancy(), 1);
    let mut l = inverse_kinematics(&a, [100.0, 50.0, 300.0]);
    l[2] += 30.0;
    let s = forward_kinematics(&a, layout, &l, [0.0; 3], &FkConfig::default());
    assert_eq!(s.status, FkStatus::Inconsistent, "{s:?}");
    assert_eq!(s.excluded, None);
}

/// A faulty string on a device whose other strings disagree by more than
/// the threshold too: no exclusion fits, but leaving the faulty string
/// out explains most of it, and that position is kept (flagged
/// inconsistent) instead of the compromise.
#[test]
fn a_dominant_exclusion_gives_the_position_of_an_inconsistent_solve() {
    let a = anchors::<f64>();
    let p = [150.0, -220.0, 90.0];
    let exact = inverse_kinematics(&a, p);
    for bad in 0..STRINGS {
        let mut l = exact;
        for (i, v) in l.iter_mut().enumerate() {
            // The sign of x y z at corner i: no position absorbs it.
            let sign = [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0][i];
            *v += if i == bad { 40.0 } else { 2.6 * sign };
        }
        let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &FkConfig::default());
        assert_eq!(s.status, FkStatus::Inconsistent, "bad {bad}: {s:?}");
        assert_eq!(s.excluded, Some(bad as u8), "bad {bad}");
        let compromise = forward_kinematics(
            &a,
            StringLayout::ALL,
            &l,
            [0.0; 3],
            &FkConfig {
                fault_threshold_mm: f64::INFINITY,
                exclusion_threshold_mm: f64::INFINITY,
                ..FkConfig::default()
            },
        );
        let (kept, spread) = (dist(s.position, p), dist(compromise.position, p));
        assert!(
            kept < 6.0 && kept < spread / 3.0,
            "bad {bad}: {kept} vs {spread} mm"
        );
    }
    // Two faulty strings: no exclusion dominates, the compromise stays.
    let mut l = exact;
    l[1] += 40.0;
    l[5] -= 35.0;
    let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &FkConfig::default());
    assert_eq!(
        (s.status, s.excluded),
        (FkStatus::Inconsistent, None),
        "{s:?}"
    );
}

#[test]
fn two_spare_strings_exclude_a_faulty_one() {
    let full = anchors::<f64>();
    // Channels 0, 1, 2, 4, 6, 7 of the cube: 6 strings, redundancy 3.
    let layout = StringLayout {
        active: 0b1101_0111,
        planar: false,
    };
    assert_eq!(layout.redundancy(), 3);
    let p = [120.0, -80.0, 60.0];
    let good = inverse_kinematics(&full, p);
    // A faulty string is excluded when it is the only one whose
    // exclusion fits; where leaving another string out fits too (the
    // fault absorbed by a different position) no string is blamed, never
    // the wrong one. At this point that happens for string 4 (and for
    // string 2 at 25 mm): leaving string 2 out fits within 0.3 mm.
    let mut excluded_right = 0;
    for bad in layout.indices() {
        for amount in [25.0, 150.0] {
            let mut l = good;
            l[bad] += amount;
            let s = forward_kinematics(&full, layout, &l, [0.0; 3], &FkConfig::default());
            match s.status {
                FkStatus::FaultyStringExcluded => {
                    assert_eq!(s.excluded, Some(bad as u8), "+{amount} on {bad}: {s:?}");
                    assert!(dist(s.position, p) < 1e-3);
                    excluded_right += 1;
                }
                FkStatus::Inconsistent => assert_eq!(s.excluded, None),
                _ => panic!("+{amount} on {bad}: {s:?}"),
            }
        }
    }
    assert!(excluded_right >= 9, "{excluded_right} of 12");
}

/// A planar device's anchors on channels 0..4: the corners of a 1.6 m x
/// 1.2 m frame in z = 25 mm.
fn planar_anchors() -> [Vec3<f64>; STRINGS] {
    let mut a = [[0.0; 3]; STRINGS];
    let corners = [
        (-800.0, -600.0),
        (800.0, -600.0),
        (800.0, 600.0),
        (-800.0, 600.0),
    ];
    for (v, (x, y)) in a.iter_mut().zip(corners) {
        *v = [x, y, 25.0];
    }
    a
}

#[test]
fn planar_layout_solves_in_the_anchors_plane() {
    let a = planar_anchors();
    for n in [3usize, 4] {
        let layout = StringLayout::first(n, true);
        assert_eq!(layout.dof(), 2);
        let p = [210.0, -130.0, 25.0];
        let l = inverse_kinematics(&a, p);
        // A start off the plane stays off by that offset in z: the
        // solve moves x, y only. Starts come from the plane (home).
        let s = forward_kinematics(&a, layout, &l, [0.0, 0.0, 25.0], &FkConfig::default());
        assert_eq!(s.status, FkStatus::Ok, "{n} strings: {s:?}");
        assert!(dist(s.position, p) < 1e-6, "{n}: {:?}", s.position);
    }
    // One string cannot fix a point in the plane.
    let s = forward_kinematics(
        &a,
        StringLayout::first(1, true),
        &[500.0; STRINGS],
        [0.0, 0.0, 25.0],
        &FkConfig::default(),
    );
    assert_eq!(s.status, FkStatus::InvalidInput);
}

#[test]
fn layout_counts() {
    assert_eq!(StringLayout::ALL.count(), 8);
    assert_eq!(StringLayout::ALL.redundancy(), 5);
    assert_eq!(StringLayout::first(3, false).redundancy(), 0);
    assert_eq!(StringLayout::first(9, false), StringLayout::ALL);
    let l = StringLayout {
        active: 0b0101_0000,
        planar: true,
    };
    assert_eq!(l.indices().collect::<Vec<_>>(), [4, 6]);
}

proptest! {
    /// Finite inputs never give a NaN or a panic, whatever their values.
    #[test]
    fn finite_inputs_never_nan(l in proptest::array::uniform8(0.0f32..1e30),
                               start in proptest::array::uniform3(-1e30f32..1e30),
                               scale in prop_oneof![Just(1.0f32), Just(1e-30), Just(1e20)]) {
        let mut a = anchors::<f32>();
        for v in a.iter_mut() { for c in v.iter_mut() { *c *= scale; } }
        let s = forward_kinematics(&a, StringLayout::ALL, &l, start, &FkConfig::default());
        prop_assert!(s.position.iter().all(|v| v.is_finite()), "{:?}", s);
        prop_assert!(!s.rms_residual_mm.is_nan());
        prop_assert!(s.iterations <= FkConfig::<f32>::default().worst_case_iterations());
    }

    #[test]
    fn realistic_lengths_round_trip(p in proptest::array::uniform3(-500.0f64..500.0),
                                    s in proptest::array::uniform3(-600.0f64..600.0)) {
        let a = anchors::<f64>();
        let l = inverse_kinematics(&a, p);
        let sol = forward_kinematics(&a, StringLayout::ALL, &l, s, &FkConfig::default());
        prop_assert_eq!(sol.status, FkStatus::Ok);
        prop_assert!(dist(sol.position, p) < 1e-6);
    }
}

/// Six strings (3 spares), one string 8 mm off and 0.1 mm of noise on
/// every string, over a 5^3 cube: where leaving a good string out also
/// fits (the fault absorbed by another position) but leaves 3 times the
/// residual or more, the faulty string is still left out; a wrong string
/// never is. Before, two fitting exclusions meant the all-string
/// compromise, several mm off (an independent 6-string device's abnormal
/// motor: test max 5.0 mm).
#[test]
fn six_strings_leave_out_the_exclusion_that_fits_clearly_best() {
    let full = anchors::<f64>();
    let layout = StringLayout {
        active: 0b0011_1111,
        planar: false,
    };
    assert_eq!(layout.redundancy(), 3);
    let config = FkConfig::default();
    let mut noise = Noise(0x5eed_0006);
    let (mut right, mut compromise, mut worst) = (0, 0, 0.0f64);
    let points = cube(5);
    for (k, p) in points.iter().enumerate() {
        let bad = k % 6;
        let mut l = inverse_kinematics(&full, *p);
        for v in l.iter_mut() {
            *v += 0.1 * noise.gauss();
        }
        l[bad] += if k % 2 == 0 { 8.0 } else { -8.0 };
        let s = forward_kinematics(&full, layout, &l, [0.0; 3], &config);
        match (s.status, s.excluded) {
            (FkStatus::FaultyStringExcluded, Some(e)) => {
                assert_eq!(e as usize, bad, "{p:?}: {s:?}");
                right += 1;
                worst = worst.max(dist(s.position, *p));
            }
            (FkStatus::Inconsistent, _) | (FkStatus::Ok, None) => compromise += 1,
            _ => panic!("{p:?}: {s:?}"),
        }
    }
    // 117 of 125 (43 when only the one set that fits was trusted).
    assert!(right >= 110, "{right} left out, {compromise} compromises");
    assert!(worst < 0.5, "{worst} mm");
}

#[test]
fn residual_weights_follow_each_strings_measured_scale() {
    let all = StringLayout::ALL;
    // The typical string (the lower median) weighs 1, the quieter ones too;
    // a string four times noisier a quarter; no string below the floor.
    let w: [f64; STRINGS] = residual_weights(all, &[0.2, 0.19, 0.21, 0.8, 0.24, 0.2, 0.2, 30.0]);
    assert_eq!(w[..2], [1.0, 1.0]);
    assert!((w[2] - 0.2 / 0.21).abs() < 1e-12, "{w:?}");
    assert!((w[3] - 0.25).abs() < 1e-12, "{w:?}");
    assert!((w[4] - 0.2 / 0.24).abs() < 1e-12, "{w:?}");
    assert_eq!(w[7], MIN_RESIDUAL_WEIGHT);
    // Inactive channels are not read and weigh 1.
    let four = StringLayout::first(4, false);
    let w = residual_weights(four, &[0.2, 0.4, 0.2, 0.2, f64::NAN, 0.0, -1.0, 9.0]);
    assert_eq!(w, [1.0, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]);
    // A scale not measured on an active string: every string alike.
    for bad in [0.0, -0.1, f64::NAN, f64::INFINITY] {
        let mut s = [0.2; STRINGS];
        s[5] = bad;
        assert_eq!(residual_weights(all, &s), [1.0; STRINGS], "{bad}");
    }
    assert_eq!(residual_weights(all, &[0.0; STRINGS]), [1.0; STRINGS]);
    // The typical scale is the lower median, measured or not at all.
    let scales = [0.2, 0.19, 0.21, 0.8, 0.24, 0.2, 0.2, 30.0];
    assert_eq!(typical_scale(all, &scales), Some(0.2));
    assert_eq!(
        typical_scale(four, &[0.3, 0.4, 0.1, 0.2, 0.0, 0.0, 0.0, 0.0]),
        Some(0.2)
    );
    assert_eq!(typical_scale(all, &[0.0; STRINGS]), None::<f64>);
}

/// A string whose reading lags (its length off by up to 3 mm, more while
/// it moves fast) on a device whose other strings read to 0.1 mm: weighed by
/// its measured scale it pulls the position much less, and where it is far
/// off it is still left out.
#[test]
fn a_noisy_string_weighed_by_its_scale_pulls_the_position_less() {
    let a = anchors::<f64>();
    let plain = FkConfig::<f64>::default();
    let weighed = FkConfig {
        residual_weight: residual_weights(
            StringLayout::ALL,
            &[0.1, 0.1, 0.1, 0.6, 0.1, 0.1, 0.1, 0.1],
        ),
        ..plain
    };
    let mut noise = Noise(0x5EED);
    let (mut e_plain, mut e_weighed) = (0.0, 0.0);
    let points = cube(5);
    for p in &points {
        let mut l = inverse_kinematics(&a, *p);
        for v in l.iter_mut() {
            *v += 0.1 * noise.gauss();
        }
        l[3] += 0.6 * noise.gauss().clamp(-5.0, 5.0);
        let s = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &plain);
        let w = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &weighed);
        assert!(matches!(
            w.status,
            FkStatus::Ok | FkStatus::FaultyStringExcluded
        ));
        e_plain += dist(s.position, *p);
        e_weighed += dist(w.position, *p);
    }
    let n = points.len() as f64;
    let (e_plain, e_weighed) = (e_plain / n, e_weighed / n);
    assert!(e_weighed < 0.7 * e_plain, "{e_plain} -> {e_weighed}");
    // Unit weights are the unweighted solve, bit for bit.
    let l = inverse_kinematics(&a, [120.0, -40.0, 310.0]).map(|v| v + 0.3);
    let ones = FkConfig {
        residual_weight: [1.0; STRINGS],
        ..plain
    };
    assert_eq!(
        forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &plain),
        forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &ones)
    );
    // A slip of 30 mm on the down-weighted string still counts it faulty.
    let p = [100.0, 200.0, -300.0];
    let mut l = inverse_kinematics(&a, p);
    l[3] += 30.0;
    let w = forward_kinematics(&a, StringLayout::ALL, &l, [0.0; 3], &weighed);
    assert_eq!(w.status, FkStatus::FaultyStringExcluded, "{w:?}");
    assert_eq!(w.excluded, Some(3));
    assert!(dist(w.position, p) < 1e-3, "{w:?}");
}

/// Two spare strings (five strings in 3-D, four in the plane), one string
/// 40-120 mm off (the abnormal motor's string out of its groove) and 0.1 mm
/// of noise on the others: where a second exclusion fits by chance, no
/// exclusion is trusted, but the one that fits [`DOMINANT_EXCLUSION`] times
/// better than every other gives the inconsistent row's position (it names
/// the string), not the all-string compromise tens of mm off. A wrong
/// string is never named.
#[test]
fn two_spares_give_an_inconsistent_row_the_exclusion_that_fits_clearly_best() {
    let square = planar_anchors();
    let five = StringLayout {
        active: 0b0001_1111,
        planar: false,
    };
    let devices = [
        (anchors::<f64>(), five, cube(6)),
        (
            square,
            StringLayout::first(4, true),
            cube(6)
                .iter()
                .map(|p| [0.7 * p[0], 0.5 * p[1], 25.0])
                .collect(),
        ),
    ];
    let weighings = [None, Some((0, 0.25)), Some((1, 0.25))];
    for ((a, layout, points), low) in devices.iter().flat_map(|d| weighings.map(|w| (d, w))) {
        let (a, layout) = (*a, *layout);
        assert_eq!(layout.redundancy(), 2);
        let n = layout.count();
        let mut noise = Noise(0x5eed_0002);
        let (mut named, mut compromise, mut trusted) = (0, 0, 0);
        let mut worst_named = 0.0f64;
        for (k, p) in points.iter().enumerate() {
            let bad = k % n;
            // The faulty string weighed low, as its measured scale would, or
            // another one.
            let mut config = FkConfig::default();
            if let Some((shift, w)) = low {
                config.residual_weight[(bad + shift) % n] = w;
            }
            let mut l = inverse_kinematics(&a, *p);
            for v in l.iter_mut() {
                *v += 0.1 * noise.gauss();
            }
            let size = 40.0 + 80.0 * (k % 7) as f64 / 6.0;
            l[bad] += if k % 2 == 0 { size } else { -size };
            let s = forward_kinematics(&a, layout, &l, [0.0, 0.0, p[2]], &config);
            match (s.status, s.excluded) {
                (FkStatus::FaultyStringExcluded, Some(e)) => {
                    assert_eq!(e as usize, bad, "{p:?}: {s:?}");
                    trusted += 1;
                }
                (FkStatus::Inconsistent, Some(e)) => {
                    assert_eq!(e as usize, bad, "{p:?}: {s:?}");
                    named += 1;
                    worst_named = worst_named.max(dist(s.position, *p));
                }
                (FkStatus::Inconsistent, None) => compromise += 1,
                _ => panic!("{p:?}: {s:?}"),
            }
        }
        // 5 strings: 187 trusted, 29 named, 0 compromises; 4 strings: 203,
        // 13, 0 (before: 29 and 13 compromises, none named).
        // Every string alike, or the faulty one weighed low: 5 strings: 187
        // trusted, 29 named, 0 compromises; 4 strings: 203, 13, 0 (before:
        // 29 and 13 compromises, none named). A good string weighed low
        // stays in every exclusion but its own, so the exclusion must also be
        // the string the compromise blames most: 5 strings 153 trusted, 16
        // named, 47 compromises (63 named, none wrong, without that rule);
        // 4 strings 150, 31, 35.
        let least_named = match (low, n) {
            (Some((1, _)), 5) => 12,
            _ => 10,
        };
        assert!(
            named >= least_named && trusted >= 140,
            "{n} strings, weights {low:?}: {trusted} trusted, {named} named, {compromise} \
             compromises"
        );
        if !matches!(low, Some((1, _))) {
            assert!(
                compromise <= 2,
                "{n} strings, {low:?}: {compromise} compromises"
            );
        }
        assert!(worst_named < 0.5, "{worst_named} mm");
    }
}
