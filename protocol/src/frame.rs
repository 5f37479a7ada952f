//! Framing: `COBS(postcard(seq, message) ++ CRC-32 LE) ++ 0x00`.
//!
//! Encoding uses postcard's own flavors (a CRC-32 flavor feeding a COBS flavor
//! feeding the caller's slice), so a frame is built in one pass without an
//! intermediate buffer. Decoding does not use `postcard::accumulator::
//! CobsAccumulator`: it neither checks a CRC nor tells a COBS error from a
//! payload error, and it cannot count or name rejected frames. [`FrameDecoder`]
//! collects bytes up to a `0x00`, COBS-decodes them in place with the `cobs`
//! crate (the one postcard uses), checks the CRC, then decodes the payload
//! with postcard, borrowing from its buffer (so `UploadChunk::data` is not
//! copied).

use core::fmt;

use postcard::ser_flavors::crc::CrcModifier;
use postcard::ser_flavors::{Cobs, Slice};
use serde::{Deserialize, Serialize};

use crate::blob::CRC32;
use crate::messages::{DeviceMessage, Message, Request};
use crate::{CRC_LEN, MAX_FRAME, PROTOCOL_VERSION};

/// A decoded frame: the sequence number and the message.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Packet<T> {
    /// Host requests: chosen by the host. Replies: the request's. Stream
    /// frames (`State`, `Event`): the device's stream counter.
    pub seq: u16,
    pub msg: T,
}

/// Why a frame could not be encoded or was rejected. Each variant names the
/// stage or field that failed.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameError {
    /// Encoding: the output buffer is too small (use [`MAX_FRAME`] bytes).
    BufferTooSmall { capacity: usize },
    /// Encoding: postcard refused the message.
    Serialize,
    /// The bytes between two `0x00` are not valid COBS.
    Cobs,
    /// The decoded frame is shorter than a sequence number, a message tag and
    /// a CRC.
    TooShort { len: usize },
    /// The CRC-32 at the end of the frame does not match its contents.
    Crc { stored: u32, computed: u32 },
    /// The CRC matched but the payload does not decode as a message.
    Payload(PayloadError),
    /// The message decoded but bytes were left after it.
    TrailingBytes { extra: usize },
    /// The message decoded (or was to be encoded) but `field` is out of range
    /// (a non-finite float, a string index >= 8, an empty or overlong chunk,
    /// ...). `seq` is the frame's, so a device can answer the request with
    /// `DeviceError::InvalidArgument`.
    Invalid { field: &'static str, seq: u16 },
    /// More than the decoder's capacity arrived without a `0x00`; the bytes
    /// up to the next `0x00` are dropped.
    Overlong { limit: usize },
    /// The frame passed its CRC and starts like the peer's frozen
    /// `Hello`/`HelloAck` but names another protocol version, and the rest of
    /// the message does not decode with this version. `seq` is the frame's,
    /// so a device can still answer with its `HelloAck`.
    VersionMismatch { peer: u16, ours: u16, seq: u16 },
}

/// What postcard reported when a payload did not decode.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PayloadError {
    /// The payload ended inside a field.
    UnexpectedEnd,
    /// A varint longer than its type allows.
    BadVarint,
    /// A bool that is neither 0 nor 1.
    BadBool,
    /// An `Option` tag that is neither 0 nor 1.
    BadOption,
    /// An enum tag that is not a valid varint.
    BadEnum,
    /// A string that is not UTF-8.
    BadUtf8,
    /// A value serde refused: an unknown enum variant (message or field), a
    /// name longer than its capacity.
    BadValue,
    /// Any other postcard error.
    Other,
}

impl From<postcard::Error> for PayloadError {
    fn from(e: postcard::Error) -> Self {
        use postcard::Error as E;
        match e {
            E::DeserializeUnexpectedEnd => Self::UnexpectedEnd,
            E::DeserializeBadVarint => Self::BadVarint,
            E::DeserializeBadBool => Self::BadBool,
            E::DeserializeBadOption => Self::BadOption,
            E::DeserializeBadEnum => Self::BadEnum,
            E::DeserializeBadUtf8 | E::DeserializeBadChar => Self::BadUtf8,
            E::SerdeDeCustom => Self::BadValue,
            _ => Self::Other,
        }
    }
}

