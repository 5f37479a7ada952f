//! A session seen as the device sees it: per row, the run-time inputs of the
//! string law (counts, direction of motion, commanded tension, time since
//! home), plus the references (tracker, legacy controller).
//!
//! Direction comes from the same `encoder::DirectionTracker` the firmware
//! runs, fed with the recorded counts in session order; time since home is
//! the session's `since_home_s` when it has one, else its `t_s` (the
//! session's clock then starts at the home capture).
//!
//! The count rate (what a latency term reads) comes from the neighbouring
//! rows, and only on a session whose rows resolve the motion
//! ([`speed_observation`]): a lattice's rows are captured seconds apart
//! (at rest, or anywhere along the way), and a difference between them is
//! not the speed at the capture. Elsewhere it is 0: speed not observed.

use spidar_core::encoder::DirectionTracker;
use spidar_core::model::StringInputs;
use spidar_core::STRINGS;

use crate::data::dataset::Sample;

/// Hysteresis of the direction of motion, in counts (about 0.1 mm of string).
pub const DIRECTION_HYSTERESIS_COUNTS: u32 = 8;

/// One session row prepared for the model.
#[derive(Clone, Debug, PartialEq)]
pub struct Observation {
    /// Index of the row in the session (CSV line = row + 2).
    pub row: usize,
    pub t_s: f64,
    pub inputs: StringInputs,
    /// Commanded tensions in N (0 when the session has no tension columns).
    pub tension_n: [f64; STRINGS],
    /// Tracker position, room frame, mm; `None` while occluded.
    pub tracker: Option<[f64; 3]>,
    /// The tracked body's rotation into the room frame (row-major), when
    /// the tracker gives its orientation ([`Sample::orientation`]).
    pub tracker_rotation: Option<[[f64; 3]; 3]>,
    /// Legacy controller position, device frame, mm, when recorded.
    pub legacy: Option<[f64; 3]>,
    /// The row follows a home capture later than the training session's
    /// ([`crate::data::home`]): the strings are counted from where they
    /// were then, so the training session's slips are not in it. Set on a
    /// later session's rows only (false on the training session's).
    pub new_home: bool,
}

/// How many of a later session's first rows share the training session's
/// home capture: those before its first row after a new one
/// ([`Observation::new_home`]; a home capture is not undone).
pub fn rows_under_the_training_home(observations: &[Observation]) -> usize {
    observations
        .iter()
        .position(|o| o.new_home)
        .unwrap_or(observations.len())
}

/// The time since home a row's time terms read (the string law's input):
/// its `since_home_s`, else its `t_s`, in whole ms.
pub fn time_since_home_ms(s: &Sample) -> u32 {
    (s.since_home_s.unwrap_or(s.t_s) * 1000.0)
        .round()
        .clamp(0.0, u32::MAX as f64) as u32
}

/// The observations of a session's rows, in order.
pub fn observations(samples: &[Sample]) -> Vec<Observation> {
    observations_skipping(samples, &[])
}

/// The observations of a session's rows but `skipped` (ascending row
/// indices: rows set aside whole, [`crate::data::impossible`]), in order;
/// every observation keeps its row's index, and the direction of motion
/// is followed over the rows kept.
pub fn observations_skipping(samples: &[Sample], skipped: &[usize]) -> Vec<Observation> {
    let mut trackers: Vec<DirectionTracker> = (0..STRINGS)
        .map(|_| DirectionTracker::new(DIRECTION_HYSTERESIS_COUNTS))
        .collect();
    let mut skipped = skipped.iter().peekable();
    let mut observations: Vec<Observation> = samples
        .iter()
        .enumerate()
        .filter(|(row, _)| {
            while skipped.next_if(|&&k| k < *row).is_some() {}
            skipped.next_if(|&&k| k == *row).is_none()
        })
        .map(|(row, s)| {
            let tension_n = s.tension_n.unwrap_or([0.0; STRINGS]);
            let mut inputs = StringInputs {
                counts: s.counts,
                time_ms: time_since_home_ms(s),
                ..StringInputs::default()
            };
            for i in 0..STRINGS {
                inputs.direction[i] = trackers[i].update(s.counts[i]);
                inputs.tension_mn[i] =
                    (tension_n[i] * 1000.0).round().clamp(0.0, u16::MAX as f64) as u16;
            }
            Observation {
                row,
                t_s: s.t_s,
                inputs,
                tension_n,
                tracker: s.tracker,
                tracker_rotation: s.orientation.map(rotation_of_quaternion),
                legacy: s.legacy,
                new_home: false,
            }
        })
        .collect();
    if speed_observation(&observations).stream {
        fill_count_rates(&mut observations);
    }
    observations
}

