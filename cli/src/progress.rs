//! The library's steps drawn as terminal bars and spinners on stderr
//! (indicatif hides them by itself when stderr is not a terminal).

use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};
use spidar::progress::{Reporter, Shown};

/// Draws every [`spidar::progress::Step`] the library begins.
pub struct TerminalBars;

impl Reporter for TerminalBars {
    fn begin(&self, message: &'static str, length: Option<u64>) -> Box<dyn Shown> {
        let bar = match length {
            Some(length) => {
                let bar = ProgressBar::new(length);
                if let Ok(style) = ProgressStyle::with_template(
                    "{msg:>12} [{bar:30}] {pos}/{len} {elapsed_precise} {prefix}",
                ) {
                    bar.set_style(style.progress_chars("=> "));
                }
                bar
            }
            None => {
                let bar = ProgressBar::new_spinner();
                if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} {elapsed}") {
                    bar.set_style(style);
                }
                bar
            }
        };
        bar.set_message(message);
        // A step may sit on one unit for seconds (an SVR axis with a small
        // epsilon): the clock keeps moving so that it shows it is working.
        bar.enable_steady_tick(Duration::from_millis(200));
        Box::new(Drawn(bar))
    }
}

struct Drawn(ProgressBar);

impl Shown for Drawn {
    fn advance(&self, units: u64) {
        self.0.inc(units);
    }

    fn finish(&self) {
        self.0.finish_and_clear();
    }
}
