//! The one reader and writer of the project's data formats.
//!
//! Two formats, fixed because other tools write them:
//!
//! - **Geometry** (TOML, [`Geometry`]): the device as designed (nominal).
//!   Keys: `anchors_mm` (N x `[x, y, z]`, index = encoder index; N = 3..8
//!   sets the number of strings, on channels `0..N`), `counts_per_rev` and
//!   `pulley_radius_mm` (one number, or an array of N), optional
//!   `mechanical_advantage` (array of N: spool payout per mm of string length
//!   change, e.g. 2 for a line doubled through a pulley block; default 1),
//!   optional `planar = true` (the end-effector moves in the anchors' plane;
//!   anchors and home may then be given as `[x, y]`, and 3-D ones must share
//!   one z), `home_mm` and `room_from_device_translation_mm`
//!   (`p_room = p_device + t`, the paper's eq. 6). An unknown key is an error
//!   that names it.
//! - **Session** (CSV with a header, [`Session`]): one row per capture.
//!   Columns are found by name, in any order:
//!   `t_s`, `enc0`..`enc{N-1}` (required, N = 3..8 consecutive from `enc0`;
//!   [`Session::strings`]); `ots_x`, `ots_y` and `ots_z` (required columns,
//!   but `ots_z` may be left out for a planar device; all empty while the
//!   marker is occluded); optional groups `ots_qw`, `ots_qx`, `ots_qy`,
//!   `ots_qz` (the tracked body's orientation: the unit quaternion
//!   `[w, x, y, z]` from body to room frame, norm within 1e-3 of 1; empty
//!   when the tracker gives a position only, and never filled without a
//!   position), `dev_x`, `dev_y`, `dev_z` (legacy controller position,
//!   device frame) and `tension0`..`tension{N-1}` (commanded tensions, N). A
//!   session whose number of strings differs from its geometry's is refused
//!   where the two meet ([`Session::check_strings`]).
//!
//! Decisions (strict where data could be lost or misread):
//! - A missing required column, a duplicate column, or an optional group with
//!   only some of its columns is an error.
//! - An **unknown column is ignored** and listed in
//!   [`Session::ignored_columns`], so that tools may add columns of their own;
//!   a misspelt known column still fails, because its group is then incomplete.
//! - Within a row, each group (tracker, orientation, legacy, tensions) is all
//!   filled or all empty (`None`); a partially empty group is an error. Time
//!   and counts are always required.
//! - An orientation is a unit quaternion (a norm off 1 by more than 1e-3 is
//!   an error, not normalized away) on a row with a position: the body is
//!   occluded (both empty) or seen (a position, with or without orientation).
//! - `t_s` must be finite, non-negative, at most [`MAX_SESSION_TIME_S`]
//!   (49.7 days; a clock's timestamp is refused) and **non-decreasing**: a time going
//!   backwards is an error (time-dependent effects such as drift and slip are
//!   fitted against it). Equal consecutive times are allowed.
//! - Counts must be whole numbers within the `i32` range (`483489` or
//!   `483489.0`, as pandas writes an integer column that had a missing
//!   value; `1.5` is an error); every other value must be a finite number.
//! - Occluded rows (no tracker) are kept: they serve diagnosis, not fitting.
//! - A read may leave an optional group unread ([`ReadOptions`]: the legacy
//!   `dev_*`, which only `calibrate --blackbox` and `--export-pairs` use);
//!   its values are then neither parsed nor checked, and its columns are
//!   listed in [`Session::unread_columns`].
//!
//! Values that parse but no device could produce (a count beyond the
//! frame, a position kilometres off) are the calibration's to set aside by
//! line (`crate::data::impossible`), not the reader's: the file is read as
//! written.
//!
//! Every error names the file, the line (1-based, header = line 1) and the
//! column. Writing checks the same rules, so a written file always reads back,
//! and floats are written in their shortest exact form, so a round trip is
//! lossless.
//!
//! A session can also be written one row at a time ([`SessionAppender`],
//! `spidar collect`): each row flushed to the disk before the next, an
//! unterminated last line (a crash mid-write) cut off and reported when the
//! file is opened again. A new appended file has the orientation columns
//! (empty on rows without one); a file started without them (by an older
//! `spidar`) is still appended to, with position-only rows.
//!
//! The reader in parts: `geometry` (the TOML format), `columns` (a session's
//! column names, found in a header and written in one), `values` (a row's
//! values read from its text), `session` (the CSV format, read and written,
//! with the checks every written row passes) and `append` (one row at a
//! time, crash-safe).

mod append;
mod columns;
mod geometry;
mod session;
mod values;

use std::io;
use std::path::{Path, PathBuf};

pub use append::{OpenedSession, SessionAppender, TornLine};
pub use columns::{
    session_header, session_header_for, OptionalColumns, ENCODER_COLUMNS, HOME_COLUMN,
    LEGACY_COLUMNS, ORIENTATION_COLUMNS, SINCE_HOME_COLUMN, TENSION_COLUMNS, TIME_COLUMN,
    TRACKER_COLUMNS,
};
pub use geometry::{Geometry, MAX_HOME_TENSION_N};
pub use session::{LayoutMismatch, ReadOptions, Sample, Session};
pub use values::MAX_SESSION_TIME_S;

/// Fewest strings a device may have (3 hold a point in 3-D, with no spare).
pub const MIN_STRINGS: usize = 3;

