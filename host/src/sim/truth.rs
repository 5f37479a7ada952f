//! `truth.toml`: the true parameters of a simulated device and the injected
//! effects. For tests and benchmarks only: calibration never reads it.

use std::path::Path;

use serde::{Deserialize, Serialize};
use spidar_core::model::{EffectTerm, Frame, StringLaw};
use spidar_core::STRINGS;

use super::config::SimConfig;
use super::effects::InjectedEffect;
use super::simulated_device::SimulatedDevice;
use super::SimError;

const HEADER: &str = "# Simulator ground truth: the device as built and the injected effects.\n\
# For tests and benchmarks only; calibration never reads this file.\n";

/// The true parameters of a simulated device.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Truth {
    /// Device seed.
    pub seed: u64,
    /// True anchors, home and room-from-device transform (tracker frame).
    pub frame: Frame<f64>,
    /// True base winding law of each string: `[r_home, -d^2/(4 pi), 0, 0]`.
    pub strings: [StringLaw; STRINGS],
    /// Injected model-family terms, in order: what identification should find.
    pub effects: Vec<EffectTerm>,
    /// Every injected effect (model families, unexplained, geometry), resolved per string.
    pub injected: Vec<InjectedEffect>,
    /// True bare pulley radius `r0` of each string, mm.
    pub bare_pulley_radius_mm: [f64; STRINGS],
    /// String wound on each pulley at initialization, mm.
    pub home_wound_mm: [f64; STRINGS],
    /// True total length of each string, mm.
    pub string_total_mm: [f64; STRINGS],
    /// The configuration the device was built from.
    pub config: SimConfig,
}

impl Truth {
    /// The truth of `device`.
    pub fn of(device: &SimulatedDevice) -> Truth {
        Truth {
            seed: device.seed,
            frame: device.frame,
            strings: device.laws,
            effects: device.effects.clone(),
            injected: device.injected.clone(),
            bare_pulley_radius_mm: device.bare_radius_mm,
            home_wound_mm: device.home_wound_mm,
            string_total_mm: device.string_total_mm,
            config: device.config.clone(),
        }
    }

    /// TOML text, with a header saying what the file is for.
    pub fn to_toml_string(&self) -> Result<String, SimError> {
        let body = toml::to_string(self).map_err(|e| {
            SimError::Config(crate::ConfigError::new(
                "truth",
                format!("cannot be written as TOML: {e}"),
            ))
        })?;
        Ok(format!("{HEADER}{body}"))
    }

    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), SimError> {
        let path = path.as_ref();
        let text = self.to_toml_string()?;
        crate::data::output::write_atomically(path, text.as_bytes()).map_err(|source| {
            SimError::Io {
                file: path.to_path_buf(),
                action: "cannot write",
                source,
            }
        })
    }

    pub fn load(path: impl AsRef<Path>) -> Result<Truth, SimError> {
        super::config::read_toml(path.as_ref())
    }
}
