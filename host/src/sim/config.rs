//! [`SimConfig`]: every switch and parameter of the simulator, with
//! paper-like defaults. Read from TOML (`--config sim.toml`); every key is
//! optional, an unknown key is an error that names it.

use std::path::Path;

use serde::{Deserialize, Serialize};
use spidar_core::model::Vec3;
use spidar_core::STRINGS;

use super::SimError;
use crate::data::dataset::Geometry;

/// The whole simulator configuration.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    pub nominal: NominalConfig,
    pub as_built: AsBuiltConfig,
    pub tracker: TrackerConfig,
    pub abnormal_motor: AbnormalMotorConfig,
    pub tension: CommandedTensions,
    pub lattice: LatticeConfig,
    pub random: RandomConfig,
    pub legacy: LegacyConfig,
    /// Injected effects, in the `--effect` syntax (see [`super::effects`]).
    pub effects: Vec<String>,
}

/// The device as designed: what `geometry.toml` says.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NominalConfig {
    /// Number of strings, 3..=8 (on encoder channels `0..strings`). Eight
    /// strings sit at the cube's corners in the Scalable-SPIDAR's order;
    /// fewer take corners that spread them (4: a tetrahedron, SPIDAR-G
    /// style), or, planar, the corners of a regular polygon.
    pub strings: usize,
    /// The end-effector moves in the plane `z = 0` of the device frame,
    /// where the anchors are (a planar SPIDAR).
    pub planar: bool,
    pub counts_per_rev: u32,
    /// Nominal (bare) pulley radius the designers give, mm.
    pub pulley_radius_mm: f64,
    /// Motors sit at the corners of a cube of this half size (mm), centred on
    /// the device origin: 1100 mm for the 2.2 m human-scale frame.
    pub frame_half_size_mm: f64,
    pub home_mm: Vec3<f64>,
    /// Eq. 6: `p_room = p_device + t`.
    pub room_from_device_translation_mm: Vec3<f64>,
    /// The design's anchors (string exit points), one per string in encoder
    /// order, mm: a frame that is not the cube or the regular polygon (a
    /// wall robot's rectangle). Empty: the corners above.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub anchors_mm: Vec<Vec3<f64>>,
    /// Each string's line runs this many times between a pulley block at
    /// its anchor and one at the end-effector (a Hangprinter's doubled
    /// lines), one per string in encoder order: the spool pays out this
    /// many mm per mm of the anchor's distance. Empty: 1 (a line straight
    /// to the end-effector). The independent simulator's only.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub mechanical_advantage: Vec<f64>,
}

impl Default for NominalConfig {
    fn default() -> Self {
        NominalConfig {
            strings: STRINGS,
            planar: false,
            counts_per_rev: 4096,
            pulley_radius_mm: 7.5,
            frame_half_size_mm: 1100.0,
            home_mm: [0.0; 3],
            room_from_device_translation_mm: [0.0, 0.0, 1500.0],
            anchors_mm: Vec::new(),
            mechanical_advantage: Vec::new(),
        }
    }
}

