//! The A.R.T. DTrack ASCII output (DTrack2, DTrack3): parsing and formatting
//! one datagram.
//!
//! Format, as documented in the DTrack2 user manual, Technical Appendix B.2
//! "Output of Measurement Data via Ethernet" (A.R.T. GmbH; read in the
//! Flystick2/Flystick3 manual editions, pages 259-264), with DTRACK3's
//! `ts2`, and as A.R.T.'s DTrackSDK (`DTrackParser.cpp`, `DTrackParse.cpp`)
//! and VRPN (`vrpn_Tracker_DTrack.C`) read it:
//!
//! - one UDP datagram per measurement frame, ASCII, one record per line;
//!   DTrack ends lines with CR LF; a bare LF or a bare CR ends a line too
//!   (the SDK splits lines at either character);
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
//! - `6d <n> [id qu][sx sy sz ...][b0 .. b8] ...` (B.2.3): the *tracked*
//!   standard bodies only ("bodies that are not tracked ... don't appear in
//!   the output"), `id` counted from 0, position in mm in the room frame, and
//!   the rotation matrix given column-wise:
//!   `R = [[b0 b3 b6], [b1 b4 b7], [b2 b5 b8]]`. The DTrack2 manual's example
//!   has three angles after the position (`[sx sy sz eta theta phi]`); later
//!   DTrack versions write `[sx sy sz]`. Both are read: like the SDK we read
//!   the first three values of that block. The manual calls `qu` "unused"
//!   for `6d`; other record types use `qu = -1` for a target that is not
//!   visible, so we treat a negative quality as occluded too;
//! - `6di <n> [id st error][sx sy sz][b0 .. b8] ...` (hybrid, optical and
//!   inertial bodies): read as bodies too, with the same position and
//!   rotation. `st` is the tracking state: 0 not tracked, 1 inertial only,
//!   2 optical and inertial. State 2 gets the quality 1; any other state
//!   (0, 1 inertial only, and states not known to us) the quality -1,
//!   occluded: an inertial-only pose is dead reckoning that drifts within
//!   seconds, not a measurement to calibrate against (the pose is kept in
//!   the body for whoever wants it). `error` is read (checked as a number) and
//!   not kept. The bodies of `6d` and `6di` are merged, `6d` first; an id
//!   listed by both keeps its `6d` pose;
//! - other records (`3d`, `6dcov`, `6df`, `6df2`, `6dmt`, `6dmt2`, `6dmtr`,
//!   `6dj`, `gl`, `glcal`, `st`, ...) are legitimate outputs we do not use:
//!   they are skipped without error, whatever they contain.
//!
//! Tolerance. As the SDK: a record is read for the values we need and what
//! follows them is ignored (`fr 1 2`, `ts 1.5 x`, values after the ninth of
//! a rotation block, text after the last body); the blocks of a body record
//! are found by their `[`, text between blocks is ignored; a body count
//! smaller than the bodies present reads the count, the bodies after it are
//! not read; the first NUL byte ends the datagram (the SDK reads the buffer
//! as a C string): what follows it (padding, the rest of an older datagram
//! in a reused buffer) is ignored, text or not. More tolerant than the SDK,
//! which rejects the whole datagram there: a body count larger than the
//! bodies present reads the complete bodies present (a body missing blocks
//! at the end of the line, or whose last block has no `]`, is left out as
//! cut off). Unlike the SDK, where a later line overwrites an earlier one,
//! a repeated record keeps its first line and later ones are ignored
//! unread: the first is where DTrack writes its records, and a stray repeat
//! then cannot change a frame, nor drop it.
//!
//! A value we read that is malformed is an error that names the line
//! (1-based) and the field, e.g. `6d body 2: qu`, and the datagram is
//! skipped: a frame is not built from damaged values.

use std::fmt::{self, Write as _};

/// One 6DOF body of a `6d` (or `6di`) record.
#[derive(Clone, Debug, PartialEq)]
pub struct BodyPose {
    /// Body id as DTrack numbers it (from 0).
    pub id: u32,
    /// Position of the body origin in the room frame (mm).
    pub position_mm: [f64; 3],
    /// Rotation body -> room, `rotation[row][col]` (the paper's eq. 1:
    /// `x_room = R x_body + s`), as the tracker gives it (not checked to be
    /// a rotation). Always given by a `6d`/`6di` record; `None` from a
    /// source that has a position only (a replayed session without
    /// orientation columns).
    pub rotation: Option<[[f64; 3]; 3]>,
    /// DTrack's quality value; negative means not visible.
    pub quality: f64,
}

