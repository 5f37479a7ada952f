//! Configuration of the independent simulator (`spidar simulate --physics
//! independent --config FILE`, every key optional). The design, the
//! tracker, the tensions and the paths are the model simulator's sections
//! (same keys, same defaults), so both simulators sample the same volume
//! with the same protocol; the as-built physics and the abnormal motor are
//! this simulator's own. Ranges `[lo, hi]` are drawn uniformly per device.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::sim::config::{
    bad, non_negative, probability, CommandedTensions, LatticeConfig, NominalConfig, RandomConfig,
    TrackerConfig,
};
use crate::sim::SimError;

/// The whole configuration.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhysicsConfig {
    pub nominal: NominalConfig,
    pub as_built: PhysicsAsBuilt,
    pub tracker: TrackerConfig,
    pub abnormal_motor: PhysicsAbnormalMotor,
    pub tension: CommandedTensions,
    pub lattice: LatticeConfig,
    pub random: RandomConfig,
    pub orientation: OrientationConfig,
    /// Undeclared effects, `NAME` or `NAME:KEY=VALUE,...` (see [`super::effects`]).
    pub effects: Vec<String>,
    #[serde(skip_serializing_if = "CarriageConfig::is_point")]
    pub carriage: CarriageConfig,
    #[serde(skip_serializing_if = "StreamConfig::is_default")]
    pub stream: StreamConfig,
}

/// Where the strings attach to the end-effector. A SPIDAR's strings meet
/// at one point (a ring, a grip); a cable robot's carriage is a rigid
/// plate with each cable tied at its own corner, so a string's length is
/// `|exit - (p + R attachment)|` and the carriage's turn (the hand's
/// posture, `as_built.posture_*`; on a planar device its yaw) changes it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CarriageConfig {
    /// Each string's attachment point in the carriage's body frame, from
    /// the point the tracker's marker offset is measured from (the
    /// carriage's reference point), mm, one per string in encoder order.
    /// Empty: the strings meet at that point.
    pub attachment_mm: Vec<[f64; 3]>,
}

impl CarriageConfig {
    /// The strings meet at one point (no carriage).
    pub fn is_point(&self) -> bool {
        self.attachment_mm.is_empty()
    }
}

/// Streams (`--kind stream`, `--kind wide-stream`): a continuous path
/// through the workspace captured at a tracker's rate, as a cable robot's
/// calibration run records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StreamConfig {
    /// Captures of a stream (`--points` overrides), 10..=30000.
    pub rows: usize,
    /// Captures per second (the device time `t_s` of row `k` is `k /
    /// rate_hz`, whole milliseconds), at most 1000.
    pub rate_hz: f64,
    /// Range of each leg's mean speed, mm/s (the speed rises and falls
    /// along a leg: its peak is 1.875 times its mean).
    pub speed_mm_s: [f64; 2],
    /// Sides of the workspace, a box centred on the room image of the
    /// nominal home (room axes), mm: a wide stream covers it.
    pub area_mm: [f64; 3],
    /// A training stream covers the central part of the workspace: this
    /// fraction of each side (0.8: 64 % of a planar workspace's area).
    pub training_span: f64,
}

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            rows: 6000,
            rate_hz: 100.0,
            speed_mm_s: [800.0, 1200.0],
            area_mm: [1000.0, 1000.0, 1000.0],
            training_span: 0.8,
        }
    }
}

impl StreamConfig {
    fn is_default(&self) -> bool {
        *self == StreamConfig::default()
    }

    /// Checks the keys of `[stream]`; errors name the key.
    fn validate(&self) -> Result<(), SimError> {
        stream_rows("stream.rows", self.rows)?;
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 1000.0) {
            return Err(bad(
                "stream.rate_hz",
                format!(
                    "{} is not a capture rate in (0, 1000] Hz (rows are stamped in whole milliseconds)",
                    self.rate_hz
                ),
            ));
        }
        range("stream.speed_mm_s", self.speed_mm_s, true)?;
        for (k, x) in self.area_mm.iter().enumerate() {
            non_negative(&format!("stream.area_mm[{k}]"), *x)?;
        }
        if !(self.training_span > 0.0 && self.training_span <= 1.0) {
            return Err(bad(
                "stream.training_span",
                format!("{} is not a fraction in (0, 1]", self.training_span),
            ));
        }
        Ok(())
    }
}

/// A stream holds 10 to 30000 rows; `field` names where the count came from.
pub(crate) fn stream_rows(field: &str, rows: usize) -> Result<(), SimError> {
    if (10..=30_000).contains(&rows) {
        Ok(())
    } else {
        Err(bad(
            field,
            format!("{rows} rows: a stream holds 10 to 30000"),
        ))
    }
}

