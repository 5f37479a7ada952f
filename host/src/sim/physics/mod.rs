//! The independent simulator (`spidar simulate --physics independent`): a
//! string-based haptic device written from a different physical
//! description than the calibration model, so that the model cannot be
//! exact on its data. It shares with the model simulator ([`super`]) only
//! what is not physics: the design (`[nominal]`), the tracker's frame,
//! noise and occlusions, the commanded tensions, the paper's lattice and
//! the random test paths (the model simulator's `trajectory` module), and the dataset writer. It
//! never evaluates the model's string law, effect terms, identification or
//! kinematics.
//!
//! # The physics (device frame, mm, N)
//!
//! The number of strings is the number of anchors of the design. String
//! `i`, from its spool to the end-effector:
//!
//! 1. **Layered spool** ([`spool`]): the string is wound in layers on a
//!    spool of bare radius `r0` (7.5 mm design, 2 % shared + 0.3 % own
//!    error), width `W` in 3..6 mm, string diameter `d` 0.5 mm (2 %); the
//!    winding radius is a staircase `R_k = r0 + d/2 + k c d` (`c` in
//!    0.86..1), `n_k = W / (d (1 + u_k))` turns per layer (`u_k` in 0..0.2:
//!    uneven pitch), a ramp of 0.5..1.5 rad at each layer change and a
//!    cross-over of 0.05..0.15 mm over 0.3..0.6 rad in every turn.
//!    `wound(phi)` is its exact integral.
//! 2. **Lead**: 50..300 mm of string from the spool to the guide, fixed.
//! 3. **Guide pulley** ([`guide`]) at the corner, radius `rho` 6..12 mm,
//!    swivelling about the frame edge (tilted up to 2 degrees): the string
//!    wraps `rho beta` and leaves at a tangent point that moves with its
//!    direction; free length `l = sqrt(m^2 - rho^2)`. The design anchor is
//!    the exit point for a string to the nominal home (each as-built exit
//!    point 3 mm sd off the design).
//! 4. **Frame flex**: each guide moves by `k_i * sum_j T_j` along its own
//!    direction (towards the frame centre, tilted at random), `k_i` in
//!    0.005..0.02 mm/N.
//! 5. **Sag**: the free span of a string of linear weight `w` (0.3..1 g/m)
//!    under tension `T` is longer than its chord by
//!    `w^2 cos^2(a) l^3 / (24 T^2)` (parabolic catenary, `a` the chord's
//!    inclination).
//! 6. **Elastic string**: the geometric length `G = lead + rho beta + l + sag`
//!    is the natural length `U` stretched: `G = U (1 + T / EA)`, `EA` in
//!    10..30 kN.
//! 7. **Counts**: the string on the spool is `wound = total - U` (total
//!    4000 mm + lead, 30 mm sd); the spool angle is `wound^-1` of it
//!    (bisection); counts `= round((phi_home - phi) counts_per_rev / 2 pi)`
//!    with `phi_home` the angle at the home capture (tension
//!    `pretension + jitter / 2` on every string): counts grow as string is
//!    paid out, whole counts (quantization).
//! 8. **End-effector and marker**: the tracker sees a marker 8..15 mm from
//!    the strings' meeting point (fixed in the end-effector's body); the
//!    end-effector turns with the hand's posture, a smooth rotation of
//!    2 degrees amplitude per axis across the volume (wavelength 2 m) plus
//!    0.3 degrees sd of jitter per capture. The paths are the marker's.
//! 9. **Home error**: the true home is 25 mm sd off the nominal one.
//! 10. **Abnormal motor** (string 4): when its free string is shorter than
//!     1600 mm the string may ride out of its groove (probability 0.7 per
//!     visit of that region) onto a radius 10..30 % larger, so the encoder
//!     under-counts what is wound in since the visit began; and the spool
//!     jams (probability 0.1 per capture there): the encoder repeats its
//!     previous reading.
//! 11. **Tracker**: the model simulator's (`[tracker]`): 0.2 mm sd per axis,
//!     1 degree rotation, occlusions (empty ots fields).
//!
//! Undeclared effects ([`effects`]): `drift-all`, `frame-flex`,
//! `marker-offset`, `slip`, `heavy-string`.

