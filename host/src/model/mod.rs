//! The calibration model (`../shared/notes/model-spine.md`) and what fits it.
//!
//! - [`predict`]: a model's room positions through the device pipeline (f64);
//! - [`identify`]: the kinematic identification (anchors, home, winding laws,
//!   effects) by Levenberg-Marquardt;
//! - [`diagnose`]: the loop that finds what the model still misses in the
//!   residual, traces it to an effect and adds it when validation agrees;
//! - [`layers`]: each spool's layer table in the string law;
//! - [`validate`]: held-out validation (folds blocked in time and space)
//!   and the verdict on a change, which the loop and the layer tables use;
//! - `normal`: the identification's normal equations, summed from the
//!   Jacobian's block-arrow rows without forming it;
//! - [`learn`]: model-less corrections (NN, SVR) and their searches;
//! - [`rule`]: the forward kinematics' rule (faulty-string exclusion,
//!   thresholds, weights) chosen on held-out folds;
//! - [`tolerance`]: how far the anchors may be from the drawing, chosen
//!   on held-out rows;
//! - [`mod@reference`]: the plain least-squares reference every calibration is
//!   held to;
//! - [`compile`]: the model compiled to the device's fixed-point blob, with
//!   its error against f64.

pub mod compile;
pub mod diagnose;
pub mod identify;
pub mod layers;
pub mod learn;
pub(crate) mod normal;
pub mod predict;
pub mod reference;
pub mod rule;
pub mod tolerance;
pub mod validate;
