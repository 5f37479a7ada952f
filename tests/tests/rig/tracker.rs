//! Tracker input: DTrack2/DTrack3 datagrams (real-format examples, ts2,
//! hybrid bodies, the SDK's tolerance, skipped records, typed errors,
//! arbitrary bytes), the UDP receiver over loopback (loss, duplicates,
//! reordering, occlusion, bad datagrams, midnight, restarts), the CSV replay
//! of the shared example session, and the time-shift estimate. Every socket
//! is on 127.0.0.1; every loop is bounded.

use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use proptest::prelude::*;
use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use spidar::device::tracker::dtrack::{
    format_datagram, parse_datagram, BodyPose, DtrackError, DtrackFrame, FieldProblem,
};
use spidar::device::tracker::receiver::Reorder;
use spidar::device::tracker::{
    collect, estimate_time_shift, DtrackReceiver, Next, Pacing, ReceiverConfig, ReplaySource,
    ShiftConfig, SyncError, TimedPosition, TrackerError, TrackerFrame, TrackerSource,
};
use spidar::sim::tracker::{SimReport, SimSender, SimSenderConfig};

const LOOPBACK_ANY_PORT: &str = "127.0.0.1:0";

/// The example of the DTrack2 manual (B.2.1-B.2.3) as one datagram.
const MANUAL: &str = "fr 21753\r\nts 39596.024470\r\n6dcal 2\r\n6d 1 [0 1.000][326.848 -187.216 109.503 -160.4704 -3.6963 -7.0913][-0.940508 -0.339238 0.019025 0.333599 -0.932599 -0.137735 0.064467 -0.123194 0.990286]\r\n";

fn loopback() -> SocketAddr {
    LOOPBACK_ANY_PORT.parse().unwrap()
}

// ---------------------------------------------------------------------------
// Parsing
// ---------------------------------------------------------------------------

#[test]
fn parses_the_manual_example() {
    let f = parse_datagram(MANUAL.as_bytes()).unwrap();
    assert_eq!(f.frame, 21753);
    assert_eq!(f.ts_s, Some(39596.024470));
    assert_eq!(f.calibrated_bodies, Some(2));
    assert!(f.has_6d);
    assert_eq!(f.bodies.len(), 1);
    let b = &f.bodies[0];
    assert_eq!(b.id, 0);
    assert_eq!(b.quality, 1.0);
    assert_eq!(b.position_mm, [326.848, -187.216, 109.503]);
    // b0..b8 column-wise: the first row is b0 b3 b6.
    let r = b.rotation.expect("a 6d body has a rotation");
    assert_eq!(r[0], [-0.940508, 0.333599, 0.064467]);
    assert_eq!(r[1], [-0.339238, -0.932599, -0.123194]);
    assert_eq!(r[2], [0.019025, -0.137735, 0.990286]);
    assert_eq!(f.visible_body(0), Some(b));
    assert_eq!(f.visible_body(1), None);
}

#[test]
fn accepts_bare_lf_and_several_bodies() {
    let d = "fr 7\nts 1.5\n6d 2 [3 1.000][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1] [5 0.5][4 5 6 0 0 0][1 0 0 0 1 0 0 0 1]\n";
    let f = parse_datagram(d.as_bytes()).unwrap();
    assert_eq!(f.bodies.iter().map(|b| b.id).collect::<Vec<_>>(), [3, 5]);
    assert_eq!(f.visible_body(5).unwrap().position_mm, [4.0, 5.0, 6.0]);
}

#[test]
fn skips_records_it_does_not_use() {
    let d = "fr 10\r\nts 2.0\r\n6dcal 3\r\n\
             3d 2 [1 1.000][1.0 2.0 3.0] [2 1.000][4.0 5.0 6.0]\r\n\
             6dcov 1 [0 0 0 0][0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0]\r\n\
             6df2 1 1 [0 1.000 2 4][1 2 3][1 0 0 0 1 0 0 0 1][0 0 0 0]\r\n\
             6dmt 1 [0 -1.000 0][0 0 0][0 0 0 0 0 0 0 0 0]\r\n\
             6dj 1 1 [0 1][0 1.000][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1]\r\n\
             gl 1 [0 1.000 0 3][1 2 3][1 0 0 0 1 0 0 0 1] whatever [[[\r\n\
             st 1 [0 x y]\r\n\
             6d 0\r\n";
    let f = parse_datagram(d.as_bytes()).unwrap();
    assert_eq!(f.frame, 10);
    assert!(f.has_6d);
    assert!(f.bodies.is_empty());
    assert_eq!(f.visible_body(0), None);
}

#[test]
fn occlusion_is_no_visible_body() {
    // Not listed (the 6d record lists tracked bodies only).
    let f = parse_datagram(b"fr 1\r\nts 0.1\r\n6d 0\r\n").unwrap();
    assert_eq!(f.visible_body(0), None);
    // No 6d record at all.
    let f = parse_datagram(b"fr 1\r\nts 0.1\r\n").unwrap();
    assert!(!f.has_6d);
    assert_eq!(f.visible_body(0), None);
    // Listed with a negative quality.
    let f = parse_datagram(b"fr 1\r\n6d 1 [0 -1.000][0 0 0 0 0 0][0 0 0 0 0 0 0 0 0]\r\n").unwrap();
    assert_eq!(f.bodies.len(), 1);
    assert_eq!(f.visible_body(0), None);
}

/// The error of a malformed datagram names the line and the field.
fn field_error(d: &str) -> (usize, String, FieldProblem) {
    match parse_datagram(d.as_bytes()) {
        Err(DtrackError::Field {
            line,
            field,
            problem,
        }) => {
            let e = DtrackError::Field {
                line,
                field: field.clone(),
                problem: problem.clone(),
            };
            assert!(e.to_string().contains(&field), "{e}");
            (line, field, problem)
        }
        other => panic!("{d:?}: expected a field error, got {other:?}"),
    }
}