impl NominalConfig {
    /// `mechanical_advantage`: one ratio of at least 1 per string, or none.
    pub(crate) fn validate_pulley_blocks(&self) -> Result<(), SimError> {
        let m = &self.mechanical_advantage;
        if !m.is_empty() && m.len() != self.strings {
            return Err(bad(
                "nominal.mechanical_advantage",
                format!(
                    "{} values for {} strings: give one per string, or none for lines straight \
                     to the end-effector",
                    m.len(),
                    self.strings
                ),
            ));
        }
        if let Some((i, v)) = m
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v >= 1.0))
        {
            return Err(bad(
                &format!("nominal.mechanical_advantage[{i}]"),
                format!("{v} is not a ratio of at least 1 (the times the line runs to the end-effector)"),
            ));
        }
        Ok(())
    }

    /// The nominal geometry, anchors in encoder order. Eight strings: the
    /// lower square (`z = -h`) counter-clockwise from `(-h, -h)`, then the
    /// upper square. Fewer in 3-D: the cube corners in the order 0, 2, 5, 7
    /// (a tetrahedron), then 1, 3, 4, 6 (index as in the 8-string order).
    /// Planar: a regular polygon of circumradius `h sqrt 2` in `z = 0`, its
    /// first corner at `(-h, -h)`; home is put in the plane. Given
    /// `anchors_mm`, those (a planar home is put in their plane).
    pub fn geometry(&self) -> Geometry {
        let h = self.frame_half_size_mm;
        let n = self.strings.clamp(1, STRINGS);
        let corners = [(-h, -h), (h, -h), (h, h), (-h, h)];
        let cube = |i: usize| {
            let (x, y) = corners[i % 4];
            [x, y, if i < 4 { -h } else { h }]
        };
        const SPREAD: [usize; STRINGS] = [0, 2, 5, 7, 1, 3, 4, 6];
        let polygon = |i: usize| {
            let angle = -3.0 * std::f64::consts::FRAC_PI_4
                + 2.0 * std::f64::consts::PI * i as f64 / n as f64;
            let r = h * std::f64::consts::SQRT_2;
            [r * angle.cos(), r * angle.sin(), 0.0]
        };
        let anchor = |i: usize| {
            let i = i.min(n - 1);
            if let Some(last) = self.anchors_mm.len().checked_sub(1) {
                self.anchors_mm[i.min(last)]
            } else if self.planar {
                polygon(i)
            } else if n == STRINGS {
                cube(i)
            } else {
                cube(SPREAD[i])
            }
        };
        let mut home_mm = self.home_mm;
        if self.planar {
            home_mm[2] = self.anchors_mm.first().map_or(0.0, |a| a[2]);
        }
        Geometry {
            layout: spidar_core::model::StringLayout::first(n, self.planar),
            counts_per_rev: [self.counts_per_rev; STRINGS],
            pulley_radius_mm: [self.pulley_radius_mm; STRINGS],
            mechanical_advantage: core::array::from_fn(|i| {
                self.mechanical_advantage.get(i).copied().unwrap_or(1.0)
            }),
            home_mm,
            anchors_mm: core::array::from_fn(anchor),
            room_from_device_translation_mm: self.room_from_device_translation_mm,
            // The design says nothing of it; the simulators' initialization
            // declares its pretension (`SimConfig::tension`).
            home_tension_n: None,
            anchor_sd_mm: None,
            home_sd_mm: None,
        }
    }
}

/// How the built device differs from the design (random draws per device seed).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AsBuiltConfig {
    /// Standard deviation of each anchor coordinate's as-built error, mm.
    pub anchor_sigma_mm: f64,
    /// Standard deviation of each coordinate of the true home (initialization)
    /// position around the nominal home, mm: the built-in initialization is
    /// off by a few centimetres (the paper's fig. 3).
    pub home_sigma_mm: f64,
    /// Standard deviation of the relative bare-radius error shared by all
    /// pulleys (one machining batch).
    pub pulley_radius_shared_sigma: f64,
    /// Standard deviation of each pulley's own relative bare-radius error.
    pub pulley_radius_each_sigma: f64,
    /// Winding-radius growth: the string winds in level layers, so the
    /// winding radius grows by `d^2 / (2 pi)` per radian wound.
    pub winding_growth: bool,
    /// String diameter `d`, mm.
    pub string_diameter_mm: f64,
    /// Total string length of each string (pulley to end-effector), mm.
    pub string_total_mm: f64,
    /// Standard deviation of each string's total length, mm.
    pub string_total_sigma_mm: f64,
}

impl Default for AsBuiltConfig {
    fn default() -> Self {
        AsBuiltConfig {
            anchor_sigma_mm: 3.0,
            home_sigma_mm: 25.0,
            pulley_radius_shared_sigma: 0.02,
            pulley_radius_each_sigma: 0.003,
            winding_growth: true,
            string_diameter_mm: 0.5,
            string_total_mm: 4000.0,
            string_total_sigma_mm: 30.0,
        }
    }
}

