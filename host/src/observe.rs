//! A session seen as the device sees it: per row, the run-time inputs of the
//! string law (counts, direction of motion, commanded tension, time since
//! home), plus the references (tracker, legacy controller).
//!
//! Direction comes from the same `encoder::DirectionTracker` the firmware
//! runs, fed with the recorded counts in session order; time since home is
//! the session's `t_s` (sessions start at initialization).

use spidar_core::encoder::DirectionTracker;
use spidar_core::model::StringInputs;
use spidar_core::STRINGS;

use crate::dataset::Sample;

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
}

/// The observations of a session's rows, in order.
pub fn observations(samples: &[Sample]) -> Vec<Observation> {
    let mut trackers: Vec<DirectionTracker> = (0..STRINGS)
        .map(|_| DirectionTracker::new(DIRECTION_HYSTERESIS_COUNTS))
        .collect();
    samples
        .iter()
        .enumerate()
        .map(|(row, s)| {
            let tension_n = s.tension_n.unwrap_or([0.0; STRINGS]);
            let mut inputs = StringInputs {
                counts: s.counts,
                time_ms: (s.t_s * 1000.0).round().clamp(0.0, u32::MAX as f64) as u32,
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
            }
        })
        .collect()
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
