//! The audio cue of guided initialization (paper, eq. 3): discrete beeps
//! whose pitch is `f(d) = 1000 h(d)` Hz, silent beyond `d_min`.
//!
//! [`BeepSynth`] makes the sound: 16-bit mono PCM, beeps of
//! [`BEEP_ON`] separated by [`BEEP_OFF`] of silence, a sine at the current
//! pitch with the phase kept across pitch changes (no clicks). [`AudioOut`]
//! plays it:
//! - `Player`: raw PCM piped to `aplay` (ALSA) or `pacat` (PulseAudio /
//!   PipeWire), whichever is on `PATH`, from a thread that keeps the pipe
//!   fed in 20 ms blocks (the player's own clock paces it);
//! - `Bell`: the terminal bell, once per beep, faster as `h` grows (a pitch
//!   the terminal cannot play; the rate still says "closer");
//! - `Off`.
//!
//! We pipe to a player instead of linking an audio crate (cpal and the like
//! need the ALSA development headers on every build machine, CI included,
//! for a cue that is one sine wave).

use std::io::Write;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Samples per second of the synthesized cue.
pub const SAMPLE_RATE_HZ: u32 = 16_000;
/// Length of one beep.
pub const BEEP_ON: Duration = Duration::from_millis(80);
/// Silence between beeps.
pub const BEEP_OFF: Duration = Duration::from_millis(70);
/// Peak amplitude (about a quarter of full scale).
const AMPLITUDE: f64 = 8_000.0;

/// The beep generator: a sine at the current pitch, gated on and off.
#[derive(Clone, Debug, Default)]
pub struct BeepSynth {
    phase: f64,
    /// Samples since the start of the current beep period.
    in_period: u64,
}

impl BeepSynth {
    pub fn new() -> BeepSynth {
        BeepSynth::default()
    }

    /// Appends `n` samples at pitch `frequency_hz` (0 or not finite: silence)
    /// to `out`.
    pub fn fill(&mut self, frequency_hz: f32, n: usize, out: &mut Vec<i16>) {
        let rate = f64::from(SAMPLE_RATE_HZ);
        let on = (BEEP_ON.as_secs_f64() * rate) as u64;
        let period = on + (BEEP_OFF.as_secs_f64() * rate) as u64;
        let f = f64::from(frequency_hz);
        let audible = f.is_finite() && f > 0.0;
        for _ in 0..n {
            let gate = audible && self.in_period < on;
            let sample = if gate {
                (AMPLITUDE * self.phase.sin()).round() as i16
            } else {
                0
            };
            out.push(sample);
            if audible {
                self.phase = (self.phase + 2.0 * std::f64::consts::PI * f / rate)
                    % (2.0 * std::f64::consts::PI);
            }
            self.in_period = (self.in_period + 1) % period;
        }
    }
}

/// Where the audio cue goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
// The variants are described in the options' help (`--audio`), not here:
// clap would print them as a list and every command's help would change
// layout.
pub enum AudioChoice {
    // A PCM player if one is installed, else the terminal bell.
    Auto,
    // `aplay` or `pacat` (fails if neither is on PATH).
    Player,
    // The terminal bell.
    Bell,
    Off,
}

/// Why the audio cue cannot play.
#[derive(Debug, thiserror::Error)]
pub enum AudioError {
    #[error("audio: neither `aplay` nor `pacat` is on PATH (use --audio bell or --audio off)")]
    NoPlayer,
    #[error("audio: cannot start `{player}`: {source}")]
    Spawn {
        player: &'static str,
        source: std::io::Error,
    },
}

/// A running audio cue.
pub enum AudioOut {
    Player {
        frequency: Arc<AtomicU32>,
        stop: Arc<AtomicBool>,
        thread: Option<JoinHandle<()>>,
        child: Child,
    },
    Bell {
        last: Option<Instant>,
    },
    Off,
}

fn on_path(program: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|paths| std::env::split_paths(&paths).any(|dir| dir.join(program).is_file()))
}

fn player_command() -> Option<(&'static str, Command)> {
    let rate = SAMPLE_RATE_HZ.to_string();
    if on_path("aplay") {
        let mut c = Command::new("aplay");
        c.args([
            "-q", "-t", "raw", "-f", "S16_LE", "-c", "1", "-r", &rate, "-",
        ]);
        return Some(("aplay", c));
    }
    if on_path("pacat") {
        let mut c = Command::new("pacat");
        c.args([
            "--playback",
            "--raw",
            "--format=s16le",
            "--channels=1",
            &format!("--rate={rate}"),
        ]);
        return Some(("pacat", c));
    }
    None
}

impl AudioOut {
    /// Starts the cue as chosen.
    pub fn open(choice: AudioChoice) -> Result<AudioOut, AudioError> {
        match choice {
            AudioChoice::Off => Ok(AudioOut::Off),
            AudioChoice::Bell => Ok(AudioOut::Bell { last: None }),
            AudioChoice::Auto => match Self::player() {
                Ok(p) => Ok(p),
                Err(_) => Ok(AudioOut::Bell { last: None }),
            },
            AudioChoice::Player => Self::player(),
        }
    }