#[test]
fn malformed_known_records_name_the_field() {
    let body = "[0 1.0][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1]";
    let cases: Vec<(String, usize, &str)> = vec![
        ("fr x\r\n".into(), 1, "fr"),
        ("fr\r\n".into(), 1, "fr"),
        ("fr -3\r\n".into(), 1, "fr"),
        ("fr 1\r\nts abc\r\n".into(), 2, "ts"),
        ("fr 1\r\nts inf\r\n".into(), 2, "ts"),
        ("fr 1\r\nts\r\n".into(), 2, "ts"),
        ("fr 1\r\nts2\r\n".into(), 2, "ts2 seconds"),
        ("fr 1\r\nts2 1.5 0 0\r\n".into(), 2, "ts2 seconds"),
        ("fr 1\r\nts2 -1 0 0\r\n".into(), 2, "ts2 seconds"),
        ("fr 1\r\nts2 1700000000\r\n".into(), 2, "ts2 microseconds"),
        (
            "fr 1\r\nts2 1700000000 0.5 0\r\n".into(),
            2,
            "ts2 microseconds",
        ),
        (
            "fr 1\r\nts2 1700000000 1000000 0\r\n".into(),
            2,
            "ts2 microseconds",
        ),
        ("fr 1\r\nts2 1700000000 5 x\r\n".into(), 2, "ts2 latency"),
        ("fr 1\r\nts2 1700000000 5 -7\r\n".into(), 2, "ts2 latency"),
        // The ts line is checked even though ts2 gives the time.
        ("fr 1\r\nts2 1700000000 5 7\r\nts x\r\n".into(), 3, "ts"),
        ("fr 1\r\n6dcal -1\r\n".into(), 2, "6dcal"),
        ("fr 1\r\n6d\r\n".into(), 2, "6d count"),
        (format!("fr 1\r\n6d x {body}\r\n"), 2, "6d count"),
        (
            "fr 1\r\n6d 1 [0 1.0][1 2 3 0 0 0][1 0 0]\r\n".into(),
            2,
            "6d body 1: [b0..b8]",
        ),
        (
            "fr 1\r\n6d 1 [0 1.0][1 2][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6d body 1: [sx sy sz]",
        ),
        (
            "fr 1\r\n6d 1 [0 1.0][1 2 zz 0 0 0][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6d body 1: [sx sy sz][2]",
        ),
        (
            "fr 1\r\n6d 1 [0 1.0][1 2 3][1 0 0 0 1 0 0 x 1]\r\n".into(),
            2,
            "6d body 1: [b0..b8][7]",
        ),
        (
            "fr 1\r\n6d 1 [0 good][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6d body 1: qu",
        ),
        (
            "fr 1\r\n6d 1 [1.5 1.0][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6d body 1: id",
        ),
        (
            "fr 1\r\n6d 1 [0][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6d body 1: [id qu]",
        ),
        // A count larger than the bodies present: the bodies present are
        // still read, and checked.
        (
            format!("fr 1\r\n6d 3 {body} [1 q][1 2 3][1 0 0 0 1 0 0 0 1]\r\n"),
            2,
            "6d body 2: qu",
        ),
        ("fr 1\r\n6di\r\n".into(), 2, "6di count"),
        (
            "fr 1\r\n6di 1 [0 2][1 2 3][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6di body 1: [id st error]",
        ),
        (
            "fr 1\r\n6di 1 [0 x 0.1][1 2 3][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6di body 1: st",
        ),
        (
            "fr 1\r\n6di 1 [0 2 e][1 2 3][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6di body 1: error",
        ),
        (
            "fr 1\r\n6di 1 [0 2 0.1][1 2][1 0 0 0 1 0 0 0 1]\r\n".into(),
            2,
            "6di body 1: [sx sy sz]",
        ),
    ];
    for (d, line, field) in cases {
        let (l, f, _) = field_error(&d);
        assert_eq!((l, f.as_str()), (line, field), "{d:?}");
    }
    assert_eq!(
        field_error("fr 1\r\n6d 1 [0 1.0][1 2][1 0 0 0 1 0 0 0 1]\r\n").2,
        FieldProblem::BlockLength {
            expected: 3,
            found: 2
        }
    );
    assert_eq!(
        field_error("fr 1\r\nts2 1700000000 1000000 0\r\n").2,
        FieldProblem::NotBelow {
            text: "1000000".into(),
            limit: 1_000_000
        }
    );
}

#[test]
fn datagram_level_errors() {
    assert_eq!(parse_datagram(b""), Err(DtrackError::Empty));
    assert_eq!(parse_datagram(b"\r\n \r\n"), Err(DtrackError::Empty));
    assert_eq!(
        parse_datagram(b"ts 1.0\r\n6d 0\r\n"),
        Err(DtrackError::MissingFrameCounter)
    );
    assert_eq!(
        parse_datagram(b"fr 1\r\n\xff\xfe"),
        Err(DtrackError::NotText { offset: 6 })
    );
    // The first NUL ends the datagram: nothing before it is nothing.
    assert_eq!(
        parse_datagram(b"\0fr 1\r\nts 1.0\r\n"),
        Err(DtrackError::Empty)
    );
    assert_eq!(parse_datagram(b" \r\n\0\0\0"), Err(DtrackError::Empty));
}

// ---------------------------------------------------------------------------
// What real DTrack output contains (DTrack3 records, SDK tolerance)
// ---------------------------------------------------------------------------

/// One complete standard body `id` at `p` (identity rotation).
fn body_text(id: u32, p: [i32; 3]) -> String {
    format!(
        "[{id} 1.000][{} {} {}][1 0 0 0 1 0 0 0 1]",
        p[0], p[1], p[2]
    )
}

fn ids(f: &DtrackFrame) -> Vec<u32> {
    f.bodies.iter().map(|b| b.id).collect()
}

/// 2023-11-14 00:00:00 UTC, seconds since 1970.
const DAY_START_1970_S: u64 = 19_675 * 86_400;

#[test]
fn ts2_alone_gives_the_time_of_day() {
    // The manual's time of day, 10:59:56.024470 UTC, as DTrack3's ts2.
    let secs = DAY_START_1970_S + 39_596;
    let d = format!("fr 21753\r\nts2 {secs} 24470 1800\r\n6d 0\r\n");
    let f = parse_datagram(d.as_bytes()).unwrap();
    // Exactly the f64 that `ts 39596.024470` gives: the same clock.
    assert_eq!(f.ts_s, parse_datagram(MANUAL.as_bytes()).unwrap().ts_s);
    assert_eq!(f.ts_s, Some(39596.024470));
    // Without the latency field, and with values after it: the same time.
    for tail in ["", " 1800 extra 3"] {
        let d = format!("fr 1\r\nts2 {secs} 24470{tail}\r\n");
        assert_eq!(
            parse_datagram(d.as_bytes()).unwrap().ts_s,
            Some(39596.024470)
        );
    }
    // Midnight and the last microsecond of the day.
    let f = parse_datagram(format!("fr 1\r\nts2 {DAY_START_1970_S} 0 0\r\n").as_bytes());
    assert_eq!(f.unwrap().ts_s, Some(0.0));
    let last = DAY_START_1970_S + 86_399;
    let f = parse_datagram(format!("fr 1\r\nts2 {last} 999999 0\r\n").as_bytes());
    assert_eq!(f.unwrap().ts_s, Some(86_399.999999));
}

