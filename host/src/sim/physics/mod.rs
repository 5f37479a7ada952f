//! The independent simulator (`spidar simulate --physics independent`): a
//! string-based haptic device written from a different physical
//! description than the calibration model, so that the model cannot be
//! exact on its data. It shares with the model simulator ([`super`]) only
//! what is not physics: the design (`[nominal]`), the tracker's frame,
//! noise, occlusions and clock, the commanded tensions, the paper's lattice,
//! the random test paths and the streams (the model simulator's
//! `trajectory` module), and the dataset writer. It
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
//!    point 3 mm sd per coordinate off the design, `as_built.anchor_sigma_mm`;
//!    a wall robot's cables leave from pulleys tens of mm off the frame's
//!    corners its drawing gives: 60 mm in the `wall-robot` preset).
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
//! 9. **Carriage** (`[carriage]`, off by default: the strings meet at one
//!    point): each string is tied at its own attachment point `a_i` of a
//!    rigid carriage (fixed in the end-effector's body, from its reference
//!    point `p`, the meeting point above), so its free span ends at
//!    `p + R a_i` and its length is `|exit - (p + R a_i)|` over the guide;
//!    `R` is the end-effector's turn of item 8, about the plane's normal
//!    only on a planar device (the carriage's yaw, a few degrees: a smooth
//!    function of position plus jitter). The `wall-robot` preset ties each
//!    cable at the corner of a 100 mm square carriage facing its anchor.
//! 10. **Home error**: the true home is 25 mm sd off the nominal one.
//! 11. **Abnormal motor** (string 4): when its free string is shorter than
//!     1600 mm the string may ride out of its groove (probability 0.7 per
//!     visit of that region) onto a radius 10..30 % larger, so the encoder
//!     under-counts what is wound in since the visit began; and the spool
//!     jams (probability 0.1 per capture there): the encoder repeats its
//!     previous reading.
//! 12. **Tracker**: the model simulator's (`[tracker]`): 0.2 mm sd per axis,
//!     1 degree rotation, occlusions (empty ots fields), and its clock:
//!     the row stamped `t` (device time) holds the marker where it was at
//!     `t - tracker.clock_offset_s` (plus `tracker.clock_drift_ppm`),
//!     interpolated between captures; rows before the tracker's first
//!     instant are occluded.
//!
//! # Sessions
//!
//! The paper's lattice and random test points (the model simulator's), and
//! **streams** (`[stream]`, `--kind stream` / `--kind wide-stream`): a
//! continuous path captured at `stream.rate_hz` (100 Hz), the hand moving
//! between random waypoints in minimum-jerk strokes at about
//! `stream.speed_mm_s` (0.8..1.2 m/s mean per leg), 10 to 30000 rows; a
//! training stream covers the central `stream.training_span` of each side
//! of the workspace `stream.area_mm`, a wide stream (a test session) the
//! whole of it, beyond the training area.
//!
//! # Presets
//!
//! Named devices ([`PRESET_NAMES`], `--preset NAME`), each a configuration
//! file in `presets/`: `wall-robot`, a planar 4-cable wall robot (2 m x
//! 1.5 m frame, exits 60 mm sd off its corners, 30 mm spools, the carriage
//! above, a position-only tracker 0.3 mm sd whose clock is 1.8 s ahead,
//! 60 s streams at 100 Hz).
//!
//! Undeclared effects ([`effects`]): `drift-all`, `drift-each`, `frame-flex`,
//! `marker-offset`, `slip`, `heavy-string`, `latency`.

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

pub use config::{
    CarriageConfig, PhysicsAbnormalMotor, PhysicsAsBuilt, PhysicsConfig, StreamConfig, PRESET_NAMES,
};
pub use effects::{parse_effect, parse_effects, PhysicsEffect, EFFECT_NAMES};
pub use guide::{Guide, GuidePath};
pub use spool::{Spool, SpoolParams};

use super::simulated_device::{declaring_pretension, draw_home, normal, stream};
use super::{trajectory, SessionKind, SimError, SimulateReport, SimulateRequest, StreamArea};
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
    /// Strings' meeting point, device frame, mm (on a carriage, its
    /// reference point: where the strings would meet without it).
    pub meeting_mm: Vec3<f64>,
    /// The end-effector's (carriage's) turn, a rotation vector in the
    /// device frame, rad: `[0, 0, yaw]` on a planar device.
    pub carriage_turn_rad: Vec3<f64>,
    /// Per string: where it is tied to the end-effector, device frame, mm
    /// (the meeting point, or the carriage's attachment point).
    pub attachment_mm: Vec<Vec3<f64>>,
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
                since_home_s: None,
                home: None,
            })
        })
        .collect::<Result<Vec<_>, SimError>>()?;
    Ok(Session {
        strings,
        samples,
        ignored_columns: Vec::new(),
        unread_columns: Vec::new(),
        tracker_z: true,
    })
}