/// The named devices of the independent simulator (`spidar simulate
/// --physics independent --preset NAME`), each a configuration file of
/// this directory: copy one to change it and pass it as `--config`.
pub const PRESET_NAMES: [&str; 2] = ["wall-robot", "hangprinter"];

/// The configuration text of preset `name`.
fn preset_text(name: &str) -> Option<&'static str> {
    match name {
        "wall-robot" => Some(include_str!("presets/wall-robot.toml")),
        "hangprinter" => Some(include_str!("presets/hangprinter.toml")),
        _ => None,
    }
}

/// The tracker's orientation of the tracked body (a rigid body of markers,
/// as optical trackers give it): written as `ots_qw, ots_qx, ots_qy,
/// ots_qz` beside the position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OrientationConfig {
    /// Write the orientation (false: a tracker of single markers, position
    /// only).
    pub enabled: bool,
    /// Standard deviation of the measured orientation about each axis,
    /// degrees (optical rigid bodies: about 0.1).
    pub sigma_deg: f64,
}

impl Default for OrientationConfig {
    fn default() -> Self {
        OrientationConfig {
            enabled: true,
            sigma_deg: 0.1,
        }
    }
}

/// The device as built: every physical parameter and its spread.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhysicsAsBuilt {
    /// Standard deviation of each coordinate of a string's exit point around the design, mm.
    pub anchor_sigma_mm: f64,
    /// Standard deviation of each coordinate of the true home around the nominal home, mm.
    pub home_sigma_mm: f64,
    /// Guide pulley radius `rho`, mm.
    pub guide_radius_mm: [f64; 2],
    /// Tilt of each guide's swivel axis off the frame edge, degrees (random direction).
    pub guide_tilt_deg: f64,
    /// String from the spool to the guide (fixed), mm.
    pub lead_mm: [f64; 2],
    /// Relative spool bare-radius error shared by all spools (one batch), sd.
    pub spool_radius_shared_sigma: f64,
    /// Each spool's own relative bare-radius error, sd.
    pub spool_radius_each_sigma: f64,
    /// Spool width `W` (the string is laid across it in layers), mm.
    pub spool_width_mm: [f64; 2],
    /// Nominal string diameter `d`, mm.
    pub string_diameter_mm: f64,
    /// Relative sd of each string's diameter.
    pub string_diameter_sigma: f64,
    /// Layer rise in string diameters, `c`.
    pub layer_packing: [f64; 2],
    /// Relative pitch excess of a layer, `u_k`: `n_k = W / (d (1 + u_k))` turns.
    pub pitch_excess: [f64; 2],
    /// Angle over which the string climbs to the next layer, rad.
    pub layer_change_rad: [f64; 2],
    /// Cross-over height over the neighbouring turn, mm.
    pub crossover_rise_mm: [f64; 2],
    /// Cross-over width in each turn, rad.
    pub crossover_rad: [f64; 2],
    /// Axial stiffness `E A` of each string, N.
    pub string_stiffness_n: [f64; 2],
    /// Linear mass of each string, g/m (sag).
    pub string_mass_g_per_m: [f64; 2],
    /// Total string length beyond the guide entry at home plus what is wound, mm
    /// (the lead is added to it).
    pub string_total_mm: f64,
    pub string_total_sigma_mm: f64,
    /// Frame compliance at each corner: the guide moves by this times the
    /// sum of all string tensions, mm/N.
    pub frame_compliance_mm_per_n: [f64; 2],
    /// Distance of the tracker's marker from the strings' meeting point, mm.
    pub marker_offset_mm: [f64; 2],
    /// Amplitude of the end-effector's rotation with the hand's posture
    /// (a smooth function of position), degrees per axis.
    pub posture_amplitude_deg: f64,
    /// Wavelength of the posture's variation across the volume, mm.
    pub posture_wavelength_mm: f64,
    /// Random rotation of the hand from capture to capture, sd per axis, degrees.
    pub posture_jitter_deg: f64,
}

impl Default for PhysicsAsBuilt {
    fn default() -> Self {
        PhysicsAsBuilt {
            anchor_sigma_mm: 3.0,
            home_sigma_mm: 25.0,
            guide_radius_mm: [6.0, 12.0],
            guide_tilt_deg: 2.0,
            lead_mm: [50.0, 300.0],
            spool_radius_shared_sigma: 0.02,
            spool_radius_each_sigma: 0.003,
            spool_width_mm: [3.0, 6.0],
            string_diameter_mm: 0.5,
            string_diameter_sigma: 0.02,
            layer_packing: [0.86, 1.0],
            pitch_excess: [0.0, 0.2],
            layer_change_rad: [0.5, 1.5],
            crossover_rise_mm: [0.05, 0.15],
            crossover_rad: [0.3, 0.6],
            string_stiffness_n: [10_000.0, 30_000.0],
            string_mass_g_per_m: [0.3, 1.0],
            string_total_mm: 4000.0,
            string_total_sigma_mm: 30.0,
            frame_compliance_mm_per_n: [0.005, 0.02],
            marker_offset_mm: [8.0, 15.0],
            posture_amplitude_deg: 2.0,
            posture_wavelength_mm: 2000.0,
            posture_jitter_deg: 0.3,
        }
    }
}

