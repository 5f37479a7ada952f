//! Kinematic identification: Levenberg-Marquardt on anchors, home, the winding
//! law and the tracker frame (plus any effect terms the diagnosis loop added),
//! from a session with tracker positions.
//!
//! ## Formulation
//! The tracker gives the true end-effector position in the room; mapped into
//! the device frame it gives each string's true geometric length
//! `|p - anchor_i|`. The model gives the same length from the counts
//! (`spidar_core::string_law::string_lengths_f64`). Identification minimizes
//! the string-space residuals
//!
//! `r_ki = |p_k - anchor_i| - L_i(counts_k, direction_k, tension_k, t_k)`
//!
//! (8 per captured row; 2197 x 8 for a lattice) plus prior terms. String space
//! keeps every residual explicit (no forward kinematics inside the fit) and
//! attributes errors to strings, which is what diagnosis needs next.
//!
//! ## Winding law
//! A string wound in level layers on a pulley has a winding radius that
//! shrinks linearly as it is paid out, so the payout is exactly quadratic in
//! the pulley angle (`model::StringLaw`): `payout_i = r_home_i theta - kappa
//! theta^2`. The radius at home differs per string (each pulley holds its own
//! amount of string at home, and pulleys differ by their machining), so it is
//! a per-string parameter. The thinning rate `kappa = d^2 / (4 pi)` of an
//! ideal spool depends only on the string diameter d and is shared, but a
//! level-wound spool of width `W` thins by `d^2 / (2 pi W)` per radian:
//! spools of other widths, packing or pitch thin at other rates. So each
//! string also has its own departure `kappa_i` from the shared rate
//! ([`WindingPhysics::kappa_each_mm`], prior sd [`KAPPA_EACH_SD_MM`], mean 0
//! over the strings). The base model holds them at 0; the diagnosis loop
//! frees them first, kept when the blocked-fold error falls
//! ([`Structure::hold_kappa_each`]): on the independent simulator's spools
//! (widths 3 to 6 mm) this took the string model's held-out error after
//! the loop from 0.85 to 0.44 mm (20 clean devices, `docs/benchmarks.md`),
//! while on the Hangprinter's 34 training rows, fitted unconditionally, it
//! raised the held-out error from 2.69 to 2.83 mm. With them free, a payout
//! scale error of one string (another pulley diameter, another encoder
//! resolution) is the string's own `r_home` and `kappa_i`. What a string
//! needs beyond this law (a constant offset, a higher order, ...) is an
//! effect the diagnosis loop adds when the data show it.
//!
//! ## Gauge and priors
//! Moving all anchors and home rigidly can be undone by the tracker frame, so
//! the anchors' centroid and mean orientation are pinned to the nominal design
//! (six tight prior rows). Each anchor coordinate has a prior around its
//! nominal value with the as-built tolerance (`Priors::anchor_sd_mm`); home
//! and the tracker frame have wide priors. A parameter whose posterior
//! standard deviation is close to its prior's is reported as not determined by
//! the data.
//!
//! ## Devices with 3 to 8 strings, planar devices
//! The parameter vector always has the controller's 8 channels; the frame's
//! [`StringLayout`] says which carry a string. Residual rows of inactive
//! channels have weight 0 and their parameters are held at the nominal value
//! by tight priors (they are not reported). The gauge uses the active
//! anchors. A planar device keeps anchors, home and the end-effector in the
//! plane `z = anchors' z`: the z coordinates, the tracker's rotation about x
//! and y and its z translation are held, and the tracker's z is not used.
//!
//! ## Mechanical advantage
//! A line doubled `m` times through pulley blocks changes length by
//! `payout / m`. The spool's winding physics is shared (one thinning rate
//! for one kind of line); string `i`'s law is `r_home_i theta - (kappa /
//! m_i) theta^2`, with `r_home_i` the effective radius (spool radius / m_i).
//!
//! ## Robustness
//! Iteratively reweighted least squares: a plain least-squares round, a Huber
//! round, then Tukey biweight rounds with the scale from the median absolute
//! deviation, so residuals of a misbehaving motor (the paper's outliers) stop
//! pulling on the fit. Weights are per string and row: one bad string does not
//! discard the other seven.

// Vector algebra indexes several 3-vectors by the same axis; index loops read best.
#![allow(clippy::needless_range_loop)]

use nalgebra::{DMatrix, DVector, Dyn, Owned};
use serde::{Deserialize, Serialize};
use spidar_core::geometry::{
    cross, device_from_room, distance, mat_mul, mat_vec, rotation_from_vector, sub, transpose,
    vector_from_rotation,
};
use spidar_core::kinematics::KinematicsRule;
use spidar_core::model::{
    Effect, EffectTerm, Frame, LayerTable, StringInputs, StringLaw, StringLayout, EVERY_STRING,
    WINDING_ORDER,
};
use spidar_core::string_law::{
    cos2_inclinations, sag_home_slope, sag_slope, string_lengths_f64, EffectContext,
};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::model::normal::{ArrowColumns, NormalEquations};

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
    /// ([`WindingPhysics::kappa_each_mm`]), mm/rad^2.
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
    /// ([`WindingPhysics::kappa_each_mm`]) instead of fitting it. The base
    /// model holds them (at 0: one shared rate); the diagnosis loop frees
    /// them when that lowers the blocked-fold error (spools of other
    /// widths), and the monitor holds a calibration's (in a window of
    /// seconds a string's `theta^2` would stand in for a step or a drift).
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

fn hold_by_default() -> bool {
    true
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

/// One identified parameter with its uncertainty.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ParameterEstimate {
    pub name: String,
    pub unit: String,
    pub value: f64,
    /// Posterior standard deviation (from the Gauss-Newton covariance).
    pub sd: f64,
    /// Prior standard deviation, when the parameter has a prior.
    pub prior_sd: Option<f64>,
    /// False when the data do not determine the parameter (see warnings).
    pub determined: bool,
}

/// Result of an identification.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Identification {
    pub frame: Frame<f64>,
    pub winding: WindingPhysics,
    pub laws: [StringLaw; STRINGS],
    pub effects: Vec<EffectTerm>,
    pub parameters: Vec<ParameterEstimate>,
    pub warnings: Vec<String>,
    /// Robust scale of the string-space residuals, mm.
    pub residual_scale_mm: f64,
    /// Each active string's scale of the part of its residual that changes
    /// from row to row (the residual less its running median over 41 rows),
    /// mm (0 on inactive channels): what forward kinematics weighs the
    /// strings by ([`spidar_core::kinematics::residual_weights`]).
    pub length_scale_mm: [f64; STRINGS],
    /// Share of (row, string) residuals the robust weights rejected (weight < 0.1).
    pub rejected_fraction: f64,
    /// LM evaluations over all robust rounds.
    pub evaluations: usize,
    /// When forward kinematics leaves a string out and calls the strings
    /// inconsistent: the device's defaults until the calibration chooses
    /// ([`crate::model::rule`]).
    #[serde(default)]
    pub kinematics: KinematicsRule,
}

impl Identification {
    /// Its kinematic model (what forward kinematics needs).
    pub fn kinematic_model(&self) -> crate::model::predict::KinematicModel<'_> {
        crate::model::predict::KinematicModel {
            frame: &self.frame,
            laws: &self.laws,
            effects: &self.effects,
            length_scale_mm: &self.length_scale_mm,
            kinematics: self.kinematics,
        }
    }

    /// The model as it holds for another session, started from a new home
    /// capture: without the slips found in this one. A slip is an event of
    /// the session it happened in (the string slid on its spool); a new home
    /// capture counts from the string as it is, so the step is not there.
    /// Applied to a later session by its time since home, a training
    /// session's early slip put 4 mm on one string of every test row after
    /// it (independent simulator, slip seed 3: test 1.23 mm).
    pub fn for_a_new_session(&self) -> Identification {
        Identification {
            effects: self
                .effects
                .iter()
                .filter(|t| !matches!(t.effect, Effect::Slip { .. }))
                .copied()
                .collect(),
            ..self.clone()
        }
    }
}