fn wrong_count(n: usize) -> SimError {
    SimError::Config(crate::ConfigError::new(
        "nominal",
        format!(
            "a row of {n} strings: a session holds {}..={} strings, the same in every row",
            crate::data::dataset::MIN_STRINGS,
            spidar_core::STRINGS
        ),
    ))
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
    SimError::Config(crate::ConfigError::new(
        format!("string {string}"),
        what.to_string(),
    ))
}

/// The as-built guides' exit points (stream 101): each 3 mm sd off its
/// design anchor (in the anchors' plane on a planar device).
fn draw_exits(
    nominal: &Geometry,
    ab: &PhysicsAsBuilt,
    seed: u64,
) -> Result<Vec<Vec3<f64>>, SimError> {
    let planar = nominal.layout.planar;
    let mut rng = stream(seed, 101);
    let anchor_noise = normal("as_built.anchor_sigma_mm", ab.anchor_sigma_mm)?;
    Ok(nominal
        .anchors_mm
        .iter()
        .take(nominal.strings())
        .map(|a| {
            let mut e = a.map(|x| x + anchor_noise.sample(&mut rng));
            if planar {
                e[2] = a[2];
            }
            e
        })
        .collect())
}

/// The guides (stream 103): swivel axis along the frame edge, away from the
/// home height; entry point placed so that the string to the nominal home
/// leaves at the as-built exit point.
fn place_guides(
    nominal: &Geometry,
    ab: &PhysicsAsBuilt,
    exits: &[Vec3<f64>],
    seed: u64,
) -> Result<Vec<Guide>, SimError> {
    let mut rng = stream(seed, 103);
    let mut guides = Vec::with_capacity(exits.len());
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
    Ok(guides)
}

/// What every string is built against: the design, the as-built spreads,
/// the true home, the tension the strings hold there and the undeclared
/// effects on the strings and the frame.
struct StringBuild<'a> {
    nominal: &'a Geometry,
    ab: &'a PhysicsAsBuilt,
    /// Where each string is tied at the home capture.
    home_attachments: Vec<Vec3<f64>>,
    home_tension_n: f64,
    /// `heavy-string`: every string's linear mass, g/m.
    heavy: Option<f64>,
    /// `frame-flex`: the factor on every guide's compliance.
    flex: f64,
}

/// The spools' and strings' spreads: the spool radius error shared by every
/// spool, and the distributions of each one's own errors.
struct SpoolSpreads {
    shared: f64,
    each: rand_distr::Normal<f64>,
    diameter: rand_distr::Normal<f64>,
    total_noise: rand_distr::Normal<f64>,
}

impl StringBuild<'_> {
    /// Every string with its guide, spool and home spool angle (spools,
    /// string dimensions and stiffness from stream 104, frame flex from 106).
    fn strings(
        &self,
        guides: Vec<Guide>,
        seed: u64,
    ) -> Result<(Vec<PhysicsString>, Vec<Spool>), SimError> {
        let ab = self.ab;
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
        let spreads = SpoolSpreads {
            shared,
            each,
            diameter,
            total_noise,
        };
        let home_total_tension = self.home_tension_n * guides.len() as f64;

        let mut out = Vec::with_capacity(guides.len());
        let mut spools = Vec::with_capacity(guides.len());
        let mut flex_rng = stream(seed, 106);
        for (i, guide) in guides.into_iter().enumerate() {
            let (s, spool) = self.string(
                i,
                guide,
                &spreads,
                home_total_tension,
                &mut rng,
                &mut flex_rng,
            )?;
            out.push(s);
            spools.push(spool);
        }
        Ok((out, spools))
    }

    /// String `i` on `guide`: its spool wound in layers until it holds the
    /// whole string, its lead, stiffness, weight and frame flex, and the
    /// spool angle at the home capture.
    fn string(
        &self,
        i: usize,
        guide: Guide,
        spreads: &SpoolSpreads,
        home_total_tension: f64,
        rng: &mut ChaCha8Rng,
        flex_rng: &mut ChaCha8Rng,
    ) -> Result<(PhysicsString, Spool), SimError> {
        let ab = self.ab;
        let d = ab.string_diameter_mm * (1.0 + spreads.diameter.sample(rng)).max(0.5);
        let bare =
            self.nominal.pulley_radius_mm[i] * spreads.shared * (1.0 + spreads.each.sample(rng));
        let width = uniform(rng, ab.spool_width_mm);
        let lead_mm = uniform(rng, ab.lead_mm);
        let total_mm = ab.string_total_mm + spreads.total_noise.sample(rng) + lead_mm;
        let mut params = SpoolParams {
            bare_radius_mm: bare,
            string_diameter_mm: d,
            layer_packing: uniform(rng, ab.layer_packing),
            turns_per_layer: Vec::new(),
            layer_change_rad: uniform(rng, ab.layer_change_rad),
            crossover_rise_mm: uniform(rng, ab.crossover_rise_mm),
            crossover_rad: uniform(rng, ab.crossover_rad),
        };
        wind_layers(&mut params, width, total_mm, ab.pitch_excess, rng)
            .map_err(|e| string_error(i, e))?;
        let spool = Spool::new(params.clone());
        let towards_centre = unit(sub(self.nominal.home_mm, guide.entry_mm));
        let mut s = PhysicsString {
            guide,
            lead_mm,
            spool: params,
            stiffness_n: uniform(rng, ab.string_stiffness_n),
            mass_g_per_m: {
                let drawn = uniform(rng, ab.string_mass_g_per_m);
                self.heavy.unwrap_or(drawn)
            },
            total_mm,
            compliance_mm_per_n: self.flex * uniform(flex_rng, ab.frame_compliance_mm_per_n),
            flex_direction: tilted(towards_centre, 0.5, flex_rng),
            home_spool_rad: 0.0,
        };
        let home = s
            .natural_length(
                &self.home_attachments[i],
                self.home_tension_n,
                home_total_tension,
                0.0,
            )
            .map_err(|e| string_error(i, e))?;
        let wound = total_mm - home.natural_mm;
        s.home_spool_rad = spool
            .angle_for_wound(wound)
            .map_err(|e| string_error(i, format!("at home ({:.1} mm wound): {e}", wound)))?;
        Ok((s, spool))
    }
}

