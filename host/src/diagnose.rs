//! Closing the loop: find what the identified model still misses in the
//! residual, trace it to a physical effect, add the effect, refit, and keep it
//! only if it helps on data it was not fitted on.

use serde::{Deserialize, Serialize};
use spidar_core::model::{EffectTerm, Frame};

use crate::identify::{identify, Identification, IdentifyError, Start, Structure};
use crate::observe::Observation;
use crate::predict::{paired_with_tracker, predict, StringModel};
use crate::stats::{position_errors, ErrorStats};

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
    Slip,
    Geometry,
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
}

/// A structural change to the model that a finding proposes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Change {
    /// Add an effect term (its parameters are refitted).
    Effect(EffectTerm),
    /// Free the tracker's scale relative to the device.
    RoomScale,
}

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
    /// A step is kept only if the held-out error falls by this fraction.
    pub min_relative_gain: f64,
}

impl Default for LoopConfig {
    fn default() -> Self {
        LoopConfig {
            max_effects: 8,
            chi2_threshold: 40.0,
            min_relative_gain: 0.02,
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
    /// Held-out (cross-validated) mean error before and after, mm.
    pub validation_before_mm: f64,
    pub validation_after_mm: f64,
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
}

/// Position errors of an identified string model against the tracker.
pub fn model_errors(id: &Identification, observations: &[Observation]) -> ErrorStats {
    let predictions = predict(
        StringModel {
            frame: &id.frame,
            laws: &id.laws,
            effects: &id.effects,
        },
        observations,
    );
    let room: Vec<[f64; 3]> = predictions.iter().map(|p| p.room).collect();
    let (p, t) = paired_with_tracker(&room, observations);
    ErrorStats::of(&position_errors(&p, &t))
}

/// Runs the loop: identify, diagnose, add the strongest significant effect,
/// refit, repeat until nothing significant that helps remains.
pub fn close_loop(
    train: &[Observation],
    test: Option<&[Observation]>,
    nominal: &Frame<f64>,
    start: &Start,
    _config: &LoopConfig,
) -> Result<LoopResult, IdentifyError> {
    let structure = Structure::default();
    let base = identify(train, nominal, start, &structure)?;
    let base_train = model_errors(&base, train);
    let base_test = test.map(|t| model_errors(&base, t));
    Ok(LoopResult {
        identification: base.clone(),
        base,
        base_train,
        base_test,
        structure,
        stages: Vec::new(),
        findings: Vec::new(),
    })
}
