//! The verdict on a change: [`judge`] on the held-out figures before and
//! after it ([`Check`]), with the tests particular to some changes: a step
//! in time on the folds that see it ([`judge_step`]), a drift that only
//! moves error between the halves ([`refuse_on_fold_rise`]), a term whose
//! gain only the folds show ([`refuse_a_fold_repair`]), and the halves'
//! stability of an added term ([`stability`]).

use serde::{Deserialize, Serialize};

use super::folds::{Folds, FOLD_NAMES, MIN_BLOCKED_ROWS};
use super::held_out::{fold_errors, fold_means, Validation};
use crate::data::stats::{chi_square_p001, ErrorStats};
use crate::model::identify::Identification;

#[cfg(test)]
mod tests;

/// A held-out row whose error exceeds this many times the p95 before a
/// change, before or after it, is one the model fails on (a faulty string
/// it did not reject): its error moves by mm with any change. [`judge`]
/// holds the max of the other rows to its noise and lets each of these rise
/// by at most [`FAILING_ROW_RISE`] plus that noise (a term that blows up
/// outside the lattice, by tens of mm, is still refused).
pub const FAILING_ROW_FACTOR: f64 = 4.0;

/// How much (relative) a row the model already fails on may worsen.
pub const FAILING_ROW_RISE: f64 = 0.25;

/// A held-out check of a change: the figures before and after, and why it
/// was or was not taken.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Check {
    pub before: Validation,
    pub after: Validation,
    /// Chi-square of the difference between the added term's parameters
    /// fitted on the earlier and on the later half (see `reason`); absent
    /// without time folds.
    pub stability_chi2: Option<f64>,
    pub accepted: bool,
    /// One line for people.
    pub reason: String,
}

impl Check {
    /// The check as a finding keeps it: its validations' figures
    /// ([`Validation::summary`]) and the verdict.
    pub fn summarized(self) -> Check {
        Check {
            before: self.before.summary(),
            after: self.after.summary(),
            ..self
        }
    }
}

/// Whether a change that turns held-out errors `before` into `after` is
/// taken: the mean must fall by `min_gain` (relative) and neither the p95
/// nor the max may rise beyond its noise (that of `before`); nor may the
/// rows the kinematics find inconsistent grow by more than twice the
/// standard deviation of the difference between the rows that become
/// inconsistent and those that cease to be, were each flip as likely either
/// way (`sqrt` of their sum).
pub fn judge(
    before: &Validation,
    after: &Validation,
    stable: Option<(f64, usize)>,
    min_gain: f64,
) -> Check {
    let (gain, figures) = figures(before, after);
    let (accepted, why) = verdict(before, after, stable, min_gain, gain);
    Check {
        before: before.clone(),
        after: after.clone(),
        stability_chi2: stable.map(|s| s.0),
        accepted,
        reason: if accepted {
            format!("{why}: {figures}")
        } else {
            format!("not added: {why}: {figures}")
        },
    }
}

/// The relative fall of the held-out mean from `before` to `after`, and the
/// figures a check reports: the mean, p95 and max before and after, on
/// which folds.
fn figures(before: &Validation, after: &Validation) -> (f64, String) {
    let (b, a) = (&before.held, &after.held);
    let folds = match after.folds {
        Folds::Blocked => "blocked folds (time, space)".to_string(),
        Folds::Interleaved => format!(
            "interleaved folds only ({} tracked rows; blocked folds need {MIN_BLOCKED_ROWS})",
            a.n
        ),
    };
    let gain = 1.0 - a.mean_mm / b.mean_mm;
    let figures = format!(
        "held-out mean {:.3} -> {:.3} mm ({:+.1} %), p95 {:.3} -> {:.3}, max {:.2} -> {:.2} on {folds}",
        b.mean_mm,
        a.mean_mm,
        -100.0 * gain,
        b.p95_mm,
        a.p95_mm,
        b.max_mm,
        a.max_mm
    );
    (gain, figures)
}

/// The held-out maxima [`judge`] holds a change to: the max before and
/// after of the rows the model does not fail on (before or after, beyond
/// [`FAILING_ROW_FACTOR`] times the p95), and of the rows it fails on, the
/// one that worsens most beyond [`FAILING_ROW_RISE`] and the max noise
/// (before, after).
struct Maxima {
    before_mm: f64,
    after_mm: f64,
    worst_failing: Option<(f64, f64)>,
}

