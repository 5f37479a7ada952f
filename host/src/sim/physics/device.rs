//! What a built device of the independent simulator does at a position:
//! each string's path over its guide, its sag, stretch and natural length,
//! the spool angle and encoder counts that length gives, the tracker's
//! room frame and the marker, and the undeclared effects' rates on the
//! strings (latency, thermal drift).

use rand::RngExt;
use spidar_core::model::Vec3;
use std::f64::consts::TAU;

use super::build::{string_end, string_error};
use super::{GuidePath, PhysicsDevice, PhysicsEffect, PhysicsString, Spool};
use crate::sim::SimError;
use spidar_core::geometry::{mat_t_vec, mat_vec, rotation_from_vector, sub};

const G_MM_PER_S2: f64 = 9806.65;

impl PhysicsDevice {
    /// How late string `string`'s encoder is read, s (`latency`'s `ms`
    /// on that string or on every string; 0 without it).
    pub fn encoder_latency_s(&self, string: usize) -> f64 {
        self.effects
            .iter()
            .map(|e| match e {
                PhysicsEffect::Latency { string: s, ms } if s.is_none_or(|s| s == string) => {
                    ms / 1000.0
                }
                _ => 0.0,
            })
            .sum()
    }

    /// The strings' thermal strain per second (`drift-all`'s `ppm_per_h`
    /// in 1/s; 0 without it): what a creep term's `per_s` is.
    pub fn creep_per_s(&self) -> f64 {
        self.effects
            .iter()
            .map(|e| match e {
                PhysicsEffect::DriftAll { ppm_per_h } => ppm_per_h * 1e-6 / 3600.0,
                _ => 0.0,
            })
            .sum()
    }

    /// String `string`'s thermal strain per second: the shared
    /// `drift-all`'s and its own `drift-each` rate (the rate plus a uniform
    /// draw in `-spread..spread` per string from the device's seed; the
    /// same for the string whatever the session).
    pub fn string_creep_per_s(&self, string: usize) -> f64 {
        let mut draws = crate::sim::simulated_device::stream(self.seed, 131);
        let own: f64 = (0..=string)
            .map(|_| draws.random_range(-1.0..1.0))
            .last()
            .unwrap_or(0.0);
        self.creep_per_s()
            + self
                .effects
                .iter()
                .map(|e| match e {
                    PhysicsEffect::DriftEach {
                        ppm_per_h,
                        spread_ppm_per_h,
                    } => (ppm_per_h + spread_ppm_per_h * own) * 1e-6 / 3600.0,
                    _ => 0.0,
                })
                .sum::<f64>()
    }

    /// Where `string` is tied when the end-effector's reference point is at
    /// `p` and it is turned by `turn` (rotation vector): `p`, or the
    /// carriage's attachment point `p + R(turn) attachment`.
    pub fn string_end(&self, string: usize, p: &Vec3<f64>, turn: &Vec3<f64>) -> Vec3<f64> {
        string_end(&self.config.carriage, string, p, turn)
    }

    /// Number of strings (the design's anchors).
    pub fn string_count(&self) -> usize {
        self.strings.len()
    }

    /// The built spool of `string`.
    pub fn spool(&self, string: usize) -> &Spool {
        &self.spools[string]
    }

    /// Room position of a device-frame position.
    pub fn room_from_device(&self, p: &Vec3<f64>) -> Vec3<f64> {
        let r = mat_vec(&self.room_rotation, *p);
        core::array::from_fn(|k| self.room_scale * r[k] + self.room_translation_mm[k])
    }

    /// Device-frame position of a room position.
    pub fn device_from_room(&self, p: &Vec3<f64>) -> Vec3<f64> {
        self.device_from_room_vector(&sub(*p, self.room_translation_mm))
    }

    /// Device-frame vector (a displacement, a velocity) of a room vector:
    /// turned and scaled, not moved.
    pub fn device_from_room_vector(&self, v: &Vec3<f64>) -> Vec3<f64> {
        mat_t_vec(&self.room_rotation, *v).map(|x| x / self.room_scale)
    }

    /// The marker (device frame) when the meeting point is `p` and the
    /// end-effector is turned by `omega`.
    pub fn marker_of(&self, p: &Vec3<f64>, omega: &Vec3<f64>) -> Vec3<f64> {
        let o = mat_vec(&rotation_from_vector(*omega), self.marker_body_mm);
        core::array::from_fn(|k| p[k] + o[k])
    }

    /// Natural length of `string` beyond its spool with the meeting point
    /// at `p`, its tension `tension_n`, all strings' tension
    /// `total_tension_n` and thermal strain `strain`.
    pub fn natural_length(
        &self,
        string: usize,
        p: &Vec3<f64>,
        tension_n: f64,
        total_tension_n: f64,
        strain: f64,
    ) -> Result<StringState, SimError> {
        self.strings[string]
            .natural_length(p, tension_n, total_tension_n, strain)
            .map_err(|e| string_error(string, e))
    }

    /// Spool angle of `string` for `wound_mm` of string wound.
    pub fn spool_angle(&self, string: usize, wound_mm: f64) -> Result<f64, SimError> {
        self.spools[string]
            .angle_for_wound(wound_mm)
            .map_err(|e| string_error(string, e))
    }

    /// Encoder counts of a spool angle of `string`.
    pub fn counts_of(&self, string: usize, spool_rad: f64) -> Result<i32, SimError> {
        let theta = self.strings[string].home_spool_rad - spool_rad;
        let counts = (theta * f64::from(self.nominal.counts_per_rev[string]) / TAU).round();
        if counts.is_nan() || counts.abs() > f64::from(i32::MAX) {
            return Err(string_error(string, "its counts overflow 32 bits"));
        }
        Ok(counts as i32)
    }

    /// Centre of the sampled volume in the room frame: the nominal room
    /// image of the nominal home (as the model simulator).
    pub fn volume_centre_room(&self) -> Vec3<f64> {
        core::array::from_fn(|k| {
            self.nominal.home_mm[k] + self.nominal.room_from_device_translation_mm[k]
        })
    }
}

/// A string's state at one capture.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StringState {
    pub path: GuidePath,
    /// Sag: arc minus chord of the free span, mm.
    pub sag_mm: f64,
    /// Lead + (arc + free + sag) times the line's runs, mm.
    pub geometric_mm: f64,
    /// Unstretched length beyond the spool, mm.
    pub natural_mm: f64,
}

impl PhysicsString {
    pub(super) fn natural_length(
        &self,
        p: &Vec3<f64>,
        tension_n: f64,
        total_tension_n: f64,
        strain: f64,
    ) -> Result<StringState, String> {
        let shift = self
            .flex_direction
            .map(|x| x * self.compliance_mm_per_n * total_tension_n);
        let path = self.guide.path(&shift, p).map_err(|e| e.to_string())?;
        // Weight per mm (N/mm) and its part across the chord.
        let w = self.mass_g_per_m * 1e-6 * G_MM_PER_S2 * 1e-3;
        let cos2 = 1.0 - path.direction[2] * path.direction[2];
        let t = tension_n.max(0.05);
        let sag_mm = w * w * cos2 * path.free_mm.powi(3) / (24.0 * t * t);
        // Through pulley blocks the line runs the path (and sags) this many
        // times, at the one tension of the line.
        let geometric_mm = self.lead_mm + self.line_runs * (path.length_mm + sag_mm);
        let natural_mm = geometric_mm / (1.0 + tension_n / self.stiffness_n) / (1.0 + strain);
        Ok(StringState {
            path,
            sag_mm,
            geometric_mm,
            natural_mm,
        })
    }
}
