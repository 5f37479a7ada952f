//! The identified geometry against the drawing: a string's radius or an
//! anchor the identification places where the other strings' do not go
//! (a mechanical advantage written for another string, a coordinate
//! mistyped or typed in metres).

use std::path::Path;

use spidar_core::geometry::{distance, norm};
use spidar_core::model::StringLaw;
use spidar_core::STRINGS;

use crate::data::dataset::Geometry;

/// Whether an anchor written as `written` (mm) reads as metres beside the
/// identified `identified` (mm, less what every anchor moved alike): a
/// thousand times it lies nearer the identified anchor than it does, by a
/// factor of ten (an anchor typed `[1.1, 1.1, -1.1]` among anchors in mm
/// was called a typo).
fn in_metres(written: [f64; 3], identified: [f64; 3]) -> bool {
    10.0 * distance(written.map(|v| v * 1000.0), identified) < distance(written, identified)
}

/// A string's effective radius this many times the other strings' (each
/// over its own `pulley_radius_mm / mechanical_advantage`), either way, is
/// named: the log-midpoint of 1 and 2, nearer a line doubled through a
/// pulley block (or a block left out) than the spread of spools wound
/// alike. Relative to the strings' median, so a device whose every spool
/// winds wider than its bare pulley (the paper's, about 2x) is not named.
const RADIUS_APART_FACTOR: f64 = core::f64::consts::SQRT_2;

/// Warnings for strings whose identified radius at home (`laws`) departs
/// from the geometry's by a factor the other strings do not share: a
/// `mechanical_advantage` (or `pulley_radius_mm`) written for another
/// string. The identification absorbs it into the radius, so nothing else
/// says so (two strings' mechanical advantages swapped held out 44 % worse
/// than the plain fit, the warning blaming the kinematics' rule).
pub(in crate::procedures::calibrate) fn radius_warnings(
    geometry_path: &Path,
    geometry: &Geometry,
    laws: &[StringLaw; STRINGS],
) -> Vec<String> {
    let nominal = geometry.nominal_string_laws();
    let layout = geometry.layout;
    let ratios: Vec<(usize, f64)> = layout
        .indices()
        .map(|i| (i, laws[i].winding_mm[0] / nominal[i].winding_mm[0]))
        // A string that counts down (a negative radius) is named elsewhere.
        .filter(|(_, r)| r.is_finite() && *r > 0.0)
        .collect();
    if ratios.len() < 2 {
        return Vec::new();
    }
    let mut sorted: Vec<f64> = ratios.iter().map(|(_, r)| *r).collect();
    let median = crate::data::stats::median(&mut sorted);
    ratios
        .iter()
        .filter_map(|&(i, r)| {
            let apart = r / median;
            if apart.max(1.0 / apart) < RADIUS_APART_FACTOR {
                return None;
            }
            Some(format!(
                "string {i}'s radius at home is identified at {:.3} mm, {apart:.2} times the other \
                 strings' against the geometry ({}: pulley_radius_mm {} / mechanical_advantage {} \
                 = {:.3} mm, the others {median:.2} times theirs): is string {i}'s \
                 mechanical_advantage (lines through a pulley block) or pulley_radius_mm another \
                 string's?",
                laws[i].winding_mm[0],
                geometry_path.display(),
                geometry.pulley_radius_mm[i],
                geometry.mechanical_advantage[i],
                nominal[i].winding_mm[0],
            ))
        })
        .collect()
}

/// An anchor identified this many times further from the geometry's than
/// the other anchors' median departure is named ...
const ANCHOR_APART_FACTOR: f64 = 3.0;
/// ... when its departure is also this many sds of its estimate, and
/// beyond the anchors' tolerance (the prior the fit held it to: an anchor
/// within it of the drawing is where the geometry said it may be; a model
/// simulator's anchor 9 mm off among others 2 mm off was named a typo).
const ANCHOR_APART_SDS: f64 = 3.0;

