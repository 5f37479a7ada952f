//! A spool wound in layers: the string's winding radius is a staircase in
//! the spool angle, not the smooth continuum law of the calibration model.
//!
//! The spool has a bare radius `r0` and a width `W`; the string (diameter
//! `d`) is laid side by side across the width, one layer after the other.
//! Layer `k` (from 0) has its string centre at
//!
//! `R_k = r0 + d/2 + k * c * d`
//!
//! (`c` in `[0.85, 1]`: how deep a layer nests in the grooves of the one
//! below; 0.866 is hexagonal packing, 1 square). The pitch of a layer is
//! uneven: `n_k = W / (d (1 + u_k))` turns (not an integer), `u_k` drawn per
//! layer. Between two layers the string climbs from `R_k` to `R_{k+1}` over
//! a layer change of `chi` rad (linear ramp). Within every turn it crosses
//! over its neighbour once: over the first `w_x` rad of each turn (spool
//! angle modulo `2 pi`) it rides `h_x` mm higher.
//!
//! Wound length from the empty spool to spool angle `phi`:
//!
//! `wound(phi) = integral_0^phi R(phi') dphi' + h_x (floor(phi / 2 pi) w_x + min(phi mod 2 pi, w_x))`
//!
//! exact per segment (a constant or linear radius). It is strictly
//! increasing; [`Spool::angle_for_wound`] inverts it by bisection.

use serde::{Deserialize, Serialize};

use std::f64::consts::TAU;

/// The drawn parameters of one spool.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpoolParams {
    /// Bare radius `r0`, mm.
    pub bare_radius_mm: f64,
    /// String diameter `d`, mm.
    pub string_diameter_mm: f64,
    /// Layer rise per layer in string diameters, `c`.
    pub layer_packing: f64,
    /// Turns per layer `n_k`, one per layer, bottom layer first.
    pub turns_per_layer: Vec<f64>,
    /// Angle over which the string climbs to the next layer, `chi`, rad.
    pub layer_change_rad: f64,
    /// Height of the cross-over over the neighbouring turn, `h_x`, mm.
    pub crossover_rise_mm: f64,
    /// Angular width of the cross-over in every turn, `w_x`, rad.
    pub crossover_rad: f64,
}

/// One piece of the radius staircase: the radius goes linearly from
/// `r_start` to `r_end` over `[phi_start, phi_end)`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Segment {
    phi_start: f64,
    phi_end: f64,
    r_start: f64,
    r_end: f64,
    /// Base wound length at `phi_start` (cross-overs not included), mm.
    wound_start: f64,
}

/// A spool built from [`SpoolParams`].
#[derive(Clone, Debug, PartialEq)]
pub struct Spool {
    params: SpoolParams,
    segments: Vec<Segment>,
}

/// Why a spool angle cannot be found.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum SpoolError {
    #[error("the spool would be empty (it holds {wound_mm:.1} mm less than nothing)")]
    Empty { wound_mm: f64 },
    #[error("the spool holds at most {capacity_mm:.1} mm, {wound_mm:.1} mm asked")]
    Full { wound_mm: f64, capacity_mm: f64 },
}

impl Spool {
    /// The spool of `params`; its layers are those of `turns_per_layer`.
    /// `params` must be checked by the caller (positive radius, diameter,
    /// turns longer than the layer change).
    pub fn new(params: SpoolParams) -> Spool {
        let d = params.string_diameter_mm;
        let radius =
            |k: usize| params.bare_radius_mm + d / 2.0 + k as f64 * params.layer_packing * d;
        let mut segments = Vec::new();
        let mut phi = 0.0;
        let mut wound = 0.0;
        let layers = params.turns_per_layer.len();
        for (k, turns) in params.turns_per_layer.iter().enumerate() {
            let extent = TAU * turns;
            let last = k + 1 == layers;
            let chi = if last {
                0.0
            } else {
                params.layer_change_rad.min(extent / 2.0)
            };
            let flat = Segment {
                phi_start: phi,
                phi_end: phi + extent - chi,
                r_start: radius(k),
                r_end: radius(k),
                wound_start: wound,
            };
            wound += radius(k) * (extent - chi);
            phi = flat.phi_end;
            segments.push(flat);
            if !last {
                let ramp = Segment {
                    phi_start: phi,
                    phi_end: phi + chi,
                    r_start: radius(k),
                    r_end: radius(k + 1),
                    wound_start: wound,
                };
                wound += 0.5 * (radius(k) + radius(k + 1)) * chi;
                phi = ramp.phi_end;
                segments.push(ramp);
            }
        }
        Spool { params, segments }
    }

    pub fn params(&self) -> &SpoolParams {
        &self.params
    }

    /// Largest spool angle (the spool full), rad.
    pub fn max_angle_rad(&self) -> f64 {
        self.segments.last().map_or(0.0, |s| s.phi_end)
    }

    /// String the full spool holds, mm.
    pub fn capacity_mm(&self) -> f64 {
        self.wound_mm(self.max_angle_rad())
    }

