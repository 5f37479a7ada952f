//! The terminal live view of a procedure: one status block redrawn in place
//! on standard error (at most `fps` times a second) and the audio cue.
//!
//! ```text
//! cell 214/2197 [#####...............] 9.7%  ETA 71 min
//! target [ -250.0   83.3 1250.0] mm   marker [ -244.1   80.2 1262.5] mm   13.8 mm to go
//! beep 0 Hz   force 0.00 N   reach the pink cell
//! ```
//!
//! Standard error so that a report on standard output stays clean; not a
//! terminal (a log file, CI): one line per second instead of redraws.

use std::io::{IsTerminal, Write};
use std::time::{Duration, Instant};

use crate::audio::AudioOut;
use spidar::device::cues::{CueSink, Cues};

/// Renders [`Cues`] in the terminal and plays the beep.
pub struct TerminalView {
    audio: AudioOut,
    tty: bool,
    every: Duration,
    last: Option<Instant>,
    lines: usize,
}

impl TerminalView {
    /// A view that redraws at most `fps` times a second.
    pub fn new(audio: AudioOut, fps: f64) -> TerminalView {
        let tty = std::io::stderr().is_terminal();
        let fps = if fps.is_finite() && fps > 0.0 {
            fps
        } else {
            10.0
        };
        TerminalView {
            audio,
            tty,
            every: Duration::from_secs_f64(if tty { 1.0 / fps } else { 1.0 }),
            last: None,
            lines: 0,
        }
    }
}

fn fmt_mm(p: &Option<[f64; 3]>) -> String {
    match p {
        Some(p) => format!("[{:7.1} {:7.1} {:7.1}] mm", p[0], p[1], p[2]),
        None => "(occluded)".into(),
    }
}

fn fmt_duration(d: Duration) -> String {
    let s = d.as_secs();
    if s >= 3600 {
        format!("{} h {:02} min", s / 3600, (s % 3600) / 60)
    } else if s >= 60 {
        format!("{} min {:02} s", s / 60, s % 60)
    } else {
        format!("{s} s")
    }
}

/// The lines of the view for `cues`.
pub fn render(cues: &Cues) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some(p) = cues.progress {
        let total = p.total.max(1);
        let width = 30;
        let filled = (p.done * width / total).min(width);
        lines.push(format!(
            "cell {}/{} [{}{}] {:.1}%  {}",
            p.done,
            p.total,
            "#".repeat(filled),
            ".".repeat(width - filled),
            100.0 * p.done as f64 / total as f64,
            match p.time_left {
                Some(t) => format!("ETA {}", fmt_duration(t)),
                None => "ETA -".into(),
            }
        ));
    }
    let mut where_line = String::new();
    if cues.target_room_mm.is_some() {
        where_line.push_str(&format!("target {}   ", fmt_mm(&cues.target_room_mm)));
    }
    where_line.push_str(&format!("marker {}", fmt_mm(&cues.marker_room_mm)));
    if let Some(d) = cues.distance_mm {
        where_line.push_str(&format!("   {d:.1} mm to go"));
    }
    lines.push(where_line);
    let f = cues.force_n;
    let force = f.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
    lines.push(format!(
        "beep {:4.0} Hz   force {force:.2} N   {}",
        cues.beep_hz, cues.message
    ));
    lines
}

impl CueSink for TerminalView {
    fn show(&mut self, cues: &Cues) {
        self.audio.set_frequency(cues.beep_hz);
        if self.last.is_some_and(|t| t.elapsed() < self.every) {
            return;
        }
        self.last = Some(Instant::now());
        let lines = render(cues);
        let mut err = std::io::stderr().lock();
        if self.tty {
            // Back to the top of the previous block, clearing each line.
            if self.lines > 0 {
                let _ = write!(err, "\x1b[{}F", self.lines);
            }
            for l in &lines {
                let _ = writeln!(err, "\x1b[2K{l}");
            }
        } else {
            let _ = writeln!(err, "{}", lines.join(" | "));
        }
        let _ = err.flush();
        self.lines = lines.len();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use spidar::device::cues::Progress;

    #[test]
    fn the_view_names_progress_target_marker_and_cues() {
        let lines = render(&Cues {
            marker_room_mm: Some([1.0, 2.0, 3.0]),
            target_room_mm: Some([4.0, 5.0, 6.0]),
            target_half_size_mm: 40.0,
            distance_mm: Some(5.2),
            beep_hz: 500.0,
            force_n: [3.0, 4.0, 0.0],
            progress: Some(Progress {
                done: 10,
                total: 40,
                time_left: Some(Duration::from_secs(125)),
            }),
            message: "reach the cell".into(),
        });
        let text = lines.join("\n");
        assert!(text.contains("cell 10/40"), "{text}");
        assert!(text.contains("25.0%"), "{text}");
        assert!(text.contains("ETA 2 min 05 s"), "{text}");
        assert!(text.contains("5.2 mm to go"), "{text}");
        assert!(text.contains("force 5.00 N"), "{text}");
        assert!(text.contains("beep  500 Hz"), "{text}");
        let occluded = render(&Cues::default()).join("\n");
        assert!(occluded.contains("(occluded)"), "{occluded}");
    }
}
