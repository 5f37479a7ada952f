//! The slip search: each string's most likely slip time (the best step in
//! its residual off the model) and whether the residual really jumps
//! there (the slips of several strings tried together: `together`).

use spidar_core::STRINGS;

use crate::data::stats::{median, robust_centre_and_sd};

use super::evidence::{Evidence, MIN_OUTSIDE_SPAN};

#[cfg(test)]
mod tests;

/// The most likely slip time of each string: the split of its rows (in time
/// order) whose step, once the model's own directions are projected out,
/// explains the most of the residual; `None` when the string has too few
/// rows. The step is judged as the slip candidate is, off the model: a step
/// in the raw residual is partly absorbed by the offset, anchor and winding
/// parameters whenever time and position go together (a lattice walked
/// layer by layer), which leaves a step plus a ramp whose largest mean
/// difference lies elsewhere, far from the slip. Every string's search in
/// one pass over the rows, latest first.
pub(super) fn slip_times(ev: &Evidence) -> Vec<Option<f64>> {
    let mut counts = [0; STRINGS];
    for k in 0..ev.rows() {
        if ev.weight(k) > 0.0 {
            counts[ev.string_of(k)] += 1;
        }
    }
    let mut searches: [Option<StepSearch>; STRINGS] =
        core::array::from_fn(|i| ev.layout.is_active(i).then(|| StepSearch::new(counts[i])));
    ev.for_basis_rows_latest_first(|k, time, b| {
        if let Some(search) = searches[ev.string_of(k)].as_mut() {
            search.add(time, ev.weight(k), ev.residual[k], b);
        }
    });
    searches
        .into_iter()
        .map(|s| s.and_then(StepSearch::best).map(|b| b.1))
        .collect()
}

/// Whether string `string`'s residual jumps where a slip of `mm` at `at_s`
/// says ([`jumps_where_it_slipped`] on its rows in time order).
pub(super) fn steps_where_it_slipped(ev: &Evidence, string: usize, at_s: f64, mm: f64) -> bool {
    let rows = ev.rows_in_time(Some(string));
    let split = rows.partition_point(|r| r.0 < at_s);
    let residuals: Vec<f64> = rows.iter().map(|&(_, k)| ev.residual_of(k)).collect();
    jumps_where_it_slipped(&residuals, split, mm)
}

/// Rows on each side of a split that [`jumps_where_it_slipped`] compares.
const LOCAL_STEP_ROWS: usize = 15;

/// How many robust standard deviations of a string's jumps at every row the
/// jump at a proposed slip must reach ([`jumps_where_it_slipped`]).
const LOCAL_STEP_Z: f64 = 3.0;

/// Whether residuals in time order jump before row `split` as a slip of
/// `mm` does: the median of the [`LOCAL_STEP_ROWS`] rows after minus that of
/// the rows before has the step's sign, at least half its size, and stands
/// out among the same jump taken before every other row (beyond
/// [`LOCAL_STEP_Z`] times their robust standard deviation). A slip is a
/// jump in time where the end-effector barely moved (a session walks its
/// path point to point), so the rows beside it see the whole step. An error
/// that follows position varies along the path as much before any row as
/// before this one, and a step fitted to it over the session (it goes with
/// time when the session goes plane by plane) has no jump of its own there,
/// yet such steps, alone or on several strings at once, pass the held-out
/// folds (which cannot judge an early step on both time halves), e.g. at a
/// session's start where the first rows, alone in their corner, bend away. And the jump holds beyond those rows
/// ([`holds_beyond_its_windows`]). Medians: a jammed encoder's repeated
/// reading is one row far off.
fn jumps_where_it_slipped(residuals: &[f64], split: usize, mm: f64) -> bool {
    let k = LOCAL_STEP_ROWS;
    let n = residuals.len();
    let jump = |j: usize| {
        let mut before = residuals[j.saturating_sub(k)..j].to_vec();
        let mut after = residuals[j..(j + k).min(n)].to_vec();
        median(&mut after) - median(&mut before)
    };
    if split < 2 || n < split + 2 || n < 4 * k {
        return false;
    }
    let local = jump(split);
    let jumps: Vec<f64> = (k..=n - k).map(jump).collect();
    let (_, sd) = robust_centre_and_sd(&jumps);
    // And among its neighbours' (the splits 15 to 60 rows away, whose
    // windows do not hold it): where the rows vary more than elsewhere (the
    // session's first rows, alone in their corner), a jump there is no news.
    let neighbours: Vec<f64> = (k..=n - k)
        .zip(&jumps)
        .filter(|&(j, _)| j.abs_diff(split) >= k && j.abs_diff(split) <= NEIGHBOURING_ROWS)
        .map(|(_, &v)| v)
        .collect();
    let sd_near = if neighbours.len() >= k {
        robust_centre_and_sd(&neighbours).1
    } else {
        0.0
    };
    local * mm > 0.0
        && local.abs() >= 0.5 * mm.abs()
        && local.abs() >= LOCAL_STEP_Z * sd.max(sd_near)
        && holds_beyond_its_windows(residuals, split, local)
}

