//! String layouts: devices with fewer strings arm only when force closed.

use super::bench::{config, string_model, Bench, Flash, CPR, RADIUS, SLOT};
use crate::device::*;
use crate::kinematics::inverse_kinematics;
use crate::tension::TensionStatus;
use crate::test_fixtures::cube_anchors;
use spidar_protocol::messages::name;
use spidar_protocol::{DeviceError, DeviceMessage, Request, Response};

/// Raw counters for the end-effector at `p` with strings from `anchors`,
/// reading 1000 at `home`.
fn raw_for(anchors: &[[f64; 3]; STRINGS], home: [f64; 3], p: [f64; 3]) -> [u16; STRINGS] {
    let lengths = inverse_kinematics(anchors, p);
    let at_home = inverse_kinematics(anchors, home);
    core::array::from_fn(|i| {
        let theta = (lengths[i] - at_home[i]) / RADIUS;
        let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
        (1000 + counts) as u16
    })
}

/// Devices with fewer strings: the layout travels in `SetNominalGeometry`;
/// `Arm` is refused, saying why, when the strings cannot pull in every
/// direction, and the device still tracks and streams; a tetrahedron of
/// 4 strings around the end-effector arms and renders, with the unused
/// channels at tension 0.
#[test]
fn string_layouts_arm_only_when_force_closed_and_track_either_way() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    // Fewer strings than degrees of freedom: refused, naming the field.
    let mut m = string_model();
    m.active_strings = 0b0000_0011;
    assert_eq!(
        b.dev.handle(&Request::SetNominalGeometry(m), 0),
        Response::Error(DeviceError::InvalidArgument {
            field: name("active_strings")
        })
    );
    // Unused channels need no valid law or anchor.
    let mut m = string_model();
    m.active_strings = 0b0001_0110;
    m.counts_per_rev[0] = 0;
    m.pulley_radius_mm[3] = f32::NAN;
    m.anchors_mm[7] = [f32::NAN; 3];
    assert_eq!(b.request(&Request::SetNominalGeometry(m)), Response::Ack);
    // Three strings in space: never force closed.
    assert_eq!(
        b.request(&Request::Arm),
        Response::Error(DeviceError::NotForceClosed {
            strings: 3,
            dof: 3,
            too_few_strings: true
        })
    );

    // Four strings from the ceiling (a hanging design): enough strings,
    // but they only pull up.
    let h = 1100.0;
    let mut hanging = [[0.0f64; 3]; STRINGS];
    for (i, (x, y)) in [(-h, -h), (h, -h), (h, h), (-h, h)].into_iter().enumerate() {
        hanging[i] = [x, y, h];
    }
    let mut m = string_model();
    m.active_strings = 0b0000_1111;
    m.anchors_mm = hanging.map(|a| a.map(|v| v as f32));
    assert_eq!(b.request(&Request::SetNominalGeometry(m)), Response::Ack);
    assert_eq!(
        b.request(&Request::Arm),
        Response::Error(DeviceError::NotForceClosed {
            strings: 4,
            dof: 3,
            too_few_strings: false
        })
    );
    // Tracking and the stream go on unarmed.
    assert_eq!(
        b.request(&Request::StreamOn { decimation: 1 }),
        Response::Ack
    );
    let p = [120.0, -80.0, -200.0];
    let mut out = b.tick_at(raw_for(&hanging, [0.0; 3], [0.0; 3]));
    for _ in 0..20 {
        out = b.tick_at(raw_for(&hanging, [0.0; 3], p));
    }
    assert!(!out.armed);
    for (got, want) in out.position_mm.iter().zip(p) {
        assert!((got - want as f32).abs() < 0.1, "{out:?}");
    }
    let pre = config().control.safety.pretension_n;
    assert_eq!(out.tensions_n, [pre, pre, pre, pre, 0.0, 0.0, 0.0, 0.0]);
    let last_state = b
        .stream
        .iter()
        .rev()
        .find_map(|p| match &p.msg {
            DeviceMessage::State(s) => Some(*s),
            _ => None,
        })
        .expect("state frames");
    assert!(!last_state.armed);
    assert!((last_state.position_mm[0] - 120.0).abs() < 0.1);

    // A tetrahedron (cube corners 0, 3, 5, 6) around the end-effector:
    // armed, renders, unused channels at 0. Home is declared again.
    let mut m = string_model();
    m.active_strings = 0b0110_1001;
    assert_eq!(b.request(&Request::SetNominalGeometry(m)), Response::Ack);
    assert_eq!(b.request(&Request::Home), Response::Ack);
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetForceTarget {
            force_n: [1.0, -0.5, 0.5]
        }),
        Response::Ack
    );
    let home_raw = raw_for(&hanging, [0.0; 3], p);
    let shift = |q: [f64; 3]| -> [u16; STRINGS] {
        // Counters continue from where they were at Home.
        let d = raw_for(&cube_anchors(), [0.0; 3], q);
        core::array::from_fn(|i| home_raw[i].wrapping_add(d[i].wrapping_sub(1000)))
    };
    let q = [100.0, 50.0, -60.0];
    let mut out = b.tick_at(shift([0.0; 3]));
    for _ in 0..10 {
        out = b.tick_at(shift(q));
    }
    assert!(out.armed && out.faults.is_empty(), "{out:?}");
    assert_eq!(out.tension_status, TensionStatus::Exact);
    for i in [1, 2, 4, 7] {
        assert_eq!(out.tensions_n[i], 0.0);
    }
    let f = crate::tension::resultant_force(
        &cube_anchors().map(|a| a.map(|v| v as f32)),
        out.position_mm,
        &core::array::from_fn(|i| {
            if [0, 3, 5, 6].contains(&i) {
                out.tensions_n[i]
            } else {
                0.0
            }
        }),
    );
    for (got, want) in f.iter().zip([1.0, -0.5, 0.5]) {
        assert!((got - want).abs() < 1e-3, "{f:?}");
    }
}
