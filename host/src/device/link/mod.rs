//! The host's side of the device link: a client for a SPIDAR controller on a
//! serial port (a real USB CDC port, or the pseudo-terminal of
//! [`crate::sim::virtual_device`]), speaking `spidar_protocol`.
//!
//! - [`Client::open`] opens the port through the `serialport` crate (it
//!   works on pseudo-terminals too: the virtual device goes through exactly
//!   this path), flushes it and says `Hello`; a device of another protocol
//!   version is refused with [`LinkError::VersionMismatch`].
//! - [`Client::request`] sends one request and waits for the reply with the
//!   same sequence number; on a timeout it sends the same frame again (same
//!   sequence number, so a late reply to the first try is taken) up to
//!   [`ClientOptions::retries`] times, then fails with [`LinkError::Timeout`].
//!   State and event frames that arrive meanwhile are queued, lost ones
//!   counted ([`SeqTracker`]), corrupt ones counted by the decoder
//!   ([`Client::rx_stats`]).
//! - [`Client::flash`] uploads a model blob in chunks with acknowledgement,
//!   retry and resume (the device's `next_offset` after `UploadBegin`,
//!   `OutOfOrder` and `ChunkAck`), commits it atomically and reads the model
//!   info back.
//! - [`Client::stream`] runs the state stream, keeping an armed device's
//!   heartbeat alive.
//! - [`StreamingClient`] (`streaming.rs`) is a client split in two: a
//!   thread of its own reads the state stream while the caller sends
//!   requests from its threads (an application's SDK calls); it joins back
//!   into a [`Client`].

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use spidar_protocol::blob::{ModelHeader, CRC32};
use spidar_protocol::{
    encode_request, DecodeStats, DeviceError, DeviceMessage, Event, FrameDecoder, FrameError,
    HelloAck, Limits, LinkStats, ModelInfo, NominalGeometry, Packet, Request, Response, SeqTracker,
    State, UploadState, MAX_CHUNK, MAX_FRAME, PROTOCOL_VERSION,
};

mod streaming;

pub use streaming::{Received, StreamingClient};

/// Stream frames kept while waiting for a reply (the oldest are dropped).
const PENDING_CAPACITY: usize = 1 << 16;

/// Why talking to a device failed. Every variant names the port.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("serial port {port}: no such port")]
    PortMissing { port: String },
    #[error("serial port {port}: busy (another program has it open)")]
    PortBusy { port: String },
    #[error("serial port {port}: cannot open: {message}")]
    Open { port: String, message: String },
    #[error("serial port {port}: the device did not answer `{request}` ({attempts} tries, {timeout_ms} ms each)")]
    Timeout {
        port: String,
        request: &'static str,
        attempts: u32,
        timeout_ms: u64,
    },
    #[error(
        "serial port {port}: the device's state stream stopped: no frame for {silent_ms} ms after \
         {frames} frames (unplugged, powered off or hung?)"
    )]
    StreamStopped {
        port: String,
        frames: u64,
        silent_ms: u64,
    },
    #[error(
        "serial port {port}: the device did not answer `UploadCommit` ({attempts} tries, \
         {timeout_ms} ms each) after the whole model was sent: the commit may have taken effect; \
         `spidar device info` shows the model the device runs (its id and CRC), and flashing \
         again is safe"
    )]
    CommitUnanswered {
        port: String,
        attempts: u32,
        timeout_ms: u64,
    },
    #[error("serial port {port}: protocol version mismatch: the device speaks {device}, this host speaks {host}")]
    VersionMismatch {
        port: String,
        device: u16,
        host: u16,
    },
    #[error("serial port {port}: the device refused `{request}`: {reason}")]
    Rejected {
        port: String,
        request: &'static str,
        reason: DeviceError,
    },
    #[error("serial port {port}: `{request}` got an unexpected answer: {got}")]
    Unexpected {
        port: String,
        request: &'static str,
        got: String,
    },
    #[error("model blob: {0}")]
    InvalidBlob(#[source] spidar_protocol::blob::BlobError),
    #[error("serial port {port}: read-back after the upload does not match: {what}")]
    Verify { port: String, what: String },
    #[error("serial port {port}: {action}: {source}")]
    Io {
        port: String,
        action: &'static str,
        source: std::io::Error,
    },
}

