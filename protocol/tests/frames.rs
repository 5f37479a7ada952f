//! Example-based tests of the framing: round trips of every message, sizes,
//! overhead, corruption, resynchronization, version mismatch.

mod common;

use std::collections::BTreeSet;

use common::*;
use spidar_protocol::blob::{BlobError, CorrectionKind, ModelHeader};
use spidar_protocol::*;

fn enc_req(seq: u16, r: &Request) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME];
    encode_request(seq, r, &mut buf).unwrap().to_vec()
}

fn enc_dev(seq: u16, m: &DeviceMessage) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME];
    encode_device_message(seq, m, &mut buf).unwrap().to_vec()
}

fn postcard_len<T: serde::Serialize>(v: &T) -> usize {
    postcard::to_slice(v, &mut [0u8; 1024]).unwrap().len()
}

/// Decodes a whole stream of device frames, collecting results.
fn decode_stream(
    dec: &mut FrameDecoder,
    bytes: &[u8],
) -> Vec<Result<Packet<DeviceMessage>, FrameError>> {
    let mut out = Vec::new();
    dec.feed_device_messages(bytes, |r| out.push(r));
    out
}

#[test]
fn samples_cover_every_variant() {
    for max in [false, true] {
        let r: BTreeSet<_> = requests(max).iter().map(request_name).collect();
        assert_eq!(r.len(), REQUEST_VARIANTS);
        let d: BTreeSet<_> = device_messages(max)
            .iter()
            .map(device_message_name)
            .collect();
        assert_eq!(d.len(), DEVICE_MESSAGE_VARIANTS, "{d:?}");
    }
}

#[test]
fn every_request_round_trips() {
    for max in [false, true] {
        for (i, r) in requests(max).iter().enumerate() {
            let seq = (i as u16).wrapping_mul(4099);
            let mut frame = enc_req(seq, r);
            assert_eq!(frame.last(), Some(&0));
            assert!(!frame[..frame.len() - 1].contains(&0));
            // Whole-frame decode.
            let mut copy = frame.clone();
            let p: Packet<Request> = decode(&mut copy).unwrap();
            assert_eq!((p.seq, p.msg), (seq, *r));
            // Streaming, one byte at a time.
            let mut dec: FrameDecoder = FrameDecoder::new();
            let mut got = Vec::new();
            for b in &frame {
                dec.feed_requests(std::slice::from_ref(b), |res| {
                    let p = res.unwrap();
                    got.push((p.seq, request_name(&p.msg), enc_req(p.seq, &p.msg)));
                });
            }
            assert_eq!(got.len(), 1);
            assert_eq!(got[0].2, frame);
            assert_eq!(dec.stats().ok, 1);
            assert_eq!(dec.stats().rejected(), 0);
            // Without the delimiter, `decode` still works.
            frame.pop();
            let p: Packet<Request> = decode(&mut frame).unwrap();
            assert_eq!(p.msg, *r);
        }
    }
}

#[test]
fn every_device_message_round_trips() {
    for max in [false, true] {
        let msgs = device_messages(max);
        let mut stream = vec![0u8]; // a leading flush delimiter is ignored
        for (i, m) in msgs.iter().enumerate() {
            let f = enc_dev(i as u16, m);
            let p: Packet<DeviceMessage> = decode(&mut f.clone()).unwrap();
            assert_eq!(p.seq, i as u16);
            assert_eq!(&p.msg, m);
            stream.extend_from_slice(&f);
        }
        // All frames back to back, fed in 7-byte chunks.
        let mut dec: FrameDecoder = FrameDecoder::new();
        let mut got = Vec::new();
        for c in stream.chunks(7) {
            got.extend(decode_stream(&mut dec, c));
        }
        let got: Vec<_> = got.into_iter().map(|r| r.unwrap().msg).collect();
        assert_eq!(got, msgs);
        assert_eq!(dec.stats().ok as usize, msgs.len());
        assert_eq!(dec.pending(), 0);
    }
}