/// Why an identification failed.
#[derive(Debug, thiserror::Error)]
pub enum IdentifyError {
    #[error(
        "identification needs at least {needed} rows with tracker positions, the session has {got}"
    )]
    TooFewRows { needed: usize, got: usize },
    #[error("identification diverged: {0}")]
    Diverged(String),
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
    }
}

/// The prior (centre, sd) of an effect's free parameter `parameter` (in
/// the order of `Effect::parameters`), if it has one: a stretch's home
/// tension, around the pretension held at home.
fn effect_prior(effect: &Effect, parameter: usize, priors: &Priors) -> Option<(f64, f64)> {
    match (effect, parameter) {
        (Effect::Stretch { .. }, 2) => Some((priors.home_tension_n, priors.home_tension_sd_n)),
        _ => None,
    }
}

/// Everything the fit varies, in physical units.
#[derive(Clone, Debug)]
struct State {
    frame: Frame<f64>,
    winding: WindingPhysics,
    effects: Vec<EffectTerm>,
}

/// Layout of the LM parameter vector.
struct Layout {
    fit_scale: bool,
    /// (effect index, parameter index within the effect) per effect column.
    effect_columns: Vec<(usize, usize)>,
    /// Typical size of each column's parameter (LM variable = value / scale).
    scale: Vec<f64>,
    /// The columns each string's residuals touch, in the order
    /// [`Problem::string_rows`] gives their values.
    arrow: ArrowColumns,
}

const ANCHORS: usize = 0;
const HOME: usize = 24;
const ROTATION: usize = 27;
const TRANSLATION: usize = 30;
const SCALE: usize = 33;

impl Layout {
    fn new(structure: &Structure) -> Layout {
        let fit_scale = structure.fit_room_scale;
        let mut scale = vec![1.0; 27];
        scale.extend([1e-3; 3]);
        scale.extend([1.0; 3]);
        if fit_scale {
            scale.push(1e-4);
        }
        scale.extend([0.1; STRINGS]); // r_home per string
        scale.push(1e-3); // kappa
        scale.extend([1e-3; STRINGS]); // kappa_each
        let mut effect_columns = Vec::new();
        for (e, term) in structure.effects.iter().enumerate() {
            for (p, (_, s, _)) in effect_parameter_info(&term.effect).iter().enumerate() {
                effect_columns.push((e, p));
                scale.push(*s);
            }
        }
        let mut layout = Layout {
            fit_scale,
            effect_columns,
            scale,
            arrow: ArrowColumns {
                n: 0,
                shared: Vec::new(),
                own: Default::default(),
            },
        };
        layout.arrow = layout.arrow_columns(structure);
        layout
    }

    /// A string's residual touches its anchor, winding radius, spool rate
    /// and the terms on it (its own columns), and the home, the tracker
    /// frame, the shared thinning rate and the every-string terms (the
    /// shared ones).
    fn arrow_columns(&self, structure: &Structure) -> ArrowColumns {
        let terms_on = |owner: u8| -> Vec<usize> {
            self.term_columns(structure, owner)
                .map(|c| self.first_effect() + c)
                .collect()
        };
        let mut shared: Vec<usize> = (HOME..TRANSLATION + 3).collect();
        if self.fit_scale {
            shared.push(SCALE);
        }
        shared.push(self.kappa());
        shared.extend(terms_on(EVERY_STRING));
        let own = core::array::from_fn(|i| {
            let mut own = vec![
                ANCHORS + 3 * i,
                ANCHORS + 3 * i + 1,
                ANCHORS + 3 * i + 2,
                self.r_home() + i,
                self.kappa_each() + i,
            ];
            own.extend(terms_on(i as u8));
            own
        });
        ArrowColumns {
            n: self.len(),
            shared,
            own,
        }
    }

    /// The effect columns (counted from the first) of the terms on
    /// `owner`, a string or [`EVERY_STRING`].
    fn term_columns<'s>(
        &'s self,
        structure: &'s Structure,
        owner: u8,
    ) -> impl Iterator<Item = usize> + 's {
        self.effect_columns
            .iter()
            .enumerate()
            .filter(move |(_, &(e, _))| structure.effects[e].string == owner)
            .map(|(c, _)| c)
    }
    fn r_home(&self) -> usize {
        SCALE + usize::from(self.fit_scale)
    }
    fn kappa(&self) -> usize {
        self.r_home() + STRINGS
    }
    fn kappa_each(&self) -> usize {
        self.kappa() + 1
    }
    fn first_effect(&self) -> usize {
        self.kappa_each() + STRINGS
    }
    fn len(&self) -> usize {
        self.scale.len()
    }
}

/// A prior row: its value and its gradient over the physical parameters as
/// (column, d).
type PriorRow = (f64, Vec<(usize, f64)>);

/// The LM problem for one robust round: rotation is linearized around
/// `base_rotation` (the columns 27..30 are a small rotation vector on top).
struct Problem<'a> {
    observations: &'a [&'a Observation],
    weights: &'a [[f64; STRINGS]],
    residual_sd: f64,
    structure: &'a Structure,
    nominal: &'a Frame<f64>,
    layout: &'a Layout,
    base_rotation: [[f64; 3]; 3],
    /// Counts per revolution and mechanical advantage (not fitted).
    winding_fixed: WindingPhysics,
    /// Current LM variables (scaled).
    x: DVector<f64>,
}

