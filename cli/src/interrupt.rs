//! SIGINT (Ctrl-C) and SIGTERM for the commands that hold a device armed or
//! run until stopped (`device force`, `device arm --hold`, `collect`,
//! `init`, `monitor`): the first of either signal raises a flag; the
//! command's long waits poll it, stop, leave the device with no force and
//! disarmed, say so, and end as [`Interrupted`] (exit 128 + the signal's
//! number: 130 for SIGINT, 143 for SIGTERM) unless being stopped is the
//! command's normal end (`monitor` without `--seconds`). A second signal of
//! the same kind ends the process as usual (each handler resets itself):
//! a way out of a cleanup that hangs.
//!
//! Commands that hold nothing (`device info`, `stream`, `calibrate`, ...)
//! install no handler: a signal ends them at once, as it always did.

use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use nix::sys::signal::Signal;
use spidar::device::tracker::{Next, SourceStats, TrackerError, TrackerSource};

/// The first signal handled (its number), 0 before any.
static SIGNAL: AtomicI32 = AtomicI32::new(0);

/// The flag handed to the library (`CollectConfig::cancel`). Set before the
/// handlers are installed, so that in the handler `get` is one atomic load
/// and a pointer read: no lock, no allocation.
static FLAG: OnceLock<Arc<AtomicBool>> = OnceLock::new();

extern "C" fn on_signal(signo: nix::libc::c_int) {
    // Async-signal-safe: atomic operations only. The first signal is the
    // one reported.
    let _ = SIGNAL.compare_exchange(0, signo, Ordering::SeqCst, Ordering::SeqCst);
    if let Some(flag) = FLAG.get() {
        flag.store(true, Ordering::SeqCst);
    }
}

/// Installs the SIGINT and SIGTERM handlers (again is harmless); the flag
/// they raise, for a library procedure's cancel setting. `None` if a
/// handler cannot be installed (the command then runs without, and a
/// signal ends it at once).
pub fn install() -> Option<Arc<AtomicBool>> {
    use nix::sys::signal::{sigaction, SaFlags, SigAction, SigHandler, SigSet};
    let flag = FLAG
        .get_or_init(|| Arc::new(AtomicBool::new(false)))
        .clone();
    let action = SigAction::new(
        SigHandler::Handler(on_signal),
        SaFlags::SA_RESETHAND | SaFlags::SA_RESTART,
        SigSet::empty(),
    );
    for signal in [Signal::SIGINT, Signal::SIGTERM] {
        // SAFETY: the handler only does atomic operations.
        unsafe { sigaction(signal, &action) }.ok()?;
    }
    Some(flag)
}

/// The signal that interrupted the command, if one came.
pub fn received() -> Option<Signal> {
    match SIGNAL.load(Ordering::SeqCst) {
        0 => None,
        n => Signal::try_from(n).ok(),
    }
}

/// A signal came (the long waits stop on it).
pub fn raised() -> bool {
    SIGNAL.load(Ordering::SeqCst) != 0
}

/// A command stopped by a signal after its cleanup: `main` prints `output`
/// on standard output (the summary a normal end prints), `message` on
/// standard error, and exits with [`Interrupted::exit_code`].
#[derive(Debug)]
pub struct Interrupted {
    pub signal: Signal,
    pub output: String,
    pub message: String,
}

impl Interrupted {
    /// `message` (which names `signal` as [`signal_name`] gives it) after
    /// `output`; `None` when no signal came.
    pub fn if_received(
        output: String,
        message: impl FnOnce(&str) -> String,
    ) -> Option<Interrupted> {
        let signal = received()?;
        Some(Interrupted {
            signal,
            output,
            message: message(signal_name(signal)),
        })
    }

    /// 128 + the signal's number, as a shell reports a process the signal
    /// ended (130 for SIGINT, 143 for SIGTERM).
    pub fn exit_code(&self) -> i32 {
        128 + self.signal as i32
    }
}

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for Interrupted {}

/// How a signal is named in messages: `SIGINT (Ctrl-C)`, `SIGTERM`.
pub fn signal_name(signal: Signal) -> &'static str {
    match signal {
        Signal::SIGINT => "SIGINT (Ctrl-C)",
        other => other.as_str(),
    }
}

/// A tracker source that ends once a signal came: a procedure that stops
/// when its tracker ends (`monitor`, `init`) then stops there, through its
/// own cleanup (force off, disarmed, stream off).
pub struct EndOnInterrupt<'a>(pub &'a mut dyn TrackerSource);

impl TrackerSource for EndOnInterrupt<'_> {
    fn next_frame(&mut self, timeout: Duration) -> Result<Next, TrackerError> {
        if raised() {
            return Ok(Next::End);
        }
        self.0.next_frame(timeout)
    }

    fn stats(&self) -> SourceStats {
        self.0.stats()
    }

    fn busy(&mut self) {
        self.0.busy();
    }
}
