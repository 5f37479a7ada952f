//! Sample messages shared by the integration tests: one typical and one
//! worst-case (longest encoding) value of every variant, and checks that the
//! lists cover every variant.
#![allow(dead_code)]

use spidar_protocol::blob::{CorrectionKind, ModelHeader, FORMAT_VERSION};
use spidar_protocol::messages::name;
use spidar_protocol::*;

pub static CHUNK: [u8; MAX_CHUNK] = [0xA5; MAX_CHUNK];
pub static FULL_CHUNK: [u8; MAX_CHUNK] = [0xFF; MAX_CHUNK];

pub fn string_model(counts: u32) -> NominalGeometry {
    let mut anchors = [[0.0f32; 3]; STRINGS];
    for (i, a) in anchors.iter_mut().enumerate() {
        let s = |b: usize| if i >> b & 1 == 1 { 250.0 } else { -250.0 };
        *a = [s(0), s(1), s(2)];
    }
    NominalGeometry {
        counts_per_rev: [counts; STRINGS],
        pulley_radius_mm: [7.5; STRINGS],
        anchors_mm: anchors,
        home_mm: [0.5, -1.25, 3.0],
        active_strings: 0xFF,
        planar: false,
    }
}

pub fn header(max: bool) -> ModelHeader {
    let (w, b, h) = if max {
        (u32::MAX, u8::MAX, u16::MAX)
    } else {
        (1234, 8, 20)
    };
    ModelHeader {
        format_version: if max { u16::MAX } else { FORMAT_VERSION },
        kind: CorrectionKind::Svr,
        strings: b,
        effects: b,
        q_length: b,
        q_position: b,
        q_weight: b,
        hidden: h,
        support_vectors: w,
        body_len: w,
        body_crc32: w,
        model_id: w,
        created_unix_s: w,
    }
}

/// Every request variant; `max` picks the longest encoding.
pub fn requests(max: bool) -> Vec<Request<'static>> {
    let w = if max { u32::MAX } else { 1000 };
    let h = if max { u16::MAX } else { 10 };
    vec![
        Request::Hello {
            protocol_version: if max { u16::MAX } else { PROTOCOL_VERSION },
        },
        Request::Heartbeat,
        Request::GetInfo,
        Request::GetStats,
        Request::SetNominalGeometry(string_model(w)),
        Request::SetLimits(Limits {
            pre_tension_n: 0.3,
            max_tension_n: 12.0,
            heartbeat_timeout_ms: h,
        }),
        Request::SetForceTarget {
            force_n: [1.0, -2.5, 0.125],
        },
        Request::SetGuidanceTarget {
            target_mm: [10.0, 20.0, -30.0],
            d_min_mm: 2.0,
            f_max_n: 3.5,
        },
        Request::Arm,
        Request::Disarm,
        Request::ClearFaults,
        Request::StreamOn { decimation: h },
        Request::StreamOff,
        Request::UploadBegin {
            total_len: w,
            crc32: w,
            model_id: w,
        },
        Request::UploadChunk {
            offset: if max {
                u32::MAX - MAX_CHUNK as u32
            } else {
                512
            },
            data: if max { &FULL_CHUNK[..] } else { &CHUNK[..100] },
        },
        Request::UploadCommit { crc32: w },
        Request::UploadAbort,
        Request::UploadStatus,
        Request::ClearModel,
        Request::Home,
    ]
}

pub fn request_name(r: &Request) -> &'static str {
    r.name()
}
pub const REQUEST_VARIANTS: usize = 20;

pub fn state(max: bool) -> State {
    if max {
        State {
            time_us: u64::MAX,
            since_home_us: u64::MAX,
            home_id: u64::MAX,
            counts: [i32::MIN; STRINGS],
            position_mm: [f32::MAX; 3],
            corrected_mm: [i32::MIN; 3],
            tensions_n: [f32::MAX; STRINGS],
            rendered_force_n: [f32::MAX; 3],
            faults: Faults(u16::MAX),
            slack: u8::MAX,
            excluded: Some(7),
            loop_us: u16::MAX,
            loop_max_us: u16::MAX,
            armed: true,
            motors_on: true,
            model_id: Some(u32::MAX),
        }
    } else {
        // A realistic sample: one hour after boot, strings paid out by a few
        // thousand counts, end-effector ~100 mm from the centre.
        State {
            time_us: 3_600_000_000,
            since_home_us: 3_540_000_000,
            home_id: (0x5eed_0001 << 32) | 3,
            counts: [12_000, -8_500, 3_100, -15_000, 22_000, 650, -4_200, 9_900],
            position_mm: [102.5, -48.25, 77.0],
            corrected_mm: [
                (102.61 * 65536.0) as i32,
                (-48.3 * 65536.0) as i32,
                (77.02 * 65536.0) as i32,
            ],
            tensions_n: [0.5, 1.25, 2.0, 0.5, 3.75, 0.5, 1.0, 0.5],
            rendered_force_n: [1.5, -0.25, 2.0],
            faults: Faults::TENSION_CLAMPED,
            slack: 0,
            excluded: None,
            loop_us: 143,
            loop_max_us: 171,
            armed: true,
            motors_on: true,
            model_id: Some(0x5eed_1234),
        }
    }
}

