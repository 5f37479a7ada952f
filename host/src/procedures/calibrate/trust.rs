//! Warnings where a calibration is not what it seems (issue 13): the
//! held-out figure is a training figure (train and test share rows), test
//! points lie outside the volume the training session covers (the model
//! extrapolates there), or the geometry determines the position poorly in
//! some direction.

use std::collections::HashSet;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use spidar_core::model::Frame;

use crate::data::dataset::Session;
use crate::data::stats::ErrorStats;
use spidar_core::geometry::device_from_room;

/// Test rows that also appear (same counts and tracker position) in the
/// training session: `(shared, test rows)`.
pub fn shared_rows(train: &Session, test: &Session) -> (usize, usize) {
    let key = |s: &crate::data::dataset::Sample| (s.counts, s.tracker.map(|t| t.map(f64::to_bits)));
    let seen: HashSet<_> = train.samples.iter().map(key).collect();
    let shared = test
        .samples
        .iter()
        .filter(|s| seen.contains(&key(s)))
        .count();
    (shared, test.samples.len())
}

/// The axis-aligned box (device frame, mm) of the training session's
/// tracked positions, grown by `margin_mm`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrainingBox {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl TrainingBox {
    /// `None` without a tracked training row.
    pub fn of(frame: &Frame<f64>, room: &[[f64; 3]], margin_mm: f64) -> Option<TrainingBox> {
        let mut points = room.iter().map(|r| device_from_room(frame, *r));
        let first = points.next()?;
        let (mut min, mut max) = (first, first);
        for p in points {
            for k in 0..3 {
                min[k] = min[k].min(p[k]);
                max[k] = max[k].max(p[k]);
            }
        }
        Some(TrainingBox {
            min: min.map(|v| v - margin_mm),
            max: max.map(|v| v + margin_mm),
        })
    }

    /// Whether the room position `room` lies in the box.
    pub fn contains(&self, frame: &Frame<f64>, room: [f64; 3]) -> bool {
        let p = device_from_room(frame, room);
        (0..3).all(|k| p[k] >= self.min[k] && p[k] <= self.max[k])
    }
}

/// Errors of the test points inside and outside the training box.
#[derive(Clone, Copy, Debug)]
pub struct Extrapolation {
    pub inside: ErrorStats,
    pub outside: ErrorStats,
}

/// Split `errors` (one per tracked test point at `tracker`, room frame) by
/// the training box.
pub fn extrapolation(
    frame: &Frame<f64>,
    training: &TrainingBox,
    tracker: &[[f64; 3]],
    errors: &[f64],
) -> Extrapolation {
    let (mut inside, mut outside) = (Vec::new(), Vec::new());
    for (t, e) in tracker.iter().zip(errors) {
        if training.contains(frame, *t) {
            inside.push(*e);
        } else {
            outside.push(*e);
        }
    }
    Extrapolation {
        inside: ErrorStats::of(&inside),
        outside: ErrorStats::of(&outside),
    }
}

/// How well the strings determine the position at device-frame points:
/// the largest ratio of position error to string-length error, over the
/// median point (`sqrt(1 / lambda_min)` of `J^T J`, J the unit vectors from
/// the active anchors), and the direction it is worst in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Determination {
    /// mm of position per mm of string-length error, worst direction,
    /// median over the points.
    pub gain: f64,
    /// Unit vector (device frame) of the worst-determined direction at the
    /// median point.
    pub direction: [f64; 3],
}

/// A string-length error this many times larger in position is worth a
/// warning (a cube SPIDAR at its centre: ~0.6).
pub const POOR_DETERMINATION_GAIN: f64 = 5.0;

/// [`Determination`] of `frame` at `points` (device frame); `None` without
/// points.
pub fn determination(frame: &Frame<f64>, points: &[[f64; 3]]) -> Option<Determination> {
    let dof = frame.layout.dof();
    let mut per_point: Vec<(f64, [f64; 3])> = points
        .iter()
        .map(|p| {
            let mut jtj = Matrix3::zeros();
            for i in frame.layout.indices() {
                let a = frame.anchors[i];
                let d = Vector3::new(p[0] - a[0], p[1] - a[1], p[2] - a[2]);
                let n = d.norm();
                if n > 0.0 {
                    let u = d / n;
                    jtj += u * u.transpose();
                }
            }
            if dof == 2 {
                // The plane's normal is not a direction of motion.
                jtj[(2, 2)] += 1.0;
            }
            let eig = SymmetricEigen::new(jtj);
            let (k, lmin) =
                eig.eigenvalues
                    .iter()
                    .enumerate()
                    .fold(
                        (0, f64::INFINITY),
                        |b, (k, &l)| if l < b.1 { (k, l) } else { b },
                    );
            let v = eig.eigenvectors.column(k);
            let gain = if lmin > 0.0 {
                (1.0 / lmin).sqrt()
            } else {
                f64::INFINITY
            };
            (gain, [v[0], v[1], v[2]])
        })
        .collect();
    if per_point.is_empty() {
        return None;
    }
    per_point.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (gain, direction) = per_point[per_point.len() / 2];
    Some(Determination { gain, direction })
}

#[cfg(test)]
mod tests {
    use super::*;
    use spidar_core::model::StringLayout;

    fn frame(anchors: &[[f64; 3]]) -> Frame<f64> {
        let mut a = [anchors[anchors.len() - 1]; 8];
        a[..anchors.len()].copy_from_slice(anchors);
        Frame {
            layout: StringLayout::first(anchors.len(), false),
            anchors: a,
            home: [0.0; 3],
            room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            room_translation: [0.0; 3],
            room_scale: 1.0,
        }
    }

    #[test]
    fn a_cube_determines_the_centre_and_coplanar_anchors_do_not_determine_their_normal() {
        let h = 1100.0;
        let cube: Vec<[f64; 3]> = (0..8)
            .map(|i| {
                [
                    if i & 1 == 0 { -h } else { h },
                    if i & 2 == 0 { -h } else { h },
                    if i & 4 == 0 { -h } else { h },
                ]
            })
            .collect();
        let d = determination(&frame(&cube), &[[0.0; 3]]).unwrap();
        assert!(d.gain < 1.0, "{d:?}");
        // All 8 anchors in z = 0, points near that plane.
        let flat: Vec<[f64; 3]> = cube.iter().map(|a| [a[0], a[1], 0.0]).collect();
        let d = determination(&frame(&flat), &[[100.0, -50.0, 20.0]]).unwrap();
        assert!(d.gain > POOR_DETERMINATION_GAIN, "{d:?}");
        assert!(d.direction[2].abs() > 0.99, "{d:?}");
    }
}