impl fmt::Display for PayloadError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::UnexpectedEnd => "the payload ended inside a field",
            Self::BadVarint => "a varint longer than its type allows",
            Self::BadBool => "a bool that is neither 0 nor 1",
            Self::BadOption => "an option tag that is neither 0 nor 1",
            Self::BadEnum => "an enum tag that is not a valid varint",
            Self::BadUtf8 => "a string that is not UTF-8",
            Self::BadValue => "a value out of its type's range (unknown variant, name too long)",
            Self::Other => "a payload postcard could not decode",
        })
    }
}

impl core::error::Error for PayloadError {}

impl fmt::Display for FrameError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::BufferTooSmall { capacity } => {
                write!(f, "frame does not fit the {capacity}-byte buffer")
            }
            Self::Serialize => write!(f, "message could not be serialized"),
            Self::Cobs => write!(f, "corrupt frame: invalid COBS encoding"),
            Self::TooShort { len } => write!(f, "corrupt frame: only {len} bytes"),
            Self::Crc { stored, computed } => write!(
                f,
                "corrupt frame: CRC mismatch (stored {stored:#010x}, computed {computed:#010x})"
            ),
            Self::Payload(e) => write!(f, "undecodable message: {e}"),
            Self::TrailingBytes { extra } => {
                write!(f, "undecodable message: {extra} bytes after it")
            }
            Self::Invalid { field, .. } => write!(f, "message field `{field}` out of range"),
            Self::Overlong { limit } => {
                write!(f, "frame longer than {limit} bytes dropped")
            }
            Self::VersionMismatch { peer, ours, .. } => write!(
                f,
                "protocol version mismatch: peer speaks {peer}, this side speaks {ours}"
            ),
        }
    }
}

impl core::error::Error for FrameError {}

/// Counters of a [`FrameDecoder`]: frames accepted, and frames rejected by
/// reason. All counters wrap.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DecodeStats {
    /// Frames decoded and accepted.
    pub ok: u32,
    /// [`FrameError::Cobs`].
    pub cobs: u32,
    /// [`FrameError::TooShort`].
    pub too_short: u32,
    /// [`FrameError::Crc`].
    pub crc: u32,
    /// [`FrameError::Payload`] and [`FrameError::TrailingBytes`].
    pub payload: u32,
    /// [`FrameError::Invalid`].
    pub invalid: u32,
    /// [`FrameError::Overlong`].
    pub overlong: u32,
    /// [`FrameError::VersionMismatch`].
    pub version: u32,
}

impl DecodeStats {
    /// Frames rejected, all reasons.
    pub fn rejected(&self) -> u32 {
        self.cobs
            .wrapping_add(self.too_short)
            .wrapping_add(self.crc)
            .wrapping_add(self.payload)
            .wrapping_add(self.invalid)
            .wrapping_add(self.overlong)
            .wrapping_add(self.version)
    }

    fn count(&mut self, r: &Result<impl Sized, FrameError>) {
        let c = match r {
            Ok(_) => &mut self.ok,
            Err(FrameError::Cobs) => &mut self.cobs,
            Err(FrameError::TooShort { .. }) => &mut self.too_short,
            Err(FrameError::Crc { .. }) => &mut self.crc,
            Err(FrameError::Payload(_) | FrameError::TrailingBytes { .. }) => &mut self.payload,
            Err(FrameError::Invalid { .. }) => &mut self.invalid,
            Err(FrameError::Overlong { .. }) => &mut self.overlong,
            Err(FrameError::VersionMismatch { .. }) => &mut self.version,
            // Encoding errors never come out of the decoder.
            Err(FrameError::BufferTooSmall { .. } | FrameError::Serialize) => return,
        };
        *c = c.wrapping_add(1);
    }
}

/// Encodes one frame of any [`Message`] into `out` and returns the bytes to
/// send, the trailing `0x00` included. The message is validated first.
pub fn encode<'b, T: Message>(
    seq: u16,
    msg: &T,
    out: &'b mut [u8],
) -> Result<&'b [u8], FrameError> {
    msg.validate()
        .map_err(|field| FrameError::Invalid { field, seq })?;
    let capacity = out.len();
    let full = |e| match e {
        postcard::Error::SerializeBufferFull => FrameError::BufferTooSmall { capacity },
        _ => FrameError::Serialize,
    };
    let cobs = Cobs::try_new(Slice::new(out)).map_err(full)?;
    let flavor = CrcModifier::new(cobs, CRC32.digest());
    let used = postcard::serialize_with_flavor(&(seq, msg), flavor).map_err(full)?;
    Ok(used)
}

