//! Position errors of a model on tracked rows: as the device solves them
//! (the reports' figures) and as the loop's judge does (held out).

use std::borrow::Borrow;

use spidar_core::kinematics::{FkConfig, FkStatus};

use crate::data::observe::{rows_under_the_training_home, Observation};
use crate::data::stats::{position_errors, ErrorStats};
use crate::model::identify::Identification;
use crate::model::predict::{
    paired_with_tracker, predict, predict_with, KinematicModel, Prediction, UNMEASURED_SCALES,
};

/// Forward kinematics of `id` on a later session's rows ([`predict`]): a
/// row that follows a new home capture ([`Observation::new_home`]) is read
/// without the training session's slips
/// ([`Identification::for_a_new_session`]), the rows before it with them.
/// The rows after a new home capture are the session's last (a home
/// capture is not undone).
pub fn predict_later(id: &Identification, observations: &[Observation]) -> Vec<Prediction> {
    let k = rows_under_the_training_home(observations);
    let mut predictions = predict(id.kinematic_model(), &observations[..k]);
    if k < observations.len() {
        let new_home = id.for_a_new_session();
        predictions.extend(predict(new_home.kinematic_model(), &observations[k..]));
    }
    predictions
}

/// [`model_errors`] on a later session's rows, each read with the slips
/// of its home capture ([`predict_later`]).
pub fn later_session_errors(id: &Identification, observations: &[Observation]) -> ErrorStats {
    let room: Vec<[f64; 3]> = predict_later(id, observations)
        .iter()
        .map(|p| p.room)
        .collect();
    let (p, t) = paired_with_tracker(&room, observations);
    ErrorStats::of(&position_errors(&p, &t))
}

/// Position errors of an identified string model against the tracker.
pub fn model_errors(id: &Identification, observations: &[Observation]) -> ErrorStats {
    ErrorStats::of(&model_error_list(id, observations))
}

/// Position errors (eq. 7) of an identified model on the tracked rows, the
/// kinematics as the device solves them (the strings weighed by their
/// measured scales).
fn model_error_list(id: &Identification, observations: &[Observation]) -> Vec<f64> {
    error_list(
        id.kinematic_model(),
        observations,
        &id.kinematics.apply(&FkConfig::default()),
    )
}

/// Held-out position errors by which the loop judges a change: the
/// kinematics look for a faulty string only once the strings are
/// inconsistent ([`FkConfig::fault_threshold_mm`]), not from the device's
/// tighter [`FkConfig::exclusion_threshold_mm`]. A string a missing effect
/// puts a few mm off (the rows before an early slip) is what the loop is
/// looking for; leaving it out of the position hides it, and the loop then
/// takes terms of other families in its stead (decision record 0030,
/// `docs/decisions/0030-faulty-string-from-1mm.md`).
///
/// For the same reason every string weighs alike here, not by its measured
/// scale as on the device: a missing effect raises its string's scale, and
/// weighed by it the string hides the effect from the judge, which then
/// loses slips and takes stand-ins (decision record 0036,
/// `docs/decisions/0036-strings-weighed-by-scale.md`).
pub(crate) fn held_out_error_list<O: Borrow<Observation>>(
    id: &Identification,
    observations: &[O],
) -> Vec<f64> {
    held_out_errors(id, observations).0
}

/// [`held_out_error_list`] and, row by row, whether the kinematics found
/// the row's strings inconsistent ([`FkStatus::Inconsistent`]).
pub(super) fn held_out_errors<O: Borrow<Observation>>(
    id: &Identification,
    observations: &[O],
) -> (Vec<f64>, Vec<bool>) {
    let judging = FkConfig::<f64>::default();
    let judging = FkConfig {
        exclusion_threshold_mm: judging.fault_threshold_mm,
        ..judging
    };
    let unweighted = KinematicModel {
        length_scale_mm: &UNMEASURED_SCALES,
        ..id.kinematic_model()
    };
    errors_and_inconsistency(unweighted, observations, &judging)
}

