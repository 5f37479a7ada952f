//! The folds a session is validated on: two interleaved ones, and the
//! blocked ones (the later half, the earlier half, the outer shell) that see
//! extrapolation in time and in space.

use serde::{Deserialize, Serialize};

use crate::data::observe::Observation;

/// Fewest tracked rows for blocked folds: each blocked fit sees half (time) or
/// about 60 % (space) of the rows, and a full model of 8 strings has ~40
/// parameters; below this the session falls back to interleaved folds.
pub const MIN_BLOCKED_ROWS: usize = 200;

/// Outer shell of the space fold: points whose largest coordinate offset from
/// the centroid, relative to the session's extent on that axis, is at least
/// this. For points filling a cube it is the outer third of the volume
/// (1 - r^3 = 1/3); on the 13^3 lattice it is the outermost layer (39 %).
const OUTER_SHELL: f64 = 0.873_580_464_736_299_4; // (2/3)^(1/3)

/// Which folds a validation pooled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Folds {
    /// Time (fit the earlier half, validate the later, and the reverse) and
    /// space (fit the inner region, validate the outer shell).
    Blocked,
    /// The session is too small for blocked folds (fewer than
    /// [`MIN_BLOCKED_ROWS`] tracked rows): two interleaved folds only.
    Interleaved,
}

/// One fold: (fit rows, held-out rows), by index into the tracked rows.
pub(crate) type Fold = (Vec<usize>, Vec<usize>);

/// What each fold of [`folds`] holds out, by name, in its order: the two
/// interleaved folds, then the blocked ones (the later half, fitted on the
/// earlier; the earlier, fitted on the later; the outer shell, fitted on the
/// inner region).
pub(super) const FOLD_NAMES: [&str; 5] = [
    "even rows",
    "odd rows",
    "later half",
    "earlier half",
    "outer shell",
];

/// The folds of a session; the first two are the interleaved ones.
pub(crate) fn folds(tracked: &[&Observation]) -> (Folds, Vec<Fold>) {
    let n = tracked.len();
    let parity = |p: usize| -> Fold {
        (
            (0..n).filter(|k| k % 2 != p).collect(),
            (0..n).filter(|k| k % 2 == p).collect(),
        )
    };
    let mut out = vec![parity(0), parity(1)];
    if n < MIN_BLOCKED_ROWS {
        return (Folds::Interleaved, out);
    }
    // Time: the earlier and the later half (row order breaks ties).
    let mut by_time: Vec<usize> = (0..n).collect();
    by_time.sort_by(|&a, &b| tracked[a].t_s.total_cmp(&tracked[b].t_s).then(a.cmp(&b)));
    let (early, late) = by_time.split_at(n / 2);
    let (mut early, mut late) = (early.to_vec(), late.to_vec());
    early.sort_unstable();
    late.sort_unstable();
    out.push((early.clone(), late.clone()));
    out.push((late, early));
    // Space: the outer shell by the largest relative coordinate offset.
    let positions: Vec<[f64; 3]> = tracked.iter().filter_map(|o| o.tracker).collect();
    let mut centre = [0.0; 3];
    for p in &positions {
        for k in 0..3 {
            centre[k] += p[k] / n as f64;
        }
    }
    let mut extent = [0.0f64; 3];
    for p in &positions {
        for k in 0..3 {
            extent[k] = extent[k].max((p[k] - centre[k]).abs());
        }
    }
    let widest = extent.iter().cloned().fold(0.0, f64::max);
    let offset = |p: &[f64; 3]| -> f64 {
        (0..3)
            // An axis the session does not move along (a planar device's
            // height) does not define a shell.
            .filter(|&k| extent[k] > 1e-3 * widest)
            .map(|k| (p[k] - centre[k]).abs() / extent[k])
            .fold(0.0, f64::max)
    };
    let (outer, inner): (Vec<usize>, Vec<usize>) =
        (0..n).partition(|&k| offset(&positions[k]) >= OUTER_SHELL);
    if inner.len() >= MIN_BLOCKED_ROWS / 2 && outer.len() >= MIN_BLOCKED_ROWS / 4 {
        out.push((inner, outer));
    }
    (Folds::Blocked, out)
}

/// Folds of a session too small for the blocked ones: each holds out a
/// tenth.
pub const SMALL_SESSION_FOLDS: usize = 10;

/// `k` interleaved folds of `n` rows: each fits on all but a tenth of the
/// rows (or all but one, leave-one-out, below ten rows), so that a fold's
/// model is determined almost as the session's is; `None` when no fold can
/// hold a row out and keep `needed` rows to fit.
fn small_session_folds(n: usize, needed: usize) -> Option<Vec<Fold>> {
    let k = n.min(SMALL_SESSION_FOLDS);
    if k < 2 || n - n.div_ceil(k) < needed {
        return None;
    }
    let fold = |p: usize| {
        (
            (0..n).filter(|r| r % k != p).collect(),
            (0..n).filter(|r| r % k == p).collect(),
        )
    };
    Some((0..k).map(fold).collect())
}

