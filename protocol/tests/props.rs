//! Property tests: arbitrary messages round-trip; arbitrary bytes never make
//! the decoder (or the blob header parser) panic; corruption is detected.

mod common;

use proptest::array::{uniform12, uniform3, uniform8};
use proptest::collection::vec;
use proptest::prelude::*;
use spidar_protocol::blob::{split_blob, CorrectionKind, ModelHeader};
use spidar_protocol::messages::name;
use spidar_protocol::*;

type F = BoxedStrategy<f32>;

fn finite() -> F {
    (-1.0e6f32..1.0e6).boxed()
}

fn any_f32() -> F {
    any::<f32>().boxed()
}

fn chunk_data() -> impl Strategy<Value = &'static [u8]> {
    // Leaked so the borrowed `Request` can be 'static; a few KiB per run.
    vec(any::<u8>(), 0..=MAX_CHUNK + 2).prop_map(|v| &*Vec::leak(v))
}

fn request(f: fn() -> F) -> impl Strategy<Value = Request<'static>> {
    let model = (
        uniform8(any::<u32>()),
        uniform8(f()),
        uniform8(uniform3(f())),
        uniform3(f()),
        any::<u8>(),
        any::<bool>(),
    )
        .prop_map(|(c, r, a, h, active_strings, planar)| {
            Request::SetNominalGeometry(NominalGeometry {
                counts_per_rev: c,
                pulley_radius_mm: r,
                anchors_mm: a,
                home_mm: h,
                active_strings,
                planar,
            })
        });
    prop_oneof![
        any::<u16>().prop_map(|v| Request::Hello {
            protocol_version: v
        }),
        Just(Request::Heartbeat),
        Just(Request::GetInfo),
        Just(Request::GetStats),
        model,
        (f(), f(), any::<u16>()).prop_map(|(p, m, t)| Request::SetLimits(Limits {
            pre_tension_n: p,
            max_tension_n: m,
            heartbeat_timeout_ms: t
        })),
        uniform3(f()).prop_map(|force_n| Request::SetForceTarget { force_n }),
        (uniform3(f()), f(), f()).prop_map(|(t, d, m)| Request::SetGuidanceTarget {
            target_mm: t,
            d_min_mm: d,
            f_max_n: m
        }),
        Just(Request::Arm),
        Just(Request::Disarm),
        Just(Request::ClearFaults),
        any::<u16>().prop_map(|decimation| Request::StreamOn { decimation }),
        Just(Request::StreamOff),
        (any::<u32>(), any::<u32>(), any::<u32>()).prop_map(|(t, c, m)| Request::UploadBegin {
            total_len: t,
            crc32: c,
            model_id: m
        }),
        (any::<u32>(), chunk_data())
            .prop_map(|(offset, data)| Request::UploadChunk { offset, data }),
        any::<u32>().prop_map(|crc32| Request::UploadCommit { crc32 }),
        Just(Request::UploadAbort),
        Just(Request::UploadStatus),
        Just(Request::ClearModel),
        Just(Request::Home),
    ]
}

fn any_name() -> impl Strategy<Value = Name> {
    ".{0,30}".prop_map(|s| name(&s))
}

fn header() -> impl Strategy<Value = ModelHeader> {
    (
        any::<u16>(),
        0u8..3,
        uniform8(any::<u8>()),
        uniform8(any::<u32>()),
    )
        .prop_map(|(v, k, b, w)| ModelHeader {
            format_version: v,
            kind: CorrectionKind::from_u8(k).unwrap(),
            strings: b[0],
            effects: b[1],
            q_length: b[2],
            q_position: b[3],
            q_weight: b[4],
            hidden: u16::from_le_bytes([b[5], b[6]]),
            support_vectors: w[0],
            body_len: w[1],
            body_crc32: w[2],
            model_id: w[3],
            created_unix_s: w[4],
        })
}

