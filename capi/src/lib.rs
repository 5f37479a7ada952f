//! `libspidar_capi`: the C API of a SPIDAR device, in the shape haptics SDKs
//! have (Force Dimension's `dhd`, CHAI3D's `cGenericHapticDevice`): open,
//! arm, set a force, read the state, disarm, close; errors as codes with a
//! thread-local message. `include/spidar.h` is generated from this file
//! (`tests/header.rs` keeps it so) and carries the rules below; the Python
//! package (`python/`) loads this library with ctypes.
//!
//! # Threads and ownership
//!
//! - A `spidar_device *` comes from `spidar_open` or `spidar_open_virtual`
//!   and belongs to the application until `spidar_close`, which frees it;
//!   it must not be used after that, nor closed twice.
//! - Calls on one handle may come from several threads; requests are sent
//!   one at a time. `spidar_get_state` never waits for a request in flight.
//!   `spidar_flash` pauses every other call on the handle while it runs.
//!   `spidar_close` must not run while another call on the same handle does.
//! - A background thread of the library reads the device's stream; it
//!   never sends anything. The device's heartbeat is the application's own
//!   calls (`spidar_set_force`, `spidar_heartbeat`, any request): an
//!   application that stalls longer than the device's heartbeat timeout
//!   (20 ms on the firmware) finds the device disarmed by its watchdog, and
//!   its next `spidar_set_force` or `spidar_heartbeat` returns
//!   `SPIDAR_E_DISARMED`.
//! - Every function returns `SPIDAR_OK` (0) or a negative code; then
//!   `spidar_last_error()` is this thread's message, naming the port and
//!   the cause. Its pointer stays valid until this thread's next call.
//! - NULL pointers are refused with `SPIDAR_E_NULL`; no panic crosses the
//!   boundary (`SPIDAR_E_INTERNAL`).
//!
//! # Units and frames
//!
//! Millimetres, newtons, microseconds. Positions and forces are in the
//! room frame of the device's model (the calibration's tracker frame; a
//! device without a model: its nominal geometry's frame).

#![allow(non_camel_case_types)]
// Every exported function checks its pointers and documents what they
// must point to; clippy's lint asks for `unsafe fn`, which C does not see.
#![allow(clippy::not_unsafe_ptr_arg_deref)]

mod convert;
mod error;
mod session;
mod virtual_rig;

use std::ffi::{c_char, CStr};
use std::time::Duration;

pub use convert::{
    spidar_info, spidar_link_stats, spidar_model_info, spidar_state, SPIDAR_DEVICE_ID_LEN,
    SPIDAR_FAULT_NAMES_LEN, SPIDAR_STRINGS,
};
pub use error::*;
pub use session::Session;
pub use virtual_rig::{spidar_virtual_options, SPIDAR_VIRTUAL_MODEL_ID};

use host::device::link::ClientOptions;

/// An open device (opaque).
pub struct spidar_device {
    session: Session,
}

/// Version of this API: changes when a function or struct changes.
pub const SPIDAR_API_VERSION: u32 = 2;

fn device<'a>(function: &str, dev: *mut spidar_device) -> Result<&'a spidar_device, Error> {
    // SAFETY: non-NULL handles come from spidar_open*, valid until
    // spidar_close (the header's ownership rule).
    unsafe { dev.as_ref() }.ok_or_else(|| Error::null(function, "dev"))
}

fn write_out<T>(function: &str, out: *mut T, value: T) -> Result<(), Error> {
    if out.is_null() {
        return Err(Error::null(function, "out"));
    }
    // SAFETY: non-NULL, and the caller passes a pointer to a `T`.
    unsafe { out.write(value) };
    Ok(())
}

fn blob_slice<'a>(function: &str, blob: *const u8, len: usize) -> Result<&'a [u8], Error> {
    if blob.is_null() {
        return Err(Error::null(function, "blob"));
    }
    if len == 0 {
        return Err(Error::new(
            SPIDAR_E_ARGUMENT,
            format!("{function}: the blob is empty"),
        ));
    }
    // SAFETY: non-NULL, and the caller passes `len` readable bytes.
    Ok(unsafe { std::slice::from_raw_parts(blob, len) })
}

fn open_handle(out: *mut *mut spidar_device, session: Session) -> Result<(), Error> {
    let handle = Box::into_raw(Box::new(spidar_device { session }));
    // SAFETY: `out` was checked non-NULL by the caller of this function.
    unsafe { out.write(handle) };
    Ok(())
}