/// The paper's abnormal motor, as this simulator explains it: near its
/// corner the string rides out of its groove onto a larger radius (the
/// encoder then under-counts the string wound), on some visits only, and
/// the spool sometimes jams (the encoder repeats its previous reading).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhysicsAbnormalMotor {
    pub enabled: bool,
    /// Encoder index of the abnormal motor (upper left front corner by default).
    pub string: u8,
    /// The trouble starts when the free string is shorter than this, mm.
    pub region_length_mm: f64,
    /// Probability that the string leaves its groove on a visit of the region.
    pub out_of_groove_probability: f64,
    /// Relative radius excess off the groove, drawn per visit.
    pub radius_excess: [f64; 2],
    /// Probability per capture in the region that the spool is jammed.
    pub jam_probability: f64,
}

impl Default for PhysicsAbnormalMotor {
    fn default() -> Self {
        PhysicsAbnormalMotor {
            enabled: true,
            string: 4,
            region_length_mm: 1600.0,
            out_of_groove_probability: 0.7,
            radius_excess: [0.1, 0.3],
            jam_probability: 0.1,
        }
    }
}

fn range(field: &str, r: [f64; 2], positive: bool) -> Result<(), SimError> {
    let ok = r
        .iter()
        .all(|x| x.is_finite() && (*x > 0.0 || (!positive && *x >= 0.0)));
    if !ok || r[0] > r[1] {
        let sign = if positive { "> 0" } else { ">= 0" };
        return Err(bad(
            field,
            format!(
                "[{}, {}] is not a range of finite numbers {sign}",
                r[0], r[1]
            ),
        ));
    }
    Ok(())
}

impl PhysicsConfig {
    /// Read a configuration TOML file (all keys optional).
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SimError> {
        let config: PhysicsConfig = crate::sim::config::read_toml(path.as_ref())?;
        config.validate()?;
        Ok(config)
    }

    /// The configuration of preset `name` ([`PRESET_NAMES`]).
    pub fn preset(name: &str) -> Result<Self, SimError> {
        let text = preset_text(name).ok_or_else(|| {
            bad(
                "--preset",
                format!(
                    "`{name}` is not a preset of the independent simulator (presets: {})",
                    PRESET_NAMES.join(", ")
                ),
            )
        })?;
        let config: PhysicsConfig = toml::from_str(text)
            .map_err(|e| bad("--preset", format!("preset `{name}` does not parse: {e}")))?;
        config.validate()?;
        Ok(config)
    }

    /// Check every parameter; errors name the field (`section.key`). The
    /// sections shared with the model simulator are checked by its own rules.
    pub fn validate(&self) -> Result<(), SimError> {
        // The pulley blocks are this simulator's: the shared rules check
        // the rest of `[nominal]`.
        self.nominal.validate_pulley_blocks()?;
        crate::sim::SimConfig {
            nominal: crate::sim::config::NominalConfig {
                mechanical_advantage: Vec::new(),
                ..self.nominal.clone()
            },
            tracker: self.tracker.clone(),
            tension: self.tension.clone(),
            lattice: self.lattice.clone(),
            random: self.random.clone(),
            // This simulator's abnormal motor is its own section (below).
            abnormal_motor: crate::sim::config::AbnormalMotorConfig {
                enabled: false,
                ..Default::default()
            },
            ..crate::sim::SimConfig::default()
        }
        .validate()?;
        non_negative("orientation.sigma_deg", self.orientation.sigma_deg)?;
        if self.orientation.sigma_deg > 10.0 {
            return Err(bad("orientation.sigma_deg", "must be at most 10 degrees"));
        }
        self.validate_as_built()?;
        self.validate_motor_effects_and_carriage()?;
        self.stream.validate()?;
        Ok(())
    }