/// The spool's layers of `width` mm: layers until the spool holds the whole
/// string (`total_mm`), and one more; each layer's turns drawn with its
/// uneven pitch (`pitch_excess`).
fn wind_layers(
    params: &mut SpoolParams,
    width: f64,
    total_mm: f64,
    pitch_excess: [f64; 2],
    rng: &mut ChaCha8Rng,
) -> Result<(), &'static str> {
    let d = params.string_diameter_mm;
    let bare = params.bare_radius_mm;
    let mut capacity = 0.0;
    while capacity <= total_mm {
        let k = params.turns_per_layer.len();
        let turns = width / (d * (1.0 + uniform(rng, pitch_excess)));
        params.turns_per_layer.push(turns);
        capacity += TAU * turns * (bare + d / 2.0 + k as f64 * params.layer_packing * d);
        if params.turns_per_layer.len() > 100_000 {
            return Err("the spool would need over 100000 layers");
        }
    }
    params.turns_per_layer.push(width / d);
    Ok(())
}

/// The marker in the end-effector's body and the hand's posture (stream
/// 107); `marker-offset` sets the marker's distance and the posture's
/// amplitude.
fn draw_marker_and_posture(
    ab: &PhysicsAsBuilt,
    effects: &[PhysicsEffect],
    seed: u64,
) -> (Vec3<f64>, Posture) {
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
    (marker_body_mm, posture)
}

/// The tracker's true room-from-device rotation and translation (stream 108).
fn draw_room_transform(
    nominal: &Geometry,
    tr: &crate::sim::config::TrackerConfig,
    seed: u64,
) -> Result<([[f64; 3]; 3], Vec3<f64>), SimError> {
    let mut rng = stream(seed, 108);
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
    Ok((room_rotation, room_translation_mm))
}

/// A turn as the end-effector makes it: on a planar device about the
/// plane's normal only (its yaw).
fn planar_turn(nominal: &Geometry, mut turn: Vec3<f64>) -> Vec3<f64> {
    if nominal.layout.planar {
        turn[0] = 0.0;
        turn[1] = 0.0;
    }
    turn
}