#[test]
fn ts2_latency_is_read_and_checked() {
    let secs = DAY_START_1970_S + 10;
    for latency in ["0", "1800", "4294967295"] {
        let d = format!("fr 1\r\nts2 {secs} 500000 {latency}\r\n");
        assert_eq!(parse_datagram(d.as_bytes()).unwrap().ts_s, Some(10.5));
    }
    for latency in ["1.5", "-1", "lat", "4294967296"] {
        let d = format!("fr 1\r\nts2 {secs} 500000 {latency}\r\n");
        let (line, field, problem) = field_error(&d);
        assert_eq!((line, field.as_str()), (2, "ts2 latency"), "{d:?}");
        assert_eq!(problem, FieldProblem::NotAnInteger(latency.into()));
    }
}

#[test]
fn ts2_is_preferred_to_ts() {
    // Both given (and here disagreeing, to tell them apart): ts2, in either
    // order.
    let ts2 = format!("ts2 {} 250000 900", DAY_START_1970_S + 200);
    for d in [
        format!("fr 1\r\nts 100.5\r\n{ts2}\r\n"),
        format!("fr 1\r\n{ts2}\r\nts 100.5\r\n"),
    ] {
        assert_eq!(parse_datagram(d.as_bytes()).unwrap().ts_s, Some(200.25));
    }
    // Agreeing, as DTrack writes them: the same value either way.
    let d = format!(
        "fr 1\r\nts 39596.024470\r\nts2 {} 24470 1800\r\n",
        DAY_START_1970_S + 39_596
    );
    assert_eq!(
        parse_datagram(d.as_bytes()).unwrap().ts_s,
        Some(39596.024470)
    );
}

#[test]
fn a_ts2_stream_unwraps_at_midnight_like_ts() {
    let mut rx = receiver(2, 10_000);
    let now = Instant::now();
    let day = DAY_START_1970_S;
    let text = |n: u32, secs: u64, us: u32| {
        format!(
            "fr {n}\r\nts2 {secs} {us} 2000\r\n6d 1 {}\r\n",
            body_text(0, [1, 2, 3])
        )
    };
    // 23:59:59.99, then 00:00:00.01 and 00:00:01.5 of the next day.
    rx.accept(text(10, day + 86_399, 990_000).as_bytes(), now);
    rx.accept(text(11, day + 86_400, 10_000).as_bytes(), now);
    rx.accept(text(12, day + 86_401, 500_000).as_bytes(), now);
    // A set-up switched to ts: the same clock, no jump.
    rx.accept(frame_text(13, 1.51).as_bytes(), now);
    let frames = rx.drain();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [10, 11, 12, 13]
    );
    let ts: Vec<f64> = frames.iter().map(|f| f.ts_s).collect();
    let expected = [86_399.99, 86_400.01, 86_401.5, 86_401.51];
    for (t, e) in ts.iter().zip(expected) {
        assert!((t - e).abs() < 1e-6, "{ts:?}");
    }
    let s = rx.stats();
    assert_eq!((s.delivered, s.malformed, s.lost, s.restarts), (4, 0, 0, 0));
}

#[test]
fn values_after_those_read_are_ignored() {
    let d = format!(
        "fr 123 456\r\nts 1.5 extra\r\n6dcal 2 7\r\n6d 1 {} trailing words\r\n",
        body_text(4, [1, 2, 3])
    );
    let f = parse_datagram(d.as_bytes()).unwrap();
    assert_eq!(
        (f.frame, f.ts_s, f.calibrated_bodies),
        (123, Some(1.5), Some(2))
    );
    assert_eq!(ids(&f), [4]);
    // Extra values inside blocks (the SDK reads the first ones of each),
    // and text between blocks.
    let d = "fr 1\r\n6d 1 [0 0.9 x] junk [1 2 3 4 5 6 7][1 0 0 0 1 0 0 0 1 0.5]\r\n";
    let f = parse_datagram(d.as_bytes()).unwrap();
    let b = &f.bodies[0];
    assert_eq!((b.id, b.quality), (0, 0.9));
    assert_eq!(b.position_mm, [1.0, 2.0, 3.0]);
    assert_eq!(b.rotation, Some(spidar::device::tracker::dtrack::IDENTITY));
}

#[test]
fn the_dtrack3_position_block_of_three_values() {
    // The manual's example as later DTrack versions write it: no angles.
    let short = MANUAL.replace(
        "[326.848 -187.216 109.503 -160.4704 -3.6963 -7.0913]",
        "[326.848 -187.216 109.503]",
    );
    assert_ne!(short, MANUAL);
    assert_eq!(
        parse_datagram(short.as_bytes()),
        parse_datagram(MANUAL.as_bytes())
    );
}

#[test]
fn a_body_count_larger_than_the_bodies_reads_those_present() {
    let (b0, b1) = (body_text(0, [1, 2, 3]), body_text(1, [4, 5, 6]));
    let cases = [
        // Two complete bodies for a count of 3.
        (format!("6d 3 {b0} {b1}"), vec![0, 1]),
        // The second body lacks its rotation block: cut off, left out.
        (format!("6d 2 {b0} [1 1.000][4 5 6]"), vec![0]),
        (format!("6d 2 {b0} [1 1.000]"), vec![0]),
        // ... or its last block has no `]`.
        (format!("6d 2 {b0} [1 1.000][4 5 6][1 0 0 0 1"), vec![0]),
        ("6d 1 [0 1.0][1 2 3 0 0 0][1 0 0".to_string(), vec![]),
        // A huge count allocates nothing for absent bodies.
        (format!("6d 4294967295 {b0}"), vec![0]),
    ];
    for (record, want) in cases {
        let d = format!("fr 9\r\nts 1.0\r\n{record}\r\n");
        let f = parse_datagram(d.as_bytes()).unwrap_or_else(|e| panic!("{d:?}: {e}"));
        assert!(f.has_6d);
        assert_eq!(ids(&f), want, "{d:?}");
    }
}