/// Whether `observations` carry count rates (a stream's rows,
/// [`speed_observation`]): what a latency term can be told from.
pub fn observes_speed(observations: &[Observation]) -> bool {
    observations
        .iter()
        .any(|o| o.inputs.count_rate_cps.iter().any(|&r| r != 0))
}

/// Whether a session's rows observe the strings' speed, and what says so.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SpeedObservation {
    /// The rows resolve the motion: each row's count rate is the
    /// difference of its neighbours.
    pub stream: bool,
    /// The median, over the (row, string) pairs that move, of how much a
    /// string's speed changes from the interval before a row to the one
    /// after it, relative to the speed (`|v+ - v-| / ((|v+| + |v-|) / 2)`;
    /// NaN without such pairs).
    pub speed_change: f64,
    /// How many (row, string) pairs moved by at least
    /// [`DIRECTION_HYSTERESIS_COUNTS`] on both sides of their row.
    pub moving: usize,
    /// Median time between rows (s; NaN with fewer than two times).
    pub median_interval_s: f64,
}

/// The rows resolve the motion when a moving string's speed changes by
/// less than this share of itself from one row interval to the next (the
/// median pair): the rows sample the motion at least four times in the
/// time its speed takes to change by its own size. A stream sampled at
/// 100 Hz changes by a few percent; a lattice's rows, captured after
/// pauses of their own length, by about the speed itself (the model
/// simulator's lattice: near 1; decision record 0048).
pub const MAX_STREAM_SPEED_CHANGE: f64 = 0.25;

/// [`SpeedObservation`] of `observations` (their times and counts, in
/// order): a stream when the median moving pair's speed changes by less
/// than [`MAX_STREAM_SPEED_CHANGE`] of itself between the intervals around
/// its row. Rows of one instant (a logger that wrote a row twice) are
/// passed over; a string moves on both sides of its row by at least
/// [`DIRECTION_HYSTERESIS_COUNTS`] (0.1 mm: a count's rounding is then an
/// eighth of it at most).
pub fn speed_observation(observations: &[Observation]) -> SpeedObservation {
    let distinct = distinct_times(observations);
    let mut changes = Vec::new();
    let min = f64::from(DIRECTION_HYSTERESIS_COUNTS);
    for w in distinct.windows(3) {
        let (a, b, c) = (
            &observations[w[0]],
            &observations[w[1]],
            &observations[w[2]],
        );
        for i in 0..STRINGS {
            let before = f64::from(b.inputs.counts[i]) - f64::from(a.inputs.counts[i]);
            let after = f64::from(c.inputs.counts[i]) - f64::from(b.inputs.counts[i]);
            if before.abs() < min || after.abs() < min {
                continue;
            }
            let v_before = before / (b.t_s - a.t_s);
            let v_after = after / (c.t_s - b.t_s);
            changes.push((v_after - v_before).abs() / ((v_after.abs() + v_before.abs()) / 2.0));
        }
    }
    let median = |v: &mut Vec<f64>| {
        if v.is_empty() {
            f64::NAN
        } else {
            crate::data::stats::median(v)
        }
    };
    let mut intervals: Vec<f64> = distinct
        .windows(2)
        .map(|w| observations[w[1]].t_s - observations[w[0]].t_s)
        .collect();
    let moving = changes.len();
    let speed_change = median(&mut changes);
    SpeedObservation {
        stream: speed_change < MAX_STREAM_SPEED_CHANGE,
        speed_change,
        moving,
        median_interval_s: median(&mut intervals),
    }
}

