use super::*;
use crate::blob::{compile, BlobHead};
use crate::control::LoopInput;
use crate::correction::{CorrectionModel, NnModel, OutputMode, Standardization};
use crate::kinematics::inverse_kinematics;
use crate::model::{Calibration, StringLaw};
use crate::model_store::RamFlash;
use crate::safety::SafetyFaults;
use crate::tension::TensionStatus;
use crate::test_fixtures::{cube_anchors, cube_frame};
use spidar_protocol::blob::{CorrectionKind, CRC32};
use spidar_protocol::messages::name;
use spidar_protocol::{
    encode, encode_request, BadState, BlobRejection, DeviceError, DeviceMessage, FrameDecoder,
    Limits, Message, NominalGeometry, Packet, Request, Response, SeqTracker, State, UploadState,
    MAX_FRAME,
};
use std::vec::Vec;

const SLOT: usize = 16 * 1024;
type Flash = RamFlash<SLOT>;
const CPR: u32 = 4096;
const RADIUS: f64 = 10.0;

fn nn(hidden: usize) -> CorrectionModel {
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

fn calibration(correction: CorrectionModel) -> Calibration {
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
fn raw_at(p: [f64; 3]) -> [u16; STRINGS] {
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

fn config() -> DeviceConfig {
    DeviceConfig {
        firmware_version: [0, 1, 0],
        device_id: [7; 12],
        loop_period_us: 100,
        boot_id: 0x5eed,
        control: ControlConfig::default(),
    }
}

fn string_model() -> NominalGeometry {
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
struct Bench<'m> {
    dev: Device<'m, Flash>,
    link: DeviceLink,
    host_rx: FrameDecoder,
    seq: u16,
    now_us: u64,
    stream: Vec<Packet<DeviceMessage>>,
    stream_seq: SeqTracker,
}

impl<'m> Bench<'m> {
    fn new(flash: Flash, ram: &'m mut [u8], spare: &'m mut [u8]) -> Self {
        Self::new_at(flash, ram, spare, raw_at([0.0; 3]))
    }

    /// Boots with the encoders reading `raw`.
    fn new_at(flash: Flash, ram: &'m mut [u8], spare: &'m mut [u8], raw: [u16; STRINGS]) -> Self {
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
    fn feed(&mut self, bytes: &[u8]) -> Vec<Packet<DeviceMessage>> {
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

    fn request(&mut self, req: &Request<'_>) -> Response {
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

    fn tick_at(&mut self, raw: [u16; STRINGS]) -> LoopOutput {
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

    fn upload(&mut self, blob: &[u8], model_id: u32, chunk: usize) -> Response {
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
    fn states(&self) -> impl DoubleEndedIterator<Item = State> + '_ {
        self.stream.iter().filter_map(|p| match p.msg {
            DeviceMessage::State(s) => Some(s),
            _ => None,
        })
    }
}

fn bad_state(s: BadState) -> Response {
    Response::Error(DeviceError::BadState(s))
}

/// A frame whose message is not checked by `validate` (to send out-of-range
/// fields the way a buggy host would).
fn unchecked_frame<T: serde::Serialize>(seq: u16, msg: &T) -> Vec<u8> {
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
struct FutureHello {
    tag: u8,
    protocol_version: u16,
    new_field: u32,
}

impl Message for FutureHello {
    fn validate(&self) -> Result<(), &'static str> {
        Ok(())
    }
    fn peek_protocol_version(_: &[u8]) -> Option<u16> {
        None
    }
}

/// One session over the frames, phase by phase: hello and upload, arm,
/// force and stream, corrupted frames, heartbeat loss, version mismatch.
#[test]
fn full_session_through_frames() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let begin = session_hello_and_upload(&mut b);
    let p = [100.0, -50.0, 200.0];
    session_arm_force_and_stream(&mut b, &begin, p);
    session_corrupted_frames(&mut b);
    session_heartbeat_loss(&mut b, &begin, p);
    session_version_mismatch(&mut b);
}

/// Hello, then an upload in chunks with a gap, a resend, a status and a
/// resume; returns the upload's begin request (refused later while armed).
fn session_hello_and_upload(b: &mut Bench<'_>) -> Request<'static> {
    // A host flushing the line first: a lone delimiter is ignored.
    assert!(b.feed(&[0]).is_empty());
    let Response::HelloAck(ack) = b.request(&Request::Hello {
        protocol_version: PROTOCOL_VERSION,
    }) else {
        panic!("no HelloAck")
    };
    assert_eq!(ack.protocol_version, PROTOCOL_VERSION);
    assert_eq!(ack.max_blob_len, (SLOT - 32) as u32);
    assert_eq!(usize::from(ack.max_chunk), MAX_CHUNK);
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    assert_eq!(b.request(&Request::Arm), bad_state(BadState::NoGeometry));

    // Upload in chunks, with a gap, a resend, a status and a resume.
    let blob = compile(&calibration(nn(16)), 42, 1_700_000_000).unwrap();
    let crc = CRC32.checksum(&blob);
    let begin = Request::UploadBegin {
        total_len: blob.len() as u32,
        crc32: crc,
        model_id: 42,
    };
    assert_eq!(b.request(&begin), Response::ChunkAck { next_offset: 0 });
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: 0,
            data: &blob[..200]
        }),
        Response::ChunkAck { next_offset: 200 }
    );
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: 208,
            data: &blob[208..300]
        }),
        Response::Error(DeviceError::OutOfOrder {
            expected_offset: 200
        })
    );
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: 0,
            data: &blob[..200]
        }),
        Response::ChunkAck { next_offset: 200 }
    );
    assert_eq!(
        b.request(&Request::UploadStatus),
        Response::UploadStatus(UploadState::InProgress {
            model_id: 42,
            total_len: blob.len() as u32,
            crc32: crc,
            next_offset: 200
        })
    );
    // The link dropped: the host asks again and resumes where it stood.
    b.link.reset();
    assert_eq!(b.request(&begin), Response::ChunkAck { next_offset: 200 });
    let mut next = 200usize;
    while next < blob.len() {
        let end = (next + MAX_CHUNK).min(blob.len());
        assert_eq!(
            b.request(&Request::UploadChunk {
                offset: next as u32,
                data: &blob[next..end]
            }),
            Response::ChunkAck {
                next_offset: end as u32
            }
        );
        next = end;
    }
    assert_eq!(
        b.request(&Request::UploadCommit { crc32: crc ^ 1 }),
        Response::Error(DeviceError::CrcMismatch {
            expected: crc,
            computed: crc ^ 1
        })
    );
    assert_eq!(
        b.request(&Request::UploadCommit { crc32: crc }),
        Response::Committed { model_id: 42 }
    );
    assert_eq!(
        b.request(&Request::UploadStatus),
        Response::UploadStatus(UploadState::Idle)
    );
    let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
        panic!("no model info")
    };
    assert_eq!(info.slot, 0);
    assert_eq!(info.header.model_id, 42);
    assert_eq!(info.header.kind, CorrectionKind::Nn);
    assert_eq!(info.blob_crc32, crc);
    begin
}