/// Where string `i` is tied when the end-effector's reference point is at
/// `p` and it is turned by `turn`: `p` itself when the strings meet there,
/// else `p + R(turn) attachment_i` (the carriage's corner).
fn string_end(carriage: &CarriageConfig, i: usize, p: &Vec3<f64>, turn: &Vec3<f64>) -> Vec3<f64> {
    match carriage.attachment_mm.get(i) {
        None => *p,
        Some(a) => {
            let r = mat_vec(&rotation_from_vector(*turn), *a);
            core::array::from_fn(|k| p[k] + r[k])
        }
    }
}

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

    /// Build the device: draw its as-built physics from `seed`, apply the
    /// configured undeclared effects.
    pub fn new(config: &PhysicsConfig, seed: u64) -> Result<PhysicsDevice, SimError> {
        config.validate()?;
        // What the strings hold at the home capture is that and their jitter.
        let nominal = declaring_pretension(config.nominal.geometry(), config.tension.pretension_n);
        let ab = &config.as_built;
        let effects = parse_effects(&config.effects)?;
        // A planar device: the exits, home and the strings' meeting point
        // stay in the anchors' plane (the as-built errors are in it); the
        // guides swivel about the plane's normal, the strings sag out of
        // it, the hand turns about the normal only.
        let exits = draw_exits(&nominal, ab, seed)?;
        let home_mm = draw_home(&nominal, ab.home_sigma_mm, seed, 102)?;
        let guides = place_guides(&nominal, ab, &exits, seed)?;
        let (marker_body_mm, posture) = draw_marker_and_posture(ab, &effects, seed);
        // The carriage at home turned as the posture has it there (no jitter).
        let home_turn = planar_turn(&nominal, posture.rotation_vector(&home_mm));
        let home_attachments = (0..guides.len())
            .map(|i| string_end(&config.carriage, i, &home_mm, &home_turn))
            .collect();

        let home_tension_n = config.tension.pretension_n + config.tension.jitter_n / 2.0;
        let build = StringBuild {
            nominal: &nominal,
            ab,
            home_attachments,
            home_tension_n,
            heavy: effects.iter().find_map(|e| match e {
                PhysicsEffect::HeavyString { g_per_m } => Some(*g_per_m),
                _ => None,
            }),
            flex: effects
                .iter()
                .map(|e| match e {
                    PhysicsEffect::FrameFlex { factor } => *factor,
                    _ => 1.0,
                })
                .product(),
        };
        let (strings, spools) = build.strings(guides, seed)?;
        if let Some(i) = effects.iter().find_map(|e| match e {
            PhysicsEffect::Latency {
                string: Some(i), ..
            } if *i >= strings.len() => Some(*i),
            _ => None,
        }) {
            return Err(SimError::EffectSpec {
                spec: format!("latency:string={i}"),
                problem: format!(
                    "the device has {} strings (0..{})",
                    strings.len(),
                    strings.len()
                ),
            });
        }

        let (room_rotation, room_translation_mm) =
            draw_room_transform(&nominal, &config.tracker, seed)?;

        Ok(PhysicsDevice {
            seed,
            nominal,
            strings,
            home_mm,
            home_tension_n,
            room_rotation,
            room_translation_mm,
            room_scale: config.tracker.scale,
            marker_body_mm,
            posture,
            effects,
            config: config.clone(),
            spools,
        })
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

/// An earlier session of the same home capture, which a later one
/// continues ([`simulate_session_after`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EarlierSession {
    /// Its seed (its slip events are drawn again from it).
    pub seed: u64,
    /// Its last capture's time since home, s.
    pub end_s: f64,
}

/// A session that continues `earlier` under the same home capture, a
/// minute ([`crate::sim::CONTINUATION_GAP_S`]) after its last capture: its
/// clock goes on, and the earlier session's slips and drift stay in the
/// strings (its own slips add to them).
pub fn simulate_session_after(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
    earlier: EarlierSession,
) -> Result<(Session, Vec<PhysicsTruth>), SimError> {
    let (rows, truths) = simulate_rows_from(device, kind, seed, Some(earlier))?;
    Ok((rows_to_session(rows)?, truths))
}

/// [`simulate_session`] before the rows become a dataset session (any
/// number of strings).
pub fn simulate_rows(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
) -> Result<(Vec<PhysicsRow>, Vec<PhysicsTruth>), SimError> {
    simulate_rows_from(device, kind, seed, None)
}

/// [`simulate_rows`] of a session that starts at a home capture
/// (`earlier` None) or continues `earlier`.
fn simulate_rows_from(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
    earlier: Option<EarlierSession>,
) -> Result<(Vec<PhysicsRow>, Vec<PhysicsTruth>), SimError> {
    let cfg = &device.config;
    let centre = device.volume_centre_room();
    let home_omega = device.posture.rotation_vector(&device.home_mm);
    let start = device.room_from_device(&device.marker_of(&device.home_mm, &home_omega));
    let mut path_rng = stream(seed, 110);
    let captures = match kind {
        SessionKind::Stream { rows, area } => {
            config::stream_rows("stream rows (--points or stream.rows)", rows)?;
            trajectory::stream(
                &stream_path(&cfg.stream, rows, area),
                centre,
                start,
                &mut path_rng,
            )?
        }
        _ => trajectory::captures(
            kind,
            &cfg.lattice,
            &cfg.random,
            &cfg.tracker,
            centre,
            start,
            &mut path_rng,
        )?,
    };
    let duration_s = captures.last().map_or(0.0, |c| f64::from(c.t_ms) / 1000.0);
    let start_s = earlier.map_or(0.0, |e| e.end_s + crate::sim::CONTINUATION_GAP_S);
    let captures = crate::sim::trajectory::starting_at(captures, start_s)?;

    let mut session = PhysicsSession::new(device, seed, duration_s)?;
    if let Some(e) = earlier {
        session.continue_after(e, start_s);
    }
    // The hand's whole path first: the tracker, whose clock may run apart
    // from the device's, sees the marker where it was at another capture's time.
    let poses: Vec<HandPose> = captures.iter().map(|c| session.hand_pose(c)).collect();
    let tracker_clock = TrackerClock::new(&cfg.tracker, &captures, &poses);
    let mut rows = Vec::with_capacity(captures.len());
    let mut truths = Vec::with_capacity(captures.len());
    for (c, pose) in captures.iter().zip(&poses) {
        let seen = tracker_clock.seen(f64::from(c.t_ms) / 1000.0, pose);
        let (row, truth) = session.capture(c, pose, seen)?;
        rows.push(row);
        truths.push(truth);
    }
    Ok((rows, truths))
}

