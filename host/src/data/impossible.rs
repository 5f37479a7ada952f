//! Rows no device of a geometry could have produced, found before anything
//! is fitted to them: a count that would pay out more string than the
//! frame holds, a tracker (or legacy controller) position far outside the
//! frame. One such row among thousands spoils a least-squares fit silently
//! (a count of `i32::MIN` raises a held-out error threefold); a calibration
//! sets it aside by file and line, as it does the tracker's glitches, and
//! counts it in its report.
//!
//! The bounds scale with the device and hold whatever the session's home:
//! - a string's length changes by at most the frame's **span** (the largest
//!   distance between two of its anchors, or an anchor and home) over a
//!   session, and a nominal string law may misjudge a payout by up to
//!   [`NOMINAL_SCALE_LIMIT`] (beyond it the calibration refuses the
//!   geometry as a unit mistake), so a count whose nominal payout is more
//!   than that many spans from the session's median count is impossible;
//! - the marker rides the end-effector inside the frame, so a tracked (or
//!   legacy) position more than [`NOMINAL_SCALE_LIMIT`] spans from the
//!   session's median position is impossible, and so is any coordinate
//!   beyond [`MAX_ANCHOR_DISTANCE_MM`] (10 km) of the origin.
//!
//! Medians are the reference because the impossible rows are few; a
//! session where most rows break a bound is not a session with bad rows but
//! a geometry or a unit that does not fit it, which the calibration refuses
//! ([`SetAside::is_most_of`]).

use serde::Serialize;
use spidar_core::geometry::distance;
use spidar_core::plausible::MAX_ANCHOR_DISTANCE_MM;

use crate::data::dataset::{Geometry, Session, ENCODER_COLUMNS, LEGACY_COLUMNS, TRACKER_COLUMNS};

/// How far (a factor) a nominal geometry may misjudge the device's scale:
/// the calibration refuses a tracker spread this many times the nominal
/// model's as a unit mistake, and a row this many frame spans from its
/// session's median is impossible.
pub const NOMINAL_SCALE_LIMIT: f64 = spidar_core::plausible::MAX_ROOM_SCALE_FACTOR;

/// What of a row is set aside.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SetAsidePart {
    /// The whole row: its counts cannot be.
    Row,
    /// Its tracker position (the row is read as occluded).
    Tracker,
    /// Its legacy controller position (`dev_*`).
    Legacy,
}

/// One row's value that cannot be, and what of the row goes with it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ImpossibleValue {
    /// Index of the row in the session.
    #[serde(skip)]
    pub row: usize,
    /// Its line in the file (the header is line 1).
    pub line: u64,
    pub column: String,
    pub value: f64,
    pub part: SetAsidePart,
    /// Why it cannot be, in millimetres of the device.
    pub why: String,
    /// The line this row repeats exactly ([`Session::repeated_rows`]):
    /// set aside as a duplicate, not as a value no device could produce.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub repeats_line: Option<u64>,
}

/// The impossible values of one session, at most one per row (the whole
/// row's when its counts cannot be), in row order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SetAside {
    pub values: Vec<ImpossibleValue>,
}

impl SetAside {
    /// The values of `session` that no device of `geometry` could produce
    /// (the legacy positions when the session was read with them,
    /// [`crate::data::dataset::ReadOptions`]).
    pub fn find(session: &Session, geometry: &Geometry) -> SetAside {
        let span = frame_span_mm(geometry);
        let limit = NOMINAL_SCALE_LIMIT * span;
        let strings = session.strings.min(geometry.strings());
        let mm_per_count = geometry.nominal_mm_per_count();
        let median_counts: Vec<f64> = (0..strings)
            .map(|i| median(session.samples.iter().map(|s| f64::from(s.counts[i]))))
            .collect();
        let tracker_median = median_position(session.samples.iter().filter_map(|s| s.tracker));
        let legacy_median = median_position(session.samples.iter().filter_map(|s| s.legacy));
        let mut values = Vec::new();
        let repeated = session.repeated_rows();
        for (row, s) in session.samples.iter().enumerate() {
            let line = row as u64 + 2;
            if let Some(&(_, of)) = repeated.iter().find(|r| r.0 == row) {
                let of_line = of as u64 + 2;
                values.push(ImpossibleValue {
                    row,
                    line,
                    column: crate::data::dataset::TIME_COLUMN.to_string(),
                    value: s.t_s,
                    part: SetAsidePart::Row,
                    why: format!(
                        "line {line} repeats line {of_line} (the same time and every value): \
                         a row duplicated on its way to the file, not a second pose"
                    ),
                    repeats_line: Some(of_line),
                });
                continue;
            }
            let count = (0..strings).find_map(|i| {
                let payout = (f64::from(s.counts[i]) - median_counts[i]) * mm_per_count[i].abs();
                (payout.abs() > limit).then(|| ImpossibleValue {
                    row,
                    line,
                    column: ENCODER_COLUMNS[i].to_string(),
                    value: f64::from(s.counts[i]),
                    part: SetAsidePart::Row,
                    why: format!(
                        "string {i} would pay out {payout:.0} mm from its median length in \
                         this session, where the frame spans {span:.0} mm"
                    ),
                    repeats_line: None,
                })
            });
            let position = |p: Option<[f64; 3]>, median: Option<[f64; 3]>, columns, part, what| {
                far_position(p?, median?, limit, span, columns, what).map(|(c, v, why)| {
                    ImpossibleValue {
                        row,
                        line,
                        column: c,
                        value: v,
                        part,
                        why,
                        repeats_line: None,
                    }
                })
            };
            let found = count
                .or_else(|| {
                    position(
                        s.tracker,
                        tracker_median,
                        &TRACKER_COLUMNS,
                        SetAsidePart::Tracker,
                        "the tracker puts the marker",
                    )
                })
                .or_else(|| {
                    position(
                        s.legacy,
                        legacy_median,
                        &LEGACY_COLUMNS,
                        SetAsidePart::Legacy,
                        "the legacy controller puts the end-effector",
                    )
                });
            values.extend(found);
        }
        SetAside { values }
    }