/// Arm, render a force at `p`, stream; no model change while armed.
fn session_arm_force_and_stream(b: &mut Bench<'_>, begin: &Request<'static>, p: [f64; 3]) {
    let home = raw_at([0.0; 3]);
    b.tick_at(home);
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert!(b.dev.motors_enabled());
    assert_eq!(
        b.request(&Request::SetForceTarget {
            force_n: [0.0, 0.0, 2.0]
        }),
        Response::Ack
    );
    assert_eq!(
        b.request(&Request::StreamOn { decimation: 4 }),
        Response::Ack
    );
    b.stream.clear();
    let mut out = None;
    for k in 0..40 {
        if k % 5 == 0 {
            assert_eq!(b.request(&Request::Heartbeat), Response::Ack);
        }
        out = Some(b.tick_at(raw_at(p)));
    }
    let out = out.unwrap();
    assert!(out.armed && out.faults.is_empty(), "{out:?}");
    let f = crate::tension::resultant_force(
        &cube_anchors().map(|a| a.map(|v| v as f32)),
        out.position_mm,
        &out.tensions_n,
    );
    assert!((f[2] - 2.0).abs() < 1e-2 && f[0].abs() < 1e-2, "{f:?}");
    let states: Vec<State> = b.states().collect();
    assert_eq!(states.len(), 10);
    assert_eq!(b.stream_seq.lost, 0);
    let last = states.last().unwrap();
    assert!(last.armed);
    assert_eq!(last.model_id, Some(42));
    assert_eq!(last.counts, out.counts);
    assert_eq!(last.corrected_mm, out.corrected_q16);
    assert_eq!(last.loop_us, 40);
    // Booted (and homed) at device time 0: both clocks agree.
    assert_eq!(last.since_home_us, last.time_us);
    for (got, want) in last.position_mm.iter().zip(p) {
        assert!((got - want as f32).abs() < 0.05);
    }
    // No model change while armed.
    assert_eq!(b.request(begin), bad_state(BadState::Armed));
    assert_eq!(b.request(&Request::ClearModel), bad_state(BadState::Armed));
    assert_eq!(
        b.request(&Request::SetNominalGeometry(string_model())),
        bad_state(BadState::Armed)
    );
}

/// Corrupted frames: rejected, counted, no reply; an out-of-range field is
/// answered, naming it.
fn session_corrupted_frames(b: &mut Bench<'_>) {
    let mut buf = [0u8; MAX_FRAME];
    let mut bad = encode_request(900, &Request::Heartbeat, &mut buf)
        .unwrap()
        .to_vec();
    bad[2] ^= 0x10;
    assert!(b.feed(&bad).is_empty());
    assert!(b.feed(&[0x05, 0x01, 0x00]).is_empty()); // bad COBS / too short
    let Response::Stats(stats) = b.request(&Request::GetStats) else {
        panic!("no stats")
    };
    assert!(stats.rx.crc + stats.rx.cobs >= 1, "{stats:?}");
    assert_eq!(stats.rx.rejected(), 2);
    assert!(stats.rx.ok > 30);
    assert_eq!(stats.uptime_us, b.now_us);
    // An out-of-range field is answered, naming it.
    let frame = unchecked_frame(
        901,
        &Request::SetForceTarget {
            force_n: [f32::NAN, 0.0, 0.0],
        },
    );
    let replies = b.feed(&frame);
    assert_eq!(replies.len(), 1);
    assert_eq!(replies[0].seq, 901);
    assert_eq!(
        replies[0].msg,
        DeviceMessage::Reply(Response::Error(DeviceError::InvalidArgument {
            field: name("force_n")
        }))
    );
}

