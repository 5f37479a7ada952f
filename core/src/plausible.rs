//! Whether a calibration can be a device at all: checks a compiler runs
//! before it turns a calibration into a model blob.
//!
//! The fixed-point compiler checks that every number fits its format, and
//! the host compares fixed point with f64; neither asks whether the f64
//! model is a physical device. These checks do, with bounds that no real
//! rig comes near (they catch a corrupted or hand-edited calibration, not a
//! poor one):
//!
//! - the room rotation is a rotation (`R R^T = I` to 1e-3: a rotation
//!   written with four decimals passes, a skewed or scaled matrix does not);
//! - the room scale (the tracker's millimetre in the device's) is within a
//!   factor of [`MAX_ROOM_SCALE_FACTOR`] of 1: beyond it the tracker is in
//!   another unit, which the calibration refuses in a session too;
//! - no two active anchors closer than [`MIN_ANCHOR_SEPARATION_MM`]: two
//!   strings leaving one point cannot be told apart;
//! - no anchor [`FAR_BEYOND_FACTOR`] times further from home than the
//!   anchors' median, nor beyond [`MAX_ANCHOR_DISTANCE_MM`];
//! - home no further from the anchors' centre than [`FAR_BEYOND_FACTOR`]
//!   times the anchors' own extent (the farthest anchor from that centre):
//!   a suspended robot's home may lie outside the anchors' hull, not
//!   orders of magnitude beyond the frame;
//! - each string's winding polynomial pays out more string as the counts
//!   rise over the whole range the frame allows: from wound up to its
//!   anchor (`-|home - anchor|`) to paid out across the frame (the farthest
//!   other anchor). The layer table's bounded departure is not part of it.

use core::fmt;

use crate::model::{Frame, StringLaw};
use crate::string_law::{polynomial_payout_at_f64, polynomial_slope_f64};
use crate::STRINGS;

/// Two active anchors closer than this (mm) are one point.
pub const MIN_ANCHOR_SEPARATION_MM: f64 = 1.0;
/// An anchor this many times further from home than the anchors' median
/// distance is orders of magnitude beyond the frame.
pub const FAR_BEYOND_FACTOR: f64 = 100.0;
/// No anchor further than this from home (mm): 10 km, beyond the largest
/// cable robots built (hundreds of metres).
pub const MAX_ANCHOR_DISTANCE_MM: f64 = 1e7;
/// Largest deviation of `R R^T` from the identity, per element: a rotation
/// rounded to four decimals deviates by ~1e-4 (the QEMU benchmarks' own
/// calibration does), an identified one by ~1e-15.
pub const ROTATION_TOLERANCE: f64 = 1e-3;
/// The room scale is within this factor of 1 either way: a tracker and a
/// device that both give millimetres agree to a fraction of a percent; at
/// this factor the tracker gives another unit (the calibration refuses a
/// session whose tracker spreads this many times the nominal model's
/// positions, `data::impossible::NOMINAL_SCALE_LIMIT` on the host).
pub const MAX_ROOM_SCALE_FACTOR: f64 = 5.0;
/// Steps of the march along the pulley angle on either side of home.
const PAYOUT_STEPS: usize = 1024;

/// Why a calibration cannot be a device, naming the field.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Implausible {
    /// `frame.room_rotation` is not orthonormal.
    RoomRotation { deviation: f64 },
    /// `frame.room_scale` is not positive, or beyond
    /// [`MAX_ROOM_SCALE_FACTOR`] of 1.
    RoomScale { scale: f64 },
    /// `frame.anchors[a]` and `frame.anchors[b]` coincide.
    CoincidentAnchors { a: u8, b: u8, apart_mm: f64 },
    /// `frame.anchors[string]` lies orders of magnitude beyond the others.
    AnchorFarBeyond {
        string: u8,
        distance_mm: f64,
        median_mm: f64,
    },
    /// `frame.home` lies orders of magnitude beyond the anchors' frame.
    HomeFarBeyond { distance_mm: f64, extent_mm: f64 },
    /// `strings[string].winding_mm`: the payout already falls (or stands
    /// still) as the counts rise at home: the winding radius at home
    /// (`radius_mm`, the slope there) is not positive. The string's counts
    /// fall as it pays out: a reversed encoder, or two strings' encoder
    /// channels swapped.
    CountsFallAtHome { string: u8, radius_mm: f64 },
    /// `strings[string].winding_mm`: the payout stops rising (falls as the
    /// counts rise) at `paid_out_mm` from home, inside the range the frame
    /// needs (`needed_mm`, negative: winding up toward the anchor).
    PayoutFalls {
        string: u8,
        paid_out_mm: f64,
        needed_mm: f64,
    },
}

