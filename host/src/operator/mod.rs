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

/// Euclidean distance, mm.
pub(crate) fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}