impl Problem<'_> {
    fn state(&self) -> State {
        let v: Vec<f64> = self
            .x
            .iter()
            .zip(&self.layout.scale)
            .map(|(x, s)| x * s)
            .collect();
        let mut frame = *self.nominal;
        for i in 0..STRINGS {
            for c in 0..3 {
                frame.anchors[i][c] = v[ANCHORS + 3 * i + c];
            }
        }
        frame.home = [v[HOME], v[HOME + 1], v[HOME + 2]];
        frame.room_rotation = mat_mul(
            &self.base_rotation,
            &rotation_from_vector([v[ROTATION], v[ROTATION + 1], v[ROTATION + 2]]),
        );
        frame.room_translation = [v[TRANSLATION], v[TRANSLATION + 1], v[TRANSLATION + 2]];
        frame.room_scale = if self.layout.fit_scale {
            1.0 + v[SCALE]
        } else {
            self.nominal.room_scale
        };
        let mut r_home_mm = [0.0; STRINGS];
        r_home_mm.copy_from_slice(&v[self.layout.r_home()..self.layout.r_home() + STRINGS]);
        let winding = WindingPhysics {
            r_home_mm,
            kappa_mm: v[self.layout.kappa()],
            kappa_each_mm: core::array::from_fn(|i| v[self.layout.kappa_each() + i]),
            ..self.winding_fixed
        };
        let mut effects = self.structure.effects.clone();
        let first = self.layout.first_effect();
        let mut col = first;
        for term in effects.iter_mut() {
            let n = term.effect.parameters().len();
            if let Some(e) = term.effect.with_parameters(&v[col..col + n]) {
                term.effect = e;
            }
            col += n;
        }
        State {
            frame,
            winding,
            effects,
        }
    }

    fn anchor_sd(&self, i: usize) -> f64 {
        anchor_prior_sd(self.structure, self.nominal.layout, i)
    }

    /// Prior rows: (row value, gradient over physical parameters as (column, d)).
    fn prior_rows(&self, state: &State) -> Vec<PriorRow> {
        let mut rows = Vec::new();
        self.frame_prior_rows(state, &mut rows);
        self.winding_prior_rows(state, &mut rows);
        self.effect_prior_rows(state, &mut rows);
        self.gauge_rows(state, &mut rows);
        rows
    }

    /// The frame's priors: each anchor, the home position, the tracker's
    /// translation and rotation around nominal.
    fn frame_prior_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let p = &self.structure.priors;
        let nominal = self.nominal;
        let layout = nominal.layout;
        let held = |active: bool, sd: f64| if active { sd } else { HELD_SD };
        for i in 0..STRINGS {
            for c in 0..3 {
                let sd = if layout.planar && c == 2 {
                    HELD_SD
                } else {
                    self.anchor_sd(i)
                };
                rows.push((
                    (state.frame.anchors[i][c] - nominal.anchors[i][c]) / sd,
                    vec![(ANCHORS + 3 * i + c, 1.0 / sd)],
                ));
            }
        }
        for c in 0..3 {
            let in_plane = !(layout.planar && c == 2);
            let sd = held(in_plane, p.home_sd_mm);
            rows.push((
                (state.frame.home[c] - nominal.home[c]) / sd,
                vec![(HOME + c, 1.0 / sd)],
            ));
            let sd = held(in_plane, p.translation_sd_mm);
            rows.push((
                (state.frame.room_translation[c] - nominal.room_translation[c]) / sd,
                vec![(TRANSLATION + c, 1.0 / sd)],
            ));
        }
        let total_rotation = vector_from_rotation(&mat_mul(
            &transpose(&nominal.room_rotation),
            &state.frame.room_rotation,
        ));
        for c in 0..3 {
            // A planar device's tracker frame turns about z only.
            let sd = held(!(layout.planar && c < 2), p.rotation_sd_rad);
            rows.push((total_rotation[c] / sd, vec![(ROTATION + c, 1.0 / sd)]));
        }
    }

    /// The winding's priors: the radius of a channel without a string, each
    /// spool's own thinning rate and their mean.
    fn winding_prior_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let p = &self.structure.priors;
        let layout = self.nominal.layout;
        // Channels without a string: their winding radius stays nominal.
        for i in (0..STRINGS).filter(|&i| !layout.is_active(i)) {
            let col = self.layout.r_home() + i;
            let s = self.layout.scale[col];
            rows.push((
                (state.winding.r_home_mm[i] - self.winding_fixed.r_home_mm[i]) / s,
                vec![(col, 1.0 / s)],
            ));
        }
        // Each spool's own thinning rate: a prior around the shared one on
        // active channels, held at 0 on the others, and their mean held at
        // 0 (the shared rate carries it); or all held at the start's.
        let hold = self.structure.hold_kappa_each;
        for i in 0..STRINGS {
            let col = self.layout.kappa_each() + i;
            let (centre, sd) = if hold {
                (
                    self.winding_fixed.kappa_each_mm[i],
                    1e-3 * self.layout.scale[col],
                )
            } else if layout.is_active(i) {
                (0.0, p.kappa_each_sd_mm)
            } else {
                (0.0, self.layout.scale[col])
            };
            rows.push((
                (state.winding.kappa_each_mm[i] - centre) / sd,
                vec![(col, 1.0 / sd)],
            ));
        }
        if !hold {
            const KAPPA_GAUGE_SD: f64 = 1e-6;
            let n = layout.count().max(1) as f64;
            let mean = layout
                .indices()
                .map(|i| state.winding.kappa_each_mm[i])
                .sum::<f64>()
                / n;
            rows.push((
                mean / KAPPA_GAUGE_SD,
                layout
                    .indices()
                    .map(|i| (self.layout.kappa_each() + i, 1.0 / (n * KAPPA_GAUGE_SD)))
                    .collect(),
            ));
        }
    }

    /// Effect parameters with a prior.
    fn effect_prior_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let p = &self.structure.priors;
        for (c, &(e, pi)) in self.layout.effect_columns.iter().enumerate() {
            let effect = &state.effects[e].effect;
            if let (Some((centre, sd)), Some(&value)) =
                (effect_prior(effect, pi, p), effect.parameters().get(pi))
            {
                rows.push((
                    (value - centre) / sd,
                    vec![(self.layout.first_effect() + c, 1.0 / sd)],
                ));
            }
        }
    }

    /// Gauge: the active anchors' centroid and mean orientation stay
    /// nominal (in the plane: the orientation about z only).
    fn gauge_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let nominal = self.nominal;
        let layout = nominal.layout;
        const GAUGE_SD_MM: f64 = 0.01;
        let n_active = layout.count() as f64;
        let centroid_nominal = centroid(&nominal.anchors, layout);
        let centroid_now = centroid(&state.frame.anchors, layout);
        for c in 0..3 {
            let grad = layout
                .indices()
                .map(|i| (ANCHORS + 3 * i + c, 1.0 / (n_active * GAUGE_SD_MM)))
                .collect();
            rows.push(((centroid_now[c] - centroid_nominal[c]) / GAUGE_SD_MM, grad));
        }
        let spread: f64 = layout
            .indices()
            .map(|i| {
                let d = sub(nominal.anchors[i], centroid_nominal);
                d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            })
            .sum();
        // Small-rotation gauge: sum_i (a0_i - c0) x (a_i - a0_i) / spread = 0.
        let mut value = [0.0; 3];
        let mut grads: [Vec<(usize, f64)>; 3] = Default::default();
        for i in layout.indices() {
            let r = sub(nominal.anchors[i], centroid_nominal);
            let d = sub(state.frame.anchors[i], nominal.anchors[i]);
            let x = cross(r, d);
            for c in 0..3 {
                value[c] += x[c] / spread;
            }
            // d(r x d)/dd = [r]x
            let rx = [[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]];
            for c in 0..3 {
                for k in 0..3 {
                    if rx[c][k] != 0.0 {
                        grads[c].push((ANCHORS + 3 * i + k, rx[c][k] / spread));
                    }
                }
            }
        }
        // Angle tolerance equivalent to GAUGE_SD_MM at the frame's size.
        let angle_sd = GAUGE_SD_MM / (spread / n_active).sqrt();
        // In the plane, rotations about x and y are held by the anchors' z
        // already; only the one about z is a gauge freedom.
        let gauge_axes = if layout.planar { 2..3 } else { 0..3 };
        for c in gauge_axes {
            let g = grads[c].iter().map(|&(j, d)| (j, d / angle_sd)).collect();
            rows.push((value[c] / angle_sd, g));
        }
    }

    /// The effect columns of one observation, per column and string:
    /// analytic gradients of the terms (each term touches only its own
    /// string) at each string's `contexts`.
    fn effect_gradients(
        &self,
        state: &State,
        contexts: &[Option<EffectContext>; STRINGS],
    ) -> Vec<[f64; STRINGS]> {
        let mut effect_grad = vec![[0.0; STRINGS]; self.layout.effect_columns.len()];
        for (c, &(e, pi)) in self.layout.effect_columns.iter().enumerate() {
            let term = &state.effects[e];
            for s in state.frame.layout.indices().filter(|&s| term.applies_to(s)) {
                if let Some(ctx) = &contexts[s] {
                    if let Some(g) = term.effect.gradient_f64(ctx).get(pi) {
                        effect_grad[c][s] = -g;
                    }
                }
            }
        }
        effect_grad
    }

    fn n_rows(&self) -> usize {
        let layout = self.nominal.layout;
        let gauge = if layout.planar { 4 } else { 6 };
        // Anchors, home/rotation/translation, inactive radii, each spool's
        // thinning rate and its mean, the gauge.
        self.observations.len() * STRINGS
            + 24
            + 9
            + (STRINGS - layout.count())
            + STRINGS
            + usize::from(!self.structure.hold_kappa_each)
            + self
                .layout
                .effect_columns
                .iter()
                .filter(|&&(e, pi)| {
                    effect_prior(
                        &self.structure.effects[e].effect,
                        pi,
                        &self.structure.priors,
                    )
                    .is_some()
                })
                .count()
            + gauge
    }

    /// String-space residuals of one observation (geometric minus model; 0
    /// on channels without a string).
    fn string_residuals(state: &State, laws: &[StringLaw; STRINGS], o: &Observation) -> [f64; 8] {
        residuals_at(&state.frame, laws, &state.effects, o)
    }
}

