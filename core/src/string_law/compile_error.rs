//! Why a string law or an effect term cannot be compiled to fixed point
//! ([`StringLawCompileError`]), and the checked conversions every compiler
//! of the law goes through: a parameter finite, in its range, and fitting
//! its fixed-point format.

use core::f64::consts::TAU;
use core::fmt;

use super::COUNTS_SHIFT;
use crate::model::WINDING_ORDER;
use crate::STRINGS;

/// Why a string law or an effect term cannot be compiled to fixed point (or a
/// compiled one is invalid). Fields are named as in [`StringLaw`], [`Effect`]
/// and [`Frame`].
///
/// [`Effect`]: crate::model::Effect
/// [`Frame`]: crate::model::Frame
/// [`StringLaw`]: crate::model::StringLaw
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StringLawCompileError {
    /// The string index is not in `0..STRINGS`.
    StringOutOfRange { string: usize },
    /// A parameter is NaN or infinite.
    NotFinite { string: usize, field: &'static str },
    /// A parameter, scaled to its fixed-point format, does not fit it.
    DoesNotFit {
        string: usize,
        field: &'static str,
        value: f64,
        format: &'static str,
    },
    /// A parameter is outside its allowed range.
    OutOfRange {
        string: usize,
        field: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
}

impl fmt::Display for StringLawCompileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            StringLawCompileError::StringOutOfRange { string } => {
                write!(f, "string {string} is out of range 0..{STRINGS}")
            }
            StringLawCompileError::NotFinite { string, field } => {
                write!(f, "string {string}: {field} is not finite")
            }
            StringLawCompileError::DoesNotFit {
                string,
                field,
                value,
                format,
            } => write!(
                f,
                "string {string}: {field} = {value} does not fit {format}"
            ),
            StringLawCompileError::OutOfRange {
                string,
                field,
                value,
                min,
                max,
            } => write!(
                f,
                "string {string}: {field} = {value} is outside [{min}, {max}]"
            ),
        }
    }
}

impl core::error::Error for StringLawCompileError {}

pub(super) const WINDING_FIELDS: [&str; WINDING_ORDER] = [
    "winding_mm[0]",
    "winding_mm[1]",
    "winding_mm[2]",
    "winding_mm[3]",
];

pub(super) fn finite(
    string: usize,
    field: &'static str,
    v: f64,
) -> Result<f64, StringLawCompileError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(StringLawCompileError::NotFinite { string, field })
    }
}

/// `v` when finite and within `min..=max`, else the error naming `field`.
pub(super) fn in_range(
    string: usize,
    field: &'static str,
    v: f64,
    min: f64,
    max: f64,
) -> Result<f64, StringLawCompileError> {
    let v = finite(string, field, v)?;
    if (min..=max).contains(&v) {
        Ok(v)
    } else {
        Err(StringLawCompileError::OutOfRange {
            string,
            field,
            value: v,
            min,
            max,
        })
    }
}

/// `round(v * 2^frac)` as i64, or an error naming `field`.
pub(super) fn to_fixed(
    string: usize,
    field: &'static str,
    v: f64,
    frac: i32,
    format: &'static str,
) -> Result<i64, StringLawCompileError> {
    let v = finite(string, field, v)?;
    let scaled = libm::round(v * libm::exp2(f64::from(frac)));
    // 2^63 is exactly representable; i64::MAX is not.
    const TWO_63: f64 = 9_223_372_036_854_775_808.0;
    if !(-TWO_63..TWO_63).contains(&scaled) {
        return Err(StringLawCompileError::DoesNotFit {
            string,
            field,
            value: v,
            format,
        });
    }
    Ok(scaled as i64)
}

pub(super) fn to_fixed_i32(
    string: usize,
    field: &'static str,
    v: f64,
    frac: i32,
    format: &'static str,
) -> Result<i32, StringLawCompileError> {
    let q = to_fixed(string, field, v, frac, format)?;
    i32::try_from(q).map_err(|_| StringLawCompileError::DoesNotFit {
        string,
        field,
        value: v,
        format,
    })
}

pub(super) fn check_counts_per_rev(
    string: usize,
    counts_per_rev: u32,
) -> Result<(), StringLawCompileError> {
    if counts_per_rev == 0 || counts_per_rev > i32::MAX as u32 {
        return Err(StringLawCompileError::OutOfRange {
            string,
            field: "counts_per_rev",
            value: f64::from(counts_per_rev),
            min: 1.0,
            max: f64::from(i32::MAX),
        });
    }
    Ok(())
}

/// `2 pi 2^COUNTS_SHIFT / counts_per_rev`: rad per unit of `x`.
pub(super) fn rad_per_x(counts_per_rev: u32) -> f64 {
    TAU * libm::exp2(f64::from(COUNTS_SHIFT)) / f64::from(counts_per_rev)
}