impl LinkError {
    /// The device's reason if it refused a request.
    pub fn device_error(&self) -> Option<&DeviceError> {
        match self {
            LinkError::Rejected { reason, .. } => Some(reason),
            _ => None,
        }
    }
}

/// Timeouts and retries of a [`Client`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClientOptions {
    /// How long to wait for one reply.
    pub timeout: Duration,
    /// Resends of a request whose reply did not come (0: one try only).
    pub retries: u32,
    /// Baud rate (ignored by USB CDC and pseudo-terminals).
    pub baud: u32,
    /// Largest upload chunk, bytes (the device's `max_chunk` caps it).
    pub max_chunk: usize,
}

impl Default for ClientOptions {
    fn default() -> Self {
        ClientOptions {
            timeout: Duration::from_millis(250),
            retries: 3,
            baud: 921_600,
            max_chunk: MAX_CHUNK,
        }
    }
}

impl ClientOptions {
    /// For a simulated device: it answers from a thread of this machine,
    /// and a machine busy with other work may not run it for a while; a
    /// device that is there but slow is not a lost link (1 s per try, 10
    /// tries).
    pub fn for_simulated_device() -> ClientOptions {
        ClientOptions {
            timeout: Duration::from_secs(1),
            retries: 9,
            ..ClientOptions::default()
        }
    }
}

/// Where an upload stands, for progress reports.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlashPhase {
    /// `UploadBegin` answered: `sent` is where the device resumes.
    Begin,
    /// A chunk was acknowledged: `sent` bytes are on the device.
    Upload,
    /// `UploadCommit` answered.
    Committed,
    /// `GetInfo` matched the blob.
    Verified,
}

/// One progress report of [`Client::flash`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FlashProgress {
    pub phase: FlashPhase,
    pub sent: u32,
    pub total: u32,
}

/// What [`Client::flash`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct FlashReport {
    pub model_id: u32,
    pub blob_len: u32,
    pub blob_crc32: u32,
    /// Offset the device resumed at (0 for a new upload).
    pub resumed_at: u32,
    pub chunks: u32,
    /// Chunks or requests sent again after a timeout or an out-of-order answer.
    pub resends: u32,
    /// Slot the model is active in.
    pub slot: u8,
    /// `UploadBegin` and every chunk acknowledged.
    pub upload: Duration,
    /// `UploadCommit` (read back, CRC, validation, commit record).
    pub commit: Duration,
    /// `GetInfo` read-back.
    pub verify: Duration,
}

/// Settings of [`Client::stream`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamOptions {
    /// One state frame every `decimation` loop iterations (>= 1).
    pub decimation: u16,
    /// Stop after this long (None: until the callback says stop).
    pub duration: Option<Duration>,
    /// Stop after this many state frames.
    pub max_frames: Option<u64>,
    /// Send a `Heartbeat` this often (keeps an armed device armed).
    pub heartbeat: Option<Duration>,
    /// Fail with `Timeout` when no frame came for this long.
    pub idle_timeout: Duration,
}

impl Default for StreamOptions {
    fn default() -> Self {
        StreamOptions {
            decimation: 1,
            duration: None,
            max_frames: None,
            heartbeat: Some(Duration::from_millis(5)),
            idle_timeout: Duration::from_secs(2),
        }
    }
}

/// What [`Client::stream`] received.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamReport {
    pub frames: u64,
    /// State/event frames missing from the sequence numbers.
    pub lost: u32,
    /// Frames rejected by the decoder (CRC, COBS, ...) during the stream.
    pub rejected: u32,
    /// Bytes received during the stream.
    pub bytes: u64,
    pub elapsed: Duration,
}

/// A session with one device.
pub struct Client {
    port: Box<dyn serialport::SerialPort>,
    name: String,
    options: ClientOptions,
    rx: FrameDecoder,
    seq: u16,
    hello: Option<HelloAck>,
    pending: VecDeque<Packet<DeviceMessage>>,
    events: Vec<Event>,
    stream_seq: SeqTracker,
    bytes_in: u64,
    bytes_out: u64,
}