/// Heartbeat loss: the host goes silent; pre-tension until Disarm.
fn session_heartbeat_loss(b: &mut Bench<'_>, begin: &Request<'static>, p: [f64; 3]) {
    b.stream.clear();
    let timeout = config().control.safety.heartbeat_timeout_ms;
    let last_request_ms = (b.now_us / 1000) as u32;
    let pretension = config().control.safety.pretension_n;
    let mut dropped_at = None;
    for _ in 0..2 * timeout {
        let out = b.tick_at(raw_at(p));
        let age = (b.now_us / 1000) as u32 - last_request_ms;
        if age <= timeout {
            assert!(out.armed, "still armed {age} ms after the last request");
        } else if dropped_at.is_none() {
            dropped_at = Some(age);
            assert!(out.tensions_n.iter().all(|&t| t == pretension), "{out:?}");
            assert!(out.faults.contains(SafetyFaults::HEARTBEAT_LOST));
        }
    }
    assert_eq!(dropped_at, Some(timeout + 1));
    // Strings stay taut: drivers on at pre-tension until Disarm.
    assert!(b.dev.motors_enabled());
    let events: Vec<Event> = b
        .stream
        .iter()
        .filter_map(|p| match p.msg {
            DeviceMessage::Event(e) => Some(e),
            _ => None,
        })
        .collect();
    assert!(events.contains(&Event::HeartbeatLost), "{events:?}");
    assert!(events.contains(&Event::Fault {
        raised: Faults::HEARTBEAT_LOST
    }));
    // Still holding pre-tension: no flash work until Disarm, and the state
    // says why (the loop disarmed, the motors on).
    assert_eq!(b.request(begin), bad_state(BadState::Armed));
    let last = b.states().next_back().unwrap();
    assert!(!last.armed && last.faults.contains(Faults::HEARTBEAT_LOST));
    assert!(last.motors_on, "{last:?}");
    assert_eq!(last.tensions_n, [pretension; STRINGS]);
    assert_eq!(b.stream_seq.lost, 0);
    let Response::Stats(stats) = b.request(&Request::GetStats) else {
        panic!("no stats")
    };
    assert_eq!(stats.heartbeat_losses, 1);
    // Arm clears the fault and arms again.
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert!(b.tick_at(raw_at(p)).armed);
    assert_eq!(b.request(&Request::Disarm), Response::Ack);
    assert!(!b.dev.motors_enabled());
    b.stream.clear();
    while b.states().next().is_none() {
        b.tick_at(raw_at(p));
    }
    let last = b.states().next_back().unwrap();
    assert!(!last.armed && !last.motors_on, "{last:?}");
}

/// Version mismatch: typed error until a matching Hello; a future Hello
/// this version cannot decode still gets a HelloAck.
fn session_version_mismatch(b: &mut Bench<'_>) {
    let Response::HelloAck(ack) = b.request(&Request::Hello {
        protocol_version: 99,
    }) else {
        panic!("no HelloAck")
    };
    assert_eq!(ack.protocol_version, PROTOCOL_VERSION);
    assert_eq!(
        b.request(&Request::GetInfo),
        Response::Error(DeviceError::VersionMismatch {
            device: PROTOCOL_VERSION,
            host: 99
        })
    );
    assert_eq!(
        b.request(&Request::Arm),
        Response::Error(DeviceError::VersionMismatch {
            device: PROTOCOL_VERSION,
            host: 99
        })
    );
    // A future Hello that this version cannot decode still gets a HelloAck.
    let mut buf = [0u8; MAX_FRAME];
    let future = encode(
        77,
        &FutureHello {
            tag: 0,
            protocol_version: PROTOCOL_VERSION + 1,
            new_field: 5,
        },
        &mut buf,
    )
    .unwrap()
    .to_vec();
    let replies = b.feed(&future);
    assert_eq!(replies.len(), 1);
    assert_eq!(replies[0].seq, 77);
    assert!(matches!(
        replies[0].msg,
        DeviceMessage::Reply(Response::HelloAck(HelloAck {
            protocol_version: PROTOCOL_VERSION,
            ..
        }))
    ));
    assert!(matches!(
        b.request(&Request::Hello {
            protocol_version: PROTOCOL_VERSION
        }),
        Response::HelloAck(_)
    ));
    assert!(matches!(
        b.request(&Request::GetInfo),
        Response::Info(Some(_))
    ));
}

#[test]
fn models_survive_power_cycles_and_uploads_never_disturb_the_active_one() {
    let blob1 = compile(&calibration(CorrectionModel::None), 1, 0).unwrap();
    let blob2 = compile(&calibration(nn(8)), 2, 0).unwrap();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    assert_eq!(
        b.upload(&blob1, 1, 256),
        Response::Committed { model_id: 1 }
    );
    b.request(&Request::StreamOn { decimation: 1 });
    // Half of model 2, then the loop still runs model 1.
    let crc2 = CRC32.checksum(&blob2);
    b.request(&Request::UploadBegin {
        total_len: blob2.len() as u32,
        crc32: crc2,
        model_id: 2,
    });
    b.request(&Request::UploadChunk {
        offset: 0,
        data: &blob2[..100],
    });
    b.tick_at(raw_at([0.0; 3]));
    let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
        panic!("no state")
    };
    assert_eq!(s.model_id, Some(1));
    // Power cycle mid-upload: model 1, intact, and no upload.
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
        panic!("model 1 lost")
    };
    assert_eq!(info.header.model_id, 1);
    assert_eq!(info.blob_crc32, CRC32.checksum(&blob1));
    assert_eq!(
        b.request(&Request::UploadStatus),
        Response::UploadStatus(UploadState::Idle)
    );
    // The stored model homed the controller at boot: arming works at once.
    b.tick_at(raw_at([0.0; 3]));
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    b.request(&Request::Disarm);
    // Commit model 2, power cycle: model 2 in slot B.
    assert_eq!(
        b.upload(&blob2, 2, 100),
        Response::Committed { model_id: 2 }
    );
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
        panic!("model 2 lost")
    };
    assert_eq!((info.slot, info.header.model_id), (1, 2));
    // A power loss in the middle of the next upload keeps model 2.
    let mut flash = b.dev.into_flash();
    flash.cut_after(10);
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let r = b.upload(&blob1, 1, 256);
    assert!(
        matches!(r, Response::Error(DeviceError::Storage { .. })),
        "{r:?}"
    );
    let mut flash = b.dev.into_flash();
    flash.power_cycle();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
        panic!("model 2 lost")
    };
    assert_eq!(info.header.model_id, 2);
    // ClearModel: no model, no geometry.
    assert_eq!(b.request(&Request::ClearModel), Response::Ack);
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    assert_eq!(b.request(&Request::Arm), bad_state(BadState::NoGeometry));
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
}