#[test]
fn a_body_count_smaller_than_the_bodies_reads_the_count() {
    let (b0, b1) = (body_text(0, [1, 2, 3]), body_text(1, [4, 5, 6]));
    let d = format!("fr 9\r\n6d 1 {b0} {b1}\r\n");
    assert_eq!(ids(&parse_datagram(d.as_bytes()).unwrap()), [0]);
    // Unread bodies are not checked.
    let d = format!("fr 9\r\n6d 1 {b0} [1 bad][x][y]\r\n");
    assert_eq!(ids(&parse_datagram(d.as_bytes()).unwrap()), [0]);
    let d = format!("fr 9\r\n6d 0 {b0}\r\n");
    let f = parse_datagram(d.as_bytes()).unwrap();
    assert!(f.has_6d && f.bodies.is_empty());
}

#[test]
fn a_repeated_record_keeps_its_first_line() {
    let d = format!(
        "fr 1\r\nts 1.5\r\n6dcal 2\r\n6d 1 {}\r\n\
         fr 2\r\nts 9.5\r\n6dcal 5\r\n6d 1 {}\r\n\
         fr x\r\nts nan\r\n6d 1 [bad]\r\n",
        body_text(0, [1, 2, 3]),
        body_text(7, [4, 5, 6])
    );
    let f = parse_datagram(d.as_bytes()).unwrap();
    assert_eq!(
        (f.frame, f.ts_s, f.calibrated_bodies),
        (1, Some(1.5), Some(2))
    );
    assert_eq!(ids(&f), [0]);
    assert_eq!(f.bodies[0].position_mm, [1.0, 2.0, 3.0]);
    let secs = DAY_START_1970_S;
    let d = format!("fr 1\r\nts2 {secs} 1 0\r\nts2 {secs} 2 0\r\n");
    assert_eq!(parse_datagram(d.as_bytes()).unwrap().ts_s, Some(1e-6));
}

#[test]
fn a_bare_cr_ends_a_line() {
    let b = body_text(3, [1, 2, 3]);
    for d in [
        format!("fr 7\rts 1.5\r6d 1 {b}\r"),
        format!("fr 7\rts 1.5\r6d 1 {b}"),
        // Mixed: CR, CR LF, LF.
        format!("fr 7\rts 1.5\r\n6d 1 {b}\n"),
    ] {
        let f = parse_datagram(d.as_bytes()).unwrap_or_else(|e| panic!("{d:?}: {e}"));
        assert_eq!((f.frame, f.ts_s), (7, Some(1.5)), "{d:?}");
        assert_eq!(ids(&f), [3], "{d:?}");
    }
    // Lines are counted as a reader sees them: CR LF is one line end.
    assert_eq!(field_error("fr 1\rts x\r").0, 2);
    assert_eq!(field_error("fr 1\r\n\r\nts x\r\n").0, 3);
    assert_eq!(field_error("fr 1\r\rts x\r").0, 3);
}

#[test]
fn a_nul_ends_the_datagram() {
    let good = format!("fr 5\r\nts 2.5\r\n6d 1 {}", body_text(0, [1, 2, 3]));
    let want = parse_datagram(good.as_bytes()).unwrap();
    let tails: [&[u8]; 7] = [
        b"\r\n\0",
        b"\r\n\0\0\0\0\0\0\0\0",
        // Right after the record, with no line end.
        b"\0",
        b"\0\r\n",
        // Whatever follows the NUL is not read: not text, or the rest of
        // an older datagram in a reused buffer.
        b"\r\n\0\xff\xfe garbage",
        b"\0\xff",
        b"\r\n\0fr 4\r\nts 2.49\r\n6d 1 [0 1.0][9 9 9][1 0 0",
    ];
    for tail in tails {
        let mut d = good.clone().into_bytes();
        d.extend_from_slice(tail);
        assert_eq!(parse_datagram(&d).as_ref(), Ok(&want), "{tail:?}");
    }
}