/// Prior sd of a parameter held at its nominal value (mm or rad): a
/// channel without a string, a planar device's z.
const HELD_SD: f64 = 1e-3;

/// Prior sd of anchor `i` (mm): its override, the default tolerance, or
/// held when the channel carries no string.
fn anchor_prior_sd(structure: &Structure, layout: StringLayout, i: usize) -> f64 {
    if !layout.is_active(i) {
        return HELD_SD;
    }
    structure.anchor_sd_override_mm[i].unwrap_or(structure.priors.anchor_tolerance_mm(i))
}

/// The tracker position of `o` in the device frame (mm); on a planar
/// device, in the anchors' plane whatever the tracker's z.
pub fn device_position(frame: &Frame<f64>, o: &Observation) -> [f64; 3] {
    let mut p = device_from_room(frame, o.tracker.unwrap_or([0.0; 3]));
    if frame.layout.planar {
        p[2] = frame.anchors[0][2];
    }
    p
}

/// `o`'s inputs with each string's inclination (what a sag term reads) at
/// `p`, the tracker's position in the device frame ([`device_position`]).
pub fn inputs_at(frame: &Frame<f64>, o: &Observation, p: &[f64; 3]) -> StringInputs {
    StringInputs {
        cos2_inclination_q16: cos2_inclinations(&frame.anchors, p),
        ..o.inputs
    }
}

/// String-space residuals (geometric minus model, mm) of one observation; 0
/// on channels without a string.
pub(crate) fn residuals_at(
    frame: &Frame<f64>,
    laws: &[StringLaw; STRINGS],
    effects: &[EffectTerm],
    o: &Observation,
) -> [f64; STRINGS] {
    let p = device_position(frame, o);
    let lengths = string_lengths_f64(frame, laws, effects, &inputs_at(frame, o, &p));
    let mut r = [0.0; STRINGS];
    for i in frame.layout.indices() {
        r[i] = distance(p, frame.anchors[i]) - lengths[i];
    }
    r
}

fn centroid(points: &[[f64; 3]; STRINGS], layout: StringLayout) -> [f64; 3] {
    let n = layout.count().max(1) as f64;
    let mut c = [0.0; 3];
    for i in layout.indices() {
        for k in 0..3 {
            c[k] += points[i][k] / n;
        }
    }
    c
}

/// The derivatives of string `i`'s model length over its payout and over
/// its home length at `o` (1 each without effects): effects that scale with
/// the payout or the home length (scale, elasticity, stretch, sag) carry
/// those derivatives along. `context`: the string's, for the sag.
fn length_derivatives(
    effects: &[EffectTerm],
    i: usize,
    o: &Observation,
    context: Option<&EffectContext>,
) -> (f64, f64) {
    let (mut d_payout, mut d_home) = (1.0, 1.0);
    for term in effects.iter().filter(|t| t.applies_to(i)) {
        match term.effect {
            Effect::Scale { relative } => d_payout += relative,
            Effect::Elasticity { per_newton } => {
                let t = f64::from(o.inputs.tension_mn[i]) / 1000.0;
                d_payout += per_newton * t;
                d_home += per_newton * t;
            }
            Effect::Stretch {
                per_newton,
                home_tension_n,
                ..
            } => {
                let t = f64::from(o.inputs.tension_mn[i]) / 1000.0;
                d_payout += per_newton * t;
                d_home += per_newton * (t - home_tension_n);
            }
            Effect::Sag {
                mm_at_1m_1n,
                home_mm_at_1m,
            } => {
                if let Some(ctx) = context {
                    let slope = sag_slope(mm_at_1m_1n, ctx);
                    d_payout += slope;
                    d_home += slope + sag_home_slope(home_mm_at_1m, ctx);
                }
            }
            _ => {}
        }
    }
    (d_payout, d_home)
}

impl levenberg_marquardt::LeastSquaresProblem<f64, Dyn, Dyn> for Problem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.x.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.x.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let state = self.state();
        let laws = state.winding.laws();
        let mut r = DVector::zeros(self.n_rows());
        for (k, o) in self.observations.iter().enumerate() {
            let res = Problem::string_residuals(&state, &laws, o);
            for i in 0..STRINGS {
                r[k * STRINGS + i] = self.weights[k][i].sqrt() * res[i] / self.residual_sd;
            }
        }
        let base = self.observations.len() * STRINGS;
        for (j, (value, _)) in self.prior_rows(&state).into_iter().enumerate() {
            r[base + j] = value;
        }
        r.iter().all(|v| v.is_finite()).then_some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let state = self.state();
        let columns = &self.layout.arrow;
        let mut jac = DMatrix::zeros(self.n_rows(), columns.n);
        let strings_finite = self.string_rows(&state, |row, i, own, shared| {
            for (&c, &v) in columns.own[i].iter().zip(own) {
                jac[(row, c)] = v;
            }
            for (&c, &v) in columns.shared.iter().zip(shared) {
                jac[(row, c)] = v;
            }
        });
        let base = self.observations.len() * STRINGS;
        for (j, values) in self.scaled_prior_rows(&state).into_iter().enumerate() {
            jac.row_mut(base + j).copy_from_slice(&values);
        }
        (strings_finite && jac.iter().all(|v| v.is_finite())).then_some(jac)
    }
}

