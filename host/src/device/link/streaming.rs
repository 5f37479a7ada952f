//! A [`Client`] split in two while the state stream is on: a reader thread
//! of its own takes every frame the device sends (state frames, events,
//! replies), so that the stream is read whatever the caller does, and the
//! caller sends requests from its own threads and waits for their replies.
//!
//! This is what an application's SDK needs (`capi/`): the application asks
//! for the latest state without blocking, and its own calls (a force
//! command, a heartbeat) are the only requests the device hears. The reader
//! thread never sends anything, so an application that stalls is disarmed
//! by the device's own heartbeat watchdog, as it must be.
//!
//! Requests are serialized (one in flight at a time); a reply is matched by
//! its sequence number and the same frame is resent on a timeout, as
//! [`Client::request`] does. [`StreamingClient::into_client`] stops the
//! reader and joins the two halves back into a [`Client`] (to flash a model
//! with [`Client::flash`], say).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use spidar_protocol::{
    encode_request, DeviceMessage, Event, FrameDecoder, FrameError, HelloAck, Request, Response,
    SeqTracker, State, MAX_FRAME, PROTOCOL_VERSION,
};

use super::{read_port, refusal_as_error, write_port, Client, ClientOptions, LinkError};

/// How long the reader waits for bytes before it looks whether it must
/// stop: the longest [`StreamingClient::into_client`] waits for it.
const READ_POLL: Duration = Duration::from_millis(10);

/// A state frame as the reader thread received it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Received {
    pub state: State,
    /// When the reader decoded it (host clock).
    pub at: Instant,
    /// State frames received since the stream started, this one included
    /// (1 for the first).
    pub index: u64,
}

/// What the reader thread found, shared with the callers.
#[derive(Default)]
struct Inbox {
    latest: Option<Received>,
    states: u64,
    stream_seq: SeqTracker,
    events: Vec<Event>,
    /// The sequence number a caller waits for, and its reply once it came.
    awaiting: Option<u16>,
    reply: Option<Response>,
    /// Frames the reader's decoder rejected (CRC, COBS, ...).
    rejected: u32,
    bytes_in: u64,
    /// Why the reader stopped early.
    failure: Option<Failure>,
}

/// Why the reader thread stopped before it was told to.
#[derive(Clone, Debug)]
enum Failure {
    /// The port failed (unplugged, closed).
    Read(std::io::ErrorKind, String),
    /// The device speaks another protocol version.
    Version(u16),
}

