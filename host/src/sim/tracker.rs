//! A simulated DTrack2 sender on loopback, for tests and demos.
//!
//! A thread formats one DTrack2 ASCII datagram per frame from a trajectory
//! (`true time -> Option<position>`, `None` = occluded) and sends it to a
//! **loopback** address (anything else is refused). It can drop, duplicate
//! and swap datagrams, and runs its tracker clock with an offset. It stops by
//! itself after `frames` frames or `max_duration`, whichever comes first, and
//! reports exactly what it sent, so a test can check a receiver's counters.
//!
//! Frame `k` (from 0) has counter `first_frame + k`, true time
//! `t = k / frame_rate_hz` and timestamp `ts = ts_start_s + t + clock_offset_s`.
//! The first and last frames are always sent, in order, so that every loss
//! lies between frames the receiver has.

use std::net::{SocketAddr, UdpSocket};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};

use crate::device::tracker::dtrack::{format_datagram, BodyPose, DtrackFrame};
use crate::device::tracker::TrackerError;

/// Settings of the simulated sender.
#[derive(Clone, Debug, PartialEq)]
pub struct SimSenderConfig {
    /// Where to send (must be a loopback address).
    pub target: SocketAddr,
    pub frame_rate_hz: f64,
    /// Number of frames to simulate.
    pub frames: u32,
    pub first_frame: u32,
    pub body_id: u32,
    /// `ts` of the frame at true time 0, before the offset.
    pub ts_start_s: f64,
    /// Added to every `ts` (the tracker clock's offset to true time).
    pub clock_offset_s: f64,
    /// Probability that a frame's datagram is not sent.
    pub loss: f64,
    /// Probability that a datagram is sent twice.
    pub duplicate: f64,
    /// Probability that a datagram is held back and sent after the next one.
    pub reorder: f64,
    /// Occluded frames: send the body with quality -1 instead of leaving it
    /// out of the `6d` record.
    pub occluded_as_negative_quality: bool,
    /// Add records the receiver must skip (`6dcal`, `3d`, `6df2`, `gl`).
    pub extra_records: bool,
    /// Pause between datagrams (zero: as fast as possible).
    pub send_interval: Duration,
    /// Stop after this long whatever is left.
    pub max_duration: Duration,
    pub seed: u64,
}

impl SimSenderConfig {
    /// 100 frames at 100 Hz to `target`, clean (no loss, no offset), 1 ms
    /// between datagrams, at most 10 s.
    pub fn new(target: SocketAddr) -> Self {
        SimSenderConfig {
            target,
            frame_rate_hz: 100.0,
            frames: 100,
            first_frame: 1,
            body_id: 0,
            ts_start_s: 0.0,
            clock_offset_s: 0.0,
            loss: 0.0,
            duplicate: 0.0,
            reorder: 0.0,
            occluded_as_negative_quality: false,
            extra_records: false,
            send_interval: Duration::from_millis(1),
            max_duration: Duration::from_secs(10),
            seed: 0,
        }
    }

    fn validate(&self) -> Result<(), TrackerError> {
        if !self.target.ip().is_loopback() {
            return Err(TrackerError::NotLoopback(self.target));
        }
        let bad = |field: &'static str, problem: String| {
            Err(TrackerError::Config(crate::ConfigError::new(
                field, problem,
            )))
        };
        if !(self.frame_rate_hz.is_finite() && self.frame_rate_hz > 0.0) {
            return bad(
                "frame_rate_hz",
                format!("{} is not a positive rate", self.frame_rate_hz),
            );
        }
        for (field, v) in [
            ("ts_start_s", self.ts_start_s),
            ("clock_offset_s", self.clock_offset_s),
        ] {
            if !v.is_finite() {
                return bad(field, format!("{v} is not finite"));
            }
        }
        for (field, p) in [
            ("loss", self.loss),
            ("duplicate", self.duplicate),
            ("reorder", self.reorder),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return bad(field, format!("{p} is not a probability"));
            }
        }
        if self.first_frame.checked_add(self.frames).is_none() {
            return bad(
                "frames",
                "first_frame + frames overflows the frame counter".into(),
            );
        }
        Ok(())
    }
}

/// What the sender did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SimReport {
    /// Frame counters in the order their datagrams were sent (with repeats).
    pub sent: Vec<u32>,
    /// Frames never sent.
    pub dropped: Vec<u32>,
    /// Frames sent with the body occluded.
    pub occluded: Vec<u32>,
    /// Frames simulated (less than asked if `max_duration` cut it short).
    pub frames: u32,
    pub stopped_early: bool,
}

impl SimReport {
    /// Frames a receiver should count lost: never sent, between the first
    /// and the last sent frame.
    pub fn expected_lost(&self) -> u64 {
        let (Some(lo), Some(hi)) = (self.sent.iter().min(), self.sent.iter().max()) else {
            return 0;
        };
        self.dropped.iter().filter(|&&f| f > *lo && f < *hi).count() as u64
    }

