//! The C calls as C sees them, from Rust: NULL pointers and bad arguments
//! are codes with messages, never undefined behaviour; a missing port is
//! named; a stalled application finds the device disarmed by its watchdog
//! and is told so on its next call (in device time: `fast` virtual device).

use std::ffi::{CStr, CString};
use std::ptr::{null, null_mut};

use spidar_capi::*;

fn last_error() -> String {
    unsafe { CStr::from_ptr(spidar_last_error()) }
        .to_str()
        .unwrap()
        .to_string()
}

/// A virtual device of simulator seed `seed` holding still, in device
/// time (its clock runs only while the stream is read), the default
/// heartbeat timeout.
fn open_virtual_in_device_time(seed: u64) -> *mut spidar_device {
    let options = spidar_virtual_options {
        seed,
        heartbeat_timeout_ms: 0,
        fast: 1,
        hold: 1,
    };
    let mut dev = null_mut();
    assert_eq!(
        spidar_open_virtual(&options, &mut dev),
        SPIDAR_OK,
        "{}",
        last_error()
    );
    dev
}

fn zeroed<T>() -> T {
    // SAFETY: the library's structs are plain integers, floats and arrays.
    unsafe { std::mem::zeroed() }
}

#[test]
fn null_pointers_are_errors_that_name_the_argument() {
    let mut state: spidar_state = zeroed();
    let mut info: spidar_info = zeroed();
    let mut model: spidar_model_info = zeroed();
    let calls: [(&str, i32); 12] = [
        ("spidar_open", spidar_open(null(), null_mut())),
        (
            "spidar_open_virtual",
            spidar_open_virtual(null(), null_mut()),
        ),
        ("spidar_close", spidar_close(null_mut())),
        ("spidar_get_info", spidar_get_info(null_mut(), &mut info)),
        ("spidar_arm", spidar_arm(null_mut())),
        ("spidar_disarm", spidar_disarm(null_mut())),
        ("spidar_heartbeat", spidar_heartbeat(null_mut())),
        (
            "spidar_set_force",
            spidar_set_force(null_mut(), 0.0, 0.0, 0.0),
        ),
        ("spidar_get_state", spidar_get_state(null_mut(), &mut state)),
        (
            "spidar_wait_state",
            spidar_wait_state(null_mut(), 1, &mut state),
        ),
        (
            "spidar_flash",
            spidar_flash(null_mut(), null(), 0, &mut model),
        ),
        (
            "spidar_get_model_info",
            spidar_get_model_info(null_mut(), &mut model),
        ),
    ];
    for (name, code) in calls {
        assert_eq!(code, SPIDAR_E_NULL, "{name}");
        let _ = name;
    }
    assert_eq!(spidar_use_model(null_mut(), null(), 0), SPIDAR_E_NULL);
    assert!(
        last_error().contains("spidar_use_model: `dev` is NULL"),
        "{}",
        last_error()
    );
    let name = unsafe { CStr::from_ptr(spidar_error_name(SPIDAR_E_DISARMED)) };
    assert_eq!(name.to_str().unwrap(), "SPIDAR_E_DISARMED");
    let name = unsafe { CStr::from_ptr(spidar_error_name(12345)) };
    assert_eq!(name.to_str().unwrap(), "SPIDAR_E_UNKNOWN");
    assert_eq!(spidar_struct_size(null()), 0);
    let state_name = CString::new("spidar_state").unwrap();
    assert_eq!(
        spidar_struct_size(state_name.as_ptr()),
        std::mem::size_of::<spidar_state>()
    );
}

#[test]
fn a_missing_port_is_named() {
    let port = CString::new("/dev/spidar-no-such-port").unwrap();
    let mut dev = null_mut();
    assert_eq!(spidar_open(port.as_ptr(), &mut dev), SPIDAR_E_PORT);
    assert!(dev.is_null());
    assert!(
        last_error().contains("/dev/spidar-no-such-port"),
        "{}",
        last_error()
    );
}

#[test]
fn a_stalled_application_is_disarmed_by_the_watchdog_and_told_on_its_next_call() {
    // Device time runs only while the stream is read, back to back: the
    // application's stall is measured in device time, whatever the machine.
    let dev = open_virtual_in_device_time(3);
    let mut model: spidar_model_info = zeroed();
    assert_eq!(spidar_get_model_info(dev, &mut model), SPIDAR_OK);
    assert_eq!(
        (model.has_model, model.model_id),
        (1, SPIDAR_VIRTUAL_MODEL_ID)
    );
    assert_eq!(spidar_arm(dev), SPIDAR_OK, "{}", last_error());
    // The application stalls: no call. The stream goes on; wait (in device
    // time) for the watchdog, then 100 ms more.
    let mut s: spidar_state = zeroed();
    let mut tripped: Option<u64> = None;
    for _ in 0..100_000 {
        assert_eq!(
            spidar_wait_state(dev, 10_000, &mut s),
            SPIDAR_OK,
            "{}",
            last_error()
        );
        if tripped.is_none() && s.faults & 1 != 0 {
            tripped = Some(s.time_us);
        }
        if tripped.is_some_and(|t| s.time_us >= t + 100_000) {
            break;
        }
    }
    assert!(tripped.is_some(), "the watchdog never tripped: {s:?}");
    let names = unsafe { CStr::from_ptr(s.fault_names.as_ptr()) };
    assert!(names.to_str().unwrap().contains("HEARTBEAT_LOST"));
    assert_eq!((s.armed, s.motors_on), (0, 1), "{s:?}");
    // The next call says so, naming the port and the cause...
    assert_eq!(spidar_set_force(dev, 0.0, 0.0, 1.0), SPIDAR_E_DISARMED);
    let why = last_error();
    assert!(why.contains("serial port /dev/pts/"), "{why}");
    assert!(
        why.contains("disarmed itself, faults HEARTBEAT_LOST"),
        "{why}"
    );
    // ...once: the device holds pre-tension, the application knows.
    assert_eq!(spidar_heartbeat(dev), SPIDAR_OK, "{}", last_error());
    assert_eq!(spidar_disarm(dev), SPIDAR_OK);
    // A force of NaN is refused before it goes anywhere.
    assert_eq!(spidar_set_force(dev, f64::NAN, 0.0, 0.0), SPIDAR_E_ARGUMENT);
    assert_eq!(s.lost, 0);
    assert_eq!(spidar_close(dev), SPIDAR_OK, "{}", last_error());
}

