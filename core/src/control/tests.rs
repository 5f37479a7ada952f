use super::*;
use crate::blob::compile;
use crate::correction::CorrectionModel;
use crate::model::{Calibration, StringLaw};
use crate::test_fixtures::cube_frame;

const CPR: u32 = 4096;
const RADIUS: f64 = 10.0;

fn calibration() -> Calibration {
    Calibration {
        frame: cube_frame([0.0; 3]),
        strings: [StringLaw::polynomial(CPR, [RADIUS, 0.0, 0.0, 0.0]); STRINGS],
        effects: alloc::vec![],
        correction: CorrectionModel::None,
        length_scale_mm: [0.0; STRINGS],
        kinematics: Default::default(),
        home: None,
    }
}

/// Raw 16-bit counters for the end-effector at `p` (device frame), with
/// the linear law of `calibration()` and counters that read 1000 at home.
fn raw_counts_at(cal: &Calibration, p: [f64; 3]) -> [u16; STRINGS] {
    let lengths = inverse_kinematics(&cal.frame.anchors, p);
    let home = inverse_kinematics(&cal.frame.anchors, cal.frame.home);
    let mut raw = [0u16; STRINGS];
    for i in 0..STRINGS {
        let theta = (lengths[i] - home[i]) / RADIUS;
        let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
        raw[i] = (1000 + counts) as u16;
    }
    raw
}

#[test]
fn tracks_a_trajectory_and_renders_a_force_when_armed() {
    let cal = calibration();
    let blob = compile(&cal, 1, 0).unwrap();
    let compiled = CompiledCalibration::from_blob(&blob).unwrap();
    let mut ctl = Controller::new(
        ControlConfig::default(),
        &compiled,
        raw_counts_at(&cal, [0.0; 3]),
        0,
    )
    .unwrap();
    ctl.safety().heartbeat(0);
    ctl.safety().arm().unwrap();
    ctl.set_target(Target::Force([0.0, 0.0, 2.0]));
    let mut out = None;
    for k in 1..=300 {
        let t = k as f64 / 300.0;
        let p = [300.0 * t, -200.0 * t, 400.0 * t];
        ctl.safety().heartbeat(k);
        let o = ctl.step(
            &compiled,
            &LoopInput {
                raw_counts: raw_counts_at(&cal, p),
                now_ms: k,
                now_us: k * 1000,
                estop: false,
            },
        );
        let err = (0..3)
            .map(|c| (o.position_mm[c] as f64 - p[c]).powi(2))
            .sum::<f64>()
            .sqrt();
        // Quantization: one count is 2 pi 10 / 4096 = 0.015 mm of string.
        assert!(err < 0.05, "step {k}: error {err} mm");
        out = Some(o);
    }
    let o = out.unwrap();
    assert!(o.armed && o.faults.is_empty());
    assert_eq!(o.tension_status, TensionStatus::Exact);
    let f =
        crate::tension::resultant_force(&compiled.head.frame.anchors, o.position_mm, &o.tensions_n);
    assert!((f[2] - 2.0).abs() < 1e-3 && f[0].abs() < 1e-3 && f[1].abs() < 1e-3);
    // Room frame: eq. 6 translation.
    let room = position_mm(o.room_q16);
    assert!((room[2] - (400.0 + 1500.0)).abs() < 0.05);
}

/// Counters of a spool whose radius grows with the wound string (the
/// paper's pulley) read with the linear law: 700 mm from home the
/// strings disagree by tens of mm. With the law taken as calibrated that
/// is a forward-kinematics fault and the device drops to pre-tension;
/// taken as nominal (before calibration) it is the model's own error,
/// and the loop goes on armed with its least-squares position.
#[test]
fn uncalibrated_lengths_raise_no_consistency_fault() {
    let cal = calibration();
    let blob = compile(&cal, 1, 0).unwrap();
    let compiled = CompiledCalibration::from_blob(&blob).unwrap();
    let home = inverse_kinematics(&cal.frame.anchors, cal.frame.home);
    // payout = r theta - kappa theta^2: theta from the true payout.
    let kappa = 0.03;
    let raw_at = |p: [f64; 3]| -> [u16; STRINGS] {
        let lengths = inverse_kinematics(&cal.frame.anchors, p);
        core::array::from_fn(|i| {
            let payout = lengths[i] - home[i];
            let theta =
                2.0 * payout / (RADIUS + libm::sqrt(RADIUS * RADIUS - 4.0 * kappa * payout));
            let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
            (1000 + counts) as u16
        })
    };
    let run = |calibrated: bool| {
        let mut ctl =
            Controller::new(ControlConfig::default(), &compiled, raw_at([0.0; 3]), 0).unwrap();
        ctl.set_lengths_calibrated(calibrated);
        ctl.safety().heartbeat(0);
        ctl.safety().arm().unwrap();
        let mut last = None;
        for k in 1..=200u32 {
            let t = f64::from(k) / 200.0;
            ctl.safety().heartbeat(k);
            last = Some(ctl.step(
                &compiled,
                &LoopInput {
                    raw_counts: raw_at([-400.0 * t, -400.0 * t, -400.0 * t]),
                    now_ms: k,
                    now_us: k * 1000,
                    estop: false,
                },
            ));
        }
        last.unwrap()
    };
    let calibrated = run(true);
    assert!(calibrated.faults.contains(SafetyFaults::FK_FAULT));
    assert!(!calibrated.armed);
    let nominal = run(false);
    assert!(nominal.faults.is_empty(), "{:?}", nominal.faults);
    assert!(nominal.armed);
    assert_eq!(nominal.fk_status, FkStatus::Ok);
}