/// A model whose correction is larger than the device evaluates within its
/// tick is refused on commit by name, and the model before it stays active:
/// the largest it takes commits, one neuron more does not (a hand-made blob,
/// since the compiler refuses to make one).
#[test]
fn a_correction_over_the_tick_budget_is_refused_on_commit() {
    use crate::correction::{MAX_HIDDEN_NEURONS, NN_NEURON_LEN};
    use spidar_protocol::blob::{ModelHeader, HEADER_LEN};
    let most = MAX_HIDDEN_NEURONS as usize;
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let largest = compile(&calibration(nn(most)), 5, 0).unwrap();
    assert_eq!(
        b.upload(&largest, 5, 256),
        Response::Committed { model_id: 5 }
    );
    // The same network with one more neuron: its bytes appended, the
    // header's count, length and checksums made to agree.
    let mut over = largest.clone();
    over.extend_from_within(over.len() - NN_NEURON_LEN..);
    let mut header = ModelHeader::parse(&over).unwrap();
    header.hidden += 1;
    header.model_id = 6;
    header.body_len = (over.len() - HEADER_LEN) as u32;
    header.body_crc32 = CRC32.checksum(&over[HEADER_LEN..]);
    over[..HEADER_LEN].copy_from_slice(&header.to_bytes());
    assert_eq!(
        b.upload(&over, 6, 256),
        Response::Error(DeviceError::BlobRejected(BlobRejection::OverBudget {
            field: name("nn.hidden"),
            found: most as u32 + 1,
            most: most as u32,
        }))
    );
    match b.request(&Request::GetInfo) {
        Response::Info(Some(info)) => assert_eq!(info.header.model_id, 5),
        other => panic!("{other:?}"),
    }
}

#[test]
fn bad_uploads_are_refused_with_the_reason() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let blob = compile(&calibration(CorrectionModel::None), 5, 0).unwrap();
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: 0,
            data: &blob[..10]
        }),
        bad_state(BadState::NoUpload)
    );
    assert_eq!(
        b.request(&Request::UploadCommit { crc32: 0 }),
        bad_state(BadState::NoUpload)
    );
    assert_eq!(
        b.request(&Request::UploadBegin {
            total_len: 1 << 20,
            crc32: 0,
            model_id: 5
        }),
        Response::Error(DeviceError::TooLarge {
            total_len: 1 << 20,
            capacity: (SLOT - 32) as u32
        })
    );
    assert_eq!(
        b.request(&Request::UploadBegin {
            total_len: 0,
            crc32: 0,
            model_id: 5
        }),
        Response::Error(DeviceError::InvalidArgument {
            field: name("total_len")
        })
    );
    // A corrupted body whose whole-blob CRC matches: from_blob refuses it.
    let mut bad = blob.clone();
    let last = bad.len() - 1;
    bad[last] ^= 0x01;
    let r = b.upload(&bad, 5, 256);
    assert!(
        matches!(
            r,
            Response::Error(DeviceError::BlobRejected(BlobRejection::BodyCrc { .. }))
        ),
        "{r:?}"
    );
    // Announced model id differs from the blob's.
    assert_eq!(
        b.upload(&blob, 6, 256),
        Response::Error(DeviceError::InvalidArgument {
            field: name("model_id")
        })
    );
    // Not a blob at all.
    assert_eq!(
        b.upload(&[0x55; 100], 5, 64),
        Response::Error(DeviceError::BlobRejected(BlobRejection::BadMagic))
    );
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    // Incomplete, then abort.
    let crc = CRC32.checksum(&blob);
    b.request(&Request::UploadBegin {
        total_len: blob.len() as u32,
        crc32: crc,
        model_id: 5,
    });
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: 0,
            data: &blob[..blob.len().min(200) + 56]
        }),
        Response::ChunkAck {
            next_offset: blob.len().min(200) as u32 + 56
        }
    );
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: blob.len() as u32 - 10,
            data: &[0; 20]
        }),
        Response::Error(DeviceError::PastEnd {
            end: blob.len() as u32 + 10,
            total_len: blob.len() as u32
        })
    );
    assert_eq!(
        b.request(&Request::UploadCommit { crc32: crc }),
        Response::Error(DeviceError::Incomplete {
            next_offset: blob.len().min(200) as u32 + 56,
            total_len: blob.len() as u32
        })
    );
    assert_eq!(b.request(&Request::UploadAbort), Response::Ack);
    assert_eq!(
        b.request(&Request::UploadStatus),
        Response::UploadStatus(UploadState::Idle)
    );
    assert_eq!(b.upload(&blob, 5, 64), Response::Committed { model_id: 5 });
}