/// [`Maxima`] of a change from `before` to `after`; without row-by-row
/// pairs, the held-out maxima themselves and no failing row.
fn maxima(before: &Validation, after: &Validation) -> Maxima {
    let (b, a) = (&before.held, &after.held);
    let paired =
        before.held_errors.len() == after.held_errors.len() && !before.held_errors.is_empty();
    if !paired {
        return Maxima {
            before_mm: b.max_mm,
            after_mm: a.max_mm,
            worst_failing: None,
        };
    }
    let failing = |e: f64| e > FAILING_ROW_FACTOR * b.p95_mm;
    let mut mb = 0.0f64;
    let mut ma = 0.0f64;
    let mut worst: Option<(f64, f64)> = None;
    for (k, (&x, &y)) in before
        .held_errors
        .iter()
        .zip(&after.held_errors)
        .enumerate()
    {
        if failing(x) || failing(y) {
            // Where the kinematics find the strings inconsistent after
            // the change, the row's position is a guess among solutions
            // that fit alike (with 2 spare strings a second exclusion
            // fits by chance, and any change of the lengths flips it, by
            // tens of mm on a planar 4-string device) and the device
            // turns force off: such rows are counted (in the verdict), not
            // held to their error.
            if after.held_inconsistent.get(k) == Some(&true) {
                continue;
            }
            if y > x * (1.0 + FAILING_ROW_RISE) + before.noise_max_mm
                && worst.is_none_or(|w| y - x > w.1 - w.0)
            {
                worst = Some((x, y));
            }
        } else {
            mb = mb.max(x);
            ma = ma.max(y);
        }
    }
    Maxima {
        before_mm: mb,
        after_mm: ma,
        worst_failing: worst,
    }
}

/// [`judge`]'s verdict on a change from `before` to `after` whose held-out
/// mean falls by `gain` (relative): whether it is taken and, in words, why
/// (the first rule it breaks, or "added").
fn verdict(
    before: &Validation,
    after: &Validation,
    stable: Option<(f64, usize)>,
    min_gain: f64,
    gain: f64,
) -> (bool, String) {
    let (b, a) = (&before.held, &after.held);
    // The max is judged on the rows the model does not fail on (before or
    // after); those it fails on may not worsen by more than FAILING_ROW_RISE.
    let Maxima {
        before_mm: max_before,
        after_mm: max_after,
        worst_failing,
    } = maxima(before, after);
    let (became, recovered) = inconsistency_changes(before, after);
    let limit = chi_square_p001;
    if let Some((chi2, k)) = stable.filter(|s| s.0 > limit(s.1)) {
        (
            false,
            format!(
                "its value fitted on the earlier half and on the later half differ beyond their \
                 uncertainty (chi-square {chi2:.1} > {:.1}, {k} dof): it stands in for something \
                 else (time and position go together in this session)",
                limit(k)
            ),
        )
    } else if !(a.mean_mm.is_finite() && gain >= min_gain) {
        (
            false,
            format!("the mean does not fall by {:.1} %", 100.0 * min_gain),
        )
    } else if a.p95_mm > b.p95_mm + before.noise_p95_mm {
        (
            false,
            format!(
                "the p95 rises beyond its noise ({:.3} mm)",
                before.noise_p95_mm
            ),
        )
    } else if max_after > max_before + before.noise_max_mm {
        (
            false,
            format!(
                "the max rises beyond its noise ({:.2} mm): {max_before:.2} -> {max_after:.2} mm \
                 on the rows the model does not fail on",
                before.noise_max_mm
            ),
        )
    } else if became as f64 > recovered as f64 + 2.0 * ((became + recovered) as f64).sqrt() {
        (
            false,
            format!(
                "more held-out rows become inconsistent (the kinematics cannot settle them, the \
                 device turns force off) than their noise allows: {became} become so, \
                 {recovered} cease to be"
            ),
        )
    } else if let Some((x, y)) = worst_failing {
        (
            false,
            format!(
                "a row the model fails on gets worse beyond {:.0} % and the max noise: \
                 {x:.2} -> {y:.2} mm",
                100.0 * FAILING_ROW_RISE
            ),
        )
    } else {
        (true, "added".to_string())
    }
}

/// How many held-out rows a change turns inconsistent
/// ([`FkStatus::Inconsistent`](spidar_core::kinematics::FkStatus::Inconsistent)) and how many it settles, row by row; (0, 0)
/// when the two validations do not hold the same rows.
fn inconsistency_changes(before: &Validation, after: &Validation) -> (usize, usize) {
    let n = before.held_errors.len();
    if before.held_inconsistent.len() != n || after.held_inconsistent.len() != n {
        return (0, 0);
    }
    let pairs = before
        .held_inconsistent
        .iter()
        .zip(&after.held_inconsistent);
    pairs.fold((0, 0), |(became, recovered), (&x, &y)| {
        (
            became + usize::from(y && !x),
            recovered + usize::from(x && !y),
        )
    })
}