/// Opens the device on serial `port` (e.g. "/dev/ttyACM0"), says Hello,
/// and starts the state stream (every control-loop iteration). On success
/// `*out` is the handle; on failure `*out` is left as it was.
#[no_mangle]
pub extern "C" fn spidar_open(port: *const c_char, out: *mut *mut spidar_device) -> i32 {
    guard("spidar_open", || {
        if port.is_null() {
            return Err(Error::null("spidar_open", "port"));
        }
        if out.is_null() {
            return Err(Error::null("spidar_open", "out"));
        }
        // SAFETY: non-NULL; the caller passes a NUL-terminated string.
        let name = unsafe { CStr::from_ptr(port) }.to_str().map_err(|_| {
            Error::new(SPIDAR_E_ARGUMENT, "spidar_open: the port name is not UTF-8")
        })?;
        open_handle(out, Session::open(name, ClientOptions::default())?)
    })
}

/// Starts a virtual device in this process (the firmware's logic on a
/// simulated plant, behind a pseudo-terminal) with its true calibration
/// flashed, and opens it as `spidar_open` does. `options` may be NULL
/// (all defaults). `spidar_close` stops the virtual device.
#[no_mangle]
pub extern "C" fn spidar_open_virtual(
    options: *const spidar_virtual_options,
    out: *mut *mut spidar_device,
) -> i32 {
    guard("spidar_open_virtual", || {
        if out.is_null() {
            return Err(Error::null("spidar_open_virtual", "out"));
        }
        // SAFETY: NULL or a pointer to options (the caller's).
        let options = unsafe { options.as_ref() }.copied().unwrap_or_default();
        let (vd, client, blob) = virtual_rig::spawn_virtual(&options)?;
        let session = Session::start(client, Some(vd))?;
        // The library made the blob: its room frame is known.
        session.use_model(&blob)?;
        open_handle(out, session)
    })
}

/// Sets no force, disarms, stops the stream, closes the port and frees the
/// handle (also when one of those steps fails: its error is returned, the
/// handle is freed all the same).
#[no_mangle]
pub extern "C" fn spidar_close(dev: *mut spidar_device) -> i32 {
    guard("spidar_close", || {
        if dev.is_null() {
            return Err(Error::null("spidar_close", "dev"));
        }
        // SAFETY: a handle from spidar_open*, closed once (the header's rule).
        let handle = unsafe { Box::from_raw(dev) };
        handle.session.shut()
    })
}

/// What the device said about itself when it was opened.
#[no_mangle]
pub extern "C" fn spidar_get_info(dev: *mut spidar_device, out: *mut spidar_info) -> i32 {
    guard("spidar_get_info", || {
        let d = device("spidar_get_info", dev)?;
        write_out("spidar_get_info", out, d.session.info()?)
    })
}

/// Arms the device: the motors on, forces rendered from now on (the
/// device clears the faults whose cause has gone). Keep calling
/// `spidar_set_force` or `spidar_heartbeat` faster than its heartbeat
/// timeout.
#[no_mangle]
pub extern "C" fn spidar_arm(dev: *mut spidar_device) -> i32 {
    guard("spidar_arm", || device("spidar_arm", dev)?.session.arm())
}

/// Disarms the device: the motors off.
#[no_mangle]
pub extern "C" fn spidar_disarm(dev: *mut spidar_device) -> i32 {
    guard("spidar_disarm", || {
        device("spidar_disarm", dev)?.session.disarm()
    })
}

/// Keeps an armed device armed without changing its force.
/// `SPIDAR_E_DISARMED` (once) if the device disarmed itself since
/// `spidar_arm`.
#[no_mangle]
pub extern "C" fn spidar_heartbeat(dev: *mut spidar_device) -> i32 {
    guard("spidar_heartbeat", || {
        device("spidar_heartbeat", dev)?.session.heartbeat()
    })
}

/// Sets the force on the end-effector, room frame, N (the device limits
/// it); returns once the device has it. Also the heartbeat.
/// `SPIDAR_E_DISARMED` (once) if the device disarmed itself since
/// `spidar_arm`; `SPIDAR_E_FRAME_UNKNOWN` while the model's room frame is
/// unknown (see `spidar_use_model`).
#[no_mangle]
pub extern "C" fn spidar_set_force(
    dev: *mut spidar_device,
    fx_n: f64,
    fy_n: f64,
    fz_n: f64,
) -> i32 {
    guard("spidar_set_force", || {
        device("spidar_set_force", dev)?
            .session
            .set_force([fx_n, fy_n, fz_n])
    })
}

/// The newest state frame, without waiting; `SPIDAR_E_NO_STATE` before
/// the first.
#[no_mangle]
pub extern "C" fn spidar_get_state(dev: *mut spidar_device, out: *mut spidar_state) -> i32 {
    guard("spidar_get_state", || {
        let d = device("spidar_get_state", dev)?;
        if out.is_null() {
            return Err(Error::null("spidar_get_state", "out"));
        }
        write_out("spidar_get_state", out, d.session.state()?)
    })
}