/// The path of a stream of `rows` captures over `area` of the workspace.
fn stream_path(cfg: &StreamConfig, rows: usize, area: StreamArea) -> trajectory::StreamPath {
    let span = match area {
        StreamArea::Training => cfg.training_span,
        StreamArea::Whole => 1.0,
    };
    trajectory::StreamPath {
        rows,
        rate_hz: cfg.rate_hz,
        speed_mm_s: cfg.speed_mm_s,
        half_extent_mm: cfg.area_mm.map(|x| x * span / 2.0),
    }
}

/// The tracker's clock against the device's: the row stamped `t` (device
/// time) holds the marker where it was at `t - offset`, with `offset =
/// tracker.clock_offset_s + 1e-6 tracker.clock_drift_ppm t` (as the model
/// simulator's tracker), between captures by linear interpolation.
struct TrackerClock<'a> {
    offset_s: f64,
    drift_ppm: f64,
    times_s: Vec<f64>,
    poses: &'a [HandPose],
}

/// What the tracker sees at one row: the marker (room frame, mm) and the
/// body's turn (rotation vector, device frame).
type Seen = (Vec3<f64>, Vec3<f64>);

impl<'a> TrackerClock<'a> {
    fn new(
        tracker: &crate::sim::config::TrackerConfig,
        captures: &[trajectory::Capture],
        poses: &'a [HandPose],
    ) -> TrackerClock<'a> {
        TrackerClock {
            offset_s: tracker.clock_offset_s,
            drift_ppm: tracker.clock_drift_ppm,
            times_s: captures
                .iter()
                .map(|c| f64::from(c.t_ms) / 1000.0)
                .collect(),
            poses,
        }
    }

    /// What the row at device time `t_s` (the hand at `pose`) holds; None
    /// before the session's first instant or after its last.
    fn seen(&self, t_s: f64, pose: &HandPose) -> Option<Seen> {
        let offset_s = self.offset_s + 1e-6 * self.drift_ppm * t_s;
        if offset_s == 0.0 {
            return Some((pose.marker_room, pose.omega));
        }
        let t = t_s - offset_s;
        let k = self.times_s.partition_point(|&s| s <= t);
        let a = &self.poses[k.checked_sub(1)?];
        let ta = self.times_s[k - 1];
        if ta == t {
            return Some((a.marker_room, a.omega));
        }
        let (b, tb) = (self.poses.get(k)?, self.times_s[k]);
        let f = (t - ta) / (tb - ta);
        let lerp = |x: &Vec3<f64>, y: &Vec3<f64>| -> Vec3<f64> {
            core::array::from_fn(|i| x[i] + f * (y[i] - x[i]))
        };
        Some((
            lerp(&a.marker_room, &b.marker_room),
            lerp(&a.omega, &b.omega),
        ))
    }
}

/// One session of the independent simulator under way: each part of the
/// world's own random stream, the session's slips and drift, and what
/// carries over from one capture to the next (the abnormal motor's state,
/// the tracker's occlusion).
struct PhysicsSession<'a> {
    device: &'a PhysicsDevice,
    tension_rng: ChaCha8Rng,
    noise_rng: ChaCha8Rng,
    occlusion_rng: ChaCha8Rng,
    posture_rng: ChaCha8Rng,
    orientation_rng: ChaCha8Rng,
    orientation_noise: rand_distr::Normal<f64>,
    noise: rand_distr::Normal<f64>,
    jitter: rand_distr::Normal<f64>,
    /// `(time s, string, mm)`.
    slips: Vec<(f64, usize, f64)>,
    /// Each string's thermal strain per second (`drift-all`, `drift-each`).
    strain_per_s: Vec<f64>,
    /// Each string's encoder latency, s (`latency`).
    latency_s: Vec<f64>,
    abnormal: AbnormalMotor<'a>,
    occluded: bool,
}

