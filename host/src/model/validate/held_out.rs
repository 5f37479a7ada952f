//! Held-out figures: a structure refitted on each fold's fitting rows and
//! its position errors on the rows the fold holds out ([`Validation`]).

use serde::{Deserialize, Serialize};
use spidar_core::model::Frame;

use super::errors::{held_out_error_list, held_out_errors, tail_noise};
use super::folds::{folds, judged_folds, Folds};
use crate::data::observe::Observation;
use crate::data::stats::ErrorStats;
use crate::model::identify::{identify, Identification, IdentifyError, Start, Structure};

#[cfg(test)]
mod tests;

/// Held-out position errors of one structure, every fold refitted warm from
/// the current identification.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    pub folds: Folds,
    /// The errors acceptance looks at: the blocked folds pooled (each later
    /// and earlier half once, the outer shell once), or the interleaved ones
    /// when `folds` is `interleaved`.
    pub held: ErrorStats,
    /// The two interleaved folds pooled (every row once).
    pub interleaved: ErrorStats,
    /// Sampling noise (two standard errors) of `held`'s p95 and max, see
    /// [`tail_noise`](super::tail_noise).
    pub noise_p95_mm: f64,
    pub noise_max_mm: f64,
    /// The held-out errors behind `held`, row by row in fold order (the same
    /// order for every structure of one session), mm.
    #[serde(skip)]
    pub held_errors: Vec<f64>,
    /// How many of `held_errors` each fold behind `held` gave, in order
    /// (the blocked folds: later half, earlier half, outer shell; or the two
    /// interleaved ones).
    #[serde(skip)]
    pub fold_sizes: Vec<usize>,
    /// The interleaved folds' errors behind `interleaved`, row by row, mm.
    #[serde(skip)]
    pub interleaved_errors: Vec<f64>,
    /// Row by row as `held_errors`: the kinematics found the row's strings
    /// inconsistent ([`FkStatus::Inconsistent`](spidar_core::kinematics::FkStatus::Inconsistent); the device turns force
    /// off there).
    #[serde(skip)]
    pub held_inconsistent: Vec<bool>,
    /// Row by row as `interleaved_errors`, as `held_inconsistent`.
    #[serde(skip)]
    pub interleaved_inconsistent: Vec<bool>,
}

impl Validation {
    /// Its figures without the errors row by row (empty), as a finding's
    /// check keeps them once judged: nothing reads those again, and a long
    /// session's are megabytes a validation.
    pub fn summary(&self) -> Validation {
        Validation {
            folds: self.folds,
            held: self.held,
            interleaved: self.interleaved,
            noise_p95_mm: self.noise_p95_mm,
            noise_max_mm: self.noise_max_mm,
            held_errors: Vec::new(),
            fold_sizes: Vec::new(),
            interleaved_errors: Vec::new(),
            held_inconsistent: Vec::new(),
            interleaved_inconsistent: Vec::new(),
        }
    }

    /// What a step in time (a slip) is judged on: the interleaved folds
    /// (every fit straddles the step and every held-out set has rows on
    /// both sides of it) and, of the blocked folds, those `keep` says (their
    /// fit rows reach both sides of the step, `judgeable_folds`).
    pub fn for_step(&self, keep: &[bool]) -> Validation {
        let mut held_errors = Vec::with_capacity(self.held_errors.len());
        let mut held_inconsistent = Vec::with_capacity(self.held_errors.len());
        let mut fold_sizes = Vec::with_capacity(self.fold_sizes.len());
        if self.folds == Folds::Blocked {
            held_errors.extend_from_slice(&self.interleaved_errors);
            held_inconsistent.extend_from_slice(&self.interleaved_inconsistent);
            fold_sizes.push(self.interleaved_errors.len());
            let mut from = 0;
            for (k, &size) in self.fold_sizes.iter().enumerate() {
                if keep.get(k).copied().unwrap_or(true) {
                    held_errors.extend_from_slice(&self.held_errors[from..from + size]);
                    held_inconsistent.extend_from_slice(&self.held_inconsistent[from..from + size]);
                    fold_sizes.push(size);
                }
                from += size;
            }
        } else {
            held_errors.extend_from_slice(&self.held_errors);
            held_inconsistent.extend_from_slice(&self.held_inconsistent);
            fold_sizes.extend_from_slice(&self.fold_sizes);
        }
        let (noise_p95_mm, noise_max_mm) = tail_noise(&held_errors);
        Validation {
            folds: self.folds,
            held: ErrorStats::of(&held_errors),
            interleaved: self.interleaved,
            noise_p95_mm,
            noise_max_mm,
            held_errors,
            fold_sizes,
            interleaved_errors: self.interleaved_errors.clone(),
            held_inconsistent,
            interleaved_inconsistent: self.interleaved_inconsistent.clone(),
        }
    }
}

/// The held-out errors of each fold of `v`, in order.
pub(super) fn fold_errors(v: &Validation) -> impl Iterator<Item = &[f64]> + '_ {
    v.fold_sizes.iter().scan(0, |from, &size| {
        let errors = &v.held_errors[*from..*from + size];
        *from += size;
        Some(errors)
    })
}

/// The mean held-out error of each fold of `v`, in order.
pub(super) fn fold_means(v: &Validation) -> impl Iterator<Item = f64> + '_ {
    fold_errors(v).map(|errors| errors.iter().sum::<f64>() / errors.len().max(1) as f64)
}

/// Held-out errors of `structure` on the folds of `train` (see [`Folds`]),
/// each fold's fit warm from `from`, the fits in parallel.
pub fn validate(
    train: &[Observation],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
) -> Result<Validation, IdentifyError> {
    validate_fits(train, nominal, from, structure).map(|v| v.0)
}

