//! Error statistics: the one place every report computes them.
//!
//! The absolute position error of the paper's eq. 7 is the Euclidean distance
//! between a position and its reference (the tracker), in mm; reports give its
//! mean, standard deviation and maximum (tables 1-6).

use serde::{Deserialize, Serialize};

/// Eq. 7: `|p - reference|`, in mm.
pub fn position_error(p: [f64; 3], reference: [f64; 3]) -> f64 {
    let d = [
        p[0] - reference[0],
        p[1] - reference[1],
        p[2] - reference[2],
    ];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

/// Eq. 7 for paired lists of positions.
pub fn position_errors(positions: &[[f64; 3]], references: &[[f64; 3]]) -> Vec<f64> {
    positions
        .iter()
        .zip(references)
        .map(|(p, r)| position_error(*p, *r))
        .collect()
}

/// Median of `values` (reorders them in place; 0 when empty): the middle
/// value, or the mean of the two middle ones, in `f64::total_cmp`'s order.
/// Selected, not sorted: the robust rounds take two medians of every
/// residual of a session at each round.
pub fn median(values: &mut [f64]) -> f64 {
    let n = values.len();
    if n == 0 {
        return 0.0;
    }
    let (below, &mut middle, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        middle
    } else {
        // The lower middle value is the largest of those below.
        let lower = below
            .iter()
            .copied()
            .max_by(f64::total_cmp)
            .unwrap_or(middle);
        0.5 * (lower + middle)
    }
}

/// The median of each value's window `values[t - half ..= t + half]` (cut
/// at the ends), as [`median`] of that window, for every `t`. The window
/// is kept sorted from one value to the next (one removal and one
/// insertion), not sorted again: a session of 2,000 rows and a window of
/// 41 cost 2,000 shifts of 41 values instead of 2,000 sorts and
/// allocations, which made every identification 10 % slower.
pub fn running_median(values: &[f64], half: usize) -> Vec<f64> {
    let n = values.len();
    let mut window: Vec<f64> = Vec::with_capacity(2 * half + 1);
    let insert = |window: &mut Vec<f64>, v: f64| {
        let at = window.partition_point(|x| x.total_cmp(&v).is_lt());
        window.insert(at, v);
    };
    for &v in &values[..half.min(n)] {
        insert(&mut window, v);
    }
    let mut out = Vec::with_capacity(n);
    for t in 0..n {
        if t + half < n {
            insert(&mut window, values[t + half]);
        }
        if t > half {
            let gone = values[t - half - 1];
            let at = window.partition_point(|x| x.total_cmp(&gone).is_lt());
            window.remove(at);
        }
        let m = window.len();
        out.push(if m % 2 == 1 {
            window[m / 2]
        } else {
            0.5 * (window[m / 2 - 1] + window[m / 2])
        });
    }
    out
}

/// Robust centre and spread of `values`: the median and 1.4826 times the
/// median absolute deviation (the standard deviation for Gaussian data, not
/// moved by a few gross values). `(0, 0)` when empty.
pub fn robust_centre_and_sd(values: &[f64]) -> (f64, f64) {
    let mut v = values.to_vec();
    let centre = median(&mut v);
    for x in v.iter_mut() {
        *x = (*x - centre).abs();
    }
    (centre, 1.4826 * median(&mut v))
}

/// Summary of a set of absolute errors (mm), as in the paper's tables.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ErrorStats {
    /// Number of errors summarized.
    pub n: usize,
    pub mean_mm: f64,
    /// Sample standard deviation (n - 1 in the denominator); 0 for n < 2.
    pub sd_mm: f64,
    pub max_mm: f64,
    /// Median and 95th percentile (nearest rank), for robust reading.
    pub median_mm: f64,
    pub p95_mm: f64,
}

impl ErrorStats {
    /// Statistics of `errors`; non-finite values are not summarized but
    /// counted by the caller (see [`error_stats_checked`]).
    pub fn of(errors: &[f64]) -> ErrorStats {
        let n = errors.len();
        if n == 0 {
            return ErrorStats {
                n: 0,
                mean_mm: f64::NAN,
                sd_mm: f64::NAN,
                max_mm: f64::NAN,
                median_mm: f64::NAN,
                p95_mm: f64::NAN,
            };
        }
        let mean = errors.iter().sum::<f64>() / n as f64;
        let sd = if n > 1 {
            (errors.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / (n - 1) as f64).sqrt()
        } else {
            0.0
        };
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let rank = |q: f64| sorted[(((q * n as f64).ceil() as usize).max(1) - 1).min(n - 1)];
        ErrorStats {
            n,
            mean_mm: mean,
            sd_mm: sd,
            max_mm: sorted[n - 1],
            median_mm: rank(0.5),
            p95_mm: rank(0.95),
        }
    }
}

impl ErrorStats {
    /// Statistics of `|a_i - b_i|` over paired positions (eq. 7; the
    /// shorter slice decides how many).
    pub fn between(a: &[[f64; 3]], b: &[[f64; 3]]) -> ErrorStats {
        let d: Vec<f64> = a
            .iter()
            .zip(b)
            .map(|(p, q)| position_error(*p, *q))
            .collect();
        ErrorStats::of(&d)
    }
}

