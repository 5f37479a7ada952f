//! UDP receiver of DTrack2 ASCII datagrams.
//!
//! UDP may lose, duplicate and reorder datagrams. The receiver holds frames
//! in a small buffer keyed by the frame counter and hands them out in order:
//! a missing frame is waited for until `reorder_window` later frames have
//! arrived or the oldest waiting frame has waited `max_delay`; then it is
//! given up and counted lost. A frame arriving after that is counted `late`
//! (it stays lost). Repeated frames are counted `duplicates` and dropped.
//! A frame counter that jumps back by more than [`RESTART_GAP`] frames means
//! DTrack restarted its measurement: the buffer is flushed and counting
//! starts over (`restarts`).
//!
//! Bad datagrams never stop the receiver: they are counted (`malformed`) and
//! the last error is kept in [`ReceiverStats::last_error`].

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::dtrack::{parse_datagram, DtrackError};
use super::{Next, SourceStats, TrackerError, TrackerFrame, TrackerSource};

/// A backwards jump of the frame counter larger than this is a restart.
pub const RESTART_GAP: u32 = 1000;

/// Seconds in a day: DTrack's `ts` restarts from 0 at midnight UTC. The
/// parser gives a `ts2` (seconds since 1970) as the same time of day
/// ([`super::dtrack::DtrackFrame::ts_s`]), so one unwrap serves both.
const DAY_S: f64 = 86_400.0;

/// Receiver settings.
#[derive(Clone, Debug, PartialEq)]
pub struct ReceiverConfig {
    /// Address to bind (DTrack's "send to" port on this host).
    pub bind: SocketAddr,
    /// Id of the marker body on the end-effector (DTrack counts from 0).
    pub body_id: u32,
    /// How many later frames may arrive before a missing one is given up.
    pub reorder_window: u32,
    /// How long the oldest buffered frame may wait for a missing one.
    pub max_delay: Duration,
}

impl ReceiverConfig {
    /// Body 0, a window of 4 frames, 30 ms.
    pub fn new(bind: SocketAddr) -> Self {
        ReceiverConfig {
            bind,
            body_id: 0,
            reorder_window: 4,
            max_delay: Duration::from_millis(30),
        }
    }
}

/// Counters of a receiver.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReceiverStats {
    pub source: SourceStats,
    /// Datagrams received (good or bad).
    pub datagrams: u64,
    /// The last reason a datagram was skipped.
    pub last_error: Option<DtrackError>,
}

/// Puts frames back in frame-counter order (no I/O; the receiver feeds it).
#[derive(Debug)]
pub struct Reorder {
    window: u32,
    max_delay: Duration,
    next: Option<u32>,
    highest: Option<u32>,
    pending: BTreeMap<u32, TrackerFrame>,
    given_up: BTreeSet<u32>,
    stats: SourceStats,
}

impl Reorder {
    pub fn new(window: u32, max_delay: Duration) -> Self {
        Reorder {
            window,
            max_delay,
            next: None,
            highest: None,
            pending: BTreeMap::new(),
            given_up: BTreeSet::new(),
            stats: SourceStats::default(),
        }
    }

    /// Counters so far (`malformed` is the caller's).
    pub fn stats(&self) -> &SourceStats {
        &self.stats
    }

    /// Take one frame as it arrives.
    pub fn push(&mut self, frame: TrackerFrame, out: &mut VecDeque<TrackerFrame>) {
        let f = frame.frame;
        if self.highest.is_some_and(|h| h > f && h - f > RESTART_GAP) {
            // DTrack restarted its frame counter: what is buffered belongs
            // to the old run and goes out first.
            self.flush(out);
            self.next = None;
            self.highest = None;
            self.given_up.clear();
            self.stats.restarts += 1;
        }
        if let Some(next) = self.next {
            if f < next {
                if self.given_up.remove(&f) {
                    self.stats.late += 1;
                    return;
                } else {
                    self.stats.duplicates += 1;
                    return;
                }
            }
        }
        if self.pending.contains_key(&f) {
            self.stats.duplicates += 1;
            return;
        }
        if self.highest.is_some_and(|h| f < h) {
            self.stats.out_of_order += 1;
        }
        self.highest = Some(self.highest.map_or(f, |h| h.max(f)));
        self.pending.insert(f, frame);
    }