    /// No value set aside.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// More than half of `rows` set aside: not bad rows but a geometry or a
    /// unit that does not fit the session.
    pub fn is_most_of(&self, rows: usize) -> bool {
        2 * self.impossible().count() > rows
    }

    /// The values no device could produce (not the repeated rows).
    pub fn impossible(&self) -> impl Iterator<Item = &ImpossibleValue> + '_ {
        self.values.iter().filter(|v| v.repeats_line.is_none())
    }

    /// The rows that repeat the row before them, set aside whole.
    pub fn repeats(&self) -> impl Iterator<Item = &ImpossibleValue> + '_ {
        self.values.iter().filter(|v| v.repeats_line.is_some())
    }

    /// The rows set aside whole, in order.
    pub fn rows(&self) -> Vec<usize> {
        self.values
            .iter()
            .filter(|v| v.part == SetAsidePart::Row)
            .map(|v| v.row)
            .collect()
    }

    /// `session` with the tracker and legacy positions set aside emptied
    /// (those rows then read as occluded, or without a legacy position);
    /// rows set aside whole stay, for the caller to skip ([`SetAside::rows`])
    /// so that every row keeps its index and line.
    pub fn without_positions(&self, session: &Session) -> Session {
        let mut out = session.clone();
        for v in &self.values {
            let s = &mut out.samples[v.row];
            match v.part {
                SetAsidePart::Row => {}
                SetAsidePart::Tracker => {
                    s.tracker = None;
                    s.orientation = None;
                }
                SetAsidePart::Legacy => s.legacy = None,
            }
        }
        out
    }

    /// The first impossible values' lines with their column and value, and
    /// how many more.
    pub fn lines(&self, first: usize) -> String {
        first_of(
            self.impossible().map(|v| {
                format!(
                    "line {} (`{}` = {}: {})",
                    v.line,
                    v.column,
                    shown(v.value),
                    v.why
                )
            }),
            first,
        )
    }

    /// The first repeated rows ("line 7 repeats line 6"), and how many
    /// more.
    pub fn repeat_lines(&self, first: usize) -> String {
        first_of(
            self.repeats().map(|v| {
                format!(
                    "line {} repeats line {}",
                    v.line,
                    v.repeats_line.unwrap_or_default()
                )
            }),
            first,
        )
    }
}

/// The first `first` of `texts` and how many more, joined by "; ".
pub(crate) fn first_of(texts: impl Iterator<Item = String>, first: usize) -> String {
    let all: Vec<String> = texts.collect();
    let more = all.len().saturating_sub(first);
    let mut text: Vec<String> = all.into_iter().take(first).collect();
    if more > 0 {
        text.push(format!("and {more} more"));
    }
    text.join("; ")
}

/// A value as a person reads it: whole numbers (counts) in full up to 1e9,
/// others in the shortest exact form, the very large in scientific notation.
fn shown(value: f64) -> String {
    if value.abs() >= 1e9 && value.fract() != 0.0 || value.abs() >= 1e15 {
        format!("{value:e}")
    } else {
        value.to_string()
    }
}

/// The column, value and reason of a position `p` that lies more than
/// `limit` from the session's `median` position, or beyond
/// [`MAX_ANCHOR_DISTANCE_MM`] of the origin; `None` if it can be.
fn far_position(
    p: [f64; 3],
    median: [f64; 3],
    limit: f64,
    span: f64,
    columns: &[&str; 3],
    what: &str,
) -> Option<(String, f64, String)> {
    let off = distance(p, median);
    let beyond_origin = p.iter().any(|v| v.abs() > MAX_ANCHOR_DISTANCE_MM);
    if off <= limit && !beyond_origin {
        return None;
    }
    // The coordinate furthest from the median names the column.
    let k = (0..3)
        .max_by(|&a, &b| {
            (p[a] - median[a])
                .abs()
                .total_cmp(&(p[b] - median[b]).abs())
        })
        .unwrap_or(0);
    let why = if beyond_origin {
        format!("{what} beyond {MAX_ANCHOR_DISTANCE_MM:.0e} mm of the origin")
    } else {
        format!(
            "{what} {off:.0} mm from the session's median position, where the frame spans \
             {span:.0} mm"
        )
    };
    Some((columns[k].to_string(), p[k], why))
}

/// The frame's span: the largest distance between two of its active
/// anchors, or an anchor and home (mm).
pub fn frame_span_mm(geometry: &Geometry) -> f64 {
    let active: Vec<[f64; 3]> = geometry
        .layout
        .indices()
        .map(|i| geometry.anchors_mm[i])
        .collect();
    let mut span: f64 = 0.0;
    for (k, a) in active.iter().enumerate() {
        span = span.max(distance(*a, geometry.home_mm));
        for b in &active[k + 1..] {
            span = span.max(distance(*a, *b));
        }
    }
    span
}

fn median(values: impl Iterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = values.collect();
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// The per-coordinate median of `points`; `None` without a point.
pub(crate) fn median_position(points: impl Iterator<Item = [f64; 3]> + Clone) -> Option<[f64; 3]> {
    points.clone().next()?;
    Some(core::array::from_fn(|k| {
        median(points.clone().map(|p| p[k]))
    }))
}

#[cfg(test)]
mod tests;
