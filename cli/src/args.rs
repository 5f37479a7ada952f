//! Parsers of the numeric options that clap's own cannot say: a duration or
//! a size must be a finite number of the right sign, and the message names
//! the unit (`--seconds NaN` had run a virtual device for ever).

/// A finite number > 0.
pub fn positive(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not a finite number above 0")),
        Err(e) => Err(format!("`{text}` is not a number: {e}")),
    }
}

/// A finite number >= 0.
pub fn non_negative(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not a finite number of 0 or more")),
        Err(e) => Err(format!("`{text}` is not a number: {e}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_and_sizes_are_finite_numbers_of_their_sign() {
        assert_eq!(positive("2.5"), Ok(2.5));
        assert_eq!(non_negative("0"), Ok(0.0));
        for bad in ["NaN", "inf", "-1", "0", "x"] {
            assert!(positive(bad).is_err(), "{bad}");
        }
        for bad in ["NaN", "-inf", "-0.1", ""] {
            assert!(non_negative(bad).is_err(), "{bad}");
        }
    }
}