impl BodyPose {
    /// A body seen at `position_mm` with the identity rotation and quality 1.
    pub fn at(id: u32, position_mm: [f64; 3]) -> Self {
        BodyPose {
            id,
            position_mm,
            rotation: Some(IDENTITY),
            quality: 1.0,
        }
    }

    /// A body seen at `position_mm`, its rotation unknown, quality 1.
    pub fn position_only(id: u32, position_mm: [f64; 3]) -> Self {
        BodyPose {
            rotation: None,
            ..BodyPose::at(id, position_mm)
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
    /// `6d` then `6di`: the bodies listed (tracked ones; may include
    /// negative quality), an id given by both once, with its `6d` pose.
    /// Empty if neither record is present or they list no body.
    pub bodies: Vec<BodyPose>,
    /// True if a `6d` or a `6di` record was present.
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
    #[error("{found} values in the block, at least {expected} expected")]
    BlockLength { expected: usize, found: usize },
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

/// The contents of the `[...]` blocks of `rest`, at most `max`, each found
/// by its `[` (text between blocks is ignored). A last `[` without its `]`
/// ends the list: a truncated block is not a block.
fn blocks(rest: &str, max: usize) -> Vec<&str> {
    let mut out = Vec::new();
    let mut rest = rest;
    while out.len() < max {
        let Some(open) = rest.find('[') else { break };
        let inner = &rest[open + 1..];
        let Some(close) = inner.find(']') else { break };
        out.push(&inner[..close]);
        rest = &inner[close + 1..];
    }
    out
}

/// The first `N` numbers of one block; more values are ignored.
fn block_numbers<const N: usize>(
    line: usize,
    field: &dyn Fn() -> String,
    block: &str,
) -> Result<[f64; N], DtrackError> {
    let words: Vec<&str> = block.split_ascii_whitespace().take(N).collect();
    if words.len() < N {
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

/// The body records: standard (`6d`) and hybrid (`6di`) bodies, which
/// differ in their first block only.
#[derive(Clone, Copy)]
enum BodyRecord {
    /// `[id qu]`
    Standard,
    /// `[id st error]`
    Hybrid,
}

impl BodyRecord {
    fn name(self) -> &'static str {
        match self {
            BodyRecord::Standard => "6d",
            BodyRecord::Hybrid => "6di",
        }
    }

    /// Id and quality from the first block of a body.
    fn head(
        self,
        line: usize,
        name: &dyn Fn(&str) -> String,
        block: &str,
    ) -> Result<(u32, f64), DtrackError> {
        let (layout, expected) = match self {
            BodyRecord::Standard => ("[id qu]", 2),
            BodyRecord::Hybrid => ("[id st error]", 3),
        };
        let words: Vec<&str> = block.split_ascii_whitespace().take(expected).collect();
        if words.len() < expected {
            return Err(field_error(
                line,
                name(layout),
                FieldProblem::BlockLength {
                    expected,
                    found: words.len(),
                },
            ));
        }
        let id = parse_u32(line, &name("id"), Some(words[0]))?;
        let quality = match self {
            BodyRecord::Standard => parse_f64(line, &|| name("qu"), words[1])?,
            BodyRecord::Hybrid => {
                let state = parse_u32(line, &name("st"), Some(words[1]))?;
                parse_f64(line, &|| name("error"), words[2])?;
                // Only an optically tracked pose is a measurement: an
                // inertial-only one is dead reckoning that drifts within
                // seconds, and a calibration paired with it would learn
                // the drift.
                match state {
                    2 => 1.0,
                    _ => -1.0,
                }
            }
        };
        Ok((id, quality))
    }
}

fn parse_bodies(line: usize, record: BodyRecord, rest: &str) -> Result<Vec<BodyPose>, DtrackError> {
    let kind = record.name();
    let rest = rest.trim_start();
    let (count_text, blocks_text) = match rest.find(|c: char| c.is_ascii_whitespace() || c == '[') {
        Some(i) => (&rest[..i], &rest[i..]),
        None => (rest, ""),
    };
    let count_text = (!count_text.is_empty()).then_some(count_text);
    let declared = parse_u32(line, &format!("{kind} count"), count_text)?;
    let blocks = blocks(blocks_text, (declared as usize).saturating_mul(3));
    // A body short of blocks can only be the last: it was cut off.
    let mut bodies = Vec::with_capacity(blocks.len() / 3);
    for (n, b) in blocks.chunks_exact(3).enumerate() {
        let name = |part: &str| format!("{kind} body {}: {part}", n + 1);
        let (id, quality) = record.head(line, &name, b[0])?;
        let s: [f64; 3] = block_numbers(line, &|| name("[sx sy sz]"), b[1])?;
        let m: [f64; 9] = block_numbers(line, &|| name("[b0..b8]"), b[2])?;
        // Column-wise: b0 b1 b2 is the first column.
        let rotation = core::array::from_fn(|row| core::array::from_fn(|col| m[col * 3 + row]));
        bodies.push(BodyPose {
            id,
            position_mm: s,
            rotation: Some(rotation),
            quality,
        });
    }
    Ok(bodies)
}

/// The lines of `text`: a line ends at CR LF, at a bare LF or at a bare CR.
fn lines(text: &str) -> Vec<&str> {
    let bytes = text.as_bytes();
    let mut out = Vec::new();
    let mut start = 0;
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'\r' => {
                out.push(&text[start..i]);
                if bytes.get(i + 1) == Some(&b'\n') {
                    i += 1;
                }
                start = i + 1;
            }
            b'\n' => {
                out.push(&text[start..i]);
                start = i + 1;
            }
            _ => {}
        }
        i += 1;
    }
    out.push(&text[start..]);
    out
}

/// Parse one datagram.
pub fn parse_datagram(bytes: &[u8]) -> Result<DtrackFrame, DtrackError> {
    // The first NUL ends the datagram (see the module documentation).
    let bytes = match bytes.iter().position(|&b| b == 0) {
        Some(end) => &bytes[..end],
        None => bytes,
    };
    let text = std::str::from_utf8(bytes).map_err(|e| DtrackError::NotText {
        offset: e.valid_up_to(),
    })?;
    if text.trim().is_empty() {
        return Err(DtrackError::Empty);
    }
    let mut frame: Option<u32> = None;
    let mut ts: Option<f64> = None;
    let mut ts2: Option<f64> = None;
    let mut cal: Option<u32> = None;
    let mut six_d: Option<Vec<BodyPose>> = None;
    let mut six_di: Option<Vec<BodyPose>> = None;
    for (index, raw) in lines(text).into_iter().enumerate() {
        let line = index + 1;
        let content = raw.trim();
        if content.is_empty() {
            continue;
        }
        let (kind, rest) = match content.find(|c: char| c.is_ascii_whitespace() || c == '[') {
            Some(i) => (&content[..i], &content[i..]),
            None => (content, ""),
        };
        let first_word = || rest.split_ascii_whitespace().next();
        // A repeated record keeps its first line: later ones are not read.
        match kind {
            "fr" if frame.is_none() => frame = Some(parse_u32(line, "fr", first_word())?),
            "ts" if ts.is_none() => {
                let word =
                    first_word().ok_or_else(|| field_error(line, "ts", FieldProblem::Missing))?;
                ts = Some(parse_f64(line, &|| "ts".to_string(), word)?);
            }
            "ts2" if ts2.is_none() => ts2 = Some(parse_ts2(line, rest)?),
            "6dcal" if cal.is_none() => cal = Some(parse_u32(line, "6dcal", first_word())?),
            "6d" if six_d.is_none() => {
                six_d = Some(parse_bodies(line, BodyRecord::Standard, rest)?);
            }
            "6di" if six_di.is_none() => {
                six_di = Some(parse_bodies(line, BodyRecord::Hybrid, rest)?);
            }
            // Repeats, and 3d, 6dcov, 6df, 6df2, 6dmt, 6dmt2, 6dmtr, 6dj, gl,
            // glcal, st and any future record: output we do not consume.
            _ => {}
        }
    }
    let frame = frame.ok_or(DtrackError::MissingFrameCounter)?;
    let has_6d = six_d.is_some() || six_di.is_some();
    let mut bodies = six_d.unwrap_or_default();
    let standard = bodies.len();
    for b in six_di.unwrap_or_default() {
        if !bodies[..standard].iter().any(|s| s.id == b.id) {
            bodies.push(b);
        }
    }
    Ok(DtrackFrame {
        frame,
        ts_s: ts2.or(ts),
        calibrated_bodies: cal,
        bodies,
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
/// (`R = Rx(eta) Ry(theta) Rz(phi)`, degrees). A `6d` body always has a
/// rotation: a body without one is written with the identity.
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
            let rotation = b.rotation.unwrap_or(IDENTITY);
            let [eta, theta, phi] = euler_deg(&rotation);
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
            // Column-wise: b0 b1 b2 is the first column.
            for k in 0..9 {
                let sep = if k == 0 { "" } else { " " };
                let _ = write!(s, "{sep}{}", Num(rotation[k % 3][k / 3]));
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
            Some([[1.0, 4.0, 7.0], [2.0, 5.0, 8.0], [3.0, 6.0, 9.0]])
        );
    }
}