/// The abnormal motor and its state: inside its region at the last capture,
/// off the groove since wound = `w0` on a radius `1 + g` larger, the counts
/// of the last capture (what a jammed encoder repeats).
struct AbnormalMotor<'a> {
    config: &'a PhysicsAbnormalMotor,
    /// Its string (None: disabled, or not on this device).
    string: Option<usize>,
    rng: ChaCha8Rng,
    in_region: bool,
    /// `(w0, g)`.
    off_groove: Option<(f64, f64)>,
    previous_counts: Option<Vec<i32>>,
}

/// Where the hand holds the end-effector at one capture.
struct HandPose {
    /// Strings' meeting point, device frame, mm.
    meeting: Vec3<f64>,
    /// The marker, room frame, mm.
    marker_room: Vec3<f64>,
    /// The end-effector's turn (rotation vector, device frame).
    omega: Vec3<f64>,
    /// The meeting point's velocity (device frame, mm/s): the marker's,
    /// the turn's rate left out.
    velocity: Vec3<f64>,
}

impl<'a> PhysicsSession<'a> {
    /// The streams of the session `seed` (111..117), its slips over
    /// `duration_s` and its drift.
    fn new(
        device: &'a PhysicsDevice,
        seed: u64,
        duration_s: f64,
    ) -> Result<PhysicsSession<'a>, SimError> {
        let cfg = &device.config;
        let n = device.string_count();
        let tension_rng = stream(seed, 111);
        let noise_rng = stream(seed, 112);
        let occlusion_rng = stream(seed, 113);
        let abnormal_rng = stream(seed, 114);
        let posture_rng = stream(seed, 115);
        let mut slip_rng = stream(seed, 116);
        let orientation_rng = stream(seed, 117);
        let orientation_noise = normal(
            "orientation.sigma_deg",
            cfg.orientation.sigma_deg.to_radians(),
        )?;
        let noise = normal("tracker.noise_sigma_mm", cfg.tracker.noise_sigma_mm)?;
        let jitter = normal("as_built.posture_jitter_deg", device.posture.jitter_rad)?;
        let slips = slip_events(&device.effects, n, duration_s, &mut slip_rng);
        let strain_per_s = (0..n).map(|i| device.string_creep_per_s(i)).collect();
        let latency_s = (0..n).map(|i| device.encoder_latency_s(i)).collect();
        let am = &cfg.abnormal_motor;
        let abnormal = AbnormalMotor {
            config: am,
            string: (am.enabled && usize::from(am.string) < n).then_some(usize::from(am.string)),
            rng: abnormal_rng,
            in_region: false,
            off_groove: None,
            previous_counts: None,
        };
        Ok(PhysicsSession {
            device,
            tension_rng,
            noise_rng,
            occlusion_rng,
            posture_rng,
            orientation_rng,
            orientation_noise,
            noise,
            jitter,
            slips,
            strain_per_s,
            latency_s,
            abnormal,
            occluded: false,
        })
    }

    /// This session continues `earlier` from `start_s`: the earlier
    /// session's slip events (drawn again from its seed) come first, this
    /// session's own move to its start.
    fn continue_after(&mut self, earlier: EarlierSession, start_s: f64) {
        let n = self.device.string_count();
        let mut slips = slip_events(
            &self.device.effects,
            n,
            earlier.end_s,
            &mut stream(earlier.seed, 116),
        );
        slips.extend(self.slips.iter().map(|&(t, i, mm)| (t + start_s, i, mm)));
        self.slips = slips;
    }

    /// One capture: the hand at `pose`, the commanded tensions, the
    /// encoders, the tracker (which sees `seen`).
    fn capture(
        &mut self,
        c: &trajectory::Capture,
        pose: &HandPose,
        seen: Option<Seen>,
    ) -> Result<(PhysicsRow, PhysicsTruth), SimError> {
        let n = self.device.string_count();
        let t_s = f64::from(c.t_ms) / 1000.0;
        let tension_n = self.draw_tensions();
        let mut truth = PhysicsTruth {
            meeting_mm: pose.meeting,
            carriage_turn_rad: pose.omega,
            attachment_mm: Vec::with_capacity(n),
            marker_room_mm: pose.marker_room,
            exit_mm: Vec::with_capacity(n),
            free_mm: Vec::with_capacity(n),
            geometric_mm: Vec::with_capacity(n),
            natural_mm: Vec::with_capacity(n),
            spool_rad: Vec::with_capacity(n),
            slipped_mm: Vec::with_capacity(n),
            abnormal: false,
            cell: c.cell,
        };
        let counts = self.read_encoders(pose, &tension_n, t_s, &mut truth)?;
        let (tracker, orientation) = self.track(seen);
        let row = PhysicsRow {
            t_s,
            counts,
            tracker,
            orientation,
            tension_n,
        };
        Ok((row, truth))
    }

    /// The hand at the capture's marker position: the end-effector turned
    /// with the posture (and its jitter), the strings' meeting point behind
    /// the marker.
    fn hand_pose(&mut self, c: &trajectory::Capture) -> HandPose {
        let device = self.device;
        let planar = device.nominal.layout.planar;
        let mut marker = device.device_from_room(&c.room);
        let mut omega = device.posture.rotation_vector(&marker);
        for w in omega.iter_mut() {
            *w += self.jitter.sample(&mut self.posture_rng);
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
            meeting[2] = device.home_mm[2];
            marker = core::array::from_fn(|k| meeting[k] + o[k]);
        }
        // Not a round trip through the device frame unless the marker moved:
        // the 3-D sessions stay bit for bit what they were.
        let marker_room = if planar {
            device.room_from_device(&marker)
        } else {
            c.room
        };
        let mut velocity = device.device_from_room_vector(&c.velocity);
        if planar {
            velocity[2] = 0.0;
        }
        HandPose {
            meeting,
            marker_room,
            omega,
            velocity,
        }
    }

    /// The commanded tension of every string, whole millinewtons.
    fn draw_tensions(&mut self) -> Vec<f64> {
        let device = self.device;
        let ts = &device.config.tension;
        let rng = &mut self.tension_rng;
        (0..device.string_count())
            .map(|_| {
                let mut t = ts.pretension_n + ts.jitter_n * rng.random_range(0.0..1.0);
                if rng.random_bool(ts.active_probability) {
                    t += ts.active_max_n * rng.random_range(0.0..1.0);
                }
                round_to(t.clamp(0.0, 65.535), 1000.0)
            })
            .collect()
    }

    /// Every string's encoder counts with the hand at `pose` (each string
    /// tied where the pose puts its end) under `tension_n` at `t_s` (slips,
    /// drift and the abnormal motor included); what really happened goes to
    /// `truth`.
    fn read_encoders(
        &mut self,
        pose: &HandPose,
        tension_n: &[f64],
        t_s: f64,
        truth: &mut PhysicsTruth,
    ) -> Result<Vec<i32>, SimError> {
        let device = self.device;
        let n = device.string_count();
        let total_tension: f64 = tension_n.iter().sum();
        let mut counts = Vec::with_capacity(n);
        for (i, &tension) in tension_n.iter().enumerate() {
            // An encoder read late holds its string as it was then: the
            // meeting point back along its velocity (the tension and the
            // turn as now).
            let tau = self.latency_s[i];
            let meeting: Vec3<f64> =
                core::array::from_fn(|k| pose.meeting[k] - tau * pose.velocity[k]);
            let end = device.string_end(i, &meeting, &pose.omega);
            let strain = self.strain_per_s[i] * t_s;
            let state = device.natural_length(i, &end, tension, total_tension, strain)?;
            truth.attachment_mm.push(end);
            let slipped: f64 = self
                .slips
                .iter()
                .filter(|(at, s, _)| *s == i && *at <= t_s)
                .map(|(_, _, mm)| mm)
                .sum();
            truth.slipped_mm.push(slipped);
            let wound = device.strings[i].total_mm - slipped - state.natural_mm;
            let phi = device.spool_angle(i, wound).map_err(|e| at_time(e, t_s))?;
            let mut read_phi = phi;
            if let Some(off) =
                self.abnormal
                    .off_groove_angle(device, i, state.path.free_mm, wound, t_s)?
            {
                read_phi = off;
                truth.abnormal = true;
            }
            let mut k = device.counts_of(i, read_phi)?;
            if let Some(previous) = self.abnormal.jammed(i) {
                k = previous;
                truth.abnormal = true;
            }
            counts.push(k);
            truth.exit_mm.push(state.path.exit_mm);
            truth.free_mm.push(state.path.free_mm);
            truth.geometric_mm.push(state.geometric_mm);
            truth.natural_mm.push(state.natural_mm);
            truth.spool_rad.push(phi);
        }
        self.abnormal.previous_counts = Some(counts.clone());
        Ok(counts)
    }

    /// The tracker's reading of what it sees (the marker and the body's
    /// turn, [`TrackerClock::seen`]): the marker's position (noisy, whole
    /// micrometres) and the body's orientation, unless occluded or outside
    /// the tracker's recording.
    fn track(&mut self, seen: Option<Seen>) -> (Option<Vec3<f64>>, Option<[f64; 4]>) {
        let device = self.device;
        let cfg = &device.config;
        let tr = &cfg.tracker;
        self.occluded = if self.occluded {
            !self.occlusion_rng.random_bool(1.0 / tr.occlusion_mean_rows)
        } else {
            self.occlusion_rng.random_bool(tr.occlusion_probability)
        };
        let occluded = self.occluded;
        // Every draw is made whatever the tracker sees, so that the clock
        // changes nothing else.
        let (marker_room, omega) = seen.unwrap_or(([0.0; 3], [0.0; 3]));
        let (noise, noise_rng) = (&self.noise, &mut self.noise_rng);
        let measured: Vec3<f64> =
            core::array::from_fn(|k| round_to(marker_room[k] + noise.sample(noise_rng), 1000.0));
        // The body turns with the hand (`omega`, device frame); the tracker
        // reads its orientation in the room, with its own noise.
        let (orientation_noise, orientation_rng) =
            (&self.orientation_noise, &mut self.orientation_rng);
        let orientation = (cfg.orientation.enabled && !occluded)
            .then(|| {
                let err: [f64; 3] =
                    core::array::from_fn(|_| orientation_noise.sample(orientation_rng));
                body_to_room_quaternion(&device.room_rotation, &omega, &err)
            })
            .flatten()
            .filter(|_| seen.is_some());
        let visible = !occluded && seen.is_some();
        (visible.then_some(measured), orientation)
    }
}

