//! A session appended one row at a time, crash-safe ([`SessionAppender`],
//! `spidar collect`).

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use spidar_core::STRINGS;

use super::columns::{session_header_for, OptionalColumns};
use super::session::{check_home, check_sample, csv_write_error, row_fields, Sample, Session};
use super::{io_error, DatasetError, MIN_STRINGS};

/// An unterminated last line found when a session was opened for appending:
/// the remains of a write that a crash or power loss cut short. It was
/// removed from the file.
#[derive(Clone, Debug, PartialEq)]
pub struct TornLine {
    /// Its line number (1-based, header = line 1).
    pub line: u64,
    /// What it held.
    pub text: String,
}

/// A session file opened by [`SessionAppender::open`].
pub struct OpenedSession {
    pub appender: SessionAppender,
    /// The rows already in the file (read strictly, as [`Session::load`]).
    pub existing: Session,
    /// The unterminated last line that was cut off, if there was one.
    pub torn: Option<TornLine>,
    /// The file was new (or empty) and its header was written now.
    pub created: bool,
}

/// Appends rows to a session CSV one at a time, crash-safe: every row is
/// written whole and ends in a newline, then flushed to the disk
/// (`sync_data`) before [`SessionAppender::append`] returns, so a crash or a
/// power loss loses at most the row being written. A new file gets
/// [`session_header`](super::session_header) with `ots_q*`, `dev_*` and
/// `tension0..` (a row without an orientation leaves `ots_q*` empty). An
/// existing file may also have that header without `ots_q*` (as an older
/// `spidar collect` starts a file): rows are appended to it as they are,
/// and a sample with an orientation is refused rather than written without
/// it ([`DatasetError::OrientationNotAppended`]).
///
/// A row is committed once its newline is on the disk: when a file is
/// opened again, an unterminated last line is a write that was cut short
/// (even if what is left of it parses: its last number may be cut), so it is
/// removed and reported ([`OpenedSession::torn`]); complete rows are never
/// dropped. Anything else the strict reader rejects is an error, and so is
/// a header other than one of its two in their order (a file of another
/// tool: this writer does not append to it).
pub struct SessionAppender {
    file: fs::File,
    path: PathBuf,
    /// Strings of the device (`enc0..enc{strings-1}`).
    strings: usize,
    /// The file's optional columns: [`SessionAppender::COLUMNS`], or
    /// [`SessionAppender::COLUMNS_WITHOUT_ORIENTATION`] for an older file.
    columns: OptionalColumns,
    rows: usize,
    last: Option<(f64, u64)>,
    /// The last row's time since home and home id (what the next row's
    /// are checked against).
    last_home: Option<Sample>,
    /// A write failed part-way: the file may end in a partial row, so no
    /// more rows go after it (open the file again to repair it).
    failed: bool,
}

impl SessionAppender {
    /// The optional groups of a new appended session: orientation (empty
    /// on rows without one), legacy positions, tensions, the time since home
    /// and the home capture's id. The header is fixed whatever the rows
    /// hold, so that a file can be reopened.
    pub const COLUMNS: OptionalColumns = OptionalColumns {
        orientation: true,
        legacy: true,
        tension: true,
        since_home: true,
        home: true,
    };

    /// The optional groups of a session an older `spidar collect` started
    /// before it recorded the home: [`SessionAppender::COLUMNS`] without
    /// `since_home_s` and `home`. Such a file is still appended to (its rows
    /// without them).
    pub const COLUMNS_WITHOUT_HOME: OptionalColumns = OptionalColumns {
        since_home: false,
        home: false,
        ..Self::COLUMNS
    };

    /// The optional groups of a session a still older `spidar collect`
    /// started: [`SessionAppender::COLUMNS_WITHOUT_HOME`] without the
    /// orientation. Such a file is still appended to (with position-only
    /// rows).
    pub const COLUMNS_WITHOUT_ORIENTATION: OptionalColumns = OptionalColumns {
        orientation: false,
        ..Self::COLUMNS_WITHOUT_HOME
    };

