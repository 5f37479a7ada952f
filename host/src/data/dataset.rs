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

use std::fmt::Write as _;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use serde::de::{self, Deserializer, SeqAccess, Visitor};
use serde::Deserialize;
use spidar_core::geometry::distance;
use spidar_core::model::{Frame, StringLaw, StringLayout, Vec3, WINDING_ORDER};
use spidar_core::STRINGS;

/// Name of the time column.
pub const TIME_COLUMN: &str = "t_s";
/// Names of the encoder-count columns, index = encoder index.
pub const ENCODER_COLUMNS: [&str; STRINGS] = [
    "enc0", "enc1", "enc2", "enc3", "enc4", "enc5", "enc6", "enc7",
];
/// Names of the optical-tracker columns (room frame, mm).
pub const TRACKER_COLUMNS: [&str; 3] = ["ots_x", "ots_y", "ots_z"];
/// Names of the tracked body's orientation columns: the unit quaternion
/// `[w, x, y, z]` that turns the body's frame into the room frame.
pub const ORIENTATION_COLUMNS: [&str; 4] = ["ots_qw", "ots_qx", "ots_qy", "ots_qz"];
/// How far from 1 the norm of an orientation quaternion may be (its values
/// are rounded, but a rotation is a unit quaternion).
const ORIENTATION_NORM_TOLERANCE: f64 = 1e-3;
/// The latest `t_s` a session may have (s): the device counts time since
/// home in `u32` milliseconds. A session stamped with a clock's time (Unix
/// seconds, 1.7e9) read as one instant, `u32::MAX` ms, on every row.
pub const MAX_SESSION_TIME_S: f64 = u32::MAX as f64 / 1000.0;
/// Names of the legacy-controller columns (device frame, mm).
pub const LEGACY_COLUMNS: [&str; 3] = ["dev_x", "dev_y", "dev_z"];
/// Names of the commanded-tension columns (N), index = encoder index.
pub const TENSION_COLUMNS: [&str; STRINGS] = [
    "tension0", "tension1", "tension2", "tension3", "tension4", "tension5", "tension6", "tension7",
];

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
    #[error("empty while `{filled}` is filled: the group {group} must be all empty or all filled")]
    PartialGroup { filled: String, group: String },
    #[error("orientation quaternion has norm {0:.4}; a rotation needs a unit quaternion (norm within 1e-3 of 1)")]
    NotUnitQuaternion(f64),
    #[error("an orientation on a row whose position (`ots_x`...) is empty: the body is occluded (position and orientation empty) or seen (a position, with or without an orientation)")]
    OrientationWithoutPosition,
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

// ---------------------------------------------------------------------------
// Geometry
// ---------------------------------------------------------------------------

/// Fewest strings a device may have (3 hold a point in 3-D, with no spare).
pub const MIN_STRINGS: usize = 3;

/// Nominal geometry of a device, as its designers give it (never as built).
///
/// Arrays have the controller's [`STRINGS`] entries (index = encoder
/// channel); a device with N strings uses channels `0..N` (`layout`), and the
/// entries of the other channels repeat string N-1's values: they are never
/// read, but stay valid numbers for code that walks all 8.
#[derive(Clone, Debug, PartialEq)]
pub struct Geometry {
    /// Which channels carry a string (`0..N`), planar or 3-D.
    pub layout: StringLayout,
    /// Quadrature counts per pulley (spool) revolution, per string.
    pub counts_per_rev: [u32; STRINGS],
    /// Nominal pulley (spool) radius of each string (mm), index = encoder index.
    pub pulley_radius_mm: [f64; STRINGS],
    /// Spool payout per mm of string length change (1 for a string straight
    /// from its pulley to the end-effector, 2 or 4 for a line doubled through
    /// pulley blocks).
    pub mechanical_advantage: [f64; STRINGS],
    /// End-effector position at initialization (device frame, mm).
    pub home_mm: Vec3<f64>,
    /// String exit points (device frame, mm), index = encoder index.
    pub anchors_mm: [Vec3<f64>; STRINGS],
    /// `t` of `p_room = p_device + t` (mm), the paper's eq. 6.
    pub room_from_device_translation_mm: Vec3<f64>,
    /// Tension every string held when home was captured (N): the pretension
    /// the initialization holds (`spidar init` records it). The strings'
    /// stretch is counted from it; `None`: the firmware's default, 1 N,
    /// within 1 N.
    pub home_tension_n: Option<f64>,
    /// How far each anchor (string exit point) may be from where the
    /// geometry puts it, per coordinate, mm (one sd; a hand-measured rig's
    /// tolerance): the identification's prior. `None`: the calibration's
    /// default ([`crate::model::identify::Priors::anchor_sd_mm`]).
    pub anchor_sd_mm: Option<[f64; STRINGS]>,
    /// How far home may be from `home_mm`, per coordinate, mm (one sd).
    /// `None`: the calibration's default.
    pub home_sd_mm: Option<f64>,
}

/// Largest home tension a geometry may declare, N (the firmware's tension
/// ceiling is 20 N).
pub const MAX_HOME_TENSION_N: f64 = 50.0;

/// A key that is one number for all strings or an array of one per string.
#[derive(Debug)]
enum PerString<T> {
    One(T),
    Each(Vec<T>),
}

impl<'de, T: Deserialize<'de>> Deserialize<'de> for PerString<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct PerStringVisitor<T>(std::marker::PhantomData<T>);
        impl<'de, T: Deserialize<'de>> Visitor<'de> for PerStringVisitor<T> {
            type Value = PerString<T>;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                write!(f, "a number or an array of one number per string")
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Self::Value, E> {
                T::deserialize(de::value::F64Deserializer::new(v)).map(PerString::One)
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Self::Value, E> {
                T::deserialize(de::value::I64Deserializer::new(v)).map(PerString::One)
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Self::Value, E> {
                T::deserialize(de::value::U64Deserializer::new(v)).map(PerString::One)
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
                let mut values = Vec::new();
                while let Some(v) = seq.next_element::<T>()? {
                    values.push(v);
                }
                Ok(PerString::Each(values))
            }
        }
        deserializer.deserialize_any(PerStringVisitor(std::marker::PhantomData))
    }
}