fn blob_rejection() -> impl Strategy<Value = BlobRejection> {
    prop_oneof![
        (any::<u32>(), any::<u32>())
            .prop_map(|(n, g)| BlobRejection::Truncated { needed: n, got: g }),
        any::<u32>().prop_map(|extra| BlobRejection::TrailingBytes { extra }),
        Just(BlobRejection::BadMagic),
        (any::<u16>(), any::<u16>()).prop_map(|(f, s)| BlobRejection::UnsupportedVersion {
            found: f,
            supported: s
        }),
        any::<u8>().prop_map(|found| BlobRejection::UnknownKind { found }),
        (any::<u32>(), any::<u32>()).prop_map(|(s, c)| BlobRejection::HeaderCrc {
            stored: s,
            computed: c
        }),
        (any::<u32>(), any::<u32>()).prop_map(|(s, c)| BlobRejection::BodyCrc {
            stored: s,
            computed: c
        }),
        (any_name(), any::<u32>(), any::<u32>()).prop_map(|(field, found, expected)| {
            BlobRejection::Dimension {
                field,
                found,
                expected,
            }
        }),
        any_name().prop_map(|field| BlobRejection::Body { field }),
    ]
}

fn device_error() -> impl Strategy<Value = DeviceError> {
    let u = any::<u32>;
    prop_oneof![
        (any::<u16>(), any::<u16>())
            .prop_map(|(d, h)| DeviceError::VersionMismatch { device: d, host: h }),
        prop_oneof![
            Just(BadState::Armed),
            Just(BadState::NotArmed),
            Just(BadState::Faulted),
            Just(BadState::NoUpload),
            Just(BadState::NoGeometry),
        ]
        .prop_map(DeviceError::BadState),
        any_name().prop_map(|field| DeviceError::InvalidArgument { field }),
        Just(DeviceError::Unsupported),
        (u(), u()).prop_map(|(t, c)| DeviceError::TooLarge {
            total_len: t,
            capacity: c
        }),
        u().prop_map(|expected_offset| DeviceError::OutOfOrder { expected_offset }),
        (u(), u()).prop_map(|(end, total_len)| DeviceError::PastEnd { end, total_len }),
        (u(), u()).prop_map(|(n, t)| DeviceError::Incomplete {
            next_offset: n,
            total_len: t
        }),
        (u(), u()).prop_map(|(e, c)| DeviceError::CrcMismatch {
            expected: e,
            computed: c
        }),
        blob_rejection().prop_map(DeviceError::BlobRejected),
        u().prop_map(|code| DeviceError::Storage { code }),
    ]
}

fn state(f: fn() -> F) -> impl Strategy<Value = State> {
    (
        (any::<u64>(), any::<u64>(), any::<u64>()),
        uniform8(any::<i32>()),
        uniform3(f()),
        uniform3(any::<i32>()),
        (uniform8(f()), uniform3(f())),
        (any::<u16>(), any::<u8>(), proptest::option::of(0u8..8)),
        (
            any::<u16>(),
            any::<u16>(),
            (any::<bool>(), any::<bool>()),
            proptest::option::of(any::<u32>()),
        ),
    )
        .prop_map(
            |((t, h, id), c, p, q, (tn, rf), (fl, sl, ex), (lu, lm, (ar, mo), mi))| State {
                time_us: t,
                since_home_us: h,
                home_id: id,
                counts: c,
                position_mm: p,
                corrected_mm: q,
                tensions_n: tn,
                rendered_force_n: rf,
                faults: Faults(fl),
                slack: sl,
                excluded: ex,
                loop_us: lu,
                loop_max_us: lm,
                armed: ar,
                motors_on: mo,
                model_id: mi,
            },
        )
}

