//! The bench the tests drive the device through: a host talking to it in
//! encoded frames, one ms per tick, and the calibrations, geometry and raw
//! counts they load and read.

use crate::correction::{CorrectionModel, NnModel, OutputMode, Standardization};
use crate::device::*;
use crate::kinematics::inverse_kinematics;
use crate::model::{Calibration, StringLaw};
use crate::model_store::RamFlash;
use crate::test_fixtures::{cube_anchors, cube_frame};
use spidar_protocol::blob::CRC32;
use spidar_protocol::{
    encode_request, BadState, DeviceError, DeviceMessage, FrameDecoder, Message, NominalGeometry,
    Packet, Request, Response, SeqTracker, State, MAX_FRAME,
};
use std::vec::Vec;

pub(super) const SLOT: usize = 16 * 1024;
pub(super) type Flash = RamFlash<SLOT>;
pub(super) const CPR: u32 = 4096;
pub(super) const RADIUS: f64 = 10.0;

pub(super) fn nn(hidden: usize) -> CorrectionModel {
    let s = Standardization {
        mean: [0.0, 0.0, 1500.0],
        std: [500.0; 3],
    };
    let w = |k: usize| ((k * 37 % 17) as f64 - 8.0) / 20.0;
    CorrectionModel::Nn(NnModel {
        input: s,
        output: s,
        w1: (0..hidden).map(|h| [w(h), w(h + 1), w(h + 2)]).collect(),
        b1: (0..hidden).map(|h| w(h + 3) / 4.0).collect(),
        w2: [0, 1, 2].map(|a| (0..hidden).map(|h| w(h + a + 5) / 1000.0).collect()),
        b2: [0.0; 3],
        mode: OutputMode::Residual,
    })
}

pub(super) fn calibration(correction: CorrectionModel) -> Calibration {
    Calibration {
        frame: cube_frame([0.0; 3]),
        strings: [StringLaw::polynomial(CPR, [RADIUS, 0.0, 0.0, 0.0]); STRINGS],
        effects: alloc::vec![],
        correction,
        length_scale_mm: [0.0; STRINGS],
        kinematics: Default::default(),
        home: None,
    }
}

/// Raw counters for the end-effector at `p` (device frame), counters
/// reading 1000 at home.
pub(super) fn raw_at(p: [f64; 3]) -> [u16; STRINGS] {
    let lengths = inverse_kinematics(&cube_anchors(), p);
    let home = inverse_kinematics(&cube_anchors(), [0.0; 3]);
    let mut raw = [0u16; STRINGS];
    for i in 0..STRINGS {
        let theta = (lengths[i] - home[i]) / RADIUS;
        let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
        raw[i] = (1000 + counts) as u16;
    }
    raw
}

pub(super) fn config() -> DeviceConfig {
    DeviceConfig {
        firmware_version: [0, 1, 0],
        device_id: [7; 12],
        loop_period_us: 100,
        boot_id: 0x5eed,
        control: ControlConfig::default(),
    }
}

pub(super) fn string_model() -> NominalGeometry {
    NominalGeometry {
        counts_per_rev: [CPR; STRINGS],
        pulley_radius_mm: [RADIUS as f32; STRINGS],
        anchors_mm: cube_anchors().map(|a| a.map(|v| v as f32)),
        home_mm: [0.0; 3],
        active_strings: 0xFF,
        planar: false,
    }
}

/// A host talking to a device through encoded frames, one ms per tick.
pub(super) struct Bench<'m> {
    pub(super) dev: Device<'m, Flash>,
    pub(super) link: DeviceLink,
    host_rx: FrameDecoder,
    seq: u16,
    pub(super) now_us: u64,
    pub(super) stream: Vec<Packet<DeviceMessage>>,
    pub(super) stream_seq: SeqTracker,
}

impl<'m> Bench<'m> {
    pub(super) fn new(flash: Flash, ram: &'m mut [u8], spare: &'m mut [u8]) -> Self {
        Self::new_at(flash, ram, spare, raw_at([0.0; 3]))
    }

    /// Boots with the encoders reading `raw`.
    pub(super) fn new_at(
        flash: Flash,
        ram: &'m mut [u8],
        spare: &'m mut [u8],
        raw: [u16; STRINGS],
    ) -> Self {
        Bench {
            dev: Device::new(config(), flash, ram, spare, raw, 0).unwrap(),
            link: DeviceLink::new(),
            host_rx: FrameDecoder::new(),
            seq: 0,
            now_us: 0,
            stream: Vec::new(),
            stream_seq: SeqTracker::default(),
        }
    }