#[test]
fn hybrid_bodies_are_read_as_bodies() {
    let d = "fr 1\r\nts 1.0\r\n\
             6di 3 [0 0 0.000][0 0 0][0 0 0 0 0 0 0 0 0] \
             [1 2 0.120][10 20 30][0 1 0 -1 0 0 0 0 1] \
             [2 1 0.800][40 50 60][1 0 0 0 1 0 0 0 1]\r\n";
    let f = parse_datagram(d.as_bytes()).unwrap();
    assert!(f.has_6d);
    assert_eq!(ids(&f), [0, 1, 2]);
    // State 0: not tracked, listed as occluded.
    assert_eq!(f.bodies[0].quality, -1.0);
    assert_eq!(f.visible_body(0), None);
    // State 2: optical and inertial, visible.
    let b = f.visible_body(1).unwrap();
    assert_eq!(b.quality, 1.0);
    assert_eq!(b.position_mm, [10.0, 20.0, 30.0]);
    // b0..b8 column-wise: the first row is b0 b3 b6.
    assert_eq!(
        b.rotation,
        Some([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    );
    // State 1: inertial only (dead reckoning): kept, not visible.
    assert_eq!(f.visible_body(2), None);
    assert_eq!(f.bodies[2].quality, -1.0);
    assert_eq!(f.bodies[2].position_mm, [40.0, 50.0, 60.0]);
}

#[test]
fn standard_and_hybrid_bodies_merge() {
    let six_d = format!(
        "6d 2 {} {}",
        body_text(0, [1, 2, 3]),
        body_text(1, [4, 5, 6])
    );
    let six_di = "6di 2 [1 2 0.1][70 80 90][1 0 0 0 1 0 0 0 1] \
                  [2 2 0.1][7 8 9][1 0 0 0 1 0 0 0 1]";
    // 6d first, whichever line comes first; id 1 keeps its 6d pose.
    for d in [
        format!("fr 1\r\n{six_d}\r\n{six_di}\r\n"),
        format!("fr 1\r\n{six_di}\r\n{six_d}\r\n"),
    ] {
        let f = parse_datagram(d.as_bytes()).unwrap();
        assert_eq!(ids(&f), [0, 1, 2], "{d:?}");
        assert_eq!(f.visible_body(1).unwrap().position_mm, [4.0, 5.0, 6.0]);
        assert_eq!(f.visible_body(2).unwrap().position_mm, [7.0, 8.0, 9.0]);
    }
    // 6di alone: bodies, as 6d's.
    let f = parse_datagram(format!("fr 1\r\n{six_di}\r\n").as_bytes()).unwrap();
    assert!(f.has_6d);
    assert_eq!(ids(&f), [1, 2]);
    // The merged frame writes as a 6d record and reads back the same.
    let f =
        parse_datagram(format!("fr 1\r\nts 3.0\r\n{six_d}\r\n{six_di}\r\n").as_bytes()).unwrap();
    assert_eq!(parse_datagram(format_datagram(&f).as_bytes()), Ok(f));
}

fn arb_body() -> impl Strategy<Value = BodyPose> {
    (
        0u32..100,
        prop_oneof![Just(1.0), Just(-1.0), -2.0f64..2.0],
        prop::array::uniform3(-5000.0f64..5000.0),
        prop::array::uniform3(prop::array::uniform3(-1.0f64..1.0)),
    )
        .prop_map(|(id, quality, position_mm, rotation)| BodyPose {
            id,
            position_mm,
            // A 6d body always has one.
            rotation: Some(rotation),
            quality,
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        let _ = parse_datagram(&bytes);
    }

    #[test]
    fn arbitrary_record_soup_never_panics(
        parts in prop::collection::vec(
            prop_oneof![
                Just("fr ".to_string()), Just("ts ".to_string()), Just("6d ".to_string()),
                Just("6dcal ".to_string()), Just("3d ".to_string()), Just("[".to_string()),
                Just("]".to_string()), Just("\r\n".to_string()), Just(" ".to_string()),
                Just("-1.000".to_string()), Just("nan".to_string()), Just("1e999".to_string()),
                Just("4294967296".to_string()), "[0-9.e+-]{1,8}",
                Just("ts2 ".to_string()), Just("6di ".to_string()), Just("\r".to_string()),
                Just("\0".to_string()),
            ],
            0..64,
        )
    ) {
        let _ = parse_datagram(parts.concat().as_bytes());
    }

    #[test]
    fn format_then_parse_is_identity(
        frame in any::<u32>(),
        ts in prop::option::of(0.0f64..86_400.0),
        cal in prop::option::of(0u32..10),
        bodies in prop::collection::vec(arb_body(), 0..4),
    ) {
        let f = DtrackFrame { frame, ts_s: ts, calibrated_bodies: cal, bodies, has_6d: true };
        let text = format_datagram(&f);
        prop_assert!(text.ends_with("\r\n"));
        prop_assert_eq!(parse_datagram(text.as_bytes()), Ok(f));
    }
}

// ---------------------------------------------------------------------------
// Receiver
// ---------------------------------------------------------------------------

fn receiver(window: u32, max_delay_ms: u64) -> DtrackReceiver {
    DtrackReceiver::bind(ReceiverConfig {
        reorder_window: window,
        max_delay: Duration::from_millis(max_delay_ms),
        ..ReceiverConfig::new(loopback())
    })
    .unwrap()
}

/// Receive until the sender is done and the line is quiet, then drain.
fn receive_all(rx: &mut DtrackReceiver, sender: SimSender) -> (Vec<TrackerFrame>, SimReport) {
    let start = Instant::now();
    let mut frames = Vec::new();
    while start.elapsed() < Duration::from_secs(30) {
        match rx.next_frame(Duration::from_millis(100)).unwrap() {
            Next::Frame(f) => frames.push(f),
            Next::Timeout if sender.is_finished() => break,
            Next::Timeout => {}
            Next::End => break,
        }
    }
    frames.extend(rx.drain());
    (frames, sender.join().unwrap())
}

fn circle(t: f64) -> Option<[f64; 3]> {
    let w = 2.0 * std::f64::consts::PI * 0.5;
    Some([300.0 * (w * t).cos(), 300.0 * (w * t).sin(), 1500.0])
}

#[test]
fn receiver_counts_loss_duplicates_and_reordering() {
    let mut rx = receiver(8, 500);
    let cfg = SimSenderConfig {
        frames: 400,
        first_frame: 1000,
        ts_start_s: 100.0,
        loss: 0.1,
        duplicate: 0.05,
        reorder: 0.1,
        extra_records: true,
        seed: 7,
        ..SimSenderConfig::new(rx.local_addr())
    };
    let sender = SimSender::spawn(cfg, circle).unwrap();
    let (frames, report) = receive_all(&mut rx, sender);
    let stats = rx.receiver_stats();
    // The seed gives some of each, or the test proves nothing.
    assert!(report.expected_lost() > 10, "{report:?}");
    assert!(report.expected_duplicates() > 3, "{report:?}");
    assert!(report.expected_out_of_order() > 10, "{report:?}");

    assert_eq!(stats.datagrams, report.sent.len() as u64);
    assert_eq!(stats.source.malformed, 0, "{:?}", stats.last_error);
    assert_eq!(stats.source.lost, report.expected_lost());
    assert_eq!(stats.source.duplicates, report.expected_duplicates());
    assert_eq!(stats.source.out_of_order, report.expected_out_of_order());
    assert_eq!(stats.source.late, 0);
    let mut distinct = report.sent.clone();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        distinct,
        "every frame sent, once, in order"
    );
    assert_eq!(stats.source.delivered, frames.len() as u64);
    for f in &frames {
        let t = f64::from(f.frame - 1000) / 100.0;
        assert!((f.ts_s - (100.0 + t)).abs() < 1e-9);
        let p = f.body.as_ref().expect("never occluded").position_mm;
        let q = circle(t).unwrap();
        assert!((0..3).all(|k| (p[k] - q[k]).abs() < 1e-9));
    }
}

fn occluded_between(t: f64) -> Option<[f64; 3]> {
    if (0.2..0.4).contains(&t) || (0.71..0.73).contains(&t) {
        None
    } else {
        circle(t)
    }
}

#[test]
fn occlusion_gives_body_none_both_ways() {
    for negative_quality in [false, true] {
        let mut rx = receiver(4, 30);
        let cfg = SimSenderConfig {
            frames: 100,
            occluded_as_negative_quality: negative_quality,
            ..SimSenderConfig::new(rx.local_addr())
        };
        let sender = SimSender::spawn(cfg, occluded_between).unwrap();
        let (frames, report) = receive_all(&mut rx, sender);
        assert_eq!(frames.len(), 100);
        assert_eq!(report.occluded.len(), 22, "20 + 2 frames");
        let none: Vec<u32> = frames
            .iter()
            .filter(|f| f.body.is_none())
            .map(|f| f.frame)
            .collect();
        assert_eq!(none, report.occluded);
        assert_eq!(rx.stats().occluded, 22);
        assert_eq!(rx.stats().lost, 0);
    }
}

#[test]
fn bad_datagrams_are_counted_and_skipped() {
    let mut rx = receiver(4, 30);
    let tx = UdpSocket::bind(loopback()).unwrap();
    let to = rx.local_addr();
    let good = |n: u32| {
        format!(
            "fr {n}\r\nts {}.5\r\n6d 1 [0 1.0][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1]\r\n",
            n
        )
    };
    tx.send_to(good(1).as_bytes(), to).unwrap();
    tx.send_to(b"\x00\x01garbage\xff", to).unwrap();
    tx.send_to(b"fr 2\r\n6d 1 [0 1.0][1 2 3][1 0 0]\r\n", to)
        .unwrap();
    tx.send_to(b"fr 3\r\n6d 0\r\n", to).unwrap(); // no ts
    tx.send_to(good(2).as_bytes(), to).unwrap();
    tx.send_to(good(3).as_bytes(), to).unwrap();
    let frames = collect(&mut rx, 3, Duration::from_secs(5)).unwrap();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [1, 2, 3]
    );
    let stats = rx.receiver_stats();
    assert_eq!(stats.datagrams, 6);
    assert_eq!(stats.source.malformed, 3);
    assert_eq!(stats.last_error, Some(DtrackError::MissingTimestamp));
    assert_eq!(stats.source.lost, 0);
}

fn frame_text(n: u32, ts: f64) -> String {
    format_datagram(&DtrackFrame {
        frame: n,
        ts_s: Some(ts),
        calibrated_bodies: None,
        bodies: vec![BodyPose::at(0, [1.0, 2.0, 3.0])],
        has_6d: true,
    })
}

#[test]
fn reordering_rules_on_a_fixed_sequence() {
    let mut rx = receiver(8, 10_000);
    let now = Instant::now();
    for n in [1, 2, 4, 3, 3, 7, 6, 2] {
        rx.accept(frame_text(n, f64::from(n)).as_bytes(), now);
    }
    let frames = rx.drain();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [1, 2, 3, 4, 6, 7]
    );
    let s = rx.stats();
    assert_eq!(
        (s.delivered, s.lost, s.out_of_order, s.duplicates, s.late),
        (6, 1, 2, 2, 0)
    );
    // 5 was given up: late; 1 was delivered: duplicate.
    rx.accept(frame_text(5, 5.0).as_bytes(), now);
    rx.accept(frame_text(1, 1.0).as_bytes(), now);
    let s = rx.stats();
    assert_eq!((s.late, s.duplicates), (1, 3));
    assert!(rx.drain().is_empty());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Whatever the arrival order: frames come out once each, in order;
    /// every arrival is delivered, a duplicate or late; every number in the
    /// delivered range is delivered or lost.
    #[test]
    fn reorder_accounts_for_every_arrival(
        arrivals in prop::collection::vec(0u32..60, 1..200),
        window in 0u32..10,
    ) {
        let mut r = Reorder::new(window, Duration::from_secs(3600));
        let now = Instant::now();
        let mut out = std::collections::VecDeque::new();
        for &n in &arrivals {
            let frame = TrackerFrame { frame: n, ts_s: f64::from(n), received_at: now, body: None };
            r.push(frame, &mut out);
            r.release(now, &mut out);
        }
        r.flush(&mut out);
        let got: Vec<u32> = out.iter().map(|f| f.frame).collect();
        prop_assert!(got.windows(2).all(|w| w[0] < w[1]), "{got:?}");
        let s = r.stats().clone();
        prop_assert_eq!(s.delivered as usize, got.len());
        prop_assert_eq!(s.delivered + s.duplicates + s.late, arrivals.len() as u64);
        let span = u64::from(got[got.len() - 1] - got[0]) + 1;
        prop_assert_eq!(s.delivered + s.lost, span);
        prop_assert_eq!(s.occluded, s.delivered);
        prop_assert_eq!(s.restarts, 0);
    }
}