impl AbnormalMotor<'_> {
    /// The spool angle the encoder of string `i` reads when the motor is
    /// off its groove (None: on the groove, or not the abnormal string);
    /// entering the region (free string shorter than its length) may throw
    /// the string off the groove, leaving it puts it back.
    fn off_groove_angle(
        &mut self,
        device: &PhysicsDevice,
        i: usize,
        free_mm: f64,
        wound: f64,
        t_s: f64,
    ) -> Result<Option<f64>, SimError> {
        if Some(i) != self.string {
            return Ok(None);
        }
        let am = self.config;
        let inside = free_mm < am.region_length_mm;
        if inside && !self.in_region {
            let rng = &mut self.rng;
            self.off_groove = rng
                .random_bool(am.out_of_groove_probability)
                .then(|| (wound, uniform(rng, am.radius_excess)));
        }
        if !inside {
            self.off_groove = None;
        }
        self.in_region = inside;
        if let Some((w0, g)) = self.off_groove {
            if wound > w0 {
                // Wound in off the groove, on a radius 1 + g larger:
                // the spool turned 1 + g times less.
                return device
                    .spool_angle(i, w0 + (wound - w0) / (1.0 + g))
                    .map(Some)
                    .map_err(|e| at_time(e, t_s));
            }
        }
        Ok(None)
    }

    /// The previous counts of string `i` when its spool jams at this
    /// capture (only the abnormal string, inside its region, after a first
    /// capture).
    fn jammed(&mut self, i: usize) -> Option<i32> {
        if Some(i) == self.string
            && self.in_region
            && self.rng.random_bool(self.config.jam_probability)
        {
            if let Some(prev) = &self.previous_counts {
                return Some(prev[i]);
            }
        }
        None
    }
}

