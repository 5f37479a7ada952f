//! What real DTrack output contains (DTrack3 records, SDK tolerance): ts2,
//! body counts, repeated records, line and datagram ends, hybrid bodies,
//! and arbitrary bytes.

use std::time::Instant;

use super::fixtures::{field_error, frame_text, receiver, MANUAL};
use proptest::prelude::*;
use spidar::device::tracker::dtrack::{
    format_datagram, parse_datagram, BodyPose, DtrackFrame, FieldProblem,
};
use spidar::device::tracker::TrackerSource;

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
