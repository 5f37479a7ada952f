//! Optical-tracker input: what calibration pairs with the device's state.
//!
//! - [`dtrack`]: the A.R.T. DTrack2/DTrack3 ASCII datagram (parse and format);
//! - [`receiver`]: a UDP receiver of those datagrams that puts frames back in
//!   order, drops duplicates and counts lost, reordered and bad datagrams;
//! - [`replay`]: the tracker columns of a session CSV played back as frames;
//! - a simulated DTrack sender on loopback (tests, demos) is
//!   [`crate::sim::tracker`];
//! - [`sync`]: the time shift (and drift) between the tracker and device
//!   streams, with its uncertainty.
//!
//! Live and replayed input share [`TrackerSource`]: consumers (guided
//! initialization, lattice collection, runtime recalibration) ask for the
//! next [`TrackerFrame`] with a timeout and get [`Next::Frame`],
//! [`Next::Timeout`] or [`Next::End`]. Frames come in frame-counter order,
//! once each; an occluded marker is a frame with `body: None`, so the
//! consumer sees occlusion as such, not as silence.

pub mod clock;
pub mod dtrack;
pub mod receiver;
pub mod replay;
pub mod sync;

use std::io;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

pub use clock::{ClockSync, HostClock, StateHistory};
pub use dtrack::{BodyPose, DtrackError, DtrackFrame};
pub use receiver::{DtrackReceiver, ReadProgress, ReceiverConfig, ReceiverStats};
pub use replay::{Pacing, ReplaySource};
pub use sync::{estimate_time_shift, ShiftConfig, SyncError, TimeShift, TimedPosition};

/// One tracker measurement of the end-effector's marker body.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackerFrame {
    /// Frame counter (DTrack `fr`; row index for a replayed session).
    pub frame: u32,
    /// Tracker time of the measurement (s). DTrack `ts`, or `ts2` as its
    /// time of day (seconds since 00:00 UTC, unwrapped across midnight by
    /// the receiver); `t_s` of the session for a replay.
    pub ts_s: f64,
    /// Host time the frame reached us (the datagram's arrival; the moment
    /// it was played for a replay).
    pub received_at: Instant,
    /// The marker body; `None` while it is occluded.
    pub body: Option<BodyPose>,
}

/// What a [`TrackerSource`] has next.
#[derive(Clone, Debug, PartialEq)]
pub enum Next {
    Frame(TrackerFrame),
    /// Nothing within the timeout; ask again.
    Timeout,
    /// The source has no more frames (a replay at its end).
    End,
}

/// Counters common to every source.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SourceStats {
    /// Frames handed out.
    pub delivered: u64,
    /// Of those, frames with the body occluded.
    pub occluded: u64,
    /// Frames never delivered: gaps in the frame counter.
    pub lost: u64,
    /// Frames that arrived after a later one and were put back in order.
    pub out_of_order: u64,
    /// Frames received again after the first copy.
    pub duplicates: u64,
    /// Frames that arrived after their slot was given up (counted lost too).
    pub late: u64,
    /// Datagrams that could not be parsed (skipped).
    pub malformed: u64,
    /// Times the frame counter jumped back far enough to mean a restart.
    pub restarts: u64,
}

/// A stream of tracker frames: live (UDP) or replayed.
pub trait TrackerSource {
    /// The next frame in frame-counter order, waiting at most `timeout`.
    fn next_frame(&mut self, timeout: Duration) -> Result<Next, TrackerError>;
    /// Counters so far.
    fn stats(&self) -> SourceStats;
    /// The procedure is busy (computing, flashing) and reads no frame
    /// until its next [`TrackerSource::next_frame`]. A real tracker goes on
    /// and its frames queue; a simulated world in step with the procedure
    /// waits for it, so that how long the machine takes to compute plays
    /// no part in what is simulated.
    fn busy(&mut self) {}
}

/// Failures of a tracker source (bad datagrams are counted, not returned).
#[derive(Debug, thiserror::Error)]
pub enum TrackerError {
    #[error("{action} {addr}: {source}")]
    Socket {
        action: &'static str,
        addr: SocketAddr,
        source: io::Error,
    },
    #[error("{0}")]
    Dataset(#[from] crate::data::dataset::DatasetError),
    #[error("simulated sender: target {0} is not a loopback address")]
    NotLoopback(SocketAddr),
    #[error("configuration field {0}")]
    Config(#[from] crate::ConfigError),
    #[error("simulated sender thread panicked")]
    SenderPanicked,
}

/// Pull frames from `source` until `count` frames, its end, or `deadline`
/// after the call, whichever comes first (a bounded loop for tools and tests).
pub fn collect(
    source: &mut dyn TrackerSource,
    count: usize,
    deadline: Duration,
) -> Result<Vec<TrackerFrame>, TrackerError> {
    let start = Instant::now();
    let mut out = Vec::new();
    while out.len() < count {
        let Some(left) = deadline.checked_sub(start.elapsed()) else {
            break;
        };
        match source.next_frame(left.min(Duration::from_millis(50)))? {
            Next::Frame(f) => out.push(f),
            Next::Timeout => {}
            Next::End => break,
        }
    }
    Ok(out)
}
