//! The independent simulator (`sim::physics`): deterministic per seed,
//! physically sane (counts follow the string, the exit point moves, the
//! spool winds in layers), its effects selectable by name, bad input named,
//! and what today's calibration pipeline reaches on it.

mod calibration;
mod clean_devices;
mod fixtures;
mod glitches;
mod latency;
mod marker_offset;
mod simulator;
mod slips;
mod tension_terms;
mod time_terms;

pub(crate) use fixtures::{loop_of_device, loop_with};