#[test]
fn home_rezeroes_the_strings_where_the_operator_holds_the_end_effector() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    // Booted with the end-effector 40 mm off the true home: the nominal
    // model homes there, so every position is off by 40 mm.
    let off = [40.0, -25.0, 10.0];
    let mut b = Bench::new_at(Flash::new(), ram.bytes(), spare.bytes(), raw_at(off));
    // No geometry yet: nothing to home.
    assert_eq!(b.request(&Request::Home), bad_state(BadState::NoGeometry));
    assert_eq!(b.dev.home_declared_us(), None);
    b.tick_at(raw_at(off));
    assert_eq!(
        b.request(&Request::SetNominalGeometry(string_model())),
        Response::Ack
    );
    // The first geometry homes the device where it is, at the last tick.
    assert_eq!(b.dev.home_declared_us(), Some(b.now_us));
    let out = b.tick_at(raw_at([0.0; 3]));
    assert!(
        (out.position_mm[0] + 40.0).abs() < 0.5,
        "{:?}",
        out.position_mm
    );
    // Armed with a force: Home is accepted, the force is dropped.
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetForceTarget {
            force_n: [1.0, 0.0, 0.0]
        }),
        Response::Ack
    );
    let out = b.tick_at(raw_at([0.0; 3]));
    assert_eq!(out.force_n, [1.0, 0.0, 0.0]);
    assert_eq!(
        b.request(&Request::StreamOn { decimation: 1 }),
        Response::Ack
    );
    let homed_at_us = b.now_us;
    // The first geometry was this boot's first home capture.
    assert_eq!(b.dev.home_id(), 0x5eed << 32 | 1);
    assert_eq!(b.request(&Request::Home), Response::Ack);
    assert_eq!(
        b.dev.home_id(),
        0x5eed << 32 | 2,
        "a new home capture, a new id"
    );
    assert_eq!(b.dev.home_declared_us(), Some(homed_at_us));
    let mut out = b.tick_at(raw_at([0.0; 3]));
    for _ in 0..5 {
        out = b.tick_at(raw_at([0.0; 3]));
    }
    // The state frame says when it was sampled, since boot and since home.
    let last = b.states().next_back().unwrap();
    assert_eq!(last.time_us, b.now_us);
    assert_eq!(last.since_home_us, b.now_us - homed_at_us);
    assert_eq!(last.since_home_us, 6000);
    assert_eq!(last.home_id, b.dev.home_id());
    assert_eq!(out.counts, [0; STRINGS]);
    assert!(out.armed);
    assert_eq!(out.force_n, [0.0; 3]);
    for k in 0..3 {
        assert!(out.position_mm[k].abs() < 1e-3, "{:?}", out.position_mm);
    }
    // A move of 100 mm now reads as 100 mm.
    let out = b.tick_at(raw_at([100.0, 0.0, 0.0]));
    assert!(
        (out.position_mm[0] - 100.0).abs() < 0.5,
        "{:?}",
        out.position_mm
    );
    let homed = b
        .stream
        .iter()
        .filter(|p| matches!(p.msg, DeviceMessage::Event(Event::Homed)))
        .count();
    assert_eq!(homed, 1);
}

/// Raw counters for the end-effector at `p` with strings from `anchors`,
/// reading 1000 at `home`.
fn raw_for(anchors: &[[f64; 3]; STRINGS], home: [f64; 3], p: [f64; 3]) -> [u16; STRINGS] {
    let lengths = inverse_kinematics(anchors, p);
    let at_home = inverse_kinematics(anchors, home);
    core::array::from_fn(|i| {
        let theta = (lengths[i] - at_home[i]) / RADIUS;
        let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
        (1000 + counts) as u16
    })
}

