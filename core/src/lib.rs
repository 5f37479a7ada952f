//! Device math for string-based haptic devices of the SPIDAR family.
//!
//! `no_std`, no embassy: the firmware, the virtual device and the host link
//! this crate, so that host and device compute bit-identical string lengths,
//! positions and corrections.
//!
//! The calibration model is the spine (see `docs/design.md`):
//! - [`model`]: the physical model the host fits, in f64 and physical units;
//! - [`geometry`]: points, rotations and the room/device frames (f32 and f64);
//! - [`blob`]: its compiled, fixed-point form that the device evaluates;
//! - [`string_law`]: string length from encoder counts (winding law + effects);
//! - [`kinematics`]: forward kinematics from 8 strings with faulty-string rejection;
//! - [`correction`]: fixed-point NN / SVR position corrections;
//! - [`tension`], [`guidance`], [`safety`]: force rendering and its limits;
//! - [`control`]: one control-loop iteration wiring all of the above;
//! - [`model_store`]: two flash slots holding the model blob, power-loss safe uploads;
//! - [`device`]: the device behind the link: requests, uploads, the loop, the state stream.
//! - [`time_base`]: the firmware clock from two cascaded 16-bit timers, which survives a flash erase.
#![cfg_attr(not(test), no_std)]
#![forbid(unsafe_code)]

#[cfg(feature = "alloc")]
extern crate alloc;

/// Number of strings (and motors, encoders) of a Scalable-SPIDAR: the
/// controller's channels, defined once, in the protocol both sides share.
pub use spidar_protocol::STRINGS;

pub mod blob;
pub mod control;
pub mod correction;
pub mod device;
pub mod encoder;
pub mod fixed;
pub mod geometry;
pub mod guidance;
pub mod kinematics;
pub mod model;
pub mod model_store;
pub mod plausible;
pub mod real;
pub mod safety;
pub mod string_law;
pub mod tension;
#[cfg(test)]
pub(crate) mod test_fixtures;
pub mod tick_cost;
pub mod time_base;

// With the `defmt` feature, the errors a firmware may log are defmt::Format,
// so it logs them without Debug2Format. Fails the build if one loses its
// derive (scripts/test builds core with the feature for thumbv7em).
#[cfg(feature = "defmt")]
const _: () = {
    const fn format<T: defmt::Format>() {}
    format::<safety::SafetyConfigError>();
    format::<model_store::FlashError>();
    format::<model_store::StoreError>();
    format::<model_store::CommitError<spidar_protocol::DeviceError>>();
    format::<string_law::StringLawCompileError>();
    format::<plausible::Implausible>();
    #[cfg(feature = "alloc")]
    {
        format::<correction::CorrectionCompileError>();
        format::<blob::BlobCompileError>();
    }
};

#[cfg(test)]
mod tests {
    /// Every error of the crate is a `core::error::Error` (the host chains
    /// them as sources; the firmware can report them through the trait).
    #[test]
    fn errors_are_errors() {
        fn error<E: core::error::Error>() {}
        error::<crate::string_law::StringLawCompileError>();
        error::<crate::correction::CorrectionCompileError>();
        error::<crate::blob::BlobCompileError>();
        error::<crate::plausible::Implausible>();
        error::<crate::safety::SafetyConfigError>();
        error::<crate::model_store::FlashError>();
        error::<crate::model_store::StoreError>();
        error::<crate::model_store::CommitError<spidar_protocol::DeviceError>>();
    }
}