struct Shared {
    inbox: Mutex<Inbox>,
    changed: Condvar,
    stop: AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Inbox> {
        // A caller that panicked while holding the lock left a whole inbox:
        // every update of it is a single assignment or push.
        self.inbox.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The sending half: the port as the caller writes to it.
struct Writer {
    port: Box<dyn serialport::SerialPort>,
    seq: u16,
    bytes_out: u64,
}

/// A link client whose state stream is read by a thread of its own.
pub struct StreamingClient {
    name: String,
    options: ClientOptions,
    hello: Option<HelloAck>,
    writer: Mutex<Writer>,
    reader: Reader,
}

/// The reader thread and what it shares; dropping it stops the thread.
struct Reader {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<FrameDecoder>>,
}

impl Reader {
    /// Stops the thread and returns its decoder.
    fn join(&mut self) -> FrameDecoder {
        self.shared.stop.store(true, Ordering::SeqCst);
        self.thread
            .take()
            .and_then(|h| h.join().ok())
            .unwrap_or_default()
    }
}

impl Drop for Reader {
    fn drop(&mut self) {
        if self.thread.is_some() {
            let _ = self.join();
        }
    }
}

/// The reader thread: takes frames until told to stop or the port fails;
/// returns its decoder (with its counters) for the rejoined client.
fn read_frames(
    mut port: Box<dyn serialport::SerialPort>,
    mut rx: FrameDecoder,
    shared: Arc<Shared>,
) -> FrameDecoder {
    let mut buf = [0u8; 4096];
    let rejected0 = rx.stats().rejected();
    while !shared.stop.load(Ordering::SeqCst) {
        let n = match read_port(port.as_mut(), &mut buf) {
            Ok(n) => n,
            Err(source) => {
                shared.lock().failure = Some(Failure::Read(source.kind(), source.to_string()));
                shared.changed.notify_all();
                return rx;
            }
        };
        if n == 0 {
            continue;
        }
        let now = Instant::now();
        let mut inbox = shared.lock();
        inbox.bytes_in += n as u64;
        let mut version = None;
        rx.feed_device_messages(&buf[..n], |r| match r {
            Ok(p) => take(&mut inbox, p, now),
            Err(FrameError::VersionMismatch { peer, .. }) => version = Some(peer),
            Err(_) => {}
        });
        inbox.rejected = rx.stats().rejected().wrapping_sub(rejected0);
        if let Some(device) = version {
            inbox.failure = Some(Failure::Version(device));
            drop(inbox);
            shared.changed.notify_all();
            return rx;
        }
        drop(inbox);
        shared.changed.notify_all();
    }
    rx
}

/// Files one decoded frame: the newest state, an event, the awaited reply
/// (a reply nobody waits for, as to a heartbeat sent without waiting, is
/// dropped).
fn take(inbox: &mut Inbox, p: spidar_protocol::Packet<DeviceMessage>, now: Instant) {
    match p.msg {
        DeviceMessage::State(state) => {
            inbox.stream_seq.observe(p.seq);
            inbox.states += 1;
            inbox.latest = Some(Received {
                state,
                at: now,
                index: inbox.states,
            });
        }
        DeviceMessage::Event(e) => {
            inbox.stream_seq.observe(p.seq);
            inbox.events.push(e);
        }
        DeviceMessage::Reply(r) => {
            if inbox.awaiting == Some(p.seq) && inbox.reply.is_none() {
                inbox.reply = Some(r);
            }
        }
    }
}

impl StreamingClient {
    /// Splits `client`: a reader thread takes the port's input from now
    /// on, then `StreamOn { decimation }` starts the state stream.
    pub fn start(client: Client, decimation: u16) -> Result<StreamingClient, LinkError> {
        let Client {
            port,
            name,
            options,
            rx,
            seq,
            hello,
            pending: _,
            events,
            stream_seq,
            bytes_in,
            bytes_out,
        } = client;
        let mut read_half = port.try_clone().map_err(|e| LinkError::Io {
            port: name.clone(),
            action: "split the port into a reader and a writer",
            source: e.into(),
        })?;
        read_half
            .set_timeout(READ_POLL)
            .map_err(|e| LinkError::Io {
                port: name.clone(),
                action: "set the reader's timeout",
                source: e.into(),
            })?;
        let shared = Arc::new(Shared {
            inbox: Mutex::new(Inbox {
                stream_seq,
                bytes_in,
                events,
                ..Inbox::default()
            }),
            changed: Condvar::new(),
            stop: AtomicBool::new(false),
        });
        let thread_shared = shared.clone();
        let reader = std::thread::Builder::new()
            .name(format!("spidar-link-reader {name}"))
            .spawn(move || read_frames(read_half, rx, thread_shared))
            .map_err(|e| LinkError::Io {
                port: name.clone(),
                action: "start the reader thread",
                source: e,
            })?;
        let streaming = StreamingClient {
            name,
            options,
            hello,
            writer: Mutex::new(Writer {
                port,
                seq,
                bytes_out,
            }),
            reader: Reader {
                shared,
                thread: Some(reader),
            },
        };
        streaming.expect_ack(&Request::StreamOn {
            decimation: decimation.max(1),
        })?;
        Ok(streaming)
    }

    /// The port's name.
    pub fn port_name(&self) -> &str {
        &self.name
    }

    /// The device's answer to the last `Hello` before the split.
    pub fn device(&self) -> Option<&HelloAck> {
        self.hello.as_ref()
    }

    fn writer(&self) -> MutexGuard<'_, Writer> {
        self.writer.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn encode(&self, seq: u16, req: &Request<'_>) -> Result<Vec<u8>, LinkError> {
        let mut tx = [0u8; MAX_FRAME];
        encode_request(seq, req, &mut tx)
            .map(<[u8]>::to_vec)
            .map_err(|e| LinkError::Unexpected {
                port: self.name.clone(),
                request: req.name(),
                got: format!("request does not encode: {e}"),
            })
    }

    fn send(&self, w: &mut Writer, frame: &[u8]) -> Result<(), LinkError> {
        write_port(
            w.port.as_mut(),
            frame,
            self.options.timeout,
            &mut w.bytes_out,
        )
        .map_err(|source| LinkError::Io {
            port: self.name.clone(),
            action: "write",
            source,
        })
    }

    /// Waits until `take` finds in the inbox what the caller waits for
    /// (`Some`), the reader fails (its error), or `deadline` passes (`None`).
    fn wait_for<R>(
        &self,
        deadline: Instant,
        mut take: impl FnMut(&mut Inbox) -> Option<R>,
    ) -> Result<Option<R>, LinkError> {
        let mut inbox = self.reader.shared.lock();
        loop {
            if let Some(r) = take(&mut inbox) {
                return Ok(Some(r));
            }
            if let Some(e) = self.failed(&inbox) {
                return Err(e);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            inbox = self
                .reader
                .shared
                .changed
                .wait_timeout(inbox, deadline - now)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
    }

    /// The reader's failure, as an error of this call.
    fn failed(&self, inbox: &Inbox) -> Option<LinkError> {
        inbox.failure.as_ref().map(|f| match f {
            Failure::Version(device) => LinkError::VersionMismatch {
                port: self.name.clone(),
                device: *device,
                host: PROTOCOL_VERSION,
            },
            Failure::Read(kind, message) => LinkError::Io {
                port: self.name.clone(),
                action: "read",
                source: std::io::Error::new(*kind, message.clone()),
            },
        })
    }

    /// Sends `req` and returns the device's response (an `Error` response
    /// included), resending the same frame on a timeout.
    pub fn request_raw(&self, req: &Request<'_>) -> Result<Response, LinkError> {
        let mut w = self.writer();
        w.seq = w.seq.wrapping_add(1);
        let seq = w.seq;
        let frame = self.encode(seq, req)?;
        {
            let mut inbox = self.reader.shared.lock();
            inbox.awaiting = Some(seq);
            inbox.reply = None;
        }
        let attempts = self.options.retries.saturating_add(1);
        for _ in 0..attempts {
            self.send(&mut w, &frame)?;
            let deadline = Instant::now() + self.options.timeout;
            let reply = self.wait_for(deadline, |inbox| {
                let r = inbox.reply.take()?;
                inbox.awaiting = None;
                Some(r)
            })?;
            if let Some(r) = reply {
                return Ok(r);
            }
        }
        self.reader.shared.lock().awaiting = None;
        Err(LinkError::Timeout {
            port: self.name.clone(),
            request: req.name(),
            attempts,
            timeout_ms: self.options.timeout.as_millis() as u64,
        })
    }

    /// Sends `req`; an `Error` response becomes [`LinkError::Rejected`].
    pub fn request(&self, req: &Request<'_>) -> Result<Response, LinkError> {
        let r = self.request_raw(req)?;
        refusal_as_error(&self.name, req.name(), r)
    }

    /// Sends `req` and expects `Ack`.
    pub fn expect_ack(&self, req: &Request<'_>) -> Result<(), LinkError> {
        match self.request(req)? {
            Response::Ack => Ok(()),
            got => Err(LinkError::Unexpected {
                port: self.name.clone(),
                request: req.name(),
                got: format!("{got:?}"),
            }),
        }
    }

    /// The newest state frame, if any came (never waits).
    pub fn latest(&self) -> Option<Received> {
        self.reader.shared.lock().latest
    }

    /// The newest state frame, once it is newer than the `after`-th (its
    /// [`Received::index`]; 0: any), waiting at most `timeout` for that.
    /// Frames between are not returned (their count is in the index). A
    /// stream silent that long is [`LinkError::StreamStopped`].
    pub fn wait_newer(&self, after: u64, timeout: Duration) -> Result<Received, LinkError> {
        let deadline = Instant::now() + timeout;
        self.wait_for(deadline, |inbox| inbox.latest.filter(|r| r.index > after))?
            .ok_or_else(|| LinkError::StreamStopped {
                port: self.name.clone(),
                frames: after,
                silent_ms: timeout.as_millis() as u64,
            })
    }

    /// Events received so far (drained), in the order they came.
    pub fn take_events(&self) -> Vec<Event> {
        std::mem::take(&mut self.reader.shared.lock().events)
    }

    /// Stream frames received and lost (from their sequence numbers).
    pub fn stream_seq(&self) -> SeqTracker {
        self.reader.shared.lock().stream_seq
    }

    /// Frames the reader's decoder rejected since the split.
    pub fn rejected(&self) -> u32 {
        self.reader.shared.lock().rejected
    }

    /// `StreamOff`, then [`StreamingClient::into_client`].
    pub fn stop(self) -> Result<Client, LinkError> {
        self.expect_ack(&Request::StreamOff)?;
        Ok(self.into_client())
    }

    /// Stops the reader thread and joins the halves into a [`Client`] (the
    /// stream is left as it is: [`StreamingClient::stop`] turns it off
    /// first). State frames not taken are dropped; events are kept.
    pub fn into_client(mut self) -> Client {
        let rx = self.reader.join();
        let inbox = std::mem::take(&mut *self.reader.shared.lock());
        let writer = self
            .writer
            .into_inner()
            .unwrap_or_else(PoisonError::into_inner);
        Client {
            port: writer.port,
            name: self.name,
            options: self.options,
            rx,
            seq: writer.seq,
            hello: self.hello,
            pending: Default::default(),
            events: inbox.events,
            stream_seq: inbox.stream_seq,
            bytes_in: inbox.bytes_in,
            bytes_out: writer.bytes_out,
        }
    }
}
