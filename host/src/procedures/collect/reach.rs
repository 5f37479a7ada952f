//! Where the strings can hold the end-effector: the convex hull of the
//! anchors (room frame). Strings only pull, so a point outside the hull has
//! every string pulling it to one side: the device cannot hold it there (it
//! refuses to arm where its strings cannot pull in every direction), and a
//! lattice cell out there can only be "captured" with the strings slack or
//! the tracker and the device disagreeing. A planar device's hull is the
//! anchors' polygon in their plane; the lattice's extent across that plane
//! is not constrained by it.
//!
//! The hull is kept as half-spaces `n . x <= d`. A cube of half edge `h`
//! centred on `c` lies inside one iff `n . c + h (|n_x| + |n_y| + |n_z|) <=
//! d` (its farthest corner along `n`), so the largest cube around `c` inside
//! the hull is exact: `h = min (d - n . c) / |n|_1`. No margin is added: a
//! cell on the hull's face is still held (the hull is the limit, not a
//! safety distance), and the only tolerance is the floating point's, for
//! deciding which anchors lie on a face.

use spidar_core::geometry::{cross, dot, sub};

use crate::data::dataset::Geometry;

/// Relative floating-point rounding: which anchors lie on a face, and a
/// cube whose corner meets a face to within it meets the face (a frame of
/// anchors at +-1100 mm holds a cube of 2200 mm, not of 2199.9999999).
const ROUNDING: f64 = 1e-9;

/// The anchors' convex hull, room frame, as half-spaces `n . x <= d` (`n` a
/// unit vector).
#[derive(Clone, Debug, PartialEq)]
pub struct Reach {
    half_spaces: Vec<([f64; 3], f64)>,
    planar: bool,
}

impl Reach {
    /// The hull of `geometry`'s active anchors in the room frame (`p_room =
    /// p_device + t`, the frame the tracker and the lattice are in).
    pub fn of(geometry: &Geometry) -> Reach {
        let t = geometry.room_from_device_translation_mm;
        let anchors: Vec<[f64; 3]> = geometry
            .layout
            .indices()
            .map(|i| core::array::from_fn(|k| geometry.anchors_mm[i][k] + t[k]))
            .collect();
        Reach::of_anchors(&anchors, geometry.layout.planar)
    }

    /// The hull of `anchors` (room frame); `planar`: the end-effector moves
    /// in the anchors' plane, and the hull is their polygon there. Anchors
    /// that all lie in one plane give that polygon too (a flat hull holds no
    /// cube).
    pub fn of_anchors(anchors: &[[f64; 3]], planar: bool) -> Reach {
        let scale = anchors
            .iter()
            .flat_map(|a| anchors.iter().map(move |b| norm(sub(*a, *b))))
            .fold(0.0, f64::max);
        let eps = scale * ROUNDING;
        let mut half_spaces = Vec::new();
        // The best-conditioned plane through three anchors (the anchors'
        // plane when they are coplanar).
        let mut widest: Option<[f64; 3]> = None;
        let n = anchors.len();
        for i in 0..n {
            for j in i + 1..n {
                for k in j + 1..n {
                    let normal = cross(sub(anchors[j], anchors[i]), sub(anchors[k], anchors[i]));
                    let area = norm(normal);
                    if area <= eps * scale {
                        continue;
                    }
                    if widest.is_none_or(|w| area > norm(w)) {
                        widest = Some(normal);
                    }
                    if !planar {
                        push_supporting(&mut half_spaces, anchors, normal, anchors[i], eps);
                    }
                }
            }
        }
        let flat = half_spaces.is_empty();
        if flat {
            // Edges of the polygon: planes through two anchors, across the
            // anchors' plane.
            if let Some(plane) = widest {
                for i in 0..n {
                    for j in i + 1..n {
                        let across = cross(plane, sub(anchors[j], anchors[i]));
                        push_supporting(&mut half_spaces, anchors, across, anchors[i], eps);
                    }
                }
            }
        }
        Reach {
            half_spaces,
            planar: planar || flat,
        }
    }

    /// The hull is the anchors' polygon in their plane.
    pub fn is_planar(&self) -> bool {
        self.planar
    }