#[test]
fn gaps_are_given_up_after_the_window_or_the_delay() {
    // Window: frame 2 never comes; 3..=6 arrive; with a window of 4 the
    // receiver gives 2 up and hands the rest out without waiting.
    let mut rx = receiver(4, 60_000);
    let tx = UdpSocket::bind(loopback()).unwrap();
    for n in [1, 3, 4, 5, 6] {
        tx.send_to(frame_text(n, f64::from(n)).as_bytes(), rx.local_addr())
            .unwrap();
    }
    let frames = collect(&mut rx, 5, Duration::from_secs(5)).unwrap();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [1, 3, 4, 5, 6]
    );
    assert_eq!(rx.stats().lost, 1);
    // Delay: 8 after 6 with a large window; 7 is given up after max_delay.
    let mut rx = receiver(1000, 20);
    for n in [6, 8] {
        tx.send_to(frame_text(n, f64::from(n)).as_bytes(), rx.local_addr())
            .unwrap();
    }
    let start = Instant::now();
    let frames = collect(&mut rx, 2, Duration::from_secs(5)).unwrap();
    assert_eq!(frames.iter().map(|f| f.frame).collect::<Vec<_>>(), [6, 8]);
    assert!(start.elapsed() >= Duration::from_millis(20));
    assert_eq!(rx.stats().lost, 1);
}

#[test]
fn timestamp_unwraps_at_midnight_and_counter_restarts() {
    let mut rx = receiver(2, 10_000);
    let now = Instant::now();
    rx.accept(frame_text(5000, 86_399.99).as_bytes(), now);
    rx.accept(frame_text(5001, 0.01).as_bytes(), now);
    // DTrack restarted: the counter starts again.
    rx.accept(frame_text(1, 0.02).as_bytes(), now);
    rx.accept(frame_text(2, 0.03).as_bytes(), now);
    let frames = rx.drain();
    let ts: Vec<f64> = frames.iter().map(|f| f.ts_s).collect();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [5000, 5001, 1, 2]
    );
    assert!((ts[1] - 86_400.01).abs() < 1e-6, "{ts:?}");
    assert!((ts[3] - 86_400.03).abs() < 1e-6, "{ts:?}");
    let s = rx.stats();
    assert_eq!((s.restarts, s.lost, s.duplicates), (1, 0, 0));
}

#[test]
fn simulated_sender_refuses_other_than_loopback() {
    let target: SocketAddr = "192.0.2.1:5000".parse().unwrap();
    let err = SimSender::spawn(SimSenderConfig::new(target), circle).unwrap_err();
    assert!(matches!(err, TrackerError::NotLoopback(a) if a == target));
    let err = SimSender::spawn(
        SimSenderConfig {
            loss: 1.5,
            ..SimSenderConfig::new(loopback())
        },
        circle,
    )
    .unwrap_err();
    assert!(
        matches!(&err, TrackerError::Config(c) if c.field == "loss"),
        "{err}"
    );
}