/// Devices with fewer strings: the layout travels in `SetNominalGeometry`;
/// `Arm` is refused, saying why, when the strings cannot pull in every
/// direction, and the device still tracks and streams; a tetrahedron of
/// 4 strings around the end-effector arms and renders, with the unused
/// channels at tension 0.
#[test]
fn string_layouts_arm_only_when_force_closed_and_track_either_way() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    // Fewer strings than degrees of freedom: refused, naming the field.
    let mut m = string_model();
    m.active_strings = 0b0000_0011;
    assert_eq!(
        b.dev.handle(&Request::SetNominalGeometry(m), 0),
        Response::Error(DeviceError::InvalidArgument {
            field: name("active_strings")
        })
    );
    // Unused channels need no valid law or anchor.
    let mut m = string_model();
    m.active_strings = 0b0001_0110;
    m.counts_per_rev[0] = 0;
    m.pulley_radius_mm[3] = f32::NAN;
    m.anchors_mm[7] = [f32::NAN; 3];
    assert_eq!(b.request(&Request::SetNominalGeometry(m)), Response::Ack);
    // Three strings in space: never force closed.
    assert_eq!(
        b.request(&Request::Arm),
        Response::Error(DeviceError::NotForceClosed {
            strings: 3,
            dof: 3,
            too_few_strings: true
        })
    );

    // Four strings from the ceiling (a hanging design): enough strings,
    // but they only pull up.
    let h = 1100.0;
    let mut hanging = [[0.0f64; 3]; STRINGS];
    for (i, (x, y)) in [(-h, -h), (h, -h), (h, h), (-h, h)].into_iter().enumerate() {
        hanging[i] = [x, y, h];
    }
    let mut m = string_model();
    m.active_strings = 0b0000_1111;
    m.anchors_mm = hanging.map(|a| a.map(|v| v as f32));
    assert_eq!(b.request(&Request::SetNominalGeometry(m)), Response::Ack);
    assert_eq!(
        b.request(&Request::Arm),
        Response::Error(DeviceError::NotForceClosed {
            strings: 4,
            dof: 3,
            too_few_strings: false
        })
    );
    // Tracking and the stream go on unarmed.
    assert_eq!(
        b.request(&Request::StreamOn { decimation: 1 }),
        Response::Ack
    );
    let p = [120.0, -80.0, -200.0];
    let mut out = b.tick_at(raw_for(&hanging, [0.0; 3], [0.0; 3]));
    for _ in 0..20 {
        out = b.tick_at(raw_for(&hanging, [0.0; 3], p));
    }
    assert!(!out.armed);
    for (got, want) in out.position_mm.iter().zip(p) {
        assert!((got - want as f32).abs() < 0.1, "{out:?}");
    }
    let pre = config().control.safety.pretension_n;
    assert_eq!(out.tensions_n, [pre, pre, pre, pre, 0.0, 0.0, 0.0, 0.0]);
    let last_state = b
        .stream
        .iter()
        .rev()
        .find_map(|p| match &p.msg {
            DeviceMessage::State(s) => Some(*s),
            _ => None,
        })
        .expect("state frames");
    assert!(!last_state.armed);
    assert!((last_state.position_mm[0] - 120.0).abs() < 0.1);

    // A tetrahedron (cube corners 0, 3, 5, 6) around the end-effector:
    // armed, renders, unused channels at 0. Home is declared again.
    let mut m = string_model();
    m.active_strings = 0b0110_1001;
    assert_eq!(b.request(&Request::SetNominalGeometry(m)), Response::Ack);
    assert_eq!(b.request(&Request::Home), Response::Ack);
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetForceTarget {
            force_n: [1.0, -0.5, 0.5]
        }),
        Response::Ack
    );
    let home_raw = raw_for(&hanging, [0.0; 3], p);
    let shift = |q: [f64; 3]| -> [u16; STRINGS] {
        // Counters continue from where they were at Home.
        let d = raw_for(&cube_anchors(), [0.0; 3], q);
        core::array::from_fn(|i| home_raw[i].wrapping_add(d[i].wrapping_sub(1000)))
    };
    let q = [100.0, 50.0, -60.0];
    let mut out = b.tick_at(shift([0.0; 3]));
    for _ in 0..10 {
        out = b.tick_at(shift(q));
    }
    assert!(out.armed && out.faults.is_empty(), "{out:?}");
    assert_eq!(out.tension_status, TensionStatus::Exact);
    for i in [1, 2, 4, 7] {
        assert_eq!(out.tensions_n[i], 0.0);
    }
    let f = crate::tension::resultant_force(
        &cube_anchors().map(|a| a.map(|v| v as f32)),
        out.position_mm,
        &core::array::from_fn(|i| {
            if [0, 3, 5, 6].contains(&i) {
                out.tensions_n[i]
            } else {
                0.0
            }
        }),
    );
    for (got, want) in f.iter().zip([1.0, -0.5, 0.5]) {
        assert!((got - want).abs() < 1e-3, "{f:?}");
    }
}

#[test]
fn nominal_string_model_limits_and_estop() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let mut m = string_model();
    m.pulley_radius_mm[3] = -1.0;
    assert_eq!(
        b.dev.handle(&Request::SetNominalGeometry(m), 0),
        Response::Error(DeviceError::InvalidArgument {
            field: name("pulley_radius_mm")
        })
    );
    m = string_model();
    m.anchors_mm[2][1] = f32::INFINITY;
    assert_eq!(
        b.dev.handle(&Request::SetNominalGeometry(m), 0),
        Response::Error(DeviceError::InvalidArgument {
            field: name("anchors_mm")
        })
    );
    // The nominal model homes the device now (end-effector at home).
    assert_eq!(
        b.request(&Request::SetNominalGeometry(string_model())),
        Response::Ack
    );
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    let limits = Limits {
        pre_tension_n: 2.0,
        max_tension_n: 20.0,
        heartbeat_timeout_ms: 50,
    };
    assert_eq!(b.request(&Request::SetLimits(limits)), Response::Ack);
    assert_eq!(
        b.dev.handle(
            &Request::SetLimits(Limits {
                heartbeat_timeout_ms: 0,
                ..limits
            }),
            0
        ),
        Response::Error(DeviceError::InvalidArgument {
            field: name("heartbeat_timeout_ms")
        })
    );
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetLimits(limits)),
        bad_state(BadState::Armed)
    );
    let p = [-150.0, 80.0, 30.0];
    let out = b.tick_at(raw_at(p));
    assert!(out.armed, "{out:?}");
    for (got, want) in out.position_mm.iter().zip(p) {
        assert!((got - want as f32).abs() < 0.05, "{out:?}");
    }
    // Idle: the distribution's internal tension level, within the limits.
    assert!(
        out.tensions_n.iter().all(|&t| (0.5..=20.0).contains(&t)),
        "{out:?}"
    );
    // The new heartbeat timeout: 50 ms (Arm at T, ticks at T+1..=T+50).
    for _ in 0..49 {
        assert!(b.tick_at(raw_at(p)).armed);
    }
    let out = b.tick_at(raw_at(p));
    assert!(!out.armed && out.faults.contains(SafetyFaults::HEARTBEAT_LOST));
    assert_eq!(out.tensions_n, [2.0; STRINGS]);
    // Guidance target, then the emergency stop.
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert_eq!(
        b.request(&Request::SetGuidanceTarget {
            target_mm: [0.0, 0.0, 0.0],
            d_min_mm: 5.0,
            f_max_n: 3.0
        }),
        Response::Ack
    );
    assert!(b.tick_at(raw_at(p)).force_n.iter().any(|f| f.abs() > 0.1));
    b.now_us += 1000;
    let out = b.dev.tick(&TickInput {
        raw_counts: raw_at(p),
        now_us: b.now_us,
        estop: true,
    });
    assert!(!out.armed && out.faults.contains(SafetyFaults::ESTOP));
    assert!(!b.dev.motors_enabled());
    assert_eq!(b.request(&Request::Arm), bad_state(BadState::Faulted));
    let out = b.tick_at(raw_at(p)); // e-stop released
    assert!(out.faults.contains(SafetyFaults::ESTOP)); // still latched
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    assert!(b.tick_at(raw_at(p)).armed);
    // Overrun: latched, reported, cleared by ClearFaults.
    b.dev.record_loop_time(150);
    b.request(&Request::StreamOn { decimation: 1 });
    b.tick_at(raw_at(p));
    let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
        panic!("no state")
    };
    assert!(s.faults.contains(Faults::LOOP_OVERRUN));
    assert_eq!(b.dev.stats().loop_overruns, 1);
    b.request(&Request::ClearFaults);
    b.tick_at(raw_at(p));
    let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
        panic!("no state")
    };
    assert!(!s.faults.contains(Faults::LOOP_OVERRUN));
    assert!(s.armed);
}

