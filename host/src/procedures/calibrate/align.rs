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

use crate::data::observe::Observation;
use crate::device::tracker::sync::{CoarseShift, ShiftConfig, SyncError, TimeShift, TimedPosition};

/// Rows further apart than this (median, s) make a static session.
pub const MAX_STREAM_INTERVAL_S: f64 = 0.1;
/// How far a row interval read from decimal times may exceed the stream
/// interval it was written at (s).
const STEP_ROUNDING_S: f64 = 1e-6;
/// Largest clock offset searched (s).
pub const MAX_OFFSET_S: f64 = 5.0;
/// The identification and the alignment are alternated until the offset
/// moves by less than this (s) or twice its standard deviation ...
pub const OFFSET_SETTLED_S: f64 = 0.0005;
/// ... or this many rounds have run.
pub const MAX_ALIGN_ROUNDS: usize = 6;
/// A clock-rate difference is kept when it is this many standard
/// deviations from 0 ...
pub const DRIFT_SIGNIFICANCE: f64 = 3.0;
/// ... and moves the stream's ends by at least this much (s) ...
pub const DRIFT_MIN_EFFECT_S: f64 = 0.001;
/// ... on a stream at least this long (s); else the offset is fitted alone.
pub const DRIFT_MIN_SPAN_S: f64 = 60.0;

/// How an alignment takes the clocks' rate difference.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ClockRate {
    /// The offset alone: one rate assumed.
    Same,
    /// Fitted with the offset where the data tell it (`DRIFT_*`).
    Fitted,
    /// Known from another session of the same two clocks (the training
    /// stream's): the rate of two oscillators holds from one recording to
    /// the next, the offset does not (a logger restarted).
    Known { drift_ppm: f64, drift_sd_ppm: f64 },
}

impl ClockRate {
    /// The rate `timing` found, for a later session of the same clocks:
    /// `Same` where it found none.
    pub fn of(timing: &SessionTiming) -> ClockRate {
        match timing {
            SessionTiming::Aligned(a) if a.drift_ppm != 0.0 => ClockRate::Known {
                drift_ppm: a.drift_ppm,
                drift_sd_ppm: a.drift_sd_ppm,
            },
            _ => ClockRate::Same,
        }
    }
}

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
    /// A stream whose rows the user declared paired by one clock
    /// (`calibrate --clocks-paired`): read as written, no offset searched.
    Paired {
        /// Median time between rows (s).
        median_interval_s: f64,
        rows: usize,
    },
}

/// The tracker-minus-device clock offset of a dynamic session.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ClockAlignment {
    /// `tracker time - device time` (s) at device time `reference_t_s`: the
    /// row stamped `t` holds where the marker was at `t - offset_s` there.
    pub offset_s: f64,
    /// One standard deviation of `offset_s` (s).
    pub offset_sd_s: f64,
    /// How much faster the tracker's clock runs, parts per million (0 when
    /// the data do not tell it from nothing): the offset at device time `t`
    /// is `offset_s + 1e-6 drift_ppm (t - reference_t_s)`.
    pub drift_ppm: f64,
    /// One standard deviation of `drift_ppm` (0 when not kept).
    pub drift_sd_ppm: f64,
    /// The device time `offset_s` refers to (the middle of the stream), s.
    pub reference_t_s: f64,
    /// Peak correlation of the speed profiles (-1..1).
    pub correlation: f64,
    /// Rows paired in the fit.
    pub pairs: usize,
    /// Rows that lost their tracker position (outside the tracker's span
    /// at the new pairing, or across a gap).
    pub rows_unpaired: usize,
    /// Whether the positions confirmed the speed profiles' peak (the fine
    /// fit was determined to within the row interval); `false`: the offset
    /// is the peak's, to the row interval.
    pub refined: bool,
    /// The offset the alignment found (s), when the loop then found a
    /// latency every string shares and `offset_s` is that offset moved by
    /// it: the alignment's quick model had no latency of one string, and
    /// the shared latency is the offset's error (decision record 0064).
    /// Absent when the alignment's offset stands.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_offset_s: Option<f64>,
}

