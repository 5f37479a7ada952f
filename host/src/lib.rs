//! Host side of the SPIDAR stack, in layers (each a folder; a layer uses the
//! ones above it, never one below):
//!
//! - [`data`]: measured sessions (the one dataset reader and writer), how a
//!   session is observed (tracker frame, orientation, meeting point) and the
//!   one error statistic every report uses;
//! - [`model`]: the calibration model and what fits it: prediction through
//!   the device pipeline, identification, the diagnosis loop (residual ->
//!   effect), layer tables, learned corrections (NN, SVR) and the compiler
//!   to the device's fixed-point blob;
//! - [`device`]: what the host talks to: the device link (postcard frames
//!   over serial), the optical tracker (DTrack input, clock pairing) and the
//!   operator (the cues a procedure shows and plays);
//! - [`sim`]: everything simulated: the model simulator, the independent
//!   physics simulator, the plant, the virtual device (the firmware's logic
//!   behind a pseudo-terminal, on the plant), a simulated tracker and a
//!   simulated operator, and a model measured on the virtual device;
//! - [`procedures`]: what a lab engineer runs: calibration, guided
//!   initialization, lattice collection, runtime monitoring, and the cues
//!   they show the operator.
//!
//! The `spidar` command line (`src/main.rs`) is a thin shell over these.

pub mod data;
pub mod device;
mod error;
pub mod model;
pub mod procedures;
pub mod progress;
pub mod sim;

pub use error::ConfigError;