/// [`validate`], with the fold fits (interleaved, then time: earlier, later;
/// then space).
pub(crate) fn validate_fits(
    train: &[Observation],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
) -> Result<(Validation, Vec<Identification>), IdentifyError> {
    let start = Start::from_identification(from);
    validate_by(train, |rows| identify(rows, nominal, &start, structure))
}

/// [`validate_fits`] with each fold's model made by `fit` from the fold's
/// fitting rows (the session's, referred to: a copy of each fold's rows
/// took the session's size again per fold in flight).
pub(crate) fn validate_by(
    train: &[Observation],
    fit: impl Fn(&[&Observation]) -> Result<Identification, IdentifyError> + Sync,
) -> Result<(Validation, Vec<Identification>), IdentifyError> {
    use rayon::prelude::*;
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let (kind, folds) = folds(&tracked);
    let pick = |rows: &[usize]| -> Vec<&Observation> { rows.iter().map(|&k| tracked[k]).collect() };
    let fits: Vec<(Identification, Vec<f64>, Vec<bool>)> = folds
        .par_iter()
        .map(|(rows, held)| {
            let id = fit(&pick(rows))?;
            let (errors, inconsistent) = held_out_errors(&id, &pick(held));
            Ok((id, errors, inconsistent))
        })
        .collect::<Result<_, IdentifyError>>()?;
    let errors: Vec<&[f64]> = fits.iter().map(|f| f.1.as_slice()).collect();
    let statuses: Vec<&[bool]> = fits.iter().map(|f| f.2.as_slice()).collect();
    let interleaved_inconsistent = statuses[..2].concat();
    let held_inconsistent = match kind {
        Folds::Blocked => statuses[2..].concat(),
        Folds::Interleaved => statuses[..2].concat(),
    };
    let interleaved_errors = errors[..2].concat();
    let interleaved = ErrorStats::of(&interleaved_errors);
    let pooled = match kind {
        Folds::Blocked => &errors[2..],
        Folds::Interleaved => &errors[..2],
    };
    let held_errors = pooled.concat();
    let fold_sizes = pooled.iter().map(|e| e.len()).collect();
    let held = ErrorStats::of(&held_errors);
    let (noise_p95_mm, noise_max_mm) = tail_noise(&held_errors);
    Ok((
        Validation {
            folds: kind,
            held,
            interleaved,
            noise_p95_mm,
            noise_max_mm,
            held_errors,
            fold_sizes,
            interleaved_errors,
            held_inconsistent,
            interleaved_inconsistent,
        },
        fits.into_iter().map(|f| f.0).collect(),
    ))
}

/// Held-out errors of `structure` on the forward-chaining folds of `train`
/// (fit the earlier half and predict the third quarter, fit three quarters
/// and predict the last, in time; each fit warm from `from`), pooled;
/// `None` for a session of fewer than [`MIN_BLOCKED_ROWS`](super::MIN_BLOCKED_ROWS) tracked rows.
pub fn validate_forward(
    train: &[Observation],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
) -> Result<Option<ErrorStats>, IdentifyError> {
    use rayon::prelude::*;
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let folds = super::folds::forward_folds(&tracked);
    if folds.is_empty() {
        return Ok(None);
    }
    let start = Start::from_identification(from);
    let pick = |rows: &[usize]| -> Vec<&Observation> { rows.iter().map(|&k| tracked[k]).collect() };
    let errors: Vec<Vec<f64>> = folds
        .par_iter()
        .map(|(rows, held)| {
            let id = identify(&pick(rows), nominal, &start, structure)?;
            Ok(held_out_error_list(&id, &pick(held)))
        })
        .collect::<Result<_, IdentifyError>>()?;
    Ok(Some(ErrorStats::of(&errors.concat())))
}

/// The models of the folds [`validate_by`] judges by (the blocked ones when
/// the session has them, else the interleaved), each made by `fit` from its
/// fold's fitting rows, with the rows it holds out: for choices made after
/// the model (the kinematics' rule, `rule`).
pub(crate) fn judged_fold_fits(
    train: &[Observation],
    fit: impl Fn(&[&Observation]) -> Result<Identification, IdentifyError> + Sync,
) -> Result<Vec<(Identification, Vec<&Observation>)>, IdentifyError> {
    use rayon::prelude::*;
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let (_, judged) = judged_folds(&tracked);
    let pick = |rows: &[usize]| -> Vec<&Observation> { rows.iter().map(|&k| tracked[k]).collect() };
    judged
        .par_iter()
        .map(|(rows, held)| Ok((fit(&pick(rows))?, pick(held))))
        .collect()
}

/// Mean position error on data each fit did not see: two interleaved folds,
/// each fitted (warm, from `from`) on the other.
pub fn cross_validated_error(
    train: &[Observation],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
) -> Result<f64, IdentifyError> {
    let fold = |parity: usize| -> Result<(f64, usize), IdentifyError> {
        let fit: Vec<&Observation> = train
            .iter()
            .enumerate()
            .filter(|(k, _)| k % 2 != parity)
            .map(|(_, o)| o)
            .collect();
        let held: Vec<&Observation> = train
            .iter()
            .enumerate()
            .filter(|(k, _)| k % 2 == parity)
            .map(|(_, o)| o)
            .collect();
        let id = identify(&fit, nominal, &Start::from_identification(from), structure)?;
        let s = ErrorStats::of(&held_out_error_list(&id, &held));
        Ok((s.mean_mm * s.n as f64, s.n))
    };
    let (a, b) = rayon::join(|| fold(0), || fold(1));
    let (a, b) = (a?, b?);
    Ok((a.0 + b.0) / (a.1 + b.1).max(1) as f64)
}
