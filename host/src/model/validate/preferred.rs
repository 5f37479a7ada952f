//! A choice between alternatives by their held-out means, the first being
//! the default: another is taken only when it gains enough.

/// Which of a set of alternatives a choice takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Preferred {
    /// The alternative with the lowest finite held-out mean; `None` when no
    /// mean is finite (too few rows to hold any out).
    pub best: Option<usize>,
    /// The alternative taken: [`Preferred::best`] when it lowers the
    /// default's (index 0) mean by the relative gain asked for, or when the
    /// default has no finite mean; else the default, 0.
    pub chosen: usize,
}

/// The alternative taken among `means` (held-out means, mm; index 0 the
/// default) with a relative gain of `min_gain` asked of any other.
pub fn preferred(means: &[f64], min_gain: f64) -> Preferred {
    let default = means.first().copied().unwrap_or(f64::NAN);
    let best = means
        .iter()
        .enumerate()
        .filter(|(_, m)| m.is_finite())
        .min_by(|a, b| a.1.total_cmp(b.1))
        .map(|(k, _)| k);
    let chosen = match best {
        Some(k) if k != 0 && (means[k] < default * (1.0 - min_gain) || !default.is_finite()) => k,
        _ => 0,
    };
    Preferred { best, chosen }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_stays_unless_another_gains_enough() {
        assert_eq!(
            preferred(&[1.0, 0.99, 1.2], 0.02),
            Preferred {
                best: Some(1),
                chosen: 0
            }
        );
        assert_eq!(preferred(&[1.0, 0.97, 0.95], 0.02).chosen, 2);
        assert_eq!(preferred(&[f64::NAN, 3.0], 0.02).chosen, 1);
        assert_eq!(
            preferred(&[f64::NAN, f64::INFINITY], 0.02),
            Preferred {
                best: None,
                chosen: 0
            }
        );
        assert_eq!(preferred(&[], 0.02).best, None);
    }
}
