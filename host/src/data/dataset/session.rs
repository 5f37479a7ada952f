//! The session format (CSV, [`Session`]): captures in time order, read
//! strictly, and written (whole, or one row at a time by the appender)
//! only after the checks the reader makes, so that they read back.

use std::fs;
use std::io;
use std::path::Path;

use spidar_core::model::{StringLayout, Vec3};
use spidar_core::STRINGS;

use super::columns::{
    session_header_for, Layout, OptionalColumns, HOME_COLUMN, LEGACY_COLUMNS, ORIENTATION_COLUMNS,
    SINCE_HOME_COLUMN, TENSION_COLUMNS, TIME_COLUMN, TRACKER_COLUMNS,
};
use super::geometry::Geometry;
use super::values::{orientation_problem, RowReader, MAX_SESSION_TIME_S};
use super::{io_error, DatasetError, ValueProblem};

/// One capture.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// Seconds since the session started.
    pub t_s: f64,
    /// Encoder counts relative to initialization; increase as string is paid out.
    pub counts: [i32; STRINGS],
    /// Tracker position of the marker (room frame, mm); `None` while occluded.
    pub tracker: Option<Vec3<f64>>,
    /// Orientation of the tracked body when the tracker gives one: the unit
    /// quaternion `[w, x, y, z]` that turns the body's frame into the room
    /// frame. `None` while occluded or when the session has no orientation.
    pub orientation: Option<[f64; 4]>,
    /// Position reported by a legacy controller (device frame, mm), if any.
    pub legacy: Option<Vec3<f64>>,
    /// Commanded tensions (N), if recorded.
    pub tension_n: Option<[f64; STRINGS]>,
    /// Seconds since the device's home capture (`since_home_s`), if
    /// recorded (the column may leave a row's empty): what the string
    /// law's time terms read (else `t_s`).
    pub since_home_s: Option<f64>,
    /// Id of the home capture the row follows (`home`), if recorded.
    pub home: Option<u64>,
}

#[cfg(test)]
impl Sample {
    /// A row with its times and home capture only (no counts, no tracker):
    /// the home epochs' tests read nothing else.
    pub(crate) fn at_home(t_s: f64, since_home_s: Option<f64>, home: Option<u64>) -> Sample {
        Sample {
            t_s,
            counts: [0; STRINGS],
            tracker: None,
            orientation: None,
            legacy: None,
            tension_n: None,
            since_home_s,
            home,
        }
    }
}

/// Why a session is not a device's ([`Session::layout_mismatch`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LayoutMismatch {
    /// The session has this many encoder columns.
    Strings(usize),
    /// The session has no tracker z and the device moves in 3-D.
    NoTrackerZ,
}

/// A recorded (or simulated) session: captures in time order.
#[derive(Clone, Debug, PartialEq)]
pub struct Session {
    /// Number of strings: the encoder columns `enc0..enc{strings-1}` (3..=8).
    /// Counts and tensions of the other channels are 0 in every sample.
    pub strings: usize,
    pub samples: Vec<Sample>,
    /// Columns found in the file that this reader does not know; they were
    /// ignored. Empty for sessions not read from a file.
    pub ignored_columns: Vec<String>,
    /// The tracker columns include `ots_z` (false: a planar session's file
    /// gave `ots_x, ots_y` only, and every sample's tracker z reads 0; a
    /// 3-D geometry refuses it, [`Session::check_strings`]).
    pub tracker_z: bool,
    /// Known columns the file has but this read was asked to leave unread
    /// ([`ReadOptions`]): their values are neither parsed nor checked, and
    /// their group is `None` on every sample. Empty for a full read.
    pub unread_columns: Vec<String>,
}

/// Which of a session's optional groups a read parses. A group left unread
/// is not checked either: a value only an option uses (the legacy
/// controller's `dev_*`, read by `calibrate --blackbox`) cannot stop a run
/// that does not use it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReadOptions {
    /// Parse the legacy controller's `dev_x, dev_y, dev_z`.
    pub legacy: bool,
}

impl Default for ReadOptions {
    /// Every group read (and checked).
    fn default() -> Self {
        ReadOptions { legacy: true }
    }
}

impl Default for Session {
    /// An empty session of an 8-string device.
    fn default() -> Self {
        Session {
            strings: STRINGS,
            samples: Vec::new(),
            ignored_columns: Vec::new(),
            tracker_z: true,
            unread_columns: Vec::new(),
        }
    }
}

