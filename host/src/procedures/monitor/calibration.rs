//! The calibration the device runs, as the monitor reads it: checked
//! against the geometry, and seen as an identification and a structure that
//! diagnosis can test and a refit can start from.

use std::path::Path;

use spidar_core::model::{Calibration, Effect, EffectTerm, HomeSlips, WINDING_ORDER};
use spidar_core::STRINGS;

use crate::data::dataset::Geometry;
use crate::model::identify::{Identification, Structure, WindingPhysics};

use super::MonitorError;

/// Checks that `calibration` belongs to the device of `geometry`: the same
/// encoders, anchors within `tolerance_mm` of the design, and string laws of
/// the identified winding form (what diagnosis can test and refit).
pub fn check_calibration(
    calibration: &Calibration,
    geometry: &Geometry,
    tolerance_mm: f64,
    file: &Path,
) -> Result<(), MonitorError> {
    let bad = |field: String, problem: String| {
        Err(MonitorError::Calibration {
            file: file.to_path_buf(),
            field,
            problem,
        })
    };
    for i in geometry.layout.indices() {
        let law = &calibration.strings[i];
        if law.counts_per_rev != geometry.counts_per_rev[i] {
            return bad(
                format!("strings[{i}].counts_per_rev"),
                format!(
                    "{} counts per revolution, the geometry has {} (a calibration of another device?)",
                    law.counts_per_rev, geometry.counts_per_rev[i]
                ),
            );
        }
        // The identified form: [r_home_i, -(kappa + kappa_i) / m_i, 0, 0]
        // (m_i the string's mechanical advantage, 1 for a single line).
        if law.winding_mm[2..WINDING_ORDER].iter().any(|c| *c != 0.0) {
            return bad(
                format!("strings[{i}].winding_mm"),
                "not of the identified winding form [r_home, -kappa / mechanical_advantage, 0, \
                 0]: runtime diagnosis cannot test this model"
                    .into(),
            );
        }
    }
    if calibration.frame.layout != geometry.layout {
        return bad(
            "frame.layout".into(),
            format!(
                "strings on channels {:?}{}, the geometry has {:?}{}: the calibration and the \
                 geometry are of different devices",
                calibration.frame.layout.indices().collect::<Vec<_>>(),
                if calibration.frame.layout.planar {
                    " (planar)"
                } else {
                    ""
                },
                geometry.layout.indices().collect::<Vec<_>>(),
                if geometry.layout.planar {
                    " (planar)"
                } else {
                    ""
                },
            ),
        );
    }
    for i in geometry.layout.indices() {
        let a = calibration.frame.anchors[i];
        let n = geometry.anchors_mm[i];
        let d = ((a[0] - n[0]).powi(2) + (a[1] - n[1]).powi(2) + (a[2] - n[2]).powi(2)).sqrt();
        if !d.is_finite() || d > tolerance_mm {
            return bad(
                format!("frame.anchors[{i}]"),
                format!(
                    "{d:.1} mm from the geometry's anchor {i} (tolerance {tolerance_mm} mm): \
                     the calibration and the geometry are of different devices"
                ),
            );
        }
    }
    Ok(())
}

/// The calibration as an identification (its frame, winding and effects),
/// so that diagnosis can test it; `mechanical_advantage` is the geometry's
/// (each string's law carries the shared kappa over it, see
/// [`check_calibration`]).
pub fn identification_of(
    calibration: &Calibration,
    mechanical_advantage: &[f64; STRINGS],
) -> Identification {
    let laws = calibration.strings;
    let layout = calibration.frame.layout;
    // Each string's thinning rate, split into the shared mean and each
    // spool's departure (the identification's form).
    let kappa_of = |i: usize| -laws[i].winding_mm[1] * mechanical_advantage[i];
    let kappa_mm = layout.indices().map(kappa_of).sum::<f64>() / layout.count().max(1) as f64;
    Identification {
        frame: calibration.frame,
        winding: WindingPhysics {
            r_home_mm: core::array::from_fn(|i| laws[i].winding_mm[0]),
            kappa_mm,
            kappa_each_mm: core::array::from_fn(|i| {
                if layout.is_active(i) {
                    kappa_of(i) - kappa_mm
                } else {
                    0.0
                }
            }),
            counts_per_rev: laws.map(|l| l.counts_per_rev),
            mechanical_advantage: *mechanical_advantage,
            layers: laws.map(|l| l.layers),
        },
        laws,
        effects: calibration.effects.clone(),
        parameters: Vec::new(),
        warnings: Vec::new(),
        residual_scale_mm: 0.0,
        length_scale_mm: calibration.length_scale_mm,
        rejected_fraction: 0.0,
        evaluations: 0,
        kinematics: calibration.kinematics,
    }
}

/// The structure of a calibration: its effect terms, the tracker scale free
/// when it is not 1.
pub fn structure_of(calibration: &Calibration) -> Structure {
    Structure {
        fit_room_scale: (calibration.frame.room_scale - 1.0).abs() > 1e-12,
        effects: calibration.effects.clone(),
        // A window of a few seconds cannot tell a spool's thinning rate
        // from a step or a drift: the calibration's are held (the default).
        ..Structure::default()
    }
}

/// The calibration as the device runs it under home capture `home_id`
/// (`State::home_id`; `None`: not known yet): its effects, and the training
/// session's slips ([`Calibration::home`]) while `home_id` is theirs, as
/// effect terms; never after a new home capture (decision record 0049,
/// "Device side").
pub fn under_home(calibration: &Calibration, home_id: Option<u64>) -> Calibration {
    calibration.under_home(home_id)
}

/// A refitted model's effect terms (of [`under_home`]'s calibration) split
/// back into the model for the next home capture (`effects`) and the slips
/// of the current one (`home`, under `home_id`): the training's slips,
/// refitted, while `home_id` is still theirs, and every slip on one string
/// the refit added at run time. A slip is an event of the home capture it
/// happened in: the next `Home` counts the string as it is, so a run-time
/// slip in `effects` would put its step on every later capture. After a
/// new capture the training's slips are over and are not carried. A slip
/// `previous.effects` already holds stays there (a calibration written
/// before run-time slips had a capture); a slip shared by every string
/// is no slip of one string, which is all a blob's home section carries.
/// Without a known capture (`None`, no state read yet) nothing moves.
pub(super) fn split_home_slips(
    effects: &[EffectTerm],
    previous: &Calibration,
    home_id: Option<u64>,
) -> (Vec<EffectTerm>, Option<HomeSlips>) {
    let Some(home_id) = home_id else {
        return (effects.to_vec(), None);
    };
    let same_slip = |h: &EffectTerm, t: &EffectTerm| match (h.effect, t.effect) {
        (Effect::Slip { at_s: a, .. }, Effect::Slip { at_s: b, .. }) => {
            h.string == t.string && a == b
        }
        _ => false,
    };
    let of_this_home = |t: &EffectTerm| {
        matches!(t.effect, Effect::Slip { .. })
            && usize::from(t.string) < STRINGS
            && !previous.effects.iter().any(|e| same_slip(e, t))
    };
    let (slips, rest): (Vec<EffectTerm>, Vec<EffectTerm>) =
        effects.iter().partition(|t| of_this_home(t));
    let home = (!slips.is_empty()).then_some(HomeSlips { home_id, slips });
    (rest, home)
}

#[cfg(test)]
mod tests;