    /// The largest edge of a cube centred on `centre` that lies inside the
    /// hull (across a planar hull's plane: its square's); not above 0 when
    /// `centre` is outside; infinite when the anchors bound nothing (fewer
    /// than three not in a line).
    pub fn largest_cube_mm(&self, centre: [f64; 3]) -> f64 {
        let edge = self
            .half_spaces
            .iter()
            .map(|(n, d)| 2.0 * (d - dot(*n, centre)) / n.iter().map(|v| v.abs()).sum::<f64>())
            .fold(f64::INFINITY, f64::min);
        edge + edge.abs() * ROUNDING
    }
}

fn norm(v: [f64; 3]) -> f64 {
    dot(v, v).sqrt()
}

/// Keeps the plane through `on` with normal `normal` when every anchor lies
/// on one side of it (within `eps`), as the half-space holding them.
fn push_supporting(
    half_spaces: &mut Vec<([f64; 3], f64)>,
    anchors: &[[f64; 3]],
    normal: [f64; 3],
    on: [f64; 3],
    eps: f64,
) {
    let length = norm(normal);
    if !(length > 0.0 && length.is_finite()) {
        return;
    }
    let n = normal.map(|v| v / length);
    let d = dot(n, on);
    let sides: Vec<f64> = anchors.iter().map(|a| dot(n, *a) - d).collect();
    let below = sides.iter().all(|s| *s <= eps);
    let above = sides.iter().all(|s| *s >= -eps);
    match (below, above) {
        // Every anchor on the plane: it bounds no direction here.
        (true, true) | (false, false) => {}
        (true, false) => half_spaces.push((n, d)),
        (false, true) => half_spaces.push((n.map(|v| -v), -d)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cube_corners(h: f64) -> Vec<[f64; 3]> {
        let mut v = Vec::new();
        for z in [-h, h] {
            for (x, y) in [(-h, -h), (h, -h), (h, h), (-h, h)] {
                v.push([x, y, z]);
            }
        }
        v
    }

    #[test]
    fn the_largest_cube_in_a_cube_of_anchors_is_the_frame_less_the_centre_s_offset() {
        let reach = Reach::of_anchors(&cube_corners(1100.0), false);
        assert!(!reach.is_planar());
        assert!((reach.largest_cube_mm([0.0; 3]) - 2200.0).abs() < 1e-5);
        // The frame itself fits, rounding or not.
        assert!(reach.largest_cube_mm([0.0; 3]) >= 2200.0);
        // 100 mm off centre along x: 100 mm closer to one face.
        assert!((reach.largest_cube_mm([100.0, 0.0, 0.0]) - 2000.0).abs() < 1e-5);
        assert!(reach.largest_cube_mm([1200.0, 0.0, 0.0]) < 0.0);
    }

    #[test]
    fn a_tetrahedron_holds_a_cube_of_a_third_of_its_frame() {
        // Corners 0, 2, 5, 7 of the cube: faces x + y + z <= h and the like,
        // so the cube's corner (h', h', h') touches at 3 h' = h.
        let c = cube_corners(900.0);
        let reach = Reach::of_anchors(&[c[0], c[2], c[5], c[7]], false);
        assert!((reach.largest_cube_mm([0.0; 3]) - 600.0).abs() < 1e-5);
    }

    #[test]
    fn a_planar_device_s_hull_is_its_polygon_whatever_the_height() {
        let square = [
            [-1000.0, -500.0, 0.0],
            [1000.0, -500.0, 0.0],
            [1000.0, 500.0, 0.0],
            [-1000.0, 500.0, 0.0],
        ];
        for planar in [true, false] {
            let reach = Reach::of_anchors(&square, planar);
            assert!(reach.is_planar());
            assert!((reach.largest_cube_mm([0.0, 0.0, 0.0]) - 1000.0).abs() < 1e-5);
            assert!((reach.largest_cube_mm([0.0, 0.0, 300.0]) - 1000.0).abs() < 1e-5);
            assert!((reach.largest_cube_mm([800.0, 0.0, 0.0]) - 400.0).abs() < 1e-5);
        }
    }
}