    fn player() -> Result<AudioOut, AudioError> {
        let (player, mut command) = player_command().ok_or(AudioError::NoPlayer)?;
        let mut child = command
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|source| AudioError::Spawn { player, source })?;
        let Some(mut stdin) = child.stdin.take() else {
            return Err(AudioError::Spawn {
                player,
                source: std::io::Error::other("no stdin pipe"),
            });
        };
        let frequency = Arc::new(AtomicU32::new(0f32.to_bits()));
        let stop = Arc::new(AtomicBool::new(false));
        let (f, s) = (frequency.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("audio-cue".into())
            .spawn(move || {
                let mut synth = BeepSynth::new();
                let block = (SAMPLE_RATE_HZ / 50) as usize; // 20 ms
                let mut samples = Vec::with_capacity(block);
                let mut bytes = Vec::with_capacity(2 * block);
                while !s.load(Ordering::Relaxed) {
                    samples.clear();
                    synth.fill(
                        f32::from_bits(f.load(Ordering::Relaxed)),
                        block,
                        &mut samples,
                    );
                    bytes.clear();
                    for x in &samples {
                        bytes.extend_from_slice(&x.to_le_bytes());
                    }
                    // The player blocks the pipe at its own pace; an error
                    // means it is gone: the cue stops, the procedure goes on.
                    if stdin.write_all(&bytes).is_err() {
                        break;
                    }
                }
            })
            .map_err(|source| AudioError::Spawn { player, source })?;
        Ok(AudioOut::Player {
            frequency,
            stop,
            thread: Some(thread),
            child,
        })
    }

    /// Sets the pitch, Hz (0: silent).
    pub fn set_frequency(&mut self, frequency_hz: f32) {
        match self {
            AudioOut::Player { frequency, .. } => {
                frequency.store(frequency_hz.to_bits(), Ordering::Relaxed)
            }
            AudioOut::Bell { last } => {
                if !(frequency_hz.is_finite() && frequency_hz > 0.0) {
                    return;
                }
                // One bell per second far out, ten per second on the target.
                let h = f64::from(frequency_hz / 1000.0).clamp(0.0, 1.0);
                let every = Duration::from_secs_f64(1.0 / (1.0 + 9.0 * h));
                if last.is_none_or(|t| t.elapsed() >= every) {
                    let mut err = std::io::stderr();
                    let _ = err.write_all(b"\x07");
                    let _ = err.flush();
                    *last = Some(Instant::now());
                }
            }
            AudioOut::Off => {}
        }
    }
}

impl Drop for AudioOut {
    fn drop(&mut self) {
        if let AudioOut::Player {
            stop,
            thread,
            child,
            ..
        } = self
        {
            stop.store(true, Ordering::Relaxed);
            let _ = child.kill();
            if let Some(t) = thread.take() {
                let _ = t.join();
            }
            let _ = child.wait();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Upward zero crossings = cycles of the sine.
    fn cycles(samples: &[i16]) -> usize {
        samples.windows(2).filter(|w| w[0] < 0 && w[1] >= 0).count()
    }

    #[test]
    fn beeps_have_the_pitch_of_eq_3_and_a_gap() {
        let mut synth = BeepSynth::new();
        let mut out = Vec::new();
        let one_second = SAMPLE_RATE_HZ as usize;
        synth.fill(500.0, one_second, &mut out);
        // Beeps are on 80 of every 150 ms: 1 s holds 6 beeps and 2/3 of one
        // period... count cycles inside the first beep only.
        let on = (BEEP_ON.as_secs_f64() * f64::from(SAMPLE_RATE_HZ)) as usize;
        let first = cycles(&out[..on]);
        assert!(
            (39..=41).contains(&first),
            "{first} cycles in 80 ms at 500 Hz"
        );
        // Then silence.
        let gap_end = on + (BEEP_OFF.as_secs_f64() * f64::from(SAMPLE_RATE_HZ)) as usize;
        assert!(out[on..gap_end].iter().all(|&x| x == 0));
        assert!(out[gap_end..gap_end + on].iter().any(|&x| x != 0));
        // A higher pitch has more cycles per beep.
        let mut out = Vec::new();
        BeepSynth::new().fill(1000.0, on, &mut out);
        assert!((79..=81).contains(&cycles(&out)));
    }

    #[test]
    fn silence_beyond_d_min_and_for_bad_input() {
        for f in [0.0, -5.0, f32::NAN, f32::INFINITY] {
            let mut out = Vec::new();
            BeepSynth::new().fill(f, 4000, &mut out);
            assert!(out.iter().all(|&x| x == 0), "{f}");
        }
    }
}