/// Waits (at most `timeout_ms`, else `SPIDAR_E_TIMEOUT`) until a state
/// frame newer than the last one this handle returned has come, and
/// returns the newest (frames between are skipped: `index` counts them).
#[no_mangle]
pub extern "C" fn spidar_wait_state(
    dev: *mut spidar_device,
    timeout_ms: u32,
    out: *mut spidar_state,
) -> i32 {
    guard("spidar_wait_state", || {
        let d = device("spidar_wait_state", dev)?;
        if out.is_null() {
            return Err(Error::null("spidar_wait_state", "out"));
        }
        let s = d
            .session
            .wait_state(Duration::from_millis(u64::from(timeout_ms)))?;
        write_out("spidar_wait_state", out, s)
    })
}

/// Uploads the model blob `blob[0..len]` (a `spidar compile` output),
/// makes it the device's model and reads its info back into `out` (which
/// may be NULL). The device refuses while its motors are on: disarm first.
#[no_mangle]
pub extern "C" fn spidar_flash(
    dev: *mut spidar_device,
    blob: *const u8,
    len: usize,
    out: *mut spidar_model_info,
) -> i32 {
    guard("spidar_flash", || {
        let d = device("spidar_flash", dev)?;
        let bytes = blob_slice("spidar_flash", blob, len)?;
        let info = d.session.flash(bytes)?;
        if !out.is_null() {
            write_out("spidar_flash", out, info)?;
        }
        Ok(())
    })
}

/// Tells the library that the device's model is `blob[0..len]` (flashed
/// before this session), checked against the device's model header and
/// blob CRC: forces
/// and the rendered force use its room frame from now on.
#[no_mangle]
pub extern "C" fn spidar_use_model(dev: *mut spidar_device, blob: *const u8, len: usize) -> i32 {
    guard("spidar_use_model", || {
        let d = device("spidar_use_model", dev)?;
        d.session
            .use_model(blob_slice("spidar_use_model", blob, len)?)
    })
}

/// The device's active model (`has_model` 0 when it has none).
#[no_mangle]
pub extern "C" fn spidar_get_model_info(
    dev: *mut spidar_device,
    out: *mut spidar_model_info,
) -> i32 {
    guard("spidar_get_model_info", || {
        let d = device("spidar_get_model_info", dev)?;
        if out.is_null() {
            return Err(Error::null("spidar_get_model_info", "out"));
        }
        write_out("spidar_get_model_info", out, d.session.model_info()?)
    })
}

/// How the stream fared since the handle was opened (asks the device for
/// its counters: a request, also a heartbeat).
#[no_mangle]
pub extern "C" fn spidar_get_link_stats(
    dev: *mut spidar_device,
    out: *mut spidar_link_stats,
) -> i32 {
    guard("spidar_get_link_stats", || {
        let d = device("spidar_get_link_stats", dev)?;
        if out.is_null() {
            return Err(Error::null("spidar_get_link_stats", "out"));
        }
        write_out("spidar_get_link_stats", out, d.session.link_stats()?)
    })
}

/// This thread's last error message ("" after a success); valid until this
/// thread's next call into the library. Never NULL.
#[no_mangle]
pub extern "C" fn spidar_last_error() -> *const c_char {
    error::last_error_ptr()
}

/// The name of an error code ("SPIDAR_E_TIMEOUT", ...; "SPIDAR_E_UNKNOWN"
/// for a code this library does not have). Static; never NULL.
#[no_mangle]
pub extern "C" fn spidar_error_name(code: i32) -> *const c_char {
    error::NAMES
        .iter()
        .find(|(c, _)| *c == code)
        .map_or("SPIDAR_E_UNKNOWN\0", |(_, n)| n)
        .as_ptr()
        .cast()
}

/// `SPIDAR_API_VERSION` of the library (a program checks it against the
/// header it was built with).
#[no_mangle]
pub extern "C" fn spidar_api_version() -> u32 {
    SPIDAR_API_VERSION
}

/// Size in bytes of the library's struct `name` ("spidar_state",
/// "spidar_info", "spidar_model_info", "spidar_virtual_options",
/// "spidar_link_stats"), 0 for
/// another name or NULL: bindings (Python's ctypes) check their layouts
/// with it.
#[no_mangle]
pub extern "C" fn spidar_struct_size(name: *const c_char) -> usize {
    if name.is_null() {
        return 0;
    }
    // SAFETY: non-NULL; the caller passes a NUL-terminated string.
    let name = unsafe { CStr::from_ptr(name) };
    match name.to_bytes() {
        b"spidar_state" => std::mem::size_of::<spidar_state>(),
        b"spidar_info" => std::mem::size_of::<spidar_info>(),
        b"spidar_model_info" => std::mem::size_of::<spidar_model_info>(),
        b"spidar_virtual_options" => std::mem::size_of::<spidar_virtual_options>(),
        b"spidar_link_stats" => std::mem::size_of::<spidar_link_stats>(),
        _ => 0,
    }
}
