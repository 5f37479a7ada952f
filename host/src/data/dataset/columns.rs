//! A session's columns: their names, where a header puts them, and the
//! header a writer writes.

use std::path::Path;

use spidar_core::STRINGS;

use super::{DatasetError, MIN_STRINGS};

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
/// Names of the legacy-controller columns (device frame, mm).
pub const LEGACY_COLUMNS: [&str; 3] = ["dev_x", "dev_y", "dev_z"];
/// Names of the commanded-tension columns (N), index = encoder index.
pub const TENSION_COLUMNS: [&str; STRINGS] = [
    "tension0", "tension1", "tension2", "tension3", "tension4", "tension5", "tension6", "tension7",
];

/// Name of the column of the time since the device's home capture (s):
/// `State::since_home_us`, what the string law's time terms read. Optional;
/// without it they read `t_s`.
pub const SINCE_HOME_COLUMN: &str = "since_home_s";
/// Name of the column naming the home capture a row follows (an integer
/// id, `State::home_id`): rows of two sessions with the same id count from
/// the same home, so a slip of one is still in the other. Optional.
pub const HOME_COLUMN: &str = "home";

/// Which optional column groups a session file has.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OptionalColumns {
    /// `ots_qw, ots_qx, ots_qy, ots_qz`.
    pub orientation: bool,
    /// `dev_x, dev_y, dev_z`.
    pub legacy: bool,
    /// `tension0..tension{N-1}`.
    pub tension: bool,
    /// `since_home_s` ([`SINCE_HOME_COLUMN`]).
    pub since_home: bool,
    /// `home` ([`HOME_COLUMN`]).
    pub home: bool,
}

/// The header [`Session::write_to`](super::Session::write_to) writes for an
/// 8-string device: `t_s`, `enc0..7`, `ots_x, ots_y, ots_z`, then the
/// optional groups of `columns`: `ots_q*`, `dev_*`, `tension0..7`,
/// `since_home_s`, `home`.
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
    if columns.since_home {
        header.push(SINCE_HOME_COLUMN);
    }
    if columns.home {
        header.push(HOME_COLUMN);
    }
    header
}

/// Where each known column sits in a header.
pub(super) struct Layout {
    pub(super) time: usize,
    /// `enc0..enc{N-1}`.
    pub(super) counts: Vec<usize>,
    /// `ots_x, ots_y` and, unless the session is planar, `ots_z`.
    pub(super) tracker: Vec<usize>,
    /// `ots_qw, ots_qx, ots_qy, ots_qz`.
    pub(super) orientation: Option<[usize; 4]>,
    pub(super) legacy: Option<[usize; 3]>,
    /// `tension0..tension{N-1}`.
    pub(super) tension: Option<Vec<usize>>,
    pub(super) since_home: Option<usize>,
    pub(super) home: Option<usize>,
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
    pub(super) fn from_header(
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
                || n == SINCE_HOME_COLUMN
                || n == HOME_COLUMN
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
                since_home: index_of(SINCE_HOME_COLUMN),
                home: index_of(HOME_COLUMN),
            },
            ignored,
        ))
    }
}