/// Whether `x` is 0 (a key left out of a written configuration, as it was
/// before the key existed).
fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// The optical tracker (ARTrack/DTrack in the paper) and its room frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackerConfig {
    /// Per-axis standard deviation of the tracker noise, mm.
    pub noise_sigma_mm: f64,
    /// The share of the captures located poorly (0: none): a marker partly
    /// hidden, a reflection beside it. On those a further normal noise of
    /// [`TrackerConfig::tail_sigma_mm`] per axis.
    #[serde(skip_serializing_if = "is_zero")]
    pub tail_share: f64,
    /// Per-axis standard deviation of the poorly located captures' further
    /// noise, mm.
    #[serde(skip_serializing_if = "is_zero")]
    pub tail_sigma_mm: f64,
    /// Angle of the true room-from-device rotation (random axis), degrees.
    pub rotation_deg: f64,
    /// Standard deviation of each coordinate of the true translation around
    /// the nominal eq. 6 translation, mm.
    pub translation_sigma_mm: f64,
    /// Scale of the tracker relative to the device (`p_room = s R p + t`).
    pub scale: f64,
    /// Probability that an occlusion starts at a given row.
    pub occlusion_probability: f64,
    /// Mean length of an occlusion, in rows (geometric distribution).
    pub occlusion_mean_rows: f64,
    /// Tracker frame rate: the capture happens at the first tracker frame
    /// after the marker enters a lattice cell.
    pub frame_rate_hz: f64,
    /// How far the tracker's clock runs ahead of the device's (s): the
    /// tracker position written in a row stamped `t` (device clock) is where
    /// the marker was at `t - clock_offset_s` (a recording paired by the two
    /// clocks' timestamps). Rows before the first tracked instant are
    /// occluded. Calibration finds and removes it for dynamic sessions.
    pub clock_offset_s: f64,
    /// How much faster the tracker's clock runs than the device's, parts
    /// per million: the offset grows by this much per second of the session
    /// (`clock_offset_s + 1e-6 clock_drift_ppm t` at device time `t`). Two
    /// crystal clocks differ by tens of ppm: 50 ppm is 15 ms after five
    /// minutes, 15 mm at a hand's 1 m/s.
    pub clock_drift_ppm: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            noise_sigma_mm: 0.2,
            tail_share: 0.0,
            tail_sigma_mm: 0.0,
            rotation_deg: 1.0,
            translation_sigma_mm: 3.0,
            scale: 1.0,
            occlusion_probability: 0.01,
            occlusion_mean_rows: 4.0,
            frame_rate_hz: 60.0,
            clock_offset_s: 0.0,
            clock_drift_ppm: 0.0,
        }
    }
}

/// The paper's abnormal motor: when the end-effector comes close to its
/// corner, much string is wound, the badly designed guide lets the string
/// slide out of the pulley groove and it winds on a larger radius: the encoder
/// under-reports the string's motion: a jump when the string leaves the
/// groove, growing with the depth into that region, erratic from capture to
/// capture (the outliers of section 5.1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AbnormalMotorConfig {
    pub enabled: bool,
    /// Encoder index of the abnormal motor. Default 4: upper (`+z`) left
    /// (`-x`) front (`-y`) corner.
    pub string: u8,
    /// The string slides out of the groove when its true length is below
    /// this, mm. 1600 mm covers about 12 % of the lattice cells (the paper
    /// removed nearly 300 of 2197 points).
    pub region_length_mm: f64,
    /// Length error as soon as the string leaves the groove, mm.
    pub step_mm: f64,
    /// Additional length error per mm of depth into the region.
    pub gain: f64,
    /// Relative random spread of the error from capture to capture (0..1).
    pub jitter: f64,
}

impl Default for AbnormalMotorConfig {
    fn default() -> Self {
        AbnormalMotorConfig {
            enabled: true,
            string: 4,
            region_length_mm: 1600.0,
            step_mm: 300.0,
            gain: 1.0,
            jitter: 0.5,
        }
    }
}

/// Commanded tensions: a pre-tension plus a varying haptic component, so that
/// tension-dependent effects are observable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CommandedTensions {
    pub pretension_n: f64,
    /// Uniform jitter added to the pre-tension, N.
    pub jitter_n: f64,
    /// Probability that a string renders a force at a capture.
    pub active_probability: f64,
    /// The rendered force is uniform in `[0, active_max_n]`, N.
    pub active_max_n: f64,
}

impl Default for CommandedTensions {
    fn default() -> Self {
        CommandedTensions {
            pretension_n: 1.0,
            jitter_n: 0.2,
            active_probability: 0.35,
            active_max_n: 4.0,
        }
    }
}

/// The paper's lattice protocol (section 4.3.1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LatticeConfig {
    pub cells_per_axis: u32,
    /// Edge of the sampled cube, centred on the room image of the nominal home, mm.
    pub size_mm: f64,
    /// Total duration of the session, s (the paper: about 80 minutes).
    pub duration_s: f64,
    /// Hand speed range while moving to the next cell, mm/s.
    pub speed_mm_s: [f64; 2],
    /// The user aims at a point within this fraction of a cell from its centre.
    pub target_jitter: f64,
}

impl Default for LatticeConfig {
    fn default() -> Self {
        LatticeConfig {
            cells_per_axis: 13,
            size_mm: 1000.0,
            duration_s: 4800.0,
            speed_mm_s: [30.0, 90.0],
            target_jitter: 0.3,
        }
    }
}

/// Test sessions: random trajectories of sequential points through the
/// lattice's volume (the paper's generalization set).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RandomConfig {
    pub points: usize,
    /// Time between captures, s.
    pub capture_interval_s: f64,
    /// Hand speed range along each straight leg of the trajectory, mm/s.
    pub speed_mm_s: [f64; 2],
}

