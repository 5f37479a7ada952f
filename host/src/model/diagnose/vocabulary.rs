//! The loop's vocabulary: the effect families and residual variables
//! findings are named by, the changes they propose, the findings, the
//! loop's settings, and what the loop reports (its stages and result).

use serde::{Deserialize, Serialize};
use spidar_core::model::{Effect, EffectTerm};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::data::stats::ErrorStats;
use crate::model::identify::{Identification, Structure};
use crate::model::layers::StringLayers;
use crate::model::validate::{later_session_errors, model_errors, Check};

use super::outliers::TrackerOutliers;

/// Effect families (the JSON report's `family`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Family {
    Offset,
    Scale,
    Winding,
    Eccentricity,
    Elasticity,
    Backlash,
    Drift,
    /// A string's natural length growing by a share of itself with time
    /// since home (thermal creep, [`Effect::Creep`]).
    Creep,
    Slip,
    /// A heavy string's sag, `l^3 / T^2` ([`Effect::Sag`]).
    Sag,
    /// The guides moving with the strings' total pull ([`Effect::FrameFlex`]).
    FrameFlex,
    /// An encoder read late: the string's speed times the delay
    /// ([`Effect::Latency`]); tested only where the rows observe the speed
    /// (a stream).
    Latency,
    /// A guide pulley swivelling toward the end-effector: the string wraps
    /// on it by its elevation from the swivel axis ([`Effect::Guide`]).
    Guide,
    /// Layer tables ([`crate::model::layers`]): the spool's departure from the
    /// smooth winding law, per string.
    Layers,
    Geometry,
    /// The tracked body's origin off the strings' meeting point, seen
    /// through the tracker's orientation ([`Change::MarkerOffset`]).
    Marker,
    Unexplained,
}

/// Variables a residual is tested against (the JSON report's `variable`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Variable {
    Position,
    Length,
    WoundLength,
    PulleyAngle,
    Tension,
    Direction,
    Speed,
    Time,
    Order,
    /// The tracked body's orientation.
    Orientation,
    /// A string's elevation from its guide's swivel axis (the frame edge).
    Elevation,
}

/// A structural change to the model that a finding proposes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Change {
    /// Add an effect term (its parameters are refitted).
    Effect(EffectTerm),
    /// Free the tracker's scale relative to the device.
    RoomScale,
    /// Release an anchor from its design tolerance (it was built elsewhere).
    ReleaseAnchor(u8),
    /// Read the tracker at the strings' meeting point, the tracked body's
    /// origin being this far from it (body frame, mm;
    /// [`Structure::marker_body_mm`]).
    MarkerOffset([f64; 3]),
    /// Add a slip on each of several strings at once (`(at_s, mm)` per
    /// encoder index, `None`: no slip): several strings that slipped
    /// during one session, none of whose steps helps alone while the others
    /// are missing (`slips_together`, tried when no single change helps).
    Slips([Option<(f64, f64)>; STRINGS]),
    /// Add a drift on each of several strings at once, each its own rate
    /// (mm/s per encoder index, `None`: no drift): strings that drift at
    /// different rates, whose terms added one at a time each take the
    /// others' share of what time and position share on a lattice.
    Drifts([Option<f64>; STRINGS]),
    /// Add a latency on each of several strings at once (s per encoder
    /// index, `None`: none): strings that lag, none of whose latencies
    /// helps alone while the others are missing (`latencies_together`,
    /// tried when no single change helps).
    Latencies([Option<f64>; STRINGS]),
    /// Add a stretch on each of several strings at once, each its own
    /// (`per_newton`, `mm_per_newton`) (strings of other stiffness and
    /// leads), all from one home tension ([`Effect::Stretch`]).
    Stretches([Option<(f64, f64)>; STRINGS], f64),
}