#[test]
fn worst_case_sizes() {
    println!(
        "{:<34} {:>8} {:>8}",
        "message (worst case)", "message", "frame"
    );
    let mut largest = 0;
    for r in requests(true) {
        let m = postcard_len(&r);
        let f = enc_req(u16::MAX, &r).len();
        println!(
            "{:<34} {m:>8} {f:>8}",
            format!("Request::{}", request_name(&r))
        );
        assert!(m <= MAX_MESSAGE && f <= MAX_FRAME);
        largest = largest.max(f);
    }
    for d in device_messages(true) {
        let m = postcard_len(&d);
        let f = enc_dev(u16::MAX, &d).len();
        println!("{:<34} {m:>8} {f:>8}", device_message_name(&d));
        assert!(m <= MAX_MESSAGE && f <= MAX_FRAME);
    }
    // The bound is tight: the largest chunk frame is exactly MAX_FRAME or one less.
    println!("largest frame {largest} bytes, MAX_FRAME {MAX_FRAME}");
    assert!(largest + 1 >= MAX_FRAME);
    // A buffer one byte short of the frame is refused by name.
    let r = &requests(true)[14];
    let n = enc_req(u16::MAX, r).len();
    let mut small = vec![0u8; n - 1];
    assert_eq!(
        encode_request(u16::MAX, r, &mut small),
        Err(FrameError::BufferTooSmall { capacity: n - 1 })
    );
}

#[test]
fn state_frame_overhead() {
    for (label, s, seq) in [
        ("typical", state(false), 1234u16),
        ("worst case", state(true), u16::MAX),
    ] {
        let msg = DeviceMessage::State(s);
        let state_bytes = postcard_len(&s);
        let message_bytes = postcard_len(&msg);
        let frame_bytes = enc_dev(seq, &msg).len();
        let overhead = frame_bytes - state_bytes;
        println!(
            "State frame ({label}): State {state_bytes} B, message {message_bytes} B, frame {frame_bytes} B on the wire, \
             protocol overhead {overhead} B (tag 1 + seq {} + CRC 4 + COBS {} + delimiter 1)",
            postcard_len(&seq),
            frame_bytes - 1 - (message_bytes + postcard_len(&seq) + CRC_LEN),
        );
        assert!(overhead <= 11, "{overhead}");
    }
}

#[test]
fn every_single_bit_flip_is_rejected_and_counted() {
    let frames = [
        enc_dev(7, &DeviceMessage::State(state(false))),
        enc_dev(8, &device_messages(false)[3]),
        enc_req(9, &requests(false)[14]),
    ];
    let good = enc_dev(42, &DeviceMessage::Reply(Response::Ack));
    for (k, frame) in frames.iter().enumerate() {
        for byte in 0..frame.len() {
            for bit in 0..8 {
                let mut bad = frame.clone();
                bad[byte] ^= 1 << bit;
                // A flip may turn a byte into 0x00 (two pieces) or the
                // delimiter into data (the bad frame swallows the next one):
                // follow with a flush and a good frame to check resync.
                let mut stream = bad;
                stream.push(0);
                stream.extend_from_slice(&good);
                if k < 2 {
                    let mut dec: FrameDecoder = FrameDecoder::new();
                    let got = decode_stream(&mut dec, &stream);
                    let (ok, err): (Vec<_>, Vec<_>) = got.into_iter().partition(|r| r.is_ok());
                    assert!(!err.is_empty(), "frame {k} byte {byte} bit {bit}");
                    assert_eq!(ok.len(), 1, "frame {k} byte {byte} bit {bit}");
                    assert_eq!(ok[0].as_ref().unwrap().seq, 42);
                    assert_eq!(dec.stats().rejected() as usize, err.len());
                } else {
                    let mut dec: FrameDecoder = FrameDecoder::new();
                    let mut oks = 0;
                    let mut errs = 0;
                    dec.feed_requests(&stream[..stream.len() - good.len()], |r| match r {
                        Ok(_) => oks += 1,
                        Err(_) => errs += 1,
                    });
                    assert_eq!(oks, 0, "byte {byte} bit {bit}");
                    assert!(errs >= 1);
                    assert_eq!(dec.stats().rejected(), errs);
                }
            }
        }
    }
}

#[test]
fn every_truncation_is_rejected_and_counted() {
    let frame = enc_dev(3, &DeviceMessage::State(state(false)));
    let body = &frame[..frame.len() - 1];
    for cut in 1..body.len() {
        let mut stream = body[..cut].to_vec();
        stream.push(0);
        let mut dec: FrameDecoder = FrameDecoder::new();
        let got = decode_stream(&mut dec, &stream);
        assert_eq!(got.len(), 1);
        let e = got[0].as_ref().unwrap_err();
        assert!(
            matches!(
                e,
                FrameError::Cobs | FrameError::Crc { .. } | FrameError::TooShort { .. }
            ),
            "cut {cut}: {e:?}"
        );
        assert_eq!(dec.stats().rejected(), 1);
    }
}