/// Whether a `jump` at row `split` holds beyond the windows that measured
/// it: the median of the [`NEIGHBOURING_ROWS`] rows past the window after
/// minus that of those before the window before has its sign and half its
/// size at least. A slip stays; an error that comes and goes jumps and
/// falls back: the abnormal motor's string off its groove while the walk
/// crosses its region, which taken as a slip raises the test error. Half
/// the jump, not half the fitted step: a step fitted before the session's
/// other slips are in is larger than its jump. With fewer than [`LOCAL_STEP_ROWS`] rows on a
/// side there (a slip near the session's end) the jump alone decides.
fn holds_beyond_its_windows(residuals: &[f64], split: usize, jump: f64) -> bool {
    let (k, n) = (LOCAL_STEP_ROWS, residuals.len());
    let before = split.saturating_sub(k + NEIGHBOURING_ROWS)..split.saturating_sub(k);
    let after = (split + k).min(n)..(split + k + NEIGHBOURING_ROWS).min(n);
    if before.len() < k || after.len() < k {
        return true;
    }
    let beyond = median(&mut residuals[after].to_vec()) - median(&mut residuals[before].to_vec());
    beyond * jump > 0.0 && beyond.abs() >= 0.5 * jump.abs()
}

/// How far from a proposed slip its neighbours' jumps are taken
/// ([`jumps_where_it_slipped`]), rows.
const NEIGHBOURING_ROWS: usize = 60;

/// Fewest rows on each side of a step [`StepSearch`] takes.
const MIN_SIDE: usize = 20;

/// The best single step of one string's rows in key order, judged off the
/// model: a step column `x` (the rows after the split, each `sqrt(weight)`)
/// explains `(x . r)^2 / (x . x - |B^T x|^2)` of the projected weighted
/// residual `r` (`B`: the model's orthonormal basis; `r` is already
/// orthogonal to it, so `x . r` needs no projection). The rows come last
/// first ([`StepSearch::add`]): running sums give every split in one pass.
pub(super) struct StepSearch {
    /// The string's rows.
    n: usize,
    /// Index of the next row to come.
    next: usize,
    x_r: f64,
    x_x: f64,
    bt_x: Vec<f64>,
    /// The split before the last row added, judged once the row before it
    /// (its key) comes.
    pending: Option<Split>,
    best: (f64, Option<(usize, f64)>),
}

/// The split before row `j`: `x` holds rows `j..n`.
struct Split {
    j: usize,
    key: f64,
    x_r: f64,
    x_x: f64,
    outside: f64,
}

impl StepSearch {
    /// A search over `n` rows.
    pub(super) fn new(n: usize) -> StepSearch {
        StepSearch {
            n,
            next: n.saturating_sub(1),
            x_r: 0.0,
            x_x: 0.0,
            bt_x: Vec::new(),
            pending: None,
            best: (0.0, None),
        }
    }

    /// The next row, last first: its key, robust weight, projected
    /// weighted residual and row of the model's basis.
    pub(super) fn add(&mut self, key: f64, weight: f64, residual: f64, basis: &[f64]) {
        let j = self.next;
        if let Some(split) = self.pending.take() {
            self.judge(split, key);
        }
        // The first row is never in `x`.
        if j >= 1 {
            let sw = weight.sqrt();
            self.x_r += sw * residual;
            self.x_x += weight;
            self.bt_x.resize(basis.len(), 0.0);
            for (b, &v) in self.bt_x.iter_mut().zip(basis) {
                *b += sw * v;
            }
            let outside = self.x_x - self.bt_x.iter().map(|b| b * b).sum::<f64>();
            self.pending = Some(Split {
                j,
                key,
                x_r: self.x_r,
                x_x: self.x_x,
                outside,
            });
        }
        self.next = j.saturating_sub(1);
    }

    /// Scores `split`, whose row before has key `before`: at least
    /// `MIN_SIDE` rows on each side, a step between two keys and not
    /// (almost) in the model's span.
    fn judge(&mut self, split: Split, before: f64) {
        let Split {
            j,
            key,
            x_r,
            x_x,
            outside,
        } = split;
        if j < MIN_SIDE || self.n - j < MIN_SIDE || key == before {
            return;
        }
        if outside <= MIN_OUTSIDE_SPAN * MIN_OUTSIDE_SPAN * x_x {
            return;
        }
        let stat = x_r * x_r / outside;
        if stat > self.best.0 {
            self.best = (stat, Some((j, 0.5 * (before + key))));
        }
    }

    /// (Its statistic, the key halfway across it) of the best step;
    /// `None` with too few rows. A best split on the edge of the allowed
    /// range is no step found: what stands out is the first or last few
    /// rows (the session's start), which a step further in would fit
    /// better still.
    pub(super) fn best(self) -> Option<(f64, f64)> {
        if self.n < 2 * MIN_SIDE {
            return None;
        }
        let (j, at) = self.best.1?;
        (j > MIN_SIDE && self.n - j > MIN_SIDE).then_some((self.best.0, at))
    }
}
