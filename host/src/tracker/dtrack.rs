//! The A.R.T. DTrack ASCII output (DTrack2, DTrack3): parsing and formatting
//! one datagram.
//!
//! Format, as documented in the DTrack2 user manual, Technical Appendix B.2
//! "Output of Measurement Data via Ethernet" (A.R.T. GmbH; read in the
//! Flystick2/Flystick3 manual editions, pages 259-264):
//!
//! - one UDP datagram per measurement frame, ASCII, one record per line;
//!   DTrack ends lines with CR LF (we also accept a bare LF);
//! - `fr <n>` (B.2.1): the frame counter, "always the first" line, counting
//!   at the synchronization frequency;
//! - `ts <s>` (B.2.2, optional output): the time of the camera flash, seconds
//!   since 00:00 UTC with microsecond resolution, **reset to 0 at midnight**;
//! - `ts2 <s> <us> <latency>` (DTRACK3, optional output): the measurement
//!   time as whole seconds since 1970-01-01 UTC plus microseconds, then the
//!   latency in microseconds. (The DTrackSDK sources read for this, up to
//!   2023, do not parse `ts2`: they skip it as an unknown record; the layout
//!   is DTRACK3's.) See [`DtrackFrame::ts_s`] for the clock we give it;
//! - `6dcal <n>`: the number of calibrated standard bodies;
//! - `6d <n> [id qu][sx sy sz eta theta phi][b0 .. b8] ...` (B.2.3): the
//!   *tracked* standard bodies only ("bodies that are not tracked ... don't
//!   appear in the output"), `id` counted from 0, position in mm in the room
//!   frame, and the rotation matrix given column-wise:
//!   `R = [[b0 b3 b6], [b1 b4 b7], [b2 b5 b8]]`. The manual calls `qu`
//!   "unused" for `6d`; other record types use `qu = -1` for a target that is
//!   not visible, so we treat a negative quality as occluded too;
//! - other records (`3d`, `6di`, `6df`, `6df2`, `6dmt`, `6dmt2`, `6dmtr`, `gl`,
//!   `glcal`, ...) are legitimate outputs we do not use: they are skipped
//!   without error, whatever they contain.
//!
//! Errors name the line (1-based) and the field, e.g. `6d body 2: qu`.

use std::fmt::{self, Write as _};

/// One 6DOF body of a `6d` record.
#[derive(Clone, Debug, PartialEq)]
pub struct BodyPose {
    /// Body id as DTrack numbers it (from 0).
    pub id: u32,
    /// Position of the body origin in the room frame (mm).
    pub position_mm: [f64; 3],
    /// Rotation body -> room, `rotation[row][col]` (the paper's eq. 1:
    /// `x_room = R x_body + s`).
    pub rotation: [[f64; 3]; 3],
    /// DTrack's quality value; negative means not visible.
    pub quality: f64,
}

impl BodyPose {
    /// A body seen at `position_mm` with the identity rotation and quality 1.
    pub fn at(id: u32, position_mm: [f64; 3]) -> Self {
        BodyPose {
            id,
            position_mm,
            rotation: IDENTITY,
            quality: 1.0,
        }
    }

    /// True if DTrack reports the body as visible (quality >= 0).
    pub fn is_visible(&self) -> bool {
        self.quality >= 0.0
    }
}