/// The virtual device's calibration again (the same simulated device as
/// `spidar_open_virtual` with `seed`), compiled under another model id.
fn virtual_blob(seed: u64, model_id: u32) -> Vec<u8> {
    let mut sim = host::sim::SimConfig::default();
    sim.abnormal_motor.enabled = false;
    sim.effects.clear();
    let device = host::sim::SimulatedDevice::new(&sim, seed).unwrap();
    let calibration = spidar_core::model::Calibration {
        frame: device.frame,
        strings: device.laws,
        effects: device.effects.clone(),
        correction: spidar_core::correction::CorrectionModel::None,
        length_scale_mm: [0.0; spidar_core::STRINGS],
        kinematics: Default::default(),
        home: None,
    };
    spidar_core::blob::compile(&calibration, model_id, 0).unwrap()
}

#[test]
fn a_model_is_flashed_while_the_stream_runs_and_a_bad_blob_is_refused() {
    let dev = open_virtual_in_device_time(4);
    let mut s: spidar_state = zeroed();
    assert_eq!(spidar_wait_state(dev, 10_000, &mut s), SPIDAR_OK);
    assert_eq!(s.model_id, SPIDAR_VIRTUAL_MODEL_ID);
    // The virtual device's first boot (id 1) homed once, with its model.
    assert_eq!(s.home_id, 1 << 32 | 1);
    // A blob that is not one: refused before anything is sent, named.
    let junk = [7u8; 64];
    assert_eq!(
        spidar_flash(dev, junk.as_ptr(), junk.len(), null_mut()),
        SPIDAR_E_BLOB
    );
    assert!(last_error().starts_with("model blob: "), "{}", last_error());
    assert_eq!(
        spidar_flash(dev, junk.as_ptr(), 0, null_mut()),
        SPIDAR_E_ARGUMENT
    );
    // A real one: uploaded with the stream paused, read back, and the
    // stream's states carry it from then on.
    let blob = virtual_blob(4, 0x0BAD_CAFE);
    let mut model: spidar_model_info = zeroed();
    assert_eq!(
        spidar_flash(dev, blob.as_ptr(), blob.len(), &mut model),
        SPIDAR_OK,
        "{}",
        last_error()
    );
    assert_eq!((model.has_model, model.model_id), (1, 0x0BAD_CAFE));
    let mut again: spidar_model_info = zeroed();
    assert_eq!(spidar_get_model_info(dev, &mut again), SPIDAR_OK);
    assert_eq!(again.blob_crc32, model.blob_crc32);
    let mut seen = false;
    for _ in 0..1000 {
        assert_eq!(
            spidar_wait_state(dev, 10_000, &mut s),
            SPIDAR_OK,
            "{}",
            last_error()
        );
        if s.model_id == 0x0BAD_CAFE {
            seen = true;
            break;
        }
    }
    assert!(seen, "the stream never carried the new model: {s:?}");
    // Another blob is not the device's model: use_model refuses it,
    // naming both CRCs; the flashed one is accepted.
    let other = virtual_blob(4, 0x0BAD_F00D);
    assert_eq!(
        spidar_use_model(dev, other.as_ptr(), other.len()),
        SPIDAR_E_BLOB
    );
    assert!(
        last_error().contains("is not this blob"),
        "{}",
        last_error()
    );
    assert_eq!(spidar_use_model(dev, blob.as_ptr(), blob.len()), SPIDAR_OK);
    // Refused while the motors are on: the device's reason, named.
    assert_eq!(spidar_arm(dev), SPIDAR_OK);
    assert_eq!(
        spidar_flash(dev, other.as_ptr(), other.len(), null_mut()),
        SPIDAR_E_REFUSED
    );
    assert!(last_error().contains("refused"), "{}", last_error());
    // The stream runs on after the refusal.
    let before = s.index;
    assert_eq!(
        spidar_wait_state(dev, 10_000, &mut s),
        SPIDAR_OK,
        "{}",
        last_error()
    );
    assert!(s.index > before);
    assert_eq!(spidar_close(dev), SPIDAR_OK, "{}", last_error());
}