impl Session {
    /// Read a session CSV file, every group.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, DatasetError> {
        Self::load_with(path, ReadOptions::default())
    }

    /// Read a session CSV file, the optional groups `options` asks for.
    pub fn load_with(path: impl AsRef<Path>, options: ReadOptions) -> Result<Self, DatasetError> {
        let path = path.as_ref();
        let f = fs::File::open(path).map_err(|e| io_error(path, "cannot open", e))?;
        Self::read_from_with(io::BufReader::new(f), path, options)
    }

    /// Read a session from any reader, every group; `file` names it in errors.
    pub fn read_from<R: io::Read>(reader: R, file: &Path) -> Result<Self, DatasetError> {
        Self::read_from_with(reader, file, ReadOptions::default())
    }

    /// Read a session from any reader, the optional groups `options` asks
    /// for; `file` names it in errors.
    pub fn read_from_with<R: io::Read>(
        reader: R,
        file: &Path,
        options: ReadOptions,
    ) -> Result<Self, DatasetError> {
        let mut csv = csv::ReaderBuilder::new()
            .has_headers(true)
            .flexible(false)
            .trim(csv::Trim::All)
            .from_reader(reader);
        let header = csv.headers().map_err(|e| csv_error(file, e))?.clone();
        let (mut layout, ignored_columns) = Layout::from_header(file, &header)?;
        let mut unread_columns = Vec::new();
        if !options.legacy && layout.legacy.take().is_some() {
            unread_columns.extend(LEGACY_COLUMNS.iter().map(|c| c.to_string()));
        }
        let strings = layout.counts.len();
        let tracker_group = if layout.tracker.len() == 3 {
            "ots_x, ots_y, ots_z"
        } else {
            "ots_x, ots_y"
        };
        let tension_group = format!("tension0..tension{}", strings - 1);
        let orientation_group = ORIENTATION_COLUMNS.join(", ");
        let mut samples = Vec::new();
        let mut record = csv::StringRecord::new();
        let mut previous: Option<(f64, u64)> = None;
        loop {
            match csv.read_record(&mut record) {
                Ok(true) => {}
                Ok(false) => break,
                Err(e) => return Err(csv_error(file, e)),
            }
            let line = record.position().map(|p| p.line()).unwrap_or(0);
            let row = RowReader {
                file,
                line,
                header: &header,
                record: &record,
            };
            let t_s = row.float(layout.time)?;
            if t_s < 0.0 {
                return Err(row.error(layout.time, ValueProblem::NegativeTime(t_s)));
            }
            if t_s > MAX_SESSION_TIME_S {
                return Err(row.error(layout.time, ValueProblem::TimeTooLarge(t_s)));
            }
            if let Some((prev, prev_line)) = previous {
                if t_s < prev {
                    return Err(row.error(
                        layout.time,
                        ValueProblem::TimeDecreasing {
                            value: t_s,
                            previous: prev,
                            previous_line: prev_line,
                        },
                    ));
                }
            }
            let previous_line = previous.map(|(_, l)| l);
            previous = Some((t_s, line));
            let mut counts = [0i32; STRINGS];
            for (c, &k) in counts.iter_mut().zip(&layout.counts) {
                *c = row.count(k)?;
            }
            let tracker = row.group(&layout.tracker, tracker_group)?;
            let orientation = match &layout.orientation {
                Some(ix) => {
                    let q = row.group(ix, &orientation_group)?;
                    if let Some(p) = q.and_then(|q| orientation_problem(&q, tracker.is_some())) {
                        return Err(row.error(ix[0], p));
                    }
                    q
                }
                None => None,
            };
            let legacy = match &layout.legacy {
                Some(ix) => row.group(ix, "dev_x, dev_y, dev_z")?,
                None => None,
            };
            let tension_n = match &layout.tension {
                Some(ix) => row.group(ix, &tension_group)?,
                None => None,
            };
            let since_home_s = layout
                .since_home
                .map(|k| row.optional_float(k))
                .transpose()?
                .flatten();
            let home = layout.home.map(|k| row.home_id(k)).transpose()?.flatten();
            let sample = Sample {
                t_s,
                counts,
                tracker,
                orientation,
                legacy,
                tension_n,
                since_home_s,
                home,
            };
            let before = samples.last().zip(previous_line);
            if let Some(p) = home_problem(&sample, before) {
                let column = if p.is_since_home() {
                    layout.since_home
                } else {
                    layout.home
                };
                return Err(row.error(column.unwrap_or(layout.time), p));
            }
            samples.push(sample);
        }
        Ok(Session {
            strings,
            samples,
            ignored_columns,
            tracker_z: layout.tracker.len() == 3,
            unread_columns,
        })
    }

    /// The rows that repeat the row before them exactly (the same `t_s`
    /// and every value), each with that row: a row duplicated on its way to
    /// the file, never a second pose (the reader refuses a time that goes
    /// back; the same time with the same values is the same sample twice).
    pub fn repeated_rows(&self) -> Vec<(usize, usize)> {
        (1..self.samples.len())
            .filter(|&k| self.samples[k] == self.samples[k - 1])
            .map(|k| (k, k - 1))
            .collect()
    }

    /// The rows whose `t_s` is the row before's while a string moved
    /// between them by `min_counts` or more, each with that row and the
    /// largest move (counts): a log whose timestamps are coarser than its
    /// rows (a 100 Hz stream stamped to 20 ms has every second row at its
    /// neighbour's time). Whatever reads time from `t_s` (a stream's speed
    /// and latency, the clocks' alignment, drifts) sees such rows at one
    /// instant. Exact repeats ([`Self::repeated_rows`]) are not among them.
    pub fn rows_at_one_time_moving(&self, min_counts: u32) -> Vec<(usize, usize, u32)> {
        (1..self.samples.len())
            .filter_map(|k| {
                let (a, b) = (&self.samples[k - 1], &self.samples[k]);
                if b.t_s != a.t_s {
                    return None;
                }
                let moved = a
                    .counts
                    .iter()
                    .zip(&b.counts)
                    .map(|(x, y)| x.abs_diff(*y))
                    .max()
                    .unwrap_or(0);
                (moved >= min_counts).then_some((k, k - 1, moved))
            })
            .collect()
    }

    /// Checks that this session has `geometry`'s number of strings, and
    /// tracker z positions unless the geometry is planar; the error names
    /// both files.
    pub fn check_strings(
        &self,
        file: &Path,
        geometry: &Geometry,
        geometry_file: &Path,
    ) -> Result<(), DatasetError> {
        match self.layout_mismatch(geometry.layout) {
            None => Ok(()),
            Some(LayoutMismatch::Strings(strings)) => Err(DatasetError::StringCount {
                file: file.to_path_buf(),
                strings,
                geometry_file: geometry_file.to_path_buf(),
                geometry_strings: geometry.strings(),
            }),
            Some(LayoutMismatch::NoTrackerZ) => Err(DatasetError::NoTrackerZ {
                file: file.to_path_buf(),
                geometry_file: geometry_file.to_path_buf(),
            }),
        }
    }

    /// What keeps this session from being a device of `layout`'s: another
    /// number of encoder columns, or no tracker z for a device that moves
    /// in 3-D. `None` when it fits.
    pub fn layout_mismatch(&self, layout: StringLayout) -> Option<LayoutMismatch> {
        if self.strings != layout.count() {
            Some(LayoutMismatch::Strings(self.strings))
        } else if !self.tracker_z && !layout.planar {
            Some(LayoutMismatch::NoTrackerZ)
        } else {
            None
        }
    }

    /// True if any sample has an orientation (the `ots_q*` columns are written).
    pub fn has_orientation(&self) -> bool {
        self.samples.iter().any(|s| s.orientation.is_some())
    }

    /// True if any sample has a legacy position (the `dev_*` columns are written).
    pub fn has_legacy(&self) -> bool {
        self.samples.iter().any(|s| s.legacy.is_some())
    }

    /// True if any sample has tensions (the `tension*` columns are written).
    pub fn has_tension(&self) -> bool {
        self.samples.iter().any(|s| s.tension_n.is_some())
    }

    /// Check what [`Session::read_from`] would check, naming the line and
    /// column each sample would be written at.
    pub fn validate(&self, file: &Path) -> Result<(), DatasetError> {
        let mut previous: Option<(f64, u64)> = None;
        for (row, s) in self.samples.iter().enumerate() {
            let line = row as u64 + 2;
            check_sample(file, line, s, previous)?;
            let before = row.checked_sub(1).map(|r| (&self.samples[r], line - 1));
            check_home(file, line, s, before)?;
            previous = Some((s.t_s, line));
        }
        Ok(())
    }

    /// Write the session as CSV (after [`Session::validate`]).
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), DatasetError> {
        let path = path.as_ref();
        self.validate(path)?;
        crate::data::output::write_atomically_with(
            path,
            |w| self.write_to(w, path),
            |e| io_error(path, "cannot write", e),
        )
    }

    /// Write the session as CSV to any writer; `file` names it in errors.
    /// Columns: `t_s`, `enc0..7`, `ots_x, ots_y, ots_z`, then
    /// `ots_qw, ots_qx, ots_qy, ots_qz` if any sample has an orientation,
    /// `dev_*` if any has a legacy position and `tension0..7` if any has
    /// tensions.
    pub fn write_to<W: io::Write>(&self, writer: W, file: &Path) -> Result<(), DatasetError> {
        self.validate(file)?;
        let columns = OptionalColumns {
            orientation: self.has_orientation(),
            legacy: self.has_legacy(),
            tension: self.has_tension(),
            since_home: self.samples.iter().any(|s| s.since_home_s.is_some()),
            home: self.samples.iter().any(|s| s.home.is_some()),
        };
        let header = session_header_for(self.strings, columns);
        let mut w = csv::WriterBuilder::new().from_writer(writer);
        w.write_record(&header)
            .map_err(|e| csv_write_error(file, e))?;
        let mut fields: Vec<String> = Vec::with_capacity(header.len());
        for s in &self.samples {
            row_fields(s, self.strings, columns, &mut fields);
            w.write_record(&fields)
                .map_err(|e| csv_write_error(file, e))?;
        }
        w.flush().map_err(|e| io_error(file, "cannot write", e))
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
    if let Some(v) = s.since_home_s {
        finite(SINCE_HOME_COLUMN, v)?;
    }
    Ok(())
}

