//! Home captures: where the strings are zeroed, and the slips and drifts
//! that run under a home capture.

use super::bench::{bad_state, calibration, config, raw_at, string_model, Bench, Flash, SLOT};
use crate::blob::compile;
use crate::correction::CorrectionModel;
use crate::device::*;
use crate::kinematics::inverse_kinematics;
use crate::test_fixtures::cube_anchors;
use spidar_protocol::{BadState, DeviceMessage, Request, Response};

#[test]
fn home_rezeroes_the_strings_where_the_operator_holds_the_end_effector() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    // Booted with the end-effector 40 mm off the true home: the nominal
    // model homes there, so every position is off by 40 mm.
    let off = [40.0, -25.0, 10.0];
    let mut b = Bench::new_at(Flash::new(), ram.bytes(), spare.bytes(), raw_at(off));
    // No geometry yet: nothing to home.
    assert_eq!(b.request(&Request::Home), bad_state(BadState::NoGeometry));
    assert_eq!(b.dev.home_declared_us(), None);
    b.tick_at(raw_at(off));
    assert_eq!(
        b.request(&Request::SetNominalGeometry(string_model())),
        Response::Ack
    );
    // The first geometry homes the device where it is, at the last tick.
    assert_eq!(b.dev.home_declared_us(), Some(b.now_us));
    let out = b.tick_at(raw_at([0.0; 3]));
    assert!(
        (out.position_mm[0] + 40.0).abs() < 0.5,
        "{:?}",
        out.position_mm
    );
    // Armed with a force: Home is accepted, the force is dropped.
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetForceTarget {
            force_n: [1.0, 0.0, 0.0]
        }),
        Response::Ack
    );
    let out = b.tick_at(raw_at([0.0; 3]));
    assert_eq!(out.force_n, [1.0, 0.0, 0.0]);
    assert_eq!(
        b.request(&Request::StreamOn { decimation: 1 }),
        Response::Ack
    );
    let homed_at_us = b.now_us;
    // The first geometry was this boot's first home capture.
    assert_eq!(b.dev.home_id(), 0x5eed << 32 | 1);
    assert_eq!(b.request(&Request::Home), Response::Ack);
    assert_eq!(
        b.dev.home_id(),
        0x5eed << 32 | 2,
        "a new home capture, a new id"
    );
    assert_eq!(b.dev.home_declared_us(), Some(homed_at_us));
    let mut out = b.tick_at(raw_at([0.0; 3]));
    for _ in 0..5 {
        out = b.tick_at(raw_at([0.0; 3]));
    }
    // The state frame says when it was sampled, since boot and since home.
    let last = b.states().next_back().unwrap();
    assert_eq!(last.time_us, b.now_us);
    assert_eq!(last.since_home_us, b.now_us - homed_at_us);
    assert_eq!(last.since_home_us, 6000);
    assert_eq!(last.home_id, b.dev.home_id());
    assert_eq!(out.counts, [0; STRINGS]);
    assert!(out.armed);
    assert_eq!(out.force_n, [0.0; 3]);
    for k in 0..3 {
        assert!(out.position_mm[k].abs() < 1e-3, "{:?}", out.position_mm);
    }
    // A move of 100 mm now reads as 100 mm.
    let out = b.tick_at(raw_at([100.0, 0.0, 0.0]));
    assert!(
        (out.position_mm[0] - 100.0).abs() < 0.5,
        "{:?}",
        out.position_mm
    );
    let homed = b
        .stream
        .iter()
        .filter(|p| matches!(p.msg, DeviceMessage::Event(Event::Homed)))
        .count();
    assert_eq!(homed, 1);
}

