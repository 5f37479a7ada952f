//! The string's way out of its corner: a swivelling guide pulley of finite
//! radius, so the exit point moves with the string's direction.
//!
//! The string comes from the spool along the frame edge and reaches the
//! guide at the entry point `A`, travelling along the unit swivel axis `e`.
//! The guide pulley (radius `rho`) swivels about that axis so that its plane
//! contains the end-effector `P`; its centre is `M = A + rho u`, with `u`
//! the unit component of `P - A` perpendicular to `e`. In the pulley's plane
//! (coordinates along `u` and `e`, origin `M`), `P` is at
//! `(x, y) = ((P - A).u - rho, (P - A).e)`, at distance `m = |(x, y)|`.
//! The string leaves the pulley at the tangent point of angle
//! `phi_T = atan2(y, x) + acos(rho / m)` after wrapping `beta = (pi - phi_T) mod 2 pi`,
//! so that its length from `A` to `P` is
//!
//! `arc + tangent = rho beta + sqrt(m^2 - rho^2)`
//!
//! and the exit point is `T = M + rho (cos phi_T u + sin phi_T e)`. A fixed
//! anchor (the model) is exact only for `rho = 0`.

use serde::{Deserialize, Serialize};
use spidar_core::model::Vec3;

use spidar_core::geometry::{dot, norm, sub};

/// One guide pulley, device frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Guide {
    /// Entry point `A` (on the swivel axis), mm.
    pub entry_mm: Vec3<f64>,
    /// Unit swivel axis `e`: the string's direction of travel at `A`.
    pub axis: Vec3<f64>,
    /// Pulley radius `rho`, mm.
    pub radius_mm: f64,
}

/// The string's path over a guide to the end-effector.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuidePath {
    /// Arc on the guide plus the tangent segment, mm.
    pub length_mm: f64,
    /// Tangent (free) segment from the exit point to the end-effector, mm.
    pub free_mm: f64,
    /// Exit (tangent) point `T`, mm.
    pub exit_mm: Vec3<f64>,
    /// Unit direction of the free segment, from `T` to `P`.
    pub direction: Vec3<f64>,
    /// Wrap angle `beta`, rad.
    pub wrap_rad: f64,
}

/// The end-effector is on or inside the guide pulley.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
#[error("the end-effector is {distance_mm:.2} mm from the guide pulley's centre, inside its radius {radius_mm:.2} mm")]
pub struct GuideError {
    pub distance_mm: f64,
    pub radius_mm: f64,
}

impl Guide {
    /// The path to `p` with the guide displaced by `shift_mm` (frame
    /// compliance).
    pub fn path(&self, shift_mm: &Vec3<f64>, p: &Vec3<f64>) -> Result<GuidePath, GuideError> {
        let a: Vec3<f64> = core::array::from_fn(|k| self.entry_mm[k] + shift_mm[k]);
        let e = self.axis;
        let v = sub(*p, a);
        let along = dot(v, e);
        let perp: Vec3<f64> = core::array::from_fn(|k| v[k] - along * e[k]);
        let perp_len = norm(perp);
        let u: Vec3<f64> = if perp_len > 1e-9 {
            perp.map(|x| x / perp_len)
        } else {
            // On the swivel axis: any plane will do.
            let trial = if e[0].abs() < 0.9 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 1.0, 0.0]
            };
            let t = dot(trial, e);
            let w: Vec3<f64> = core::array::from_fn(|k| trial[k] - t * e[k]);
            let n = norm(w);
            w.map(|x| x / n)
        };
        let rho = self.radius_mm;
        let (x, y) = (perp_len - rho, along);
        let m = x.hypot(y);
        if m.is_nan() || m <= rho {
            return Err(GuideError {
                distance_mm: m,
                radius_mm: rho,
            });
        }
        let phi_t = y.atan2(x) + (rho / m).acos();
        let wrap_rad = (std::f64::consts::PI - phi_t).rem_euclid(std::f64::consts::TAU);
        let free_mm = (m * m - rho * rho).sqrt();
        let (s, c) = phi_t.sin_cos();
        let exit_mm: Vec3<f64> =
            core::array::from_fn(|k| a[k] + rho * u[k] + rho * (c * u[k] + s * e[k]));
        let to_p = sub(*p, exit_mm);
        let n = norm(to_p);
        let direction = if n > 0.0 { to_p.map(|x| x / n) } else { e };
        Ok(GuidePath {
            length_mm: rho * wrap_rad + free_mm,
            free_mm,
            exit_mm,
            direction,
            wrap_rad,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_path_is_tangent_and_its_length_adds_up() {
        let g = Guide {
            entry_mm: [-1100.0, -1100.0, 1100.0],
            axis: [0.0, 0.0, 1.0],
            radius_mm: 10.0,
        };
        for p in [
            [0.0, 0.0, 0.0],
            [300.0, -200.0, 500.0],
            [-600.0, 100.0, -400.0],
        ] {
            let path = g.path(&[0.0; 3], &p).unwrap();
            // The exit point is on the pulley, the free segment is tangent to it.
            let u = {
                let v = sub(p, g.entry_mm);
                let h = (v[0] * v[0] + v[1] * v[1]).sqrt();
                [v[0] / h, v[1] / h, 0.0]
            };
            let m: Vec3<f64> = core::array::from_fn(|k| g.entry_mm[k] + 10.0 * u[k]);
            let r = sub(path.exit_mm, m);
            assert!((norm(r) - 10.0).abs() < 1e-9);
            assert!(dot(r, path.direction).abs() < 1e-9);
            assert!((norm(sub(p, path.exit_mm)) - path.free_mm).abs() < 1e-9);
            assert!(
                path.wrap_rad > 1.0 && path.wrap_rad < 3.0,
                "{}",
                path.wrap_rad
            );
            // A zero-radius guide is the fixed anchor.
            let point = Guide {
                radius_mm: 1e-9,
                ..g.clone()
            };
            let fixed = point.path(&[0.0; 3], &p).unwrap();
            assert!((fixed.length_mm - norm(sub(p, g.entry_mm))).abs() < 1e-6);
        }
        assert!(g.path(&[0.0; 3], &[-1090.0, -1100.0, 1100.0]).is_err());
    }
}