    /// Hand out what is in order, giving up gaps that waited long enough.
    pub fn release(&mut self, now: Instant, out: &mut VecDeque<TrackerFrame>) {
        self.release_inner(now, false, out);
    }

    /// Hand out everything buffered (end of input), counting the gaps lost.
    pub fn flush(&mut self, out: &mut VecDeque<TrackerFrame>) {
        self.release_inner(Instant::now(), true, out);
    }

    /// When the oldest buffered frame's wait ends, if anything is buffered.
    pub fn deadline(&self) -> Option<Instant> {
        self.pending
            .values()
            .map(|f| f.received_at)
            .min()
            .map(|t| t + self.max_delay)
    }

    fn release_inner(&mut self, now: Instant, all: bool, out: &mut VecDeque<TrackerFrame>) {
        while let Some((&first, _)) = self.pending.first_key_value() {
            let expected = match self.next {
                Some(n) => n,
                None => {
                    // Start: wait as for a gap, so that an early frame that
                    // arrives second is not taken for a duplicate.
                    if !all && !self.waited_enough(first, first, now) {
                        return;
                    }
                    first
                }
            };
            if first != expected {
                if !all && !self.waited_enough(expected, first, now) {
                    return;
                }
                let gap = first - expected;
                self.stats.lost += u64::from(gap);
                for g in expected.max(first.saturating_sub(RESTART_GAP))..first {
                    self.given_up.insert(g);
                }
            }
            if let Some(frame) = self.pending.remove(&first) {
                self.stats.delivered += 1;
                if frame.body.is_none() {
                    self.stats.occluded += 1;
                }
                out.push_back(frame);
            }
            self.next = Some(first.saturating_add(1));
            if let Some(n) = self.next {
                let horizon = n.saturating_sub(RESTART_GAP);
                while self.given_up.first().is_some_and(|&g| g < horizon) {
                    self.given_up.pop_first();
                }
            }
        }
    }

    fn waited_enough(&self, expected: u32, first: u32, now: Instant) -> bool {
        let span = self.highest.unwrap_or(first).saturating_sub(expected);
        span >= self.window || self.deadline().is_some_and(|d| now >= d)
    }
}

/// Receives DTrack2 datagrams on a UDP socket; a [`TrackerSource`].
#[derive(Debug)]
pub struct DtrackReceiver {
    socket: UdpSocket,
    addr: SocketAddr,
    body_id: u32,
    reorder: Reorder,
    ready: VecDeque<TrackerFrame>,
    buf: Vec<u8>,
    datagrams: u64,
    malformed: u64,
    last_error: Option<DtrackError>,
    day_offset_s: f64,
    last_ts_s: Option<f64>,
    progress: ReadProgress,
}

/// How far the procedure reading a [`DtrackReceiver`] has got, shared with
/// a simulated tracker in step with it (see
/// [`crate::sim::operator::SimOperator::spawn_in_step`]): the frames it
/// has taken, and whether it said it is busy and reads nothing for a while
/// ([`TrackerSource::busy`]). Clones share the counters.
#[derive(Clone, Debug, Default)]
pub struct ReadProgress {
    taken: Arc<AtomicU64>,
    busy: Arc<AtomicBool>,
}

impl ReadProgress {
    /// Frames handed out by [`TrackerSource::next_frame`] so far.
    pub fn taken(&self) -> u64 {
        self.taken.load(Ordering::SeqCst)
    }

    /// The procedure has not read a frame yet, or said it is busy since its
    /// last read.
    pub fn busy(&self) -> bool {
        self.busy.load(Ordering::SeqCst)
    }
}

impl DtrackReceiver {
    /// Bind the socket.
    pub fn bind(config: ReceiverConfig) -> Result<Self, TrackerError> {
        let socket = UdpSocket::bind(config.bind).map_err(|source| TrackerError::Socket {
            action: "cannot bind",
            addr: config.bind,
            source,
        })?;
        let addr = socket.local_addr().map_err(|source| TrackerError::Socket {
            action: "cannot read the local address of",
            addr: config.bind,
            source,
        })?;
        Ok(DtrackReceiver {
            socket,
            addr,
            body_id: config.body_id,
            reorder: Reorder::new(config.reorder_window, config.max_delay),
            ready: VecDeque::new(),
            buf: vec![0; 65_536],
            datagrams: 0,
            malformed: 0,
            last_error: None,
            day_offset_s: 0.0,
            last_ts_s: None,
            // Nothing read yet: busy until the first read.
            progress: ReadProgress {
                taken: Arc::new(AtomicU64::new(0)),
                busy: Arc::new(AtomicBool::new(true)),
            },
        })
    }