pub mod config;
pub mod effects;
pub mod guide;
pub mod spool;

use rand::rngs::ChaCha8Rng;
use rand::RngExt;
use rand_distr::Distribution;
use serde::{Deserialize, Serialize};
use spidar_core::model::Vec3;
use std::f64::consts::TAU;

pub use config::{PhysicsAbnormalMotor, PhysicsAsBuilt, PhysicsConfig};
pub use effects::{parse_effect, parse_effects, PhysicsEffect, EFFECT_NAMES};
pub use guide::{Guide, GuidePath};
pub use spool::{Spool, SpoolParams};

use super::device::{normal, stream};
use super::{trajectory, SessionKind, SimError, SimulateReport, SimulateRequest};
use crate::data::dataset::{Geometry, Sample, Session};
use spidar_core::geometry::{
    dot, mat_t_vec, mat_vec, norm, rotation_about_axis, rotation_from_vector, sub,
};

const G_MM_PER_S2: f64 = 9806.65;

/// One string as built.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsString {
    pub guide: Guide,
    /// String from the spool to the guide entry, mm.
    pub lead_mm: f64,
    pub spool: SpoolParams,
    /// Axial stiffness `E A`, N.
    pub stiffness_n: f64,
    /// Linear mass, g/m.
    pub mass_g_per_m: f64,
    /// Natural length of the whole string (spool core to end-effector), mm.
    pub total_mm: f64,
    /// Guide displacement per newton of total string tension, mm/N.
    pub compliance_mm_per_n: f64,
    /// Unit direction of that displacement.
    pub flex_direction: Vec3<f64>,
    /// Spool angle at the home capture, rad.
    pub home_spool_rad: f64,
}

/// The end-effector's rotation with the hand's posture: rotation vector
/// `omega_k = amplitude sin(wave_k . p + phase_k)` (+ jitter per capture).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Posture {
    pub amplitude_rad: f64,
    /// Wave vectors, rad/mm.
    pub wave: [Vec3<f64>; 3],
    pub phase: Vec3<f64>,
    pub jitter_rad: f64,
}

impl Posture {
    fn rotation_vector(&self, p: &Vec3<f64>) -> Vec3<f64> {
        core::array::from_fn(|k| self.amplitude_rad * (dot(self.wave[k], *p) + self.phase[k]).sin())
    }
}

/// The tracker's reading of the body's orientation: the room rotation after
/// the body's turn `omega` (device frame), then a measurement error `error`
/// (rotation vector, room frame), written as a tracker's rotation is
/// ([`crate::data::observe::orientation_of_rotation`]).
fn body_to_room_quaternion(
    room_rotation: &[[f64; 3]; 3],
    omega: &Vec3<f64>,
    error: &Vec3<f64>,
) -> Option<[f64; 4]> {
    use nalgebra::{Matrix3, Rotation3, Vector3};
    // The room rotation is one (drawn as an axis and an angle), taken as it
    // is: `from_matrix`'s search misses some exact half turns.
    let room = Rotation3::from_matrix_unchecked(Matrix3::from_fn(|r, c| room_rotation[r][c]));
    let body = Rotation3::new(Vector3::new(omega[0], omega[1], omega[2]));
    let noise = Rotation3::new(Vector3::new(error[0], error[1], error[2]));
    let m = (noise * room * body).into_inner();
    crate::data::observe::orientation_of_rotation(&core::array::from_fn(|r| {
        core::array::from_fn(|c| m[(r, c)])
    }))
}

/// One device of the independent simulator, as built (serialized as its
/// `truth.toml`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PhysicsDevice {
    /// The device seed.
    pub seed: u64,
    /// The design, as written to `geometry.toml` (not in the truth).
    #[serde(skip)]
    pub nominal: Geometry,
    pub strings: Vec<PhysicsString>,
    /// True strings' meeting point at home, mm.
    pub home_mm: Vec3<f64>,
    /// Tension of every string at the home capture, N.
    pub home_tension_n: f64,
    /// True room-from-device transform of the tracker: `p_room = s R p + t`.
    pub room_rotation: [[f64; 3]; 3],
    pub room_translation_mm: Vec3<f64>,
    pub room_scale: f64,
    /// The marker in the end-effector's body frame (origin: the meeting point), mm.
    pub marker_body_mm: Vec3<f64>,
    pub posture: Posture,
    pub effects: Vec<PhysicsEffect>,
    pub config: PhysicsConfig,
    #[serde(skip)]
    spools: Vec<Spool>,
}