/// The folds a choice made beside the model (the anchors' tolerance, the
/// robust weights, a small session's kinematics' rule) is judged on, each
/// fold's fitting rows identifying the model (`needed` rows), and their
/// name: the loop's blocked folds from [`MIN_BLOCKED_ROWS`]
/// tracked rows, else ten interleaved ones ([`small_session_folds`]); none
/// when the session cannot spare a row.
pub(crate) fn choice_folds(tracked: &[&Observation], needed: usize) -> (String, Vec<Fold>) {
    let n = tracked.len();
    if n >= MIN_BLOCKED_ROWS {
        let (_, blocked) = judged_folds(tracked);
        return (
            "blocked folds (later, earlier half, outer shell)".into(),
            blocked,
        );
    }
    match small_session_folds(n, needed) {
        Some(f) => (format!("{} interleaved folds", f.len()), f),
        None => ("none".into(), Vec::new()),
    }
}

/// The folds [`validate_by`](super::validate_by) judges by: the blocked ones when the session
/// has them, else the two interleaved ones.
pub(crate) fn judged_folds(tracked: &[&Observation]) -> (Folds, Vec<Fold>) {
    let (kind, mut all) = folds(tracked);
    match kind {
        Folds::Blocked => {
            all.drain(..2);
        }
        Folds::Interleaved => all.truncate(2),
    }
    (kind, all)
}

/// The forward-chaining folds of a session of at least [`MIN_BLOCKED_ROWS`]
/// tracked rows (none for a smaller one): in time order, fit the earlier
/// half and hold out the third quarter, fit the earlier three quarters and
/// hold out the last. Every fit is earlier than what it predicts, as every
/// use of a calibration is later than its training: what a term that reads
/// time (a drift) is judged on besides the blocked folds.
pub(crate) fn forward_folds(tracked: &[&Observation]) -> Vec<Fold> {
    let n = tracked.len();
    if n < MIN_BLOCKED_ROWS {
        return Vec::new();
    }
    let mut by_time: Vec<usize> = (0..n).collect();
    by_time.sort_by(|&a, &b| tracked[a].t_s.total_cmp(&tracked[b].t_s).then(a.cmp(&b)));
    let sorted = |rows: &[usize]| {
        let mut rows = rows.to_vec();
        rows.sort_unstable();
        rows
    };
    let (half, three_quarters) = (n / 2, 3 * n / 4);
    vec![
        (
            sorted(&by_time[..half]),
            sorted(&by_time[half..three_quarters]),
        ),
        (
            sorted(&by_time[..three_quarters]),
            sorted(&by_time[three_quarters..]),
        ),
    ]
}

/// Fewest fit rows a fold needs on each side of a step in time (a slip) to
/// fit the step's size.
pub const MIN_STEP_SIDE_ROWS: usize = 20;

/// Which of the blocked folds of `train` (indexed as
/// [`Validation::fold_sizes`]) can judge a change that adds steps in time
/// (slips) at `steps_at_s`, with the names of those that cannot. A step in
/// time (a slip at `t`) has a size only a fit whose rows lie on both sides
/// of `t` can find: the fold that fits the later half of a session whose
/// slip came early never sees the string before it, so its prediction of
/// the earlier rows is arbitrary with or without the slip. A step is judged
/// on the interleaved folds and these ([`Validation::for_step`]).
///
/// [`Validation::fold_sizes`]: super::Validation::fold_sizes
/// [`Validation::for_step`]: super::Validation::for_step
pub(crate) fn judgeable_folds(
    steps_at_s: &[f64],
    train: &[Observation],
) -> (Vec<bool>, Vec<&'static str>) {
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let (kind, folds) = folds(&tracked);
    let (pooled, names): (&[Fold], &[&'static str]) = match kind {
        Folds::Blocked => (&folds[2..], &FOLD_NAMES[2..]),
        Folds::Interleaved => (&folds[..2], &FOLD_NAMES[..2]),
    };
    let keep: Vec<bool> = pooled
        .iter()
        .map(|(fit, _)| {
            steps_at_s.iter().all(|&at_s| {
                let before = fit.iter().filter(|&&k| tracked[k].t_s < at_s).count();
                before >= MIN_STEP_SIDE_ROWS && fit.len() - before >= MIN_STEP_SIDE_ROWS
            })
        })
        .collect();
    let left_out = keep
        .iter()
        .zip(names)
        .filter(|(k, _)| !**k)
        .map(|(_, n)| *n)
        .collect();
    (keep, left_out)
}

#[cfg(test)]
mod tests;
