//! The tracker's clock against the device's, found by the calibration.
//!
//! A session pairs each device row (counts at the device's time `t_s`) with
//! a tracker position. When the two streams were paired by timestamps of
//! two clocks that disagree (a tracker PC whose clock runs seconds ahead, a
//! logger that stamped tracker frames on arrival), each row carries the
//! marker where it was `offset` seconds earlier (or later), and every
//! string residual grows with the speed of the hand: a calibration fitted
//! on such pairs is wrong everywhere the hand moved.
//!
//! For a **dynamic** session (a stream: rows at 10 Hz or faster over a
//! moving end-effector) the offset is found from the data:
//! `tracker::sync::estimate_time_shift` (speed-profile cross-correlation,
//! then least squares with sub-frame interpolation) between the positions a
//! model gives from the counts and the tracker's, then every row gets the
//! tracker position interpolated at its own time on the tracker's clock
//! (`t_s + offset`); rows outside the tracker's span, or across a tracker gap,
//! become occluded, never paired with a stale position. Calibration runs it
//! twice: with the nominal model (good enough for the speed profiles), then
//! with the model identified from the first alignment (position residuals at
//! the tracker's noise, which is what makes the fine fit sharp).
//!
//! A **static** session (one pose per row: a lattice captured cell by cell,
//! the Hangprinter's 44 poses with `t_s` a pose index) has no time to align:
//! it is recognised by its row interval and left as it is.

use serde::Serialize;

use crate::observe::Observation;
use crate::tracker::sync::{estimate_time_shift, ShiftConfig, TimeShift, TimedPosition};

/// Rows further apart than this (median, s) make a static session.
pub const MAX_STREAM_INTERVAL_S: f64 = 0.1;
/// Fewest tracked rows a stream needs to be aligned.
pub const MIN_STREAM_ROWS: usize = 200;
/// Largest clock offset searched (s).
pub const MAX_OFFSET_S: f64 = 5.0;

/// What the calibration did about the clocks of one session.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SessionTiming {
    /// One pose per row: nothing to align.
    Static {
        /// Median time between rows (s).
        median_interval_s: f64,
        rows: usize,
    },
    /// A stream whose tracker positions were re-paired by the found offset.
    Aligned(ClockAlignment),
}

/// The tracker-minus-device clock offset of a dynamic session.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ClockAlignment {
    /// `tracker time - device time` (s): the row stamped `t` holds where
    /// the marker was at `t - offset_s`.
    pub offset_s: f64,
    /// One standard deviation of `offset_s` (s).
    pub offset_sd_s: f64,
    /// Peak correlation of the speed profiles (-1..1).
    pub correlation: f64,
    /// Rows paired in the fit.
    pub pairs: usize,
    /// Rows that lost their tracker position (outside the tracker's span
    /// at the new pairing, or across a gap).
    pub rows_unpaired: usize,
}

/// Why a dynamic session could not be aligned.
#[derive(Debug, thiserror::Error)]
#[error("tracker clock alignment: {0}")]
pub struct AlignError(#[from] pub crate::tracker::sync::SyncError);

/// Median time between consecutive rows (s); `None` with fewer than 2 rows.
pub fn median_interval_s(obs: &[Observation]) -> Option<f64> {
    let mut d: Vec<f64> = obs.windows(2).map(|w| w[1].t_s - w[0].t_s).collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

/// `Some(static timing)` when `obs` is not a stream to align.
pub fn static_timing(obs: &[Observation]) -> Option<SessionTiming> {
    let tracked = obs.iter().filter(|o| o.tracker.is_some()).count();
    let interval = median_interval_s(obs).unwrap_or(f64::INFINITY);
    (interval > MAX_STREAM_INTERVAL_S || tracked < MIN_STREAM_ROWS).then_some(
        SessionTiming::Static {
            median_interval_s: interval,
            rows: obs.len(),
        },
    )
}

/// The clock offset between the tracker positions of `obs` and `positions`
/// (room frame, mm; one per row, `None` where the model has none).
pub fn estimate_offset(
    obs: &[Observation],
    positions: &[Option<[f64; 3]>],
    prior_offset_s: f64,
) -> Result<TimeShift, AlignError> {
    let device: Vec<TimedPosition> = obs
        .iter()
        .zip(positions)
        .filter_map(|(o, p)| {
            p.map(|position_mm| TimedPosition {
                t_s: o.t_s,
                position_mm,
            })
        })
        .collect();
    let tracker: Vec<TimedPosition> = obs
        .iter()
        .filter_map(|o| {
            o.tracker.map(|position_mm| TimedPosition {
                t_s: o.t_s,
                position_mm,
            })
        })
        .collect();
    let interval = median_interval_s(obs).unwrap_or(MAX_STREAM_INTERVAL_S);
    let config = ShiftConfig {
        prior_offset_s,
        max_shift_s: MAX_OFFSET_S,
        grid_step_s: None,
        // A gap of a few missing rows (an occlusion) is not bridged.
        max_gap_s: 4.0 * interval,
        estimate_drift: false,
        max_iterations: 50,
    };
    Ok(estimate_time_shift(&device, &tracker, &config)?)
}

/// `obs` re-paired by `offset_s`: each row's tracker position is the
/// tracker stream (as recorded, on its own clock) interpolated at
/// `t_s + offset_s`; `None` outside the stream or across a gap longer than
/// `max_gap_s`. Returns the rows and how many lost their position.
pub fn repaired(obs: &[Observation], offset_s: f64, max_gap_s: f64) -> (Vec<Observation>, usize) {
    let stream: Vec<(f64, [f64; 3])> = obs
        .iter()
        .filter_map(|o| o.tracker.map(|p| (o.t_s, p)))
        .collect();
    let at = |t: f64| -> Option<[f64; 3]> {
        let k = stream.partition_point(|s| s.0 <= t);
        if k == 0 {
            return None;
        }
        let (ta, a) = stream[k - 1];
        if ta == t {
            return Some(a);
        }
        let (tb, b) = *stream.get(k)?;
        if tb - ta > max_gap_s {
            return None;
        }
        let f = (t - ta) / (tb - ta);
        Some(core::array::from_fn(|i| a[i] + f * (b[i] - a[i])))
    };
    let mut lost = 0;
    let out = obs
        .iter()
        .map(|o| {
            let mut o = o.clone();
            let had = o.tracker.is_some();
            o.tracker = at(o.t_s + offset_s);
            lost += usize::from(had && o.tracker.is_none());
            o
        })
        .collect();
    (out, lost)
}

/// Aligns `obs` with positions from `model_positions` (room frame, one per
/// row): the offset, its uncertainty, and the re-paired rows.
pub fn align(
    obs: &[Observation],
    model_positions: &[Option<[f64; 3]>],
    prior_offset_s: f64,
) -> Result<(ClockAlignment, Vec<Observation>), AlignError> {
    let shift = estimate_offset(obs, model_positions, prior_offset_s)?;
    let interval = median_interval_s(obs).unwrap_or(MAX_STREAM_INTERVAL_S);
    let (rows, lost) = repaired(obs, shift.offset_s, 4.0 * interval);
    Ok((
        ClockAlignment {
            offset_s: shift.offset_s,
            offset_sd_s: shift.offset_std_s,
            correlation: shift.correlation,
            pairs: shift.pairs,
            rows_unpaired: lost,
        },
        rows,
    ))
}
