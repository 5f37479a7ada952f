//! What an identification gives: the identified model, each parameter's
//! estimate, the warnings; or why it failed.

use serde::{Deserialize, Serialize};
use spidar_core::correction::CorrectionModel;
use spidar_core::kinematics::KinematicsRule;
use spidar_core::model::{Calibration, Effect, EffectTerm, Frame, StringLaw};
use spidar_core::STRINGS;

use super::winding::WindingPhysics;

/// One identified parameter with its uncertainty.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ParameterEstimate {
    pub name: String,
    pub unit: String,
    pub value: f64,
    /// Posterior standard deviation (from the Gauss-Newton covariance).
    pub sd: f64,
    /// Prior standard deviation, when the parameter has a prior.
    pub prior_sd: Option<f64>,
    /// False when the data do not determine the parameter (see warnings).
    pub determined: bool,
}

/// A parameter's value and its sd to the decimals the sd warrants (two
/// significant digits of the sd): `None` when there is no positive sd to
/// go by (the value alone is then written as it comes). The one way the
/// summary and the page write an estimate.
pub fn value_with_sd(value: f64, sd: f64) -> Option<String> {
    let usable = sd > 0.0 && sd.is_finite() && value.is_finite() && value.abs() < 1e9;
    if !usable {
        return None;
    }
    let decimals = (1 - sd.log10().floor() as i32).clamp(0, 9) as usize;
    Some(format!("{value:.decimals$} ± {sd:.decimals$}"))
}

/// The stem of three parameters `stem.x`, `stem.y`, `stem.z` of one unit
/// (an anchor, the home, the tracker's frame): they are shown as one point.
pub fn xyz_stem<'a>(names: [&'a str; 3], units: [&str; 3]) -> Option<&'a str> {
    let stem = names[0].strip_suffix(".x")?;
    (names[1].strip_suffix(".y") == Some(stem)
        && names[2].strip_suffix(".z") == Some(stem)
        && units[1] == units[0]
        && units[2] == units[0])
        .then_some(stem)
}

/// The string of a per-string winding parameter `string{k}.r_home`: its
/// value is the effective radius, the spool's radius over the string's
/// mechanical advantage.
pub fn radius_string(name: &str) -> Option<usize> {
    name.strip_prefix("string")?
        .strip_suffix(".r_home")?
        .parse()
        .ok()
}

/// Result of an identification.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Identification {
    pub frame: Frame<f64>,
    pub winding: WindingPhysics,
    pub laws: [StringLaw; STRINGS],
    pub effects: Vec<EffectTerm>,
    pub parameters: Vec<ParameterEstimate>,
    pub warnings: Vec<String>,
    /// Robust scale of the string-space residuals, mm.
    pub residual_scale_mm: f64,
    /// Each active string's scale of the part of its residual that changes
    /// from row to row (the residual less its running median over 41 rows),
    /// mm (0 on inactive channels): what forward kinematics weighs the
    /// strings by ([`spidar_core::kinematics::residual_weights`]).
    pub length_scale_mm: [f64; STRINGS],
    /// Share of (row, string) residuals the robust weights rejected (weight < 0.1).
    pub rejected_fraction: f64,
    /// LM evaluations over all robust rounds.
    pub evaluations: usize,
    /// When forward kinematics leaves a string out and calls the strings
    /// inconsistent: the device's defaults until the calibration chooses
    /// ([`crate::model::rule`]).
    #[serde(default)]
    pub kinematics: KinematicsRule,
}

impl Identification {
    /// Its kinematic model (what forward kinematics needs).
    pub fn kinematic_model(&self) -> crate::model::predict::KinematicModel<'_> {
        crate::model::predict::KinematicModel {
            frame: &self.frame,
            laws: &self.laws,
            effects: &self.effects,
            length_scale_mm: &self.length_scale_mm,
            kinematics: self.kinematics,
        }
    }

    /// The calibration of this model with `correction` on top of it, and
    /// no home capture.
    pub fn calibration(&self, correction: CorrectionModel) -> Calibration {
        Calibration {
            frame: self.frame,
            strings: self.laws,
            effects: self.effects.clone(),
            correction,
            length_scale_mm: self.length_scale_mm,
            kinematics: self.kinematics,
            home: None,
        }
    }

    /// The model as it holds for another session, started from a new home
    /// capture: without the slips found in this one. A slip is an event of
    /// the session it happened in (the string slid on its spool); a new home
    /// capture counts from the string as it is, so the step is not there.
    /// Applied to a later session by its time since home, a training
    /// session's early slip would put its step on one string of every test
    /// row after it.
    pub fn for_a_new_session(&self) -> Identification {
        self.with_slips_where(|_| false)
    }

    /// The model with the slips whose `at_s` `keep` keeps, every other
    /// effect kept: under the training's last home capture, the slips of
    /// that capture
    /// ([`crate::data::home::TrainingHome::slip_is_of_last_capture`]), as
    /// the device keeps them.
    pub fn with_slips_where(&self, keep: impl Fn(f64) -> bool) -> Identification {
        Identification {
            effects: self
                .effects
                .iter()
                .filter(|t| match t.effect {
                    Effect::Slip { at_s, .. } => keep(at_s),
                    _ => true,
                })
                .copied()
                .collect(),
            ..self.clone()
        }
    }
}

/// Why an identification failed.
#[derive(Debug, thiserror::Error)]
pub enum IdentifyError {
    #[error(
        "identification needs at least {needed} rows with tracker positions, the session has {got}"
    )]
    TooFewRows { needed: usize, got: usize },
    #[error("identification diverged: {0}")]
    Diverged(String),
}