/// The identity rotation.
pub const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Everything of one datagram that this module understands.
#[derive(Clone, Debug, PartialEq)]
pub struct DtrackFrame {
    /// `fr`: frame counter.
    pub frame: u32,
    /// The measurement time, seconds since 00:00 UTC, if DTrack's timestamp
    /// output is enabled: from `ts2` if present, else from `ts`.
    ///
    /// `ts2` gives whole seconds since 1970 and microseconds; we keep the
    /// time of day, `(s % 86400) + us / 1e6` (computed in integer
    /// microseconds, so `ts 39596.024470` and `ts2 1699959596 24470` give
    /// the same `f64`). Every `ts_s` is then on the clock of `ts`, which
    /// restarts at midnight: the receiver unwraps that one clock (see its
    /// `day_offset_s`), whichever record a set-up sends, and a stream that
    /// switches between the two records does not jump by 1.7e9 s. The date
    /// that `ts2` would add is of no use to the time shift, which is
    /// estimated over seconds to minutes.
    ///
    /// Both present: `ts2` is used, always. It gives the time as whole
    /// numbers, with no decimal rounding, and it is DTRACK3's newer record;
    /// preferring one record for every frame keeps the stream on one source
    /// even if the two were ever to differ. The `ts` line is still checked
    /// (a malformed one is an error).
    pub ts_s: Option<f64>,
    /// `6dcal`: number of calibrated bodies, if present.
    pub calibrated_bodies: Option<u32>,
    /// `6d`: the bodies listed (tracked ones; may include negative quality).
    /// Empty if the record is absent or lists no body.
    pub bodies: Vec<BodyPose>,
    /// True if a `6d` record was present.
    pub has_6d: bool,
}

impl DtrackFrame {
    /// The body `id` if it is listed and visible; `None` means occluded.
    pub fn visible_body(&self, id: u32) -> Option<&BodyPose> {
        self.bodies
            .iter()
            .find(|b| b.id == id)
            .filter(|b| b.is_visible())
    }
}

/// Why one value of a datagram is rejected.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FieldProblem {
    #[error("missing")]
    Missing,
    #[error("`{0}` is not an unsigned integer")]
    NotAnInteger(String),
    #[error("`{0}` is not a number")]
    NotANumber(String),
    #[error("`{0}` is not a finite number")]
    NotFinite(String),
    #[error("`{text}` is not below {limit}")]
    NotBelow { text: String, limit: u64 },
    #[error("unexpected `{0}`")]
    Unexpected(String),
    #[error("expected `[`, found `{0}`")]
    ExpectedBlock(String),
    #[error("`[` without its `]`")]
    UnclosedBlock,
    #[error("{found} values in the block, {expected} expected")]
    BlockLength { expected: usize, found: usize },
    #[error("the count says {declared}, but {found} bodies follow")]
    CountMismatch { declared: u32, found: usize },
    #[error("given twice (lines {first} and {second})")]
    Repeated { first: usize, second: usize },
}

/// A malformed datagram. Unknown record types are never an error.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum DtrackError {
    #[error("the datagram is empty")]
    Empty,
    #[error("byte {offset}: the datagram is not ASCII/UTF-8 text")]
    NotText { offset: usize },
    #[error("no `fr` (frame counter) line")]
    MissingFrameCounter,
    /// The receiver needs a timestamp: enable DTrack's timestamp output
    /// (DTrack2: Settings -> Output 'ts'; DTrack3: 'ts' or 'ts2').
    #[error("no `ts` or `ts2` (timestamp) line: enable the DTrack timestamp output")]
    MissingTimestamp,
    #[error("line {line}, field `{field}`: {problem}")]
    Field {
        line: usize,
        field: String,
        problem: FieldProblem,
    },
}

fn field_error(line: usize, field: impl Into<String>, problem: FieldProblem) -> DtrackError {
    DtrackError::Field {
        line,
        field: field.into(),
        problem,
    }
}

fn parse_u32(line: usize, field: &str, text: Option<&str>) -> Result<u32, DtrackError> {
    let text = text.ok_or_else(|| field_error(line, field, FieldProblem::Missing))?;
    text.parse::<u32>()
        .map_err(|_| field_error(line, field, FieldProblem::NotAnInteger(text.to_string())))
}

fn parse_f64(line: usize, field: &dyn Fn() -> String, text: &str) -> Result<f64, DtrackError> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(field_error(
            line,
            field(),
            FieldProblem::NotFinite(text.to_string()),
        )),
        Err(_) => Err(field_error(
            line,
            field(),
            FieldProblem::NotANumber(text.to_string()),
        )),
    }
}