impl<T: Copy> PerString<T> {
    /// One value per string of `n`, the rest of the channels repeating the
    /// last; `None` when an array has another length than `n`.
    fn per_channel(&self, n: usize) -> Result<[T; STRINGS], usize> {
        let values: Vec<T> = match self {
            PerString::One(v) => vec![*v; n],
            PerString::Each(v) if v.len() == n => v.clone(),
            PerString::Each(v) => return Err(v.len()),
        };
        Ok(core::array::from_fn(|i| values[i.min(n - 1)]))
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct GeometryFile {
    counts_per_rev: PerString<u32>,
    pulley_radius_mm: PerString<f64>,
    #[serde(default)]
    mechanical_advantage: Option<PerString<f64>>,
    #[serde(default)]
    planar: bool,
    home_mm: Vec<f64>,
    anchors_mm: Vec<Vec<f64>>,
    room_from_device_translation_mm: Vec3<f64>,
    #[serde(default)]
    home_tension_n: Option<f64>,
    #[serde(default)]
    anchor_sd_mm: Option<PerString<f64>>,
    #[serde(default)]
    home_sd_mm: Option<f64>,
}

fn field_error(file: &Path, field: impl Into<String>, problem: impl Into<String>) -> DatasetError {
    DatasetError::GeometryField {
        file: file.to_path_buf(),
        field: field.into(),
        problem: problem.into(),
    }
}

fn check_finite3(file: &Path, field: &str, v: &Vec3<f64>) -> Result<(), DatasetError> {
    for (axis, x) in v.iter().enumerate() {
        if !x.is_finite() {
            return Err(field_error(
                file,
                format!("{field}[{axis}]"),
                format!("{x} is not a finite number"),
            ));
        }
    }
    Ok(())
}

impl Geometry {
    /// Read a geometry TOML file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, DatasetError> {
        let path = path.as_ref();
        let text = fs::read_to_string(path).map_err(|e| io_error(path, "cannot read", e))?;
        Self::from_toml_str(&text, path)
    }

    /// Parse geometry TOML text; `file` names it in errors.
    pub fn from_toml_str(text: &str, file: &Path) -> Result<Self, DatasetError> {
        let raw: GeometryFile = toml::from_str(text).map_err(|e| DatasetError::Toml {
            file: file.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let n = raw.anchors_mm.len();
        if !(MIN_STRINGS..=STRINGS).contains(&n) {
            return Err(field_error(
                file,
                "anchors_mm",
                format!(
                    "{n} anchors given: a device has {MIN_STRINGS} to {STRINGS} strings, one anchor each"
                ),
            ));
        }
        let planar = raw.planar;
        let point = |field: String, v: &[f64]| -> Result<Vec3<f64>, DatasetError> {
            match (v.len(), planar) {
                (3, _) => Ok([v[0], v[1], v[2]]),
                (2, true) => Ok([v[0], v[1], 0.0]),
                (len, true) => Err(field_error(
                    file,
                    field,
                    format!("{len} coordinates: [x, y] or [x, y, z] (mm) expected"),
                )),
                (len, false) => Err(field_error(
                    file,
                    field,
                    format!(
                        "{len} coordinates: [x, y, z] (mm) expected (2-D points need `planar = true`)"
                    ),
                )),
            }
        };
        let mut given = Vec::with_capacity(n);
        for (i, a) in raw.anchors_mm.iter().enumerate() {
            given.push(point(format!("anchors_mm[{i}]"), a)?);
        }
        let mut home_mm = point("home_mm".to_string(), &raw.home_mm)?;
        if planar && raw.home_mm.len() == 2 {
            // A 2-D home lies in the anchors' plane.
            home_mm[2] = given[0][2];
        }
        let anchors_mm: [Vec3<f64>; STRINGS] = core::array::from_fn(|i| given[i.min(n - 1)]);
        let per_string = |field: &str, len: usize| {
            field_error(
                file,
                field,
                format!("{len} values given, {n} expected (one per anchor, or one number for all)"),
            )
        };
        let counts_per_rev = raw
            .counts_per_rev
            .per_channel(n)
            .map_err(|len| per_string("counts_per_rev", len))?;
        let pulley_radius_mm = raw
            .pulley_radius_mm
            .per_channel(n)
            .map_err(|len| per_string("pulley_radius_mm", len))?;
        let mechanical_advantage = match &raw.mechanical_advantage {
            None => [1.0; STRINGS],
            Some(m) => m
                .per_channel(n)
                .map_err(|len| per_string("mechanical_advantage", len))?,
        };
        let anchor_sd_mm = raw
            .anchor_sd_mm
            .as_ref()
            .map(|sd| sd.per_channel(n))
            .transpose()
            .map_err(|len| per_string("anchor_sd_mm", len))?;
        let geometry = Geometry {
            layout: StringLayout::first(n, planar),
            counts_per_rev,
            pulley_radius_mm,
            mechanical_advantage,
            home_mm,
            anchors_mm,
            room_from_device_translation_mm: raw.room_from_device_translation_mm,
            home_tension_n: raw.home_tension_n,
            anchor_sd_mm,
            home_sd_mm: raw.home_sd_mm,
        };
        geometry.validate(file)?;
        Ok(geometry)
    }

    /// Number of strings (anchors), 3..=8.
    pub fn strings(&self) -> usize {
        self.layout.count()
    }

    /// Check the values: positive counts per revolution and radii, finite
    /// coordinates, anchors apart from home. `file` names the file in errors.
    pub fn validate(&self, file: &Path) -> Result<(), DatasetError> {
        self.check_channels(file)?;
        check_finite3(file, "home_mm", &self.home_mm)?;
        check_finite3(
            file,
            "room_from_device_translation_mm",
            &self.room_from_device_translation_mm,
        )?;
        self.check_anchors(file)?;
        if self.layout.planar && self.home_mm[2] != self.anchors_mm[0][2] {
            return Err(field_error(
                file,
                "home_mm",
                format!(
                    "z = {} is not the anchors' plane z = {}: the end-effector of a planar device moves in that plane",
                    self.home_mm[2], self.anchors_mm[0][2]
                ),
            ));
        }
        Ok(())
    }

    /// The strings are on channels 0..N (N in 3..=8), the home tension is a
    /// tension, and each channel's counts per revolution, pulley radius and
    /// mechanical advantage are positive.
    fn check_channels(&self, file: &Path) -> Result<(), DatasetError> {
        let n = self.strings();
        if n < MIN_STRINGS || self.layout != StringLayout::first(n, self.layout.planar) {
            return Err(field_error(
                file,
                "anchors_mm",
                format!(
                    "strings on channels {:?}: a device has {MIN_STRINGS} to {STRINGS} strings on channels 0..N",
                    self.layout.indices().collect::<Vec<_>>()
                ),
            ));
        }
        if let Some(t) = self.home_tension_n {
            if !(t.is_finite() && t > 0.0 && t <= MAX_HOME_TENSION_N) {
                return Err(field_error(
                    file,
                    "home_tension_n",
                    format!(
                        "{t} N: the tension the strings held at the home capture is above 0 and \
                         at most {MAX_HOME_TENSION_N} N"
                    ),
                ));
            }
        }
        let tolerance = |field: String, sd: f64| {
            if sd.is_finite() && sd > 0.0 {
                Ok(())
            } else {
                Err(field_error(
                    file,
                    field,
                    format!("{sd} mm: a tolerance (one standard deviation) is a positive number"),
                ))
            }
        };
        if let Some(sd) = self.home_sd_mm {
            tolerance("home_sd_mm".into(), sd)?;
        }
        if let Some(sd) = self.anchor_sd_mm {
            for i in self.layout.indices() {
                tolerance(format!("anchor_sd_mm[{i}]"), sd[i])?;
            }
        }
        for i in self.layout.indices() {
            if self.counts_per_rev[i] == 0 {
                return Err(field_error(
                    file,
                    format!("counts_per_rev[{i}]"),
                    "must be positive",
                ));
            }
            let r = self.pulley_radius_mm[i];
            if !(r.is_finite() && r > 0.0) {
                return Err(field_error(
                    file,
                    format!("pulley_radius_mm[{i}]"),
                    format!("{r} is not a positive finite radius"),
                ));
            }
            let m = self.mechanical_advantage[i];
            if !(m.is_finite() && m > 0.0) {
                return Err(field_error(
                    file,
                    format!("mechanical_advantage[{i}]"),
                    format!("{m} is not a positive finite ratio"),
                ));
            }
        }
        Ok(())
    }

    /// Each anchor is finite, apart from home and (planar) in the first
    /// one's plane; together they are not at one point or on one line.
    fn check_anchors(&self, file: &Path) -> Result<(), DatasetError> {
        for i in self.layout.indices() {
            let a = &self.anchors_mm[i];
            let field = format!("anchors_mm[{i}]");
            check_finite3(file, &field, a)?;
            if distance(*a, self.home_mm) == 0.0 {
                return Err(field_error(
                    file,
                    field,
                    "the anchor coincides with home_mm",
                ));
            }
            if self.layout.planar && a[2] != self.anchors_mm[0][2] {
                return Err(field_error(
                    file,
                    field,
                    format!(
                        "z = {} but anchors_mm[0] has z = {}: the anchors of a planar device lie in one plane z = const",
                        a[2], self.anchors_mm[0][2]
                    ),
                ));
            }
        }
        if let Some(why) = self.degenerate_anchors() {
            return Err(field_error(
                file,
                "anchors_mm",
                format!(
                    "the geometry is degenerate: {why}, so string lengths cannot fix a \
                     position (copied one anchor into every row?)"
                ),
            ));
        }
        Ok(())
    }

    /// Why no position can be solved from the anchors: all at one point, or
    /// all on one line (None: they span a plane or more).
    fn degenerate_anchors(&self) -> Option<&'static str> {
        let active: Vec<Vec3<f64>> = self.layout.indices().map(|i| self.anchors_mm[i]).collect();
        let far = active
            .iter()
            .map(|a| distance(*a, active[0]))
            .fold(0.0, f64::max);
        if far == 0.0 {
            Some("all anchors are at one point")
        } else {
            let (k, _) = active
                .iter()
                .enumerate()
                .map(|(k, a)| (k, distance(*a, active[0])))
                .fold((0, 0.0), |b, x| if x.1 > b.1 { x } else { b });
            let u = [0, 1, 2].map(|c| (active[k][c] - active[0][c]) / far);
            let off_line = active
                .iter()
                .map(|a| {
                    let d = [0, 1, 2].map(|c| a[c] - active[0][c]);
                    let along = d[0] * u[0] + d[1] * u[1] + d[2] * u[2];
                    let p = [0, 1, 2].map(|c| d[c] - along * u[c]);
                    (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
                })
                .fold(0.0, f64::max);
            (off_line <= 1e-9 * far).then_some("all anchors lie on one line")
        }
    }

    /// TOML text of this geometry, in the layout of the shared example
    /// (the N-string keys only where they differ from a Scalable-SPIDAR's).
    pub fn to_toml_string(&self) -> String {
        let n = self.strings();
        let mut s = String::from("# Nominal geometry of the device (as designed, not as built)\n");
        let one_or_each = |s: &mut String, key: &str, v: &[String]| {
            if v.iter().all(|x| *x == v[0]) {
                let _ = writeln!(s, "{key} = {}", v[0]);
            } else {
                let _ = writeln!(s, "{key} = [{}]", v.join(", "));
            }
        };
        let cpr: Vec<String> = self.counts_per_rev[..n]
            .iter()
            .map(u32::to_string)
            .collect();
        one_or_each(&mut s, "counts_per_rev", &cpr);
        let radii: Vec<String> = self.pulley_radius_mm[..n]
            .iter()
            .map(|r| format!("{r:?}"))
            .collect();
        one_or_each(&mut s, "pulley_radius_mm", &radii);
        if self.mechanical_advantage[..n].iter().any(|m| *m != 1.0) {
            let m: Vec<String> = self.mechanical_advantage[..n]
                .iter()
                .map(|m| format!("{m:?}"))
                .collect();
            let _ = writeln!(s, "mechanical_advantage = [{}]", m.join(", "));
        }
        if self.layout.planar {
            s.push_str("planar = true\n");
        }
        let _ = writeln!(s, "home_mm = {:?}", self.home_mm);
        s.push_str("anchors_mm = [\n");
        for a in &self.anchors_mm[..n] {
            let _ = writeln!(s, "  {a:?},");
        }
        s.push_str("]\n");
        let _ = writeln!(
            s,
            "room_from_device_translation_mm = {:?}",
            self.room_from_device_translation_mm
        );
        if let Some(t) = self.home_tension_n {
            let _ = writeln!(s, "home_tension_n = {t:?}");
        }
        if let Some(sd) = self.anchor_sd_mm {
            let sd: Vec<String> = sd[..n].iter().map(|v| format!("{v:?}")).collect();
            one_or_each(&mut s, "anchor_sd_mm", &sd);
        }
        if let Some(sd) = self.home_sd_mm {
            let _ = writeln!(s, "home_sd_mm = {sd:?}");
        }
        s
    }

    /// Write this geometry as TOML (after [`Geometry::validate`]).
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), DatasetError> {
        let path = path.as_ref();
        self.validate(path)?;
        fs::write(path, self.to_toml_string()).map_err(|e| io_error(path, "cannot write", e))
    }

    /// The nominal frame: nominal anchors and home, identity rotation, unit
    /// scale and the eq. 6 translation.
    pub fn nominal_frame(&self) -> Frame<f64> {
        Frame {
            layout: self.layout,
            anchors: self.anchors_mm,
            home: self.home_mm,
            room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            room_translation: self.room_from_device_translation_mm,
            room_scale: 1.0,
        }
    }

    /// The nominal string laws: a constant winding radius, the nominal pulley
    /// radius over the mechanical advantage (`winding_mm = [r / m, 0, 0, 0]`:
    /// a spool paying out `r theta` shortens a line doubled `m` times by
    /// `r theta / m`).
    pub fn nominal_string_laws(&self) -> [StringLaw; STRINGS] {
        core::array::from_fn(|i| {
            let mut winding_mm = [0.0; WINDING_ORDER];
            winding_mm[0] = self.pulley_radius_mm[i] / self.mechanical_advantage[i];
            StringLaw::polynomial(self.counts_per_rev[i], winding_mm)
        })
    }

    /// Nominal string payout per encoder count, mm, per channel (the
    /// nominal law's payout of one count: `r 2 pi / counts_per_rev` over
    /// the mechanical advantage).
    pub fn nominal_mm_per_count(&self) -> [f64; STRINGS] {
        self.nominal_string_laws()
            .map(|law| spidar_core::string_law::payout_f64(&law, 1))
    }

    /// The device's nominal string model (`SetStringModel`): what a device
    /// without a calibration blob runs on.
    pub fn string_model(&self) -> spidar_protocol::StringModel {
        let layout = self.nominal_frame().layout;
        spidar_protocol::StringModel {
            counts_per_rev: self.counts_per_rev,
            pulley_radius_mm: core::array::from_fn(|i| {
                (self.pulley_radius_mm[i] / self.mechanical_advantage[i]) as f32
            }),
            anchors_mm: self.anchors_mm.map(|a| a.map(|v| v as f32)),
            home_mm: self.home_mm.map(|v| v as f32),
            active_strings: layout.active,
            planar: layout.planar,
        }
    }

    /// Nominal string length of each string at home (mm).
    pub fn home_lengths_mm(&self) -> [f64; STRINGS] {
        core::array::from_fn(|i| distance(self.anchors_mm[i], self.home_mm))
    }
}

// ---------------------------------------------------------------------------
// Session
// ---------------------------------------------------------------------------

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
}

impl Default for Session {
    /// An empty session of an 8-string device.
    fn default() -> Self {
        Session {
            strings: STRINGS,
            samples: Vec::new(),
            ignored_columns: Vec::new(),
            tracker_z: true,
        }
    }
}

/// Where each known column sits in a header.
struct Layout {
    time: usize,
    /// `enc0..enc{N-1}`.
    counts: Vec<usize>,
    /// `ots_x, ots_y` and, unless the session is planar, `ots_z`.
    tracker: Vec<usize>,
    /// `ots_qw, ots_qx, ots_qy, ots_qz`.
    orientation: Option<[usize; 4]>,
    legacy: Option<[usize; 3]>,
    /// `tension0..tension{N-1}`.
    tension: Option<Vec<usize>>,
}

/// The columns `names[..n]` as a group: all present (`Some`), all absent
/// (`None`, if not `required`), else an error naming a present and a
/// missing one.
fn find_columns(
    file: &Path,
    index_of: &dyn Fn(&str) -> Option<usize>,
    names: &[&str],
    required: bool,
) -> Result<Option<Vec<usize>>, DatasetError> {
    let found: Vec<Option<usize>> = names.iter().map(|n| index_of(n)).collect();
    let present = found.iter().position(Option::is_some);
    let missing = found.iter().position(Option::is_none);
    match (present, missing) {
        (_, None) => Ok(Some(found.into_iter().flatten().collect())),
        (None, Some(_)) if !required => Ok(None),
        (Some(p), Some(m)) if !required => Err(DatasetError::IncompleteGroup {
            file: file.to_path_buf(),
            present: names[p].to_string(),
            missing: names[m].to_string(),
        }),
        (_, Some(m)) => Err(DatasetError::MissingColumn {
            file: file.to_path_buf(),
            column: names[m].to_string(),
        }),
    }
}

fn find_group<const N: usize>(
    file: &Path,
    index_of: &dyn Fn(&str) -> Option<usize>,
    names: &[&str; N],
    required: bool,
) -> Result<Option<[usize; N]>, DatasetError> {
    Ok(find_columns(file, index_of, names, required)?.map(|v| core::array::from_fn(|k| v[k])))
}

impl Layout {
    fn from_header(
        file: &Path,
        header: &csv::StringRecord,
    ) -> Result<(Layout, Vec<String>), DatasetError> {
        if header.is_empty() || (header.len() == 1 && header[0].is_empty()) {
            return Err(DatasetError::Empty {
                file: file.to_path_buf(),
            });
        }
        let names: Vec<&str> = header.iter().collect();
        for (second, name) in names.iter().enumerate() {
            if let Some(first) = names[..second].iter().position(|n| n == name) {
                return Err(DatasetError::DuplicateColumn {
                    file: file.to_path_buf(),
                    column: name.to_string(),
                    first: first + 1,
                    second: second + 1,
                });
            }
        }
        let index_of = |name: &str| names.iter().position(|n| *n == name);
        let time = index_of(TIME_COLUMN).ok_or_else(|| DatasetError::MissingColumn {
            file: file.to_path_buf(),
            column: TIME_COLUMN.to_string(),
        })?;
        // The strings are enc0, enc1, ... up to the first one missing;
        // an encoder column after a gap names the gap.
        let strings = ENCODER_COLUMNS
            .iter()
            .position(|c| index_of(c).is_none())
            .unwrap_or(STRINGS);
        if ENCODER_COLUMNS[strings.min(STRINGS)..]
            .iter()
            .any(|c| index_of(c).is_some())
        {
            // enc0..enc{N-1} without gaps: a gap is the missing column.
            return Err(DatasetError::MissingColumn {
                file: file.to_path_buf(),
                column: ENCODER_COLUMNS[strings].to_string(),
            });
        }
        if strings < MIN_STRINGS {
            return Err(DatasetError::MissingColumn {
                file: file.to_path_buf(),
                column: format!(
                    "{} (a device has at least {MIN_STRINGS} strings: enc0..enc{})",
                    ENCODER_COLUMNS[strings],
                    MIN_STRINGS - 1
                ),
            });
        }
        let counts =
            find_columns(file, &index_of, &ENCODER_COLUMNS[..strings], true)?.unwrap_or_default();
        // `ots_z` may be left out (a planar device's tracker gives x, y).
        let tracker_names: &[&str] = if index_of(TRACKER_COLUMNS[2]).is_some() {
            &TRACKER_COLUMNS
        } else {
            &TRACKER_COLUMNS[..2]
        };
        let tracker = find_columns(file, &index_of, tracker_names, true)?.unwrap_or_default();
        let orientation = find_group(file, &index_of, &ORIENTATION_COLUMNS, false)?;
        let legacy = find_group(file, &index_of, &LEGACY_COLUMNS, false)?;
        let tension = find_columns(file, &index_of, &TENSION_COLUMNS[..strings], false)?;
        if let Some(extra) = TENSION_COLUMNS[strings..]
            .iter()
            .find(|c| index_of(c).is_some())
        {
            return Err(DatasetError::Csv {
                file: file.to_path_buf(),
                line: 1,
                message: format!(
                    "column `{extra}` but the session has {strings} strings (enc0..enc{})",
                    strings - 1
                ),
            });
        }
        let known = |n: &str| {
            n == TIME_COLUMN
                || ENCODER_COLUMNS.contains(&n)
                || TRACKER_COLUMNS.contains(&n)
                || ORIENTATION_COLUMNS.contains(&n)
                || LEGACY_COLUMNS.contains(&n)
                || TENSION_COLUMNS.contains(&n)
        };
        let ignored = names
            .iter()
            .filter(|n| !known(n))
            .map(|n| n.to_string())
            .collect();
        Ok((
            Layout {
                time,
                counts,
                tracker,
                orientation,
                legacy,
                tension,
            },
            ignored,
        ))
    }
}

struct RowReader<'a> {
    file: &'a Path,
    line: u64,
    header: &'a csv::StringRecord,
    record: &'a csv::StringRecord,
}