/// What really happened at one capture (for tests and benchmarks).
#[derive(Clone, Debug, PartialEq)]
pub struct PhysicsTruth {
    /// Strings' meeting point, device frame, mm.
    pub meeting_mm: Vec3<f64>,
    /// True marker position, room frame, mm.
    pub marker_room_mm: Vec3<f64>,
    /// Per string: the guide's exit point, mm.
    pub exit_mm: Vec<Vec3<f64>>,
    /// Per string: free (tangent) length, mm.
    pub free_mm: Vec<f64>,
    /// Per string: geometric length from the spool (lead + arc + free + sag), mm.
    pub geometric_mm: Vec<f64>,
    /// Per string: natural (unstretched) length beyond the spool, mm.
    pub natural_mm: Vec<f64>,
    /// Per string: true spool angle, rad.
    pub spool_rad: Vec<f64>,
    /// Per string: what it has slipped on its spool since home, mm (the
    /// `slip` effect's events up to this capture).
    pub slipped_mm: Vec<f64>,
    /// The abnormal motor's counts are wrong at this capture.
    pub abnormal: bool,
    /// Lattice cell (lattice sessions).
    pub cell: Option<[u32; 3]>,
}

/// One capture of an N-string device, before it becomes a dataset row.
#[derive(Clone, Debug, PartialEq)]
pub struct PhysicsRow {
    pub t_s: f64,
    pub counts: Vec<i32>,
    pub tracker: Option<Vec3<f64>>,
    /// The tracked body's orientation (`[w, x, y, z]`, body to room), when
    /// the tracker gives one and sees the body.
    pub orientation: Option<[f64; 4]>,
    pub tension_n: Vec<f64>,
}

/// The one step from N-string captures to dataset rows (N = 3..8, on
/// channels `0..N`; the other channels' counts and tensions are 0).
pub fn rows_to_session(rows: Vec<PhysicsRow>) -> Result<Session, SimError> {
    let strings = rows
        .first()
        .map_or(spidar_core::STRINGS, |r| r.counts.len());
    let samples = rows
        .into_iter()
        .map(|r| {
            let n = r.counts.len();
            if n != strings
                || r.tension_n.len() != n
                || !(crate::data::dataset::MIN_STRINGS..=spidar_core::STRINGS).contains(&n)
            {
                return Err(wrong_count(n));
            }
            let mut counts = [0i32; spidar_core::STRINGS];
            counts[..n].copy_from_slice(&r.counts);
            let mut tension = [0.0; spidar_core::STRINGS];
            tension[..n].copy_from_slice(&r.tension_n);
            Ok(Sample {
                t_s: r.t_s,
                counts,
                tracker: r.tracker,
                orientation: r.orientation,
                legacy: None,
                tension_n: Some(tension),
            })
        })
        .collect::<Result<Vec<_>, SimError>>()?;
    Ok(Session {
        strings,
        samples,
        ignored_columns: Vec::new(),
        tracker_z: true,
    })
}

fn wrong_count(n: usize) -> SimError {
    SimError::Config {
        field: "nominal".into(),
        problem: format!(
            "a row of {n} strings: a session holds {}..={} strings, the same in every row",
            crate::data::dataset::MIN_STRINGS,
            spidar_core::STRINGS
        ),
    }
}

/// Uniform in `[r[0], r[1]]`; always one draw, so that narrowing one range
/// (to a point, say) leaves every other parameter of the device unchanged.
fn uniform(rng: &mut ChaCha8Rng, r: [f64; 2]) -> f64 {
    r[0] + (r[1] - r[0]) * rng.random_range(0.0..=1.0)
}

fn unit(v: Vec3<f64>) -> Vec3<f64> {
    let n = norm(v);
    v.map(|x| x / n)
}