    /// Datagrams that repeat an earlier one.
    pub fn expected_duplicates(&self) -> u64 {
        let mut seen = std::collections::BTreeSet::new();
        self.sent.iter().filter(|f| !seen.insert(**f)).count() as u64
    }

    /// First copies sent after a higher frame.
    pub fn expected_out_of_order(&self) -> u64 {
        let mut seen = std::collections::BTreeSet::new();
        let mut highest = None;
        let mut n = 0;
        for &f in &self.sent {
            if !seen.insert(f) {
                continue;
            }
            if highest.is_some_and(|h| f < h) {
                n += 1;
            }
            highest = Some(highest.map_or(f, |h: u32| h.max(f)));
        }
        n
    }
}

/// A running simulated sender.
#[derive(Debug)]
pub struct SimSender {
    handle: JoinHandle<Result<SimReport, TrackerError>>,
}

impl SimSender {
    /// Start sending. `trajectory(t)` gives the marker position (room frame,
    /// mm) at true time `t` (s), or `None` while occluded.
    pub fn spawn<F>(config: SimSenderConfig, trajectory: F) -> Result<SimSender, TrackerError>
    where
        F: FnMut(f64) -> Option<[f64; 3]> + Send + 'static,
    {
        config.validate()?;
        let local: SocketAddr = if config.target.is_ipv4() {
            SocketAddr::from(([127, 0, 0, 1], 0))
        } else {
            SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, 0))
        };
        let socket = UdpSocket::bind(local).map_err(|source| TrackerError::Socket {
            action: "cannot bind",
            addr: local,
            source,
        })?;
        let handle = std::thread::Builder::new()
            .name("dtrack-sim".into())
            .spawn(move || run(config, socket, trajectory))
            .map_err(|source| TrackerError::Socket {
                action: "cannot start the sender thread for",
                addr: local,
                source,
            })?;
        Ok(SimSender { handle })
    }

    /// True once the sender has sent everything (or stopped).
    pub fn is_finished(&self) -> bool {
        self.handle.is_finished()
    }

    /// Wait for the sender to finish and get its report.
    pub fn join(self) -> Result<SimReport, TrackerError> {
        self.handle
            .join()
            .map_err(|_| TrackerError::SenderPanicked)?
    }
}

fn run<F>(
    config: SimSenderConfig,
    socket: UdpSocket,
    mut trajectory: F,
) -> Result<SimReport, TrackerError>
where
    F: FnMut(f64) -> Option<[f64; 3]>,
{
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let start = Instant::now();
    let mut report = SimReport::default();
    let mut held: Option<(u32, String)> = None;
    let send = |report: &mut SimReport, frame: u32, text: &str| -> Result<(), TrackerError> {
        socket
            .send_to(text.as_bytes(), config.target)
            .map_err(|source| TrackerError::Socket {
                action: "cannot send to",
                addr: config.target,
                source,
            })?;
        report.sent.push(frame);
        if !config.send_interval.is_zero() {
            std::thread::sleep(config.send_interval);
        }
        Ok(())
    };
    for k in 0..config.frames {
        if start.elapsed() > config.max_duration {
            report.stopped_early = true;
            break;
        }
        report.frames = k + 1;
        let frame = config.first_frame + k;
        let t = f64::from(k) / config.frame_rate_hz;
        let position = trajectory(t).filter(|p| p.iter().all(|v| v.is_finite()));
        let bodies = match position {
            Some(p) => vec![BodyPose::at(config.body_id, p)],
            None if config.occluded_as_negative_quality => vec![BodyPose {
                quality: -1.0,
                rotation: Some([[0.0; 3]; 3]),
                ..BodyPose::at(config.body_id, [0.0; 3])
            }],
            None => Vec::new(),
        };
        let mut text = format_datagram(&DtrackFrame {
            frame,
            ts_s: Some(config.ts_start_s + t + config.clock_offset_s),
            calibrated_bodies: Some(1).filter(|_| config.extra_records),
            bodies,
            has_6d: true,
        });
        if config.extra_records {
            text.push_str("3d 1 [7 1.000][10.0 20.0 30.0]\r\n");
            text.push_str("6df2 1 0\r\n");
            text.push_str("gl 0\r\n");
        }
        let edge = k == 0 || k + 1 == config.frames;
        if !edge && rng.random::<f64>() < config.loss {
            report.dropped.push(frame);
            continue;
        }
        if position.is_none() {
            report.occluded.push(frame);
        }
        let copies = if rng.random::<f64>() < config.duplicate {
            2
        } else {
            1
        };
        let hold = !edge && held.is_none() && rng.random::<f64>() < config.reorder;
        if hold {
            held = Some((frame, text));
            continue;
        }
        for _ in 0..copies {
            send(&mut report, frame, &text)?;
        }
        if let Some((f, t)) = held.take() {
            send(&mut report, f, &t)?;
        }
    }
    if let Some((f, t)) = held.take() {
        send(&mut report, f, &t)?;
    }
    Ok(report)
}
