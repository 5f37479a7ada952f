//! Safety: the nominal model's and the limits' checks, the heartbeat, the
//! e-stop and overruns, and the loop's faults on the wire.

use super::bench::{bad_state, raw_at, string_model, Bench, Flash, SLOT};
use crate::device::*;
use crate::safety::SafetyFaults;
use spidar_protocol::messages::name;
use spidar_protocol::{BadState, DeviceError, DeviceMessage, Limits, Request, Response};

#[test]
fn nominal_string_model_limits_and_estop() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let mut m = string_model();
    m.pulley_radius_mm[3] = -1.0;
    assert_eq!(
        b.dev.handle(&Request::SetNominalGeometry(m), 0),
        Response::Error(DeviceError::InvalidArgument {
            field: name("pulley_radius_mm")
        })
    );
    m = string_model();
    m.anchors_mm[2][1] = f32::INFINITY;
    assert_eq!(
        b.dev.handle(&Request::SetNominalGeometry(m), 0),
        Response::Error(DeviceError::InvalidArgument {
            field: name("anchors_mm")
        })
    );
    // The nominal model homes the device now (end-effector at home).
    assert_eq!(
        b.request(&Request::SetNominalGeometry(string_model())),
        Response::Ack
    );
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    let limits = Limits {
        pre_tension_n: 2.0,
        max_tension_n: 20.0,
        heartbeat_timeout_ms: 50,
    };
    assert_eq!(b.request(&Request::SetLimits(limits)), Response::Ack);
    assert_eq!(
        b.dev.handle(
            &Request::SetLimits(Limits {
                heartbeat_timeout_ms: 0,
                ..limits
            }),
            0
        ),
        Response::Error(DeviceError::InvalidArgument {
            field: name("heartbeat_timeout_ms")
        })
    );
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetLimits(limits)),
        bad_state(BadState::Armed)
    );
    let p = [-150.0, 80.0, 30.0];
    let out = b.tick_at(raw_at(p));
    assert!(out.armed, "{out:?}");
    for (got, want) in out.position_mm.iter().zip(p) {
        assert!((got - want as f32).abs() < 0.05, "{out:?}");
    }
    // Idle: the distribution's internal tension level, within the limits.
    assert!(
        out.tensions_n.iter().all(|&t| (0.5..=20.0).contains(&t)),
        "{out:?}"
    );
    // The new heartbeat timeout: 50 ms (Arm at T, ticks at T+1..=T+50).
    for _ in 0..49 {
        assert!(b.tick_at(raw_at(p)).armed);
    }
    let out = b.tick_at(raw_at(p));
    assert!(!out.armed && out.faults.contains(SafetyFaults::HEARTBEAT_LOST));
    assert_eq!(out.tensions_n, [2.0; STRINGS]);
    // Guidance target, then the emergency stop.
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetGuidanceTarget {
            target_mm: [0.0, 0.0, 0.0],
            d_min_mm: 5.0,
            f_max_n: 3.0
        }),
        Response::Ack
    );
    assert!(b.tick_at(raw_at(p)).force_n.iter().any(|f| f.abs() > 0.1));
    b.now_us += 1000;
    let out = b.dev.tick(&TickInput {
        raw_counts: raw_at(p),
        now_us: b.now_us,
        estop: true,
    });
    assert!(!out.armed && out.faults.contains(SafetyFaults::ESTOP));
    assert!(!b.dev.motors_enabled());
    assert_eq!(b.request(&Request::Arm), bad_state(BadState::Faulted));
    let out = b.tick_at(raw_at(p)); // e-stop released
    assert!(out.faults.contains(SafetyFaults::ESTOP)); // still latched
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert!(b.tick_at(raw_at(p)).armed);
    // Overrun: latched, reported, cleared by ClearFaults.
    b.dev.record_loop_time(150);
    b.request(&Request::StreamOn { decimation: 1 });
    b.tick_at(raw_at(p));
    let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
        panic!("no state")
    };
    assert!(s.faults.contains(Faults::LOOP_OVERRUN));
    assert_eq!(b.dev.stats().loop_overruns, 1);
    b.request(&Request::ClearFaults);
    b.tick_at(raw_at(p));
    let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
        panic!("no state")
    };
    assert!(!s.faults.contains(Faults::LOOP_OVERRUN));
    assert!(s.armed);
}

/// Every combination of the loop's faults maps to the wire by name: a fault
/// the wire names keeps its bit, the kinematic ones become `KINEMATICS`,
/// `OVERFORCE` does not go out, and nothing else is set.
#[test]
fn every_loop_fault_combination_reaches_the_wire_by_name() {
    let singles = [
        (SafetyFaults::HEARTBEAT_LOST, Faults::HEARTBEAT_LOST),
        (SafetyFaults::MODEL_INVALID, Faults::MODEL_INVALID),
        (SafetyFaults::ESTOP, Faults::ESTOP),
        (SafetyFaults::SLACK, Faults::KINEMATICS),
        (SafetyFaults::FK_FAULT, Faults::KINEMATICS),
        (SafetyFaults::NON_FINITE, Faults::KINEMATICS),
        (SafetyFaults::OVERFORCE, Faults(0)),
    ];
    let mut every = SafetyFaults::NONE;
    for (f, _) in singles {
        assert!(!every.intersects(f), "two loop faults share a bit");
        every |= f;
    }
    assert_eq!(every, SafetyFaults::ALL);
    for combination in 0u32..(1 << singles.len()) {
        let mut faults = SafetyFaults::NONE;
        let mut expected = 0u16;
        for (k, (f, wire)) in singles.iter().enumerate() {
            if combination & (1 << k) != 0 {
                faults |= *f;
                expected |= wire.0;
            }
        }
        let mut out = idle_output(false, false);
        out.faults = faults;
        assert_eq!(protocol_faults(&out, false), Faults(expected), "{faults:?}");
        assert_eq!(
            protocol_faults(&out, true),
            Faults(expected | Faults::LOOP_OVERRUN.0)
        );
    }
    // The shared names sit on the same bits on both sides.
    for (f, name) in Faults::NAMED {
        let loop_side = match name {
            "HEARTBEAT_LOST" => SafetyFaults::HEARTBEAT_LOST,
            "MODEL_INVALID" => SafetyFaults::MODEL_INVALID,
            "ESTOP" => SafetyFaults::ESTOP,
            _ => continue,
        };
        assert_eq!(loop_side.bits(), f.0, "{name}");
    }
}