/// Indices of the observations at times later than the one before them
/// (the first of each instant).
fn distinct_times(observations: &[Observation]) -> Vec<usize> {
    let mut out: Vec<usize> = Vec::with_capacity(observations.len());
    for (k, o) in observations.iter().enumerate() {
        if out.last().is_none_or(|&j| o.t_s > observations[j].t_s) {
            out.push(k);
        }
    }
    out
}

/// Each observation's count rate: the central difference of the nearest
/// rows at other times before and after it (one-sided at the ends),
/// counts per second rounded, saturating.
fn fill_count_rates(observations: &mut [Observation]) {
    let distinct = distinct_times(observations);
    let rate = |a: &Observation, b: &Observation, i: usize| {
        let v = (f64::from(b.inputs.counts[i]) - f64::from(a.inputs.counts[i])) / (b.t_s - a.t_s);
        v.round().clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
    };
    let mut rates = vec![[0i32; STRINGS]; observations.len()];
    for (n, &k) in distinct.iter().enumerate() {
        let before = distinct[n.saturating_sub(1)];
        let after = distinct[(n + 1).min(distinct.len() - 1)];
        if before == after {
            continue;
        }
        let end = distinct.get(n + 1).map_or(observations.len(), |&j| j);
        for r in &mut rates[k..end] {
            *r = core::array::from_fn(|i| rate(&observations[before], &observations[after], i));
        }
    }
    for (o, r) in observations.iter_mut().zip(rates) {
        o.inputs.count_rate_cps = r;
    }
}

impl Observation {
    /// This observation with its tracker position moved from the tracked
    /// body's origin to the strings' meeting point, which is
    /// `marker_body_mm` (body frame) from it: `p - R_body d`. Unchanged
    /// without a position or without an orientation.
    pub fn at_meeting_point(&self, marker_body_mm: &[f64; 3]) -> Observation {
        let mut o = self.clone();
        if let (Some(p), Some(r)) = (self.tracker, self.tracker_rotation) {
            o.tracker = Some(meeting_point(&p, &r, marker_body_mm));
        }
        o
    }
}

/// The strings' meeting point (room frame, mm) of a tracked body at `p`
/// turned by `body` (body to room, row-major) whose origin is
/// `marker_body_mm` (body frame) from it: `p - R_body d`.
pub fn meeting_point(p: &[f64; 3], body: &[[f64; 3]; 3], marker_body_mm: &[f64; 3]) -> [f64; 3] {
    core::array::from_fn(|k| p[k] - (0..3).map(|j| body[k][j] * marker_body_mm[j]).sum::<f64>())
}

/// `observations` read at the strings' meeting point
/// ([`Observation::at_meeting_point`]) when a marker offset is known; as
/// they are otherwise.
pub fn at_meeting_points(
    observations: &[Observation],
    marker_body_mm: Option<[f64; 3]>,
) -> std::borrow::Cow<'_, [Observation]> {
    match marker_body_mm {
        Some(d) => observations
            .iter()
            .map(|o| o.at_meeting_point(&d))
            .collect(),
        None => std::borrow::Cow::Borrowed(observations),
    }
}

