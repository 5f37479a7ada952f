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

mod build;
mod device;
mod session;

use serde::{Deserialize, Serialize};
use spidar_core::model::Vec3;

pub use config::{
    CarriageConfig, PhysicsAbnormalMotor, PhysicsAsBuilt, PhysicsConfig, StreamConfig, PRESET_NAMES,
};
pub use effects::{parse_effect, parse_effects, PhysicsEffect, EFFECT_NAMES};
pub use guide::{Guide, GuidePath};
pub use spool::{Spool, SpoolParams};

pub use device::StringState;
pub use session::{simulate_rows, simulate_session, simulate_session_after, EarlierSession};

use super::{SimError, SimulateReport, SimulateRequest};
use crate::data::dataset::{Geometry, Sample, Session};
use spidar_core::geometry::dot;

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
    /// Times the line runs between the pulley blocks at its guide and at
    /// the end-effector (the nominal `mechanical_advantage`): each run is
    /// the guide's path, so the spool pays out this many mm per mm of it.
    #[serde(default = "one_run", skip_serializing_if = "is_one_run")]
    pub line_runs: f64,
}

/// A line straight from its guide to the end-effector.
fn one_run() -> f64 {
    1.0
}

/// Whether `runs` is [`one_run`] (not written to the truth).
fn is_one_run(runs: &f64) -> bool {
    *runs == 1.0
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