/// Writes all of `bytes` to `port`, retrying what would block until
/// `timeout`; counts the bytes written into `bytes_out`.
fn write_port(
    port: &mut dyn serialport::SerialPort,
    bytes: &[u8],
    timeout: Duration,
    bytes_out: &mut u64,
) -> Result<(), std::io::Error> {
    let deadline = Instant::now() + timeout;
    let mut rest = bytes;
    while !rest.is_empty() {
        match port.write(rest) {
            Ok(0) => return Err(std::io::ErrorKind::WriteZero.into()),
            Ok(n) => {
                *bytes_out += n as u64;
                rest = &rest[n..];
            }
            Err(e) if is_transient(&e) && Instant::now() < deadline => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// Reads what `port` has into `buf`, waiting at most the port's timeout:
/// the number of bytes (0 when nothing came).
fn read_port(
    port: &mut dyn serialport::SerialPort,
    buf: &mut [u8],
) -> Result<usize, std::io::Error> {
    match port.read(buf) {
        Ok(n) => Ok(n),
        Err(e) if is_transient(&e) => Ok(0),
        Err(e) => Err(e),
    }
}

/// A read or write that found nothing to do yet (not a lost port).
fn is_transient(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::TimedOut
            | std::io::ErrorKind::WouldBlock
            | std::io::ErrorKind::Interrupted
    )
}

/// The device's answer to `request` on `port` as a result: an `Error`
/// response becomes [`LinkError::Rejected`] (or
/// [`LinkError::VersionMismatch`]).
fn refusal_as_error(port: &str, request: &'static str, r: Response) -> Result<Response, LinkError> {
    match r {
        Response::Error(DeviceError::VersionMismatch { device, host }) => {
            Err(LinkError::VersionMismatch {
                port: port.to_string(),
                device,
                host,
            })
        }
        Response::Error(reason) => Err(LinkError::Rejected {
            port: port.to_string(),
            request,
            reason,
        }),
        r => Ok(r),
    }
}

fn open_error(port: &str, e: serialport::Error) -> LinkError {
    match e.kind() {
        serialport::ErrorKind::NoDevice => LinkError::PortBusy {
            port: port.to_string(),
        },
        serialport::ErrorKind::Io(std::io::ErrorKind::NotFound) => LinkError::PortMissing {
            port: port.to_string(),
        },
        _ => LinkError::Open {
            port: port.to_string(),
            message: e.description,
        },
    }
}

impl Client {
    /// Opens `port` with the default options and says `Hello`.
    pub fn open(port: &str) -> Result<Client, LinkError> {
        Self::open_with(port, ClientOptions::default())
    }

    /// Opens `port` (exclusively) and says `Hello`.
    pub fn open_with(port: &str, options: ClientOptions) -> Result<Client, LinkError> {
        if !std::path::Path::new(port).exists() && port.starts_with('/') {
            return Err(LinkError::PortMissing {
                port: port.to_string(),
            });
        }
        let sp = serialport::new(port, options.baud)
            .timeout(Duration::from_millis(5))
            .open()
            .map_err(|e| open_error(port, e))?;
        let mut client = Client {
            port: sp,
            name: port.to_string(),
            options,
            rx: FrameDecoder::new(),
            seq: 0,
            hello: None,
            pending: VecDeque::new(),
            events: Vec::new(),
            stream_seq: SeqTracker::default(),
            bytes_in: 0,
            bytes_out: 0,
        };
        // Stale bytes from an earlier session; a lone 0x00 flushes the
        // device's decoder of any half frame.
        let _ = client.port.clear(serialport::ClearBuffer::Input);
        client.write_all(&[0], "flush")?;
        client.hello()?;
        Ok(client)
    }

    /// The port's name.
    pub fn port_name(&self) -> &str {
        &self.name
    }

    /// The options in use.
    pub fn options(&self) -> ClientOptions {
        self.options
    }

    /// Changes the timeouts and retries.
    pub fn set_options(&mut self, options: ClientOptions) {
        self.options = options;
    }

    /// The device's answer to the last `Hello`.
    pub fn device(&self) -> Option<&HelloAck> {
        self.hello.as_ref()
    }

    /// Frames the client's decoder accepted and rejected (by reason).
    pub fn rx_stats(&self) -> DecodeStats {
        self.rx.stats()
    }

    /// Stream frames received and lost (from their sequence numbers).
    pub fn stream_seq(&self) -> SeqTracker {
        self.stream_seq
    }

    /// Bytes received and sent since the port was opened.
    pub fn bytes(&self) -> (u64, u64) {
        (self.bytes_in, self.bytes_out)
    }

    /// Events received so far (drained).
    pub fn take_events(&mut self) -> Vec<Event> {
        std::mem::take(&mut self.events)
    }

    /// State frames received outside [`Client::stream`] (drained).
    pub fn take_states(&mut self) -> Vec<State> {
        self.pending
            .drain(..)
            .filter_map(|p| match p.msg {
                DeviceMessage::State(s) => Some(s),
                _ => None,
            })
            .collect()
    }

    fn io(&self, action: &'static str, source: std::io::Error) -> LinkError {
        LinkError::Io {
            port: self.name.clone(),
            action,
            source,
        }
    }

    fn write_all(&mut self, bytes: &[u8], action: &'static str) -> Result<(), LinkError> {
        write_port(
            self.port.as_mut(),
            bytes,
            self.options.timeout,
            &mut self.bytes_out,
        )
        .map_err(|e| self.io(action, e))
    }

    /// Reads what the port has (waiting at most a few ms) and decodes it.
    /// Returns the device messages that ended in it; stream frames are
    /// counted by the sequence tracker.
    fn poll_frames(&mut self) -> Result<Vec<Packet<DeviceMessage>>, LinkError> {
        let mut buf = [0u8; 4096];
        let n = read_port(self.port.as_mut(), &mut buf).map_err(|e| self.io("read", e))?;
        self.bytes_in += n as u64;
        let mut out = Vec::new();
        let mut version = None;
        self.rx.feed_device_messages(&buf[..n], |r| match r {
            Ok(p) => out.push(p),
            Err(FrameError::VersionMismatch { peer, .. }) => version = Some(peer),
            Err(_) => {}
        });
        if let Some(device) = version {
            return Err(LinkError::VersionMismatch {
                port: self.name.clone(),
                device,
                host: PROTOCOL_VERSION,
            });
        }
        for p in &out {
            match p.msg {
                DeviceMessage::State(_) => {
                    self.stream_seq.observe(p.seq);
                }
                DeviceMessage::Event(e) => {
                    self.stream_seq.observe(p.seq);
                    self.events.push(e);
                }
                DeviceMessage::Reply(_) => {}
            }
        }
        Ok(out)
    }

    fn queue(&mut self, p: Packet<DeviceMessage>) {
        if let DeviceMessage::State(_) = p.msg {
            if self.pending.len() >= PENDING_CAPACITY {
                self.pending.pop_front();
            }
            self.pending.push_back(p);
        }
    }

    fn send_frame(&mut self, seq: u16, req: &Request<'_>) -> Result<(), LinkError> {
        let mut tx = [0u8; MAX_FRAME];
        let frame = encode_request(seq, req, &mut tx).map_err(|e| LinkError::Unexpected {
            port: self.name.clone(),
            request: req.name(),
            got: format!("request does not encode: {e}"),
        })?;
        let frame = frame.to_vec();
        self.write_all(&frame, "write")
    }

    /// Sends a request without waiting for its reply (the reply is dropped
    /// when it comes). Used for heartbeats during a stream.
    pub fn send_only(&mut self, req: &Request<'_>) -> Result<(), LinkError> {
        self.seq = self.seq.wrapping_add(1);
        self.send_frame(self.seq, req)
    }

    /// Sends `req` and returns the device's response (an `Error` response
    /// included), resending on a timeout.
    pub fn request_raw(&mut self, req: &Request<'_>) -> Result<Response, LinkError> {
        self.seq = self.seq.wrapping_add(1);
        let seq = self.seq;
        let attempts = self.options.retries.saturating_add(1);
        for _ in 0..attempts {
            self.send_frame(seq, req)?;
            let deadline = Instant::now() + self.options.timeout;
            while Instant::now() < deadline {
                let mut reply = None;
                for p in self.poll_frames()? {
                    match p.msg {
                        DeviceMessage::Reply(r) if p.seq == seq && reply.is_none() => {
                            reply = Some(r);
                        }
                        DeviceMessage::Reply(_) => {}
                        _ => self.queue(p),
                    }
                }
                if let Some(r) = reply {
                    return Ok(r);
                }
            }
        }
        Err(LinkError::Timeout {
            port: self.name.clone(),
            request: req.name(),
            attempts,
            timeout_ms: self.options.timeout.as_millis() as u64,
        })
    }

    /// Sends `req`; an `Error` response becomes [`LinkError::Rejected`] (or
    /// [`LinkError::VersionMismatch`]).
    pub fn request(&mut self, req: &Request<'_>) -> Result<Response, LinkError> {
        let r = self.request_raw(req)?;
        refusal_as_error(&self.name, req.name(), r)
    }

    fn unexpected(&self, req: &'static str, got: &Response) -> LinkError {
        LinkError::Unexpected {
            port: self.name.clone(),
            request: req,
            got: format!("{got:?}"),
        }
    }

    fn expect_ack(&mut self, req: &Request<'_>) -> Result<(), LinkError> {
        match self.request(req)? {
            Response::Ack => Ok(()),
            r => Err(self.unexpected(req.name(), &r)),
        }
    }

    /// `Hello`: opens the session; fails with `VersionMismatch` if the
    /// device speaks another protocol version.
    pub fn hello(&mut self) -> Result<HelloAck, LinkError> {
        let req = Request::Hello {
            protocol_version: PROTOCOL_VERSION,
        };
        match self.request(&req)? {
            Response::HelloAck(ack) if ack.protocol_version == PROTOCOL_VERSION => {
                self.hello = Some(ack);
                Ok(ack)
            }
            Response::HelloAck(ack) => Err(LinkError::VersionMismatch {
                port: self.name.clone(),
                device: ack.protocol_version,
                host: PROTOCOL_VERSION,
            }),
            r => Err(self.unexpected("Hello", &r)),
        }
    }

    /// `GetInfo`: the active model, if any.
    pub fn info(&mut self) -> Result<Option<ModelInfo>, LinkError> {
        match self.request(&Request::GetInfo)? {
            Response::Info(i) => Ok(i),
            r => Err(self.unexpected("GetInfo", &r)),
        }
    }

    /// `GetStats`: the device's link and loop counters.
    pub fn stats(&mut self) -> Result<LinkStats, LinkError> {
        match self.request(&Request::GetStats)? {
            Response::Stats(s) => Ok(s),
            r => Err(self.unexpected("GetStats", &r)),
        }
    }

    /// `UploadStatus`.
    pub fn upload_status(&mut self) -> Result<UploadState, LinkError> {
        match self.request(&Request::UploadStatus)? {
            Response::UploadStatus(s) => Ok(s),
            r => Err(self.unexpected("UploadStatus", &r)),
        }
    }

    pub fn heartbeat(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::Heartbeat)
    }

    pub fn arm(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::Arm)
    }

    pub fn disarm(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::Disarm)
    }

    pub fn clear_faults(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::ClearFaults)
    }

    /// `SetForceTarget` (device frame, N).
    pub fn set_force(&mut self, force_n: [f32; 3]) -> Result<(), LinkError> {
        self.expect_ack(&Request::SetForceTarget { force_n })
    }

    pub fn set_limits(&mut self, limits: Limits) -> Result<(), LinkError> {
        self.expect_ack(&Request::SetLimits(limits))
    }

    pub fn set_string_model(&mut self, model: NominalGeometry) -> Result<(), LinkError> {
        self.expect_ack(&Request::SetNominalGeometry(model))
    }

    /// `ClearModel`.
    pub fn clear_model(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::ClearModel)
    }

    fn chunk_ack(&mut self, req: &Request<'_>) -> Result<u32, LinkError> {
        match self.request(req)? {
            Response::ChunkAck { next_offset } => Ok(next_offset),
            r => Err(self.unexpected(req.name(), &r)),
        }
    }

    /// Uploads `blob` (header + body), commits it and reads the model info
    /// back. Resumes an upload of the same blob the device still has; resends
    /// a chunk whose acknowledgement was lost; follows the device's
    /// `OutOfOrder` offset. The blob's header is checked here first.
    pub fn flash(
        &mut self,
        blob: &[u8],
        mut progress: impl FnMut(FlashProgress),
    ) -> Result<FlashReport, LinkError> {
        let (header, _) =
            spidar_protocol::blob::split_blob(blob).map_err(LinkError::InvalidBlob)?;
        let header: ModelHeader = header;
        let total = u32::try_from(blob.len()).map_err(|_| {
            LinkError::InvalidBlob(spidar_protocol::blob::BlobError::Truncated {
                needed: u32::MAX,
                got: u32::MAX,
            })
        })?;
        let crc32 = CRC32.checksum(blob);
        let chunk_len = self
            .hello
            .map_or(MAX_CHUNK, |h| usize::from(h.max_chunk))
            .min(self.options.max_chunk)
            .clamp(1, MAX_CHUNK);
        let t0 = Instant::now();
        let resumed_at = self.chunk_ack(&Request::UploadBegin {
            total_len: total,
            crc32,
            model_id: header.model_id,
        })?;
        progress(FlashProgress {
            phase: FlashPhase::Begin,
            sent: resumed_at,
            total,
        });
        let (chunks, resends) = self.upload_chunks(blob, resumed_at, chunk_len, &mut progress)?;
        let upload = t0.elapsed();
        let t1 = Instant::now();
        let committed = self
            .request(&Request::UploadCommit { crc32 })
            .map_err(|e| match e {
                LinkError::Timeout {
                    port,
                    attempts,
                    timeout_ms,
                    ..
                } => LinkError::CommitUnanswered {
                    port,
                    attempts,
                    timeout_ms,
                },
                e => e,
            })?;
        let model_id = match committed {
            Response::Committed { model_id } => model_id,
            r => return Err(self.unexpected("UploadCommit", &r)),
        };
        let commit = t1.elapsed();
        progress(FlashProgress {
            phase: FlashPhase::Committed,
            sent: total,
            total,
        });
        let t2 = Instant::now();
        let info = self.info()?;
        let verify = t2.elapsed();
        let info = self.check_flashed(info, &header, crc32, model_id)?;
        progress(FlashProgress {
            phase: FlashPhase::Verified,
            sent: total,
            total,
        });
        Ok(FlashReport {
            model_id,
            blob_len: total,
            blob_crc32: crc32,
            resumed_at,
            chunks,
            resends,
            slot: info.slot,
            upload,
            commit,
            verify,
        })
    }

    /// Sends `blob` from `offset` on in chunks of `chunk_len` until the
    /// device has all of it: (chunks acknowledged, chunks resent). A chunk
    /// the device does not move past is resent, and the device's
    /// `OutOfOrder` offset followed, up to the retries.
    fn upload_chunks(
        &mut self,
        blob: &[u8],
        mut offset: u32,
        chunk_len: usize,
        progress: &mut impl FnMut(FlashProgress),
    ) -> Result<(u32, u32), LinkError> {
        let total = blob.len() as u32;
        let mut chunks = 0u32;
        let mut resends = 0u32;
        let mut stalls = 0u32;
        while offset < total {
            let start = offset as usize;
            let end = (start + chunk_len).min(blob.len());
            let req = Request::UploadChunk {
                offset,
                data: &blob[start..end],
            };
            match self.request(&req) {
                Ok(Response::ChunkAck { next_offset }) => {
                    if next_offset <= offset {
                        stalls += 1;
                        resends += 1;
                        if stalls > self.options.retries + 1 {
                            return Err(LinkError::Unexpected {
                                port: self.name.clone(),
                                request: "UploadChunk",
                                got: format!("the device stays at offset {next_offset}"),
                            });
                        }
                    } else {
                        stalls = 0;
                    }
                    offset = next_offset.min(total);
                    chunks += 1;
                    progress(FlashProgress {
                        phase: FlashPhase::Upload,
                        sent: offset,
                        total,
                    });
                }
                Ok(r) => return Err(self.unexpected("UploadChunk", &r)),
                Err(LinkError::Rejected {
                    reason: DeviceError::OutOfOrder { expected_offset },
                    ..
                }) if expected_offset < total && stalls <= self.options.retries => {
                    stalls += 1;
                    resends += 1;
                    offset = expected_offset;
                }
                Err(e) => return Err(e),
            }
        }
        Ok((chunks, resends))
    }

    /// The model info read back after a commit, when it is the uploaded
    /// blob's (`header`, `crc32`, committed as `model_id`).
    fn check_flashed(
        &self,
        info: Option<ModelInfo>,
        header: &ModelHeader,
        crc32: u32,
        model_id: u32,
    ) -> Result<ModelInfo, LinkError> {
        let Some(info) = info else {
            return Err(LinkError::Verify {
                port: self.name.clone(),
                what: "the device reports no active model after the commit".into(),
            });
        };
        if info.header != *header || info.blob_crc32 != crc32 || model_id != header.model_id {
            return Err(LinkError::Verify {
                port: self.name.clone(),
                what: format!(
                    "device has model {:#010x} (blob CRC {:#010x}), uploaded {:#010x} (blob CRC {:#010x})",
                    info.header.model_id, info.blob_crc32, header.model_id, crc32
                ),
            });
        }
        Ok(info)
    }

    /// Runs the state stream: `StreamOn{decimation}`, then `on_state` for
    /// each state frame until it returns `false` or a limit of `options` is
    /// reached, then `StreamOff`. Sends heartbeats as `options` says.
    pub fn stream(
        &mut self,
        options: StreamOptions,
        mut on_state: impl FnMut(&State) -> bool,
    ) -> Result<StreamReport, LinkError> {
        let lost0 = self.stream_seq.lost;
        let rejected0 = self.rx.stats().rejected();
        let bytes0 = self.bytes_in;
        self.pending.clear();
        self.expect_ack(&Request::StreamOn {
            decimation: options.decimation.max(1),
        })?;
        let t0 = Instant::now();
        let mut last_frame = Instant::now();
        let mut last_heartbeat = Instant::now();
        let mut frames = 0u64;
        let mut go = true;
        let mut result = Ok(());
        while go {
            while let Some(p) = self.pending.pop_front() {
                if let DeviceMessage::State(s) = p.msg {
                    frames += 1;
                    if !on_state(&s) || options.max_frames.is_some_and(|m| frames >= m) {
                        go = false;
                        break;
                    }
                }
            }
            if !go || options.duration.is_some_and(|d| t0.elapsed() >= d) {
                break;
            }
            if let Some(every) = options.heartbeat {
                if last_heartbeat.elapsed() >= every {
                    self.send_only(&Request::Heartbeat)?;
                    last_heartbeat = Instant::now();
                }
            }
            let got = self.poll_frames()?;
            if got.is_empty() {
                if last_frame.elapsed() > options.idle_timeout {
                    result = Err(LinkError::StreamStopped {
                        port: self.name.clone(),
                        frames,
                        silent_ms: options.idle_timeout.as_millis() as u64,
                    });
                    break;
                }
            } else {
                last_frame = Instant::now();
            }
            for p in got {
                self.queue(p);
            }
        }
        let elapsed = t0.elapsed();
        let off = self.expect_ack(&Request::StreamOff);
        self.pending.clear();
        result?;
        off?;
        Ok(StreamReport {
            frames,
            lost: self.stream_seq.lost.wrapping_sub(lost0),
            rejected: self.rx.stats().rejected().wrapping_sub(rejected0),
            bytes: self.bytes_in - bytes0,
            elapsed,
        })
    }

    /// `Home`: the end-effector is at the calibration's home point now (the
    /// encoder readings become every string's zero). The device drops its
    /// target to idle and sends `Event::Homed`.
    pub fn home(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::Home)
    }

    /// `StreamOn` for the polling procedures ([`Client::poll_states`]): state
    /// frames queue up on the host as they come, between and during requests.
    pub fn stream_on(&mut self, decimation: u16) -> Result<(), LinkError> {
        self.pending.clear();
        self.expect_ack(&Request::StreamOn {
            decimation: decimation.max(1),
        })
    }

    /// `StreamOff`; drops the state frames not taken yet.
    pub fn stream_off(&mut self) -> Result<(), LinkError> {
        let r = self.expect_ack(&Request::StreamOff);
        self.pending.clear();
        r
    }

    /// The state frames that came since the last call (queued during
    /// requests, and what the port holds now), oldest first. Waits at most
    /// the port's read timeout for bytes; never blocks longer. Events go to
    /// [`Client::take_events`]; lost frames are counted in
    /// [`Client::stream_seq`].
    pub fn poll_states(&mut self) -> Result<Vec<State>, LinkError> {
        for p in self.poll_frames()? {
            self.queue(p);
        }
        Ok(self.take_states())
    }

    /// Writes raw bytes to the port (tests: corrupt frames, cut frames).
    pub fn write_raw(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.write_all(bytes, "write")
    }
}