    fn crossovers_mm(&self, phi: f64) -> f64 {
        let (h, w) = (self.params.crossover_rise_mm, self.params.crossover_rad);
        h * ((phi / TAU).floor() * w + phi.rem_euclid(TAU).min(w))
    }

    fn segment(&self, phi: f64) -> Option<&Segment> {
        let i = self.segments.partition_point(|s| s.phi_end <= phi);
        self.segments.get(i).or(self.segments.last())
    }

    /// Winding radius (string centre) at spool angle `phi`, mm: the
    /// staircase plus the cross-over.
    pub fn radius_mm(&self, phi: f64) -> f64 {
        let Some(s) = self.segment(phi) else {
            return 0.0;
        };
        let x = ((phi - s.phi_start) / (s.phi_end - s.phi_start)).clamp(0.0, 1.0);
        let bump = if phi.rem_euclid(TAU) < self.params.crossover_rad {
            self.params.crossover_rise_mm
        } else {
            0.0
        };
        s.r_start + (s.r_end - s.r_start) * x + bump
    }

    /// String wound on the spool at spool angle `phi` (0 = empty), mm.
    pub fn wound_mm(&self, phi: f64) -> f64 {
        let phi = phi.clamp(0.0, self.max_angle_rad());
        let Some(s) = self.segment(phi) else {
            return 0.0;
        };
        let len = s.phi_end - s.phi_start;
        let x = phi - s.phi_start;
        let slope = if len > 0.0 {
            (s.r_end - s.r_start) / len
        } else {
            0.0
        };
        s.wound_start + s.r_start * x + 0.5 * slope * x * x + self.crossovers_mm(phi)
    }

    /// The spool angle at which `wound_mm` of string is wound: the inverse
    /// of [`Spool::wound_mm`], by bisection to 1e-12 rad.
    pub fn angle_for_wound(&self, wound_mm: f64) -> Result<f64, SpoolError> {
        if wound_mm.is_nan() || wound_mm < 0.0 {
            return Err(SpoolError::Empty { wound_mm });
        }
        let capacity_mm = self.capacity_mm();
        if wound_mm > capacity_mm {
            return Err(SpoolError::Full {
                wound_mm,
                capacity_mm,
            });
        }
        let (mut lo, mut hi) = (0.0, self.max_angle_rad());
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if self.wound_mm(mid) < wound_mm {
                lo = mid;
            } else {
                hi = mid;
            }
            if hi - lo <= 1e-12 {
                break;
            }
        }
        Ok(0.5 * (lo + hi))
    }

    /// Spool angles at which the string climbs to the next layer (the
    /// middle of each layer change), rad.
    pub fn layer_changes_rad(&self) -> Vec<f64> {
        self.segments
            .iter()
            .filter(|s| s.r_end != s.r_start)
            .map(|s| 0.5 * (s.phi_start + s.phi_end))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spool() -> Spool {
        Spool::new(SpoolParams {
            bare_radius_mm: 7.5,
            string_diameter_mm: 0.5,
            layer_packing: 0.9,
            turns_per_layer: vec![8.0, 7.3, 8.6, 7.9],
            layer_change_rad: 1.0,
            crossover_rise_mm: 0.1,
            crossover_rad: 0.4,
        })
    }

    #[test]
    fn wound_length_is_continuous_increasing_and_inverted() {
        let s = spool();
        let mut prev = -1.0;
        let n = 20_000;
        for k in 0..=n {
            let phi = s.max_angle_rad() * k as f64 / n as f64;
            let w = s.wound_mm(phi);
            assert!(w > prev, "not increasing at {phi}");
            // Continuity: the step is at most the largest radius times the angle step.
            if k > 0 {
                assert!(w - prev < 12.0 * s.max_angle_rad() / n as f64 + 1e-9);
            }
            prev = w;
            let back = s.angle_for_wound(w).unwrap();
            assert!((back - phi).abs() < 1e-9, "{phi} -> {w} -> {back}");
        }
        assert!(s.angle_for_wound(-1.0).is_err());
        assert!(s.angle_for_wound(s.capacity_mm() + 1.0).is_err());
        assert!(s.angle_for_wound(f64::NAN).is_err());
    }

    #[test]
    fn the_radius_steps_by_one_layer() {
        let s = spool();
        let changes = s.layer_changes_rad();
        assert_eq!(changes.len(), 3);
        for (k, c) in changes.iter().enumerate() {
            // Away from the cross-overs (angle = 2 pi m + pi), a turn or
            // two from the layer change.
            let before = (((c - 1.0) / TAU).floor() - 1.0) * TAU + std::f64::consts::PI;
            let after = ((c + 1.0) / TAU).ceil() * TAU + std::f64::consts::PI;
            let step = s.radius_mm(after) - s.radius_mm(before);
            assert!((step - 0.45).abs() < 1e-12, "layer {k}: {step}");
        }
    }
}
