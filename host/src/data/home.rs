//! Which home capture a later session's rows count from: the training
//! session's (a slip found in training is still in them, a drift goes on)
//! or a new one (the strings are counted from where they are, the slips are
//! gone and the time since home starts again).
//!
//! A new home capture cannot be undone, so the rows that share the training
//! session's home are the later session's first rows, up to the first row
//! of a new home ([`LaterHome::first_new_home_row`]). The sessions say it,
//! in this order of trust:
//! 1. `home` on both sessions' rows: a row shares the training's home while
//!    its id is the training's last row's.
//! 2. `since_home_s` on both: the later session shares the home when its
//!    first time since home is not before the training's last, until its
//!    time since home steps back (a new capture).
//! 3. `t_s` alone: sessions whose clocks continue one another (the later
//!    session's first `t_s` not before the training's last) share a home; a
//!    session whose `t_s` starts again before it follows a new one.

use serde::{Deserialize, Serialize};

use crate::data::dataset::{Sample, Session};
use crate::data::observe::Observation;

/// What told which home a later session follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HomeBasis {
    /// The sessions' `home` columns.
    HomeId,
    /// The sessions' `since_home_s` columns.
    SinceHome,
    /// The sessions' `t_s` clocks.
    Clock,
    /// Nothing to compare with: the training session has no rows, or
    /// (a calibration's home capture, [`LaterHome::under`]) the later
    /// session does not record `home`.
    Unknown,
}

/// Which home capture a later session's rows count from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LaterHome {
    /// Index (session row) of the later session's first row that follows a
    /// new home capture; the session's length when every row shares the
    /// training session's home, 0 when none does.
    pub first_new_home_row: usize,
    /// Rows in the later session.
    pub rows: usize,
    pub basis: HomeBasis,
    /// Why, in a sentence the report prints.
    pub reason: String,
}

impl LaterHome {
    /// Every row of the later session shares the training session's home.
    pub fn shares_home(&self) -> bool {
        self.first_new_home_row == self.rows
    }

    /// Marks the rows of `observations` (this later session's, set-aside
    /// rows left out) that follow a new home capture
    /// ([`Observation::new_home`]); the others share the training
    /// session's ([`rows_under_the_training_home`](crate::data::observe::rows_under_the_training_home)
    /// counts them).
    pub fn mark(&self, observations: &mut [Observation]) {
        for o in observations {
            o.new_home = o.row >= self.first_new_home_row;
        }
    }

    /// Which home `later`'s rows follow, after `training`.
    pub fn of(training: &Session, later: &Session) -> LaterHome {
        let rows = later.samples.len();
        let (Some(last), Some(first)) = (training.samples.last(), later.samples.first()) else {
            return LaterHome {
                first_new_home_row: 0,
                rows,
                basis: HomeBasis::Unknown,
                reason: "a new home capture: the training session has no row to continue".into(),
            };
        };
        let every = |s: &Session, has: fn(&Sample) -> bool| s.samples.iter().all(has);
        let (k, basis, reason) =
            if every(training, |s| s.home.is_some()) && every(later, |s| s.home.is_some()) {
                by_home_id(last.home.unwrap_or_default(), later)
            } else if every(training, |s| s.since_home_s.is_some())
                && every(later, |s| s.since_home_s.is_some())
            {
                by_since_home(last, later)
            } else {
                by_clock(last, first, rows)
            };
        LaterHome {
            first_new_home_row: k,
            rows,
            basis,
            reason,
        }
    }

