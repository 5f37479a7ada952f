//! What a procedure shows and plays the operator at one moment.
//!
//! Procedures talk to the operator through [`Cues`]: everything shown or
//! played at one moment (target, marker, distance, beep, force, progress),
//! handed to a [`CueSink`]. The command line renders them in the terminal
//! and plays the beep; a simulated operator reads them to decide where to
//! move, exactly what a person would see and hear, nothing more.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// How far a procedure has got.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Progress {
    pub done: usize,
    pub total: usize,
    /// Estimated time to finish (None until there is a rate to go by).
    pub time_left: Option<Duration>,
}

/// Everything a procedure shows and plays to the operator at one moment.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Cues {
    /// The marker as the tracker sees it, room frame, mm (None: occluded).
    pub marker_room_mm: Option<[f64; 3]>,
    /// A visible target to bring the marker to (the lattice's target cell),
    /// room frame, mm. Guided initialization shows none: its cues are the
    /// beep and the force.
    pub target_room_mm: Option<[f64; 3]>,
    /// Half edge of the target cell, mm (0 without a target).
    pub target_half_size_mm: f64,
    /// Distance from the marker to where it should go, mm.
    pub distance_mm: Option<f64>,
    /// Audio cue: beep frequency, Hz (0: silent), eq. 3.
    pub beep_hz: f32,
    /// Haptic cue sent to the device, device frame, N.
    pub force_n: [f32; 3],
    pub progress: Option<Progress>,
    /// One line for the operator ("hold still", "marker occluded", ...).
    pub message: String,
}

/// Where cues go: a terminal view and speaker, or a simulated operator.
pub trait CueSink {
    fn show(&mut self, cues: &Cues);
}

/// Cues kept for whoever reads them next (a simulated operator in another
/// thread). Clones share the same cues.
///
/// Stamped ([`SharedCues::stamped_by`]): each cue is kept with the number of
/// tracker frames the procedure had taken when it showed it, so that a
/// reader in step with the procedure can ask for its answer to a given
/// frame ([`SharedCues::shown_before`]) instead of whatever the procedure
/// has got to by the time the machine runs the reader.
#[derive(Clone, Debug, Default)]
pub struct SharedCues {
    /// The latest cue per stamp, the last [`SharedCues::KEEP`] stamps.
    inner: Arc<Mutex<BTreeMap<u64, Cues>>>,
    progress: Option<crate::device::tracker::ReadProgress>,
}

impl SharedCues {
    /// Stamps kept (a reader asks for one of the last two).
    const KEEP: usize = 8;

    /// Unstamped: every cue has stamp 0.
    pub fn new() -> SharedCues {
        SharedCues::default()
    }

    /// Stamped with the frames taken from `progress` (the receiver the
    /// procedure showing the cues reads).
    pub fn stamped_by(progress: crate::device::tracker::ReadProgress) -> SharedCues {
        SharedCues {
            inner: Arc::default(),
            progress: Some(progress),
        }
    }

    fn log(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Cues>> {
        match self.inner.lock() {
            Ok(c) => c,
            Err(poisoned) => poisoned.into_inner(),
        }
    }

    /// The latest cues.
    pub fn latest(&self) -> Cues {
        self.log()
            .last_key_value()
            .map(|(_, c)| c.clone())
            .unwrap_or_default()
    }

    /// The latest cues shown before the procedure took frame `frames` (its
    /// answer to the frames before; unstamped: the latest). Once the
    /// procedure has taken `frames` frames, no later cue can change it.
    pub fn shown_before(&self, frames: u64) -> Cues {
        self.log()
            .range(..frames.max(1))
            .next_back()
            .map(|(_, c)| c.clone())
            .unwrap_or_default()
    }
}

impl CueSink for SharedCues {
    fn show(&mut self, cues: &Cues) {
        let stamp = self.progress.as_ref().map_or(0, |p| p.taken());
        let mut log = self.log();
        log.insert(stamp, cues.clone());
        while log.len() > Self::KEEP {
            log.pop_first();
        }
    }
}

/// Shows each cue to every sink in turn (the terminal view and a recorder).
pub struct Tee<'a>(pub Vec<&'a mut dyn CueSink>);

impl CueSink for Tee<'_> {
    fn show(&mut self, cues: &Cues) {
        for s in self.0.iter_mut() {
            s.show(cues);
        }
    }
}

#[cfg(test)]
mod cue_tests {
    use super::*;
    use crate::device::tracker::{DtrackReceiver, ReceiverConfig, TrackerSource};

    #[test]
    fn a_stamped_cue_is_the_answer_to_the_frames_before() {
        let message = |m: &str| Cues {
            message: m.into(),
            ..Cues::default()
        };
        // Unstamped: the latest.
        let mut plain = SharedCues::new();
        plain.show(&message("a"));
        plain.show(&message("b"));
        assert_eq!(plain.shown_before(1).message, "b");
        // Stamped by what the procedure has taken (nothing yet: 0).
        let mut rx = DtrackReceiver::bind(ReceiverConfig::new(std::net::SocketAddr::from((
            [127, 0, 0, 1],
            0,
        ))))
        .unwrap();
        let mut cues = SharedCues::stamped_by(rx.progress());
        cues.show(&message("before any frame"));
        cues.show(&message("still before"));
        // The procedure takes frame 1, then answers it.
        let frame = crate::device::tracker::dtrack::format_datagram(
            &crate::device::tracker::dtrack::DtrackFrame {
                frame: 1,
                ts_s: Some(1.0),
                calibrated_bodies: Some(1),
                bodies: Vec::new(),
                has_6d: true,
            },
        );
        let tx = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        tx.send_to(frame.as_bytes(), rx.local_addr()).unwrap();
        let mut taken = false;
        for _ in 0..1000 {
            if let Ok(crate::device::tracker::Next::Frame(_)) =
                rx.next_frame(std::time::Duration::from_millis(5))
            {
                taken = true;
                break;
            }
        }
        assert!(taken, "the frame sent on loopback");
        cues.show(&message("answer to frame 1"));
        // A reader in step asking before frame 1 still sees the answer to
        // the frames before it, however late it asks; after it, the answer.
        assert_eq!(cues.shown_before(1).message, "still before");
        assert_eq!(cues.shown_before(2).message, "answer to frame 1");
        assert_eq!(cues.latest().message, "answer to frame 1");
        assert_eq!(SharedCues::default().shown_before(3), Cues::default());
    }
}
