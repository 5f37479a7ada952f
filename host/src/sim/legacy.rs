//! The legacy (black-box HDHC) controller: forward kinematics with the
//! nominal geometry and a constant nominal pulley radius, from its
//! imprecise built-in home.

use spidar_core::model::Vec3;
use spidar_core::STRINGS;

use crate::dataset::Geometry;

pub(crate) struct LegacyController {
    #[allow(dead_code)]
    geometry: Geometry,
}

impl LegacyController {
    pub(crate) fn new(geometry: &Geometry) -> Self {
        LegacyController {
            geometry: geometry.clone(),
        }
    }

    /// Waiting for `spidar_core::kinematics::forward_kinematics` on main.
    pub(crate) fn position(&self, _counts: &[i32; STRINGS]) -> Option<Vec3<f64>> {
        None
    }
}