impl Problem<'_> {
    /// Each string residual's row of the Jacobian (over the scaled LM
    /// variables) at `state`, in row order: `visit(row, string, own,
    /// shared)` with its values on the string's own columns and on the
    /// shared ones ([`Layout::arrow`]); it is zero elsewhere. Rows of
    /// weight 0 (zero) are not visited. False when a value is not finite.
    fn string_rows(
        &self,
        state: &State,
        mut visit: impl FnMut(usize, usize, &[f64], &[f64]),
    ) -> bool {
        let laws = state.winding.laws();
        let layout = self.layout;
        let columns = &layout.arrow;
        let shared_terms: Vec<usize> = layout.term_columns(self.structure, EVERY_STRING).collect();
        let own_terms: [Vec<usize>; STRINGS] =
            core::array::from_fn(|i| layout.term_columns(self.structure, i as u8).collect());
        let frame = &state.frame;
        let w = &state.winding;
        let home_lengths: Vec<f64> = (0..STRINGS)
            .map(|i| distance(frame.home, frame.anchors[i]))
            .collect();
        let two_pi = 2.0 * std::f64::consts::PI;
        let planar = frame.layout.planar;
        let mut own = Vec::with_capacity(columns.n);
        let mut shared = Vec::with_capacity(columns.n);
        let mut finite = true;
        for (k, o) in self.observations.iter().enumerate() {
            let p = device_position(frame, o);
            let inputs = inputs_at(frame, o, &p);
            // Each string's context once per row, not once per column.
            let contexts: [Option<EffectContext>; STRINGS] =
                core::array::from_fn(|s| EffectContext::for_string(frame, &laws, &inputs, s));
            let effect_grad = self.effect_gradients(state, &contexts);
            for i in 0..STRINGS {
                let row = k * STRINGS + i;
                let f = self.weights[k][i].sqrt() / self.residual_sd;
                if f == 0.0 {
                    continue;
                }
                let a = frame.anchors[i];
                let geo = distance(p, a);
                let up = {
                    let d = sub(p, a);
                    [d[0] / geo, d[1] / geo, d[2] / geo]
                };
                let lh = home_lengths[i];
                let uh = {
                    let d = sub(frame.home, a);
                    [d[0] / lh, d[1] / lh, d[2] / lh]
                };
                let theta = two_pi * o.inputs.counts[i] as f64 / w.counts_per_rev[i] as f64;
                let (d_payout, d_home) =
                    length_derivatives(&state.effects, i, o, contexts[i].as_ref());
                own.clear();
                shared.clear();
                // Anchor, then home.
                own.extend((0..3).map(|c| f * (-up[c] + d_home * uh[c])));
                shared.extend((0..3).map(|c| f * (-d_home * uh[c])));
                // The tracker frame: rotation, translation.
                let rup = mat_vec(&frame.room_rotation, up);
                let wgrad = cross(up, p);
                shared.extend((0..3).map(|c| f * wgrad[c]));
                shared.extend((0..3).map(|c| f * (-rup[c] / frame.room_scale)));
                if planar {
                    // The position is held in the plane: the tracker's
                    // tilts and z translation do not move it.
                    shared[ROTATION - HOME] = 0.0;
                    shared[ROTATION + 1 - HOME] = 0.0;
                    shared[TRANSLATION + 2 - HOME] = 0.0;
                }
                if layout.fit_scale {
                    let dot = up[0] * p[0] + up[1] * p[1] + up[2] * p[2];
                    shared.push(f * (-dot / frame.room_scale));
                }
                // The winding law: radius, shared and own thinning rates.
                own.push(f * (-theta * d_payout));
                let d_kappa = f * (theta * theta * d_payout / w.mechanical_advantage[i]);
                shared.push(d_kappa);
                own.push(if self.structure.hold_kappa_each {
                    0.0
                } else {
                    d_kappa
                });
                own.extend(own_terms[i].iter().map(|&c| f * effect_grad[c][i]));
                shared.extend(shared_terms.iter().map(|&c| f * effect_grad[c][i]));
                // To the scaled LM variables.
                for (v, &c) in own.iter_mut().zip(&columns.own[i]) {
                    *v *= layout.scale[c];
                }
                for (v, &c) in shared.iter_mut().zip(&columns.shared) {
                    *v *= layout.scale[c];
                }
                finite &= own.iter().chain(&shared).all(|v| v.is_finite());
                visit(row, i, &own, &shared);
            }
        }
        finite
    }

    /// The prior rows of the Jacobian (over the scaled LM variables) at
    /// `state`, each on every column.
    fn scaled_prior_rows(&self, state: &State) -> Vec<Vec<f64>> {
        let scale = &self.layout.scale;
        self.prior_rows(state)
            .into_iter()
            .map(|(_, grad)| {
                let mut values = vec![0.0; scale.len()];
                for (c, d) in grad {
                    values[c] += d;
                }
                for (v, s) in values.iter_mut().zip(scale) {
                    *v *= s;
                }
                values
            })
            .collect()
    }

    /// `J^T J` and `J^T residuals` of the Jacobian `J` at the current
    /// variables, summed without forming `J` ([`crate::model::normal`]):
    /// the same figures as the dense products. `None` when `J` is not
    /// finite.
    fn normal_equations(&self, residuals: &DVector<f64>) -> Option<(DMatrix<f64>, DVector<f64>)> {
        let state = self.state();
        let mut normal = NormalEquations::new(&self.layout.arrow);
        let strings_finite = self.string_rows(&state, |row, i, own, shared| {
            normal.add_string_row(row, i, own, shared, residuals[row]);
        });
        let base = self.observations.len() * STRINGS;
        let mut priors_finite = true;
        for (j, values) in self.scaled_prior_rows(&state).into_iter().enumerate() {
            priors_finite &= values.iter().all(|v| v.is_finite());
            normal.add_row(base + j, &values, residuals[base + j]);
        }
        (strings_finite && priors_finite).then(|| normal.finish())
    }
}

/// LM variables of a state (rotation encoded as zero on top of the state's own).
fn encode(state: &State, layout: &Layout) -> DVector<f64> {
    let mut x = DVector::zeros(layout.len());
    let mut put = |i: usize, v: f64| x[i] = v / layout.scale[i];
    for i in 0..STRINGS {
        for c in 0..3 {
            put(ANCHORS + 3 * i + c, state.frame.anchors[i][c]);
        }
    }
    for c in 0..3 {
        put(HOME + c, state.frame.home[c]);
        put(TRANSLATION + c, state.frame.room_translation[c]);
    }
    if layout.fit_scale {
        put(SCALE, state.frame.room_scale - 1.0);
    }
    for i in 0..STRINGS {
        put(layout.r_home() + i, state.winding.r_home_mm[i]);
    }
    put(layout.kappa(), state.winding.kappa_mm);
    for i in 0..STRINGS {
        put(layout.kappa_each() + i, state.winding.kappa_each_mm[i]);
    }
    let mut col = layout.first_effect();
    for term in &state.effects {
        for v in term.effect.parameters() {
            put(col, v);
            col += 1;
        }
    }
    x
}

/// Levenberg-Marquardt on the normal equations: `(J^T J + lambda D) dx =
/// -J^T r` by Cholesky, with Marquardt's diagonal scaling `D = diag(J^T J)`.
///
/// Written here rather than using the `levenberg-marquardt` crate's driver
/// (which this module still uses for the problem trait) because the crate
/// takes a QR of the whole Jacobian (17,576 x 45 for a lattice) at every
/// step; the 45 x 45 normal equations are several times faster and are well
/// conditioned here (parameters are scaled to their typical size, priors keep
/// every direction determined).
fn minimize(mut problem: Problem<'_>) -> Result<(Problem<'_>, usize), String> {
    use levenberg_marquardt::LeastSquaresProblem;
    const MAX_ITERATIONS: usize = 60;
    let mut evaluations = 1;
    let mut x = problem.params();
    let mut r = problem
        .residuals()
        .ok_or("residuals not finite at the start")?;
    let mut cost = r.norm_squared();
    // Settled when a step lowers the cost by less than 1e-4 of one
    // residual's share of it (a chi-square change of 1e-4): a relative gain
    // of 6e-9 on a 2197-point lattice. Iterating on to 1e-12 cost each
    // loop step ~10 % more time and moved no decision.
    let settled = 1e-4 / r.len().max(1) as f64;
    let mut lambda = 1e-3;
    for _ in 0..MAX_ITERATIONS {
        let (normal, gradient) = problem.normal_equations(&r).ok_or("Jacobian not finite")?;
        let mut improved = false;
        while lambda < 1e12 {
            let mut damped = normal.clone();
            for j in 0..damped.nrows() {
                damped[(j, j)] += lambda * normal[(j, j)].max(1e-12);
            }
            let Some(chol) = damped.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = -chol.solve(&gradient);
            let trial = &x + &step;
            problem.set_params(&trial);
            evaluations += 1;
            match problem.residuals() {
                Some(r_trial) if r_trial.norm_squared() < cost => {
                    let new_cost = r_trial.norm_squared();
                    let relative_gain = (cost - new_cost) / cost.max(1e-300);
                    let small_step = step.amax() <= 1e-10 * (1.0 + x.amax());
                    x = trial;
                    r = r_trial;
                    cost = new_cost;
                    lambda = (lambda / 3.0).max(1e-12);
                    improved = true;
                    if relative_gain < settled || small_step {
                        return Ok((problem, evaluations));
                    }
                    break;
                }
                _ => {
                    problem.set_params(&x);
                    lambda *= 4.0;
                }
            }
        }
        if !improved {
            // No step lowers the cost: at the minimum (to rounding).
            problem.set_params(&x);
            return Ok((problem, evaluations));
        }
    }
    Ok((problem, evaluations))
}

/// Rows on each side of a row whose median residual is taken off it before
/// its string's scale is read ([`fast_residual_scales`]): 41 rows span
/// three rows of a 13-point lattice walked back and forth, so both
/// directions of approach.
const SCALE_WINDOW_ROWS: usize = 20;

