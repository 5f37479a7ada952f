//! Held-out figures: a structure refitted on each fold's fitting rows and
//! its position errors on the rows the fold holds out ([`Validation`]).

use serde::{Deserialize, Serialize};
use spidar_core::model::Frame;

use super::errors::{held_out_error_list, held_out_errors, tail_noise};
use super::folds::{folds, judged_folds, Fold, Folds};
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
    /// The two interleaved folds pooled (every row once): `None` where
    /// blocked folds judge and the interleaved ones were not fitted (they
    /// judge only steps in time, [`Validation::for_step`]).
    pub interleaved: Option<ErrorStats>,
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

    /// Whether a blocked validation lacks its interleaved folds (fitted with
    /// [`FoldScope::WithInterleaved`] or added by `add_interleaved`), which
    /// [`for_step`](Self::for_step) needs.
    pub fn lacks_interleaved(&self) -> bool {
        self.folds == Folds::Blocked && self.interleaved.is_none()
    }

    /// Adds its interleaved folds' errors and kinematics statuses
    /// ([`interleaved_fold_errors`]).
    pub(crate) fn add_interleaved(&mut self, errors: Vec<f64>, inconsistent: Vec<bool>) {
        self.interleaved = Some(ErrorStats::of(&errors));
        self.interleaved_errors = errors;
        self.interleaved_inconsistent = inconsistent;
    }

    /// What a step in time (a slip) is judged on: the interleaved folds
    /// (every fit straddles the step and every held-out set has rows on
    /// both sides of it) and, of the blocked folds, those `keep` says (their
    /// fit rows reach both sides of the step, `judgeable_folds`). A blocked
    /// validation must have its interleaved folds
    /// ([`lacks_interleaved`](Self::lacks_interleaved)).
    pub fn for_step(&self, keep: &[bool]) -> Validation {
        debug_assert!(
            !self.lacks_interleaved(),
            "a step judged without interleaved folds"
        );
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

/// Which folds a validation fits where the session has blocked ones.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FoldScope {
    /// The blocked folds, which judge every change but a step in time.
    Judged,
    /// The interleaved folds as well, which a step in time (a slip) is
    /// also judged on ([`Validation::for_step`]).
    WithInterleaved,
}

/// Held-out errors of `structure` on the folds of `train` (see [`Folds`];
/// `scope`: with the interleaved ones or not), each fold's fit warm from
/// `from`, the fits in parallel.
pub fn validate(
    train: &[Observation],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
    scope: FoldScope,
) -> Result<Validation, IdentifyError> {
    validate_fits(train, nominal, from, structure, scope).map(|v| v.0)
}

/// [`validate`], with the fold fits in the folds' order (interleaved when
/// fitted, then time: the later half's, fitted on the earlier, the earlier
/// half's; then space).
pub(crate) fn validate_fits(
    train: &[Observation],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
    scope: FoldScope,
) -> Result<(Validation, Vec<Identification>), IdentifyError> {
    let start = Start::from_identification(from);
    validate_by(train, scope, |rows| {
        identify(rows, nominal, &start, structure)
    })
}

/// A fold's model, with its position errors and kinematics statuses
/// (inconsistent or not) on the rows the fold holds out.
type FoldFit = (Identification, Vec<f64>, Vec<bool>);

/// The models fitted on `folds` of `tracked` by `fit`, with their errors
/// and kinematics statuses on the rows each holds out, the fits in
/// parallel.
fn fit_folds(
    tracked: &[&Observation],
    folds: &[Fold],
    fit: impl Fn(&[&Observation]) -> Result<Identification, IdentifyError> + Sync,
) -> Result<Vec<FoldFit>, IdentifyError> {
    use rayon::prelude::*;
    let pick = |rows: &[usize]| -> Vec<&Observation> { rows.iter().map(|&k| tracked[k]).collect() };
    folds
        .par_iter()
        .map(|(rows, held)| {
            let id = fit(&pick(rows))?;
            let (errors, inconsistent) = held_out_errors(&id, &pick(held));
            Ok((id, errors, inconsistent))
        })
        .collect()
}

/// The interleaved folds' held-out errors and kinematics statuses of
/// `structure` on `train`, each fold's fit warm from `from`: what
/// `Validation::add_interleaved` adds to a validation fitted without
/// them.
pub(crate) fn interleaved_fold_errors(
    train: &[Observation],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
) -> Result<(Vec<f64>, Vec<bool>), IdentifyError> {
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let (_, folds) = folds(&tracked);
    let start = Start::from_identification(from);
    let fits = fit_folds(&tracked, &folds[..2], |rows| {
        identify(rows, nominal, &start, structure)
    })?;
    let errors = fits.iter().flat_map(|f| f.1.iter().copied()).collect();
    let statuses = fits.iter().flat_map(|f| f.2.iter().copied()).collect();
    Ok((errors, statuses))
}

/// [`validate_fits`] with each fold's model made by `fit` from the fold's
/// fitting rows (the session's, referred to: a copy of each fold's rows
/// took the session's size again per fold in flight).
pub(crate) fn validate_by(
    train: &[Observation],
    scope: FoldScope,
    fit: impl Fn(&[&Observation]) -> Result<Identification, IdentifyError> + Sync,
) -> Result<(Validation, Vec<Identification>), IdentifyError> {
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let (kind, folds) = folds(&tracked);
    // The interleaved folds come first; blocked folds judge without them.
    let interleaved_fitted = kind == Folds::Interleaved || scope == FoldScope::WithInterleaved;
    let first = if interleaved_fitted { 0 } else { 2 };
    let fits = fit_folds(&tracked, &folds[first..], fit)?;
    let errors: Vec<&[f64]> = fits.iter().map(|f| f.1.as_slice()).collect();
    let statuses: Vec<&[bool]> = fits.iter().map(|f| f.2.as_slice()).collect();
    let (interleaved_errors, interleaved_inconsistent) = if interleaved_fitted {
        (errors[..2].concat(), statuses[..2].concat())
    } else {
        (Vec::new(), Vec::new())
    };
    let interleaved = interleaved_fitted.then(|| ErrorStats::of(&interleaved_errors));
    let judged = match kind {
        Folds::Blocked => 2 - first..,
        Folds::Interleaved => 0..,
    };
    let held_inconsistent = statuses[judged.clone()].concat();
    let pooled = &errors[judged];
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
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let (_, judged) = judged_folds(&tracked);
    fold_fits(&tracked, &judged, fit)
}

/// The models of `folds` (by index into `tracked`), each made by `fit`
/// from its fold's fitting rows on its own core, with the rows it holds
/// out.
pub(crate) fn fold_fits<'a>(
    tracked: &[&'a Observation],
    folds: &[Fold],
    fit: impl Fn(&[&Observation]) -> Result<Identification, IdentifyError> + Sync,
) -> Result<Vec<(Identification, Vec<&'a Observation>)>, IdentifyError> {
    use rayon::prelude::*;
    let pick =
        |rows: &[usize]| -> Vec<&'a Observation> { rows.iter().map(|&k| tracked[k]).collect() };
    folds
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