/// [`home_problem`] as the error the reader gives, naming `line` of `file`.
pub(super) fn check_home(
    file: &Path,
    line: u64,
    s: &Sample,
    previous: Option<(&Sample, u64)>,
) -> Result<(), DatasetError> {
    match home_problem(s, previous) {
        None => Ok(()),
        Some(problem) => Err(DatasetError::Value {
            file: file.to_path_buf(),
            line,
            column: if problem.is_since_home() {
                SINCE_HOME_COLUMN
            } else {
                HOME_COLUMN
            }
            .to_string(),
            problem,
        }),
    }
}

/// What is wrong with `s`'s time since home, alone or after the row
/// before it, `previous` (and its line): negative, beyond the
/// device's 32-bit milliseconds, or going backwards under the same home
/// capture (without a `home` column a step back is a new home capture).
pub(super) fn home_problem(s: &Sample, previous: Option<(&Sample, u64)>) -> Option<ValueProblem> {
    let t = s.since_home_s?;
    if t < 0.0 {
        return Some(ValueProblem::NegativeSinceHome(t));
    }
    if t > MAX_SESSION_TIME_S {
        return Some(ValueProblem::TimeTooLarge(t));
    }
    let (p, previous_line) = previous?;
    match (p.since_home_s, p.home, s.home) {
        (Some(before), Some(h0), Some(h1)) if h0 == h1 && t < before => {
            Some(ValueProblem::SinceHomeDecreasing {
                value: t,
                previous: before,
                previous_line,
                home: h1,
            })
        }
        _ => None,
    }
}

