//! What a lab engineer runs (the paper's sections 4.1, 4.3.1, 5 and 5.5).
//!
//! - [`calibrate`]: the whole calibration of a device from a training and a
//!   test session (`spidar calibrate`);
//! - [`report_page`]: the calibration's report as one page for people,
//!   `report.html` (written by `calibrate`, rebuilt by `spidar report`);
//! - [`demo`]: a simulated device calibrated from its simulated sessions,
//!   then measured on a virtual device (`spidar demo`);
//! - [`init`]: guided initialization (`spidar init`): the haptic and audio
//!   cues (eqs. 2-5) bring the marker to the frame centre, home is declared
//!   when it holds there, and the room-to-device transform is recorded;
//! - [`collect`]: lattice data collection (`spidar collect`);
//! - [`monitor`]: runtime monitoring and refit (`spidar monitor`);
//! - what the operator is shown and hears is [`crate::device::cues`] (the
//!   command line draws it in the terminal and plays the beep).
//!
//! A simulated operator for tests and demos is [`crate::sim::operator`].

/// "1 row", "3 rows": a count and its noun, for every message a
/// procedure writes (the report page's too).
pub(crate) fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

mod arm_watch;
pub mod calibrate;
pub mod collect;
pub mod demo;
pub mod init;
pub mod monitor;
pub mod report_page;
