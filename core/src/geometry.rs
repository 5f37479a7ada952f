//! Points, directions and rotations of the device's two frames: the small
//! 3-D math that the device (f32) and the host (f64) both use, in one place.
//!
//! The device frame is the frame's own (anchors, home, the kinematic
//! solution); the room frame is the optical tracker's:
//! `p_room = s R p_device + t` ([`Frame`]). Every function is generic over
//! [`Real`] and evaluates in one fixed order of operations (no FMA
//! contraction in Rust), so a result is the same bits on the host and on the
//! Cortex-M7 for f32, and the host's f64 figures do not depend on which
//! module asked.

use crate::model::Frame;
use crate::real::Real;

/// A point or a direction, mm (or a unit vector), `[x, y, z]`.
pub type Vec3<F> = [F; 3];

/// A 3x3 matrix, row-major (`m[row][column]`).
pub type Mat3<F> = [[F; 3]; 3];

/// `a + b`.
#[inline(always)]
pub fn add<F: Real>(a: Vec3<F>, b: Vec3<F>) -> Vec3<F> {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `a - b`.
#[inline(always)]
pub fn sub<F: Real>(a: Vec3<F>, b: Vec3<F>) -> Vec3<F> {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `s a`.
#[inline(always)]
pub fn scale<F: Real>(s: F, a: Vec3<F>) -> Vec3<F> {
    [s * a[0], s * a[1], s * a[2]]
}

/// `a . b`, summed x, y, z in that order.
#[inline(always)]
pub fn dot<F: Real>(a: Vec3<F>, b: Vec3<F>) -> F {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a x b`.
#[inline(always)]
pub fn cross<F: Real>(a: Vec3<F>, b: Vec3<F>) -> Vec3<F> {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `|a|` (a correctly rounded square root: [`Real::sqrt_rounded`]).
#[inline(always)]
pub fn norm<F: Real>(a: Vec3<F>) -> F {
    dot(a, a).sqrt_rounded()
}

/// `|a - b|`.
#[inline(always)]
pub fn distance<F: Real>(a: Vec3<F>, b: Vec3<F>) -> F {
    norm(sub(a, b))
}

/// `M v`.
#[inline(always)]
pub fn mat_vec<F: Real>(m: &Mat3<F>, v: Vec3<F>) -> Vec3<F> {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

/// `M^T v`.
#[inline(always)]
pub fn mat_t_vec<F: Real>(m: &Mat3<F>, v: Vec3<F>) -> Vec3<F> {
    [
        m[0][0] * v[0] + m[1][0] * v[1] + m[2][0] * v[2],
        m[0][1] * v[0] + m[1][1] * v[1] + m[2][1] * v[2],
        m[0][2] * v[0] + m[1][2] * v[1] + m[2][2] * v[2],
    ]
}

/// `A B`.
pub fn mat_mul<F: Real>(a: &Mat3<F>, b: &Mat3<F>) -> Mat3<F> {
    let mut m = [[F::zero(); 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    m
}

/// `M^T`.
pub fn transpose<F: Real>(m: &Mat3<F>) -> Mat3<F> {
    [
        [m[0][0], m[1][0], m[2][0]],
        [m[0][1], m[1][1], m[2][1]],
        [m[0][2], m[1][2], m[2][2]],
    ]
}

/// The rotation matrix of a rotation vector `w` (axis times angle, rad;
/// Rodrigues). Below 1e-15 rad it is the first-order `I + [w]x`.
pub fn rotation_from_vector<F: Real>(w: Vec3<F>) -> Mat3<F> {
    let angle = norm(w);
    let tiny = F::from(1e-15).unwrap_or_else(F::epsilon);
    let one = F::one();
    if angle < tiny {
        return [[one, -w[2], w[1]], [w[2], one, -w[0]], [-w[1], w[0], one]];
    }
    rotation_about_axis([w[0] / angle, w[1] / angle, w[2] / angle], angle)
}

/// The rotation by `angle` rad about the unit vector `axis` (Rodrigues).
pub fn rotation_about_axis<F: Real>(axis: Vec3<F>, angle: F) -> Mat3<F> {
    let (s, c) = angle.sin_cos();
    let v = F::one() - c;
    let [x, y, z] = axis;
    [
        [c + x * x * v, x * y * v - z * s, x * z * v + y * s],
        [y * x * v + z * s, c + y * y * v, y * z * v - x * s],
        [z * x * v - y * s, z * y * v + x * s, c + z * z * v],
    ]
}

/// The rotation vector of a rotation matrix (the inverse of
/// [`rotation_from_vector`] for angles below a half turn).
pub fn vector_from_rotation<F: Real>(r: &Mat3<F>) -> Vec3<F> {
    let one = F::one();
    let two = one + one;
    let trace_cos = (r[0][0] + r[1][1] + r[2][2] - one) / two;
    // Clamped (rounding can leave it just outside [-1, 1]); NaN stays NaN.
    let cos = if trace_cos < -one {
        -one
    } else if trace_cos > one {
        one
    } else {
        trace_cos
    };
    let angle = cos.acos();
    let axis = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]];
    let s = angle.sin();
    if s.abs() < F::from(1e-12).unwrap_or_else(F::epsilon) {
        return [axis[0] / two, axis[1] / two, axis[2] / two];
    }
    let f = angle / (two * s);
    [axis[0] * f, axis[1] * f, axis[2] * f]
}

/// The room-frame position of a device-frame point: `s R p + t`.
#[inline]
pub fn room_from_device<F: Real>(frame: &Frame<F>, p: Vec3<F>) -> Vec3<F> {
    let v = mat_vec(&frame.room_rotation, p);
    [
        frame.room_scale * v[0] + frame.room_translation[0],
        frame.room_scale * v[1] + frame.room_translation[1],
        frame.room_scale * v[2] + frame.room_translation[2],
    ]
}

/// The device-frame position of a room-frame point: `R^T (p - t) / s`.
#[inline]
pub fn device_from_room<F: Real>(frame: &Frame<F>, p: Vec3<F>) -> Vec3<F> {
    let v = mat_t_vec(&frame.room_rotation, sub(p, frame.room_translation));
    [
        v[0] / frame.room_scale,
        v[1] / frame.room_scale,
        v[2] / frame.room_scale,
    ]
}

/// A room-frame direction (a force) in the device frame: `R^T f`.
#[inline]
pub fn device_direction<F: Real>(frame: &Frame<F>, f: Vec3<F>) -> Vec3<F> {
    mat_t_vec(&frame.room_rotation, f)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> Frame<f64> {
        Frame {
            anchors: [[0.0; 3]; crate::STRINGS],
            layout: Default::default(),
            home: [0.0; 3],
            room_rotation: rotation_from_vector([0.1, -0.2, 0.3]),
            room_translation: [10.0, -20.0, 1500.0],
            room_scale: 1.001,
        }
    }

    #[test]
    fn room_and_device_frames_are_inverse() {
        let f = frame();
        let p = [123.0, -45.0, 67.0];
        let back = device_from_room(&f, room_from_device(&f, p));
        assert!(distance(p, back) < 1e-9, "{back:?}");
    }

    #[test]
    fn a_rotation_vector_survives_the_matrix_and_back() {
        let w = [0.1, -0.2, 0.3];
        let r = rotation_from_vector(w);
        let rt_r = mat_mul(&transpose(&r), &r);
        for (i, row) in rt_r.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let want: f64 = if i == j { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-12);
            }
        }
        assert!(distance(vector_from_rotation(&r), w) < 1e-12);
        assert_eq!(mat_vec(&r, [1.0, 0.0, 0.0])[1], r[1][0]);
        assert_eq!(cross([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]);
    }
}