pub fn device_errors(max: bool) -> Vec<DeviceError> {
    let w = if max { u32::MAX } else { 300 };
    let h = if max { u16::MAX } else { 2 };
    let field = if max {
        name("a_field_name_longer_than_max_name")
    } else {
        name("hidden")
    };
    vec![
        DeviceError::VersionMismatch { device: h, host: h },
        DeviceError::BadState(BadState::Armed),
        DeviceError::BadState(BadState::NotArmed),
        DeviceError::BadState(BadState::Faulted),
        DeviceError::BadState(BadState::NoUpload),
        DeviceError::BadState(BadState::NoGeometry),
        DeviceError::InvalidArgument {
            field: field.clone(),
        },
        DeviceError::Unsupported,
        DeviceError::TooLarge {
            total_len: w,
            capacity: w,
        },
        DeviceError::OutOfOrder { expected_offset: w },
        DeviceError::PastEnd {
            end: w,
            total_len: w,
        },
        DeviceError::Incomplete {
            next_offset: w,
            total_len: w,
        },
        DeviceError::CrcMismatch {
            expected: w,
            computed: w,
        },
        DeviceError::BlobRejected(BlobRejection::Truncated { needed: w, got: w }),
        DeviceError::BlobRejected(BlobRejection::TrailingBytes { extra: w }),
        DeviceError::BlobRejected(BlobRejection::BadMagic),
        DeviceError::BlobRejected(BlobRejection::UnsupportedVersion {
            found: h,
            supported: h,
        }),
        DeviceError::BlobRejected(BlobRejection::UnknownKind { found: 9 }),
        DeviceError::BlobRejected(BlobRejection::HeaderCrc {
            stored: w,
            computed: w,
        }),
        DeviceError::BlobRejected(BlobRejection::BodyCrc {
            stored: w,
            computed: w,
        }),
        DeviceError::BlobRejected(BlobRejection::Dimension {
            field: field.clone(),
            found: w,
            expected: w,
        }),
        DeviceError::BlobRejected(BlobRejection::Body {
            field: field.clone(),
        }),
        DeviceError::BlobRejected(BlobRejection::TooFewStrings {
            strings: if max { u8::MAX } else { 2 },
            dof: 3,
        }),
        DeviceError::BlobRejected(BlobRejection::InactiveString {
            field: field.clone(),
            string: if max { u8::MAX } else { 5 },
        }),
        DeviceError::BlobRejected(BlobRejection::OverBudget {
            field,
            found: w,
            most: w,
        }),
        DeviceError::NotForceClosed {
            strings: if max { u8::MAX } else { 4 },
            dof: 3,
            too_few_strings: max,
        },
        DeviceError::Storage { code: w },
    ]
}

/// Every device-message variant (every response, every error, every event).
pub fn device_messages(max: bool) -> Vec<DeviceMessage> {
    let w = if max { u32::MAX } else { 4096 };
    let mut v = vec![
        DeviceMessage::Reply(Response::HelloAck(HelloAck {
            protocol_version: if max { u16::MAX } else { PROTOCOL_VERSION },
            firmware_version: if max { [u16::MAX; 3] } else { [0, 3, 1] },
            device_id: [0xEE; 12],
            capabilities: if max {
                Capabilities(u32::MAX)
            } else {
                Capabilities::FORCE.union(Capabilities::MODEL_NN)
            },
            max_chunk: MAX_CHUNK as u16,
            max_blob_len: w,
            loop_period_us: if max { u32::MAX } else { 250 },
        })),
        DeviceMessage::Reply(Response::Ack),
        DeviceMessage::Reply(Response::Info(None)),
        DeviceMessage::Reply(Response::Info(Some(ModelInfo {
            slot: if max { u8::MAX } else { 1 },
            header: header(max),
            blob_crc32: w,
        }))),
        DeviceMessage::Reply(Response::Stats(LinkStats {
            rx: DecodeStats {
                ok: w,
                cobs: w,
                too_short: w,
                crc: w,
                payload: w,
                invalid: w,
                overlong: w,
                version: w,
            },
            tx_frames: w,
            tx_dropped: w,
            loop_overruns: w,
            heartbeat_losses: w,
            uptime_us: if max { u64::MAX } else { 1_000_000 },
        })),
        DeviceMessage::Reply(Response::ChunkAck { next_offset: w }),
        DeviceMessage::Reply(Response::Committed { model_id: w }),
        DeviceMessage::Reply(Response::UploadStatus(UploadState::Idle)),
        DeviceMessage::Reply(Response::UploadStatus(UploadState::InProgress {
            model_id: w,
            total_len: w,
            crc32: w,
            next_offset: w,
        })),
        DeviceMessage::State(state(max)),
        DeviceMessage::Event(Event::HeartbeatLost),
        DeviceMessage::Event(Event::Fault {
            raised: Faults(if max { u16::MAX } else { 2 }),
        }),
        DeviceMessage::Event(Event::Disarmed {
            faults: Faults(if max { u16::MAX } else { 2 }),
        }),
        DeviceMessage::Event(Event::Homed),
    ];
    v.extend(
        device_errors(max)
            .into_iter()
            .map(|e| DeviceMessage::Reply(Response::Error(e))),
    );
    v
}