/// The training's slips in a blob flashed under their home capture: the
/// device applies them until the next `Home` (or a reboot), not after.
#[test]
fn training_slips_apply_under_their_home_capture_until_the_next_home() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    b.tick_at(raw_at([0.0; 3]));
    assert_eq!(
        b.request(&Request::SetNominalGeometry(string_model())),
        Response::Ack
    );
    let training_home = b.dev.home_id();
    // Slips that lengthen each string as a move of `d` would: under them
    // the strings at home read as the end-effector at `d`.
    let d = [6.0, -4.0, 3.0];
    let at_d = inverse_kinematics(&cube_anchors(), d);
    let at_home = inverse_kinematics(&cube_anchors(), [0.0; 3]);
    let mut cal = calibration(CorrectionModel::None);
    cal.home = Some(crate::model::HomeSlips {
        home_id: training_home,
        slips: (0..STRINGS)
            .map(|i| crate::model::EffectTerm {
                string: i as u8,
                effect: crate::model::Effect::Slip {
                    at_s: 0.0,
                    mm: at_d[i] - at_home[i],
                },
            })
            .collect(),
    });
    let blob = compile(&cal, 9, 0).unwrap();
    for _ in 0..3 {
        b.tick_at(raw_at([0.0; 3]));
    }
    assert_eq!(b.upload(&blob, 9, 256), Response::Committed { model_id: 9 });
    assert_eq!(b.dev.home_id(), training_home, "a flash keeps the home");
    // The room position less the frame's translation (its rotation and
    // scale are the identity): the device-frame position, corrected.
    let t = cal.frame.room_translation;
    let corrected = |out: &LoopOutput| {
        let p = out.corrected_q16.map(|v| f64::from(v) / 65536.0);
        [p[0] - t[0], p[1] - t[1], p[2] - t[2]]
    };
    let near = |p: [f64; 3], q: [f64; 3]| (0..3).all(|k| (p[k] - q[k]).abs() < 0.05);
    let mut out = b.tick_at(raw_at([0.0; 3]));
    for _ in 0..20 {
        out = b.tick_at(raw_at([0.0; 3]));
    }
    assert!(near(corrected(&out), d), "{:?}", corrected(&out));
    for i in 0..STRINGS {
        let slip = (at_d[i] - at_home[i]) as f32;
        assert!(
            (out.string_lengths_mm[i] - at_home[i] as f32 - slip).abs() < 1e-3,
            "string {i}: {} mm",
            out.string_lengths_mm[i]
        );
    }
    // A new home capture: the strings are counted as they are, no slip.
    assert_eq!(b.request(&Request::Home), Response::Ack);
    assert_ne!(b.dev.home_id(), training_home);
    for _ in 0..20 {
        out = b.tick_at(raw_at([0.0; 3]));
    }
    assert!(near(corrected(&out), [0.0; 3]), "{:?}", corrected(&out));
    // A reboot (another boot id): a new home capture too.
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let config = DeviceConfig {
        boot_id: 0x5eee,
        ..config()
    };
    let mut dev = Device::new(
        config,
        flash,
        ram.bytes(),
        spare.bytes(),
        raw_at([0.0; 3]),
        0,
    )
    .unwrap();
    assert_eq!(dev.home_id(), 0x5eee << 32 | 1);
    for k in 1..=20 {
        out = dev.tick(&TickInput {
            raw_counts: raw_at([0.0; 3]),
            now_us: k * 1000,
            estop: false,
        });
    }
    assert!(near(corrected(&out), [0.0; 3]), "{:?}", corrected(&out));
}

/// A drift reads the time since home: it starts again from 0 at a new home
/// capture by itself (decision record 0049, "Device side").
#[test]
fn a_drift_starts_again_at_a_new_home_capture() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let mut cal = calibration(CorrectionModel::None);
    cal.effects.push(crate::model::EffectTerm {
        string: 4,
        effect: crate::model::Effect::Drift { mm_per_s: 0.5 },
    });
    let blob = compile(&cal, 3, 0).unwrap();
    assert_eq!(b.upload(&blob, 3, 256), Response::Committed { model_id: 3 });
    let home_length = inverse_kinematics(&cube_anchors(), [0.0; 3])[4] as f32;
    let drift_at =
        |b: &mut Bench<'_>| b.tick_at(raw_at([0.0; 3])).string_lengths_mm[4] - home_length;
    for _ in 0..1999 {
        b.tick_at(raw_at([0.0; 3]));
    }
    // 2 s after the boot's home capture: 1 mm.
    assert!((drift_at(&mut b) - 1.0).abs() < 2e-3);
    assert_eq!(b.request(&Request::Home), Response::Ack);
    // 1 ms after the new one: 0.5 um.
    assert!(drift_at(&mut b).abs() < 2e-3);
}