fn device_message(f: fn() -> F) -> impl Strategy<Value = DeviceMessage> {
    let u = any::<u32>;
    let response = prop_oneof![
        (
            any::<u16>(),
            uniform3(any::<u16>()),
            uniform12(any::<u8>()),
            u(),
            1..=MAX_CHUNK as u16,
            u(),
            u()
        )
            .prop_map(|(v, fw, id, cap, mc, mb, lp)| Response::HelloAck(HelloAck {
                protocol_version: v,
                firmware_version: fw,
                device_id: id,
                capabilities: Capabilities(cap),
                max_chunk: mc,
                max_blob_len: mb,
                loop_period_us: lp,
            })),
        Just(Response::Ack),
        proptest::option::of((any::<u8>(), header(), u()).prop_map(
            |(slot, header, blob_crc32)| {
                ModelInfo {
                    slot,
                    header,
                    blob_crc32,
                }
            }
        ))
        .prop_map(Response::Info),
        (uniform8(u()), uniform8(u()), any::<u64>()).prop_map(|(a, b, up)| Response::Stats(
            LinkStats {
                rx: DecodeStats {
                    ok: a[0],
                    cobs: a[1],
                    too_short: a[2],
                    crc: a[3],
                    payload: a[4],
                    invalid: a[5],
                    overlong: a[6],
                    version: a[7],
                },
                tx_frames: b[0],
                tx_dropped: b[1],
                loop_overruns: b[2],
                heartbeat_losses: b[3],
                uptime_us: up,
            }
        )),
        u().prop_map(|next_offset| Response::ChunkAck { next_offset }),
        u().prop_map(|model_id| Response::Committed { model_id }),
        Just(Response::UploadStatus(UploadState::Idle)),
        (u(), u(), u(), u()).prop_map(|(m, t, c, n)| Response::UploadStatus(
            UploadState::InProgress {
                model_id: m,
                total_len: t,
                crc32: c,
                next_offset: n
            }
        )),
        device_error().prop_map(Response::Error),
    ];
    let event = prop_oneof![
        Just(Event::HeartbeatLost),
        any::<u16>().prop_map(|b| Event::Fault { raised: Faults(b) }),
        any::<u16>().prop_map(|b| Event::Disarmed { faults: Faults(b) }),
        Just(Event::Homed),
    ];
    prop_oneof![
        response.prop_map(DeviceMessage::Reply),
        state(f).prop_map(DeviceMessage::State),
        event.prop_map(DeviceMessage::Event),
    ]
}

