//! Error codes, the thread-local last-error message, and the guard every
//! exported function runs its body in (no panic crosses the FFI boundary).

use std::cell::RefCell;
use std::ffi::{c_char, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};

use host::device::link::LinkError;

/// Every code the library returns (as `int32_t`: the functions' return
/// type does not depend on the size C gives an enum).
#[repr(i32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum spidar_error {
    /// Success.
    SPIDAR_OK = 0,
    /// A pointer argument was NULL.
    SPIDAR_E_NULL = -1,
    /// An argument is out of range (a force that is not finite, a port name
    /// that is not UTF-8, an empty blob, ...).
    SPIDAR_E_ARGUMENT = -2,
    /// The serial port is missing, busy or cannot be opened.
    SPIDAR_E_PORT = -3,
    /// The device did not answer in time (or the stream fell silent).
    SPIDAR_E_TIMEOUT = -4,
    /// The device speaks another protocol version.
    SPIDAR_E_VERSION = -5,
    /// The device refused the request (its reason is in the message).
    SPIDAR_E_REFUSED = -6,
    /// The device disarmed itself since the application armed it (its
    /// heartbeat watchdog after a stalled application, or another fault,
    /// named in the message). `spidar_arm` arms it again.
    SPIDAR_E_DISARMED = -7,
    /// No state frame has arrived yet.
    SPIDAR_E_NO_STATE = -8,
    /// The model blob is invalid, or the device does not hold it.
    SPIDAR_E_BLOB = -9,
    /// The room frame of the device's model is unknown to the library (a
    /// model flashed before this session): `spidar_use_model` with its blob.
    SPIDAR_E_FRAME_UNKNOWN = -10,
    /// Reading or writing the port failed, or the device answered something
    /// unexpected.
    SPIDAR_E_IO = -11,
    /// The virtual device could not start.
    SPIDAR_E_VIRTUAL = -12,
    /// A bug in the library (a panic, caught at the boundary).
    SPIDAR_E_INTERNAL = -13,
    /// The link is gone (a failed `spidar_flash` could not restart the
    /// stream): close the handle.
    SPIDAR_E_CLOSED = -14,
}

// The codes as the functions return them (the header has the enum).
pub const SPIDAR_OK: i32 = spidar_error::SPIDAR_OK as i32;
pub const SPIDAR_E_NULL: i32 = spidar_error::SPIDAR_E_NULL as i32;
pub const SPIDAR_E_ARGUMENT: i32 = spidar_error::SPIDAR_E_ARGUMENT as i32;
pub const SPIDAR_E_PORT: i32 = spidar_error::SPIDAR_E_PORT as i32;
pub const SPIDAR_E_TIMEOUT: i32 = spidar_error::SPIDAR_E_TIMEOUT as i32;
pub const SPIDAR_E_VERSION: i32 = spidar_error::SPIDAR_E_VERSION as i32;
pub const SPIDAR_E_REFUSED: i32 = spidar_error::SPIDAR_E_REFUSED as i32;
pub const SPIDAR_E_DISARMED: i32 = spidar_error::SPIDAR_E_DISARMED as i32;
pub const SPIDAR_E_NO_STATE: i32 = spidar_error::SPIDAR_E_NO_STATE as i32;
pub const SPIDAR_E_BLOB: i32 = spidar_error::SPIDAR_E_BLOB as i32;
pub const SPIDAR_E_FRAME_UNKNOWN: i32 = spidar_error::SPIDAR_E_FRAME_UNKNOWN as i32;
pub const SPIDAR_E_IO: i32 = spidar_error::SPIDAR_E_IO as i32;
pub const SPIDAR_E_VIRTUAL: i32 = spidar_error::SPIDAR_E_VIRTUAL as i32;
pub const SPIDAR_E_INTERNAL: i32 = spidar_error::SPIDAR_E_INTERNAL as i32;
pub const SPIDAR_E_CLOSED: i32 = spidar_error::SPIDAR_E_CLOSED as i32;

