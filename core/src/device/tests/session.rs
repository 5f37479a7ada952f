//! One session over the frames, phase by phase.

use super::bench::{
    bad_state, calibration, config, nn, raw_at, string_model, unchecked_frame, Bench, Flash,
    FutureHello, SLOT,
};
use crate::blob::compile;
use crate::device::*;
use crate::safety::SafetyFaults;
use crate::test_fixtures::cube_anchors;
use spidar_protocol::blob::{CorrectionKind, CRC32};
use spidar_protocol::messages::name;
use spidar_protocol::{
    encode, encode_request, BadState, DeviceError, DeviceMessage, Request, Response, State,
    UploadState, MAX_FRAME,
};
use std::vec::Vec;

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
