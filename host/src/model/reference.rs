//! The plain least-squares reference: the floor every calibration is held
//! to.
//!
//! Anchors, effective radii, the shared spool build-up, home and the
//! tracker frame, fitted by unweighted least squares on the string-length
//! residuals of every tracked training row, with no prior beyond what makes
//! the problem determined (the anchors' gauge, which the tracker frame
//! would otherwise undo, and priors so wide they only keep an undetermined
//! direction finite); then forward kinematics with every string, weighing
//! alike. It is what a careful user fits by hand on a cable robot, and it
//! makes none of the choices the calibration makes on top (robust weights,
//! the geometry's tolerances as priors, the loop's terms, faulty-string
//! exclusion, weights by scale). Those choices are made on our simulators
//! and on held-out folds; the reference says, on the user's own data,
//! whether together they paid ([`crate::procedures::calibrate`] reports it
//! as a stage, and keeps it as the final model when the chosen one is not
//! better on the selection split).

use crate::data::observe::Observation;
use crate::model::identify::{identify, Identification, IdentifyError, Priors, Start, Structure};
use crate::model::rule::{all_strings_alike, scaled_thresholds, with_rule};
use spidar_core::model::Frame;

/// Name of the reference stage in reports.
pub const STAGE_NAME: &str = "reference (plain least squares)";

/// A prior so wide it decides nothing the data say (mm, or rad for the
/// rotation): it only keeps a direction the rows do not see finite.
const NO_PRIOR_MM: f64 = 1e5;
const NO_PRIOR_RAD: f64 = 1e3;

/// The reference's structure: the base model, unweighted, without priors.
pub fn structure() -> Structure {
    Structure {
        priors: Priors {
            anchor_sd_mm: NO_PRIOR_MM,
            home_sd_mm: NO_PRIOR_MM,
            rotation_sd_rad: NO_PRIOR_RAD,
            translation_sd_mm: NO_PRIOR_MM,
            ..Priors::default()
        },
        robust: false,
        ..Structure::default()
    }
}

/// The reference model of `train` (every tracked row): fitted from the
/// geometry's start, placing rows with all strings alike up to the fault
/// threshold the training rows' own disagreement sets.
pub fn identify_reference(
    train: &[Observation],
    nominal: &Frame<f64>,
    start: &Start,
) -> Result<Identification, IdentifyError> {
    let id = identify(train, nominal, start, &structure())?;
    let (scaled, _) = scaled_thresholds(&id, train);
    Ok(with_rule(
        &id,
        &all_strings_alike(scaled.fault_threshold_mm),
    ))
}
