//! The strings' winding laws, as the identification fits them.

use serde::{Deserialize, Serialize};
use spidar_core::model::{LayerTable, StringLaw, WINDING_ORDER};
use spidar_core::STRINGS;

/// The winding laws of the strings (see the module doc): a per-string
/// winding radius at home and one shared thinning rate.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WindingPhysics {
    /// Effective winding radius at home of each string (spool radius over
    /// the mechanical advantage), mm: each pulley holds its own amount of
    /// string at home, and pulleys differ slightly.
    pub r_home_mm: [f64; STRINGS],
    /// `d^2 / (4 pi)`, mm/rad^2: how fast the spool's radius shrinks with
    /// payout (string diameter d, the same string on every pulley).
    pub kappa_mm: f64,
    /// Each spool's departure from `kappa_mm` (mm/rad^2; mean 0 over the
    /// active strings): a level-wound spool thins by `d^2 / (2 pi W)` per
    /// radian for a width `W`, so spools of other widths or packing thin at
    /// other rates.
    #[serde(default)]
    pub kappa_each_mm: [f64; STRINGS],
    /// Counts per pulley revolution, per string.
    pub counts_per_rev: [u32; STRINGS],
    /// Spool payout per mm of string length change, per string (1 unless
    /// the line is doubled through pulley blocks).
    #[serde(default = "unit_advantage")]
    pub mechanical_advantage: [f64; STRINGS],
    /// Each string's layer table (the spool's departure from the smooth law,
    /// [`crate::model::layers`]); held, not fitted, by the identification.
    #[serde(default)]
    pub layers: [LayerTable; STRINGS],
}

fn unit_advantage() -> [f64; STRINGS] {
    [1.0; STRINGS]
}

impl WindingPhysics {
    /// The per-string laws: `payout = r_home_i theta - ((kappa + kappa_i) /
    /// m_i) theta^2`.
    pub fn laws(&self) -> [StringLaw; STRINGS] {
        core::array::from_fn(|i| {
            let mut winding_mm = [0.0; WINDING_ORDER];
            winding_mm[0] = self.r_home_mm[i];
            winding_mm[1] = -(self.kappa_mm + self.kappa_each_mm[i]) / self.mechanical_advantage[i];
            StringLaw {
                layers: self.layers[i],
                ..StringLaw::polynomial(self.counts_per_rev[i], winding_mm)
            }
        })
    }
}
