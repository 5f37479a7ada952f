//! Tracker outliers: training rows whose tracker disagrees with most of
//! their strings (a glitch of the tracker), which the loop sets aside
//! before it fits and judges.

use serde::{Deserialize, Serialize};

use crate::data::observe::Observation;
use crate::data::stats::median;
use spidar_core::string_law::StringHome;

use crate::model::identify::{residuals_at_homes, Identification};

/// A training row's tracker may be this many times the median
/// disagreement of the rows' tracker with their strings (see
/// [`TrackerOutliers`]), and [`GROSS_TRACKER_FLOOR_MM`], before the loop
/// sets it aside.
pub const GROSS_TRACKER_MEDIANS: f64 = 20.0;
/// The least disagreement (mm) at which a row's tracker is set aside: more
/// than a slip or a missing effect puts a string off.
pub const GROSS_TRACKER_FLOOR_MM: f64 = 10.0;
/// The disagreement (mm) beyond which a tracker position is a glitch, for
/// a median disagreement of `median_mm`: [`GROSS_TRACKER_MEDIANS`] times
/// it, and at least [`GROSS_TRACKER_FLOOR_MM`].
pub fn gross_tracker_threshold_mm(median_mm: f64) -> f64 {
    (GROSS_TRACKER_MEDIANS * median_mm).max(GROSS_TRACKER_FLOOR_MM)
}

/// Above this share of the tracked rows, rows far off are not a tracker's
/// glitches but a model that does not fit: none is set aside.
pub const GROSS_TRACKER_MAX_SHARE: f64 = 0.25;

/// Training rows whose tracker position disagrees with most of their
/// strings under the base model: a glitch of the tracker (a reflection, a
/// swapped marker, a lost marker written as `0, 0, 0`), not a position the
/// strings can tell. A row's disagreement is the median over its strings
/// of `| |p - anchor_i| - L_i |` (`p` the tracker in the device frame,
/// `L_i` the model's length): a faulty string is one of them and leaves the
/// median alone, a wrong tracker moves most of them. The robust
/// identification weighs such rows out, but the loop judges changes by
/// held-out means and quantiles, which a few of them dominate: a few
/// percent of rows thrown tens to hundreds of mm put the held-out mean the
/// changes are judged against an order of magnitude up, and the loop then
/// misses effects (decision record 0039,
/// `docs/decisions/0039-tracker-glitches.md`). The loop fits and judges
/// without their tracker (as occluded rows), and the report lists them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrackerOutliers {
    /// Indices (into the observations given) of the rows set aside; not
    /// written (they index this run's observations).
    #[serde(skip)]
    pub rows: Vec<usize>,
    /// Their lines in the session file ([`Observation::row`] + 2: the header
    /// is line 1).
    pub lines: Vec<usize>,
    /// Their disagreement with their strings under the first base
    /// identification, mm.
    pub errors_mm: Vec<f64>,
    /// The median disagreement of the tracked rows, mm.
    pub median_mm: f64,
    /// The disagreement beyond which a row is set aside, mm.
    pub threshold_mm: f64,
    /// Rows beyond the threshold that were kept, because they are more
    /// than [`GROSS_TRACKER_MAX_SHARE`] of the tracked rows.
    pub kept_too_many: usize,
}

impl TrackerOutliers {
    /// The rows of `train` whose tracker disagrees with their strings under
    /// `id` beyond the threshold.
    pub fn of(id: &Identification, train: &[Observation]) -> TrackerOutliers {
        Self::beyond(id, train, gross_tracker_threshold_mm)
    }

    /// The rows of another session (the test session) whose tracker
    /// disagrees with their strings under `id` beyond `threshold_mm` (the
    /// training session's).
    pub fn of_session(
        id: &Identification,
        session: &[Observation],
        threshold_mm: f64,
    ) -> TrackerOutliers {
        Self::beyond(id, session, |_| threshold_mm)
    }

    /// The rows of `session` beyond the threshold `threshold` gives for the
    /// median disagreement of its tracked rows.
    fn beyond(
        id: &Identification,
        session: &[Observation],
        threshold: impl FnOnce(f64) -> f64,
    ) -> TrackerOutliers {
        let disagreement = tracker_disagreement(id, session);
        let tracked = disagreement.len();
        let median_mm = median(&mut disagreement.iter().map(|d| d.1).collect::<Vec<_>>());
        let threshold_mm = threshold(median_mm);
        let far: Vec<(usize, f64)> = disagreement
            .into_iter()
            // A row the model cannot place (NaN) is as far as one can be.
            .filter(|(_, e)| e.is_nan() || *e > threshold_mm)
            .collect();
        if far.len() as f64 > GROSS_TRACKER_MAX_SHARE * tracked as f64 {
            return TrackerOutliers {
                median_mm,
                threshold_mm,
                kept_too_many: far.len(),
                ..TrackerOutliers::default()
            };
        }
        TrackerOutliers {
            rows: far.iter().map(|f| f.0).collect(),
            lines: far.iter().map(|f| session[f.0].row + 2).collect(),
            errors_mm: far.iter().map(|f| f.1).collect(),
            median_mm,
            threshold_mm,
            kept_too_many: 0,
        }
    }

    /// `train` without the tracker of the rows set aside (`None`: none).
    pub fn without(&self, train: &[Observation]) -> Option<Vec<Observation>> {
        if self.rows.is_empty() {
            return None;
        }
        let mut out = train.to_vec();
        for &k in &self.rows {
            if let Some(o) = out.get_mut(k) {
                o.tracker = None;
                o.tracker_rotation = None;
            }
        }
        Some(out)
    }
}

/// Each tracked row of `session` (its index) and the median over its
/// strings of `| |p - anchor_i| - L_i |` under `id`, mm.
fn tracker_disagreement(id: &Identification, session: &[Observation]) -> Vec<(usize, f64)> {
    let strings = id.frame.layout;
    // A row after a new home capture reads without the training's slips.
    let new_home = id.for_a_new_session();
    let homes = StringHome::of_every_string(&id.frame);
    session
        .iter()
        .enumerate()
        .filter(|(_, o)| o.tracker.is_some())
        .map(|(k, o)| {
            let effects = if o.new_home {
                &new_home.effects
            } else {
                &id.effects
            };
            let r = residuals_at_homes(&id.frame, &homes, &id.laws, effects, o);
            let mut abs: Vec<f64> = strings.indices().map(|i| r[i].abs()).collect();
            (k, median(&mut abs))
        })
        .collect()
}
