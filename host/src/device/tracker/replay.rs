//! The tracker columns of a session CSV played back as tracker frames.
//!
//! Reads through the project's one reader, [`Session::load`]. Row `i` (from
//! 0, header excluded) becomes frame `i` with `ts_s = t_s`; a row with empty
//! `ots_*` columns becomes `body: None`. A row's orientation (`ots_q*`,
//! when the session has one) is played back as the body's rotation (the
//! quaternion's matrix, [`crate::data::observe::rotation_of_quaternion`]); a row
//! without one gives a body whose rotation is unknown (`rotation: None`),
//! not the identity. The CSV has no quality: replayed poses have quality 1.

use std::path::Path;
use std::time::{Duration, Instant};

use crate::data::dataset::{Sample, Session};
use crate::data::observe::rotation_of_quaternion;

use super::dtrack::BodyPose;
use super::{Next, SourceStats, TrackerError, TrackerFrame, TrackerSource};

/// How fast a replay runs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Pacing {
    /// Every frame at once.
    AsFastAsPossible,
    /// Frames at their recorded spacing divided by `speed` (1 = real time).
    RealTime { speed: f64 },
}

/// One replayed row: its time, and the body's position and rotation.
type Row = (f64, Option<([f64; 3], Option<[[f64; 3]; 3]>)>);

fn row_of(s: &Sample) -> Row {
    let pose = s
        .tracker
        .map(|p| (p, s.orientation.map(rotation_of_quaternion)));
    (s.t_s, pose)
}

/// A session's tracker columns as a [`TrackerSource`].
#[derive(Clone, Debug)]
pub struct ReplaySource {
    rows: Vec<Row>,
    next: usize,
    pacing: Pacing,
    body_id: u32,
    started: Option<Instant>,
    stats: SourceStats,
}

impl ReplaySource {
    /// Load a session CSV.
    pub fn load(path: impl AsRef<Path>, pacing: Pacing) -> Result<Self, TrackerError> {
        let session = Session::load(path)?;
        Self::from_session(&session, pacing)
    }

    /// Replay a session already read; poses get body id 0.
    pub fn from_session(session: &Session, pacing: Pacing) -> Result<Self, TrackerError> {
        if let Pacing::RealTime { speed } = pacing {
            if !(speed.is_finite() && speed > 0.0) {
                return Err(TrackerError::Config(crate::ConfigError::new(
                    "pacing.speed",
                    format!("{speed} is not a positive speed"),
                )));
            }
        }
        if u32::try_from(session.samples.len()).is_err() {
            return Err(TrackerError::Config(crate::ConfigError::new(
                "session",
                "more rows than a frame counter can number",
            )));
        }
        Ok(ReplaySource {
            rows: session.samples.iter().map(row_of).collect(),
            next: 0,
            pacing,
            body_id: 0,
            started: None,
            stats: SourceStats::default(),
        })
    }

    /// Number of frames in the replay.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Start over from the first frame.
    pub fn rewind(&mut self) {
        self.next = 0;
        self.started = None;
        self.stats = SourceStats::default();
    }

    fn emit(&mut self, now: Instant) -> Next {
        let i = self.next;
        let Some(&(t, pose)) = self.rows.get(i) else {
            return Next::End;
        };
        self.next += 1;
        self.stats.delivered += 1;
        if pose.is_none() {
            self.stats.occluded += 1;
        }
        Next::Frame(TrackerFrame {
            // Checked at construction: the row count fits in u32.
            frame: u32::try_from(i).unwrap_or(u32::MAX),
            ts_s: t,
            received_at: now,
            body: pose.map(|(p, rotation)| BodyPose {
                rotation,
                ..BodyPose::position_only(self.body_id, p)
            }),
        })
    }
}

impl TrackerSource for ReplaySource {
    fn next_frame(&mut self, timeout: Duration) -> Result<Next, TrackerError> {
        let now = Instant::now();
        let speed = match self.pacing {
            Pacing::AsFastAsPossible => return Ok(self.emit(now)),
            Pacing::RealTime { speed } => speed,
        };
        let (Some(&(t0, _)), Some(&(t, _))) = (self.rows.first(), self.rows.get(self.next)) else {
            return Ok(Next::End);
        };
        let start = *self.started.get_or_insert(now);
        // Never panics: an unrepresentable due time just means "not yet".
        let due = Duration::try_from_secs_f64(((t - t0) / speed).max(0.0))
            .ok()
            .and_then(|offset| start.checked_add(offset));
        let Some(due) = due else {
            std::thread::sleep(timeout);
            return Ok(Next::Timeout);
        };
        if due <= now {
            return Ok(self.emit(now));
        }
        let wait = due - now;
        if wait > timeout {
            std::thread::sleep(timeout);
            return Ok(Next::Timeout);
        }
        std::thread::sleep(wait);
        Ok(self.emit(Instant::now()))
    }

    fn stats(&self) -> SourceStats {
        self.stats.clone()
    }
}