/// Encodes a host request. `out` of [`MAX_FRAME`] bytes always suffices.
pub fn encode_request<'b>(
    seq: u16,
    req: &Request<'_>,
    out: &'b mut [u8],
) -> Result<&'b [u8], FrameError> {
    encode(seq, req, out)
}

/// Encodes a device message. `out` of [`MAX_FRAME`] bytes always suffices.
pub fn encode_device_message<'b>(
    seq: u16,
    msg: &DeviceMessage,
    out: &'b mut [u8],
) -> Result<&'b [u8], FrameError> {
    encode(seq, msg, out)
}

/// Decodes one whole frame in place: `frame` holds the COBS bytes, with or
/// without the trailing `0x00` (anything after a first `0x00` is ignored).
/// The result may borrow from `frame`.
pub fn decode<'a, T>(frame: &'a mut [u8]) -> Result<Packet<T>, FrameError>
where
    T: Message + Deserialize<'a>,
{
    let end = frame.iter().position(|&b| b == 0).unwrap_or(frame.len());
    let frame = &mut frame[..end];
    if frame.is_empty() {
        return Err(FrameError::TooShort { len: 0 });
    }
    let n = cobs::decode_in_place(frame).map_err(|_| FrameError::Cobs)?;
    let frame: &'a [u8] = frame;
    let decoded = frame.get(..n).ok_or(FrameError::Cobs)?;
    // Shortest frame: 1-byte seq, 1-byte message tag, CRC.
    if decoded.len() < 2 + CRC_LEN {
        return Err(FrameError::TooShort { len: decoded.len() });
    }
    let (body, crc) = decoded.split_at(decoded.len() - CRC_LEN);
    let stored = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    let computed = CRC32.checksum(body);
    if stored != computed {
        return Err(FrameError::Crc { stored, computed });
    }
    let undecodable = match postcard::take_from_bytes::<Packet<T>>(body) {
        Ok((packet, [])) => {
            packet.msg.validate().map_err(|field| FrameError::Invalid {
                field,
                seq: packet.seq,
            })?;
            return Ok(packet);
        }
        Ok((_, rest)) => FrameError::TrailingBytes { extra: rest.len() },
        Err(e) => FrameError::Payload(e.into()),
    };
    // A frame that does not decode with this version but starts like the
    // peer's frozen Hello/HelloAck of another version: say so.
    match version_after_seq::<T>(body) {
        Some((seq, peer)) if peer != PROTOCOL_VERSION => Err(FrameError::VersionMismatch {
            peer,
            ours: PROTOCOL_VERSION,
            seq,
        }),
        _ => Err(undecodable),
    }
}

/// The sequence number and the protocol version named by a frozen
/// `Hello`/`HelloAck` prefix of `body` (postcard bytes: seq, message).
fn version_after_seq<T: Message>(body: &[u8]) -> Option<(u16, u16)> {
    let (seq, rest) = postcard::take_from_bytes::<u16>(body).ok()?;
    Some((seq, T::peek_protocol_version(rest)?))
}

/// Decodes a byte stream into frames: feed it whatever the serial port gives,
/// in chunks of any size. Holds at most `N` bytes of one frame (use
/// [`MAX_FRAME`]); rejects and counts corrupt frames and resynchronizes at the
/// next `0x00`. Empty frames (consecutive `0x00`, e.g. a sender flushing the
/// line before its first frame) are ignored. Never panics, never allocates.
pub struct FrameDecoder<const N: usize = MAX_FRAME> {
    buf: [u8; N],
    len: usize,
    /// Dropping the rest of an overlong frame, up to the next `0x00`.
    skipping: bool,
    stats: DecodeStats,
}

impl<const N: usize> Default for FrameDecoder<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> FrameDecoder<N> {
    /// An empty decoder.
    pub const fn new() -> Self {
        Self {
            buf: [0; N],
            len: 0,
            skipping: false,
            stats: DecodeStats {
                ok: 0,
                cobs: 0,
                too_short: 0,
                crc: 0,
                payload: 0,
                invalid: 0,
                overlong: 0,
                version: 0,
            },
        }
    }