    /// Feeds bytes to the device; returns the replies.
    pub(super) fn feed(&mut self, bytes: &[u8]) -> Vec<Packet<DeviceMessage>> {
        let mut replies = Vec::new();
        let mut rest = bytes;
        while !rest.is_empty() {
            let dev = &mut self.dev;
            let now = self.now_us;
            let (used, reply) = self.link.push(rest, |req, c| {
                dev.set_link_counters(c);
                dev.handle(req, now)
            });
            if let Some(r) = reply {
                let r = r.to_vec();
                self.host_rx
                    .feed_device_messages(&r, |p| replies.push(p.expect("reply decodes")));
            }
            rest = &rest[used..];
        }
        replies
    }

    pub(super) fn request(&mut self, req: &Request<'_>) -> Response {
        self.seq = self.seq.wrapping_add(1);
        let mut buf = [0u8; MAX_FRAME];
        let frame = encode_request(self.seq, req, &mut buf).unwrap().to_vec();
        let mut replies = self.feed(&frame);
        assert_eq!(replies.len(), 1, "one reply to {req:?}");
        let p = replies.remove(0);
        assert_eq!(p.seq, self.seq);
        match p.msg {
            DeviceMessage::Reply(r) => r,
            other => panic!("not a reply: {other:?}"),
        }
    }

    pub(super) fn tick_at(&mut self, raw: [u16; STRINGS]) -> LoopOutput {
        self.now_us += 1000;
        let out = self.dev.tick(&TickInput {
            raw_counts: raw,
            now_us: self.now_us,
            estop: false,
        });
        self.dev.record_loop_time(40);
        let mut frames = Vec::new();
        while let Some(e) = self.dev.take_event() {
            frames.push(self.link.encode_event(&e).unwrap().to_vec());
        }
        if let Some(s) = self.dev.state_frame() {
            frames.push(self.link.encode_state(&s).unwrap().to_vec());
        }
        for f in frames {
            let stream = &mut self.stream;
            let tracker = &mut self.stream_seq;
            self.host_rx.feed_device_messages(&f, |p| {
                let p = p.expect("stream frame decodes");
                tracker.observe(p.seq);
                stream.push(p);
            });
        }
        out
    }

    pub(super) fn upload(&mut self, blob: &[u8], model_id: u32, chunk: usize) -> Response {
        let crc = CRC32.checksum(blob);
        let r = self.request(&Request::UploadBegin {
            total_len: blob.len() as u32,
            crc32: crc,
            model_id,
        });
        let Response::ChunkAck { mut next_offset } = r else {
            return r;
        };
        while (next_offset as usize) < blob.len() {
            let end = (next_offset as usize + chunk).min(blob.len());
            match self.request(&Request::UploadChunk {
                offset: next_offset,
                data: &blob[next_offset as usize..end],
            }) {
                Response::ChunkAck { next_offset: n } => next_offset = n,
                other => return other,
            }
        }
        self.request(&Request::UploadCommit { crc32: crc })
    }

    /// The state frames streamed so far, in order.
    pub(super) fn states(&self) -> impl DoubleEndedIterator<Item = State> + '_ {
        self.stream.iter().filter_map(|p| match p.msg {
            DeviceMessage::State(s) => Some(s),
            _ => None,
        })
    }
}

pub(super) fn bad_state(s: BadState) -> Response {
    Response::Error(DeviceError::BadState(s))
}

/// A frame whose message is not checked by `validate` (to send out-of-range
/// fields the way a buggy host would).
pub(super) fn unchecked_frame<T: serde::Serialize>(seq: u16, msg: &T) -> Vec<u8> {
    let mut payload = postcard::to_allocvec(&(seq, msg)).unwrap();
    let crc = CRC32.checksum(&payload);
    payload.extend_from_slice(&crc.to_le_bytes());
    // COBS (the canonical algorithm), then the delimiter.
    let mut out = std::vec![0u8];
    let (mut code_at, mut code) = (0usize, 1u8);
    for &byte in &payload {
        if byte != 0 {
            out.push(byte);
            code += 1;
        }
        if byte == 0 || code == 0xFF {
            out[code_at] = code;
            code_at = out.len();
            out.push(0);
            code = 1;
        }
    }
    out[code_at] = code;
    out.push(0);
    out
}

/// `Hello` of a future protocol version that carries a new field.
#[derive(serde::Serialize)]
pub(super) struct FutureHello {
    pub(super) tag: u8,
    pub(super) protocol_version: u16,
    pub(super) new_field: u32,
}

impl Message for FutureHello {
    fn validate(&self) -> Result<(), &'static str> {
        Ok(())
    }
    fn peek_protocol_version(_: &[u8]) -> Option<u16> {
        None
    }
}