/// Each active string's scale of the part of its residual that changes
/// from row to row (mm; 0 on inactive channels), what forward kinematics
/// weighs the strings by: the robust sd of the residual less its running
/// median over `2 SCALE_WINDOW_ROWS + 1` tracked rows in session order.
/// An error the model lacks that moves slowly (a drift, a slip's step, a
/// spool's error smooth along the walk) is taken off with the median; one
/// that changes from capture to capture (an encoder that lags the string,
/// read at each capture's own speed and direction) stays. Read on the
/// residuals themselves, a slip the loop had not yet found made its string
/// weigh less, and the held-out error then hid the slip (slip seeds 4 and
/// 6 lost theirs: 0.387 -> 0.538, 0.372 -> 0.528 mm); read from one row to
/// the next, the lag canceled (a lattice row approaches its points from
/// one side; `docs/benchmarks.md`, "Each string weighed by its scale").
fn fast_residual_scales(residuals: &[[f64; STRINGS]], layout: StringLayout) -> [f64; STRINGS] {
    core::array::from_fn(|i| {
        if !layout.is_active(i) {
            return 0.0;
        }
        let own: Vec<f64> = residuals.iter().map(|r| r[i]).collect();
        let slow = crate::data::stats::running_median(&own, SCALE_WINDOW_ROWS);
        let fast: Vec<f64> = own.iter().zip(&slow).map(|(r, m)| r - m).collect();
        crate::data::stats::robust_centre_and_sd(&fast).1.max(1e-6)
    })
}

/// Robust scale (1.4826 MAD) of the residuals of the active strings.
fn robust_scale(residuals: &[[f64; STRINGS]], layout: StringLayout) -> f64 {
    let all: Vec<f64> = residuals
        .iter()
        .flat_map(|r| layout.indices().map(|i| r[i]))
        .collect();
    crate::data::stats::robust_centre_and_sd(&all).1
}

#[derive(Clone, Copy)]
enum Round {
    LeastSquares,
    Huber,
    Tukey,
}

fn weight(round: Round, r: f64, scale: f64) -> f64 {
    match round {
        Round::LeastSquares => 1.0,
        Round::Huber => {
            let c = 1.345 * scale;
            if r.abs() <= c {
                1.0
            } else {
                c / r.abs()
            }
        }
        Round::Tukey => {
            let c = 4.685 * scale;
            if r.abs() >= c {
                0.0
            } else {
                let u = r / c;
                (1.0 - u * u) * (1.0 - u * u)
            }
        }
    }
}

/// Starting point of an identification: the nominal geometry, and the winding
/// physics of the nominal pulley (`r_home` = nominal radius, no growth) unless
/// a previous identification is given.
#[derive(Clone, Debug)]
pub struct Start {
    pub frame: Frame<f64>,
    pub winding: WindingPhysics,
    /// Starting close to the solution (a refit): skip the least-squares and
    /// Huber rounds, whose only job is to get near it robustly.
    pub warm: bool,
    /// Effect terms with the values to start from (a refit's): a structure
    /// term takes the value of the term at its place here when both are
    /// the same kind on the same string (the structure's values are those
    /// diagnosis proposed, before any fit; a warm start's robust weights
    /// come from the start's residuals, so its terms must be the fitted
    /// ones). A term beyond these starts from the structure's value, and
    /// the fit from a Huber round.
    pub effects: Vec<EffectTerm>,
}

impl Start {
    /// From the nominal design: the pulley radii (spool radius over the
    /// mechanical advantage: the effective radius), no growth.
    pub fn nominal(
        frame: Frame<f64>,
        effective_radius_mm: [f64; STRINGS],
        counts_per_rev: [u32; STRINGS],
        mechanical_advantage: [f64; STRINGS],
    ) -> Start {
        Start {
            frame,
            winding: WindingPhysics {
                r_home_mm: effective_radius_mm,
                kappa_mm: 0.0,
                kappa_each_mm: [0.0; STRINGS],
                counts_per_rev,
                mechanical_advantage,
                layers: [LayerTable::NONE; STRINGS],
            },
            warm: false,
            effects: Vec::new(),
        }
    }

    /// From a geometry file: its nominal frame, pulley radii, counts per
    /// revolution and mechanical advantage.
    pub fn from_geometry(geometry: &crate::data::dataset::Geometry) -> Start {
        Start::nominal(
            geometry.nominal_frame(),
            core::array::from_fn(|i| {
                geometry.pulley_radius_mm[i] / geometry.mechanical_advantage[i]
            }),
            geometry.counts_per_rev,
            geometry.mechanical_advantage,
        )
    }

    /// Continue from an earlier identification (the diagnosis loop refits).
    pub fn from_identification(id: &Identification) -> Start {
        Start {
            frame: id.frame,
            winding: id.winding,
            warm: true,
            effects: id.effects.clone(),
        }
    }
}

/// Whether `known` (a start's term) is `term` with other values: the same
/// kind on the same string (and a slip at the same time).
fn same_term(term: &EffectTerm, known: &EffectTerm) -> bool {
    term.string == known.string
        && match (&term.effect, &known.effect) {
            (Effect::Slip { at_s: a, .. }, Effect::Slip { at_s: b, .. }) => a == b,
            (a, b) => core::mem::discriminant(a) == core::mem::discriminant(b),
        }
}

/// Identifies the model of `structure` from the observations that have a
/// tracker position. `nominal` is the design geometry (the priors' centre and
/// the gauge); `start` the starting point.
pub fn identify(
    observations: &[Observation],
    nominal: &Frame<f64>,
    start: &Start,
    structure: &Structure,
) -> Result<Identification, IdentifyError> {
    let used: Vec<&Observation> = observations
        .iter()
        .filter(|o| o.tracker.is_some())
        .collect();
    let layout = Layout::new(structure);
    let needed = rows_needed(&layout, structure, nominal.layout);
    if used.len() < needed {
        return Err(IdentifyError::TooFewRows {
            needed,
            got: used.len(),
        });
    }

    let fit = Fit {
        used: &used,
        structure,
        nominal,
        layout: &layout,
        start,
    };
    let (state, weights, evaluations) = fit.robust_rounds()?;

    // Final residuals, weights and covariance.
    let strings = nominal.layout;
    let laws = state.winding.laws();
    let residuals = fit.string_residuals(&state, &laws);
    let scale = robust_scale(&residuals, strings).max(1e-6);
    let length_scale_mm = fast_residual_scales(&residuals, strings);
    let rejected = weights
        .iter()
        .flat_map(|w| strings.indices().map(|i| w[i]))
        .filter(|&w| w < 0.1)
        .count();
    let rejected_fraction = rejected as f64 / (weights.len() * strings.count()).max(1) as f64;

    // Covariance from the last round's problem at the solution, with the
    // residual scale re-estimated from the weighted residuals.
    let weighted_ss: f64 = residuals
        .iter()
        .zip(&weights)
        .flat_map(|(r, w)| r.iter().zip(w).map(|(r, w)| w * r * r))
        .sum();
    let weight_sum: f64 = weights.iter().flatten().sum();
    let sigma = (weighted_ss / (weight_sum - layout.len() as f64).max(1.0)).sqrt();
    let problem = fit.problem(&state, &weights, sigma.max(1e-6));
    let (info, _) = problem
        .normal_equations(&DVector::zeros(problem.n_rows()))
        .ok_or_else(|| IdentifyError::Diverged("Jacobian not finite at the solution".into()))?;
    let (parameters, mut warnings) = fit.estimates(&state, info);
    warnings.extend(counting_down_warnings(&laws, strings));
    Ok(Identification {
        frame: state.frame,
        winding: state.winding,
        laws,
        effects: state.effects,
        parameters,
        warnings,
        residual_scale_mm: scale,
        length_scale_mm,
        rejected_fraction,
        evaluations,
        kinematics: KinematicsRule::default(),
    })
}

/// What the steps of [`identify`] share: the observations with a tracker
/// position, the structure and its parameter layout, the design geometry
/// and the start.
struct Fit<'a> {
    used: &'a [&'a Observation],
    structure: &'a Structure,
    nominal: &'a Frame<f64>,
    layout: &'a Layout,
    start: &'a Start,
}

