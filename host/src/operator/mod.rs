//! Operator procedures of the paper (sections 4.1, 4.3.1, 5.5): what a lab
//! engineer does with the device and the optical tracker.
//!
//! - [`init`]: guided initialization (`spidar init`): the haptic and audio
//!   cues (eqs. 2-5) bring the marker to the frame centre, home is declared
//!   when it holds there, and the room-to-device transform is recorded;
//! - [`sim_user`]: a simulated operator for tests and demos: a hand on the
//!   virtual device's end-effector that follows the cues, and the DTrack2
//!   datagrams an optical tracker would send of its marker.
//!
//! Procedures talk to the operator through [`Cues`]: everything shown or
//! played at one moment (target, marker, distance, beep, force, progress),
//! handed to a [`CueSink`]. The command line renders them in the terminal
//! and plays the beep; a simulated operator reads them to decide where to
//! move, exactly what a person would see and hear, nothing more.

pub mod audio;
pub mod collect;
pub mod init;
pub mod recalibrate;
pub mod sim_user;
pub mod view;

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
#[derive(Clone, Debug, Default)]
pub struct SharedCues {
    inner: Arc<Mutex<Cues>>,
}

impl SharedCues {
    pub fn new() -> SharedCues {
        SharedCues::default()
    }

    /// The latest cues.
    pub fn latest(&self) -> Cues {
        match self.inner.lock() {
            Ok(c) => c.clone(),
            Err(poisoned) => poisoned.into_inner().clone(),
        }
    }
}

impl CueSink for SharedCues {
    fn show(&mut self, cues: &Cues) {
        match self.inner.lock() {
            Ok(mut c) => *c = cues.clone(),
            Err(poisoned) => *poisoned.into_inner() = cues.clone(),
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

/// A device that disarmed itself while armed by a procedure: an event says
/// so, or its states have said so for [`UNARMED_GRACE`] (after a reboot it
/// may hold a latched fault and send no event).
const UNARMED_GRACE: Duration = Duration::from_millis(250);

/// Keeps the device armed through a procedure: re-arms it when it disarmed
/// itself (a late heartbeat, a slack string), at most `max` times without
/// progress in between, then gives up naming the last cause.
pub(crate) struct ArmWatch {
    max: u32,
    since_progress: u32,
    unarmed_since: Option<std::time::Instant>,
    /// Re-arms over the whole procedure.
    pub rearms: u32,
}

/// Why [`ArmWatch::check`] gave up.
pub(crate) enum ArmWatchError {
    Link(crate::link::LinkError),
    KeepsDisarming { events: u32, last: String },
}

impl ArmWatch {
    pub(crate) fn new(max: u32) -> ArmWatch {
        ArmWatch {
            max,
            since_progress: 0,
            unarmed_since: None,
            rearms: 0,
        }
    }

    /// The procedure got somewhere (a capture): the count starts again.
    pub(crate) fn progress(&mut self) {
        self.since_progress = 0;
    }

    /// Looks at the link's events and the latest state (armed, faults) and
    /// re-arms if needed; true when it did.
    pub(crate) fn check(
        &mut self,
        client: &mut crate::link::Client,
        latest: Option<(bool, spidar_protocol::Faults)>,
    ) -> Result<bool, ArmWatchError> {
        use spidar_protocol::Event;
        let event = client
            .take_events()
            .into_iter()
            .rfind(|e| matches!(e, Event::Disarmed { .. } | Event::HeartbeatLost))
            .map(|e| format!("{e:?}"));
        let unarmed = match latest {
            Some((false, faults)) => {
                let since = *self
                    .unarmed_since
                    .get_or_insert_with(std::time::Instant::now);
                (since.elapsed() > UNARMED_GRACE)
                    .then(|| format!("states say disarmed, faults {:#06x}", faults.0))
            }
            _ => {
                self.unarmed_since = None;
                None
            }
        };
        let Some(last) = event.or(unarmed) else {
            return Ok(false);
        };
        self.rearms += 1;
        self.since_progress += 1;
        if self.since_progress > self.max {
            return Err(ArmWatchError::KeepsDisarming {
                events: self.since_progress,
                last,
            });
        }
        client.clear_faults().map_err(ArmWatchError::Link)?;
        client.arm().map_err(ArmWatchError::Link)?;
        self.unarmed_since = None;
        Ok(true)
    }
}

/// Euclidean distance, mm.
pub(crate) fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}
