//! Multimodal guidance cues toward the initialization point (paper, section
//! 4.1, eqs. 2-5): a closeness index, a beep frequency and a guidance force.
//!
//! `d` is the distance (mm) from the end-effector to the target (the
//! initialization point), `d_min` (mm) the distance below which the cues
//! start to vary.
//!
//! - eq. 2: `h(d) = (d_min - d) / d_min` for `d <= d_min`, else 0
//!   ([`closeness`], 0 far away, 1 on the target);
//! - eq. 3: `f(d) = 1000 h(d)` Hz ([`beep_frequency_hz`], 0 beyond `d_min`);
//! - eq. 4: `F = Delta s(d) F_max` ([`guidance_force`]) with `Delta = v / |v|`
//!   the unit vector toward the target;
//! - eq. 5: `s = exp(-10 ((1 - h(d)) - 0.5)^2)` ([`guidance_profile`]).
//!
//! **Reading of eq. 5's domain note.** The paper writes "`s(x) = ... if
//! x in [-0.5, 0.5]`". We read `x` as the exponent's argument
//! `x = (1 - h(d)) - 0.5`: for `h` in `[0, 1]` it always lies in
//! `[-0.5, 0.5]`, so the note is a statement of range, not a case split, and
//! `s` is defined for every `d >= 0`: `s = exp(-2.5) ~ 0.082` on the target
//! and beyond `d_min` (where `h = 0`), `s = 1` at `d = d_min / 2`. The force
//! is thus a bell over `[0, d_min]` with a small constant pull (`0.082 F_max`)
//! farther away. On the target itself (`d = 0`) the direction is undefined
//! and the force is zero.
//!
//! Invalid inputs (non-finite, `d < 0`, `d_min <= 0`, `F_max < 0`) give no cue
//! (0 closeness, 0 Hz, zero force), never NaN. f32 only, `exp` from `libm`
//! so the host and the device compute the same bits.

use crate::model::Vec3;
use crate::real::Real;

/// Beep frequency (Hz) at `h = 1`, eq. 3.
pub const BEEP_FREQUENCY_SCALE_HZ: f32 = 1000.0;

/// Eq. 2: closeness index `h(d)` in `[0, 1]` of a distance `d` (mm) to the
/// target, with the cue radius `d_min` (mm). 0 for invalid input.
pub fn closeness(d: f32, d_min: f32) -> f32 {
    if !(d.is_finite() && d_min.is_finite()) || d < 0.0 || d_min <= 0.0 {
        return 0.0;
    }
    if d <= d_min {
        (d_min - d) / d_min
    } else {
        0.0
    }
}

/// Eq. 3: beep frequency (Hz) at distance `d` (mm): `1000 h(d)`, 0 beyond
/// `d_min` (mm) (no beep).
pub fn beep_frequency_hz(d: f32, d_min: f32) -> f32 {
    BEEP_FREQUENCY_SCALE_HZ * closeness(d, d_min)
}

/// Eq. 5: force profile `s(d) = exp(-10 ((1 - h(d)) - 0.5)^2)` in
/// `[exp(-2.5), 1]` (dimensionless), `d` and `d_min` in mm. See the module
/// doc for the reading of the paper's domain note. 0 for invalid input.
pub fn guidance_profile(d: f32, d_min: f32) -> f32 {
    if !(d.is_finite() && d_min.is_finite()) || d < 0.0 || d_min <= 0.0 {
        return 0.0;
    }
    let x = (1.0 - closeness(d, d_min)) - 0.5;
    libm::expf(-10.0 * (x * x))
}