impl Change {
    /// The effect terms the change adds to the structure, in the order it
    /// adds them (a slip or a drift on each of several strings in encoder
    /// order); none for a change of the geometry or the tracked body.
    pub fn effect_terms(&self) -> Vec<EffectTerm> {
        let each = |effect: &dyn Fn(usize) -> Option<Effect>| {
            (0..STRINGS)
                .filter_map(|i| {
                    effect(i).map(|effect| EffectTerm {
                        string: i as u8,
                        effect,
                    })
                })
                .collect()
        };
        match *self {
            Change::Effect(term) => vec![term],
            Change::Slips(slips) => each(&|i| slips[i].map(|(at_s, mm)| Effect::Slip { at_s, mm })),
            Change::Drifts(drifts) => {
                each(&|i| drifts[i].map(|mm_per_s| Effect::Drift { mm_per_s }))
            }
            Change::Latencies(lags) => {
                each(&|i| lags[i].map(|latency_s| Effect::Latency { latency_s }))
            }
            Change::Stretches(each_string, home_tension_n) => each(&|i| {
                each_string[i].map(|(per_newton, mm_per_newton)| Effect::Stretch {
                    per_newton,
                    mm_per_newton,
                    home_tension_n,
                })
            }),
            Change::RoomScale | Change::ReleaseAnchor(_) | Change::MarkerOffset(_) => Vec::new(),
        }
    }
}

impl Structure {
    /// This structure with `change` applied.
    pub fn with(&self, change: Change) -> Structure {
        let mut s = self.clone();
        s.effects.extend(change.effect_terms());
        match change {
            Change::RoomScale => s.fit_room_scale = true,
            Change::ReleaseAnchor(i) => {
                if let Some(sd) = s.anchor_sd_override_mm.get_mut(i as usize) {
                    *sd = Some(RELEASED_ANCHOR_SD_MM);
                }
            }
            Change::MarkerOffset(d) => s.marker_body_mm = Some(d),
            Change::Effect(_)
            | Change::Slips(_)
            | Change::Drifts(_)
            | Change::Latencies(_)
            | Change::Stretches(..) => {}
        }
        s
    }
}

/// Prior sd (mm) of an anchor the geometry family released.
pub const RELEASED_ANCHOR_SD_MM: f64 = 1000.0;

/// One thing diagnosis found in the residual.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Finding {
    pub family: Family,
    /// Encoder indices; empty for a frame-wide effect.
    pub strings: Vec<u8>,
    pub variable: Variable,
    /// Largest contribution of the effect over the data, mm.
    pub amplitude_mm: f64,
    /// Share of the string-space residual sum of squares it explains.
    pub explained: f64,
    /// Whether the loop added it to the model.
    pub added: bool,
    /// Test statistic (chi-square with the effect's degrees of freedom).
    pub chi2: f64,
    /// One line for people.
    pub description: String,
    /// The held-out check that decided `added` (figures before and after the
    /// change, and why); `None` for findings the loop did not test
    /// (unexplained structure).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validation: Option<Check>,
    /// What adding it means; `None` for unexplained structure.
    #[serde(skip)]
    pub change: Option<Change>,
}