impl RowReader<'_> {
    fn error(&self, index: usize, problem: ValueProblem) -> DatasetError {
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

    fn float(&self, index: usize) -> Result<f64, DatasetError> {
        parse_float(self.text(index)).map_err(|p| self.error(index, p))
    }

    fn count(&self, index: usize) -> Result<i32, DatasetError> {
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
    fn group<const N: usize>(
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
fn orientation_problem(q: &[f64; 4], has_position: bool) -> Option<ValueProblem> {
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

impl Session {
    /// Read a session CSV file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, DatasetError> {
        let path = path.as_ref();
        let f = fs::File::open(path).map_err(|e| io_error(path, "cannot open", e))?;
        Self::read_from(io::BufReader::new(f), path)
    }

    /// Read a session from any reader; `file` names it in errors.
    pub fn read_from<R: io::Read>(reader: R, file: &Path) -> Result<Self, DatasetError> {
        let mut csv = csv::ReaderBuilder::new()
            .has_headers(true)
            .flexible(false)
            .trim(csv::Trim::All)
            .from_reader(reader);
        let header = csv.headers().map_err(|e| csv_error(file, e))?.clone();
        let (layout, ignored_columns) = Layout::from_header(file, &header)?;
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
            samples.push(Sample {
                t_s,
                counts,
                tracker,
                orientation,
                legacy,
                tension_n,
            });
        }
        Ok(Session {
            strings,
            samples,
            ignored_columns,
            tracker_z: layout.tracker.len() == 3,
        })
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
        if self.strings != geometry.strings() {
            return Err(DatasetError::StringCount {
                file: file.to_path_buf(),
                strings: self.strings,
                geometry_file: geometry_file.to_path_buf(),
                geometry_strings: geometry.strings(),
            });
        }
        if !self.tracker_z && !geometry.layout.planar {
            return Err(DatasetError::NoTrackerZ {
                file: file.to_path_buf(),
                geometry_file: geometry_file.to_path_buf(),
            });
        }
        Ok(())
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
            previous = Some((s.t_s, line));
        }
        Ok(())
    }

    /// Write the session as CSV (after [`Session::validate`]).
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), DatasetError> {
        let path = path.as_ref();
        self.validate(path)?;
        let f = fs::File::create(path).map_err(|e| io_error(path, "cannot create", e))?;
        self.write_to(io::BufWriter::new(f), path)
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

/// Which optional column groups a session file has.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OptionalColumns {
    /// `ots_qw, ots_qx, ots_qy, ots_qz`.
    pub orientation: bool,
    /// `dev_x, dev_y, dev_z`.
    pub legacy: bool,
    /// `tension0..tension{N-1}`.
    pub tension: bool,
}

/// The header [`Session::write_to`] writes for an 8-string device: `t_s`,
/// `enc0..7`, `ots_x, ots_y, ots_z`, then the optional groups of `columns`:
/// `ots_q*`, `dev_*`, `tension0..7`.
pub fn session_header(columns: OptionalColumns) -> Vec<&'static str> {
    session_header_for(STRINGS, columns)
}