    /// How far the procedure has read, shared: a simulated tracker waits
    /// on it so that the simulated world does not run ahead of the
    /// procedure that reads it.
    pub fn progress(&self) -> ReadProgress {
        self.progress.clone()
    }

    /// The bound address (the actual port when bound to port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Counters, with the datagram count and the last error.
    pub fn receiver_stats(&self) -> ReceiverStats {
        ReceiverStats {
            source: self.stats(),
            datagrams: self.datagrams,
            last_error: self.last_error.clone(),
        }
    }

    /// Every frame still buffered, in order (call when stopping).
    pub fn drain(&mut self) -> Vec<TrackerFrame> {
        self.reorder.flush(&mut self.ready);
        self.ready.drain(..).collect()
    }

    /// Take one datagram (public so that recorded datagrams can be fed in).
    pub fn accept(&mut self, bytes: &[u8], received_at: Instant) {
        self.datagrams += 1;
        let parsed = parse_datagram(bytes).and_then(|f| match f.ts_s {
            Some(ts) => Ok((f, ts)),
            None => Err(DtrackError::MissingTimestamp),
        });
        let (frame, ts) = match parsed {
            Ok(v) => v,
            Err(e) => {
                self.malformed += 1;
                self.last_error = Some(e);
                return;
            }
        };
        // Midnight UTC: ts (and ts2 as the parser gives it) restarts at 0; a drop of more than half a day is
        // a new day, not a late frame.
        if let Some(last) = self.last_ts_s {
            if ts + DAY_S / 2.0 < last {
                self.day_offset_s += DAY_S;
            }
        }
        self.last_ts_s = Some(ts);
        let body = frame.visible_body(self.body_id).cloned();
        self.reorder.push(
            TrackerFrame {
                frame: frame.frame,
                ts_s: ts + self.day_offset_s,
                received_at,
                body,
            },
            &mut self.ready,
        );
    }
}

impl TrackerSource for DtrackReceiver {
    fn next_frame(&mut self, timeout: Duration) -> Result<Next, TrackerError> {
        self.progress.busy.store(false, Ordering::SeqCst);
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(f) = self.ready.pop_front() {
                self.progress.taken.fetch_add(1, Ordering::SeqCst);
                return Ok(Next::Frame(f));
            }
            let now = Instant::now();
            self.reorder.release(now, &mut self.ready);
            if !self.ready.is_empty() {
                continue;
            }
            if now >= deadline {
                return Ok(Next::Timeout);
            }
            let mut wait = deadline - now;
            if let Some(d) = self.reorder.deadline() {
                wait = wait.min(d.saturating_duration_since(now));
            }
            // A zero read timeout is an error for std; wait at least 1 ms.
            let wait = wait.max(Duration::from_millis(1));
            self.socket
                .set_read_timeout(Some(wait))
                .map_err(|source| TrackerError::Socket {
                    action: "cannot set the read timeout of",
                    addr: self.addr,
                    source,
                })?;
            match self.socket.recv_from(&mut self.buf) {
                Ok((n, _from)) => {
                    let at = Instant::now();
                    let buf = std::mem::take(&mut self.buf);
                    self.accept(&buf[..n], at);
                    self.buf = buf;
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock
                            | io::ErrorKind::TimedOut
                            | io::ErrorKind::Interrupted
                            // Windows reports an ICMP "port unreachable" of
                            // an earlier send as a reset on the next receive.
                            | io::ErrorKind::ConnectionReset
                    ) => {}
                Err(source) => {
                    return Err(TrackerError::Socket {
                        action: "cannot receive on",
                        addr: self.addr,
                        source,
                    })
                }
            }
        }
    }

    fn stats(&self) -> SourceStats {
        SourceStats {
            malformed: self.malformed,
            ..self.reorder.stats().clone()
        }
    }

    fn busy(&mut self) {
        self.progress.busy.store(true, Ordering::SeqCst);
    }
}