/// Settings of the loop.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct LoopConfig {
    /// At most this many effects are added.
    pub max_effects: usize,
    /// A candidate is significant when its chi-square exceeds this (after
    /// accounting for the number of candidates tested).
    pub chi2_threshold: f64,
    /// A step is kept only if the held-out error (blocked folds, see
    /// [`validate`](crate::model::validate::validate())) falls by this
    /// fraction. 2 %: the terms a lower bar adds gain 0.5 to 2 % each and
    /// leave the held-out error where it was, and every injected family of
    /// the model simulator is still found (`loop_bench`).
    pub min_relative_gain: f64,
    /// What a term on one string (not a slip: a step has its own test, that
    /// the residual jumps where it slipped) must gain instead of
    /// `min_relative_gain`. The loop searches a family on each string, and
    /// the best of some fifty per-string terms gains 2 to 3 % on a clean
    /// independent device by standing in for what no family has; a shared
    /// term or a table is one candidate. 3.5 %: every injected family of
    /// the model simulator is still found (`loop_bench`;
    /// decision record 0032, `docs/decisions/0032-one-string-term-gain.md`).
    #[serde(default = "one_string_gain")]
    pub min_relative_gain_one_string: f64,
    /// Try layer tables ([`crate::model::layers`]) before the effect families.
    #[serde(default = "yes")]
    pub layer_tables: bool,
    /// The tension the strings held at the home capture, when the device's
    /// geometry declares it ([`crate::data::dataset::Geometry::home_tension_n`]):
    /// the stretch's home tension is then fitted around it instead of the
    /// firmware's default 1 N (within 1 N either way: in a narrower range
    /// the stretch can no longer take the length every string's home
    /// shares; decision record 0028,
    /// `docs/decisions/0028-home-tension-declared.md`).
    #[serde(default)]
    pub home_tension_n: Option<f64>,
    /// Look for effects at all: false stops after the base identification
    /// (a session too small to judge a change on held-out folds).
    #[serde(default = "yes")]
    pub diagnose: bool,
    /// The anchors' and home's tolerances the geometry declares
    /// ([`crate::data::dataset::Geometry::anchor_sd_mm`], `home_sd_mm`),
    /// the identification's priors; `None`: [`crate::model::identify::Priors::default`]'s.
    #[serde(default)]
    pub anchor_sd_mm: Option<[f64; STRINGS]>,
    #[serde(default)]
    pub home_sd_mm: Option<f64>,
    /// Reweigh the rows robustly ([`Structure::robust`]).
    #[serde(default = "yes")]
    pub robust: bool,
    /// A drift must also predict forward: fitted on the earlier rows, it
    /// may not predict the later ones worse than the model without it
    /// ([`crate::model::validate::validate_forward`]). Off only to measure
    /// what the rule does (`physics_bench`).
    #[serde(default = "yes")]
    pub time_terms_forward: bool,
    /// Where the model took spool rates or layer tables and kept no term
    /// on time, try the terms on time first, from the base model, then the
    /// rates, the tables and the effects; the model of the order that
    /// gains on the blocked folds is kept (`order`, decision record 0057).
    /// Off only to measure what it does (`physics_bench`).
    #[serde(default = "yes")]
    pub time_terms_before_tables: bool,
    /// When a backlash or a latency was refused on a string that took a
    /// layer table, try the terms that follow the strings' motion first,
    /// from the base model, and keep the order the blocked folds prefer
    /// (`order`, decision record 0070). Off only to measure what it does.
    #[serde(default = "yes")]
    pub motion_terms_before_tables: bool,
    /// Offer a stretch of each string, each its own stiffness and lead
    /// ([`Change::Stretches`], decision record 0061). Off only to measure
    /// what it does (`loop_bench`) and to keep the cases of the rules made
    /// before it (record 0057's test).
    #[serde(default = "yes")]
    pub stretches_of_each_string: bool,
    /// The tracker's clock was found from these rows (a stream's
    /// alignment, `procedures::calibrate::align`). A latency shared by
    /// every string reads each string `tau` late, and a tracker clock
    /// `tau` off pairs each row with the marker `tau` away: the same
    /// change of every row. The alignment fitted the clock's offset with a
    /// quick model (no latency of one string), so a shared latency found
    /// after one string's is that offset refined, and the report says so;
    /// one string's latency is its lag behind the others.
    #[serde(default)]
    pub clock_aligned: bool,
}

impl LoopConfig {
    /// The defaults with what `geometry` declares (the home tension).
    pub fn for_geometry(geometry: &crate::data::dataset::Geometry) -> LoopConfig {
        LoopConfig::default().with_geometry(geometry)
    }

    /// These settings with what `geometry` declares (the home tension, the
    /// anchors' and home's tolerances) where it declares it.
    pub fn with_geometry(&self, geometry: &crate::data::dataset::Geometry) -> LoopConfig {
        LoopConfig {
            home_tension_n: geometry.home_tension_n.or(self.home_tension_n),
            anchor_sd_mm: geometry.anchor_sd_mm.or(self.anchor_sd_mm),
            home_sd_mm: geometry.home_sd_mm.or(self.home_sd_mm),
            ..*self
        }
    }