#[test]
fn overlong_frame_is_reported_once_then_resyncs() {
    let good = enc_dev(5, &DeviceMessage::Reply(Response::Ack));
    let mut stream = vec![0x11u8; 3 * MAX_FRAME];
    stream.push(0);
    stream.extend_from_slice(&good);
    for chunk in [1, 13, stream.len()] {
        let mut dec: FrameDecoder = FrameDecoder::new();
        let mut got = Vec::new();
        for c in stream.chunks(chunk) {
            got.extend(decode_stream(&mut dec, c));
        }
        assert_eq!(got.len(), 2, "chunk {chunk}");
        assert_eq!(got[0], Err(FrameError::Overlong { limit: MAX_FRAME }));
        assert_eq!(got[1].as_ref().unwrap().seq, 5);
        assert_eq!(dec.stats().overlong, 1);
        assert_eq!(dec.stats().ok, 1);
    }
    // A smaller decoder rejects a frame that fits a bigger one.
    let big = enc_req(1, &requests(true)[14]);
    let mut dec = FrameDecoder::<64>::new();
    let mut errs = Vec::new();
    dec.feed_requests(&big, |r| errs.push(r.map(|p| p.seq)));
    assert_eq!(errs, vec![Err(FrameError::Overlong { limit: 64 })]);
}

#[test]
fn rejection_reasons_are_named() {
    let mut dec: FrameDecoder = FrameDecoder::new();
    // Bad COBS: a code byte pointing past the end.
    let r = decode_stream(&mut dec, &[0x05, 0x01, 0x02, 0x00]);
    assert_eq!(r, vec![Err(FrameError::Cobs)]);
    // Too short: 3 bytes.
    let r = decode_stream(&mut dec, &[0x04, 0x01, 0x02, 0x03, 0x00]);
    assert_eq!(r, vec![Err(FrameError::TooShort { len: 3 })]);
    // Unknown message tag with a good CRC.
    let r = decode_stream(&mut dec, &raw_frame(&[0x01, 0x7f]));
    assert_eq!(r, vec![Err(FrameError::Payload(PayloadError::BadValue))]);
    // Good message followed by extra bytes.
    let r = decode_stream(&mut dec, &raw_frame(&[0x01, 0x00, 0x01, 0x33]));
    assert_eq!(r, vec![Err(FrameError::TrailingBytes { extra: 1 })]);
    // A message that ends early.
    let r = decode_stream(&mut dec, &raw_frame(&[0x01, 0x01]));
    assert_eq!(
        r,
        vec![Err(FrameError::Payload(PayloadError::UnexpectedEnd))]
    );
    // A state frame naming string 9 as excluded.
    let mut s = state(false);
    s.excluded = Some(9);
    let mut payload = to_vec(&(1u16, DeviceMessage::State(s)));
    let r = decode_stream(&mut dec, &raw_frame(&payload));
    assert_eq!(
        r,
        vec![Err(FrameError::Invalid {
            field: "excluded",
            seq: 1
        })]
    );
    // Bad CRC.
    let mut f = raw_frame(&payload);
    payload.clear();
    f[5] ^= 0x01;
    let r = decode_stream(&mut dec, &f);
    assert!(matches!(r[..], [Err(FrameError::Crc { .. })]), "{r:?}");
    let s = dec.stats();
    assert_eq!(
        (s.cobs, s.too_short, s.payload, s.invalid, s.crc, s.ok),
        (1, 1, 3, 1, 1, 0)
    );
    assert_eq!(s.rejected(), 7);
    // The decoder counts the same way on the device side.
    let mut dec: FrameDecoder = FrameDecoder::new();
    dec.feed_requests(&[0x05, 0x01, 0x00], |_| {});
    assert_eq!(dec.stats().cobs, 1);
}