/// Least relative sd of a half's value in the halves test ([`stability`]):
/// each half's sd is that of white residuals, and a model that misses
/// something leaves residuals correlated along the lattice, so that two
/// halves that agree to 1-2 % would be refused at sds of 0.3 %.
const STABILITY_RELATIVE_SD: f64 = 0.03;

/// How far apart the added change's `k` parameters (the last of the
/// structure: an effect's, or several strings' drifts added together) come
/// out of the fits on the earlier and on the later half
/// (`fits` in [`validate_fits`](super::validate_fits)' order, the blocked
/// folds last: the later half's, the earlier half's, the outer shell's): chi-square of
/// the difference over the two fits' standard deviations, and its dof. A
/// physical effect has one value; a term that stands in for something else
/// (a drift standing in for position on a lattice collected plane by plane)
/// takes the local slope of what it replaces, different in each half.
/// `None` without time folds. [`judge`] holds the chi-square to the level
/// `k` standard normals exceed with probability 0.001. Each half's sd is
/// that of white residuals times `sqrt(n / n_eff)` of `held_errors` (the
/// candidate's held-out errors in session order, [`independent_rows`]:
/// the rows they are worth, decision record 0058); empty: white.
///
/// [`independent_rows`]: super::errors::independent_rows
pub(crate) fn stability(
    k: usize,
    fits: &[Identification],
    held_errors: &[f64],
) -> Option<(f64, usize)> {
    // The rows' errors correlate along the session (a stream's neighbours
    // see nearly the same pose): a half's estimate is worth the rows they
    // make, not their count.
    let n = held_errors.len() as f64;
    let inflation = if held_errors.len() >= 3 {
        (n / super::errors::independent_rows(held_errors)).sqrt()
    } else {
        1.0
    };
    let later_half = fits.len().checked_sub(3)?;
    let (early, late) = (fits.get(later_half)?, fits.get(later_half + 1)?);
    let tail = |id: &Identification| {
        let from = id.parameters.len().checked_sub(k)?;
        Some(id.parameters[from..].to_vec())
    };
    let (a, b) = (tail(early)?, tail(late)?);
    let chi2 = a
        .iter()
        .zip(&b)
        .map(|(x, y)| {
            let floor = |v: f64, sd: f64| sd.max(STABILITY_RELATIVE_SD * v.abs());
            let (sx, sy) = (
                floor(x.value, inflation * x.sd),
                floor(y.value, inflation * y.sd),
            );
            let v = sx * sx + sy * sy;
            if v > 0.0 && v.is_finite() {
                (x.value - y.value).powi(2) / v
            } else {
                0.0
            }
        })
        .sum::<f64>();
    Some((chi2, k))
}

/// [`judge`] for a step in time (a slip) on the folds that see it
/// (`keep`, [`judgeable_folds`](super::judgeable_folds); `left_out` names the others). No
/// halves-stability test (one half may not see the step), and every fold
/// that sees the step must gain: a slip is a fact of the session, so every
/// fit that straddles it predicts better with it, and a term that helps on
/// some folds only stands in for something else.
pub(crate) fn judge_step(
    before: &Validation,
    after: &Validation,
    keep: &[bool],
    left_out: &[&str],
    min_gain: f64,
) -> Check {
    let mut check = judge(
        &before.for_step(keep),
        &after.for_step(keep),
        None,
        min_gain,
    );
    check.reason += " and interleaved folds (a step in time)";
    let worse = fold_means(&check.before)
        .zip(fold_means(&check.after))
        .filter(|(b, a)| a > b)
        .count();
    if check.accepted && worse > 0 {
        check.accepted = false;
        check.reason = format!(
            "not added: it raises the mean on {worse} of the {} folds that see the step (a slip \
             lowers it on every one): {}",
            check.before.fold_sizes.len(),
            check.reason.trim_start_matches("added: ")
        );
    }
    if !left_out.is_empty() {
        check.reason += &format!(
            ", without the {} fold{}: its fit rows do not reach both sides of the step",
            left_out.join(" and "),
            if left_out.len() > 1 { "s" } else { "" }
        );
    }
    check
}

