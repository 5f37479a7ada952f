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
//! ([`Structure::hold_kappa_each`]): spools of other widths need them, but
//! a short session that fits them unconditionally over-fits them (its
//! held-out error rises; decision record 0017,
//! `docs/decisions/0017-spool-thinning-rates.md`). With them free, a payout
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
//!
//! ## Where each part lives
//! - `structure`: what the fit frees ([`Structure`]) and the priors it holds
//!   the rest by ([`Priors`]);
//! - `winding`: the strings' winding laws ([`WindingPhysics`]);
//! - `start`: where a fit starts ([`Start`]);
//! - `result`: what it gives ([`Identification`], [`IdentifyError`]);
//! - `residuals`: the string-space residual of one row;
//! - `layout`: the parameter vector (its columns, their scales and names);
//! - `problem`: one robust round's least-squares problem; `prior_rows` its
//!   prior and gauge rows; `jacobian` its Jacobian, summed into the normal
//!   equations, and the data Jacobian diagnosis projects on;
//! - `solver`: Levenberg-Marquardt on the normal equations;
//! - `robust`: the robust rounds' weights and scales;
//! - `fit`: the rounds of one identification; `estimates` the parameters'
//!   uncertainties and the warnings.

// Vector algebra indexes several 3-vectors by the same axis; index loops read best.
#![allow(clippy::needless_range_loop)]

mod estimates;
mod fit;
mod jacobian;
mod layout;
mod prior_rows;
mod problem;
mod residuals;
mod result;
mod robust;
mod solver;
mod start;
mod structure;
#[cfg(test)]
mod tests;
mod winding;

use std::borrow::Borrow;

use nalgebra::DVector;
use spidar_core::kinematics::KinematicsRule;
use spidar_core::model::{Frame, StringLayout};

use crate::data::observe::Observation;

pub use jacobian::{DataJacobian, DataJacobianPass};
pub use layout::effect_parameter_names;
pub(crate) use residuals::residuals_at_homes;
pub use residuals::{device_position, inputs_at, string_residuals, GROSS_RESIDUAL_MM};
pub use result::{
    radius_string, value_with_sd, xyz_stem, Identification, IdentifyError, ParameterEstimate,
};
pub use start::Start;
pub use structure::{effect_parameter_info, Priors, Structure, KAPPA_EACH_SD_MM};
pub use winding::WindingPhysics;

use estimates::counting_down_warnings;
use fit::Fit;
use layout::{rows_needed, Layout};
use robust::{fast_residual_scales, robust_scale};

/// Identifies the model of `structure` from the observations that have a
/// tracker position (held, or referred to: a fold's rows are the session's). `nominal` is the design geometry (the priors' centre and
/// the gauge); `start` the starting point.
pub fn identify<O: Borrow<Observation>>(
    observations: &[O],
    nominal: &Frame<f64>,
    start: &Start,
    structure: &Structure,
) -> Result<Identification, IdentifyError> {
    let used: Vec<&Observation> = observations
        .iter()
        .map(Borrow::borrow)
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
        spare: Default::default(),
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

/// Fewest tracked rows an identification of `structure` takes: twice as
/// many string residuals as free parameters (so that the residual scale
/// and the robust weights mean something), and never fewer than 10 rows.
/// An 8-string device's base model (36 free parameters once the gauge is
/// fixed) needs 10 rows, a 4-string one's (20) needs 10, a 3-string one's
/// (17) needs 12; with each spool's own thinning rate free, 11, 12 and 12.
pub fn rows_needed_for(structure: &Structure, strings: StringLayout) -> usize {
    rows_needed(&Layout::new(structure), structure, strings)
}
