//! One row's values: the rules each keeps, read from a row's text, checked
//! before a sample is written, and written as the row's fields.

use std::path::Path;

use spidar_core::STRINGS;

use super::columns::{
    OptionalColumns, LEGACY_COLUMNS, ORIENTATION_COLUMNS, TENSION_COLUMNS, TIME_COLUMN,
    TRACKER_COLUMNS,
};
use super::{DatasetError, Sample, ValueProblem};

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

/// What the reader requires of one sample written at `line`, after a sample
/// at `previous` (time, line).
pub(super) fn check_sample(
    file: &Path,
    line: u64,
    s: &Sample,
    previous: Option<(f64, u64)>,
) -> Result<(), DatasetError> {
    let value_error = |column: &str, problem| DatasetError::Value {
        file: file.to_path_buf(),
        line,
        column: column.to_string(),
        problem,
    };
    let finite = |column: &str, v: f64| {
        if v.is_finite() {
            Ok(())
        } else {
            Err(value_error(column, ValueProblem::NotFinite(v.to_string())))
        }
    };
    finite(TIME_COLUMN, s.t_s)?;
    if s.t_s < 0.0 {
        return Err(value_error(TIME_COLUMN, ValueProblem::NegativeTime(s.t_s)));
    }
    if s.t_s > MAX_SESSION_TIME_S {
        return Err(value_error(TIME_COLUMN, ValueProblem::TimeTooLarge(s.t_s)));
    }
    if let Some((prev, prev_line)) = previous {
        if s.t_s < prev {
            return Err(value_error(
                TIME_COLUMN,
                ValueProblem::TimeDecreasing {
                    value: s.t_s,
                    previous: prev,
                    previous_line: prev_line,
                },
            ));
        }
    }
    if let Some(v) = &s.tracker {
        for (x, name) in v.iter().zip(&TRACKER_COLUMNS) {
            finite(name, *x)?;
        }
    }
    if let Some(q) = &s.orientation {
        for (x, name) in q.iter().zip(&ORIENTATION_COLUMNS) {
            finite(name, *x)?;
        }
        if let Some(p) = orientation_problem(q, s.tracker.is_some()) {
            return Err(value_error(ORIENTATION_COLUMNS[0], p));
        }
    }
    if let Some(v) = &s.legacy {
        for (x, name) in v.iter().zip(&LEGACY_COLUMNS) {
            finite(name, *x)?;
        }
    }
    if let Some(v) = &s.tension_n {
        for (x, name) in v.iter().zip(&TENSION_COLUMNS) {
            finite(name, *x)?;
        }
    }
    Ok(())
}

/// The fields of one row, in the order of [`session_header`]; floats in
/// their shortest exact form, an absent group as empty fields.
pub(super) fn row_fields(
    s: &Sample,
    strings: usize,
    columns: OptionalColumns,
    fields: &mut Vec<String>,
) {
    let n = strings.min(STRINGS);
    let push_group = |fields: &mut Vec<String>, g: Option<&[f64]>, n: usize| match g {
        Some(v) => fields.extend(v.iter().map(|x| x.to_string())),
        None => fields.extend(std::iter::repeat_n(String::new(), n)),
    };
    fields.clear();
    fields.push(s.t_s.to_string());
    fields.extend(s.counts[..n].iter().map(|c| c.to_string()));
    push_group(fields, s.tracker.as_ref().map(|v| &v[..]), 3);
    if columns.orientation {
        push_group(fields, s.orientation.as_ref().map(|v| &v[..]), 4);
    }
    if columns.legacy {
        push_group(fields, s.legacy.as_ref().map(|v| &v[..]), 3);
    }
    if columns.tension {
        push_group(fields, s.tension_n.as_ref().map(|v| &v[..n]), n);
    }
}