/// Standard errors (of a fold's paired differences) by which one blocked
/// fold's mean may rise under a drift while the pooled mean falls. A real
/// drift, fitted on either half, helps the other; a drift that lowers the
/// pooled error by helping one half and costing the other stands in for
/// something else, and raises the test error. Drifts only: other changes
/// trade one fold for another when something else is missing too, and
/// refusing them for it would lose real terms (offsets, a stretch;
/// decision record 0027, `docs/decisions/0027-drift-helps-both-halves.md`).
const FOLD_RISE_Z: f64 = 3.0;

/// `check` (an accepted drift's) refused when a blocked fold gets worse
/// beyond [`FOLD_RISE_Z`].
pub(crate) fn refuse_on_fold_rise(check: Check) -> Check {
    let Some(rise) = fold_rise(&check.before, &check.after) else {
        return check;
    };
    refused(
        check,
        &format!(
            "the {} fold gets worse, {:.3} -> {:.3} mm ({:.1} standard errors of its paired \
             differences): a drift fitted on either half helps the other, this one only moves \
             error between them",
            rise.fold, rise.before_mm, rise.after_mm, rise.z
        ),
    )
}

/// An accepted `check` refused for `why` by a later rule: "not added:
/// {why}: " and the figures it was accepted on.
pub(crate) fn refused(check: Check, why: &str) -> Check {
    let figures = check.reason.trim_start_matches("added: ");
    Check {
        accepted: false,
        reason: format!("not added: {why}: {figures}"),
        ..check
    }
}

/// A blocked fold whose mean rises beyond [`FOLD_RISE_Z`] standard errors.
struct FoldRise {
    fold: &'static str,
    before_mm: f64,
    after_mm: f64,
    z: f64,
}

/// The blocked fold of `after` whose mean rises most over `before`'s, in
/// standard errors of the paired row differences, when that is beyond
/// [`FOLD_RISE_Z`]; `None` for interleaved-only validations.
fn fold_rise(before: &Validation, after: &Validation) -> Option<FoldRise> {
    if after.folds != Folds::Blocked || before.fold_sizes != after.fold_sizes {
        return None;
    }
    let mut worst: Option<FoldRise> = None;
    for (k, (b, a)) in fold_errors(before).zip(fold_errors(after)).enumerate() {
        if a.len() < 2 {
            continue;
        }
        let n = a.len() as f64;
        let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
        let mean = d.iter().sum::<f64>() / n;
        let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
        if mean <= 0.0 {
            continue;
        }
        // Every row worse by the same amount: beyond any noise.
        let se = (var / n).sqrt();
        let z = if se > 0.0 { mean / se } else { f64::INFINITY };
        if z > FOLD_RISE_Z && worst.as_ref().is_none_or(|w| z > w.z) {
            worst = Some(FoldRise {
                fold: FOLD_NAMES.get(k + 2).copied().unwrap_or("blocked"),
                before_mm: b.iter().sum::<f64>() / n,
                after_mm: a.iter().sum::<f64>() / n,
                z,
            });
        }
    }
    worst
}

/// How much of its held-out gain an accepted term on one string must show on
/// the rows it is fitted on (the relative fall of the mean error there, over
/// that of the blocked folds' mean).
pub(crate) const IN_SAMPLE_SHARE_OF_GAIN: f64 = 0.25;

/// Refuses an accepted `check` whose held-out gain the fit on every row
/// (`before` -> `after`, the in-sample errors) does not show: below `share`
/// of it ([`IN_SAMPLE_SHARE_OF_GAIN`]; 0 for a drift: the in-sample error
/// must not rise). A real term lowers the error of the
/// rows it is fitted on at least as much as that of rows it is not; one
/// whose gain shows only held out repairs how the folds were fitted (each
/// fold refits anchors and home with the layer tables' levels held from
/// the fit on every row, and a free constant on one string lets it follow
/// them; decision record 0033, `docs/decisions/0033-fold-repair.md`).
pub(crate) fn refuse_a_fold_repair(
    check: &mut Check,
    before: ErrorStats,
    after: ErrorStats,
    share: f64,
) {
    let held = 1.0 - check.after.held.mean_mm / check.before.held.mean_mm.max(1e-12);
    let in_sample = 1.0 - after.mean_mm / before.mean_mm.max(1e-12);
    if check.accepted && in_sample < share * held {
        let why = format!(
            "it lowers the held-out mean by {:.1} % but that of the rows it is fitted on by \
             {:.1} % ({:.3} -> {:.3} mm): it repairs how the folds were fitted, not the model",
            100.0 * held,
            100.0 * in_sample,
            before.mean_mm,
            after.mean_mm,
        );
        *check = refused(check.clone(), &why);
    }
}