/// The fields of one row, in the order of
/// [`session_header`](super::session_header); floats in their shortest
/// exact form, an absent group as empty fields.
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
    if columns.since_home {
        fields.push(s.since_home_s.map_or_else(String::new, |v| v.to_string()));
    }
    if columns.home {
        fields.push(s.home.map_or_else(String::new, |v| v.to_string()));
    }
}

fn csv_error(file: &Path, e: csv::Error) -> DatasetError {
    let line = e.position().map(|p| p.line()).unwrap_or(0);
    match e.into_kind() {
        csv::ErrorKind::Io(source) => io_error(file, "cannot read", source),
        csv::ErrorKind::UnequalLengths {
            expected_len, len, ..
        } => DatasetError::Csv {
            file: file.to_path_buf(),
            line,
            message: format!("{len} fields, but the header has {expected_len}"),
        },
        csv::ErrorKind::Utf8 { err, .. } => DatasetError::Csv {
            file: file.to_path_buf(),
            line,
            message: format!("invalid UTF-8 in field {}", err.field() + 1),
        },
        other => DatasetError::Csv {
            file: file.to_path_buf(),
            line,
            message: format!("{other:?}"),
        },
    }
}

pub(super) fn csv_write_error(file: &Path, e: csv::Error) -> DatasetError {
    match e.into_kind() {
        csv::ErrorKind::Io(source) => io_error(file, "cannot write", source),
        other => DatasetError::Csv {
            file: file.to_path_buf(),
            line: 0,
            message: format!("{other:?}"),
        },
    }
}