impl fmt::Display for Implausible {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Implausible::RoomRotation { deviation } => write!(
                f,
                "frame.room_rotation is not a rotation: R R^T differs from the identity by {deviation:.3e}"
            ),
            Implausible::RoomScale { scale } => write!(
                f,
                "frame.room_scale is {scale:e}: a tracker and a device that both give \
                 millimetres agree within a factor of {MAX_ROOM_SCALE_FACTOR} (beyond it, one \
                 of them gives another unit)"
            ),
            Implausible::CoincidentAnchors { a, b, apart_mm } => write!(
                f,
                "frame.anchors[{a}] and frame.anchors[{b}] are {apart_mm:.3} mm apart: two strings \
                 cannot leave from one point"
            ),
            Implausible::AnchorFarBeyond {
                string,
                distance_mm,
                median_mm,
            } => write!(
                f,
                "frame.anchors[{string}] is {distance_mm:.4e} mm from home, orders of magnitude \
                 beyond the anchors' median of {median_mm:.1} mm"
            ),
            Implausible::HomeFarBeyond {
                distance_mm,
                extent_mm,
            } => write!(
                f,
                "frame.home is {distance_mm:.4e} mm from the anchors' centre, orders of magnitude \
                 beyond the frame they span ({extent_mm:.1} mm from that centre to the farthest)"
            ),
            Implausible::CountsFallAtHome { string, radius_mm } => write!(
                f,
                "strings[{string}].winding_mm: the winding radius at home is {radius_mm:.3} mm, \
                 not positive: the string's counts fall as it pays out (a reversed encoder, or \
                 two strings' encoder channels swapped); a device's counts rise as its string \
                 pays out"
            ),
            Implausible::PayoutFalls {
                string,
                paid_out_mm,
                needed_mm,
            } => write!(
                f,
                "strings[{string}].winding_mm: the payout stops rising with the counts at \
                 {paid_out_mm:.1} mm from home, inside the {needed_mm:.1} mm this frame needs \
                 (no spool winds like that)"
            ),
        }
    }
}

impl core::error::Error for Implausible {}

/// Checks that `frame` and `strings` can be a device (see the module's
/// documentation); the first problem found.
pub fn check_device(frame: &Frame<f64>, strings: &[StringLaw; STRINGS]) -> Result<(), Implausible> {
    check_rotation(&frame.room_rotation)?;
    let scale = frame.room_scale;
    // A NaN is in no range: refused too.
    if !(1.0 / MAX_ROOM_SCALE_FACTOR..=MAX_ROOM_SCALE_FACTOR).contains(&scale) {
        return Err(Implausible::RoomScale { scale });
    }
    check_anchors(frame)?;
    for i in frame.layout.indices() {
        check_payout(frame, i, &strings[i])?;
    }
    Ok(())
}

fn check_rotation(r: &[[f64; 3]; 3]) -> Result<(), Implausible> {
    let mut deviation: f64 = 0.0;
    for (i, ri) in r.iter().enumerate() {
        for (j, rj) in r.iter().enumerate() {
            let dot = ri[0] * rj[0] + ri[1] * rj[1] + ri[2] * rj[2];
            let want = if i == j { 1.0 } else { 0.0 };
            let d = (dot - want).abs();
            // A NaN compares false: it must count as the largest deviation.
            deviation = if d.is_nan() {
                f64::INFINITY
            } else {
                deviation.max(d)
            };
        }
    }
    if deviation > ROTATION_TOLERANCE {
        return Err(Implausible::RoomRotation { deviation });
    }
    Ok(())
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    libm::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
}