impl ClockAlignment {
    /// The tracker's time of device time `t_s`: the offset there, the
    /// clocks' rate difference included.
    pub fn tracker_time(&self, t_s: f64) -> f64 {
        t_s + self.offset_s + 1e-6 * self.drift_ppm * (t_s - self.reference_t_s)
    }
}

/// The longest gap in `obs`'s tracker stream a re-paired row is
/// interpolated across: four of its tracked intervals.
fn max_gap_s(obs: &[Observation]) -> f64 {
    4.0 * tracked_interval_s(obs).unwrap_or(MAX_STREAM_INTERVAL_S)
}

/// Why a dynamic session could not be aligned.
#[derive(Debug, thiserror::Error)]
#[error("tracker clock alignment: {0}")]
pub struct AlignError(#[from] pub crate::device::tracker::sync::SyncError);

/// Median time between consecutive rows that are apart in time (s); `None`
/// with no two such rows. Rows of one instant (a logger that wrote a row
/// twice) do not count: with every row written twice the median would be
/// 0, and the alignment would fail on "`max_gap_s`: 0 is not a positive
/// duration" (decision record 0013, `docs/decisions/0013-clock-offsets.md`).
pub fn median_interval_s(obs: &[Observation]) -> Option<f64> {
    median_step_s(obs.iter().map(|o| o.t_s))
}

/// Median time between consecutive *tracked* rows that are apart in time
/// (s): the tracker stream's period, which bounds the gaps the alignment
/// bridges. A log of device states at 1 kHz with a 100 Hz tracker's
/// positions on every tenth row has a row interval of 1 ms; gaps bounded by
/// it left no tracker sample bridged ("the streams overlap in 0 samples").
pub fn tracked_interval_s(obs: &[Observation]) -> Option<f64> {
    median_step_s(obs.iter().filter(|o| o.tracker.is_some()).map(|o| o.t_s))
}

/// The median of the positive steps between consecutive `times` (s).
pub(crate) fn median_step_s(times: impl Iterator<Item = f64>) -> Option<f64> {
    let times: Vec<f64> = times.collect();
    let mut d: Vec<f64> = times
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|&dt| dt > 0.0)
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

/// `Some(static timing)` when `obs` is not a stream to align: its rows are
/// further apart than a stream's. A stream however short is aligned (its
/// tracker's clock may be seconds off), or refused when that fails: read
/// as poses, its rows would pair the strings with the marker from
/// elsewhere.
pub fn static_timing(obs: &[Observation]) -> Option<SessionTiming> {
    let interval = median_interval_s(obs).unwrap_or(f64::INFINITY);
    // Times written in decimal differ by a little more than their step
    // (0.30000000000000004 - 0.2): a 10 Hz stream is a stream to a
    // microsecond.
    (interval > MAX_STREAM_INTERVAL_S + STEP_ROUNDING_S).then_some(SessionTiming::Static {
        median_interval_s: interval,
        rows: obs.len(),
    })
}

/// The timing of a session whose rows were paired by one clock when
/// logged: a stream read as written ([`SessionTiming::Paired`]), or one
/// pose per row ([`static_timing`]).
pub fn paired_timing(obs: &[Observation]) -> SessionTiming {
    static_timing(obs).unwrap_or(SessionTiming::Paired {
        median_interval_s: median_interval_s(obs).unwrap_or(f64::NAN),
        rows: obs.len(),
    })
}

/// The clock offset between the tracker positions of `obs` and `positions`
/// (room frame, mm; one per row, `None` where the model has none), and with
/// `drift` the clocks' rate difference too.
pub fn estimate_offset(
    obs: &[Observation],
    positions: &[Option<[f64; 3]>],
    prior_offset_s: f64,
    drift: bool,
) -> Result<TimeShift, AlignError> {
    with_coarse_shift(obs, positions, prior_offset_s, None, |c| c.refined(drift))
}

/// `fit` on the speed profiles' coarse search between the tracker
/// positions of `obs` and `positions` (as [`estimate_offset`] reads them),
/// made once for the fine fits `fit` asks of it (with a drift and without).
fn with_coarse_shift(
    obs: &[Observation],
    positions: &[Option<[f64; 3]>],
    prior_offset_s: f64,
    known_rate: Option<(f64, f64)>,
    fit: impl FnOnce(&CoarseShift<'_>) -> Result<TimeShift, SyncError>,
) -> Result<TimeShift, AlignError> {
    // A known rate (s per s, about device time `reference`) moves each
    // device time to the tracker's rate before the offset is searched.
    let on_tracker_rate = |t_s: f64| match known_rate {
        Some((rate, reference)) => t_s + rate * (t_s - reference),
        None => t_s,
    };
    let device: Vec<TimedPosition> = obs
        .iter()
        .zip(positions)
        .filter_map(|(o, p)| {
            p.map(|position_mm| TimedPosition {
                t_s: on_tracker_rate(o.t_s),
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
    let interval = tracked_interval_s(obs).unwrap_or(MAX_STREAM_INTERVAL_S);
    let config = ShiftConfig {
        prior_offset_s,
        max_shift_s: MAX_OFFSET_S,
        grid_step_s: None,
        // A gap of a few missing rows (an occlusion) is not bridged.
        max_gap_s: 4.0 * interval,
        // Not read by the coarse search: `fit` says, through
        // `CoarseShift::refined`.
        estimate_drift: false,
        max_iterations: 50,
    };
    Ok(fit(&CoarseShift::of(&device, &tracker, &config)?)?)
}

/// `obs` re-paired by `offset_s`: each row's tracker position is the
/// tracker stream (as recorded, on its own clock) interpolated at
/// `t_s + offset_s`; `None` outside the stream or across a gap longer than
/// `max_gap_s`. Returns the rows and how many lost their position.
/// The body's orientation, when the tracker gives one, is re-paired with
/// its position: interpolated (slerp) between the same two recorded rows,
/// `None` when either has none.
pub fn repaired(obs: &[Observation], offset_s: f64, max_gap_s: f64) -> (Vec<Observation>, usize) {
    repaired_at(obs, |t| t + offset_s, max_gap_s)
}

/// [`repaired`] with the tracker's time of each device time given by
/// `tracker_time` (an offset that drifts).
pub fn repaired_at(
    obs: &[Observation],
    tracker_time: impl Fn(f64) -> f64,
    max_gap_s: f64,
) -> (Vec<Observation>, usize) {
    type Rotation = [[f64; 3]; 3];
    let stream: Vec<(f64, [f64; 3], Option<Rotation>)> = obs
        .iter()
        .filter_map(|o| o.tracker.map(|p| (o.t_s, p, o.tracker_rotation)))
        .collect();
    let at = |t: f64| -> Option<([f64; 3], Option<Rotation>)> {
        let k = stream.partition_point(|s| s.0 <= t);
        if k == 0 {
            return None;
        }
        let (ta, a, ra) = stream[k - 1];
        if ta == t {
            return Some((a, ra));
        }
        let (tb, b, rb) = *stream.get(k)?;
        if tb - ta > max_gap_s {
            return None;
        }
        let f = (t - ta) / (tb - ta);
        let rotation = ra.zip(rb).map(|(ra, rb)| slerp(&ra, &rb, f));
        Some((core::array::from_fn(|i| a[i] + f * (b[i] - a[i])), rotation))
    };
    let mut lost = 0;
    let out = obs
        .iter()
        .map(|o| {
            let mut o = o.clone();
            let had = o.tracker.is_some();
            let seen = at(tracker_time(o.t_s));
            o.tracker = seen.map(|s| s.0);
            o.tracker_rotation = seen.and_then(|s| s.1);
            lost += usize::from(had && o.tracker.is_none());
            o
        })
        .collect();
    (out, lost)
}

/// The rotation a fraction `f` of the way from `a` to `b` (row-major
/// matrices), along the shortest arc. The matrices are rotations already
/// (made from the reader's unit quaternions), taken as they are:
/// `Rotation3::from_matrix`'s search, started from the identity, lands on
/// a wrong rotation for some exact half turns.
fn slerp(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3], f: f64) -> [[f64; 3]; 3] {
    use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
    let q = |m: &[[f64; 3]; 3]| {
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_fn(
            |r, c| m[r][c],
        )))
    };
    let m = q(a).slerp(&q(b), f).to_rotation_matrix();
    core::array::from_fn(|r| core::array::from_fn(|c| m[(r, c)]))
}

/// The report's note for an aligned training stream too short for its
/// clocks' rate to be fitted ([`DRIFT_MIN_SPAN_S`]): what was assumed and
/// what it costs (a 59.99 s stream at 200 ppm was paired 6 ms off at its
/// ends, 3 mm, and nothing said a rate was not tried).
pub fn rate_not_fitted_note(timing: &SessionTiming) -> Option<String> {
    let SessionTiming::Aligned(a) = timing else {
        return None;
    };
    // The offset refers to the middle of the stream's placed rows, and a
    // session's `t_s` starts near 0 (the format refuses a clock's
    // timestamp): twice it is the span the alignment saw.
    let span_s = 2.0 * a.reference_t_s;
    (a.drift_ppm == 0.0 && span_s < DRIFT_MIN_SPAN_S).then(|| {
        format!(
            "the training stream's clocks were taken to run at one rate: over its {span_s:.1} s \
             a rate is not told from the model's own errors ({DRIFT_MIN_SPAN_S:.0} s or more \
             are); a tracker clock 100 ppm fast would pair its ends {:.1} ms off",
            0.1 * span_s * 0.5
        )
    })
}

/// Whether `obs` spans long enough for its own clocks' rate to be told
/// from the model's errors ([`DRIFT_MIN_SPAN_S`]).
pub fn tells_a_rate(obs: &[Observation]) -> bool {
    span_s(obs) >= DRIFT_MIN_SPAN_S
}

fn span_s(obs: &[Observation]) -> f64 {
    obs.first()
        .zip(obs.last())
        .map_or(0.0, |(a, b)| b.t_s - a.t_s)
}

/// Aligns `obs` with positions from `model_positions` (room frame, one per
/// row): the offset, its uncertainty, and the re-paired rows.
pub fn align(
    obs: &[Observation],
    model_positions: &[Option<[f64; 3]>],
    prior_offset_s: f64,
    rate: ClockRate,
) -> Result<(ClockAlignment, Vec<Observation>), AlignError> {
    // With `drift`, the clocks' rate difference is kept where it matters
    // and the data tell it from nothing: beyond DRIFT_SIGNIFICANCE standard
    // deviations, and moving the stream's ends by DRIFT_MIN_EFFECT_S or
    // more, on a stream of DRIFT_MIN_SPAN_S or longer. A 120 s stream whose
    // tracker clock ran 100 ppm fast was paired 6 ms off at either end with
    // one offset (0.761 mm held out; 0.356 with the drift). Over a short
    // stream the model's own position errors, which follow the hand's path
    // and so its time, pass for a drift: a 10 s stream with none found
    // 428 +- 36 ppm, a 30 s one up to 70 ppm.
    let span_s = span_s(obs);
    let shift = if let ClockRate::Known {
        drift_ppm,
        drift_sd_ppm,
    } = rate
    {
        // The middle of the rows the model places: where the fine fit's
        // offset refers to on the moved times too.
        let placed: Vec<f64> = obs
            .iter()
            .zip(model_positions)
            .filter(|(_, p)| p.is_some())
            .map(|(o, _)| o.t_s)
            .collect();
        let reference = placed
            .first()
            .zip(placed.last())
            .map_or(0.0, |(a, b)| 0.5 * (a + b));
        let rate = 1e-6 * drift_ppm;
        let shift = with_coarse_shift(
            obs,
            model_positions,
            prior_offset_s,
            Some((rate, reference)),
            |coarse| coarse.refined(false),
        )?;
        TimeShift {
            drift: rate,
            drift_std: 1e-6 * drift_sd_ppm,
            reference_t_s: reference,
            ..shift
        }
    } else if rate == ClockRate::Fitted && span_s >= DRIFT_MIN_SPAN_S {
        // One coarse search for both fine fits.
        with_coarse_shift(obs, model_positions, prior_offset_s, None, |coarse| {
            let with_drift = coarse.refined(true)?;
            if with_drift.drift.abs() > DRIFT_SIGNIFICANCE * with_drift.drift_std
                && with_drift.drift.abs() * 0.5 * span_s >= DRIFT_MIN_EFFECT_S
            {
                Ok(with_drift)
            } else {
                coarse.refined(false)
            }
        })?
    } else {
        estimate_offset(obs, model_positions, prior_offset_s, false)?
    };
    let interval = tracked_interval_s(obs).unwrap_or(MAX_STREAM_INTERVAL_S);
    // The fine fit compares positions: with a model far from the tracker
    // (the nominal geometry of a paper-sized device, 200 mm off) it is not
    // determined and wanders off the speed profiles' peak, and a model
    // identified on rows paired that far off keeps the next pass off too
    // (decision record 0013, `docs/decisions/0013-clock-offsets.md`). A
    // fine fit less certain than the profiles' grid step keeps the peak;
    // the second pass, with the identified model, refines it.
    let refined = shift.offset_std_s <= interval;
    let used = if refined {
        shift
    } else {
        // A known rate stays: the coarse search was made on its times.
        let known = matches!(rate, ClockRate::Known { .. });
        TimeShift {
            offset_s: shift.coarse_offset_s,
            offset_std_s: interval / 12f64.sqrt(),
            drift: if known { shift.drift } else { 0.0 },
            drift_std: if known { shift.drift_std } else { 0.0 },
            ..shift
        }
    };
    let (rows, lost) = repaired_at(obs, |t| used.tracker_time(t), max_gap_s(obs));
    Ok((
        ClockAlignment {
            offset_s: used.offset_s,
            offset_sd_s: used.offset_std_s,
            drift_ppm: used.drift * 1e6,
            drift_sd_ppm: used.drift_std * 1e6,
            reference_t_s: used.reference_t_s,
            correlation: used.correlation,
            pairs: used.pairs,
            rows_unpaired: lost,
            refined,
            first_offset_s: None,
        },
        rows,
    ))
}

/// `obs` (as recorded) re-paired by `a` with its offset moved by
/// `shift_s`, its rate kept; the alignment keeps `a`'s first offset
/// (`first_offset_s`) and counts the rows the new pairing lost.
pub fn shifted(
    obs: &[Observation],
    a: &ClockAlignment,
    shift_s: f64,
) -> (ClockAlignment, Vec<Observation>) {
    let moved = ClockAlignment {
        offset_s: a.offset_s + shift_s,
        first_offset_s: Some(a.first_offset_s.unwrap_or(a.offset_s)),
        ..a.clone()
    };
    let (rows, lost) = repaired_at(obs, |t| moved.tracker_time(t), max_gap_s(obs));
    (
        ClockAlignment {
            rows_unpaired: lost,
            ..moved
        },
        rows,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::observe::rotation_of_quaternion;
    use spidar_core::model::StringInputs;
    use spidar_core::STRINGS;

    fn about_z(deg: f64) -> [[f64; 3]; 3] {
        let h = deg.to_radians() / 2.0;
        rotation_of_quaternion([h.cos(), 0.0, 0.0, h.sin()])
    }

    fn row(t_s: f64, x: f64, rotation: Option<[[f64; 3]; 3]>) -> Observation {
        Observation {
            row: 0,
            t_s,
            inputs: StringInputs::default(),
            tension_n: [0.0; STRINGS],
            tracker: Some([x, 0.0, 0.0]),
            tracker_rotation: rotation,
            legacy: None,
            new_home: false,
        }
    }

    /// An alignment moved by a shift pairs the rows as the offset plus
    /// the shift does, its rate kept, and remembers the offset it was
    /// found at (moved twice: the first one).
    #[test]
    fn a_shifted_alignment_pairs_at_the_moved_offset_and_keeps_the_first() {
        let obs: Vec<Observation> = (0..50)
            .map(|k| row(k as f64 * 0.01, k as f64, None))
            .collect();
        let found = ClockAlignment {
            offset_s: 0.002,
            offset_sd_s: 1e-5,
            drift_ppm: 0.0,
            drift_sd_ppm: 0.0,
            reference_t_s: 0.25,
            correlation: 0.99,
            pairs: 50,
            rows_unpaired: 0,
            refined: true,
            first_offset_s: None,
        };
        let (moved, rows) = shifted(&obs, &found, 0.003);
        assert!((moved.offset_s - 0.005).abs() < 1e-15);
        assert_eq!(moved.first_offset_s, Some(0.002));
        let (expected, lost) = repaired(&obs, 0.005, 0.04);
        assert_eq!(moved.rows_unpaired, lost);
        for (a, b) in rows.iter().zip(&expected) {
            assert_eq!(a.tracker, b.tracker);
        }
        assert_eq!(rows[10].tracker.map(|p| (p[0] * 1e6).round()), Some(10.5e6));
        let (twice, _) = shifted(&obs, &moved, -0.001);
        assert_eq!(twice.first_offset_s, Some(0.002));
    }

    /// Rows written twice (one instant) do not make the interval 0.
    #[test]
    fn rows_of_one_instant_do_not_make_the_interval_zero() {
        let twice: Vec<Observation> = (0..10)
            .flat_map(|k| {
                let r = row(k as f64 * 0.01, 0.0, None);
                [r.clone(), r]
            })
            .collect();
        let interval = median_interval_s(&twice).unwrap();
        assert!((interval - 0.01).abs() < 1e-12, "{interval}");
        assert_eq!(median_interval_s(&twice[..2]), None);
    }

    /// Device rows at 1 ms, the tracker's position on every tenth: the
    /// tracker's period is 10 ms.
    #[test]
    fn the_tracked_interval_is_the_tracker_s_period() {
        let log: Vec<Observation> = (0..100)
            .map(|k| {
                let mut r = row(k as f64 * 0.001, 0.0, None);
                if k % 10 != 0 {
                    r.tracker = None;
                }
                r
            })
            .collect();
        assert!((median_interval_s(&log).unwrap() - 0.001).abs() < 1e-12);
        assert!((tracked_interval_s(&log).unwrap() - 0.01).abs() < 1e-12);
    }

    /// Re-paired rows take the body's orientation from the same two
    /// recorded rows as its position, halfway turned halfway; none where a
    /// recorded row has none.
    #[test]
    fn the_orientation_is_re_paired_with_the_position() {
        let obs = vec![
            row(0.0, 0.0, Some(about_z(0.0))),
            row(1.0, 10.0, Some(about_z(10.0))),
            row(2.0, 20.0, None),
        ];
        let (rows, lost) = repaired(&obs, 0.5, 5.0);
        assert_eq!(lost, 1);
        assert_eq!(rows[0].tracker, Some([5.0, 0.0, 0.0]));
        let r = rows[0].tracker_rotation.unwrap();
        let expected = about_z(5.0);
        for (a, b) in r.iter().flatten().zip(expected.iter().flatten()) {
            assert!((a - b).abs() < 1e-12, "{r:?}");
        }
        // Exact half turns (a body mounted upside down) interpolate too.
        let half = |axis: [f64; 3]| rotation_of_quaternion([0.0, axis[0], axis[1], axis[2]]);
        let upside = vec![
            row(0.0, 0.0, Some(half([0.0, 1.0, 0.0]))),
            row(1.0, 10.0, Some(half([0.0, 1.0, 0.0]))),
        ];
        let (turned, _) = repaired(&upside, 0.5, 5.0);
        let r = turned[0].tracker_rotation.unwrap();
        for (a, b) in r
            .iter()
            .flatten()
            .zip(half([0.0, 1.0, 0.0]).iter().flatten())
        {
            assert!((a - b).abs() < 1e-12, "{r:?}");
        }
        // Between a row with an orientation and one without: a position only.
        assert_eq!(rows[1].tracker, Some([15.0, 0.0, 0.0]));
        assert_eq!(rows[1].tracker_rotation, None);
        assert_eq!(rows[2].tracker, None);
    }
}
