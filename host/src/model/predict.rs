//! Positions a calibration gives for a session, in f64: the host's reference
//! of the device pipeline (string law, forward kinematics with faulty-string
//! exclusion, room transform, position correction).
//!
//! Rows are processed in session order and forward kinematics is warm-started
//! from the previous row, as on the device. A model with a sag term reads
//! each string's inclination: the device takes it at the position its loop
//! holds, a tick (0.1 ms) old, but a session's rows are far apart, so the
//! rows are solved twice, the second time at the inclinations of the first
//! solution ([`spidar_core::model::Effect::reads_inclination`]).

use std::borrow::Borrow;

use spidar_core::correction::CorrectionModel;
use spidar_core::kinematics::{
    forward_kinematics_inclined, residual_weights, FkConfig, FkStatus, KinematicsRule,
};
use spidar_core::model::{Calibration, EffectTerm, Frame, StringInputs, StringLaw};
use spidar_core::string_law::{string_lengths_at_homes, StringHome};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use spidar_core::geometry::room_from_device;

/// The position of one row.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prediction {
    /// Forward kinematics, device frame, mm.
    pub device: [f64; 3],
    /// Room frame, before any learned correction, mm.
    pub room: [f64; 3],
    pub status: FkStatus,
    /// String excluded as faulty by forward kinematics.
    pub excluded: Option<u8>,
    /// RMS of the (weighted) string-length residuals at the position, mm:
    /// how well the row's strings agree.
    pub rms_residual_mm: f64,
}

/// The kinematic model of a calibration: its frame, string laws and effect
/// terms, what forward kinematics needs (not the nominal string model a
/// device is given over the link, `spidar_protocol::NominalGeometry`).
#[derive(Clone, Copy, Debug)]
pub struct KinematicModel<'a> {
    pub frame: &'a Frame<f64>,
    pub laws: &'a [StringLaw; STRINGS],
    pub effects: &'a [EffectTerm],
    /// Each string's measured length residual scale (mm), which weighs the
    /// strings in forward kinematics as on the device
    /// ([`spidar_core::kinematics::residual_weights`]);
    /// [`UNMEASURED_SCALES`] weighs them alike.
    pub length_scale_mm: &'a [f64; STRINGS],
    /// When forward kinematics leaves a string out and calls the strings
    /// inconsistent.
    pub kinematics: KinematicsRule,
}

/// No string's residual scale measured (a nominal model, a model not yet
/// identified): every string weighs alike in forward kinematics.
pub const UNMEASURED_SCALES: [f64; STRINGS] = [0.0; STRINGS];

impl<'a> KinematicModel<'a> {
    pub fn of(calibration: &'a Calibration) -> KinematicModel<'a> {
        KinematicModel {
            frame: &calibration.frame,
            laws: &calibration.strings,
            effects: &calibration.effects,
            length_scale_mm: &calibration.length_scale_mm,
            kinematics: calibration.kinematics,
        }
    }
}

/// Forward kinematics of every row (warm-started along the session), as
/// the device solves it ([`FkConfig::default`] with the model's thresholds,
/// the strings weighed by the model's measured scales).
pub fn predict<O: Borrow<Observation>>(
    model: KinematicModel<'_>,
    observations: &[O],
) -> Vec<Prediction> {
    predict_with(
        model,
        observations,
        &model.kinematics.apply(&FkConfig::default()),
    )
}

/// [`predict`] with the kinematics tuned by `config` (its residual weights
/// replaced by the model's; its thresholds are `config`'s).
pub fn predict_with<O: Borrow<Observation>>(
    model: KinematicModel<'_>,
    observations: &[O],
    config: &FkConfig<f64>,
) -> Vec<Prediction> {
    let frame = model.frame;
    let inclined = model.effects.iter().any(|t| t.effect.reads_inclination());
    let homes = StringHome::of_every_string(frame);
    let lengths = |inputs: &StringInputs| {
        string_lengths_at_homes(
            &homes,
            frame.layout.active,
            model.laws,
            model.effects,
            inputs,
        )
    };
    let config = &FkConfig {
        residual_weight: residual_weights(frame.layout, model.length_scale_mm),
        ..*config
    };
    let mut start = frame.home;
    observations
        .iter()
        .map(|o| {
            let o = o.borrow();
            let fk =
                forward_kinematics_inclined(frame, &o.inputs, start, config, inclined, lengths);
            if matches!(fk.status, FkStatus::Ok | FkStatus::FaultyStringExcluded) {
                start = fk.position;
            }
            Prediction {
                device: fk.position,
                room: room_from_device(model.frame, fk.position),
                status: fk.status,
                excluded: fk.excluded,
                rms_residual_mm: fk.rms_residual_mm,
            }
        })
        .collect()
}

/// Room positions after a learned position correction.
pub fn corrected(correction: &CorrectionModel, predictions: &[Prediction]) -> Vec<[f64; 3]> {
    let rooms: Vec<[f64; 3]> = predictions.iter().map(|p| p.room).collect();
    corrected_positions(correction, &rooms)
}

/// `positions` after a learned position correction, each on its own on
/// every core (an SVR of 2,000 support vectors on a 30,000-row session is
/// 60 million kernel terms).
pub fn corrected_positions(correction: &CorrectionModel, positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
    use rayon::prelude::*;
    positions
        .par_iter()
        .map(|&p| correction.evaluate(p))
        .collect()
}

/// Pairs of (position, tracker) for the rows the tracker saw.
pub fn paired_with_tracker<O: Borrow<Observation>>(
    positions: &[[f64; 3]],
    observations: &[O],
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    positions
        .iter()
        .zip(observations)
        .filter_map(|(p, o)| o.borrow().tracker.map(|t| (*p, t)))
        .unzip()
}