/// A 4-line cable robot (three low anchors, one high) on channels 0, 2,
/// 5, 7; the other channels keep the cube's anchors, which must not be
/// read, and their encoders turn as if strings were there.
#[test]
fn four_strings_track_and_render_with_inactive_channels_at_zero() {
    let mut cal = calibration();
    cal.frame.layout = crate::model::StringLayout {
        active: 0b1010_0101,
        planar: false,
    };
    cal.frame.anchors[0] = [0.0, -1620.0, -150.0];
    cal.frame.anchors[2] = [1272.8, 1272.8, -150.0];
    cal.frame.anchors[5] = [-1403.0, 810.0, -150.0];
    cal.frame.anchors[7] = [0.0, 0.0, 2350.0];
    cal.frame.home = [0.0, 0.0, 300.0];
    let blob = compile(&cal, 1, 0).unwrap();
    let compiled = CompiledCalibration::from_blob(&blob).unwrap();
    let raw_at = |p: [f64; 3]| {
        let mut c = cal.clone();
        c.frame.layout = crate::model::StringLayout::ALL;
        raw_counts_at(&c, p)
    };
    let mut ctl = Controller::new(
        ControlConfig::default(),
        &compiled,
        raw_at(cal.frame.home),
        0,
    )
    .unwrap();
    ctl.safety().heartbeat(0);
    ctl.safety().arm().unwrap();
    ctl.set_target(Target::Force([0.0, 0.0, -2.0]));
    let mut last = None;
    for k in 1..=200 {
        let t = k as f64 / 200.0;
        let p = [200.0 * t, -150.0 * t, 300.0 + 300.0 * t];
        ctl.safety().heartbeat(k);
        let o = ctl.step(
            &compiled,
            &LoopInput {
                raw_counts: raw_at(p),
                now_ms: k,
                now_us: k * 1000,
                estop: false,
            },
        );
        let err = (0..3)
            .map(|c| (o.position_mm[c] as f64 - p[c]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(err < 0.1, "step {k}: error {err} mm");
        for i in [1, 3, 4, 6] {
            assert_eq!(o.string_lengths_mm[i], 0.0);
            assert_eq!(o.tensions_n[i], 0.0);
        }
        last = Some(o);
    }
    let o = last.unwrap();
    assert!(o.armed && o.faults.is_empty(), "{o:?}");
    assert_eq!(o.tension_status, TensionStatus::Exact);
    let f =
        crate::tension::resultant_force(&compiled.head.frame.anchors, o.position_mm, &o.tensions_n);
    assert!((f[2] + 2.0).abs() < 1e-3 && f[0].abs() < 1e-3 && f[1].abs() < 1e-3);
    // Disarmed: pre-tension on the 4 strings, 0 on the other channels.
    ctl.safety().disarm();
    let o = ctl.step(
        &compiled,
        &LoopInput {
            raw_counts: raw_at([200.0, -150.0, 600.0]),
            now_ms: 201,
            now_us: 201 * 1000,
            estop: false,
        },
    );
    let pre = ControlConfig::default().safety.pretension_n;
    assert_eq!(o.tensions_n, [pre, 0.0, pre, 0.0, 0.0, pre, 0.0, pre]);
}

/// A planar device asked for a force with a `z` component renders and
/// reports its `x, y` only: its strings cannot pull along `z` (a requested
/// `[0, 0, 5]` was reported rendered whole).
#[test]
fn a_planar_device_reports_no_force_along_z() {
    let mut cal = calibration();
    cal.frame.layout = crate::model::StringLayout {
        active: 0b0000_1111,
        planar: true,
    };
    for (i, a) in [
        [-1000.0, -800.0, 0.0],
        [1000.0, -800.0, 0.0],
        [1000.0, 800.0, 0.0],
        [-1000.0, 800.0, 0.0],
    ]
    .into_iter()
    .enumerate()
    {
        cal.frame.anchors[i] = a;
    }
    cal.frame.home = [0.0; 3];
    let blob = compile(&cal, 1, 0).unwrap();
    let compiled = CompiledCalibration::from_blob(&blob).unwrap();
    let raw_at = |p: [f64; 3]| {
        let mut c = cal.clone();
        c.frame.layout = crate::model::StringLayout::ALL;
        raw_counts_at(&c, p)
    };
    let mut ctl =
        Controller::new(ControlConfig::default(), &compiled, raw_at([0.0; 3]), 0).unwrap();
    ctl.safety().heartbeat(0);
    ctl.safety().arm().unwrap();
    ctl.set_target(Target::Force([1.0, 0.0, 5.0]));
    let mut last = None;
    for k in 1..=20 {
        ctl.safety().heartbeat(k);
        last = Some(ctl.step(
            &compiled,
            &LoopInput {
                raw_counts: raw_at([50.0, -30.0, 0.0]),
                now_ms: k,
                now_us: k * 1000,
                estop: false,
            },
        ));
    }
    let o = last.unwrap();
    assert!(o.armed && o.faults.is_empty(), "{o:?}");
    assert_eq!(o.force_n, [1.0, 0.0, 0.0], "{o:?}");
    let f =
        crate::tension::resultant_force(&compiled.head.frame.anchors, o.position_mm, &o.tensions_n);
    let rendered = o.force_n.map(|c| c * o.rendered_fraction);
    assert!(
        (0..3).all(|c| (f[c] - rendered[c]).abs() < 1e-3),
        "{f:?} {rendered:?}"
    );
}

#[test]
fn heartbeat_loss_drops_to_pretension() {
    let cal = calibration();
    let blob = compile(&cal, 1, 0).unwrap();
    let compiled = CompiledCalibration::from_blob(&blob).unwrap();
    let config = ControlConfig::default();
    let raw = raw_counts_at(&cal, [0.0; 3]);
    let mut ctl = Controller::new(config, &compiled, raw, 0).unwrap();
    ctl.safety().heartbeat(0);
    ctl.safety().arm().unwrap();
    ctl.set_target(Target::Force([3.0, 0.0, 0.0]));
    let step = |ctl: &mut Controller, ms| {
        ctl.step(
            &compiled,
            &LoopInput {
                raw_counts: raw,
                now_ms: ms,
                now_us: ms * 1000,
                estop: false,
            },
        )
    };
    assert!(step(&mut ctl, 10).armed);
    let late = step(&mut ctl, 10 + config.safety.heartbeat_timeout_ms + 1);
    assert!(late.faults.contains(SafetyFaults::HEARTBEAT_LOST));
    assert!(late
        .tensions_n
        .iter()
        .all(|&t| t == config.safety.pretension_n));
}

/// A model with a latency on string 2 reads that string's count rate: at
/// 10 kHz, moving at a steady speed, its length is the same model's
/// without the term plus the delay times the string's speed (the rate
/// over the last 3 ms; one count over it is 0.005 mm of the term here),
/// and nothing at rest.
#[test]
fn a_latency_term_adds_the_delay_times_the_string_speed() {
    let plain = calibration();
    let mut late = calibration();
    late.effects.push(crate::model::EffectTerm {
        string: 2,
        effect: crate::model::Effect::Latency { latency_s: 0.006 },
    });
    let run = |cal: &Calibration, speed_mm_s: f64| {
        let blob = compile(cal, 1, 0).unwrap();
        let compiled = CompiledCalibration::from_blob(&blob).unwrap();
        let mut ctl = Controller::new(
            ControlConfig::default(),
            &compiled,
            raw_counts_at(cal, [0.0; 3]),
            0,
        )
        .unwrap();
        let mut last = None;
        for k in 1..=200u32 {
            // 10 kHz: 100 µs a step.
            let p = [speed_mm_s * f64::from(k) * 1e-4, 0.0, 0.0];
            let o = ctl.step(
                &compiled,
                &LoopInput {
                    raw_counts: raw_counts_at(cal, p),
                    now_ms: k / 10,
                    now_us: k * 100,
                    estop: false,
                },
            );
            last = Some(o.string_lengths_mm);
        }
        last.unwrap()
    };
    // String 2's anchor is [-1100, 1100, -1100]: moving along +x it pays
    // out at (x - a_x) / |p - a| of the speed.
    let a = cube_frame([0.0; 3]).anchors[2];
    let p = [400.0 * 0.02, 0.0, 0.0];
    let d = [p[0] - a[0], p[1] - a[1], p[2] - a[2]];
    let string_speed = 400.0 * d[0] / (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let (with, without) = (run(&late, 400.0), run(&plain, 400.0));
    let moved = f64::from(with[2] - without[2]);
    assert!(
        (moved - 0.006 * string_speed).abs() < 0.01,
        "{moved} mm, expected {}",
        0.006 * string_speed
    );
    for i in (0..STRINGS).filter(|&i| i != 2) {
        assert_eq!(with[i], without[i], "string {i}");
    }
    assert_eq!(run(&late, 0.0), run(&plain, 0.0));
}