    /// Which of `later`'s rows are under home capture `home_id`, the one a
    /// calibration's training slips belong to (`calibration.json`'s
    /// `home`, a blob's), when the training session is not at hand: the
    /// `home` ids alone, by rule 1. A session that does not record `home`
    /// on every row cannot be matched to the capture: every row is taken
    /// as after a new one.
    pub fn under(home_id: u64, later: &Session) -> LaterHome {
        let rows = later.samples.len();
        if rows == 0 || !later.samples.iter().all(|s| s.home.is_some()) {
            return LaterHome {
                first_new_home_row: 0,
                rows,
                basis: HomeBasis::Unknown,
                reason: format!(
                    "the session does not record its home capture on every row (`home`), so no \
                     row can be matched to home capture {home_id}: every row is taken as after a \
                     new one"
                ),
            };
        }
        let (first_new_home_row, basis, reason) = by_home_id(home_id, later);
        LaterHome {
            first_new_home_row,
            rows,
            basis,
            reason,
        }
    }
}

fn share_sentence(k: usize, rows: usize) -> String {
    if k == rows {
        "every row shares the training session's home capture (its slips and drifts go on)".into()
    } else if k == 0 {
        "every row follows a new home capture (the training session's slips are not in it)".into()
    } else {
        format!(
            "rows before line {} share the training session's home capture, the {} rows from it \
             on follow a new one",
            k + 2,
            rows - k
        )
    }
}

fn by_home_id(home: u64, later: &Session) -> (usize, HomeBasis, String) {
    let rows = later.samples.len();
    let k = later
        .samples
        .iter()
        .position(|s| s.home != Some(home))
        .unwrap_or(rows);
    let reason = format!(
        "`home`: the training session ends under home capture {home}; {}",
        share_sentence(k, rows)
    );
    (k, HomeBasis::HomeId, reason)
}

fn by_since_home(last: &Sample, later: &Session) -> (usize, HomeBasis, String) {
    let end = last.since_home_s.unwrap_or_default();
    let rows = later.samples.len();
    let times: Vec<f64> = later
        .samples
        .iter()
        .map(|s| s.since_home_s.unwrap_or_default())
        .collect();
    let k = if times[0] < end {
        0
    } else {
        times
            .windows(2)
            .position(|w| w[1] < w[0])
            .map_or(rows, |i| i + 1)
    };
    let reason = format!(
        "`since_home_s`: the training session ends {end} s after its home capture and the test \
         session starts {} s after its own; {}",
        times[0],
        share_sentence(k, rows)
    );
    (k, HomeBasis::SinceHome, reason)
}

fn by_clock(last: &Sample, first: &Sample, rows: usize) -> (usize, HomeBasis, String) {
    let k = if first.t_s >= last.t_s { rows } else { 0 };
    let how = if k == rows {
        "continues the training session's clock"
    } else {
        "starts its clock again"
    };
    let reason = format!(
        "`t_s` (no `home` or `since_home_s` columns): the test session starts at {} s, the \
         training session ends at {} s, so the test session {how}; {}",
        first.t_s,
        last.t_s,
        share_sentence(k, rows)
    );
    (k, HomeBasis::Clock, reason)
}

/// The home capture a training session ends under, as a device can match
/// it: the `home` id of its last row, when the rows of that capture (the
/// session's last rows sharing the id) record both their `home` and their
/// `since_home_s`. The training's slips are times since a capture; a
/// device still under the last one applies those of it (decision record
/// 0049, "Device side").
///
/// A session that spans several captures is fitted as one: every time
/// term reads each row's own time since its capture
/// ([`crate::data::observe::time_since_home_ms`]), so a slip term at `at_s`
/// shifts every row, of any capture, at least `at_s` after its own. A
/// slip is the last capture's ([`TrainingHome::slip_is_of_last_capture`])
/// when no row of an earlier capture is that late: it was fitted on the
/// last capture's rows alone, its `at_s` a time since that capture.
/// Otherwise it is an earlier capture's (no row of the last one is that
/// late: the slip is over with its capture) or was fitted across captures
/// (it shifted rows of both, so its size and time are those of neither).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainingHome {
    /// The capture's id (`State::home_id`); `None` when the session does
    /// not tell one a device can match.
    pub home_id: Option<u64>,
    /// Home captures the session spans (its `home` ids in row order; 1
    /// without a `home` column).
    pub captures: usize,
    /// The session's first row (index) under the last capture.
    pub first_row: usize,
    /// The latest time since its own capture of a row before `first_row`
    /// (as the time terms read it, s); `None` when the session is under
    /// one capture.
    pub earlier_until_s: Option<f64>,
    /// The latest time since the last capture of a row under it, s.
    pub last_until_s: f64,
    /// Why, in words the report prints.
    pub reason: String,
}