#[test]
fn simulated_sender_stops_by_itself() {
    let mut rx = receiver(4, 30);
    let cfg = SimSenderConfig {
        frames: 1_000_000,
        send_interval: Duration::from_millis(2),
        max_duration: Duration::from_millis(100),
        ..SimSenderConfig::new(rx.local_addr())
    };
    let sender = SimSender::spawn(cfg, circle).unwrap();
    let (frames, report) = receive_all(&mut rx, sender);
    assert!(report.stopped_early);
    assert!(report.frames < 1000, "{}", report.frames);
    assert_eq!(frames.len() as u32, report.frames);
}

// ---------------------------------------------------------------------------
// Replay
// ---------------------------------------------------------------------------

fn session_head() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/examples/session-head.csv")
}

#[test]
fn replay_of_the_shared_session_keeps_occlusions() {
    let session = spidar::data::dataset::Session::load(session_head()).unwrap();
    let mut replay = ReplaySource::load(session_head(), Pacing::AsFastAsPossible).unwrap();
    assert_eq!(replay.len(), session.samples.len());
    let frames = collect(&mut replay, usize::MAX, Duration::from_secs(5)).unwrap();
    assert_eq!(replay.next_frame(Duration::ZERO).unwrap(), Next::End);
    assert_eq!(frames.len(), session.samples.len());
    let occluded_rows: Vec<u32> = session
        .samples
        .iter()
        .enumerate()
        .filter(|(_, s)| s.tracker.is_none())
        .map(|(i, _)| i as u32)
        .collect();
    // The example's first row and tenth row have empty ots_* columns.
    assert_eq!(occluded_rows, [0, 9]);
    for (i, (f, s)) in frames.iter().zip(&session.samples).enumerate() {
        assert_eq!(f.frame, i as u32);
        assert_eq!(f.ts_s, s.t_s);
        assert_eq!(f.body.as_ref().map(|b| b.position_mm), s.tracker);
        // The session has no orientation columns: no rotation, not the
        // identity.
        assert!(f.body.as_ref().is_none_or(|b| b.rotation.is_none()));
    }
    assert_eq!(replay.stats().occluded, 2);
    assert_eq!(replay.stats().delivered, 20);
}

#[test]
fn replay_plays_back_a_session_s_orientation_as_the_body_s_rotation() {
    use spidar::data::dataset::{Sample, Session};
    let row = |t_s: f64, tracker: Option<[f64; 3]>, orientation: Option<[f64; 4]>| Sample {
        t_s,
        counts: [0; 8],
        tracker,
        orientation,
        legacy: None,
        tension_n: None,
        since_home_s: None,
        home: None,
    };
    // A quarter turn about z: x goes to y.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let session = Session {
        samples: vec![
            row(0.0, Some([1.0, 2.0, 3.0]), Some([h, 0.0, 0.0, h])),
            row(0.1, Some([4.0, 5.0, 6.0]), None),
            row(0.2, None, None),
        ],
        ..Session::default()
    };
    let mut replay = ReplaySource::from_session(&session, Pacing::AsFastAsPossible).unwrap();
    let frames = collect(&mut replay, usize::MAX, Duration::from_secs(5)).unwrap();
    assert_eq!(frames.len(), 3);
    let turned = frames[0].body.as_ref().unwrap();
    assert_eq!(turned.position_mm, [1.0, 2.0, 3.0]);
    let r = turned.rotation.expect("the row's orientation");
    let expected = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    for (a, b) in r.iter().flatten().zip(expected.iter().flatten()) {
        assert!((a - b).abs() < 1e-12, "{r:?}");
    }
    assert_eq!(frames[1].body.as_ref().unwrap().rotation, None);
    assert_eq!(frames[2].body, None);
}

#[test]
fn replay_paced_in_real_time() {
    // 45 s of session at 1500x: about 30 ms.
    let mut replay =
        ReplaySource::load(session_head(), Pacing::RealTime { speed: 1500.0 }).unwrap();
    let start = Instant::now();
    let frames = collect(&mut replay, usize::MAX, Duration::from_secs(5)).unwrap();
    let took = start.elapsed();
    assert_eq!(frames.len(), 20);
    let span = frames[19].ts_s - frames[0].ts_s;
    assert!(
        took >= Duration::from_secs_f64(span / 1500.0 * 0.9),
        "{took:?}"
    );
    for w in frames.windows(2) {
        assert!(w[1].received_at >= w[0].received_at);
    }
    // A timeout shorter than the next frame's due time gives Timeout.
    let mut slow = ReplaySource::load(session_head(), Pacing::RealTime { speed: 1.0 }).unwrap();
    assert!(matches!(
        slow.next_frame(Duration::ZERO).unwrap(),
        Next::Frame(_)
    ));
    assert_eq!(
        slow.next_frame(Duration::from_millis(5)).unwrap(),
        Next::Timeout
    );
    let err = ReplaySource::load(session_head(), Pacing::RealTime { speed: 0.0 }).unwrap_err();
    assert!(matches!(&err, TrackerError::Config(c) if c.field == "pacing.speed"));
}

#[test]
fn replay_of_a_missing_file_names_it() {
    let err = ReplaySource::load("no/such/session.csv", Pacing::AsFastAsPossible).unwrap_err();
    assert!(err.to_string().contains("no/such/session.csv"), "{err}");
}

// ---------------------------------------------------------------------------
// Time shift
// ---------------------------------------------------------------------------

/// A hand-like motion: varying speed in all three axes (room frame, mm).
fn wander(t: f64) -> [f64; 3] {
    let tau = 2.0 * std::f64::consts::PI;
    [
        250.0 * (tau * 0.31 * t).sin() + 60.0 * (tau * 1.3 * t).sin(),
        -450.0 + 180.0 * (tau * 0.53 * t + 1.0).sin(),
        1050.0 + 120.0 * (tau * 0.17 * t).sin() + 40.0 * (tau * 0.9 * t + 0.3).cos(),
    ]
}

fn wander_with_occlusion(t: f64) -> Option<[f64; 3]> {
    // 0.3 s occlusions every 4 s.
    (t % 4.0 >= 0.3).then(|| wander(t))
}

