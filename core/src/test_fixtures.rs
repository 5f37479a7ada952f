//! The device the core's unit tests share: eight strings whose anchors are
//! the corners of a 2.2 m cube centred on the origin (string `i`'s corner
//! by the bits of `i`), the tracker's frame 1.5 m above the device's.

use crate::model::{Frame, StringLayout, Vec3};
use crate::STRINGS;

/// Half the cube's edge, mm.
pub const HALF_EDGE_MM: f64 = 1100.0;

/// Anchor `i` at the corner `(±h, ±h, ±h)`, bit 0 of `i` for x, 1 for y,
/// 2 for z (clear: minus).
pub fn cube_anchors() -> [Vec3<f64>; STRINGS] {
    core::array::from_fn(|i| {
        [1, 2, 4].map(|bit| {
            if i & bit == 0 {
                -HALF_EDGE_MM
            } else {
                HALF_EDGE_MM
            }
        })
    })
}

/// The cube's frame with every string active, home at `home`, the room
/// frame the device's raised by 1.5 m.
pub fn cube_frame(home: Vec3<f64>) -> Frame<f64> {
    Frame {
        layout: StringLayout::ALL,
        anchors: cube_anchors(),
        home,
        room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        room_translation: [0.0, 0.0, 1500.0],
        room_scale: 1.0,
    }
}