impl Default for RandomConfig {
    fn default() -> Self {
        RandomConfig {
            points: 500,
            capture_interval_s: 0.25,
            speed_mm_s: [100.0, 300.0],
        }
    }
}

/// The legacy (black-box HDHC) controller output, the `dev_*` columns.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LegacyConfig {
    pub enabled: bool,
}

impl Default for LegacyConfig {
    fn default() -> Self {
        LegacyConfig { enabled: true }
    }
}

pub(crate) fn bad(field: &str, problem: impl Into<String>) -> SimError {
    SimError::Config(crate::ConfigError::new(field.to_string(), problem.into()))
}

pub(crate) fn non_negative(field: &str, v: f64) -> Result<(), SimError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(bad(field, format!("{v} must be a finite number >= 0")))
    }
}

fn positive(field: &str, v: f64) -> Result<(), SimError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(bad(field, format!("{v} must be a finite number > 0")))
    }
}

fn speed_range(field: &str, r: [f64; 2]) -> Result<(), SimError> {
    positive(field, r[0])?;
    positive(field, r[1])?;
    if r[0] > r[1] {
        return Err(bad(field, format!("[{}, {}] is not a range", r[0], r[1])));
    }
    Ok(())
}

pub(crate) fn probability(field: &str, p: f64) -> Result<(), SimError> {
    if (0.0..=1.0).contains(&p) {
        Ok(())
    } else {
        Err(bad(field, format!("{p} is not a probability")))
    }
}

/// A simulator configuration TOML file (either simulator's), parsed; errors
/// name the file, and the key and line where it does not parse.
pub(crate) fn read_toml<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, SimError> {
    let text = std::fs::read_to_string(path).map_err(|source| SimError::Io {
        file: path.to_path_buf(),
        action: "cannot read",
        source,
    })?;
    toml::from_str(&text).map_err(|e| SimError::ConfigFile {
        file: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })
}

impl SimConfig {
    /// The configuration of `path` (see [`SimConfig::load`]), or the
    /// default one without a path.
    pub fn load_or_default(path: Option<&Path>) -> Result<Self, SimError> {
        path.map_or_else(|| Ok(SimConfig::default()), SimConfig::load)
    }

    /// Read a configuration TOML file (all keys optional).
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SimError> {
        let config: SimConfig = read_toml(path.as_ref())?;
        config.validate()?;
        Ok(config)
    }

    /// Check every parameter; errors name the field (`section.key`).
    pub fn validate(&self) -> Result<(), SimError> {
        if self.nominal.mechanical_advantage.iter().any(|&m| m != 1.0) {
            return Err(bad(
                "nominal.mechanical_advantage",
                "the model simulator's lines run straight from the spool to the end-effector; \
                 lines through pulley blocks are the independent simulator's (`--physics \
                 independent`)",
            ));
        }
        self.validate_device()?;
        self.validate_tracker()?;
        self.validate_motor_and_tension()?;
        self.validate_sessions()?;
        for spec in &self.effects {
            super::effects::parse_effect(spec)?;
        }
        Ok(())
    }

    /// `[nominal]` and `[as_built]`.
    fn validate_device(&self) -> Result<(), SimError> {
        let n = &self.nominal;
        if !(crate::data::dataset::MIN_STRINGS..=STRINGS).contains(&n.strings) {
            return Err(bad(
                "nominal.strings",
                format!(
                    "{} is not in {}..={STRINGS}",
                    n.strings,
                    crate::data::dataset::MIN_STRINGS
                ),
            ));
        }
        if n.counts_per_rev == 0 {
            return Err(bad("nominal.counts_per_rev", "must be positive"));
        }
        positive("nominal.pulley_radius_mm", n.pulley_radius_mm)?;
        positive("nominal.frame_half_size_mm", n.frame_half_size_mm)?;
        if !n.anchors_mm.is_empty() && n.anchors_mm.len() != n.strings {
            return Err(bad(
                "nominal.anchors_mm",
                format!(
                    "{} anchors for {} strings: give one per string, or none for the frame's corners",
                    n.anchors_mm.len(),
                    n.strings
                ),
            ));
        }
        if n.anchors_mm.iter().flatten().any(|x| !x.is_finite()) {
            return Err(bad("nominal.anchors_mm", "must be finite numbers (mm)"));
        }

        n.geometry()
            .validate(Path::new("[nominal] of the simulator configuration"))
            .map_err(|e| bad("nominal", e.to_string()))?;
        let a = &self.as_built;
        non_negative("as_built.anchor_sigma_mm", a.anchor_sigma_mm)?;
        non_negative("as_built.home_sigma_mm", a.home_sigma_mm)?;
        non_negative(
            "as_built.pulley_radius_shared_sigma",
            a.pulley_radius_shared_sigma,
        )?;
        non_negative(
            "as_built.pulley_radius_each_sigma",
            a.pulley_radius_each_sigma,
        )?;
        positive("as_built.string_diameter_mm", a.string_diameter_mm)?;
        positive("as_built.string_total_mm", a.string_total_mm)?;
        non_negative("as_built.string_total_sigma_mm", a.string_total_sigma_mm)
    }