/// Seconds in a day: `ts` counts from midnight UTC.
const DAY_S: u64 = 86_400;
const MICROS_PER_S: u64 = 1_000_000;

/// `ts2 <s> <us> [<latency>]`: the time of day (see [`DtrackFrame::ts_s`]).
/// The latency (microseconds) is checked when present and not kept.
fn parse_ts2(line: usize, rest: &str) -> Result<f64, DtrackError> {
    let mut words = rest.split_ascii_whitespace();
    let seconds = words
        .next()
        .ok_or_else(|| field_error(line, "ts2 seconds", FieldProblem::Missing))?;
    let seconds = seconds.parse::<u64>().map_err(|_| {
        field_error(
            line,
            "ts2 seconds",
            FieldProblem::NotAnInteger(seconds.to_string()),
        )
    })?;
    let micros_text = words.next();
    let micros = parse_u32(line, "ts2 microseconds", micros_text)?;
    if u64::from(micros) >= MICROS_PER_S {
        return Err(field_error(
            line,
            "ts2 microseconds",
            FieldProblem::NotBelow {
                text: micros.to_string(),
                limit: MICROS_PER_S,
            },
        ));
    }
    if let Some(latency) = words.next() {
        parse_u32(line, "ts2 latency", Some(latency))?;
    }
    // Integer microseconds of the day (< 8.64e10, exact in an f64), divided
    // once: the correctly rounded value, as parsing `ts`'s decimal gives.
    let micros_of_day = (seconds % DAY_S) * MICROS_PER_S + u64::from(micros);
    Ok(micros_of_day as f64 / MICROS_PER_S as f64)
}

/// Split `rest` into its `[...]` blocks (contents only).
fn blocks<'a>(line: usize, field: &str, rest: &'a str) -> Result<Vec<&'a str>, DtrackError> {
    let mut out = Vec::new();
    let mut rest = rest.trim_start();
    while !rest.is_empty() {
        let Some(inner) = rest.strip_prefix('[') else {
            let shown: String = rest.chars().take(16).collect();
            return Err(field_error(line, field, FieldProblem::ExpectedBlock(shown)));
        };
        let Some(end) = inner.find(']') else {
            return Err(field_error(line, field, FieldProblem::UnclosedBlock));
        };
        out.push(&inner[..end]);
        rest = inner[end + 1..].trim_start();
    }
    Ok(out)
}

/// The numbers of one block, checking their count.
fn block_numbers<const N: usize>(
    line: usize,
    field: &dyn Fn() -> String,
    block: &str,
) -> Result<[f64; N], DtrackError> {
    let words: Vec<&str> = block.split_ascii_whitespace().collect();
    if words.len() != N {
        return Err(field_error(
            line,
            field(),
            FieldProblem::BlockLength {
                expected: N,
                found: words.len(),
            },
        ));
    }
    let mut out = [0.0; N];
    for (k, (o, w)) in out.iter_mut().zip(&words).enumerate() {
        *o = parse_f64(line, &|| format!("{}[{k}]", field()), w)?;
    }
    Ok(out)
}

