//! The legacy (black-box HDHC) controller, the `dev_*` columns: it turns the
//! encoder counts into string lengths with the NOMINAL geometry and a
//! constant NOMINAL pulley radius, from its imprecise built-in home (it
//! believes the end-effector was at the nominal home at initialization), and
//! solves the position with the project's forward kinematics over all eight
//! strings (no faulty-string rejection: the firmware of the paper had none).

use spidar_core::kinematics::{forward_kinematics, FkConfig, FkStatus};
use spidar_core::model::{StringLaw, StringLayout, Vec3};
use spidar_core::string_law::payout_f64;
use spidar_core::STRINGS;

use crate::data::dataset::Geometry;

pub(crate) struct LegacyController {
    anchors: [Vec3<f64>; STRINGS],
    home: Vec3<f64>,
    home_lengths: [f64; STRINGS],
    laws: [StringLaw; STRINGS],
    config: FkConfig<f64>,
}

impl LegacyController {
    pub(crate) fn new(geometry: &Geometry) -> Self {
        LegacyController {
            anchors: geometry.anchors_mm,
            home: geometry.home_mm,
            home_lengths: geometry.home_lengths_mm(),
            laws: geometry.nominal_string_laws(),
            config: FkConfig {
                max_iterations: 100,
                fault_threshold_mm: f64::INFINITY,
                exclusion_threshold_mm: f64::INFINITY,
                ..FkConfig::default()
            },
        }
    }

    /// Device-frame position the legacy controller reports for `counts`;
    /// `None` when the lengths are not usable (a negative nominal length).
    pub(crate) fn position(&self, counts: &[i32; STRINGS]) -> Option<Vec3<f64>> {
        let lengths: [f64; STRINGS] =
            core::array::from_fn(|i| self.home_lengths[i] + payout_f64(&self.laws[i], counts[i]));
        let solution = forward_kinematics(
            &self.anchors,
            StringLayout::ALL,
            &lengths,
            self.home,
            &self.config,
        );
        match solution.status {
            FkStatus::InvalidInput => None,
            _ => Some(solution.position),
        }
    }
}