/// Why one value of a session file is rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ValueProblem {
    #[error("empty, but a value is required")]
    Empty,
    #[error("`{0}` is not a number")]
    NotANumber(String),
    #[error("`{0}` is not a finite number")]
    NotFinite(String),
    #[error("`{0}` is not an integer count")]
    NotAnInteger(String),
    #[error("`{0}` is outside the range of a 32-bit count")]
    CountOutOfRange(String),
    #[error("negative time {0} s (time is counted from the start of the session)")]
    NegativeTime(f64),
    #[error("time {0} s is beyond {MAX_SESSION_TIME_S} s (49.7 days): time is counted from the start of the session, in the device's 32-bit milliseconds (a clock's timestamp? subtract the first row's)")]
    TimeTooLarge(f64),
    #[error("time goes backwards: {value} s after {previous} s on line {previous_line}")]
    TimeDecreasing {
        value: f64,
        previous: f64,
        previous_line: u64,
    },
    #[error("negative time since home {0} s")]
    NegativeSinceHome(f64),
    #[error("time since home goes backwards: {value} s after {previous} s on line {previous_line}, under the same home capture {home} (a new home capture has a new `home` id)")]
    SinceHomeDecreasing {
        value: f64,
        previous: f64,
        previous_line: u64,
        home: u64,
    },
    #[error("`{0}` is not a home capture's id (a whole number from 0 to 2^64-1)")]
    NotAHomeId(String),
    #[error("empty while `{filled}` is filled: the group {group} must be all empty or all filled")]
    PartialGroup { filled: String, group: String },
    #[error("orientation quaternion has norm {0:.4}; a rotation needs a unit quaternion (norm within 1e-3 of 1)")]
    NotUnitQuaternion(f64),
    #[error("an orientation on a row whose position (`ots_x`...) is empty: the body is occluded (position and orientation empty) or seen (a position, with or without an orientation)")]
    OrientationWithoutPosition,
}

impl ValueProblem {
    /// A problem of the time since home (`since_home_s`), not of the home id.
    pub(crate) fn is_since_home(&self) -> bool {
        !matches!(self, ValueProblem::NotAHomeId(_))
    }
}

/// Any failure to read or write a geometry or session file.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{}: {action}: {source}", file.display())]
    Io {
        file: PathBuf,
        action: &'static str,
        source: io::Error,
    },
    /// TOML syntax, a wrong type, or an unknown key (the message names it and its line).
    #[error("{}: {message}", file.display())]
    Toml { file: PathBuf, message: String },
    /// A geometry field that parses but is not usable.
    #[error("{}: field `{field}`: {problem}", file.display())]
    GeometryField {
        file: PathBuf,
        field: String,
        problem: String,
    },
    #[error("{}: line 1: the file is empty (a header line is required)", file.display())]
    Empty { file: PathBuf },
    #[error("{}: line 1: missing required column `{column}`", file.display())]
    MissingColumn { file: PathBuf, column: String },
    #[error("{}: line 1: duplicate column `{column}` (fields {first} and {second})", file.display())]
    DuplicateColumn {
        file: PathBuf,
        column: String,
        first: usize,
        second: usize,
    },
    #[error("{}: line 1: column `{missing}` is missing but `{present}` of the same group is present", file.display())]
    IncompleteGroup {
        file: PathBuf,
        present: String,
        missing: String,
    },
    /// A session opened for appending whose header is not the appender's
    /// columns in its order (with or without the orientation columns).
    #[error("{}: line 1: the header `{found}` is not the session header `{expected}` (or that header without ots_qw..ots_qz, as older files have) that appending requires: a file of another tool or layout; write to a new file", file.display())]
    HeaderMismatch {
        file: PathBuf,
        found: String,
        expected: String,
    },
    /// A sample with an orientation given to a [`SessionAppender`] whose
    /// file was started without orientation columns.
    #[error("{}: line {line}: the row has an orientation, but the file was started without orientation columns (ots_qw..ots_qz; an older spidar's header), so it would be lost: append it to a new file", file.display())]
    OrientationNotAppended { file: PathBuf, line: u64 },
    /// [`SessionAppender::append`] of a row with a time since home or a home
    /// id when the file was started without those columns.
    #[error("{}: line {line}: the row has a time since home or a home id, but the file was started without the `since_home_s` and `home` columns (an older spidar's header), so they would be lost: append it to a new file", file.display())]
    HomeNotAppended { file: PathBuf, line: u64 },
    /// A session without `ots_z` for a 3-D device.
    #[error("{}: line 1: no `ots_z` column (tracker positions in x, y only, as a planar device's), but {} is a 3-D device (no `planar = true`): its tracker positions need ots_z", file.display(), geometry_file.display())]
    NoTrackerZ {
        file: PathBuf,
        geometry_file: PathBuf,
    },
    /// A session whose encoder columns disagree with its geometry's anchors.
    #[error("{}: line 1: {strings} encoder columns (enc0..enc{}), but {} has {geometry_strings} anchors: a session and its geometry must describe the same strings", file.display(), strings.saturating_sub(1), geometry_file.display())]
    StringCount {
        file: PathBuf,
        strings: usize,
        geometry_file: PathBuf,
        geometry_strings: usize,
    },
    /// Malformed CSV, e.g. a row with another number of fields than the header.
    #[error("{}: line {line}: {message}", file.display())]
    Csv {
        file: PathBuf,
        line: u64,
        message: String,
    },
    #[error("{}: line {line}, column `{column}`: {problem}", file.display())]
    Value {
        file: PathBuf,
        line: u64,
        column: String,
        problem: ValueProblem,
    },
}

fn io_error(file: &Path, action: &'static str, source: io::Error) -> DatasetError {
    DatasetError::Io {
        file: file.to_path_buf(),
        action,
        source,
    }
}
