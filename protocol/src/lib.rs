//! The wire protocol between a SPIDAR controller and its host, and the header
//! of the calibration-model blob it carries.
//!
//! `no_std`, no allocation. Decoding arbitrary bytes never panics (property
//! tests in `tests/`, a cargo-fuzz target in `fuzz/`).
//!
//! # Frame
//!
//! ```text
//! on the wire:  COBS( payload ++ crc32_le ) ++ 0x00
//! payload:      postcard( seq: u16 (varint, 1-3 bytes), message )
//! crc32:        blob::CRC32 (ISO-HDLC, as zlib) of the payload, 4 bytes LE
//! ```
//!
//! The host sends [`Request`]s; the device sends [`DeviceMessage`]s. Each
//! direction carries only its own type. A request's `seq` is chosen by the
//! host (incremented per request); the device's [`DeviceMessage::Reply`]
//! echoes it. [`State`] and [`Event`] frames carry the device's own stream
//! counter, so the host counts lost frames ([`SeqTracker`]). A receiver
//! rejects and counts a frame whose COBS, CRC, payload or field values are
//! bad ([`FrameDecoder`], [`DecodeStats`]) and resynchronizes at the next
//! `0x00`; a sender may send a lone `0x00` first to flush the peer's decoder.
//!
//! ```
//! use spidar_protocol::*;
//!
//! // Host: encode a request into a stack buffer.
//! let mut tx = [0u8; MAX_FRAME];
//! let frame = encode_request(7, &Request::Hello { protocol_version: PROTOCOL_VERSION }, &mut tx)?;
//!
//! // Device: feed whatever the USB endpoint delivered, answer each request.
//! let mut rx: FrameDecoder = FrameDecoder::new();
//! let mut reply = [0u8; MAX_FRAME];
//! let mut reply_len = 0;
//! rx.feed_requests(frame, |r| match r {
//!     Ok(Packet { seq, msg: Request::Hello { .. } }) => {
//!         let ack = DeviceMessage::Reply(Response::HelloAck(HelloAck {
//!             protocol_version: PROTOCOL_VERSION,
//!             firmware_version: [0, 1, 0],
//!             device_id: [0; 12],
//!             capabilities: Capabilities::FORCE,
//!             max_chunk: MAX_CHUNK as u16,
//!             max_blob_len: 64 * 1024,
//!             loop_period_us: 250,
//!         }));
//!         reply_len = encode_device_message(seq, &ack, &mut reply).unwrap().len();
//!     }
//!     Ok(_) => {}
//!     Err(e) => panic!("{e}"), // a real device counts it (rx.stats()) and goes on
//! });
//!
//! // Host: decode the reply.
//! let mut host_rx: FrameDecoder = FrameDecoder::new();
//! let mut got = None;
//! host_rx.feed_device_messages(&reply[..reply_len], |r| got = Some(r));
//! let Some(Ok(Packet { seq: 7, msg: DeviceMessage::Reply(Response::HelloAck(ack)) })) = got else {
//!     panic!("no HelloAck")
//! };
//! assert_eq!(ack.protocol_version, PROTOCOL_VERSION);
//! # Ok::<(), FrameError>(())
//! ```
//!
//! # Sessions, heartbeat, safety
//!
//! The host opens with `Hello{PROTOCOL_VERSION}`; the device answers
//! `HelloAck` with its version (the layout of both is frozen across
//! versions, see [`messages`]), and refuses everything but `Hello` with
//! [`DeviceError::VersionMismatch`] while the versions differ. While armed,
//! the device needs a valid request at least every
//! [`Limits::heartbeat_timeout_ms`] (`Heartbeat` if nothing else); otherwise
//! every tension drops to [`Limits::pre_tension_n`], [`Faults::HEARTBEAT_LOST`]
//! latches and [`Event::HeartbeatLost`] is sent.
//!
//! # Model upload
//!
//! ```text
//! UploadBegin{total_len, crc32, model_id} -> ChunkAck{next_offset}   (0, or where a same upload stands)
//! UploadChunk{offset = next_offset, data} -> ChunkAck{next_offset + len}
//!   ... retry a chunk whose ack was lost: a chunk wholly before next_offset is acked again
//!   ... after a cut: UploadBegin (same arguments) or UploadStatus tells next_offset; resume there
//! UploadCommit{crc32} -> Committed{model_id} | Error(CrcMismatch | Incomplete | BlobRejected(..))
//! GetInfo             -> Info(Some(ModelInfo{slot, header, blob_crc32}))    read back and compare
//! ```
//!
//! The device stages the blob in the inactive slot and switches slots only
//! after every check passed, so a failed or interrupted upload leaves the old
//! model active.
//!
//! # Sizes (bytes, worst case: every varint at its longest)
//!
//! The test `worst_case_sizes` (in `tests/frames.rs`) builds the longest value
//! of every variant, checks its frame against [`MAX_FRAME`] and prints this
//! table (`cargo test -p spidar-protocol --test frames -- --nocapture`):
//!
//! | message | message | frame on the wire |
//! |---|---|---|
//! | `Request::UploadChunk` ([`MAX_CHUNK`] data bytes) | 264 | 274 = [`MAX_FRAME`] |
//! | `Request::SetNominalGeometry` | 183 | 192 |
//! | `Request::SetGuidanceTarget` | 21 | 30 |
//! | `Request::UploadBegin` | 16 | 25 |
//! | `Request::SetForceTarget` | 13 | 22 |
//! | `Request::SetLimits` | 12 | 21 |
//! | other requests | <= 6 | <= 15 |
//! | `DeviceMessage::State` | 152 | 161 |
//! | `Reply(Stats)` | 72 | 81 |
//! | `Reply(Info(Some))` | 46 | 55 |
//! | `Reply(HelloAck)` | 43 | 52 |
//! | `Reply(Error(..))` | <= 39 | <= 48 |
//! | other device messages | <= 23 | <= 32 |
//!
//! A frame adds to its message the `seq` varint (1-3 bytes), the CRC (4),
//! COBS (1 byte per started 254 bytes) and the `0x00` delimiter (1). A typical
//! `State` frame (test `state_frame_overhead`): `State` 114 bytes, frame 123
//! bytes, protocol overhead 9 bytes (message tag 1, seq 2, CRC 4, COBS 1,
//! delimiter 1); 10 bytes at worst.
#![cfg_attr(not(test), no_std)]
#![forbid(unsafe_code)]