/// Every code with its name, for [`crate::spidar_error_name`].
pub const NAMES: [(i32, &str); 15] = [
    (SPIDAR_OK, "SPIDAR_OK\0"),
    (SPIDAR_E_NULL, "SPIDAR_E_NULL\0"),
    (SPIDAR_E_ARGUMENT, "SPIDAR_E_ARGUMENT\0"),
    (SPIDAR_E_PORT, "SPIDAR_E_PORT\0"),
    (SPIDAR_E_TIMEOUT, "SPIDAR_E_TIMEOUT\0"),
    (SPIDAR_E_VERSION, "SPIDAR_E_VERSION\0"),
    (SPIDAR_E_REFUSED, "SPIDAR_E_REFUSED\0"),
    (SPIDAR_E_DISARMED, "SPIDAR_E_DISARMED\0"),
    (SPIDAR_E_NO_STATE, "SPIDAR_E_NO_STATE\0"),
    (SPIDAR_E_BLOB, "SPIDAR_E_BLOB\0"),
    (SPIDAR_E_FRAME_UNKNOWN, "SPIDAR_E_FRAME_UNKNOWN\0"),
    (SPIDAR_E_IO, "SPIDAR_E_IO\0"),
    (SPIDAR_E_VIRTUAL, "SPIDAR_E_VIRTUAL\0"),
    (SPIDAR_E_INTERNAL, "SPIDAR_E_INTERNAL\0"),
    (SPIDAR_E_CLOSED, "SPIDAR_E_CLOSED\0"),
];

/// A failed call: its code and what to tell the application.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Error {
    pub code: i32,
    pub message: String,
}

impl Error {
    pub fn new(code: i32, message: impl Into<String>) -> Error {
        Error {
            code,
            message: message.into(),
        }
    }

    /// A NULL pointer where `argument` of `function` must point somewhere.
    pub fn null(function: &str, argument: &str) -> Error {
        Error::new(SPIDAR_E_NULL, format!("{function}: `{argument}` is NULL"))
    }
}

impl From<LinkError> for Error {
    fn from(e: LinkError) -> Error {
        let code = match &e {
            LinkError::PortMissing { .. } | LinkError::PortBusy { .. } | LinkError::Open { .. } => {
                SPIDAR_E_PORT
            }
            LinkError::Timeout { .. }
            | LinkError::StreamStopped { .. }
            | LinkError::CommitUnanswered { .. } => SPIDAR_E_TIMEOUT,
            LinkError::VersionMismatch { .. } => SPIDAR_E_VERSION,
            LinkError::Rejected { .. } => SPIDAR_E_REFUSED,
            LinkError::InvalidBlob(_) | LinkError::Verify { .. } => SPIDAR_E_BLOB,
            LinkError::Unexpected { .. } | LinkError::Io { .. } => SPIDAR_E_IO,
        };
        Error::new(code, e.to_string())
    }
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

/// Records `message` as this thread's last error.
pub fn set_last_error(message: &str) {
    // An interior NUL would cut the C string: shown as a space.
    let text = CString::new(message.replace('\0', " ")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = text);
}

/// This thread's last error message; valid until this thread's next call
/// into the library.
pub fn last_error_ptr() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

/// Runs `body` as the body of an exported function: its error becomes the
/// returned code and this thread's last error; a panic becomes
/// [`SPIDAR_E_INTERNAL`]. Success clears the last error.
pub fn guard(function: &str, body: impl FnOnce() -> Result<(), Error>) -> i32 {
    match catch_unwind(AssertUnwindSafe(body)) {
        Ok(Ok(())) => {
            set_last_error("");
            SPIDAR_OK
        }
        Ok(Err(e)) => {
            set_last_error(&e.message);
            e.code
        }
        Err(panic) => {
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic".into());
            set_last_error(&format!(
                "{function}: internal error (please report it): {what}"
            ));
            SPIDAR_E_INTERNAL
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_becomes_a_code_and_a_message() {
        let code = guard("spidar_test", || panic!("boom"));
        assert_eq!(code, SPIDAR_E_INTERNAL);
        let msg = unsafe { std::ffi::CStr::from_ptr(last_error_ptr()) };
        assert!(msg
            .to_str()
            .unwrap()
            .contains("spidar_test: internal error"));
        assert!(msg.to_str().unwrap().contains("boom"));
    }

    #[test]
    fn success_clears_the_last_error_and_errors_keep_their_code() {
        assert_eq!(
            guard("f", || Err(Error::new(
                SPIDAR_E_PORT,
                "serial port /dev/x: gone"
            ))),
            SPIDAR_E_PORT
        );
        let msg = unsafe { std::ffi::CStr::from_ptr(last_error_ptr()) };
        assert_eq!(msg.to_str().unwrap(), "serial port /dev/x: gone");
        assert_eq!(guard("f", || Ok(())), SPIDAR_OK);
        let msg = unsafe { std::ffi::CStr::from_ptr(last_error_ptr()) };
        assert_eq!(msg.to_str().unwrap(), "");
    }

    #[test]
    fn every_code_has_one_name() {
        let mut codes: Vec<i32> = NAMES.iter().map(|(c, _)| *c).collect();
        codes.sort_unstable();
        codes.dedup();
        assert_eq!(codes.len(), NAMES.len());
        assert!(NAMES
            .iter()
            .all(|(_, n)| n.ends_with('\0') && n.starts_with("SPIDAR_")));
    }
}