    /// Counters since creation.
    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    /// Bytes of an unfinished frame held.
    pub fn pending(&self) -> usize {
        self.len
    }

    /// Drops an unfinished frame (e.g. after a reconnect); keeps the counters.
    pub fn reset(&mut self) {
        self.len = 0;
        self.skipping = false;
    }

    /// Consumes bytes of `input` up to the end of the first frame that ends
    /// in it (or all of it) and returns how many were consumed and, if a
    /// frame ended, the decoded packet or why it was rejected. The count is
    /// at least 1 when `input` is not empty; call again with the rest.
    /// The packet may borrow from the decoder (`UploadChunk::data`).
    pub fn push<'d, T>(&'d mut self, input: &[u8]) -> (usize, Option<Result<Packet<T>, FrameError>>)
    where
        T: Message + Deserialize<'d>,
    {
        let zero = input.iter().position(|&b| b == 0);
        let segment = &input[..zero.unwrap_or(input.len())];
        let consumed = zero.map_or(input.len(), |z| z + 1);

        if self.skipping {
            if zero.is_some() {
                self.skipping = false;
            }
            return (consumed, None);
        }
        let room = N - self.len;
        if segment.len() > room {
            // Overlong: report it now, drop everything up to the next 0x00.
            self.len = 0;
            self.skipping = zero.is_none();
            let err: Result<Packet<T>, FrameError> = Err(FrameError::Overlong { limit: N });
            self.stats.count(&err);
            return (consumed, Some(err));
        }
        self.buf[self.len..self.len + segment.len()].copy_from_slice(segment);
        self.len += segment.len();
        if zero.is_none() {
            return (consumed, None);
        }
        let len = core::mem::replace(&mut self.len, 0);
        if len == 0 {
            return (consumed, None);
        }
        let result = decode::<T>(&mut self.buf[..len]);
        self.stats.count(&result);
        (consumed, Some(result))
    }

    /// Feeds `input` and calls `on_frame` for every frame that ends in it
    /// (device side: requests borrow the decoder's buffer for the call).
    pub fn feed_requests(
        &mut self,
        input: &[u8],
        mut on_frame: impl FnMut(Result<Packet<Request<'_>>, FrameError>),
    ) {
        let mut rest = input;
        while !rest.is_empty() {
            let (used, out) = self.push::<Request<'_>>(rest);
            rest = rest.get(used..).unwrap_or(&[]);
            if let Some(r) = out {
                on_frame(r);
            }
        }
    }

    /// Feeds `input` and calls `on_frame` for every frame that ends in it
    /// (host side).
    pub fn feed_device_messages(
        &mut self,
        input: &[u8],
        mut on_frame: impl FnMut(Result<Packet<DeviceMessage>, FrameError>),
    ) {
        let mut rest = input;
        while !rest.is_empty() {
            let (used, out) = self.push::<DeviceMessage>(rest);
            rest = rest.get(used..).unwrap_or(&[]);
            if let Some(r) = out {
                on_frame(r);
            }
        }
    }
}

/// Counts stream frames lost on the way, from the gaps in their sequence
/// numbers (host side, one tracker per stream).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SeqTracker {
    next: Option<u16>,
    /// Frames received.
    pub received: u32,
    /// Frames missing between received ones.
    pub lost: u32,
    /// Frames that arrived with a sequence number at or before the previous
    /// one (duplicates, reordering, or a device restart).
    pub stale: u32,
}

impl SeqTracker {
    /// Records a received stream frame; returns how many frames were lost
    /// just before it.
    pub fn observe(&mut self, seq: u16) -> u16 {
        self.received = self.received.wrapping_add(1);
        let gap = match self.next {
            None => 0,
            Some(next) => {
                let d = seq.wrapping_sub(next);
                if d < 0x8000 {
                    d
                } else {
                    self.stale = self.stale.wrapping_add(1);
                    0
                }
            }
        };
        self.lost = self.lost.wrapping_add(u32::from(gap));
        self.next = Some(seq.wrapping_add(1));
        gap
    }
}