/// Arbitrary bytes and arbitrary upload requests never panic the device.
#[test]
fn garbage_never_panics() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let mut x = 0x1234_5678_9abc_def0u64;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    let mut bytes = Vec::new();
    for _ in 0..20_000 {
        let v = next();
        bytes.push(if v % 7 == 0 { 0 } else { v as u8 });
    }
    for piece in bytes.chunks(61) {
        let dev = &mut b.dev;
        let mut rest = piece;
        while !rest.is_empty() {
            let (used, _) = b.link.push(rest, |req, _| dev.handle(req, 0));
            rest = &rest[used..];
        }
    }
    let data = [0xA5u8; MAX_CHUNK];
    for _ in 0..2000 {
        let v = next();
        let offset = (v >> 8) as u32 % 20_000;
        let len = 1 + (v >> 40) as usize % MAX_CHUNK;
        let req = match v % 5 {
            0 => Request::UploadBegin {
                total_len: (v >> 20) as u32 % 20_000,
                crc32: v as u32,
                model_id: 1,
            },
            1 | 2 => Request::UploadChunk {
                offset,
                data: &data[..len],
            },
            3 => Request::UploadCommit {
                crc32: (v >> 3) as u32,
            },
            _ => Request::UploadStatus,
        };
        b.dev.handle(&req, 0);
        b.tick_at(raw_at([0.0; 3]));
    }
}

/// What a tick costs with the borrow handled three ways (host timings;
/// `cargo test -p spidar-core --release --lib device::tests::tick_cost
/// -- --ignored --nocapture`).
#[test]
#[ignore]
fn tick_cost() {
    use std::time::Instant;
    const N: u32 = 20_000;
    for hidden in [0usize, 16, 64] {
        let model = if hidden == 0 {
            CorrectionModel::None
        } else {
            nn(hidden)
        };
        let blob = compile(&calibration(model), 1, 0).unwrap();
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        assert_eq!(b.upload(&blob, 1, 256), Response::Committed { model_id: 1 });
        let raw = raw_at([10.0, 20.0, 30.0]);
        let input = |k: u32| TickInput {
            raw_counts: raw,
            now_us: u64::from(k) * 100,
            estop: false,
        };
        let t = Instant::now();
        for k in 0..N {
            std::hint::black_box(b.dev.tick(&input(k)));
        }
        let device_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
        let cal = CompiledCalibration::from_blob(&blob).unwrap();
        let mut ctl = Controller::new(ControlConfig::default(), &cal, raw, 0).unwrap();
        let li = |k: u32| LoopInput {
            raw_counts: raw,
            now_ms: k / 10,
            now_us: k * 100,
            estop: false,
        };
        let t = Instant::now();
        for k in 0..N {
            std::hint::black_box(ctl.step(&cal, &li(k)));
        }
        let step_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
        let t = Instant::now();
        for k in 0..N {
            let c = CompiledCalibration::from_blob(std::hint::black_box(&blob)).unwrap();
            std::hint::black_box(ctl.step(&c, &li(k)));
        }
        let reparse_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
        std::println!(
            "hidden {hidden:3}, blob {:5} B: step alone {step_ns:7.0} ns, Device::tick \
             {device_ns:7.0} ns (+{:5.0}), from_blob every tick {reparse_ns:7.0} ns (+{:5.0}); \
             BlobHead {} B",
            blob.len(),
            device_ns - step_ns,
            reparse_ns - step_ns,
            core::mem::size_of::<BlobHead>()
        );
    }
}

/// Every combination of the loop's faults maps to the wire by name: a fault
/// the wire names keeps its bit, the kinematic ones become `KINEMATICS`,
/// `OVERFORCE` does not go out, and nothing else is set.
#[test]
fn every_loop_fault_combination_reaches_the_wire_by_name() {
    let singles = [
        (SafetyFaults::HEARTBEAT_LOST, Faults::HEARTBEAT_LOST),
        (SafetyFaults::MODEL_INVALID, Faults::MODEL_INVALID),
        (SafetyFaults::ESTOP, Faults::ESTOP),
        (SafetyFaults::SLACK, Faults::KINEMATICS),
        (SafetyFaults::FK_FAULT, Faults::KINEMATICS),
        (SafetyFaults::NON_FINITE, Faults::KINEMATICS),
        (SafetyFaults::OVERFORCE, Faults(0)),
    ];
    let mut every = SafetyFaults::NONE;
    for (f, _) in singles {
        assert!(!every.intersects(f), "two loop faults share a bit");
        every |= f;
    }
    assert_eq!(every, SafetyFaults::ALL);
    for combination in 0u32..(1 << singles.len()) {
        let mut faults = SafetyFaults::NONE;
        let mut expected = 0u16;
        for (k, (f, wire)) in singles.iter().enumerate() {
            if combination & (1 << k) != 0 {
                faults |= *f;
                expected |= wire.0;
            }
        }
        let mut out = idle_output(false, false);
        out.faults = faults;
        assert_eq!(protocol_faults(&out, false), Faults(expected), "{faults:?}");
        assert_eq!(
            protocol_faults(&out, true),
            Faults(expected | Faults::LOOP_OVERRUN.0)
        );
    }
    // The shared names sit on the same bits on both sides.
    for (f, name) in Faults::NAMED {
        let loop_side = match name {
            "HEARTBEAT_LOST" => SafetyFaults::HEARTBEAT_LOST,
            "MODEL_INVALID" => SafetyFaults::MODEL_INVALID,
            "ESTOP" => SafetyFaults::ESTOP,
            _ => continue,
        };
        assert_eq!(loop_side.bits(), f.0, "{name}");
    }
}