pub mod blob;
pub mod frame;
pub mod messages;

pub use frame::{
    decode, encode, encode_device_message, encode_request, DecodeStats, FrameDecoder, FrameError,
    Packet, PayloadError, SeqTracker,
};
pub use messages::{
    BadState, BlobRejection, Capabilities, DeviceError, DeviceMessage, Event, Faults, HelloAck,
    Limits, LinkStats, Message, ModelInfo, Name, NominalGeometry, Request, Response, State,
    UploadState,
};

// With the `defmt` feature, the errors a firmware may log are defmt::Format,
// so it logs them without Debug2Format. Fails the build if one loses its
// derive (scripts/test builds protocol with the feature for thumbv7em).
#[cfg(feature = "defmt")]
const _: () = {
    const fn format<T: defmt::Format>() {}
    format::<blob::BlobError>();
    format::<BlobRejection>();
    format::<DeviceError>();
    format::<FrameError>();
};

/// Version of this protocol. Bumped whenever a message's layout changes.
/// Version 8: `BlobRejection::OverBudget`, a correction larger than the
/// device evaluates within its control loop's tick. Version 7: `State` names the home capture its counts are from
/// (`home_id`), so that sessions recorded under one home (a slip found in
/// one is still in the other) are told from sessions after a new one.
/// Version 6: `State` says whether the motors are on (`motors_on`): after a
/// fault they hold pre-tension with the loop disarmed, and the device
/// refuses model changes until `Disarm`, which a host reading `armed` alone
/// could not tell. Version 5: `State` carries the force the tensions render
/// (`rendered_force_n`), so that a host that asked for a force sees what the
/// device made of it. Version 4: `State` carries `since_home_us` next to `time_us` (both from
/// the loop's timer), so the host pairs tracker frames by the device's own
/// sample time. Version 3: `NominalGeometry` carries the string layout
/// (`active_strings`, `planar`); `DeviceError::NotForceClosed`;
/// `BlobRejection::TooFewStrings` and `InactiveString`.
pub const PROTOCOL_VERSION: u16 = 8;

/// Number of strings (and motors, and encoders) of the device.
pub const STRINGS: usize = 8;

/// Largest `UploadChunk::data`, bytes (a multiple of the STM32H7's 32-byte
/// flash word).
pub const MAX_CHUNK: usize = 256;

/// Longest [`Name`] on the wire, bytes.
pub const MAX_NAME: usize = 24;

/// Length of the frame CRC, bytes.
pub const CRC_LEN: usize = 4;

/// Longest postcard varint of a `u16`.
const VARINT_U16: usize = 3;
/// Longest postcard varint of a `u32`.
const VARINT_U32: usize = 5;

/// Longest postcard encoding of any message, bytes: `UploadChunk` (tag,
/// offset, length varint of `MAX_CHUNK`, data).
pub const MAX_MESSAGE: usize = 1 + VARINT_U32 + varint_len(MAX_CHUNK as u32) + MAX_CHUNK;

/// Longest frame before COBS: seq + message + CRC, bytes.
pub const MAX_PACKET: usize = VARINT_U16 + MAX_MESSAGE + CRC_LEN;

/// Longest frame on the wire, COBS overhead and `0x00` delimiter included,
/// bytes. Encoding buffers of this size always suffice, and
/// `FrameDecoder<MAX_FRAME>` accepts every valid frame.
pub const MAX_FRAME: usize = MAX_PACKET + MAX_PACKET / 254 + 1 + 1;

/// Bytes of the postcard varint of `v`.
const fn varint_len(mut v: u32) -> usize {
    let mut n = 1;
    while v >= 0x80 {
        v >>= 7;
        n += 1;
    }
    n
}

#[cfg(test)]
mod size_tests {
    use super::*;

    #[test]
    fn constants() {
        assert_eq!(varint_len(0), 1);
        assert_eq!(varint_len(127), 1);
        assert_eq!(varint_len(128), 2);
        assert_eq!(varint_len(u32::MAX), VARINT_U32);
        assert_eq!(MAX_MESSAGE, 264);
        assert_eq!(MAX_PACKET, 271);
        assert_eq!(MAX_FRAME, 274);
    }
}

#[cfg(test)]
mod error_tests {
    /// Every error of the crate is a `core::error::Error` (callers box it,
    /// chain it, or `?` it into their own).
    #[test]
    fn errors_are_errors() {
        fn error<E: core::error::Error>() {}
        error::<crate::blob::BlobError>();
        error::<crate::frame::FrameError>();
        error::<crate::frame::PayloadError>();
        error::<crate::messages::BlobRejection>();
        error::<crate::messages::DeviceError>();
    }
}