    /// The base model's structure these settings give: the priors the
    /// geometry declares.
    pub fn base_structure(&self) -> Structure {
        let mut structure = Structure::default();
        if let Some(t) = self.home_tension_n {
            structure.priors.home_tension_n = t;
        }
        if let Some(sd) = self.home_sd_mm {
            structure.priors.home_sd_mm = sd;
        }
        structure.priors.anchor_sd_each_mm = self.anchor_sd_mm;
        structure.robust = self.robust;
        structure
    }
}

fn yes() -> bool {
    true
}

fn one_string_gain() -> f64 {
    0.035
}

impl Default for LoopConfig {
    fn default() -> Self {
        LoopConfig {
            max_effects: 8,
            chi2_threshold: 40.0,
            min_relative_gain: 0.02,
            min_relative_gain_one_string: one_string_gain(),
            layer_tables: true,
            home_tension_n: None,
            diagnose: true,
            anchor_sd_mm: None,
            home_sd_mm: None,
            robust: true,
            time_terms_forward: true,
            time_terms_before_tables: true,
            motion_terms_before_tables: true,
            stretches_of_each_string: true,
            clock_aligned: false,
        }
    }
}

/// One added effect, with the error before and after.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LoopStage {
    /// Named after the effect, e.g. "offset string 3".
    pub name: String,
    pub finding: Finding,
    /// Position error against the tracker after adding the effect.
    pub train: ErrorStats,
    pub test: Option<ErrorStats>,
    /// Held-out mean error (blocked folds, [`Validation::held`](crate::model::validate::Validation::held); a slip's:
    /// [`Validation::for_step`](crate::model::validate::Validation::for_step)) before and after, mm.
    pub validation_before_mm: f64,
    pub validation_after_mm: f64,
}

impl LoopStage {
    /// The stage `name` of an accepted `finding`: the refit's errors on the
    /// training (and test) sessions and the held-out means its check judged
    /// (an accepted finding carries its check).
    pub(super) fn of(
        name: String,
        finding: &Finding,
        refit: &Identification,
        train: &[Observation],
        test: Option<&[Observation]>,
    ) -> LoopStage {
        let (validation_before_mm, validation_after_mm) = finding
            .validation
            .as_ref()
            .map_or((f64::NAN, f64::NAN), |c| {
                (c.before.held.mean_mm, c.after.held.mean_mm)
            });
        LoopStage {
            name,
            train: model_errors(refit, train),
            // The test session's rows after a new home capture are
            // without the training session's slips.
            test: test.map(|t| later_session_errors(refit, t)),
            finding: finding.clone(),
            validation_before_mm,
            validation_after_mm,
        }
    }
}

/// What the loop did.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LoopResult {
    /// The base identification (before any effect).
    pub base: Identification,
    pub base_train: ErrorStats,
    pub base_test: Option<ErrorStats>,
    /// The final identification (with the added effects).
    pub identification: Identification,
    pub structure: Structure,
    /// One stage per added effect, in order.
    pub stages: Vec<LoopStage>,
    /// Everything diagnosis reported: added effects, significant candidates
    /// that did not help on held-out data, and unexplained structure.
    pub findings: Vec<Finding>,
    /// The layer-table spacing chosen for each active string (before the
    /// position-space check; see the `layers` finding for whether the
    /// tables were kept).
    #[serde(default)]
    pub layers: Vec<StringLayers>,
    /// Training rows whose tracker the loop set aside (their errors in
    /// `base_train` and the stages are those of the rows left).
    #[serde(default)]
    pub tracker_outliers: TrackerOutliers,
    /// Each string's structure that follows speed and no term reads,
    /// counted once more in its scale (`identification.length_scale_mm`
    /// holds it), mm; 0 where none. The kinematics' rule keeps it or not
    /// on the held-out folds ([`crate::model::rule::choose`]).
    #[serde(default)]
    pub speed_counted_again_mm: [f64; STRINGS],
}