/// The training's slips in a blob flashed under their home capture: the
/// device applies them until the next `Home` (or a reboot), not after.
#[test]
fn training_slips_apply_under_their_home_capture_until_the_next_home() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    b.tick_at(raw_at([0.0; 3]));
    assert_eq!(
        b.request(&Request::SetNominalGeometry(string_model())),
        Response::Ack
    );
    let training_home = b.dev.home_id();
    // Slips that lengthen each string as a move of `d` would: under them
    // the strings at home read as the end-effector at `d`.
    let d = [6.0, -4.0, 3.0];
    let at_d = inverse_kinematics(&cube_anchors(), d);
    let at_home = inverse_kinematics(&cube_anchors(), [0.0; 3]);
    let mut cal = calibration(CorrectionModel::None);
    cal.home = Some(crate::model::HomeSlips {
        home_id: training_home,
        slips: (0..STRINGS)
            .map(|i| crate::model::EffectTerm {
                string: i as u8,
                effect: crate::model::Effect::Slip {
                    at_s: 0.0,
                    mm: at_d[i] - at_home[i],
                },
            })
            .collect(),
    });
    let blob = compile(&cal, 9, 0).unwrap();
    for _ in 0..3 {
        b.tick_at(raw_at([0.0; 3]));
    }
    assert_eq!(b.upload(&blob, 9, 256), Response::Committed { model_id: 9 });
    assert_eq!(b.dev.home_id(), training_home, "a flash keeps the home");
    // The room position less the frame's translation (its rotation and
    // scale are the identity): the device-frame position, corrected.
    let t = cal.frame.room_translation;
    let corrected = |out: &LoopOutput| {
        let p = out.corrected_q16.map(|v| f64::from(v) / 65536.0);
        [p[0] - t[0], p[1] - t[1], p[2] - t[2]]
    };
    let near = |p: [f64; 3], q: [f64; 3]| (0..3).all(|k| (p[k] - q[k]).abs() < 0.05);
    let mut out = b.tick_at(raw_at([0.0; 3]));
    for _ in 0..20 {
        out = b.tick_at(raw_at([0.0; 3]));
    }
    assert!(near(corrected(&out), d), "{:?}", corrected(&out));
    for i in 0..STRINGS {
        let slip = (at_d[i] - at_home[i]) as f32;
        assert!(
            (out.string_lengths_mm[i] - at_home[i] as f32 - slip).abs() < 1e-3,
            "string {i}: {} mm",
            out.string_lengths_mm[i]
        );
    }
    // A new home capture: the strings are counted as they are, no slip.
    assert_eq!(b.request(&Request::Home), Response::Ack);
    assert_ne!(b.dev.home_id(), training_home);
    for _ in 0..20 {
        out = b.tick_at(raw_at([0.0; 3]));
    }
    assert!(near(corrected(&out), [0.0; 3]), "{:?}", corrected(&out));
    // A reboot (another boot id): a new home capture too.
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let config = DeviceConfig {
        boot_id: 0x5eee,
        ..config()
    };
    let mut dev = Device::new(
        config,
        flash,
        ram.bytes(),
        spare.bytes(),
        raw_at([0.0; 3]),
        0,
    )
    .unwrap();
    assert_eq!(dev.home_id(), 0x5eee << 32 | 1);
    for k in 1..=20 {
        out = dev.tick(&TickInput {
            raw_counts: raw_at([0.0; 3]),
            now_us: k * 1000,
            estop: false,
        });
    }
    assert!(near(corrected(&out), [0.0; 3]), "{:?}", corrected(&out));
}

/// A drift reads the time since home: it starts again from 0 at a new home
/// capture by itself (decision record 0049, "Device side").
#[test]
fn a_drift_starts_again_at_a_new_home_capture() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let mut cal = calibration(CorrectionModel::None);
    cal.effects.push(crate::model::EffectTerm {
        string: 4,
        effect: crate::model::Effect::Drift { mm_per_s: 0.5 },
    });
    let blob = compile(&cal, 3, 0).unwrap();
    assert_eq!(b.upload(&blob, 3, 256), Response::Committed { model_id: 3 });
    let home_length = inverse_kinematics(&cube_anchors(), [0.0; 3])[4] as f32;
    let drift_at =
        |b: &mut Bench<'_>| b.tick_at(raw_at([0.0; 3])).string_lengths_mm[4] - home_length;
    for _ in 0..1999 {
        b.tick_at(raw_at([0.0; 3]));
    }
    // 2 s after the boot's home capture: 1 mm.
    assert!((drift_at(&mut b) - 1.0).abs() < 2e-3);
    assert_eq!(b.request(&Request::Home), Response::Ack);
    // 1 ms after the new one: 0.5 um.
    assert!(drift_at(&mut b).abs() < 2e-3);
}