fn error_list(
    model: KinematicModel<'_>,
    observations: &[Observation],
    fk: &FkConfig<f64>,
) -> Vec<f64> {
    errors_and_inconsistency(model, observations, fk).0
}

/// Position errors of `model` on the tracked rows and, row by row, whether
/// the kinematics found the row's strings inconsistent.
fn errors_and_inconsistency<O: Borrow<Observation>>(
    model: KinematicModel<'_>,
    observations: &[O],
    fk: &FkConfig<f64>,
) -> (Vec<f64>, Vec<bool>) {
    let predictions = predict_with(model, observations, fk);
    let inconsistent = predictions
        .iter()
        .zip(observations)
        .filter(|(_, o)| Borrow::<Observation>::borrow(*o).tracker.is_some())
        .map(|(p, _)| p.status == FkStatus::Inconsistent)
        .collect();
    let room: Vec<[f64; 3]> = predictions.iter().map(|p| p.room).collect();
    let (p, t) = paired_with_tracker(&room, observations);
    (position_errors(&p, &t), inconsistent)
}

/// How many independent rows `errors` (at least 2 of them) are worth:
/// `n (1 - rho) / (1 + rho)`, `rho` the correlation of each error with the
/// next (the effective sample size of a first-order autoregressive
/// series), at least 2. Errors in session order are correlated where
/// neighbouring rows see nearly the same pose: a 100 Hz stream's (`rho`
/// 0.7-0.8 on the independent simulator's 60 s streams), a lattice's
/// walked plane by plane (0.2-0.65); errors in no order give `rho` near 0
/// and count as `n`. A negative `rho` counts as 0.
pub(crate) fn independent_rows(errors: &[f64]) -> f64 {
    let n = errors.len() as f64;
    let mean = errors.iter().sum::<f64>() / n;
    let var: f64 = errors.iter().map(|e| (e - mean) * (e - mean)).sum();
    if var <= 0.0 || errors.len() < 3 {
        return n;
    }
    let cov: f64 = errors
        .windows(2)
        .map(|w| (w[0] - mean) * (w[1] - mean))
        .sum();
    let rho = (cov / var).clamp(0.0, 1.0);
    (n * (1.0 - rho) / (1.0 + rho)).max(2.0)
}

/// Sampling noise (two standard errors) of the p95 and the max of a set of
/// errors, from the set itself. p95: half the spread between the errors at
/// ranks `n (0.95 -+ 2 sqrt(0.95 0.05 / n_eff))` (the binomial uncertainty
/// of the rank among the independent rows the errors are worth, in the order
/// given: `independent_rows`). Max: the errors' tail beyond the p95 is
/// taken as exponential with the mean excess `beta`; the maximum of such a
/// sample is Gumbel-distributed with standard deviation `pi / sqrt(6)
/// beta`.
pub fn tail_noise(errors: &[f64]) -> (f64, f64) {
    let n = errors.len();
    if n < 2 {
        return (f64::INFINITY, f64::INFINITY);
    }
    let mut sorted = errors.to_vec();
    sorted.sort_by(f64::total_cmp);
    let at = |q: f64| sorted[((q * n as f64).ceil() as usize).clamp(1, n) - 1];
    let band = 2.0 * (0.95 * 0.05 / independent_rows(errors)).sqrt();
    let p95 = 0.5 * (at((0.95 + band).min(1.0)) - at(0.95 - band));
    let threshold = at(0.95);
    let tail: Vec<f64> = sorted
        .iter()
        .filter(|e| **e > threshold)
        .map(|e| e - threshold)
        .collect();
    let beta = if tail.is_empty() {
        0.0
    } else {
        tail.iter().sum::<f64>() / tail.len() as f64
    };
    let max = 2.0 * std::f64::consts::PI / 6f64.sqrt() * beta;
    (p95, max)
}