fn parse_6d(line: usize, rest: &str) -> Result<Vec<BodyPose>, DtrackError> {
    let rest = rest.trim_start();
    let (count_text, blocks_text) = match rest.find(|c: char| c.is_ascii_whitespace() || c == '[') {
        Some(i) => (&rest[..i], &rest[i..]),
        None => (rest, ""),
    };
    let count_text = (!count_text.is_empty()).then_some(count_text);
    let declared = parse_u32(line, "6d count", count_text)?;
    let blocks = blocks(line, "6d bodies", blocks_text)?;
    if blocks.len() % 3 != 0 || blocks.len() / 3 != declared as usize {
        return Err(field_error(
            line,
            "6d count",
            FieldProblem::CountMismatch {
                declared,
                found: blocks.len() / 3,
            },
        ));
    }
    let mut bodies = Vec::with_capacity(blocks.len() / 3);
    for (n, b) in blocks.chunks_exact(3).enumerate() {
        let name = |part: &str| format!("6d body {}: {part}", n + 1);
        let head: Vec<&str> = b[0].split_ascii_whitespace().collect();
        if head.len() != 2 {
            return Err(field_error(
                line,
                name("[id qu]"),
                FieldProblem::BlockLength {
                    expected: 2,
                    found: head.len(),
                },
            ));
        }
        let id = parse_u32(line, &name("id"), Some(head[0]))?;
        let quality = parse_f64(line, &|| name("qu"), head[1])?;
        let s: [f64; 6] = block_numbers(line, &|| name("[sx sy sz eta theta phi]"), b[1])?;
        let m: [f64; 9] = block_numbers(line, &|| name("[b0..b8]"), b[2])?;
        // Column-wise: b0 b1 b2 is the first column.
        let rotation = core::array::from_fn(|row| core::array::from_fn(|col| m[col * 3 + row]));
        bodies.push(BodyPose {
            id,
            position_mm: [s[0], s[1], s[2]],
            rotation,
            quality,
        });
    }
    Ok(bodies)
}

/// Parse one datagram.
pub fn parse_datagram(bytes: &[u8]) -> Result<DtrackFrame, DtrackError> {
    let text = std::str::from_utf8(bytes).map_err(|e| DtrackError::NotText {
        offset: e.valid_up_to(),
    })?;
    if text.trim().is_empty() {
        return Err(DtrackError::Empty);
    }
    let mut frame: Option<(u32, usize)> = None;
    let mut ts: Option<(f64, usize)> = None;
    let mut ts2: Option<(f64, usize)> = None;
    let mut cal: Option<(u32, usize)> = None;
    let mut six_d: Option<(Vec<BodyPose>, usize)> = None;
    let repeated = |name: &str, first: usize, second: usize| {
        field_error(second, name, FieldProblem::Repeated { first, second })
    };
    for (index, raw) in text.split('\n').enumerate() {
        let line = index + 1;
        let content = raw.trim();
        if content.is_empty() {
            continue;
        }
        let (kind, rest) = match content.find(|c: char| c.is_ascii_whitespace() || c == '[') {
            Some(i) => (&content[..i], &content[i..]),
            None => (content, ""),
        };
        match kind {
            "fr" => {
                if let Some((_, first)) = frame {
                    return Err(repeated("fr", first, line));
                }
                let mut words = rest.split_ascii_whitespace();
                let n = parse_u32(line, "fr", words.next())?;
                if let Some(extra) = words.next() {
                    return Err(field_error(
                        line,
                        "fr",
                        FieldProblem::Unexpected(extra.to_string()),
                    ));
                }
                frame = Some((n, line));
            }
            "ts" => {
                if let Some((_, first)) = ts {
                    return Err(repeated("ts", first, line));
                }
                let mut words = rest.split_ascii_whitespace();
                let word = words
                    .next()
                    .ok_or_else(|| field_error(line, "ts", FieldProblem::Missing))?;
                let v = parse_f64(line, &|| "ts".to_string(), word)?;
                if let Some(extra) = words.next() {
                    return Err(field_error(
                        line,
                        "ts",
                        FieldProblem::Unexpected(extra.to_string()),
                    ));
                }
                ts = Some((v, line));
            }
            "ts2" => {
                if let Some((_, first)) = ts2 {
                    return Err(repeated("ts2", first, line));
                }
                ts2 = Some((parse_ts2(line, rest)?, line));
            }
            "6dcal" => {
                if let Some((_, first)) = cal {
                    return Err(repeated("6dcal", first, line));
                }
                let mut words = rest.split_ascii_whitespace();
                let n = parse_u32(line, "6dcal", words.next())?;
                if let Some(extra) = words.next() {
                    return Err(field_error(
                        line,
                        "6dcal",
                        FieldProblem::Unexpected(extra.to_string()),
                    ));
                }
                cal = Some((n, line));
            }
            "6d" => {
                if let Some((_, first)) = six_d {
                    return Err(repeated("6d", first, line));
                }
                six_d = Some((parse_6d(line, rest)?, line));
            }
            // 3d, 6di, 6df, 6df2, 6dmt, 6dmt2, 6dmtr, gl, glcal and any future
            // record: legitimate output we do not consume.
            _ => {}
        }
    }
    let (frame, _) = frame.ok_or(DtrackError::MissingFrameCounter)?;
    let has_6d = six_d.is_some();
    Ok(DtrackFrame {
        frame,
        ts_s: ts2.or(ts).map(|(v, _)| v),
        calibrated_bodies: cal.map(|(v, _)| v),
        bodies: six_d.map(|(b, _)| b).unwrap_or_default(),
        has_6d,
    })
}