impl TrainingHome {
    /// The home capture `training` ends under, or why none.
    pub fn of(training: &Session) -> TrainingHome {
        let samples = &training.samples;
        let captures = if samples.is_empty() {
            0
        } else {
            1 + samples
                .windows(2)
                .filter(|w| w[0].home != w[1].home)
                .count()
        };
        let none = |reason: String| TrainingHome {
            home_id: None,
            captures,
            first_row: 0,
            earlier_until_s: None,
            last_until_s: 0.0,
            reason,
        };
        let Some(home) = samples.last().map(|s| s.home) else {
            return none("the training session has no rows".into());
        };
        let Some(home) = home else {
            return none(
                "the training session does not record its home capture (no `home` column, or \
                 none on its last row): no device state can be matched to it"
                    .into(),
            );
        };
        let first_row = samples
            .iter()
            .rposition(|s| s.home != Some(home))
            .map_or(0, |k| k + 1);
        let (earlier, last) = samples.split_at(first_row);
        if !last.iter().all(|s| s.since_home_s.is_some()) {
            return none(format!(
                "the training session has no `since_home_s` column{}: its slips' times are not \
                 times since its home capture",
                if first_row > 0 {
                    " on the rows of its last home capture"
                } else {
                    ""
                }
            ));
        }
        if earlier.iter().any(|s| s.home == Some(home)) {
            return none(format!(
                "the rows of home capture {home} are not consecutive in the training session \
                 (`home`): it cannot tell which capture it ends under"
            ));
        }
        let until_s = |rows: &[Sample]| {
            rows.iter()
                .map(crate::data::observe::time_since_home_ms)
                .max()
                .map(|ms| f64::from(ms) / 1000.0)
        };
        let earlier_until_s = until_s(earlier);
        let last_until_s = until_s(last).unwrap_or_default();
        let reason = match earlier_until_s {
            None => format!("the training session is under home capture {home} (`home`)"),
            Some(until) => format!(
                "the training session spans {captures} home captures (`home`) and ends under \
                 {home}, from line {} on; the rows of the earlier ones run to {until} s after \
                 their own capture",
                first_row + 2
            ),
        };
        TrainingHome {
            home_id: Some(home),
            captures,
            first_row,
            earlier_until_s,
            last_until_s,
            reason,
        }
    }

    /// Which captures' rows a slip term from `at_s` (time since home)
    /// shifted in the fit: the rows `at_s` or more after their own capture
    /// (what every time term reads). Always [`SlipRows::Last`] for a
    /// session under one capture.
    pub fn rows_of_slip(&self, at_s: f64) -> SlipRows {
        let earlier = self.earlier_until_s.is_some_and(|until| until >= at_s);
        match (earlier, self.last_until_s >= at_s) {
            (false, _) => SlipRows::Last,
            (true, false) => SlipRows::Earlier,
            (true, true) => SlipRows::Both,
        }
    }

    /// Whether a slip term from `at_s` is the last capture's
    /// ([`TrainingHome::rows_of_slip`]): a device under it can apply it.
    pub fn slip_is_of_last_capture(&self, at_s: f64) -> bool {
        self.rows_of_slip(at_s) == SlipRows::Last
    }
}

/// Which of a training session's home captures a slip term shifted
/// ([`TrainingHome::rows_of_slip`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SlipRows {
    /// The last capture's rows alone (or none of an earlier one).
    Last,
    /// Rows of earlier captures alone: a slip of a capture that is over.
    Earlier,
    /// Rows of an earlier capture and of the last: fitted across them.
    Both,
}

#[cfg(test)]
mod tests;