fn at_time(e: SimError, t_s: f64) -> SimError {
    match e {
        SimError::Config(c) => SimError::Config(crate::ConfigError {
            problem: format!("{} (t = {t_s} s)", c.problem),
            ..c
        }),
        other => other,
    }
}

/// `truth.toml` of the independent simulator (tests and benchmarks only).
fn write_truth(device: &PhysicsDevice, path: &std::path::Path) -> Result<(), SimError> {
    let body = toml::to_string(device).map_err(|e| {
        SimError::Config(crate::ConfigError::new(
            "truth",
            format!("cannot encode the truth as TOML: {e}"),
        ))
    })?;
    let text = format!(
        "# Independent simulator ground truth: the device as built.\n\
         # For tests and benchmarks only; calibration never reads this file.\n{body}"
    );
    crate::data::output::write_atomically(path, text.as_bytes()).map_err(|source| SimError::Io {
        file: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}

/// `spidar simulate --physics independent`: the same files as the model
/// simulator (nominal `geometry.toml`, the session CSV, `truth.toml`).
pub fn run_simulate(args: &SimulateRequest) -> Result<SimulateReport, SimError> {
    let mut config = match (&args.config, &args.preset) {
        (Some(_), Some(_)) => {
            return Err(SimError::Config(crate::ConfigError::new(
                "--preset",
                "give a preset or a --config file, not both (a preset is a configuration \
                 file: copy it from host/src/sim/physics/presets/ to change it)",
            )))
        }
        (Some(path), None) => PhysicsConfig::load(path)?,
        (None, Some(name)) => PhysicsConfig::preset(name)?,
        (None, None) => PhysicsConfig::default(),
    };
    config.effects.extend(args.effects.iter().cloned());
    let kind = super::session_kind(args, config.random.points, Some(config.stream.rows))?;
    let device = PhysicsDevice::new(&config, args.seed)?;
    let (session, _) = simulate_session(&device, kind, super::session_seed(args, kind))?;
    super::write_outputs(
        args,
        kind,
        &device.nominal,
        &session,
        |truth| write_truth(&device, truth),
        None,
        &device.config.tracker,
    )
}