/// A unit vector at `angle` rad from the unit vector `axis`, in a random direction.
fn tilted(axis: Vec3<f64>, angle: f64, rng: &mut ChaCha8Rng) -> Vec3<f64> {
    let trial = if axis[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let t = dot(trial, axis);
    let a = unit(core::array::from_fn(|k| trial[k] - t * axis[k]));
    let b = [
        axis[1] * a[2] - axis[2] * a[1],
        axis[2] * a[0] - axis[0] * a[2],
        axis[0] * a[1] - axis[1] * a[0],
    ];
    let psi = rng.random_range(0.0..TAU);
    let (s, c) = angle.sin_cos();
    unit(core::array::from_fn(|k| {
        c * axis[k] + s * (psi.cos() * a[k] + psi.sin() * b[k])
    }))
}

fn string_error(string: usize, what: impl std::fmt::Display) -> SimError {
    SimError::Config {
        field: format!("string {string}"),
        problem: what.to_string(),
    }
}

impl PhysicsDevice {
    /// Build the device: draw its as-built physics from `seed`, apply the
    /// configured undeclared effects.
    pub fn new(config: &PhysicsConfig, seed: u64) -> Result<PhysicsDevice, SimError> {
        config.validate()?;
        let nominal = Geometry {
            // The pretension its initialization commands at the home
            // capture (what the strings hold is that and their jitter).
            home_tension_n: (config.tension.pretension_n > 0.0)
                .then_some(config.tension.pretension_n),
            ..config.nominal.geometry()
        };
        let ab = &config.as_built;
        let effects = parse_effects(&config.effects)?;
        let strings = nominal.strings();
        // A planar device: the exits, home and the strings' meeting point
        // stay in the anchors' plane (the as-built errors are in it); the
        // guides swivel about the plane's normal, the strings sag out of
        // it, the hand turns about the normal only.
        let planar = nominal.layout.planar;

        let mut rng = stream(seed, 101);
        let anchor_noise = normal("as_built.anchor_sigma_mm", ab.anchor_sigma_mm)?;
        let exits: Vec<Vec3<f64>> = nominal
            .anchors_mm
            .iter()
            .take(strings)
            .map(|a| {
                let mut e = a.map(|x| x + anchor_noise.sample(&mut rng));
                if planar {
                    e[2] = a[2];
                }
                e
            })
            .collect();

        let mut rng = stream(seed, 102);
        let home_noise = normal("as_built.home_sigma_mm", ab.home_sigma_mm)?;
        let mut home_mm: Vec3<f64> =
            core::array::from_fn(|k| nominal.home_mm[k] + home_noise.sample(&mut rng));
        if planar {
            home_mm[2] = nominal.home_mm[2];
        }

        // Guides: swivel axis along the frame edge, away from the home
        // height; entry point placed so that the string to the nominal home
        // leaves at the as-built exit point.
        let mut rng = stream(seed, 103);
        let mut guides = Vec::with_capacity(strings);
        for (i, exit) in exits.iter().enumerate() {
            let up = if exit[2] >= nominal.home_mm[2] {
                1.0
            } else {
                -1.0
            };
            let axis = tilted([0.0, 0.0, up], ab.guide_tilt_deg.to_radians(), &mut rng);
            let mut guide = Guide {
                entry_mm: *exit,
                axis,
                radius_mm: uniform(&mut rng, ab.guide_radius_mm),
            };
            for _ in 0..6 {
                let path = guide
                    .path(&[0.0; 3], &nominal.home_mm)
                    .map_err(|e| string_error(i, e))?;
                for ((a, x), t) in guide.entry_mm.iter_mut().zip(exit).zip(path.exit_mm) {
                    *a += x - t;
                }
            }
            guides.push(guide);
        }

        let mut rng = stream(seed, 104);
        let shared = 1.0
            + normal(
                "as_built.spool_radius_shared_sigma",
                ab.spool_radius_shared_sigma,
            )?
            .sample(&mut rng);
        let each = normal(
            "as_built.spool_radius_each_sigma",
            ab.spool_radius_each_sigma,
        )?;
        let diameter = normal("as_built.string_diameter_sigma", ab.string_diameter_sigma)?;
        let total_noise = normal("as_built.string_total_sigma_mm", ab.string_total_sigma_mm)?;
        let heavy = effects.iter().find_map(|e| match e {
            PhysicsEffect::HeavyString { g_per_m } => Some(*g_per_m),
            _ => None,
        });
        let flex: f64 = effects
            .iter()
            .map(|e| match e {
                PhysicsEffect::FrameFlex { factor } => *factor,
                _ => 1.0,
            })
            .product();
        let home_tension_n = config.tension.pretension_n + config.tension.jitter_n / 2.0;
        let home_total_tension = home_tension_n * strings as f64;

        let mut out = Vec::with_capacity(strings);
        let mut spools = Vec::with_capacity(strings);
        let mut flex_rng = stream(seed, 106);
        for (i, guide) in guides.into_iter().enumerate() {
            let d = ab.string_diameter_mm * (1.0 + diameter.sample(&mut rng)).max(0.5);
            let bare = nominal.pulley_radius_mm[i] * shared * (1.0 + each.sample(&mut rng));
            let width = uniform(&mut rng, ab.spool_width_mm);
            let lead_mm = uniform(&mut rng, ab.lead_mm);
            let total_mm = ab.string_total_mm + total_noise.sample(&mut rng) + lead_mm;
            let mut params = SpoolParams {
                bare_radius_mm: bare,
                string_diameter_mm: d,
                layer_packing: uniform(&mut rng, ab.layer_packing),
                turns_per_layer: Vec::new(),
                layer_change_rad: uniform(&mut rng, ab.layer_change_rad),
                crossover_rise_mm: uniform(&mut rng, ab.crossover_rise_mm),
                crossover_rad: uniform(&mut rng, ab.crossover_rad),
            };
            // Layers until the spool holds the whole string, and one more.
            let mut capacity = 0.0;
            while capacity <= total_mm {
                let k = params.turns_per_layer.len();
                let turns = width / (d * (1.0 + uniform(&mut rng, ab.pitch_excess)));
                params.turns_per_layer.push(turns);
                capacity += TAU * turns * (bare + d / 2.0 + k as f64 * params.layer_packing * d);
                if params.turns_per_layer.len() > 100_000 {
                    return Err(string_error(i, "the spool would need over 100000 layers"));
                }
            }
            params.turns_per_layer.push(width / d);
            let spool = Spool::new(params.clone());
            let towards_centre = unit(sub(nominal.home_mm, guide.entry_mm));
            let mut s = PhysicsString {
                guide,
                lead_mm,
                spool: params,
                stiffness_n: uniform(&mut rng, ab.string_stiffness_n),
                mass_g_per_m: {
                    let drawn = uniform(&mut rng, ab.string_mass_g_per_m);
                    heavy.unwrap_or(drawn)
                },
                total_mm,
                compliance_mm_per_n: flex * uniform(&mut flex_rng, ab.frame_compliance_mm_per_n),
                flex_direction: tilted(towards_centre, 0.5, &mut flex_rng),
                home_spool_rad: 0.0,
            };
            let home = s
                .natural_length(&home_mm, home_tension_n, home_total_tension, 0.0)
                .map_err(|e| string_error(i, e))?;
            let wound = total_mm - home.natural_mm;
            s.home_spool_rad = spool
                .angle_for_wound(wound)
                .map_err(|e| string_error(i, format!("at home ({:.1} mm wound): {e}", wound)))?;
            out.push(s);
            spools.push(spool);
        }

        let mut rng = stream(seed, 107);
        // Drawn whatever the effects, so that an effect changes only itself.
        let drawn = uniform(&mut rng, ab.marker_offset_mm);
        let offset = match effects.iter().rev().find_map(|e| match e {
            PhysicsEffect::MarkerOffset { mm, deg } => Some((*mm, *deg)),
            _ => None,
        }) {
            Some((mm, deg)) => (mm, deg.to_radians()),
            None => (drawn, ab.posture_amplitude_deg.to_radians()),
        };
        let direction = tilted(
            [0.0, 0.0, 1.0],
            rng.random_range(0.0..std::f64::consts::PI),
            &mut rng,
        );
        let marker_body_mm = direction.map(|x| x * offset.0);
        let k = TAU / ab.posture_wavelength_mm;
        let mut wave = [[0.0; 3]; 3];
        for w in wave.iter_mut() {
            let dir = tilted(
                [0.0, 0.0, 1.0],
                rng.random_range(0.0..std::f64::consts::PI),
                &mut rng,
            );
            *w = dir.map(|x| x * k);
        }
        let posture = Posture {
            amplitude_rad: offset.1,
            wave,
            phase: core::array::from_fn(|_| rng.random_range(0.0..TAU)),
            jitter_rad: ab.posture_jitter_deg.to_radians(),
        };

        let mut rng = stream(seed, 108);
        let tr = &config.tracker;
        let axis = tilted(
            [0.0, 0.0, 1.0],
            rng.random_range(0.0..std::f64::consts::PI),
            &mut rng,
        );
        let room_rotation = rotation_about_axis(axis, tr.rotation_deg.to_radians());
        let t_noise = normal("tracker.translation_sigma_mm", tr.translation_sigma_mm)?;
        let room_translation_mm: Vec3<f64> = core::array::from_fn(|k| {
            nominal.room_from_device_translation_mm[k] + t_noise.sample(&mut rng)
        });

        Ok(PhysicsDevice {
            seed,
            nominal,
            strings: out,
            home_mm,
            home_tension_n,
            room_rotation,
            room_translation_mm,
            room_scale: tr.scale,
            marker_body_mm,
            posture,
            effects,
            config: config.clone(),
            spools,
        })
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
        let d = sub(*p, self.room_translation_mm);
        mat_t_vec(&self.room_rotation, d).map(|x| x / self.room_scale)
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
    /// Lead + arc + free + sag, mm.
    pub geometric_mm: f64,
    /// Unstretched length beyond the spool, mm.
    pub natural_mm: f64,
}

impl PhysicsString {
    fn natural_length(
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
        let geometric_mm = self.lead_mm + path.length_mm + sag_mm;
        let natural_mm = geometric_mm / (1.0 + tension_n / self.stiffness_n) / (1.0 + strain);
        Ok(StringState {
            path,
            sag_mm,
            geometric_mm,
            natural_mm,
        })
    }
}

fn round_to(x: f64, per_unit: f64) -> f64 {
    (x * per_unit).round() / per_unit
}

/// Slip events of a session: `(time s, string, mm)`.
fn slip_events(
    effects: &[PhysicsEffect],
    strings: usize,
    duration_s: f64,
    rng: &mut ChaCha8Rng,
) -> Vec<(f64, usize, f64)> {
    let mut events = Vec::new();
    for e in effects {
        if let PhysicsEffect::Slip { per_h, mm } = *e {
            if per_h <= 0.0 {
                continue;
            }
            let mut t = 0.0;
            loop {
                let u: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
                t += -u.ln() * 3600.0 / per_h;
                if t >= duration_s {
                    break;
                }
                let string = rng.random_range(0..strings);
                let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
                events.push((t, string, sign * mm * rng.random_range(0.5..=1.0)));
            }
        }
    }
    events
}

/// Simulate one session of `device`; `seed` draws the path, the tensions,
/// the posture jitter, the tracker noise, the occlusions, the slips and the
/// abnormal motor (each from its own stream). Times are whole
/// milliseconds, tensions whole millinewtons, positions whole micrometres.
pub fn simulate_session(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
) -> Result<(Session, Vec<PhysicsTruth>), SimError> {
    let (rows, truths) = simulate_rows(device, kind, seed)?;
    Ok((rows_to_session(rows)?, truths))
}

/// [`simulate_session`] before the rows become a dataset session (any
/// number of strings).
pub fn simulate_rows(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
) -> Result<(Vec<PhysicsRow>, Vec<PhysicsTruth>), SimError> {
    let cfg = &device.config;
    let n = device.string_count();
    let centre = device.volume_centre_room();
    let home_omega = device.posture.rotation_vector(&device.home_mm);
    let start = device.room_from_device(&device.marker_of(&device.home_mm, &home_omega));
    let mut path_rng = stream(seed, 110);
    let captures = trajectory::captures(
        kind,
        &cfg.lattice,
        &cfg.random,
        &cfg.tracker,
        centre,
        start,
        &mut path_rng,
    )?;
    let duration_s = captures.last().map_or(0.0, |c| f64::from(c.t_ms) / 1000.0);

    let mut tension_rng = stream(seed, 111);
    let mut noise_rng = stream(seed, 112);
    let mut occlusion_rng = stream(seed, 113);
    let mut abnormal_rng = stream(seed, 114);
    let mut posture_rng = stream(seed, 115);
    let mut slip_rng = stream(seed, 116);
    let mut orientation_rng = stream(seed, 117);
    let orientation_noise = normal(
        "orientation.sigma_deg",
        cfg.orientation.sigma_deg.to_radians(),
    )?;
    let noise = normal("tracker.noise_sigma_mm", cfg.tracker.noise_sigma_mm)?;
    let jitter = normal("as_built.posture_jitter_deg", device.posture.jitter_rad)?;
    let slips = slip_events(&device.effects, n, duration_s, &mut slip_rng);
    let drift_per_s: f64 = device
        .effects
        .iter()
        .map(|e| match e {
            PhysicsEffect::DriftAll { ppm_per_h } => ppm_per_h * 1e-6 / 3600.0,
            _ => 0.0,
        })
        .sum();
    let am = &cfg.abnormal_motor;
    let abnormal_string =
        (am.enabled && usize::from(am.string) < n).then_some(usize::from(am.string));
    // Abnormal motor state: inside its region, off the groove since wound = w0, excess g.
    let mut in_region = false;
    let mut off_groove: Option<(f64, f64)> = None;
    let mut previous_counts: Option<Vec<i32>> = None;

    let planar = device.nominal.layout.planar;
    let plane_z = device.home_mm[2];
    let mut occluded = false;
    let mut rows = Vec::with_capacity(captures.len());
    let mut truths = Vec::with_capacity(captures.len());
    for c in &captures {
        let t_s = f64::from(c.t_ms) / 1000.0;
        let mut marker = device.device_from_room(&c.room);
        let mut omega = device.posture.rotation_vector(&marker);
        for w in omega.iter_mut() {
            *w += jitter.sample(&mut posture_rng);
        }
        if planar {
            omega[0] = 0.0;
            omega[1] = 0.0;
        }
        let o = mat_vec(&rotation_from_vector(omega), device.marker_body_mm);
        let mut meeting: Vec3<f64> = core::array::from_fn(|k| marker[k] - o[k]);
        if planar {
            // The strings meet in the plane; the marker is where the hand
            // holds it from there.
            meeting[2] = plane_z;
            marker = core::array::from_fn(|k| meeting[k] + o[k]);
        }
        // Not a round trip through the device frame unless the marker moved:
        // the 3-D sessions stay bit for bit what they were.
        let marker_room = if planar {
            device.room_from_device(&marker)
        } else {
            c.room
        };

        let ts = &cfg.tension;
        let tension_n: Vec<f64> = (0..n)
            .map(|_| {
                let mut t = ts.pretension_n + ts.jitter_n * tension_rng.random_range(0.0..1.0);
                if tension_rng.random_bool(ts.active_probability) {
                    t += ts.active_max_n * tension_rng.random_range(0.0..1.0);
                }
                round_to(t.clamp(0.0, 65.535), 1000.0)
            })
            .collect();
        let total_tension: f64 = tension_n.iter().sum();
        let strain = drift_per_s * t_s;

        let mut counts = Vec::with_capacity(n);
        let mut truth = PhysicsTruth {
            meeting_mm: meeting,
            marker_room_mm: marker_room,
            exit_mm: Vec::with_capacity(n),
            free_mm: Vec::with_capacity(n),
            geometric_mm: Vec::with_capacity(n),
            natural_mm: Vec::with_capacity(n),
            spool_rad: Vec::with_capacity(n),
            slipped_mm: Vec::with_capacity(n),
            abnormal: false,
            cell: c.cell,
        };
        for i in 0..n {
            let state = device.natural_length(i, &meeting, tension_n[i], total_tension, strain)?;
            let slipped: f64 = slips
                .iter()
                .filter(|(at, s, _)| *s == i && *at <= t_s)
                .map(|(_, _, mm)| mm)
                .sum();
            truth.slipped_mm.push(slipped);
            let wound = device.strings[i].total_mm - slipped - state.natural_mm;
            let phi = device.spool_angle(i, wound).map_err(|e| at_time(e, t_s))?;
            let mut read_phi = phi;
            if Some(i) == abnormal_string {
                let inside = state.path.free_mm < am.region_length_mm;
                if inside && !in_region {
                    off_groove = abnormal_rng
                        .random_bool(am.out_of_groove_probability)
                        .then(|| (wound, uniform(&mut abnormal_rng, am.radius_excess)));
                }
                if !inside {
                    off_groove = None;
                }
                in_region = inside;
                if let Some((w0, g)) = off_groove {
                    if wound > w0 {
                        // Wound in off the groove, on a radius 1 + g larger:
                        // the spool turned 1 + g times less.
                        read_phi = device
                            .spool_angle(i, w0 + (wound - w0) / (1.0 + g))
                            .map_err(|e| at_time(e, t_s))?;
                        truth.abnormal = true;
                    }
                }
            }
            let mut k = device.counts_of(i, read_phi)?;
            if Some(i) == abnormal_string
                && in_region
                && abnormal_rng.random_bool(am.jam_probability)
            {
                if let Some(prev) = &previous_counts {
                    k = prev[i];
                    truth.abnormal = true;
                }
            }
            counts.push(k);
            truth.exit_mm.push(state.path.exit_mm);
            truth.free_mm.push(state.path.free_mm);
            truth.geometric_mm.push(state.geometric_mm);
            truth.natural_mm.push(state.natural_mm);
            truth.spool_rad.push(phi);
        }
        previous_counts = Some(counts.clone());

        let tr = &cfg.tracker;
        occluded = if occluded {
            !occlusion_rng.random_bool(1.0 / tr.occlusion_mean_rows)
        } else {
            occlusion_rng.random_bool(tr.occlusion_probability)
        };
        let measured: Vec3<f64> = core::array::from_fn(|k| {
            round_to(marker_room[k] + noise.sample(&mut noise_rng), 1000.0)
        });
        // The body turns with the hand (`omega`, device frame); the tracker
        // reads its orientation in the room, with its own noise.
        let orientation = (cfg.orientation.enabled && !occluded)
            .then(|| {
                let err: [f64; 3] =
                    core::array::from_fn(|_| orientation_noise.sample(&mut orientation_rng));
                body_to_room_quaternion(&device.room_rotation, &omega, &err)
            })
            .flatten();
        rows.push(PhysicsRow {
            t_s,
            counts,
            tracker: (!occluded).then_some(measured),
            orientation,
            tension_n,
        });
        truths.push(truth);
    }
    Ok((rows, truths))
}

fn at_time(e: SimError, t_s: f64) -> SimError {
    match e {
        SimError::Config { field, problem } => SimError::Config {
            field,
            problem: format!("{problem} (t = {t_s} s)"),
        },
        other => other,
    }
}

/// `truth.toml` of the independent simulator (tests and benchmarks only).
fn write_truth(device: &PhysicsDevice, path: &std::path::Path) -> Result<(), SimError> {
    let body = toml::to_string(device).map_err(|e| SimError::Config {
        field: "truth".into(),
        problem: format!("cannot encode the truth as TOML: {e}"),
    })?;
    let text = format!(
        "# Independent simulator ground truth: the device as built.\n\
         # For tests and benchmarks only; calibration never reads this file.\n{body}"
    );
    std::fs::write(path, text).map_err(|source| SimError::Io {
        file: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}

/// `spidar simulate --physics independent`: the same files as the model
/// simulator (nominal `geometry.toml`, the session CSV, `truth.toml`).
pub fn run_simulate(args: &SimulateRequest) -> Result<SimulateReport, SimError> {
    let mut config = match &args.config {
        Some(path) => PhysicsConfig::load(path)?,
        None => PhysicsConfig::default(),
    };
    config.effects.extend(args.effects.iter().cloned());
    let kind = super::session_kind(args, config.random.points)?;
    let device = PhysicsDevice::new(&config, args.seed)?;
    let (session, _) = simulate_session(&device, kind, super::session_seed(args, kind))?;
    super::write_outputs(
        args,
        kind,
        &device.nominal,
        &session,
        |truth| write_truth(&device, truth),
        None,
    )
}