fn check_anchors(frame: &Frame<f64>) -> Result<(), Implausible> {
    let active = frame.layout;
    for a in active.indices() {
        for b in active.indices().filter(|&b| b > a) {
            let apart_mm = distance(&frame.anchors[a], &frame.anchors[b]);
            if apart_mm < MIN_ANCHOR_SEPARATION_MM {
                return Err(Implausible::CoincidentAnchors {
                    a: a as u8,
                    b: b as u8,
                    apart_mm,
                });
            }
        }
    }
    check_home(frame)?;
    let mut from_home = [0.0f64; STRINGS];
    let mut n = 0;
    for i in active.indices() {
        from_home[n] = distance(&frame.anchors[i], &frame.home);
        n += 1;
    }
    let sorted = &mut from_home[..n];
    sorted.sort_unstable_by(f64::total_cmp);
    let median_mm = if n == 0 { 0.0 } else { sorted[(n - 1) / 2] };
    for i in active.indices() {
        let distance_mm = distance(&frame.anchors[i], &frame.home);
        if !(distance_mm <= MAX_ANCHOR_DISTANCE_MM
            && distance_mm <= FAR_BEYOND_FACTOR * median_mm.max(MIN_ANCHOR_SEPARATION_MM))
        {
            return Err(Implausible::AnchorFarBeyond {
                string: i as u8,
                distance_mm,
                median_mm,
            });
        }
    }
    Ok(())
}

/// Refuses a home [`FAR_BEYOND_FACTOR`] times the anchors' extent from
/// their centre (after the anchors are known to be apart).
fn check_home(frame: &Frame<f64>) -> Result<(), Implausible> {
    let mut centre = [0.0f64; 3];
    let mut n = 0.0;
    for i in frame.layout.indices() {
        for (c, a) in centre.iter_mut().zip(&frame.anchors[i]) {
            *c += a;
        }
        n += 1.0;
    }
    if n == 0.0 {
        return Ok(());
    }
    let centre = centre.map(|c| c / n);
    let extent_mm = frame
        .layout
        .indices()
        .map(|i| distance(&frame.anchors[i], &centre))
        .fold(0.0, f64::max);
    let distance_mm = distance(&frame.home, &centre);
    // A NaN home is in no range: refused too.
    let within = distance_mm <= FAR_BEYOND_FACTOR * extent_mm.max(MIN_ANCHOR_SEPARATION_MM);
    if !within {
        return Err(Implausible::HomeFarBeyond {
            distance_mm,
            extent_mm,
        });
    }
    Ok(())
}

/// Refuses a slope at home that is not positive (the counts fall as the
/// string pays out), then marches the pulley angle from home toward
/// `needed_mm` of payout (either sign) and refuses a slope that is not
/// positive before it is reached.
fn check_payout(frame: &Frame<f64>, i: usize, law: &StringLaw) -> Result<(), Implausible> {
    let anchor = &frame.anchors[i];
    let home_length = distance(anchor, &frame.home);
    let across = frame
        .layout
        .indices()
        .map(|j| distance(anchor, &frame.anchors[j]))
        .fold(0.0, f64::max);
    let falls = |paid_out_mm: f64, needed_mm: f64| Implausible::PayoutFalls {
        string: i as u8,
        paid_out_mm,
        needed_mm,
    };
    // A NaN slope is not a rising one.
    let rises = |slope: f64| slope > 0.0;
    let slope_at_home = polynomial_slope_f64(law, 0.0);
    if !rises(slope_at_home) {
        return Err(Implausible::CountsFallAtHome {
            string: i as u8,
            radius_mm: slope_at_home,
        });
    }
    for needed_mm in [(across - home_length).max(0.0), -home_length] {
        // At the slope at home the angle needed; a law whose slope shrinks
        // may need more, so the march goes up to 4 times as far.
        let step = needed_mm / slope_at_home * 4.0 / PAYOUT_STEPS as f64;
        for k in 1..=PAYOUT_STEPS {
            let theta = step * k as f64;
            let paid_out_mm = polynomial_payout_at_f64(law, theta);
            if paid_out_mm.abs() >= needed_mm.abs() {
                break;
            }
            if !rises(polynomial_slope_f64(law, theta)) || k == PAYOUT_STEPS {
                return Err(falls(paid_out_mm, needed_mm));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