fn enc<T: Message>(seq: u16, m: &T) -> Result<Vec<u8>, FrameError> {
    let mut buf = [0u8; MAX_FRAME];
    encode(seq, m, &mut buf).map(|b| b.to_vec())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    /// Finite values: the decoded request equals the original, through the
    /// streaming decoder fed in arbitrary pieces.
    #[test]
    fn requests_round_trip(seq: u16, r in request(finite), cut in 0usize..300) {
        match enc(seq, &r) {
            Ok(frame) => {
                prop_assert!(frame.len() <= MAX_FRAME);
                let (a, b) = frame.split_at(cut.min(frame.len()));
                let mut dec: FrameDecoder = FrameDecoder::new();
                let mut got = Vec::new();
                for part in [a, b] {
                    dec.feed_requests(part, |p| got.push(p.map(|p| (p.seq, enc(p.seq, &p.msg).unwrap()))));
                }
                prop_assert_eq!(got, vec![Ok((seq, frame.clone()))]);
                let mut copy = frame.clone();
                let p: Packet<Request> = decode(&mut copy).unwrap();
                prop_assert_eq!(p.msg, r);
            }
            // Only out-of-range values are refused, by field name.
            Err(e) => prop_assert!(matches!(e, FrameError::Invalid { .. }), "{:?}", e),
        }
    }

    /// Any bit pattern of the floats (NaN payloads included): what encodes
    /// decodes to the same bytes.
    #[test]
    fn requests_with_any_floats_round_trip_bitwise(seq: u16, r in request(any_f32)) {
        if let Ok(frame) = enc(seq, &r) {
            let mut copy = frame.clone();
            let p: Packet<Request> = decode(&mut copy).unwrap();
            prop_assert_eq!(enc(p.seq, &p.msg).unwrap(), frame);
        }
    }

    #[test]
    fn device_messages_round_trip(seq: u16, m in device_message(finite)) {
        let frame = enc(seq, &m).unwrap();
        prop_assert!(frame.len() <= MAX_FRAME);
        let mut copy = frame.clone();
        let p: Packet<DeviceMessage> = decode(&mut copy).unwrap();
        prop_assert_eq!(p.seq, seq);
        prop_assert_eq!(p.msg, m);
    }

    #[test]
    fn device_messages_with_any_floats_round_trip_bitwise(seq: u16, m in device_message(any_f32)) {
        let frame = enc(seq, &m).unwrap();
        let mut dec: FrameDecoder = FrameDecoder::new();
        let mut got = Vec::new();
        dec.feed_device_messages(&frame, |p| got.push(enc(p.as_ref().unwrap().seq, &p.unwrap().msg).unwrap()));
        prop_assert_eq!(got, vec![frame]);
    }

    /// Arbitrary bytes in arbitrary pieces: no panic, every frame that ends
    /// is either accepted or counted as rejected, nothing is lost track of.
    #[test]
    fn arbitrary_bytes_never_panic(bytes in vec(any::<u8>(), 0..2048), piece in 1usize..400) {
        let mut host: FrameDecoder = FrameDecoder::new();
        let mut dev: FrameDecoder = FrameDecoder::new();
        let (mut h, mut d) = (0u32, 0u32);
        for c in bytes.chunks(piece) {
            host.feed_device_messages(c, |_| h += 1);
            dev.feed_requests(c, |_| d += 1);
        }
        prop_assert_eq!(host.stats().ok + host.stats().rejected(), h);
        prop_assert_eq!(dev.stats().ok + dev.stats().rejected(), d);
        prop_assert!(host.pending() <= MAX_FRAME);
        let mut copy = bytes.clone();
        let _ = decode::<DeviceMessage>(&mut copy);
        let mut copy = bytes.clone();
        let _ = decode::<Request>(&mut copy);
    }

    /// Mostly-valid streams: valid frames with random bytes spliced in.
    /// Every frame not touched by garbage still decodes after a 0x00.
    #[test]
    fn garbage_between_frames_is_skipped(
        msgs in vec(device_message(finite), 1..6),
        garbage in vec(vec(any::<u8>(), 0..40), 6),
    ) {
        let mut stream = Vec::new();
        let mut expected = Vec::new();
        for (i, m) in msgs.iter().enumerate() {
            stream.extend_from_slice(&garbage[i]);
            stream.push(0); // the receiver resyncs here
            stream.extend_from_slice(&enc(i as u16, m).unwrap());
            expected.push((i as u16, m.clone()));
        }
        let mut dec: FrameDecoder = FrameDecoder::new();
        let mut got = Vec::new();
        dec.feed_device_messages(&stream, |r| if let Ok(p) = r { got.push((p.seq, p.msg)) });
        // Garbage could, with probability ~2^-32, be a valid frame itself;
        // the sent frames must all be there, in order.
        let mut it = got.iter();
        for e in &expected {
            prop_assert!(it.any(|g| g == e), "missing {:?}", e);
        }
    }

    /// A random burst of bit flips in a frame is always rejected.
    #[test]
    fn corrupted_frames_are_rejected(
        seq: u16,
        m in device_message(finite),
        flips in vec((any::<prop::sample::Index>(), 1u8..=255), 1..4),
    ) {
        let frame = enc(seq, &m).unwrap();
        let mut bad = frame.clone();
        let n = bad.len() - 1; // keep the delimiter
        for (i, x) in &flips {
            bad[i.index(n)] ^= x;
        }
        prop_assume!(bad != frame);
        let mut dec: FrameDecoder = FrameDecoder::new();
        let mut ok = 0;
        dec.feed_device_messages(&bad, |r| if r.is_ok() { ok += 1 });
        prop_assert_eq!(ok, 0);
        prop_assert!(dec.stats().rejected() >= 1);
    }

    /// Truncated frames are rejected.
    #[test]
    fn truncated_frames_are_rejected(seq: u16, m in device_message(finite), cut: prop::sample::Index) {
        let frame = enc(seq, &m).unwrap();
        let keep = cut.index(frame.len() - 1);
        let mut bad = frame[..keep].to_vec();
        bad.push(0);
        let mut dec: FrameDecoder = FrameDecoder::new();
        let mut ok = 0;
        dec.feed_device_messages(&bad, |r| if r.is_ok() { ok += 1 });
        prop_assert_eq!(ok, 0);
        prop_assert_eq!(dec.stats().rejected(), u32::from(keep > 0));
    }

    /// The blob header parser and splitter never panic on arbitrary bytes,
    /// nor on a valid header followed by arbitrary bytes.
    #[test]
    fn blob_parsing_never_panics(bytes in vec(any::<u8>(), 0..200), h in header(), body in vec(any::<u8>(), 0..64)) {
        let _ = ModelHeader::parse(&bytes);
        let _ = split_blob(&bytes);
        let mut blob = h.to_bytes().to_vec();
        blob.extend_from_slice(&body);
        let _ = ModelHeader::parse(&blob);
        let _ = split_blob(&blob);
    }
}