    /// Every header this writer appends to, the one it starts files with first.
    const HEADERS: [OptionalColumns; 3] = [
        Self::COLUMNS,
        Self::COLUMNS_WITHOUT_HOME,
        Self::COLUMNS_WITHOUT_ORIENTATION,
    ];

    /// The header line this writer writes for an 8-string device (no newline).
    pub fn header_line() -> String {
        Self::header_line_for(STRINGS)
    }

    /// The header line for a device with `strings` strings (no newline).
    pub fn header_line_for(strings: usize) -> String {
        session_header_for(strings, Self::COLUMNS).join(",")
    }

    /// The header line of a file started without orientation columns,
    /// which is still appended to (no newline).
    pub fn header_line_without_orientation_for(strings: usize) -> String {
        session_header_for(strings, Self::COLUMNS_WITHOUT_ORIENTATION).join(",")
    }

    /// Opens `path` for appending the rows of an 8-string device (see
    /// [`SessionAppender::open_for`]).
    pub fn open(path: impl AsRef<Path>) -> Result<OpenedSession, DatasetError> {
        Self::open_for(path, STRINGS)
    }

    /// Opens `path` for appending the rows of a device with `strings`
    /// strings (3..=8), creating it (with its header) if it does not exist
    /// or is empty. See the type's documentation for what an existing file
    /// must satisfy: its header must be this device's, with or without the
    /// orientation columns (a file of another number of strings is refused,
    /// naming both headers).
    pub fn open_for(path: impl AsRef<Path>, strings: usize) -> Result<OpenedSession, DatasetError> {
        use io::{Read, Seek, Write};
        let path = path.as_ref();
        let strings = strings.clamp(MIN_STRINGS, STRINGS);
        let mut file = fs::OpenOptions::new()
            .read(true)
            .append(true)
            .create(true)
            .open(path)
            .map_err(|e| io_error(path, "cannot open for appending", e))?;
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes)
            .map_err(|e| io_error(path, "cannot read", e))?;
        let header = Self::header_line_for(strings);
        let headers: Vec<(String, OptionalColumns)> = Self::HEADERS
            .iter()
            .map(|&c| (session_header_for(strings, c).join(","), c))
            .collect();
        let mismatch = |found: &[u8]| DatasetError::HeaderMismatch {
            file: path.to_path_buf(),
            found: String::from_utf8_lossy(found).trim_end().to_string(),
            expected: header.clone(),
        };
        let mut torn = None;
        let keep = match bytes.iter().rposition(|&b| b == b'\n') {
            Some(last_newline) => last_newline + 1,
            None if bytes.is_empty() => 0,
            // Not even the header's newline: a header cut short (either
            // one: the file has no row yet) is started again, with the new
            // one; anything else is not this writer's file.
            None if headers
                .iter()
                .any(|(h, _)| h.as_bytes().starts_with(&bytes)) =>
            {
                torn = Some(TornLine {
                    line: 1,
                    text: String::from_utf8_lossy(&bytes).into_owned(),
                });
                0
            }
            None => return Err(mismatch(&bytes)),
        };
        let (existing, columns) = if keep == 0 {
            let empty = Session {
                strings,
                ..Session::default()
            };
            (empty, Self::COLUMNS)
        } else {
            let first_line = bytes[..keep].split(|&b| b == b'\n').next().unwrap_or(&[]);
            let first_line = first_line.strip_suffix(b"\r").unwrap_or(first_line);
            let Some(&(_, columns)) = headers.iter().find(|(h, _)| first_line == h.as_bytes())
            else {
                return Err(mismatch(first_line));
            };
            (Session::read_from(&bytes[..keep], path)?, columns)
        };
        if keep < bytes.len() {
            if torn.is_none() {
                let line = bytes[..keep].iter().filter(|&&b| b == b'\n').count() as u64 + 1;
                torn = Some(TornLine {
                    line,
                    text: String::from_utf8_lossy(&bytes[keep..]).into_owned(),
                });
            }
            file.set_len(keep as u64)
                .and_then(|()| file.sync_all())
                .map_err(|e| io_error(path, "cannot cut off the unterminated last line of", e))?;
        }
        // Appending goes to the end whatever the position; keep it tidy.
        file.seek(io::SeekFrom::End(0))
            .map_err(|e| io_error(path, "cannot seek", e))?;
        let created = keep == 0;
        if created {
            file.write_all(format!("{header}\n").as_bytes())
                .and_then(|()| file.sync_all())
                .map_err(|e| io_error(path, "cannot write the header to", e))?;
            sync_parent_directory(path);
        }
        let rows = existing.samples.len();
        let last = existing.samples.last().map(|s| (s.t_s, rows as u64 + 1));
        let last_home = existing.samples.last().cloned();
        Ok(OpenedSession {
            appender: SessionAppender {
                file,
                path: path.to_path_buf(),
                strings,
                columns,
                rows,
                last,
                last_home,
                failed: false,
            },
            existing,
            torn,
            created,
        })
    }

    /// The file appended to.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file has the orientation columns (`ots_qw..ots_qz`): false for a
    /// file started without them, which refuses a row with an orientation.
    pub fn has_orientation_columns(&self) -> bool {
        self.columns.orientation
    }

    /// The file has the `since_home_s` and `home` columns: false for a file
    /// an older `spidar collect` started, which refuses a row with them.
    pub fn has_home_columns(&self) -> bool {
        self.columns.home
    }

    /// Rows in the file.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// `t_s` of the last row.
    pub fn last_t_s(&self) -> Option<f64> {
        self.last.map(|(t, _)| t)
    }

    /// Appends `sample` as one row (checked as [`Session::validate`] checks,
    /// its time not before the last row's), flushed to the disk before this
    /// returns. Returns the row's line number.
    pub fn append(&mut self, sample: &Sample) -> Result<u64, DatasetError> {
        use io::Write;
        let line = self.rows as u64 + 2;
        if self.failed {
            return Err(io_error(
                &self.path,
                "an earlier write failed part-way; not appending to",
                io::Error::other("open the file again to repair it"),
            ));
        }
        check_sample(&self.path, line, sample, self.last)?;
        check_home(
            &self.path,
            line,
            sample,
            self.last_home.as_ref().map(|s| (s, line - 1)),
        )?;
        if (sample.since_home_s.is_some() || sample.home.is_some()) && !self.columns.home {
            return Err(DatasetError::HomeNotAppended {
                file: self.path.clone(),
                line,
            });
        }
        if sample.orientation.is_some() && !self.columns.orientation {
            return Err(DatasetError::OrientationNotAppended {
                file: self.path.clone(),
                line,
            });
        }
        let mut fields = Vec::new();
        row_fields(sample, self.strings, self.columns, &mut fields);
        let mut w = csv::WriterBuilder::new().from_writer(Vec::new());
        w.write_record(&fields)
            .map_err(|e| csv_write_error(&self.path, e))?;
        let bytes = w.into_inner().map_err(|e| {
            io_error(
                &self.path,
                "cannot format a row for",
                io::Error::other(e.to_string()),
            )
        })?;
        if let Err(e) = self
            .file
            .write_all(&bytes)
            .and_then(|()| self.file.flush())
            .and_then(|()| self.file.sync_data())
        {
            self.failed = true;
            return Err(io_error(&self.path, "cannot append a row to", e));
        }
        self.rows += 1;
        self.last = Some((sample.t_s, line));
        self.last_home = Some(sample.clone());
        Ok(line)
    }
}

/// Makes a new file's directory entry durable (best effort: not every
/// platform can open a directory).
fn sync_parent_directory(path: &Path) {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if let Ok(dir) = fs::File::open(parent) {
        let _ = dir.sync_all();
    }
}

#[cfg(test)]
mod tests;
