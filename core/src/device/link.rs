//! The device's side of the byte stream ([`DeviceLink`]): request frames
//! in, each answered through [`Device::handle`](super::Device::handle),
//! reply frames out, and stream frames with their own sequence numbers.

use spidar_protocol::messages::name;
use spidar_protocol::{
    encode_device_message, DeviceError, DeviceMessage, Event, FrameDecoder, FrameError, Packet,
    Request, Response, State, MAX_FRAME,
};

use super::LinkCounters;

/// The device's side of the byte stream: decodes request frames, gets each
/// answered, encodes the reply; encodes stream frames with their own
/// sequence counter. Holds no device state, so the firmware keeps it in its
/// link task and locks the [`Device`] only for `handle`.
///
/// [`Device`]: super::Device
pub struct DeviceLink {
    rx: FrameDecoder,
    tx: [u8; MAX_FRAME],
    stream_seq: u16,
    tx_frames: u32,
}

impl Default for DeviceLink {
    fn default() -> Self {
        Self::new()
    }
}

impl DeviceLink {
    pub const fn new() -> Self {
        DeviceLink {
            rx: FrameDecoder::new(),
            tx: [0; MAX_FRAME],
            stream_seq: 0,
            tx_frames: 0,
        }
    }

    /// Drops a half-received frame (reconnect); keeps the counters.
    pub fn reset(&mut self) {
        self.rx.reset();
    }

    /// Counters of the link layer.
    pub fn counters(&self) -> LinkCounters {
        LinkCounters {
            rx: self.rx.stats(),
            tx_frames: self.tx_frames,
        }
    }

    /// Consumes `input` up to the end of the first frame in it and returns
    /// the bytes consumed (at least 1 for non-empty input) and the reply
    /// frame to send, if that frame needs one. `handle` answers a request
    /// (e.g. `device.set_link_counters(c); device.handle(req, now)`).
    ///
    /// Corrupt frames (COBS, CRC, undecodable) are counted and get no reply;
    /// a frame with an out-of-range field gets `InvalidArgument` naming it; a
    /// `Hello` of another protocol version that does not decode gets the
    /// device's `HelloAck` (through `handle`).
    pub fn push(
        &mut self,
        input: &[u8],
        handle: impl FnOnce(&Request<'_>, LinkCounters) -> Response,
    ) -> (usize, Option<&[u8]>) {
        let mut counters = self.counters();
        let (used, result) = self.rx.push::<Request<'_>>(input);
        let Some(result) = result else {
            return (used, None);
        };
        let (seq, response) = match result {
            Ok(Packet { seq, msg }) => {
                counters.rx.ok = counters.rx.ok.wrapping_add(1);
                (seq, handle(&msg, counters))
            }
            Err(FrameError::Invalid { field, seq }) => (
                seq,
                Response::Error(DeviceError::InvalidArgument { field: name(field) }),
            ),
            Err(FrameError::VersionMismatch { peer, seq, .. }) => (
                seq,
                handle(
                    &Request::Hello {
                        protocol_version: peer,
                    },
                    counters,
                ),
            ),
            Err(_) => return (used, None),
        };
        match encode_device_message(seq, &DeviceMessage::Reply(response), &mut self.tx) {
            Ok(frame) => {
                self.tx_frames = self.tx_frames.wrapping_add(1);
                (used, Some(frame))
            }
            Err(_) => (used, None),
        }
    }

    fn stream_frame(&mut self, msg: &DeviceMessage) -> Option<&[u8]> {
        let seq = self.stream_seq;
        let frame = encode_device_message(seq, msg, &mut self.tx).ok()?;
        self.stream_seq = seq.wrapping_add(1);
        self.tx_frames = self.tx_frames.wrapping_add(1);
        Some(frame)
    }

    /// A state frame, with the next stream sequence number.
    pub fn encode_state(&mut self, state: &State) -> Option<&[u8]> {
        self.stream_frame(&DeviceMessage::State(*state))
    }

    /// An event frame, with the next stream sequence number.
    pub fn encode_event(&mut self, event: &Event) -> Option<&[u8]> {
        self.stream_frame(&DeviceMessage::Event(*event))
    }
}
