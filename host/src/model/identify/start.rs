//! Where an identification starts: the nominal design, a geometry file, or
//! an earlier identification (a refit).

use spidar_core::model::{Effect, EffectTerm, Frame, LayerTable};
use spidar_core::STRINGS;

use super::result::Identification;
use super::winding::WindingPhysics;

/// Starting point of an identification: the nominal geometry, and the winding
/// physics of the nominal pulley (`r_home` = nominal radius, no growth) unless
/// a previous identification is given.
#[derive(Clone, Debug)]
pub struct Start {
    pub frame: Frame<f64>,
    pub winding: WindingPhysics,
    /// Starting close to the solution (a refit): skip the least-squares and
    /// Huber rounds, whose only job is to get near it robustly.
    pub warm: bool,
    /// Effect terms with the values to start from (a refit's): a structure
    /// term takes the value of the term at its place here when both are
    /// the same kind on the same string (the structure's values are those
    /// diagnosis proposed, before any fit; a warm start's robust weights
    /// come from the start's residuals, so its terms must be the fitted
    /// ones). A term beyond these starts from the structure's value, and
    /// the fit from a Huber round.
    pub effects: Vec<EffectTerm>,
}

impl Start {
    /// From the nominal design: the pulley radii (spool radius over the
    /// mechanical advantage: the effective radius), no growth.
    pub fn nominal(
        frame: Frame<f64>,
        effective_radius_mm: [f64; STRINGS],
        counts_per_rev: [u32; STRINGS],
        mechanical_advantage: [f64; STRINGS],
    ) -> Start {
        Start {
            frame,
            winding: WindingPhysics {
                r_home_mm: effective_radius_mm,
                kappa_mm: 0.0,
                kappa_each_mm: [0.0; STRINGS],
                counts_per_rev,
                mechanical_advantage,
                layers: [LayerTable::NONE; STRINGS],
            },
            warm: false,
            effects: Vec::new(),
        }
    }

    /// From a geometry file: its nominal frame, pulley radii, counts per
    /// revolution and mechanical advantage.
    pub fn from_geometry(geometry: &crate::data::dataset::Geometry) -> Start {
        Start::nominal(
            geometry.nominal_frame(),
            core::array::from_fn(|i| {
                geometry.pulley_radius_mm[i] / geometry.mechanical_advantage[i]
            }),
            geometry.counts_per_rev,
            geometry.mechanical_advantage,
        )
    }

    /// Continue from an earlier identification (the diagnosis loop refits).
    pub fn from_identification(id: &Identification) -> Start {
        Start {
            frame: id.frame,
            winding: id.winding,
            warm: true,
            effects: id.effects.clone(),
        }
    }
}

/// Whether `known` (a start's term) is `term` with other values: the same
/// kind on the same string (and a slip at the same time).
pub(super) fn same_term(term: &EffectTerm, known: &EffectTerm) -> bool {
    term.string == known.string
        && match (&term.effect, &known.effect) {
            (Effect::Slip { at_s: a, .. }, Effect::Slip { at_s: b, .. }) => a == b,
            (a, b) => core::mem::discriminant(a) == core::mem::discriminant(b),
        }
}