/// Warnings for anchors the identification places far from the geometry's
/// where the other anchors stay near theirs: a coordinate mistyped (or an
/// anchor moved). A prior around the typo holds the anchor part of the
/// way and the rest of the model bends round it, so the held-out error
/// stays ordinary and nothing else says so (the Hangprinter with one
/// anchor's x typed 500 mm off: identified 286 mm from the geometry's with
/// an sd of 9 mm, the others 61-169 mm; as written, 32-46 mm).
pub(in crate::procedures::calibrate) fn anchor_departure_warnings(
    geometry_path: &Path,
    geometry: &Geometry,
    id: &crate::model::identify::Identification,
) -> Vec<String> {
    let nominal = geometry.nominal_frame();
    let parameter = |name: String| id.parameters.iter().find(|p| p.name == name);
    let sd_of = |name: String| parameter(name).map_or(0.0, |p| p.sd);
    let tolerance_of = |k: usize| {
        parameter(format!("anchor{k}.x"))
            .and_then(|p| p.prior_sd)
            .unwrap_or(0.0)
    };
    let moved = |k: usize, c: usize| id.frame.anchors[k][c] - nominal.anchors[k][c];
    // What every anchor moved alike (the frame shifted: a typo in the top
    // anchor's height lowered the three others 110-150 mm), the median of
    // each coordinate's moves, is no anchor's own departure.
    let common: [f64; 3] = core::array::from_fn(|c| {
        let mut moves: Vec<f64> = nominal.layout.indices().map(|k| moved(k, c)).collect();
        crate::data::stats::median(&mut moves)
    });
    let departures: Vec<(usize, f64, f64)> = nominal
        .layout
        .indices()
        .map(|k| {
            let d: [f64; 3] = core::array::from_fn(|c| moved(k, c) - common[c]);
            let norm = norm(d);
            // The estimate's sd along the departure.
            let along: f64 = ["x", "y", "z"]
                .iter()
                .zip(d)
                .map(|(c, dc)| {
                    let u = if norm > 0.0 { dc / norm } else { 0.0 };
                    (u * sd_of(format!("anchor{k}.{c}"))).powi(2)
                })
                .sum::<f64>()
                .sqrt();
            (k, norm, along)
        })
        .collect();
    if departures.len() < 3 {
        return Vec::new();
    }
    // The one anchor furthest apart: the fit bends the others round a
    // typo, and the next one out is then named for it (anchor 2, 112 mm
    // beside the typo's 344).
    let mut named: Vec<(f64, String)> = departures
        .iter()
        .filter_map(|&(k, norm, sd)| {
            let mut others: Vec<f64> = departures
                .iter()
                .filter(|o| o.0 != k)
                .map(|o| o.1)
                .collect();
            let median = crate::data::stats::median(&mut others);
            let apart = norm / median.max(f64::MIN_POSITIVE);
            let named = apart >= ANCHOR_APART_FACTOR
                && norm > ANCHOR_APART_SDS * sd
                && norm > tolerance_of(k);
            named.then(|| {
                (
                    apart,
                    format!(
                        "anchor {k} is identified {norm:.0} mm from the geometry's ({}: {:?}) \
                         beyond what every anchor moved alike, {apart:.1} times the other \
                         anchors' departures (median {median:.0} mm): check anchor {k}'s \
                         coordinates ({}). The estimate is held toward the geometry's by the \
                         anchors' tolerance: with the geometry corrected, calibrate again",
                        geometry_path.display(),
                        nominal.anchors[k],
                        if in_metres(
                            nominal.anchors[k],
                            core::array::from_fn(|c| id.frame.anchors[k][c] - common[c]),
                        ) {
                            "they read as metres: `anchors_mm` is in millimetres"
                        } else {
                            "a typo, an anchor moved, or measured at another point of its pulley"
                        }
                    ),
                )
            })
        })
        .collect();
    named.sort_by(|a, b| b.0.total_cmp(&a.0));
    named.into_iter().take(1).map(|(_, w)| w).collect()
}

/// The share of a planar session's in-plane extent its tracked positions
/// may scatter off their plane before the session is named as not
/// planar, whatever the model's residual scale.
const OFF_PLANE_SHARE: f64 = 0.1;