impl Fit<'_> {
    /// The start's state, with the structure's terms; the start's values of
    /// its leading terms that are the structure's (a refit carries them).
    /// Whether the structure gained terms beyond those.
    fn start_state(&self) -> (State, bool) {
        let mut effects = self.structure.effects.clone();
        let mut carried = 0;
        for (term, known) in effects.iter_mut().zip(&self.start.effects) {
            if !same_term(term, known) {
                break;
            }
            *term = *known;
            carried += 1;
        }
        let grown = carried < effects.len();
        let state = State {
            frame: self.start.frame,
            winding: self.start.winding,
            effects,
        };
        (state, grown)
    }

    /// `w` on the channels with a string, 0 on the others.
    fn active_weights(&self, w: [f64; STRINGS]) -> [f64; STRINGS] {
        let strings = self.nominal.layout;
        core::array::from_fn(|i| if strings.is_active(i) { w[i] } else { 0.0 })
    }

    /// String-space residuals of every used observation.
    fn string_residuals(&self, state: &State, laws: &[StringLaw; STRINGS]) -> Vec<[f64; STRINGS]> {
        self.used
            .iter()
            .map(|o| Problem::string_residuals(state, laws, o))
            .collect()
    }

    /// The LM problem at `state` with the rows' `weights` and the residual
    /// scale `residual_sd`.
    fn problem<'b>(
        &'b self,
        state: &State,
        weights: &'b [[f64; STRINGS]],
        residual_sd: f64,
    ) -> Problem<'b> {
        let base_rotation = state.frame.room_rotation;
        let x = encode(state, self.layout);
        Problem {
            observations: self.used,
            weights,
            residual_sd,
            structure: self.structure,
            nominal: self.nominal,
            layout: self.layout,
            base_rotation,
            winding_fixed: self.start.winding,
            x,
        }
    }

    /// The robust rounds from the start: each reweights the rows from the
    /// current state's residuals and refits, until the weights settle. The
    /// state, the last round's weights and the evaluations used.
    fn robust_rounds(&self) -> Result<(State, Vec<[f64; STRINGS]>, usize), IdentifyError> {
        let (mut state, grown) = self.start_state();
        let strings = self.nominal.layout;
        let mut weights = vec![self.active_weights([1.0; STRINGS]); self.used.len()];
        let mut evaluations = 0;
        let cold = [
            Round::LeastSquares,
            Round::Huber,
            Round::Tukey,
            Round::Tukey,
            Round::Tukey,
        ];
        let warm = [Round::Tukey, Round::Tukey, Round::Tukey];
        // A warm start whose structure gained a term begins with a Huber round:
        // Tukey weights from the start's residuals would give the rows the new
        // term explains (the minority side of a slip) no weight before it could
        // explain them.
        let warm_grown = [Round::Huber, Round::Tukey, Round::Tukey];
        let (rounds, settled_after): (&[Round], usize) =
            match (self.structure.robust, self.start.warm, grown) {
                (false, _, _) => (&[Round::LeastSquares], 1),
                (true, true, false) => (&warm, 1),
                (true, true, true) => (&warm_grown, 1),
                (true, false, _) => (&cold, 3),
            };
        for (n, &round) in rounds.iter().enumerate() {
            // Weights from the current state's residuals.
            let laws = state.winding.laws();
            let residuals = self.string_residuals(&state, &laws);
            let scale = robust_scale(&residuals, strings).max(1e-3);
            let new_weights: Vec<[f64; STRINGS]> = residuals
                .iter()
                .map(|r| self.active_weights(r.map(|v| weight(round, v, scale))))
                .collect();
            let changed = new_weights
                .iter()
                .flatten()
                .zip(weights.iter().flatten())
                .any(|(a, b)| (a - b).abs() > 1e-3);
            if n >= settled_after && !changed {
                break;
            }
            weights = new_weights;
            let problem = self.problem(&state, &weights, scale);
            let (problem, used_evaluations) = minimize(problem)
                .map_err(|why| IdentifyError::Diverged(format!("robust round {n}: {why}")))?;
            evaluations += used_evaluations;
            state = problem.state();
        }
        Ok((state, weights, evaluations))
    }

    /// Each free parameter's value at `state` and its posterior sd from
    /// the information matrix `info` (`J^T J` at the solution); a warning
    /// for each the data do not determine (or, failing any, for a singular
    /// information matrix).
    fn estimates(
        &self,
        state: &State,
        info: DMatrix<f64>,
    ) -> (Vec<ParameterEstimate>, Vec<String>) {
        let (layout, structure, strings) = (self.layout, self.structure, self.nominal.layout);
        // Marginal posterior variances from the eigen-decomposition of the
        // information matrix: a direction with (numerically) no information
        // makes exactly the parameters that load on it undetermined (infinite
        // sd), instead of failing the whole inverse.
        let eig = info.symmetric_eigen();
        let largest = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
        let variance = |c: usize| -> f64 {
            let mut v = 0.0;
            for k in 0..eig.eigenvalues.len() {
                let load = eig.eigenvectors[(c, k)] * eig.eigenvectors[(c, k)];
                if eig.eigenvalues[k] > 1e-12 * largest {
                    v += load / eig.eigenvalues[k];
                } else if load > 1e-6 {
                    return f64::INFINITY;
                }
            }
            v
        };
        let singular = eig.eigenvalues.iter().any(|&l| l <= 1e-12 * largest);
        let mut parameters = Vec::new();
        let mut warnings = Vec::new();
        let names = parameter_names(layout, structure, strings);
        for (c, (name, unit, prior_sd)) in names.into_iter().enumerate() {
            if !column_is_free(layout, structure, strings, c) {
                continue;
            }
            let s = layout.scale[c];
            let value = column_value(layout, state, c);
            let sd = variance(c).sqrt() * s;
            let determined = match prior_sd {
                Some(p) => sd < 0.7 * p,
                None => sd.is_finite() && sd < 10.0 * s.max(value.abs()),
            };
            if !determined {
                warnings.push(match prior_sd {
                    Some(p) => format!(
                        "{name}: the data do not determine it (posterior sd {sd:.3} {unit} vs prior sd {p:.3} {unit}); its value comes from the nominal design"
                    ),
                    None => format!("{name}: the data do not determine it (sd {sd:.3e} {unit})"),
                });
            }
            parameters.push(ParameterEstimate {
                name,
                unit: unit.to_string(),
                value,
                sd,
                prior_sd,
                determined,
            });
        }
        if singular && warnings.is_empty() {
            warnings.push(
                "the information matrix is singular: some parameters are not determined by the data"
                    .into(),
            );
        }
        (parameters, warnings)
    }
}

/// A string whose identified winding radius at home is negative: its
/// encoder counts down as the string pays out (wired or mounted the other
/// way from the geometry's convention). The identification follows it (the
/// radius is free to change sign) and so does the calibration the device
/// reads; the nominal geometry (the raw stage) does not, which is why that
/// stage's error is large. A Hangprinter session with one string's counts
/// negated calibrated to 2.686 mm (2.689 as recorded) and said nothing.
fn counting_down_warnings(laws: &[StringLaw; STRINGS], strings: StringLayout) -> Vec<String> {
    strings
        .indices()
        .filter(|&i| laws[i].winding_mm[0] < 0.0)
        .map(|i| {
            format!(
                "string {i}: its counts fall as its string pays out (identified winding radius at \
                 home {:.3} mm): its encoder counts the other way from the geometry's convention; \
                 the calibration carries the sign, the nominal geometry (the raw stage) does not",
                laws[i].winding_mm[0]
            )
        })
        .collect()
}

