//! How a long step says how far it has got: a facade, as the `log` crate is
//! for messages. The library names the step (a bar of known length, or a
//! spinner) and advances it; whoever runs the library decides whether and
//! how to show it by installing a [`Reporter`] once ([`set_reporter`]): the
//! `spidar` command line draws terminal bars on stderr. Without a reporter,
//! or for a step its caller asked to keep quiet, a [`Step`] does nothing.
//!
//! The library itself never writes to the terminal.

use std::sync::OnceLock;

/// Shows steps: what `spidar` installs to draw bars and spinners.
pub trait Reporter: Send + Sync {
    /// A step begins: `length` units of work (`None`: a spinner), named
    /// `message`.
    fn begin(&self, message: &'static str, length: Option<u64>) -> Box<dyn Shown>;
}

/// One step as the reporter shows it.
pub trait Shown: Send + Sync {
    /// `units` more of the step's work are done.
    fn advance(&self, units: u64);
    /// The step is over: take it off the screen.
    fn finish(&self);
}

static REPORTER: OnceLock<Box<dyn Reporter>> = OnceLock::new();

/// Installs the process's reporter. Only the first call takes effect (as
/// `log::set_logger`); it returns `false` when a reporter was already set.
pub fn set_reporter(reporter: Box<dyn Reporter>) -> bool {
    REPORTER.set(reporter).is_ok()
}

/// A step in progress; shown by the installed reporter unless quiet.
pub struct Step(Option<Box<dyn Shown>>);

impl Step {
    /// A step of `length` units (a bar).
    pub fn bar(length: u64, message: &'static str, quiet: bool) -> Step {
        Step::begin(message, Some(length), quiet)
    }

    /// A step of unknown length (a spinner).
    pub fn spinner(message: &'static str, quiet: bool) -> Step {
        Step::begin(message, None, quiet)
    }

    fn begin(message: &'static str, length: Option<u64>, quiet: bool) -> Step {
        match REPORTER.get() {
            Some(reporter) if !quiet => Step(Some(reporter.begin(message, length))),
            _ => Step(None),
        }
    }

    /// `units` more are done.
    pub fn inc(&self, units: u64) {
        if let Some(shown) = &self.0 {
            shown.advance(units);
        }
    }

    /// The step is over.
    pub fn finish_and_clear(&self) {
        if let Some(shown) = &self.0 {
            shown.finish();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quiet_step_or_one_without_a_reporter_shows_nothing_and_does_not_fail() {
        let step = Step::bar(3, "quiet", true);
        step.inc(1);
        step.finish_and_clear();
        assert!(step.0.is_none());
        let spinner = Step::spinner("no reporter in this test binary", false);
        spinner.inc(1);
        spinner.finish_and_clear();
    }
}