/// Eq. 4: guidance force (N) `F = v / |v| * s(|v|) * f_max`, where `v` (mm)
/// is the vector from the end-effector to the target, `d_min` (mm) the cue
/// radius and `f_max` (N) the largest guidance force. Zero force when
/// `v = 0` (on the target: no direction) or for any invalid input.
pub fn guidance_force(v: Vec3<f32>, d_min: f32, f_max: f32) -> Vec3<f32> {
    if !(v.iter().all(|x| x.is_finite()) && f_max.is_finite()) || f_max < 0.0 {
        return [0.0; 3];
    }
    // Scale by the largest component first so that |v| neither underflows
    // nor overflows f32.
    let m = v
        .iter()
        .fold(0.0f32, |m, x| if x.abs() > m { x.abs() } else { m });
    if m <= 0.0 {
        return [0.0; 3]; // on the target: no direction
    }
    let w = [v[0] / m, v[1] / m, v[2] / m];
    let n = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt_rounded();
    let d = m * n;
    if !d.is_finite() {
        return [0.0; 3];
    }
    let magnitude = guidance_profile(d, d_min) * f_max;
    [
        w[0] / n * magnitude,
        w[1] / n * magnitude,
        w[2] / n * magnitude,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f32, b: f32, tol: f32) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn closeness_and_beep_hand_computed() {
        // d_min = 50 mm.
        assert_eq!(closeness(25.0, 50.0), 0.5);
        assert_eq!(beep_frequency_hz(25.0, 50.0), 500.0);
        assert_eq!(closeness(0.0, 50.0), 1.0);
        assert_eq!(beep_frequency_hz(0.0, 50.0), 1000.0);
        assert_eq!(closeness(50.0, 50.0), 0.0);
        assert_eq!(closeness(10.0, 50.0), 0.8);
        assert_eq!(beep_frequency_hz(10.0, 50.0), 800.0);
        assert_eq!(closeness(80.0, 50.0), 0.0);
        assert_eq!(beep_frequency_hz(80.0, 50.0), 0.0);
    }

    #[test]
    fn profile_hand_computed() {
        // h = 0.5: x = 0, s = 1.
        assert_eq!(guidance_profile(25.0, 50.0), 1.0);
        // h = 1 (on target) and h = 0 (at and beyond d_min): x = -/+0.5, s = e^-2.5.
        let e = (-2.5f64).exp() as f32; // 0.082085
        assert!(close(guidance_profile(0.0, 50.0), e, 1e-7));
        assert!(close(guidance_profile(50.0, 50.0), e, 1e-7));
        assert!(close(guidance_profile(500.0, 50.0), e, 1e-7));
        // d = 10 mm: h = 0.8, x = -0.3, s = e^-0.9 = 0.40657.
        assert!(close(guidance_profile(10.0, 50.0), 0.406_569_66, 1e-6));
    }

    #[test]
    fn force_points_to_target_with_hand_computed_magnitude() {
        // v = (0, 30, 40) mm, d = 50 mm, d_min = 100 mm: h = 0.5, s = 1.
        let f = guidance_force([0.0, 30.0, 40.0], 100.0, 2.0);
        assert!(close(f[0], 0.0, 1e-7));
        assert!(close(f[1], 1.2, 1e-6));
        assert!(close(f[2], 1.6, 1e-6));
        // Far away: small constant pull e^-2.5 * f_max along v.
        let f = guidance_force([-3000.0, 0.0, 0.0], 100.0, 2.0);
        assert!(close(f[0], -2.0 * 0.082_085, 1e-6));
        assert_eq!(f[1], 0.0);
    }

    #[test]
    fn degenerate_inputs_give_no_cue_and_no_nan() {
        assert_eq!(guidance_force([0.0; 3], 50.0, 2.0), [0.0; 3]);
        assert_eq!(guidance_force([f32::NAN, 0.0, 1.0], 50.0, 2.0), [0.0; 3]);
        assert_eq!(guidance_force([1.0, 0.0, 0.0], f32::NAN, 2.0), [0.0; 3]);
        assert_eq!(
            guidance_force([1.0, 0.0, 0.0], 50.0, f32::INFINITY),
            [0.0; 3]
        );
        assert_eq!(guidance_force([1.0, 0.0, 0.0], 0.0, 2.0), [0.0; 3]);
        assert_eq!(
            guidance_force([f32::MAX, f32::MAX, 0.0], 50.0, 2.0),
            [0.0; 3]
        );
        let f = guidance_force([1e30, 1e30, 0.0], 50.0, 2.0);
        assert!(close(f[0], 2.0 * 0.082_085 / 2.0f32.sqrt(), 1e-6), "{f:?}");
        assert_eq!(closeness(f32::NAN, 50.0), 0.0);
        assert_eq!(closeness(-1.0, 50.0), 0.0);
        assert_eq!(closeness(10.0, -5.0), 0.0);
        assert_eq!(beep_frequency_hz(f32::INFINITY, 50.0), 0.0);
        assert_eq!(guidance_profile(f32::NAN, 50.0), 0.0);
        // Tiny but non-zero distance: finite, toward the target.
        let f = guidance_force([1e-30, 0.0, 0.0], 50.0, 2.0);
        assert!(f.iter().all(|x| x.is_finite()) && f[0] > 0.0);
    }
}
