//! The robust rounds' weights (least squares, Huber, Tukey) and the
//! residuals' scales.

use spidar_core::model::StringLayout;
use spidar_core::STRINGS;

/// Rows on each side of a row whose median residual is taken off it before
/// its string's scale is read ([`fast_residual_scales`]): 41 rows span
/// three rows of a 13-point lattice walked back and forth, so both
/// directions of approach.
const SCALE_WINDOW_ROWS: usize = 20;

/// Each active string's scale of the part of its residual that changes
/// from row to row (mm; 0 on inactive channels), what forward kinematics
/// weighs the strings by: the robust sd of the residual less its running
/// median over `2 SCALE_WINDOW_ROWS + 1` tracked rows in session order.
/// An error the model lacks that moves slowly (a drift, a slip's step, a
/// spool's error smooth along the walk) is taken off with the median; one
/// that changes from capture to capture (an encoder that lags the string,
/// read at each capture's own speed and direction) stays. Read on the
/// residuals themselves, a slip the loop has not yet found would make its
/// string weigh less, and the held-out error would then hide the slip; read
/// from one row to the next, the lag would cancel (a lattice row approaches
/// its points from one side; decision record 0036,
/// `docs/decisions/0036-strings-weighed-by-scale.md`).
pub(super) fn fast_residual_scales(
    residuals: &[[f64; STRINGS]],
    layout: StringLayout,
) -> [f64; STRINGS] {
    core::array::from_fn(|i| {
        if !layout.is_active(i) {
            return 0.0;
        }
        let own: Vec<f64> = residuals.iter().map(|r| r[i]).collect();
        let slow = crate::data::stats::running_median(&own, SCALE_WINDOW_ROWS);
        let fast: Vec<f64> = own.iter().zip(&slow).map(|(r, m)| r - m).collect();
        crate::data::stats::robust_centre_and_sd(&fast).1.max(1e-6)
    })
}

/// Robust scale (1.4826 MAD) of the residuals of the active strings:
/// [`robust_centre_and_sd`](crate::data::stats::robust_centre_and_sd)'s,
/// taken in place (a long session's residuals are megabytes).
pub(super) fn robust_scale(residuals: &[[f64; STRINGS]], layout: StringLayout) -> f64 {
    use crate::data::stats::median;
    let mut all: Vec<f64> = residuals
        .iter()
        .flat_map(|r| layout.indices().map(|i| r[i]))
        .collect();
    let centre = median(&mut all);
    for x in all.iter_mut() {
        *x = (*x - centre).abs();
    }
    1.4826 * median(&mut all)
}

#[derive(Clone, Copy)]
pub(super) enum Round {
    LeastSquares,
    Huber,
    Tukey,
}

pub(super) fn weight(round: Round, r: f64, scale: f64) -> f64 {
    match round {
        Round::LeastSquares => 1.0,
        Round::Huber => {
            let c = 1.345 * scale;
            if r.abs() <= c {
                1.0
            } else {
                c / r.abs()
            }
        }
        Round::Tukey => {
            let c = 4.685 * scale;
            if r.abs() >= c {
                0.0
            } else {
                let u = r / c;
                (1.0 - u * u) * (1.0 - u * u)
            }
        }
    }
}