/// Device samples at `rate` Hz on the device clock, with a room-transform
/// error `bias` and `noise_mm` of Gaussian-ish noise.
fn device_samples(rate: f64, seconds: f64, bias: [f64; 3], noise_mm: f64) -> Vec<TimedPosition> {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let n = (rate * seconds) as usize;
    (0..n)
        .map(|i| {
            let t = i as f64 / rate;
            let p = wander(t);
            TimedPosition {
                t_s: t,
                position_mm: core::array::from_fn(|k| {
                    // Sum of three uniforms: close enough to Gaussian.
                    let u: f64 = (0..3).map(|_| rng.random_range(-1.0..1.0)).sum::<f64>();
                    p[k] - bias[k] + noise_mm * u
                }),
            }
        })
        .collect()
}

#[test]
fn time_shift_recovered_through_the_simulated_tracker() {
    const OFFSET: f64 = 0.0375;
    const DAY_TIME: f64 = 39_596.0;
    let mut rx = receiver(8, 200);
    let cfg = SimSenderConfig {
        frames: 2000, // 20 s at 100 Hz
        ts_start_s: DAY_TIME,
        clock_offset_s: OFFSET,
        loss: 0.05,
        reorder: 0.05,
        send_interval: Duration::from_micros(500),
        seed: 11,
        ..SimSenderConfig::new(rx.local_addr())
    };
    let sender = SimSender::spawn(cfg, wander_with_occlusion).unwrap();
    let (frames, report) = receive_all(&mut rx, sender);
    // (Exact loss accounting is tested above; here a starved receiver's
    // kernel buffer may drop a few more, which the estimate must survive.)
    assert!(rx.stats().lost >= report.expected_lost());
    assert!(frames.iter().any(|f| f.body.is_none()));
    let tracker = TimedPosition::from_frames(&frames);
    let device = device_samples(500.0, 20.0, [8.0, -5.0, 14.0], 1.0);
    let shift = estimate_time_shift(
        &device,
        &tracker,
        &ShiftConfig {
            prior_offset_s: DAY_TIME,
            max_shift_s: 0.25,
            ..ShiftConfig::default()
        },
    )
    .unwrap();
    let error = shift.offset_s - (DAY_TIME + OFFSET);
    assert!(error.abs() < 0.003, "{shift:?}");
    assert!(
        (shift.coarse_offset_s - (DAY_TIME + OFFSET)).abs() < 0.02,
        "{shift:?}"
    );
    assert!(
        shift.offset_std_s > 0.0 && shift.offset_std_s < 0.003,
        "{shift:?}"
    );
    assert!(error.abs() < 5.0 * shift.offset_std_s + 1e-4, "{shift:?}");
    assert!(shift.correlation > 0.9, "{shift:?}");
    for k in 0..3 {
        assert!(
            (shift.bias_mm[k] - [8.0, -5.0, 14.0][k]).abs() < 0.5,
            "{shift:?}"
        );
    }
    assert!(shift.rms_residual_mm < 3.0, "{shift:?}");
    // The map and its inverse.
    let t = 7.25;
    assert!((shift.device_time(shift.tracker_time(t)) - t).abs() < 1e-9);
}

#[test]
fn time_shift_with_drift() {
    // Tracker clock 200 ppm fast, 12.3 ms ahead at the middle of 60 s.
    let (offset, drift) = (0.0123, 200e-6);
    let device = device_samples(200.0, 60.0, [0.0; 3], 0.5);
    let reference = 0.5 * (device[0].t_s + device[device.len() - 1].t_s);
    let tracker: Vec<TimedPosition> = (0..6000)
        .map(|i| {
            let t = i as f64 / 100.0; // true (device) time
            TimedPosition {
                t_s: t + offset + drift * (t - reference),
                position_mm: wander(t),
            }
        })
        .collect();
    let cfg = ShiftConfig {
        estimate_drift: true,
        ..ShiftConfig::default()
    };
    let shift = estimate_time_shift(&device, &tracker, &cfg).unwrap();
    assert!((shift.offset_s - offset).abs() < 0.001, "{shift:?}");
    assert!((shift.drift - drift).abs() < 30e-6, "{shift:?}");
    assert!(shift.drift_std > 0.0, "{shift:?}");
    assert_eq!(shift.reference_t_s, reference);
    // Without drift the offset is still found (the mid-stream value).
    let plain = estimate_time_shift(&device, &tracker, &ShiftConfig::default()).unwrap();
    assert!((plain.offset_s - offset).abs() < 0.002, "{plain:?}");
    assert_eq!(plain.drift, 0.0);
}

#[test]
fn time_shift_errors_name_the_problem() {
    let device = device_samples(100.0, 5.0, [0.0; 3], 0.0);
    let still: Vec<TimedPosition> = (0..500)
        .map(|i| TimedPosition {
            t_s: i as f64 / 100.0,
            position_mm: [1.0, 2.0, 3.0],
        })
        .collect();
    let cfg = ShiftConfig::default();
    assert_eq!(
        estimate_time_shift(&device, &still, &cfg),
        Err(SyncError::NoMotion { stream: "tracker" })
    );
    assert_eq!(
        estimate_time_shift(&device[..3], &device, &cfg),
        Err(SyncError::TooFewSamples {
            stream: "device",
            have: 3,
            need: 10
        })
    );
    let mut bad = device.clone();
    bad[4].position_mm[1] = f64::NAN;
    assert!(matches!(
        estimate_time_shift(&bad, &device, &cfg),
        Err(SyncError::NotFinite {
            stream: "device",
            index: 4,
            field: "position_mm[1]",
            ..
        })
    ));
    let mut back = device.clone();
    back[7].t_s = 0.0;
    assert!(matches!(
        estimate_time_shift(&device, &back, &cfg),
        Err(SyncError::TimeDecreasing {
            stream: "tracker",
            index: 7,
            ..
        })
    ));
    // Tracker an hour away from the prior: nothing overlaps.
    let far: Vec<TimedPosition> = device
        .iter()
        .map(|p| TimedPosition {
            t_s: p.t_s + 3600.0,
            ..*p
        })
        .collect();
    let r = estimate_time_shift(&device, &far, &cfg);
    assert!(matches!(r, Err(SyncError::NoOverlap { .. })), "{r:?}");
    assert!(matches!(
        estimate_time_shift(
            &device,
            &device,
            &ShiftConfig {
                max_gap_s: 0.0,
                ..cfg.clone()
            }
        ),
        Err(SyncError::Config(c)) if c.field == "max_gap_s"
    ));
}