pub fn device_message_name(m: &DeviceMessage) -> &'static str {
    // No wildcards: adding a variant breaks this until the samples cover it.
    match m {
        DeviceMessage::Reply(r) => match r {
            Response::HelloAck(_) => "HelloAck",
            Response::Ack => "Ack",
            Response::Info(None) => "Info(None)",
            Response::Info(Some(_)) => "Info(Some)",
            Response::Stats(_) => "Stats",
            Response::ChunkAck { .. } => "ChunkAck",
            Response::Committed { .. } => "Committed",
            Response::UploadStatus(UploadState::Idle) => "UploadStatus(Idle)",
            Response::UploadStatus(UploadState::InProgress { .. }) => "UploadStatus(InProgress)",
            Response::Error(e) => match e {
                DeviceError::VersionMismatch { .. } => "Error(VersionMismatch)",
                DeviceError::BadState(_) => "Error(BadState)",
                DeviceError::InvalidArgument { .. } => "Error(InvalidArgument)",
                DeviceError::Unsupported => "Error(Unsupported)",
                DeviceError::TooLarge { .. } => "Error(TooLarge)",
                DeviceError::OutOfOrder { .. } => "Error(OutOfOrder)",
                DeviceError::PastEnd { .. } => "Error(PastEnd)",
                DeviceError::Incomplete { .. } => "Error(Incomplete)",
                DeviceError::CrcMismatch { .. } => "Error(CrcMismatch)",
                DeviceError::BlobRejected(b) => match b {
                    BlobRejection::Truncated { .. } => "Error(Blob(Truncated))",
                    BlobRejection::TrailingBytes { .. } => "Error(Blob(TrailingBytes))",
                    BlobRejection::BadMagic => "Error(Blob(BadMagic))",
                    BlobRejection::UnsupportedVersion { .. } => "Error(Blob(UnsupportedVersion))",
                    BlobRejection::UnknownKind { .. } => "Error(Blob(UnknownKind))",
                    BlobRejection::HeaderCrc { .. } => "Error(Blob(HeaderCrc))",
                    BlobRejection::BodyCrc { .. } => "Error(Blob(BodyCrc))",
                    BlobRejection::Dimension { .. } => "Error(Blob(Dimension))",
                    BlobRejection::Body { .. } => "Error(Blob(Body))",
                    BlobRejection::TooFewStrings { .. } => "Error(Blob(TooFewStrings))",
                    BlobRejection::InactiveString { .. } => "Error(Blob(InactiveString))",
                    BlobRejection::OverBudget { .. } => "Error(Blob(OverBudget))",
                },
                DeviceError::NotForceClosed { .. } => "Error(NotForceClosed)",
                DeviceError::Storage { .. } => "Error(Storage)",
            },
        },
        DeviceMessage::State(_) => "State",
        DeviceMessage::Event(e) => match e {
            Event::HeartbeatLost => "Event(HeartbeatLost)",
            Event::Fault { .. } => "Event(Fault)",
            Event::Disarmed { .. } => "Event(Disarmed)",
            Event::Homed => "Event(Homed)",
        },
    }
}
/// Distinct names `device_message_name` returns (BadState counted once).
pub const DEVICE_MESSAGE_VARIANTS: usize = 37;

/// Encodes a raw postcard payload (seq + message bytes) into a frame, CRC and
/// COBS included, bypassing the typed encoder (to build frames a correct
/// sender would never send).
pub fn raw_frame(payload: &[u8]) -> Vec<u8> {
    let mut p = payload.to_vec();
    p.extend_from_slice(&spidar_protocol::blob::CRC32.checksum(payload).to_le_bytes());
    let mut out = vec![0u8; cobs::max_encoding_length(p.len()) + 1];
    let n = cobs::encode(&p, &mut out);
    out.truncate(n);
    out.push(0);
    out
}

/// postcard bytes of `v`.
pub fn to_vec<T: serde::Serialize>(v: &T) -> Vec<u8> {
    postcard::to_slice(v, &mut [0u8; 2048]).unwrap().to_vec()
}