/// The rotation matrix (row-major) of the quaternion `[w, x, y, z]`,
/// normalized first (a reader checks it is a unit one to its digits).
pub fn rotation_of_quaternion(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// How far a tracker's rotation matrix may be from a proper rotation
/// (its determinant from 1, each entry of `R^T R` from the identity's) and
/// still be recorded as the body's orientation. A tracker writes about six
/// decimals: its matrices are within about 1e-5.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// The orientation of a body whose rotation body -> room is `r` (row-major,
/// `x_room = R x_body + s`): the unit quaternion `[w, x, y, z]` of the
/// rotation nearest to `r`, with `w >= 0`, rounded to 1e-6 as the tracker's
/// values are written (its norm stays within about 1e-6 of 1, well inside
/// the session reader's 1e-3). `None` if `r` is not a proper rotation: a
/// value not finite, `|det r - 1|` or an entry of `r^T r - I` above
/// [`ROTATION_TOLERANCE`] (a reflection, a scaled or a degenerate matrix).
pub fn orientation_of_rotation(r: &[[f64; 3]; 3]) -> Option<[f64; 4]> {
    use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
    if !r.iter().flatten().all(|v| v.is_finite()) {
        return None;
    }
    let m = Matrix3::from_fn(|row, col| r[row][col]);
    let gram = m.transpose() * m - Matrix3::identity();
    if (m.determinant() - 1.0).abs() > ROTATION_TOLERANCE || gram.amax() > ROTATION_TOLERANCE {
        return None;
    }
    // The nearest rotation, found from a guess next to it: the quaternion
    // read off the matrix as if it were one. (`Rotation3::from_matrix`
    // starts from the identity, and from there an exact half turn, such as
    // diag(-1, 1, -1), is a stationary point it does not leave: it returns
    // a wrong rotation.) Bounded, though from so close it converges in a
    // few iterations.
    let guess = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    let guess = UnitQuaternion::new_normalize(guess.into_inner());
    let nearest = Rotation3::from_matrix_eps(&m, f64::EPSILON, 100, guess.to_rotation_matrix());
    if (nearest.matrix() - m).amax() > 10.0 * ROTATION_TOLERANCE {
        return None;
    }
    let q = UnitQuaternion::from_rotation_matrix(&nearest);
    // One sign of the double cover: w >= 0 (`+ 0.0` writes -0 as 0).
    let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
    let rounded = [q.w, q.i, q.j, q.k].map(|v| (sign * v * 1e6).round() / 1e6 + 0.0);
    let norm = rounded.iter().map(|v| v * v).sum::<f64>().sqrt();
    ((norm - 1.0).abs() <= 1e-5).then_some(rounded)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rotation of a quaternion is nalgebra's, for any scaling of it.
    #[test]
    fn a_quaternion_s_rotation_is_the_one_nalgebra_gives() {
        use nalgebra::{UnitQuaternion, Vector3};
        for (axis, angle) in [
            ([0.0, 0.0, 1.0], 0.3),
            ([1.0, -2.0, 0.5], 2.5),
            ([0.2, 0.1, -1.0], -1.2),
        ] {
            let q = UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(Vector3::from(axis)),
                angle,
            );
            let r = q.to_rotation_matrix();
            let ours = rotation_of_quaternion([2.0 * q.w, 2.0 * q.i, 2.0 * q.j, 2.0 * q.k]);
            for (row, expected_row) in ours.iter().zip(r.matrix().row_iter()) {
                for (a, b) in row.iter().zip(expected_row.iter()) {
                    assert!((a - b).abs() < 1e-12, "{ours:?} vs {r}");
                }
            }
        }
    }

    /// The meeting point is the tracked origin less the body's offset turned
    /// into the room; a row without a position or an orientation stays.
    #[test]
    fn the_meeting_point_is_the_tracked_origin_less_the_turned_offset() {
        let quarter_turn_about_z = [
            core::f64::consts::FRAC_1_SQRT_2,
            0.0,
            0.0,
            core::f64::consts::FRAC_1_SQRT_2,
        ];
        let o = Observation {
            row: 0,
            t_s: 0.0,
            inputs: StringInputs::default(),
            tension_n: [0.0; STRINGS],
            tracker: Some([100.0, 200.0, 300.0]),
            tracker_rotation: Some(rotation_of_quaternion(quarter_turn_about_z)),
            legacy: None,
            new_home: false,
        };
        // The body's x axis points along the room's y.
        let p = o.at_meeting_point(&[10.0, 0.0, 5.0]).tracker.unwrap();
        for (a, b) in p.iter().zip([100.0, 190.0, 295.0]) {
            assert!((a - b).abs() < 1e-9, "{p:?}");
        }
        let blind = Observation {
            tracker_rotation: None,
            ..o.clone()
        };
        assert_eq!(blind.at_meeting_point(&[10.0, 0.0, 5.0]), blind);
        assert!(matches!(
            at_meeting_points(std::slice::from_ref(&o), None),
            std::borrow::Cow::Borrowed(_)
        ));
    }
}