/// The physical value of column `c` at `state`.
fn column_value(layout: &Layout, state: &State, c: usize) -> f64 {
    match c {
        _ if c < HOME => state.frame.anchors[(c - ANCHORS) / 3][(c - ANCHORS) % 3],
        _ if c < ROTATION => state.frame.home[c - HOME],
        _ if c < TRANSLATION => vector_from_rotation(&state.frame.room_rotation)[c - ROTATION],
        _ if c < SCALE => state.frame.room_translation[c - TRANSLATION],
        _ if layout.fit_scale && c == SCALE => state.frame.room_scale,
        _ if c >= layout.r_home() && c < layout.kappa() => {
            state.winding.r_home_mm[c - layout.r_home()]
        }
        _ if c == layout.kappa() => state.winding.kappa_mm,
        _ if c >= layout.kappa_each() && c < layout.first_effect() => {
            state.winding.kappa_each_mm[c - layout.kappa_each()]
        }
        _ => {
            let (e, p) = layout.effect_columns[c - layout.first_effect()];
            state.effects[e].effect.parameters()[p]
        }
    }
}

/// Whether column `c` is a parameter of the device (not a channel without a
/// string, nor a coordinate a planar device holds).
fn column_is_free(layout: &Layout, structure: &Structure, strings: StringLayout, c: usize) -> bool {
    let planar = strings.planar;
    match c {
        _ if c < HOME => {
            strings.is_active((c - ANCHORS) / 3) && !(planar && (c - ANCHORS) % 3 == 2)
        }
        _ if c < ROTATION => !(planar && c == HOME + 2),
        _ if c < TRANSLATION => !(planar && c < ROTATION + 2),
        _ if c < SCALE => !(planar && c == TRANSLATION + 2),
        _ if c >= layout.r_home() && c < layout.kappa() => strings.is_active(c - layout.r_home()),
        _ if c >= layout.kappa_each() && c < layout.first_effect() => {
            !structure.hold_kappa_each && strings.is_active(c - layout.kappa_each())
        }
        _ if c >= layout.first_effect() => {
            let (e, _) = layout.effect_columns[c - layout.first_effect()];
            let string = structure.effects[e].string;
            string == EVERY_STRING || strings.is_active(usize::from(string))
        }
        _ => true,
    }
}

/// Fewest tracked rows an identification of `structure` takes: twice as
/// many string residuals as free parameters (so that the residual scale
/// and the robust weights mean something), and never fewer than 10 rows.
/// An 8-string device's base model (36 free parameters once the gauge is
/// fixed) needs 10 rows, a 4-string one's (20) needs 10, a 3-string one's
/// (17) needs 12; with each spool's own thinning rate free, 11, 12 and 12.
pub fn rows_needed_for(structure: &Structure, strings: StringLayout) -> usize {
    rows_needed(&Layout::new(structure), structure, strings)
}

fn rows_needed(layout: &Layout, structure: &Structure, strings: StringLayout) -> usize {
    let free = (0..layout.len())
        .filter(|&c| column_is_free(layout, structure, strings, c))
        .count();
    // The frame's gauge, and the spools' own thinning rates' mean.
    let gauge = if strings.planar { 3 } else { 6 } + usize::from(!structure.hold_kappa_each);
    let free = free.saturating_sub(gauge);
    let per_row = strings.count().max(1);
    (2 * free).div_ceil(per_row).max(10)
}

fn parameter_names(
    layout: &Layout,
    structure: &Structure,
    strings: StringLayout,
) -> Vec<(String, &'static str, Option<f64>)> {
    let p = &structure.priors;
    let mut names = Vec::new();
    for i in 0..STRINGS {
        let sd = anchor_prior_sd(structure, strings, i);
        for c in ["x", "y", "z"] {
            names.push((format!("anchor{i}.{c}"), "mm", Some(sd)));
        }
    }
    for c in ["x", "y", "z"] {
        names.push((format!("home.{c}"), "mm", Some(p.home_sd_mm)));
    }
    for c in ["x", "y", "z"] {
        names.push((format!("room_rotation.{c}"), "rad", Some(p.rotation_sd_rad)));
    }
    for c in ["x", "y", "z"] {
        names.push((
            format!("room_translation.{c}"),
            "mm",
            Some(p.translation_sd_mm),
        ));
    }
    if layout.fit_scale {
        names.push(("room_scale".into(), "1", None));
    }
    for i in 0..STRINGS {
        names.push((format!("string{i}.r_home"), "mm", None));
    }
    names.push(("winding.kappa".into(), "mm/rad^2", None));
    for i in 0..STRINGS {
        names.push((
            format!("string{i}.kappa_each"),
            "mm/rad^2",
            Some(p.kappa_each_sd_mm),
        ));
    }
    for term in &structure.effects {
        for (k, (pname, _, unit)) in effect_parameter_info(&term.effect).iter().enumerate() {
            let owner = if term.string == EVERY_STRING {
                "every_string".to_string()
            } else {
                format!("string{}", term.string)
            };
            let prior = effect_prior(&term.effect, k, p).map(|(_, sd)| sd);
            names.push((format!("{owner}.{pname}"), *unit, prior));
        }
    }
    names
}

/// String-space residuals (geometric minus model, mm) of every observation
/// with a tracker position under an identified model; `None` for occluded rows.
pub fn string_residuals(
    frame: &Frame<f64>,
    laws: &[StringLaw; STRINGS],
    effects: &[EffectTerm],
    observations: &[Observation],
) -> Vec<Option<[f64; STRINGS]>> {
    observations
        .iter()
        .map(|o| {
            o.tracker?;
            Some(residuals_at(frame, laws, effects, o))
        })
        .collect()
}

/// String residuals larger than this (mm) are gross failures (a string off
/// its pulley, a jammed motor), not calibration effects: diagnosis leaves them
/// out. Everything smaller stays in, even what the robust fit down-weighted:
/// a systematic effect the model lacks (a slip, say) looks like outliers to
/// the fit, and diagnosis must see it to name it.
pub const GROSS_RESIDUAL_MM: f64 = 25.0;

/// The weighted Jacobian of the string-space residuals at an identified
/// solution (rows `k * STRINGS + i` for the k-th observation with a tracker
/// position and string i; weight 1, or 0 for residuals beyond
/// [`GROSS_RESIDUAL_MM`]; prior rows left out), the matching weighted
/// residuals, and the weights. Diagnosis projects candidate effects on the
/// complement of its columns: what the current model can already absorb is
/// not evidence of an effect.
pub fn data_jacobian(
    id: &Identification,
    observations: &[Observation],
    nominal: &Frame<f64>,
    structure: &Structure,
) -> Option<DataJacobian> {
    let used: Vec<&Observation> = observations
        .iter()
        .filter(|o| o.tracker.is_some())
        .collect();
    let layout = Layout::new(structure);
    let state = State {
        frame: id.frame,
        winding: id.winding,
        effects: id.effects.clone(),
    };
    let laws = state.winding.laws();
    let weights: Vec<[f64; STRINGS]> = used
        .iter()
        .map(|o| {
            let r = Problem::string_residuals(&state, &laws, o);
            core::array::from_fn(|i| {
                if nominal.layout.is_active(i) && r[i].abs() <= GROSS_RESIDUAL_MM {
                    1.0
                } else {
                    0.0
                }
            })
        })
        .collect();
    let problem = Problem {
        observations: &used,
        weights: &weights,
        residual_sd: 1.0,
        structure,
        nominal,
        layout: &layout,
        base_rotation: state.frame.room_rotation,
        winding_fixed: state.winding,
        x: encode(&state, &layout),
    };
    use levenberg_marquardt::LeastSquaresProblem;
    let jac = problem.jacobian()?;
    let residuals = problem.residuals()?;
    let rows = used.len() * STRINGS;
    Some(DataJacobian {
        jacobian: jac.rows(0, rows).into_owned(),
        residuals: residuals.rows(0, rows).into_owned(),
        weights,
    })
}

/// See [`data_jacobian`].
pub struct DataJacobian {
    /// Weighted Jacobian of the string residuals (scaled parameters).
    pub jacobian: DMatrix<f64>,
    /// Weighted string residuals, mm.
    pub residuals: DVector<f64>,
    /// Per observation with a tracker position, per string: 1 or 0 (gross).
    pub weights: Vec<[f64; STRINGS]>,
}
