//! One row's values as the reader takes them from the row's text, and the
//! rules every value keeps (the writer checks the same,
//! `session::check_sample`).

use std::path::Path;

use super::{DatasetError, ValueProblem};

/// How far from 1 the norm of an orientation quaternion may be (its values
/// are rounded, but a rotation is a unit quaternion).
const ORIENTATION_NORM_TOLERANCE: f64 = 1e-3;
/// The latest `t_s` a session may have (s): the device counts time since
/// home in `u32` milliseconds, so a session stamped with a clock's time
/// (Unix seconds, 1.7e9) would read as one instant, `u32::MAX` ms, on every
/// row.
pub const MAX_SESSION_TIME_S: f64 = u32::MAX as f64 / 1000.0;

pub(super) struct RowReader<'a> {
    pub(super) file: &'a Path,
    pub(super) line: u64,
    pub(super) header: &'a csv::StringRecord,
    pub(super) record: &'a csv::StringRecord,
}

impl RowReader<'_> {
    pub(super) fn error(&self, index: usize, problem: ValueProblem) -> DatasetError {
        DatasetError::Value {
            file: self.file.to_path_buf(),
            line: self.line,
            column: self.header.get(index).unwrap_or("?").to_string(),
            problem,
        }
    }

    fn text(&self, index: usize) -> &str {
        self.record.get(index).unwrap_or("")
    }

    pub(super) fn float(&self, index: usize) -> Result<f64, DatasetError> {
        parse_float(self.text(index)).map_err(|p| self.error(index, p))
    }

    pub(super) fn count(&self, index: usize) -> Result<i32, DatasetError> {
        let text = self.text(index);
        if text.is_empty() {
            return Err(self.error(index, ValueProblem::Empty));
        }
        match text.parse::<i64>() {
            Ok(v) => i32::try_from(v)
                .map_err(|_| self.error(index, ValueProblem::CountOutOfRange(text.to_string()))),
            // A whole number written as a float (`483489.0`: pandas writes
            // an integer column that had a missing value so) is that count.
            Err(_) => match text.parse::<f64>() {
                Ok(v) if v.is_finite() && v.fract() == 0.0 => {
                    if (f64::from(i32::MIN)..=f64::from(i32::MAX)).contains(&v) {
                        Ok(v as i32)
                    } else {
                        Err(self.error(index, ValueProblem::CountOutOfRange(text.to_string())))
                    }
                }
                Ok(_) => Err(self.error(index, ValueProblem::NotAnInteger(text.to_string()))),
                Err(_) => Err(self.error(index, ValueProblem::NotANumber(text.to_string()))),
            },
        }
    }

    /// A number, or `None` when empty.
    pub(super) fn optional_float(&self, index: usize) -> Result<Option<f64>, DatasetError> {
        if self.text(index).is_empty() {
            return Ok(None);
        }
        self.float(index).map(Some)
    }

    /// A home capture's id: a whole number, `u64`; `None` when empty (a
    /// row whose home is not known).
    pub(super) fn home_id(&self, index: usize) -> Result<Option<u64>, DatasetError> {
        let text = self.text(index);
        if text.is_empty() {
            return Ok(None);
        }
        text.parse::<u64>()
            .map(Some)
            .map_err(|_| self.error(index, ValueProblem::NotAHomeId(text.to_string())))
    }

    /// A group that is all filled (`Some`) or all empty (`None`).
    /// The values of `indices` in order (`out[k]` from `indices[k]`; `out`
    /// may be longer: its other entries stay 0).
    pub(super) fn group<const N: usize>(
        &self,
        indices: &[usize],
        group: &str,
    ) -> Result<Option<[f64; N]>, DatasetError> {
        let filled = indices.iter().position(|&k| !self.text(k).is_empty());
        let empty = indices.iter().position(|&k| self.text(k).is_empty());
        match (filled, empty) {
            (None, _) => Ok(None),
            (Some(_), None) => {
                let mut out = [0.0; N];
                for (o, &k) in out.iter_mut().zip(indices) {
                    *o = self.float(k)?;
                }
                Ok(Some(out))
            }
            (Some(f), Some(e)) => Err(self.error(
                indices[e],
                ValueProblem::PartialGroup {
                    filled: self.header.get(indices[f]).unwrap_or("?").to_string(),
                    group: group.to_string(),
                },
            )),
        }
    }
}

/// What is wrong with a row's orientation `q` (finite values), given
/// whether the row has a position.
pub(super) fn orientation_problem(q: &[f64; 4], has_position: bool) -> Option<ValueProblem> {
    if !has_position {
        return Some(ValueProblem::OrientationWithoutPosition);
    }
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    ((norm - 1.0).abs() > ORIENTATION_NORM_TOLERANCE)
        .then_some(ValueProblem::NotUnitQuaternion(norm))
}

fn parse_float(text: &str) -> Result<f64, ValueProblem> {
    if text.is_empty() {
        return Err(ValueProblem::Empty);
    }
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(ValueProblem::NotFinite(text.to_string())),
        Err(_) => Err(ValueProblem::NotANumber(text.to_string())),
    }
}
