//! What the host talks to.
//!
//! - [`link`]: the device link (postcard frames over a serial port): info,
//!   stream, arm, force, and the model upload;
//! - [`tracker`]: the optical tracker's input (DTrack datagrams, replay) and
//!   the clock pairing of its frames with the device's states;
//! - [`cues`]: the third thing a procedure talks to, the operator: what is
//!   shown and played at one moment (the binary draws it in the terminal,
//!   a simulated operator reads it).
//!
//! A virtual device (the firmware's device logic on a simulated plant) is in
//! [`crate::sim::virtual_device`].

pub mod cues;
pub mod link;
pub mod tracker;