#[test]
fn invalid_values_are_refused_when_encoding_and_decoding() {
    let mut buf = [0u8; MAX_FRAME];
    let cases: Vec<(Request, &str)> = vec![
        (
            Request::SetForceTarget {
                force_n: [0.0, f32::NAN, 0.0],
            },
            "force_n",
        ),
        (
            Request::SetGuidanceTarget {
                target_mm: [0.0; 3],
                d_min_mm: -1.0,
                f_max_n: 1.0,
            },
            "d_min_mm",
        ),
        (
            Request::SetGuidanceTarget {
                target_mm: [0.0; 3],
                d_min_mm: 1.0,
                f_max_n: f32::INFINITY,
            },
            "f_max_n",
        ),
        (
            Request::SetLimits(Limits {
                pre_tension_n: 2.0,
                max_tension_n: 1.0,
                heartbeat_timeout_ms: 100,
            }),
            "max_tension_n",
        ),
        (
            Request::SetLimits(Limits {
                pre_tension_n: 0.5,
                max_tension_n: 1.0,
                heartbeat_timeout_ms: 0,
            }),
            "heartbeat_timeout_ms",
        ),
        (Request::StreamOn { decimation: 0 }, "decimation"),
        (
            Request::UploadChunk {
                offset: 0,
                data: &[],
            },
            "data",
        ),
        (
            Request::UploadChunk {
                offset: 0,
                data: &[1u8; MAX_CHUNK + 1],
            },
            "data",
        ),
        (
            Request::UploadChunk {
                offset: u32::MAX,
                data: &[1u8; 2],
            },
            "offset",
        ),
        (
            Request::SetNominalGeometry(string_model(0)),
            "counts_per_rev",
        ),
    ];
    for (r, field) in cases {
        assert_eq!(
            encode_request(1, &r, &mut buf),
            Err(FrameError::Invalid { field, seq: 1 })
        );
        // Sent anyway by a broken peer: the decoder refuses it too.
        let payload = to_vec(&(1u16, r));
        let mut f = raw_frame(&payload);
        assert_eq!(
            decode::<Request>(&mut f),
            Err(FrameError::Invalid { field, seq: 1 })
        );
    }
    let mut m = string_model(4096);
    m.pulley_radius_mm[3] = 0.0;
    assert_eq!(
        encode_request(1, &Request::SetNominalGeometry(m), &mut buf),
        Err(FrameError::Invalid {
            field: "pulley_radius_mm",
            seq: 1
        })
    );
    let mut m = string_model(4096);
    m.anchors_mm[7][2] = f32::NEG_INFINITY;
    assert_eq!(
        encode_request(1, &Request::SetNominalGeometry(m), &mut buf),
        Err(FrameError::Invalid {
            field: "anchors_mm",
            seq: 1
        })
    );
}

#[test]
fn hello_layout_is_frozen() {
    // These bytes must never change (see `messages` docs): a device or host of
    // any protocol version must recognise them.
    let f = enc_req(
        0x0102,
        &Request::Hello {
            protocol_version: 1,
        },
    );
    let mut payload = to_vec(&(
        0x0102u16,
        Request::Hello {
            protocol_version: 1,
        },
    ));
    assert_eq!(payload, [0x82, 0x02, 0x00, 0x01]);
    payload.extend_from_slice(
        &spidar_protocol::blob::CRC32
            .checksum(&payload)
            .to_le_bytes(),
    );
    assert_eq!(f, raw_frame(&payload[..4]));
    // A Hello from any version decodes, so the device can answer it.
    let mut f = enc_req(
        3,
        &Request::Hello {
            protocol_version: 77,
        },
    );
    let p: Packet<Request> = decode(&mut f).unwrap();
    assert_eq!(
        p.msg,
        Request::Hello {
            protocol_version: 77
        }
    );
    // HelloAck starts with tag 0 (Reply), tag 0 (HelloAck), protocol_version.
    let ack = &device_messages(false)[0];
    let bytes = to_vec(ack);
    assert_eq!(&bytes[..3], &[0x00, 0x00, PROTOCOL_VERSION as u8]);
}