    /// `[as_built]`: the anchors, guides, spools, strings, frame and marker.
    fn validate_as_built(&self) -> Result<(), SimError> {
        let a = &self.as_built;
        non_negative("as_built.anchor_sigma_mm", a.anchor_sigma_mm)?;
        non_negative("as_built.home_sigma_mm", a.home_sigma_mm)?;
        range("as_built.guide_radius_mm", a.guide_radius_mm, true)?;
        non_negative("as_built.guide_tilt_deg", a.guide_tilt_deg)?;
        if a.guide_tilt_deg > 30.0 {
            return Err(bad("as_built.guide_tilt_deg", "must be at most 30 degrees"));
        }
        range("as_built.lead_mm", a.lead_mm, false)?;
        non_negative(
            "as_built.spool_radius_shared_sigma",
            a.spool_radius_shared_sigma,
        )?;
        non_negative(
            "as_built.spool_radius_each_sigma",
            a.spool_radius_each_sigma,
        )?;
        if a.spool_radius_shared_sigma + a.spool_radius_each_sigma > 0.2 {
            return Err(bad(
                "as_built.spool_radius_*_sigma",
                "spreads above 20 % would draw negative radii",
            ));
        }
        range("as_built.spool_width_mm", a.spool_width_mm, true)?;
        if !(a.string_diameter_mm.is_finite() && a.string_diameter_mm > 0.0) {
            return Err(bad(
                "as_built.string_diameter_mm",
                "must be a finite number > 0",
            ));
        }
        non_negative("as_built.string_diameter_sigma", a.string_diameter_sigma)?;
        if a.string_diameter_sigma > 0.2 {
            return Err(bad("as_built.string_diameter_sigma", "must be at most 0.2"));
        }
        if a.spool_width_mm[0] < 1.5 * a.string_diameter_mm {
            return Err(bad(
                "as_built.spool_width_mm",
                "a spool must hold at least 1.5 string diameters per layer",
            ));
        }
        range("as_built.layer_packing", a.layer_packing, true)?;
        range("as_built.pitch_excess", a.pitch_excess, false)?;
        range("as_built.layer_change_rad", a.layer_change_rad, false)?;
        range("as_built.crossover_rise_mm", a.crossover_rise_mm, false)?;
        range("as_built.crossover_rad", a.crossover_rad, false)?;
        if a.crossover_rad[1] > std::f64::consts::TAU {
            return Err(bad("as_built.crossover_rad", "must be at most one turn"));
        }
        range("as_built.string_stiffness_n", a.string_stiffness_n, true)?;
        range("as_built.string_mass_g_per_m", a.string_mass_g_per_m, false)?;
        if !(a.string_total_mm.is_finite() && a.string_total_mm > 0.0) {
            return Err(bad(
                "as_built.string_total_mm",
                "must be a finite number > 0",
            ));
        }
        non_negative("as_built.string_total_sigma_mm", a.string_total_sigma_mm)?;
        range(
            "as_built.frame_compliance_mm_per_n",
            a.frame_compliance_mm_per_n,
            false,
        )?;
        range("as_built.marker_offset_mm", a.marker_offset_mm, false)?;
        non_negative("as_built.posture_amplitude_deg", a.posture_amplitude_deg)?;
        non_negative("as_built.posture_jitter_deg", a.posture_jitter_deg)?;
        if a.posture_amplitude_deg > 45.0 || a.posture_jitter_deg > 45.0 {
            return Err(bad("as_built.posture_*_deg", "must be at most 45 degrees"));
        }
        if !(a.posture_wavelength_mm.is_finite() && a.posture_wavelength_mm > 0.0) {
            return Err(bad(
                "as_built.posture_wavelength_mm",
                "must be a finite number > 0",
            ));
        }
        Ok(())
    }

    /// `[abnormal_motor]`, the injected effects and `[carriage]`.
    fn validate_motor_effects_and_carriage(&self) -> Result<(), SimError> {
        let m = &self.abnormal_motor;
        let strings = self.nominal.geometry().strings();
        if m.enabled && usize::from(m.string) >= strings {
            return Err(bad(
                "abnormal_motor.string",
                format!(
                    "{} is not a string of this {strings}-string device (0..{}); choose one or \
                     set abnormal_motor.enabled = false",
                    m.string,
                    strings - 1
                ),
            ));
        }
        non_negative("abnormal_motor.region_length_mm", m.region_length_mm)?;
        probability(
            "abnormal_motor.out_of_groove_probability",
            m.out_of_groove_probability,
        )?;
        range("abnormal_motor.radius_excess", m.radius_excess, false)?;
        probability("abnormal_motor.jam_probability", m.jam_probability)?;
        super::effects::parse_effects(&self.effects)?;
        let attachments = &self.carriage.attachment_mm;
        if !attachments.is_empty() && attachments.len() != strings {
            return Err(bad(
                "carriage.attachment_mm",
                format!(
                    "{} attachment points for {strings} strings: give one per string, or none \
                     for strings that meet at one point",
                    attachments.len()
                ),
            ));
        }
        if attachments.iter().flatten().any(|x| !x.is_finite()) {
            return Err(bad("carriage.attachment_mm", "must be finite numbers (mm)"));
        }
        Ok(())
    }
}
