//! Tukey's box plot (paper section 5.1): a pair whose absolute position error
//! (eq. 7) lies outside [Q1 - 1.5 IQR, Q3 + 1.5 IQR] is an outlier.
//!
//! Quartiles use linear interpolation between order statistics (Hyndman-Fan
//! type 7, numpy's and R's default), so the reference script finds the same
//! fences.

use super::{dist, validate_pairs, LearnError};
use serde::{Deserialize, Serialize};

/// What the box plot kept and removed, with the numbers a report needs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OutlierReport {
    /// Indices kept, ascending.
    pub kept: Vec<usize>,
    /// Indices removed, ascending.
    pub removed: Vec<usize>,
    /// Absolute position error of every input pair, mm.
    pub errors: Vec<f64>,
    pub q1: f64,
    pub q3: f64,
    pub iqr: f64,
    /// `q1 - whisker * iqr`.
    pub lower_fence: f64,
    /// `q3 + whisker * iqr`.
    pub upper_fence: f64,
    /// The whisker factor used (1.5 for Tukey's inner fences).
    pub whisker: f64,
}

impl OutlierReport {
    /// Removed points above the upper fence (large errors).
    pub fn removed_high(&self) -> usize {
        self.removed
            .iter()
            .filter(|&&i| self.errors[i] > self.upper_fence)
            .count()
    }
    /// Removed points below the lower fence.
    pub fn removed_low(&self) -> usize {
        self.removed.len() - self.removed_high()
    }
}

/// Linear-interpolation quantile of sorted data (type 7).
pub fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let h = (sorted.len() - 1) as f64 * q.clamp(0.0, 1.0);
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(sorted.len() - 1);
    sorted[lo] + (h - lo as f64) * (sorted[hi] - sorted[lo])
}

/// Tukey fences on arbitrary finite values.
pub fn tukey_values(values: &[f64], whisker: f64) -> Result<OutlierReport, LearnError> {
    super::check_range("whisker", whisker, 0.0, f64::MAX, "a finite value >= 0")?;
    if values.len() < 4 {
        return Err(LearnError::TooFewPoints {
            what: "outlier box plot",
            got: values.len(),
            need: 4,
        });
    }
    if let Some(index) = values.iter().position(|v| !v.is_finite()) {
        return Err(LearnError::NonFinite {
            what: "outlier box plot",
            index,
            axis: 0,
        });
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let q1 = quantile_sorted(&sorted, 0.25);
    let q3 = quantile_sorted(&sorted, 0.75);
    let iqr = q3 - q1;
    let lower_fence = q1 - whisker * iqr;
    let upper_fence = q3 + whisker * iqr;
    let (mut kept, mut removed) = (Vec::new(), Vec::new());
    for (i, &v) in values.iter().enumerate() {
        if v < lower_fence || v > upper_fence {
            removed.push(i);
        } else {
            kept.push(i);
        }
    }
    Ok(OutlierReport {
        kept,
        removed,
        errors: values.to_vec(),
        q1,
        q3,
        iqr,
        lower_fence,
        upper_fence,
        whisker,
    })
}

/// Tukey's box plot (whisker 1.5) on the absolute position error between the
/// device positions and the tracker positions.
pub fn tukey(inputs: &[[f64; 3]], targets: &[[f64; 3]]) -> Result<OutlierReport, LearnError> {
    validate_pairs("outlier box plot", inputs, targets, 4)?;
    let errors: Vec<f64> = inputs
        .iter()
        .zip(targets)
        .map(|(a, b)| dist(a, b))
        .collect();
    tukey_values(&errors, 1.5)
}

/// The kept pairs of a report.
pub fn select(
    report: &OutlierReport,
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let i = report.kept.iter().filter_map(|&k| inputs.get(k).copied());
    let t = report.kept.iter().filter_map(|&k| targets.get(k).copied());
    (i.collect(), t.collect())
}