/// The `q` quantile (nearest rank, `q` in 0..=1) of `values`; NaN when
/// there are none.
pub fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let n = sorted.len();
    sorted[(((q * n as f64).ceil() as usize).max(1) - 1).min(n - 1)]
}

/// The chi-square that `dof` independent standard normals exceed with
/// probability 0.001: the level at which every test of the calibration
/// that is not a search over many columns (a term's halves, a declared
/// tolerance, an anchor beyond its tolerance) calls a difference real.
/// Exact to the table's digits up to 10 dof; beyond, the Wilson-Hilferty
/// approximation (within 1 % from 10 dof).
pub fn chi_square_p001(dof: usize) -> f64 {
    const TABLE: [f64; 10] = [
        10.828, 13.816, 16.266, 18.467, 20.515, 22.458, 24.322, 26.124, 27.877, 29.588,
    ];
    match dof {
        0 => 0.0,
        1..=10 => TABLE[dof - 1],
        _ => {
            // The normal's 0.999 quantile.
            const Z: f64 = 3.090_232;
            let k = dof as f64;
            let a = 2.0 / (9.0 * k);
            k * (1.0 - a + Z * a.sqrt()).powi(3)
        }
    }
}

/// Errors that make statistics meaningless.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StatsError {
    #[error("{what}: no errors to summarize")]
    Empty { what: String },
    #[error("{what}: error #{index} is not finite ({value})")]
    NonFinite {
        what: String,
        index: usize,
        value: f64,
    },
}

/// [`ErrorStats::of`], refusing empty or non-finite input with an error that
/// names `what` (e.g. "identified, test session") and the offending index.
pub fn error_stats_checked(what: &str, errors: &[f64]) -> Result<ErrorStats, StatsError> {
    if errors.is_empty() {
        return Err(StatsError::Empty {
            what: what.to_string(),
        });
    }
    if let Some((index, &value)) = errors.iter().enumerate().find(|(_, e)| !e.is_finite()) {
        return Err(StatsError::NonFinite {
            what: what.to_string(),
            index,
            value,
        });
    }
    Ok(ErrorStats::of(errors))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chi_square_level_runs_on_smoothly_past_its_table() {
        // Wilson-Hilferty at 10 dof against the table's 29.588, and the
        // published 0.999 quantiles at 20 and 40 dof.
        let k10 = {
            let a = 2.0 / 90.0;
            10.0 * (1.0 - a + 3.090_232 * f64::sqrt(a)).powi(3)
        };
        assert!((k10 / chi_square_p001(10) - 1.0).abs() < 0.01, "{k10}");
        assert!(
            (chi_square_p001(20) - 45.315).abs() < 0.2,
            "{}",
            chi_square_p001(20)
        );
        assert!(
            (chi_square_p001(40) - 73.402).abs() < 0.3,
            "{}",
            chi_square_p001(40)
        );
        let levels: Vec<f64> = (1..30).map(chi_square_p001).collect();
        assert!(levels.windows(2).all(|w| w[1] > w[0]));
    }

    proptest::proptest! {
        /// The selected median is the sorted list's middle, to the bit,
        /// with repeated values and both parities.
        #[test]
        fn median_is_the_sorted_middle(values in proptest::collection::vec(-4i32..4, 1..40),
                                       spread in proptest::prelude::any::<f64>()) {
            let spread = if spread.is_finite() { spread } else { 1.0 };
            let mut v: Vec<f64> = values.iter().map(|&k| f64::from(k) * spread).collect();
            let mut sorted = v.clone();
            sorted.sort_by(f64::total_cmp);
            let n = sorted.len();
            let middle = if n % 2 == 1 {
                sorted[n / 2]
            } else {
                0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
            };
            let m = median(&mut v);
            proptest::prop_assert!(m.to_bits() == middle.to_bits() || (m.is_nan() && middle.is_nan()));
        }
    }

    #[test]
    fn running_median_is_the_median_of_each_window() {
        let values: Vec<f64> = (0..57)
            .map(|k| ((k * 37) % 23) as f64 - 0.5 * k as f64)
            .collect();
        for half in [0, 1, 4, 20, 60] {
            let fast = running_median(&values, half);
            for (t, m) in fast.iter().enumerate() {
                let from = t.saturating_sub(half);
                let to = (t + half + 1).min(values.len());
                let mut w = values[from..to].to_vec();
                assert_eq!(*m, median(&mut w), "half {half}, t {t}");
            }
        }
        assert!(running_median(&[], 3).is_empty());
    }

    #[test]
    fn eq7_and_summary() {
        assert_eq!(position_error([3.0, 4.0, 12.0], [0.0, 0.0, 0.0]), 13.0);
        let s = ErrorStats::of(&[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(s.n, 4);
        assert_eq!(s.mean_mm, 2.5);
        assert!((s.sd_mm - 1.2909944487358056).abs() < 1e-12);
        assert_eq!(s.max_mm, 4.0);
        assert_eq!(s.median_mm, 2.0);
        assert_eq!(s.p95_mm, 4.0);
    }

    #[test]
    fn refuses_empty_and_nan_by_name() {
        let e = error_stats_checked("raw, train", &[]).unwrap_err();
        assert!(e.to_string().contains("raw, train"));
        let e = error_stats_checked("nn, test", &[1.0, f64::NAN]).unwrap_err();
        assert_eq!(e.to_string(), "nn, test: error #1 is not finite (NaN)");
    }
}