#[test]
fn newer_hello_ack_is_a_version_mismatch() {
    // A device of a newer protocol version whose HelloAck has another layout.
    let newer = PROTOCOL_VERSION as u8 + 1;
    let mut dec: FrameDecoder = FrameDecoder::new();
    let r = decode_stream(&mut dec, &raw_frame(&[0x09, 0x00, 0x00, newer, 0xff]));
    assert_eq!(
        r,
        vec![Err(FrameError::VersionMismatch {
            peer: u16::from(newer),
            ours: PROTOCOL_VERSION,
            seq: 9
        })]
    );
    assert_eq!(dec.stats().version, 1);
    assert!(r[0]
        .as_ref()
        .unwrap_err()
        .to_string()
        .contains("version mismatch"));
    // Same on the device side for a future Hello with extra fields.
    let mut f = raw_frame(&[0x04, 0x00, newer + 1, 0x01, 0x02]);
    assert_eq!(
        decode::<Request>(&mut f),
        Err(FrameError::VersionMismatch {
            peer: u16::from(newer + 1),
            ours: PROTOCOL_VERSION,
            seq: 4
        })
    );
    // The same bytes with our own version are just an undecodable frame.
    let mut f = raw_frame(&[0x04, 0x00, PROTOCOL_VERSION as u8, 0x01, 0x02]);
    assert_eq!(
        decode::<Request>(&mut f),
        Err(FrameError::TrailingBytes { extra: 2 })
    );
}

#[test]
fn upload_chunk_data_is_borrowed_from_the_decoder() {
    let data: Vec<u8> = (0..=255u8).collect();
    let f = enc_req(
        11,
        &Request::UploadChunk {
            offset: 1024,
            data: &data,
        },
    );
    let mut dec: FrameDecoder = FrameDecoder::new();
    let mut seen = None;
    dec.feed_requests(&f, |r| {
        if let Ok(Packet {
            seq,
            msg: Request::UploadChunk { offset, data },
        }) = r
        {
            seen = Some((seq, offset, data.to_vec()));
        }
    });
    assert_eq!(seen, Some((11, 1024, data)));
}

#[test]
fn seq_tracker_counts_gaps_across_wrap() {
    let mut t = SeqTracker::default();
    assert_eq!(t.observe(65533), 0);
    assert_eq!(t.observe(65534), 0);
    assert_eq!(t.observe(1), 2); // 65535 and 0 lost
    assert_eq!(t.observe(2), 0);
    assert_eq!(t.observe(2), 0); // duplicate
    assert_eq!((t.received, t.lost, t.stale), (5, 2, 1));
}

#[test]
fn blob_errors_travel_with_their_field_names() {
    let e = BlobError::Dimension {
        field: "hidden",
        found: 30,
        expected: 20,
    };
    let w = BlobRejection::from(e);
    let msg = DeviceMessage::Reply(Response::Error(DeviceError::BlobRejected(w.clone())));
    let mut f = enc_dev(1, &msg);
    let p: Packet<DeviceMessage> = decode(&mut f).unwrap();
    assert_eq!(p.msg, msg);
    let text = DeviceError::BlobRejected(w).to_string();
    assert_eq!(
        text,
        "model blob rejected: model blob field `hidden` is 30, the evaluator needs 20"
    );
    // Long names are cut, not refused.
    let long = BlobRejection::from(BlobError::Body {
        field: "a_very_long_field_name_of_the_svr_body",
    });
    match long {
        BlobRejection::Body { field } => assert_eq!(field.len(), MAX_NAME),
        other => panic!("{other:?}"),
    }
    // Every BlobError converts to the same-named variant.
    let all: [BlobError; 7] = [
        BlobError::Truncated { needed: 1, got: 0 },
        BlobError::TrailingBytes { extra: 1 },
        BlobError::BadMagic,
        BlobError::UnsupportedVersion {
            found: 2,
            supported: 1,
        },
        BlobError::UnknownKind { found: 3 },
        BlobError::HeaderCrc {
            stored: 1,
            computed: 2,
        },
        BlobError::BodyCrc {
            stored: 1,
            computed: 2,
        },
    ];
    for e in all {
        assert_eq!(
            e.to_string().to_string(),
            BlobRejection::from(e).to_string()
        );
    }
}

#[test]
fn model_info_carries_the_header() {
    let h = ModelHeader {
        kind: CorrectionKind::Nn,
        ..header(false)
    };
    let m = DeviceMessage::Reply(Response::Info(Some(ModelInfo {
        slot: 1,
        header: h,
        blob_crc32: 0xabcd,
    })));
    let mut f = enc_dev(2, &m);
    assert_eq!(decode::<DeviceMessage>(&mut f).unwrap().msg, m);
}

#[test]
fn q16_helper() {
    assert_eq!(spidar_protocol::messages::q16_to_mm(65536 * 3 / 2), 1.5);
    assert_eq!(spidar_protocol::messages::q16_to_mm(-65536), -1.0);
}
