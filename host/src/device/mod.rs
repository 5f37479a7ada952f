//! What the host talks to.
//!
//! - [`link`]: the device link (postcard frames over a serial port): info,
//!   stream, arm, force, and the model upload;
//! - [`virtual_device`]: the firmware's device logic behind a
//!   pseudo-terminal, on a simulated plant;
//! - [`tracker`]: the optical tracker's input (DTrack datagrams, replay) and
//!   the clock pairing of its frames with the device's states;
//! - [`measure`]: a model measured on the (virtual) device.

pub mod link;
pub mod measure;
pub mod tracker;
pub mod virtual_device;
