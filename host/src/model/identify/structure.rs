//! What an identification frees ([`Structure`]) and the priors it holds
//! the rest by ([`Priors`]).

use serde::{Deserialize, Serialize};
use spidar_core::model::{Effect, EffectTerm, StringLayout};
use spidar_core::STRINGS;

/// Prior standard deviations of the geometry.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct Priors {
    /// As-built tolerance of each anchor coordinate, mm.
    pub anchor_sd_mm: f64,
    /// Each anchor's own tolerance, mm, when the geometry gives them
    /// ([`crate::data::dataset::Geometry::anchor_sd_mm`]); else
    /// `anchor_sd_mm` for every anchor.
    #[serde(default)]
    pub anchor_sd_each_mm: Option<[f64; STRINGS]>,
    /// Home (initialization point) tolerance, mm.
    pub home_sd_mm: f64,
    /// Tracker frame rotation tolerance, rad.
    pub rotation_sd_rad: f64,
    /// Tracker frame translation tolerance, mm.
    pub translation_sd_mm: f64,
    /// How far one spool's thinning rate may depart from the shared one
    /// ([`WindingPhysics::kappa_each_mm`](super::WindingPhysics::kappa_each_mm)),
    /// mm/rad^2.
    #[serde(default = "default_kappa_each_sd")]
    pub kappa_each_sd_mm: f64,
    /// The strings' tension when home was captured ([`Effect::Stretch`]'s
    /// `home_tension_n`), N: the pretension the initialization holds, the
    /// firmware's default 1 N. The data fix it only through the stretch's
    /// home part, which is small when the strings are stiff.
    #[serde(default = "default_home_tension")]
    pub home_tension_n: f64,
    /// Its tolerance, N.
    #[serde(default = "default_home_tension_sd")]
    pub home_tension_sd_n: f64,
}

fn default_home_tension() -> f64 {
    1.0
}

fn default_home_tension_sd() -> f64 {
    1.0
}

fn default_kappa_each_sd() -> f64 {
    KAPPA_EACH_SD_MM
}

/// Prior sd of a spool's own thinning rate: `d^2 / (4 pi)` of a 0.5 mm string
/// is 0.02 mm/rad^2, and spools twice as wide as others thin half as fast.
pub const KAPPA_EACH_SD_MM: f64 = 0.02;

impl Priors {
    /// Anchor `i`'s as-built tolerance, mm.
    pub fn anchor_tolerance_mm(&self, i: usize) -> f64 {
        self.anchor_sd_each_mm
            .map_or(self.anchor_sd_mm, |each| each[i])
    }
}

impl Default for Priors {
    fn default() -> Self {
        Priors {
            anchor_sd_mm: 15.0,
            anchor_sd_each_mm: None,
            home_sd_mm: 200.0,
            rotation_sd_rad: 0.2,
            translation_sd_mm: 500.0,
            kappa_each_sd_mm: KAPPA_EACH_SD_MM,
            home_tension_n: default_home_tension(),
            home_tension_sd_n: default_home_tension_sd(),
        }
    }
}

/// Which parameters are free: the base model plus what diagnosis added.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Structure {
    pub priors: Priors,
    /// Per-anchor prior sd (mm), overriding `priors.anchor_sd_mm` for anchors
    /// the geometry family released (e.g. a bracket mounted in the wrong hole).
    pub anchor_sd_override_mm: [Option<f64>; STRINGS],
    /// Whether the tracker's scale relative to the device is free.
    pub fit_room_scale: bool,
    /// Effect terms with their starting values; their parameters are free
    /// (a slip's time is not: it is chosen by the diagnosis search).
    pub effects: Vec<EffectTerm>,
    /// Hold each spool's own thinning rate at the start's
    /// ([`WindingPhysics::kappa_each_mm`](super::WindingPhysics::kappa_each_mm))
    /// instead of fitting it. The base model holds them (at 0: one shared
    /// rate); the diagnosis loop frees them when that lowers the
    /// blocked-fold error (spools of other widths), and the monitor holds a
    /// calibration's (in a window of seconds a string's `theta^2` would
    /// stand in for a step or a drift).
    #[serde(default = "hold_by_default")]
    pub hold_kappa_each: bool,
    /// Where the tracked body's origin sits from the strings' meeting point,
    /// in the body's frame (mm), when the diagnosis loop found it from the
    /// tracker's orientation: the tracker's positions are then read at the
    /// meeting point, `p - R_body d`
    /// ([`crate::data::observe::at_meeting_points`]). Not part of what the device
    /// evaluates: it says how to read the tracker.
    #[serde(default)]
    pub marker_body_mm: Option<[f64; 3]>,
    /// Reweigh the rows robustly (Huber, then Tukey rounds) after the
    /// least-squares round; false fits plain least squares, every residual
    /// weighing alike (the reference stage, [`crate::model::reference`]).
    #[serde(default = "hold_by_default")]
    pub robust: bool,
}

