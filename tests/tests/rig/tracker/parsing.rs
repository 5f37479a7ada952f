//! Parsing: the manual's example, line ends, skipped records, occlusion,
//! and the errors that name the line and the field.

use super::fixtures::{field_error, MANUAL};
use spidar::device::tracker::dtrack::{parse_datagram, DtrackError, FieldProblem};

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