/// [`session_header`] for a device with `strings` strings (`enc0..enc{n-1}`,
/// `tension0..tension{n-1}`).
pub fn session_header_for(strings: usize, columns: OptionalColumns) -> Vec<&'static str> {
    let n = strings.min(STRINGS);
    let mut header: Vec<&'static str> = vec![TIME_COLUMN];
    header.extend(&ENCODER_COLUMNS[..n]);
    header.extend(TRACKER_COLUMNS);
    if columns.orientation {
        header.extend(ORIENTATION_COLUMNS);
    }
    if columns.legacy {
        header.extend(LEGACY_COLUMNS);
    }
    if columns.tension {
        header.extend(&TENSION_COLUMNS[..n]);
    }
    header
}

/// The fields of one row, in the order of [`session_header`]; floats in
/// their shortest exact form, an absent group as empty fields.
fn row_fields(s: &Sample, strings: usize, columns: OptionalColumns, fields: &mut Vec<String>) {
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

fn csv_write_error(file: &Path, e: csv::Error) -> DatasetError {
    match e.into_kind() {
        csv::ErrorKind::Io(source) => io_error(file, "cannot write", source),
        other => DatasetError::Csv {
            file: file.to_path_buf(),
            line: 0,
            message: format!("{other:?}"),
        },
    }
}

/// What the reader requires of one sample written at `line`, after a sample
/// at `previous` (time, line).
fn check_sample(
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

// ---------------------------------------------------------------------------
// Appending, crash-safe
// ---------------------------------------------------------------------------

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
/// [`session_header`] with `ots_q*`, `dev_*` and `tension0..` (a row
/// without an orientation leaves `ots_q*` empty). An existing file may also
/// have that header without `ots_q*` (files started before the appender
/// wrote orientations): rows are appended to it as they are, and a sample
/// with an orientation is refused rather than written without it
/// ([`DatasetError::OrientationNotAppended`]).
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
    /// A write failed part-way: the file may end in a partial row, so no
    /// more rows go after it (open the file again to repair it).
    failed: bool,
}

impl SessionAppender {
    /// The optional groups of a new appended session: orientation (empty
    /// on rows without one), legacy positions and tensions. The header is
    /// fixed whatever the rows hold, so that a file can be reopened.
    pub const COLUMNS: OptionalColumns = OptionalColumns {
        orientation: true,
        legacy: true,
        tension: true,
    };

    /// The optional groups of a session appended to before orientations
    /// were: [`SessionAppender::COLUMNS`] without the orientation. Such a
    /// file is still appended to (with position-only rows).
    pub const COLUMNS_WITHOUT_ORIENTATION: OptionalColumns = OptionalColumns {
        orientation: false,
        ..Self::COLUMNS
    };

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
        let old_header = Self::header_line_without_orientation_for(strings);
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
            None if header.as_bytes().starts_with(&bytes)
                || old_header.as_bytes().starts_with(&bytes) =>
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
            let columns = if first_line == header.as_bytes() {
                Self::COLUMNS
            } else if first_line == old_header.as_bytes() {
                Self::COLUMNS_WITHOUT_ORIENTATION
            } else {
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
        Ok(OpenedSession {
            appender: SessionAppender {
                file,
                path: path.to_path_buf(),
                strings,
                columns,
                rows,
                last,
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
mod append_tests {
    use super::*;

    fn sample(t_s: f64, x: f64) -> Sample {
        Sample {
            t_s,
            counts: [1, -2, 3, -4, 5, -6, 7, -8],
            tracker: Some([x, 0.25, -1e-3]),
            orientation: None,
            legacy: Some([0.1, 0.2, 0.3]),
            tension_n: Some([1.0; STRINGS]),
        }
    }

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("spidar-append-{}", std::process::id()));
        let _ = fs::create_dir_all(&dir);
        let path = dir.join(name);
        let _ = fs::remove_file(&path);
        path
    }

    #[test]
    fn rows_appended_one_at_a_time_read_back_and_reopen_where_they_stopped() {
        let path = temp("rows.csv");
        let mut opened = SessionAppender::open(&path).unwrap();
        assert!(opened.created && opened.torn.is_none());
        assert_eq!(opened.appender.append(&sample(1.0, 10.0)).unwrap(), 2);
        assert_eq!(opened.appender.append(&sample(1.0, 11.5)).unwrap(), 3);
        // Time going backwards is refused, naming the line and column.
        let e = opened.appender.append(&sample(0.5, 0.0)).unwrap_err();
        assert!(e.to_string().contains("line 4, column `t_s`"), "{e}");
        drop(opened);
        let read = Session::load(&path).unwrap();
        assert_eq!(read.samples, vec![sample(1.0, 10.0), sample(1.0, 11.5)]);
        let mut again = SessionAppender::open(&path).unwrap();
        assert!(!again.created && again.torn.is_none());
        assert_eq!(again.existing, read);
        assert_eq!(again.appender.last_t_s(), Some(1.0));
        assert_eq!(again.appender.append(&sample(2.0, 12.0)).unwrap(), 4);
        assert_eq!(Session::load(&path).unwrap().samples.len(), 3);
    }

    fn oriented(t_s: f64, x: f64, q: [f64; 4]) -> Sample {
        Sample {
            orientation: Some(q),
            ..sample(t_s, x)
        }
    }

    /// A file as an older `spidar collect` started it: the header without
    /// the orientation columns, and `rows` rows.
    fn old_file(path: &Path, rows: &[Sample]) -> String {
        let columns = SessionAppender::COLUMNS_WITHOUT_ORIENTATION;
        let mut text = format!("{}\n", session_header(columns).join(","));
        let mut fields = Vec::new();
        for s in rows {
            row_fields(s, STRINGS, columns, &mut fields);
            text.push_str(&fields.join(","));
            text.push('\n');
        }
        fs::write(path, &text).unwrap();
        text
    }

    #[test]
    fn a_new_file_has_the_orientation_columns_and_rows_with_and_without_one_read_back() {
        let path = temp("oriented.csv");
        let mut opened = SessionAppender::open(&path).unwrap();
        assert!(opened.appender.has_orientation_columns());
        let q = [0.5, -0.5, 0.5, 0.5];
        let tilted = [0.996195, 0.0, 0.087156, 0.0];
        assert_eq!(opened.appender.append(&oriented(1.0, 10.0, q)).unwrap(), 2);
        assert_eq!(opened.appender.append(&sample(1.5, 11.0)).unwrap(), 3);
        drop(opened);
        let text = fs::read_to_string(&path).unwrap();
        let header = text.lines().next().unwrap();
        assert_eq!(header, SessionAppender::header_line());
        // As `Session::write_to` places them: after `ots_z`.
        assert!(
            header.contains("ots_x,ots_y,ots_z,ots_qw,ots_qx,ots_qy,ots_qz,dev_x"),
            "{header}"
        );
        // A row without an orientation leaves its columns empty.
        assert!(
            text.lines().nth(2).unwrap().contains(",-0.001,,,,,0.1,"),
            "{text}"
        );
        let mut again = SessionAppender::open(&path).unwrap();
        assert!(again.appender.has_orientation_columns() && !again.created);
        assert_eq!(
            again.existing.samples,
            vec![oriented(1.0, 10.0, q), sample(1.5, 11.0)]
        );
        assert_eq!(
            again.appender.append(&oriented(2.0, 12.0, tilted)).unwrap(),
            4
        );
        // What the reader refuses is refused before anything is written.
        let e = again
            .appender
            .append(&oriented(3.0, 13.0, [1.0, 1.0, 0.0, 0.0]))
            .unwrap_err();
        assert!(e.to_string().contains("line 5, column `ots_qw`"), "{e}");
        let e = again
            .appender
            .append(&Sample {
                tracker: None,
                ..oriented(3.0, 13.0, q)
            })
            .unwrap_err();
        assert!(e.to_string().contains("line 5, column `ots_qw`"), "{e}");
        drop(again);
        assert_eq!(
            Session::load(&path).unwrap().samples,
            vec![
                oriented(1.0, 10.0, q),
                sample(1.5, 11.0),
                oriented(2.0, 12.0, tilted)
            ]
        );
    }

    #[test]
    fn a_file_started_without_orientation_columns_reopens_and_takes_position_only_rows() {
        let path = temp("old.csv");
        let text = old_file(&path, &[sample(1.0, 10.0)]);
        let mut opened = SessionAppender::open(&path).unwrap();
        assert!(!opened.created && opened.torn.is_none());
        assert!(!opened.appender.has_orientation_columns());
        assert_eq!(opened.existing.samples, vec![sample(1.0, 10.0)]);
        assert_eq!(opened.appender.last_t_s(), Some(1.0));
        assert_eq!(opened.appender.append(&sample(2.0, 11.0)).unwrap(), 3);
        drop(opened);
        // The old header stays, and the row is in its columns.
        let now = fs::read_to_string(&path).unwrap();
        assert!(now.starts_with(&text), "{now}");
        assert!(!now.contains("ots_q"), "{now}");
        assert_eq!(
            Session::load(&path).unwrap().samples,
            vec![sample(1.0, 10.0), sample(2.0, 11.0)]
        );
        // Reopened again, with a torn last line cut off as for a new file.
        fs::write(&path, format!("{now}3,1,2")).unwrap();
        let mut opened = SessionAppender::open(&path).unwrap();
        assert_eq!(opened.torn.as_ref().map(|t| t.line), Some(4));
        assert!(!opened.appender.has_orientation_columns());
        assert_eq!(opened.appender.append(&sample(3.0, 12.0)).unwrap(), 4);
        drop(opened);
        assert_eq!(Session::load(&path).unwrap().samples.len(), 3);
        // An old header cut short (no row yet) starts again with the new one.
        let old_header = SessionAppender::header_line_without_orientation_for(STRINGS);
        let cut = &old_header[..old_header.len() - 3];
        assert!(!SessionAppender::header_line().starts_with(cut));
        fs::write(&path, cut).unwrap();
        let opened = SessionAppender::open(&path).unwrap();
        assert!(opened.created && opened.appender.has_orientation_columns());
        assert_eq!(opened.torn.map(|t| t.line), Some(1));
        assert_eq!(
            fs::read_to_string(&path).unwrap(),
            format!("{}\n", SessionAppender::header_line())
        );
    }

    #[test]
    fn a_file_started_without_orientation_columns_refuses_a_row_with_one() {
        let path = temp("old-oriented.csv");
        let text = old_file(&path, &[sample(1.0, 10.0)]);
        let mut opened = SessionAppender::open(&path).unwrap();
        let e = opened
            .appender
            .append(&oriented(2.0, 11.0, [1.0, 0.0, 0.0, 0.0]))
            .unwrap_err();
        assert!(
            matches!(e, DatasetError::OrientationNotAppended { line: 3, .. }),
            "{e}"
        );
        let message = e.to_string();
        assert!(message.contains("old-oriented.csv: line 3"), "{message}");
        assert!(
            message.contains("started without orientation columns"),
            "{message}"
        );
        // Nothing was written, and the next position-only row goes on line 3.
        assert_eq!(fs::read_to_string(&path).unwrap(), text);
        assert_eq!(opened.appender.append(&sample(2.0, 11.0)).unwrap(), 3);
    }

    #[test]
    fn an_unterminated_last_line_is_cut_off_and_reported() {
        let path = temp("torn.csv");
        let mut opened = SessionAppender::open(&path).unwrap();
        opened.appender.append(&sample(1.0, 10.0)).unwrap();
        drop(opened);
        let whole = fs::read_to_string(&path).unwrap();
        // A second row cut short (it even parses: its last number is cut).
        let row = whole.lines().nth(1).unwrap();
        fs::write(&path, format!("{whole}{}", &row[..row.len() - 2])).unwrap();
        let opened = SessionAppender::open(&path).unwrap();
        let torn = opened.torn.clone().expect("torn line reported");
        assert_eq!(torn.line, 3);
        assert_eq!(torn.text, row[..row.len() - 2]);
        assert_eq!(opened.existing.samples, vec![sample(1.0, 10.0)]);
        assert_eq!(fs::read_to_string(&path).unwrap(), whole);
        // A header cut short is started again.
        let header = SessionAppender::header_line();
        fs::write(&path, &header[..20]).unwrap();
        let opened = SessionAppender::open(&path).unwrap();
        assert!(opened.created);
        assert_eq!(opened.torn.map(|t| t.line), Some(1));
        assert_eq!(fs::read_to_string(&path).unwrap(), format!("{header}\n"));
    }

    #[test]
    fn another_header_or_a_bad_complete_row_is_an_error_naming_the_file() {
        let path = temp("other.csv");
        fs::write(&path, "t_s,enc0\n1,2\n").unwrap();
        let e = SessionAppender::open(&path).err().expect("refused");
        assert!(matches!(e, DatasetError::HeaderMismatch { .. }), "{e}");
        assert!(e.to_string().contains("other.csv: line 1"), "{e}");
        assert_eq!(fs::read_to_string(&path).unwrap(), "t_s,enc0\n1,2\n");
        let header = SessionAppender::header_line();
        let fields = header.split(',').count();
        let bad = format!("{header}\n1,x{}\n", ",0".repeat(fields - 2));
        fs::write(&path, &bad).unwrap();
        let e = SessionAppender::open(&path).err().expect("refused");
        assert!(e.to_string().contains("line 2, column `enc0`"), "{e}");
        assert_eq!(fs::read_to_string(&path).unwrap(), bad);
    }
}

#[cfg(test)]
mod append_n_tests {
    use super::*;

    #[test]
    fn a_four_string_device_appends_its_own_columns_and_refuses_an_eight_string_file() {
        let dir = std::env::temp_dir().join(format!("spidar-append4-{}", std::process::id()));
        let _ = fs::create_dir_all(&dir);
        let path = dir.join("four.csv");
        let _ = fs::remove_file(&path);
        let mut opened = SessionAppender::open_for(&path, 4).unwrap();
        let sample = Sample {
            t_s: 0.5,
            counts: [1, 2, 3, 4, 0, 0, 0, 0],
            tracker: Some([1.0, 2.0, 3.0]),
            orientation: None,
            legacy: None,
            tension_n: Some([1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]),
        };
        opened.appender.append(&sample).unwrap();
        drop(opened);
        let text = fs::read_to_string(&path).unwrap();
        assert!(text.starts_with("t_s,enc0,enc1,enc2,enc3,ots_x"), "{text}");
        let read = Session::load(&path).unwrap();
        assert_eq!(read.strings, 4);
        assert_eq!(read.samples, vec![sample]);
        assert_eq!(SessionAppender::open_for(&path, 4).unwrap().existing, read);
        let e = SessionAppender::open(&path)
            .err()
            .expect("8-string writer refused");
        assert!(matches!(e, DatasetError::HeaderMismatch { .. }), "{e}");
    }
}