impl Default for Structure {
    fn default() -> Self {
        Structure {
            priors: Priors::default(),
            anchor_sd_override_mm: [None; STRINGS],
            fit_room_scale: false,
            effects: Vec::new(),
            hold_kappa_each: true,
            marker_body_mm: None,
            robust: true,
        }
    }
}

fn hold_by_default() -> bool {
    true
}

/// Names, typical sizes (used to scale the LM variables) and units of an
/// effect's free parameters, in the order of `Effect::parameters`.
pub fn effect_parameter_info(effect: &Effect) -> &'static [(&'static str, f64, &'static str)] {
    match *effect {
        Effect::Offset { .. } => &[("offset", 1.0, "mm")],
        Effect::Scale { .. } => &[("scale", 1e-3, "1")],
        Effect::Winding { power: 2, .. } => &[("winding2", 2.5e-5, "mm/rad^2")],
        Effect::Winding { power: 3, .. } => &[("winding3", 1.25e-7, "mm/rad^3")],
        Effect::Winding { .. } => &[("winding", 6e-10, "mm/rad^k")],
        Effect::Eccentricity { .. } => &[
            ("eccentricity_sin", 0.1, "mm"),
            ("eccentricity_cos", 0.1, "mm"),
        ],
        Effect::Elasticity { .. } => &[("elasticity", 1e-5, "1/N")],
        Effect::Backlash { .. } => &[("backlash", 0.1, "mm")],
        Effect::Drift { .. } => &[("drift", 1e-4, "mm/s")],
        Effect::Creep { .. } => &[("creep", 1e-7, "1/s")],
        Effect::Slip { .. } => &[("slip", 1.0, "mm")],
        Effect::Sag { .. } => &[
            ("sag", 0.1, "mm at 1 m and 1 N"),
            ("home_sag", 0.1, "mm at 1 m"),
        ],
        Effect::Stretch { .. } => &[
            ("stretch", 1e-5, "1/N"),
            ("stretch_lead", 1e-2, "mm/N"),
            ("stretch_home_tension", 1.0, "N"),
        ],
        Effect::FrameFlex { .. } => &[("frame_flex", 1e-2, "mm/N"), ("frame_flex_home", 0.1, "mm")],
        Effect::Latency { .. } => &[("latency", 1e-3, "s")],
        Effect::Guide { .. } => &[("guide_radius", 1.0, "mm")],
    }
}

/// The prior (centre, sd) of an effect's free parameter `parameter` (in
/// the order of `Effect::parameters`), if it has one: a stretch's home
/// tension, around the pretension held at home.
pub(super) fn effect_prior(
    effect: &Effect,
    parameter: usize,
    priors: &Priors,
) -> Option<(f64, f64)> {
    match (effect, parameter) {
        (Effect::Stretch { .. }, 2) => Some((priors.home_tension_n, priors.home_tension_sd_n)),
        _ => None,
    }
}

/// Prior sd of a parameter held at its nominal value (mm or rad): a
/// channel without a string, a planar device's z.
pub(super) const HELD_SD: f64 = 1e-3;

/// Prior sd of anchor `i` (mm): its override, the default tolerance, or
/// held when the channel carries no string.
pub(super) fn anchor_prior_sd(structure: &Structure, layout: StringLayout, i: usize) -> f64 {
    if !layout.is_active(i) {
        return HELD_SD;
    }
    structure.anchor_sd_override_mm[i].unwrap_or(structure.priors.anchor_tolerance_mm(i))
}