/// The warnings for a planar device's session whose tracked positions do
/// not lie in the tracker's x-y plane. A planar calibration reads the
/// tracker's `x, y` and holds the tracker frame's rotation about them (the
/// strings pull in the plane, nothing determines a tilt):
/// - on a plane tilted from it, the device is calibrated to the plane's
///   projection, where distances along the tilt read `cos(tilt)` short of
///   the device's (the wall robot's sessions tilted 6 degrees: anchors
///   moved in, held out 0.402 mm on a test session tilted alike, 0.405
///   level). Named when that shortfall over the session's extent along
///   the tilt exceeds `residual_scale_mm`, the identified model's string
///   residual scale: beyond it the tilt is an error the model takes up
///   without a word (a survey's planar session whose `ots_z` varied by
///   hundreds of millimetres);
/// - off any plane (a 3-D session), a string to a point `h` off the plane
///   is longer than its in-plane chord by about `h^2 / (2 L)`. Named when
///   that, at the scatter about the best plane and over the in-plane
///   extent, exceeds `residual_scale_mm`, or the scatter exceeds
///   [`OFF_PLANE_SHARE`] of the extent (a 3-D session given a planar
///   geometry was told only that no geometry fits it).
///
/// `rows`: the session's rows as read (the observations have a planar
/// device's tracker z set to the plane).
pub(in crate::procedures::calibrate) fn planar_session_warnings(
    path: &Path,
    rows: &[crate::data::dataset::Sample],
    residual_scale_mm: f64,
) -> Vec<String> {
    let points: Vec<[f64; 3]> = rows.iter().filter_map(|r| r.tracker).collect();
    // A plane through fewer rows says nothing of a tilt.
    if points.len() < 10 {
        return Vec::new();
    }
    // Least squares of z on x, y about the centroid.
    let n = points.len() as f64;
    let centre: [f64; 3] = core::array::from_fn(|c| points.iter().map(|p| p[c]).sum::<f64>() / n);
    let (mut xx, mut xy, mut yy, mut xz, mut yz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in &points {
        let (x, y, z) = (p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]);
        xx += x * x;
        xy += x * y;
        yy += y * y;
        xz += x * z;
        yz += y * z;
    }
    let det = xx * yy - xy * xy;
    if det <= 0.0 || !det.is_finite() {
        return Vec::new();
    }
    let slope = [(xz * yy - yz * xy) / det, (yz * xx - xz * xy) / det];
    let mut warnings = Vec::new();
    // Off the plane: the scatter about it against the in-plane extent.
    let off_plane_sd_mm = (points
        .iter()
        .map(|p| {
            let (x, y) = (p[0] - centre[0], p[1] - centre[1]);
            (p[2] - centre[2] - slope[0] * x - slope[1] * y).powi(2)
        })
        .sum::<f64>()
        / n)
        .sqrt();
    let in_plane_mm = 2.0 * ((xx + yy) / n).sqrt();
    let longer_mm = off_plane_sd_mm.powi(2) / (2.0 * in_plane_mm);
    // A session that leaves its plane by a tenth of its extent is no
    // planar device's (its end-effector stays in the plane; a marker's
    // height wobbles by millimetres): the residual scale of a model fitted
    // to it says nothing then (a 3-D session fitted to 125 mm).
    if longer_mm > residual_scale_mm || off_plane_sd_mm > OFF_PLANE_SHARE * in_plane_mm {
        warnings.push(format!(
            "{}: the tracked positions leave their plane by {off_plane_sd_mm:.0} mm (sd about \
             the best plane through them) over {in_plane_mm:.0} mm in it. A planar device's \
             calibration reads the tracker's x and y only, and a string to a point that far off \
             its plane is longer than in it by about {longer_mm:.1} mm (the identified model's \
             string residual scale: {residual_scale_mm:.2} mm): is this a 3-D device's session, \
             or the geometry's `planar = true` meant for another device?",
            path.display()
        ));
    }
    let gradient = norm([slope[0], slope[1], 0.0]);
    if gradient == 0.0 || !gradient.is_finite() {
        return warnings;
    }
    let tilt = gradient.atan();
    let along = |p: &[f64; 3]| (p[0] * slope[0] + p[1] * slope[1]) / gradient;
    let (low, high) = points
        .iter()
        .map(along)
        .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    let extent_mm = high - low;
    let short_mm = extent_mm * (1.0 / tilt.cos() - 1.0);
    if short_mm > residual_scale_mm {
        warnings.push(format!(
            "{}: the tracked positions lie on a plane tilted {:.1} degrees from the tracker's \
             x-y plane (ots_z changes by {:.0} mm across them). A planar device's calibration \
             reads the tracker's x and y only: it calibrates the device to the plane's \
             projection, where distances along the tilt read {short_mm:.2} mm short over the \
             session's {extent_mm:.0} mm, beyond the strings' residual scale \
             ({residual_scale_mm:.2} mm); the anchors are identified that much closer, and a test \
             session tracked in the same frame does not show it. Set the tracker's frame so the \
             device's plane is its x-y plane, and record the sessions again",
            path.display(),
            tilt.to_degrees(),
            gradient * extent_mm,
        ));
    }
    warnings
}
