//! Eq. 10 of the paper: `N = (P - mean) / std`, per axis.
//!
//! The standard deviation is the population one (divide by n), as
//! scikit-learn's `StandardScaler` and numpy's default: the reference script
//! uses the same, so both sides see identical standardized data.

use super::{validate_points, LearnError, Standardization};

/// Relative spread below which an axis that is not exactly constant is
/// refused: dividing by such a std would blow rounding noise up to unit
/// variance.
const MIN_REL_SPREAD: f64 = 1e-12;

/// Per-axis mean and standard deviation of `points`.
pub fn fit(what: &'static str, points: &[[f64; 3]]) -> Result<Standardization, LearnError> {
    validate_points(what, points, 2)?;
    let n = points.len() as f64;
    let mut mean = [0.0; 3];
    for p in points {
        for a in 0..3 {
            mean[a] += p[a];
        }
    }
    for m in &mut mean {
        *m /= n;
    }
    // Two-pass variance: the one-pass formula loses digits when positions sit
    // far from the origin (room coordinates in mm).
    let mut var = [0.0; 3];
    for p in points {
        for a in 0..3 {
            let d = p[a] - mean[a];
            var[a] += d * d;
        }
    }
    let mut std = [0.0; 3];
    for a in 0..3 {
        std[a] = (var[a] / n).sqrt();
        if points.iter().all(|p| p[a] == points[0][a]) {
            // An exactly constant axis (a planar device's z) carries no
            // information: scale 1, as scikit-learn's StandardScaler does,
            // so it standardizes to 0 everywhere.
            std[a] = 1.0;
            continue;
        }
        let scale = mean[a].abs().max(1.0);
        // Also catches NaN (cannot happen after validation, but cheap).
        if std[a].is_nan() || std[a] <= MIN_REL_SPREAD * scale {
            return Err(LearnError::ZeroSpread { what, axis: a });
        }
    }
    Ok(Standardization { mean, std })
}

/// `(p - mean) / std`.
pub fn apply(s: &Standardization, p: &[f64; 3]) -> [f64; 3] {
    [
        (p[0] - s.mean[0]) / s.std[0],
        (p[1] - s.mean[1]) / s.std[1],
        (p[2] - s.mean[2]) / s.std[2],
    ]
}

/// `n * std + mean`.
pub fn invert(s: &Standardization, n: &[f64; 3]) -> [f64; 3] {
    [
        n[0] * s.std[0] + s.mean[0],
        n[1] * s.std[1] + s.mean[1],
        n[2] * s.std[2] + s.mean[2],
    ]
}

pub fn apply_all(s: &Standardization, points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    points.iter().map(|p| apply(s, p)).collect()
}

/// The regression targets for a mode: the target position (absolute) or
/// target minus input (residual), in mm.
pub fn mode_targets(
    mode: super::OutputMode,
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
) -> Vec<[f64; 3]> {
    match mode {
        super::OutputMode::Absolute => targets.to_vec(),
        super::OutputMode::Residual => inputs
            .iter()
            .zip(targets)
            .map(|(i, t)| [t[0] - i[0], t[1] - i[1], t[2] - i[2]])
            .collect(),
    }
}

/// Back from a model output (standardized) to a position in mm.
pub fn output_position(
    mode: super::OutputMode,
    output: &Standardization,
    input_mm: &[f64; 3],
    y_std: &[f64; 3],
) -> [f64; 3] {
    let y = invert(output, y_std);
    match mode {
        super::OutputMode::Absolute => y,
        super::OutputMode::Residual => [input_mm[0] + y[0], input_mm[1] + y[1], input_mm[2] + y[2]],
    }
}