/// Write `x` so that it parses back to the same `f64` (shortest exact form).
struct Num(f64);

impl fmt::Display for Num {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "{:?}", self.0)
    }
}

/// Format a datagram the way DTrack2 writes one (CR LF line ends), with
/// numbers in their shortest exact form so that parsing gives the same frame
/// back. The orientation angles (eta theta phi), which this module never
/// reads, are derived from the rotation as DTrack defines them
/// (`R = Rx(eta) Ry(theta) Rz(phi)`, degrees).
pub fn format_datagram(frame: &DtrackFrame) -> String {
    let mut s = String::new();
    let _ = write!(s, "fr {}\r\n", frame.frame);
    if let Some(ts) = frame.ts_s {
        // DTrack writes microseconds; keep full precision for exact round trips.
        let _ = write!(s, "ts {}\r\n", Num(ts));
    }
    if let Some(n) = frame.calibrated_bodies {
        let _ = write!(s, "6dcal {n}\r\n");
    }
    if frame.has_6d || !frame.bodies.is_empty() {
        let _ = write!(s, "6d {}", frame.bodies.len());
        for b in &frame.bodies {
            let [eta, theta, phi] = euler_deg(&b.rotation);
            let p = b.position_mm;
            let _ = write!(
                s,
                " [{} {}][{} {} {} {} {} {}][",
                b.id,
                Num(b.quality),
                Num(p[0]),
                Num(p[1]),
                Num(p[2]),
                Num(eta),
                Num(theta),
                Num(phi)
            );
            for col in 0..3 {
                for row in 0..3 {
                    let sep = if col == 0 && row == 0 { "" } else { " " };
                    let _ = write!(s, "{sep}{}", Num(b.rotation[row][col]));
                }
            }
            s.push(']');
        }
        s.push_str("\r\n");
    }
    s
}

/// DTrack's angles of a rotation `R = Rx(eta) Ry(theta) Rz(phi)`, in degrees.
fn euler_deg(r: &[[f64; 3]; 3]) -> [f64; 3] {
    let theta = r[0][2].clamp(-1.0, 1.0).asin();
    let eta = (-r[1][2]).atan2(r[2][2]);
    let phi = (-r[0][1]).atan2(r[0][0]);
    let out = [eta.to_degrees(), theta.to_degrees(), phi.to_degrees()];
    out.map(|v| if v.is_finite() { v } else { 0.0 })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_is_column_wise() {
        let d = b"fr 1\r\n6d 1 [0 1.0][1 2 3 0 0 0][1 2 3 4 5 6 7 8 9]\r\n";
        let f = parse_datagram(d).unwrap();
        assert_eq!(
            f.bodies[0].rotation,
            [[1.0, 4.0, 7.0], [2.0, 5.0, 8.0], [3.0, 6.0, 9.0]]
        );
    }
}