    /// `[tracker]`.
    fn validate_tracker(&self) -> Result<(), SimError> {
        let t = &self.tracker;
        non_negative("tracker.noise_sigma_mm", t.noise_sigma_mm)?;
        if !(0.0..=1.0).contains(&t.tail_share) {
            return Err(bad(
                "tracker.tail_share",
                format!("{} is not a share of the captures (0 to 1)", t.tail_share),
            ));
        }
        non_negative("tracker.tail_sigma_mm", t.tail_sigma_mm)?;
        non_negative("tracker.rotation_deg", t.rotation_deg)?;
        non_negative("tracker.translation_sigma_mm", t.translation_sigma_mm)?;
        positive("tracker.scale", t.scale)?;
        probability("tracker.occlusion_probability", t.occlusion_probability)?;
        if !(t.occlusion_mean_rows.is_finite() && t.occlusion_mean_rows >= 1.0) {
            return Err(bad(
                "tracker.occlusion_mean_rows",
                "must be a finite number >= 1",
            ));
        }
        positive("tracker.frame_rate_hz", t.frame_rate_hz)?;
        if !(t.clock_drift_ppm.is_finite() && t.clock_drift_ppm.abs() <= 10_000.0) {
            return Err(bad(
                "tracker.clock_drift_ppm",
                "must be a finite number of parts per million, at most 10000 either way",
            ));
        }
        if !t.clock_offset_s.is_finite() {
            return Err(bad("tracker.clock_offset_s", "must be a finite number"));
        }
        Ok(())
    }

    /// `[abnormal_motor]` and `[tension]`.
    fn validate_motor_and_tension(&self) -> Result<(), SimError> {
        let n = &self.nominal;
        let m = &self.abnormal_motor;
        if m.enabled && usize::from(m.string) >= n.strings {
            return Err(bad(
                "abnormal_motor.string",
                format!(
                    "{} is not a string of this {}-string device (0..{}); choose one or set \
                     abnormal_motor.enabled = false",
                    m.string,
                    n.strings,
                    n.strings - 1
                ),
            ));
        }
        non_negative("abnormal_motor.region_length_mm", m.region_length_mm)?;
        non_negative("abnormal_motor.step_mm", m.step_mm)?;
        non_negative("abnormal_motor.gain", m.gain)?;
        probability("abnormal_motor.jitter", m.jitter)?;
        let s = &self.tension;
        non_negative("tension.pretension_n", s.pretension_n)?;
        non_negative("tension.jitter_n", s.jitter_n)?;
        probability("tension.active_probability", s.active_probability)?;
        non_negative("tension.active_max_n", s.active_max_n)?;
        let max_n = s.pretension_n + s.jitter_n + s.active_max_n;
        if max_n > 65.0 {
            return Err(bad(
                "tension",
                format!("tensions up to {max_n} N exceed the 65 N a u16 in mN holds"),
            ));
        }
        Ok(())
    }

    /// `[lattice]` and `[random]`.
    fn validate_sessions(&self) -> Result<(), SimError> {
        let l = &self.lattice;
        if l.cells_per_axis == 0 || l.cells_per_axis > 1000 {
            return Err(bad(
                "lattice.cells_per_axis",
                format!("{} is not in 1..=1000", l.cells_per_axis),
            ));
        }
        positive("lattice.size_mm", l.size_mm)?;
        non_negative("lattice.duration_s", l.duration_s)?;
        speed_range("lattice.speed_mm_s", l.speed_mm_s)?;
        if !(0.0..0.5).contains(&l.target_jitter) {
            return Err(bad(
                "lattice.target_jitter",
                format!("{} is not in [0, 0.5)", l.target_jitter),
            ));
        }
        let r = &self.random;
        if r.points == 0 {
            return Err(bad("random.points", "must be positive"));
        }
        positive("random.capture_interval_s", r.capture_interval_s)?;
        speed_range("random.speed_mm_s", r.speed_mm_s)
    }
}
