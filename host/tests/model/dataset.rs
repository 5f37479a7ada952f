//! Reader/writer of the geometry and session formats: the shared examples
//! written by another tool, round trips, and one test per error kind.

use std::path::{Path, PathBuf};

use spidar::data::dataset::{DatasetError, Geometry, Sample, Session, ValueProblem};

fn shared(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/examples")
        .join(file)
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spidar-dataset-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

const HEADER: &str = "t_s,enc0,enc1,enc2,enc3,enc4,enc5,enc6,enc7,ots_x,ots_y,ots_z";

fn read(text: &str) -> Result<Session, DatasetError> {
    Session::read_from(text.as_bytes(), Path::new("mem/session.csv"))
}

/// The message names the file, the line and the column; returns the problem.
fn value_error(text: &str, line: u64, column: &str) -> ValueProblem {
    let err = read(text).expect_err("must be rejected");
    let msg = err.to_string();
    assert!(msg.contains("mem/session.csv"), "{msg}");
    assert!(msg.contains(&format!("line {line}")), "{msg}");
    assert!(msg.contains(&format!("`{column}`")), "{msg}");
    match err {
        DatasetError::Value {
            line: l,
            column: c,
            problem,
            ..
        } => {
            assert_eq!((l, c.as_str()), (line, column), "{msg}");
            problem
        }
        other => panic!("expected a value error, got {other:?}"),
    }
}

#[test]
fn reads_the_shared_geometry() {
    let g = Geometry::load(shared("geometry.toml")).unwrap();
    assert_eq!(g.counts_per_rev, [4096; 8]);
    assert_eq!(g.pulley_radius_mm, [7.5; 8]);
    assert_eq!(g.home_mm, [0.0; 3]);
    assert_eq!(g.anchors_mm[6], [1100.0, 1100.0, 1100.0]);
    assert_eq!(g.room_from_device_translation_mm, [0.0, 0.0, 1500.0]);
    let frame = g.nominal_frame();
    assert_eq!(frame.anchors, g.anchors_mm);
    assert_eq!(frame.room_scale, 1.0);
    assert_eq!(frame.room_translation, [0.0, 0.0, 1500.0]);
    let laws = g.nominal_string_laws();
    assert_eq!(laws[3].winding_mm, [7.5, 0.0, 0.0, 0.0]);
    assert_eq!(laws[3].counts_per_rev, 4096);
}

#[test]
fn reads_the_shared_session() {
    let s = Session::load(shared("session-head.csv")).unwrap();
    assert!(s.samples.len() >= 10);
    assert!(s.ignored_columns.is_empty());
    let first = &s.samples[0];
    assert_eq!(first.t_s, 1.530);
    assert_eq!(first.counts[0], -40371);
    assert_eq!(first.tracker, None, "the first row is occluded");
    assert_eq!(first.legacy, Some([-259.079, -280.452, -276.065]));
    assert_eq!(first.tension_n.unwrap()[6], 2.832);
    assert_eq!(s.samples[1].tracker, Some([-354.707, -448.060, 1003.830]));
    assert!(s.samples.iter().any(|x| x.tracker.is_none()));
    assert!(s.samples.iter().filter(|x| x.tracker.is_some()).count() > 5);
}

#[test]
fn geometry_round_trip_and_per_string_radii() {
    let mut g = Geometry::load(shared("geometry.toml")).unwrap();
    let path = tmp("geometry.toml");
    g.write(&path).unwrap();
    assert_eq!(Geometry::load(&path).unwrap(), g);
    g.pulley_radius_mm[5] = 7.25;
    g.anchors_mm[2][1] = 1099.875;
    g.write(&path).unwrap();
    assert_eq!(Geometry::load(&path).unwrap(), g);
}

#[test]
fn session_round_trip_is_lossless() {
    let s = Session::load(shared("session-head.csv")).unwrap();
    let path = tmp("round.csv");
    s.write(&path).unwrap();
    assert_eq!(Session::load(&path).unwrap(), s);

    // Awkward values: exact floats, extremes of counts, mixed None groups.
    let mut samples = vec![Sample {
        t_s: 0.1 + 0.2,
        counts: [i32::MIN, i32::MAX, 0, -1, 1, 2, 3, 4],
        tracker: Some([1e-9, -123456.789012345, 1.0 / 3.0]),
        orientation: None,
        legacy: None,
        tension_n: Some([1.0, 2.5, 0.001, 3.0, 4.0, 5.0, 6.0, 7.0]),
        since_home_s: None,
        home: None,
    }];
    samples.push(Sample {
        t_s: 0.3 + 1e-12,
        counts: [5; 8],
        tracker: None,
        orientation: None,
        legacy: Some([1.5, -2.5, 3.25]),
        tension_n: None,
        since_home_s: None,
        home: None,
    });
    let s = Session {
        strings: 8,
        samples,
        ignored_columns: vec![],
        unread_columns: Vec::new(),
        tracker_z: true,
    };
    s.write(&path).unwrap();
    assert_eq!(Session::load(&path).unwrap(), s);
}

#[test]
fn columns_in_any_order_and_unknown_columns_are_listed() {
    let text = "ots_z,enc7,enc6,enc5,quality,enc4,enc3,enc2,enc1,enc0,ots_y,ots_x,t_s\n\
                3,7,6,5,good,4,3,2,1,0,2,1,0.5\n";
    let s = read(text).unwrap();
    assert_eq!(s.samples[0].counts, [0, 1, 2, 3, 4, 5, 6, 7]);
    assert_eq!(s.samples[0].tracker, Some([1.0, 2.0, 3.0]));
    assert_eq!(s.samples[0].t_s, 0.5);
    assert_eq!(s.ignored_columns, vec!["quality".to_string()]);
}

#[test]
fn error_missing_column() {
    let text = "t_s,enc0,enc1,enc2,enc3,enc4,enc5,enc7,ots_x,ots_y,ots_z\n";
    let err = read(text).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DatasetError::MissingColumn { ref column, .. } if column == "enc6"));
    assert!(msg.contains("mem/session.csv") && msg.contains("line 1") && msg.contains("`enc6`"));
}

#[test]
fn error_duplicate_column() {
    let text = format!("{HEADER},enc3\n");
    let err = read(&text).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DatasetError::DuplicateColumn { ref column, .. } if column == "enc3"));
    assert!(msg.contains("mem/session.csv") && msg.contains("line 1") && msg.contains("`enc3`"));
}

#[test]
fn error_incomplete_optional_group() {
    let text = format!("{HEADER},dev_x,dev_z\n");
    let err = read(&text).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DatasetError::IncompleteGroup { ref missing, .. } if missing == "dev_y"));
    assert!(msg.contains("mem/session.csv") && msg.contains("line 1") && msg.contains("`dev_y`"));
}

#[test]
fn error_empty_file() {
    let err = read("").unwrap_err();
    assert!(matches!(err, DatasetError::Empty { .. }), "{err}");
    assert!(err.to_string().contains("mem/session.csv"));
}

#[test]
fn error_wrong_number_of_fields() {
    let text = format!("{HEADER}\n0,1,2,3,4,5,6,7,8,1,2,3\n1,1,2,3\n");
    let err = read(&text).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DatasetError::Csv { line: 3, .. }), "{msg}");
    assert!(
        msg.contains("mem/session.csv") && msg.contains("line 3"),
        "{msg}"
    );
}

#[test]
fn error_non_numeric_value() {
    let text = format!("{HEADER}\n0,1,2,3,4,5,6,7,8,1,2,3\n1,1,2,3,4,5,6,7,8,1,abc,3\n");
    let p = value_error(&text, 3, "ots_y");
    assert_eq!(p, ValueProblem::NotANumber("abc".into()));
}

#[test]
fn error_nan_and_infinite_values() {
    let text = format!(
        "{HEADER},tension0,tension1,tension2,tension3,tension4,tension5,tension6,tension7\n\
                        0,1,2,3,4,5,6,7,8,1,2,3,1,1,1,1,NaN,1,1,1\n"
    );
    let p = value_error(&text, 2, "tension4");
    assert_eq!(p, ValueProblem::NotFinite("NaN".into()));
    let text = format!("{HEADER}\n0,1,2,3,4,5,6,7,8,inf,2,3\n");
    assert_eq!(
        value_error(&text, 2, "ots_x"),
        ValueProblem::NotFinite("inf".into())
    );
}

#[test]
fn error_partially_empty_tracker() {
    let text = format!("{HEADER}\n0,1,2,3,4,5,6,7,8,,,\n1,1,2,3,4,5,6,7,8,1.5,,3\n");
    let p = value_error(&text, 3, "ots_y");
    assert!(matches!(p, ValueProblem::PartialGroup { ref filled, .. } if filled == "ots_x"));
}

#[test]
fn error_partially_empty_legacy() {
    let text = format!("{HEADER},dev_x,dev_y,dev_z\n0,1,2,3,4,5,6,7,8,1,2,3,,4,\n");
    let p = value_error(&text, 2, "dev_x");
    assert!(matches!(p, ValueProblem::PartialGroup { .. }));
}

#[test]
fn error_time_going_backwards() {
    let text = format!(
        "{HEADER}\n1,1,2,3,4,5,6,7,8,1,2,3\n1,1,2,3,4,5,6,7,8,1,2,3\n0.5,1,2,3,4,5,6,7,8,1,2,3\n"
    );
    let p = value_error(&text, 4, "t_s");
    assert_eq!(
        p,
        ValueProblem::TimeDecreasing {
            value: 0.5,
            previous: 1.0,
            previous_line: 3
        }
    );
}

#[test]
fn error_negative_time() {
    let text = format!("{HEADER}\n-0.5,1,2,3,4,5,6,7,8,1,2,3\n");
    assert_eq!(
        value_error(&text, 2, "t_s"),
        ValueProblem::NegativeTime(-0.5)
    );
}

/// A clock's timestamp (Unix seconds) is not time since the session's
/// start: refused naming the line, where every row read as one instant.
#[test]
fn a_timestamp_of_a_clock_is_refused_as_time() {
    let text = format!("{HEADER}\n1700000000.5,1,2,3,4,5,6,7,8,1,2,3\n");
    assert_eq!(
        value_error(&text, 2, "t_s"),
        ValueProblem::TimeTooLarge(1_700_000_000.5)
    );
    // 49 days is a session still.
    let text = format!("{HEADER}\n4233600,1,2,3,4,5,6,7,8,1,2,3\n");
    assert!(read(&text).is_ok());
}

#[test]
fn error_empty_time_and_counts() {
    let text = format!("{HEADER}\n,1,2,3,4,5,6,7,8,1,2,3\n");
    assert_eq!(value_error(&text, 2, "t_s"), ValueProblem::Empty);
    let text = format!("{HEADER}\n0,1,2,,4,5,6,7,8,1,2,3\n");
    assert_eq!(value_error(&text, 2, "enc2"), ValueProblem::Empty);
}

/// Counts written as whole floats (pandas writes an integer column that
/// had a missing value so) read as those counts.
#[test]
fn counts_written_as_whole_floats_are_those_counts() {
    let text = format!("{HEADER}\n0,483489.0,-7.0,2,3,4,5,6,-2147483648.0,1,2,3\n");
    let s = read(&text).unwrap();
    assert_eq!(s.samples[0].counts, [483489, -7, 2, 3, 4, 5, 6, i32::MIN]);
}

#[test]
fn error_count_out_of_range_or_not_integer() {
    let text = format!("{HEADER}\n0,1,2,3,4,5,6,2147483648,8,1,2,3\n");
    assert_eq!(
        value_error(&text, 2, "enc6"),
        ValueProblem::CountOutOfRange("2147483648".into())
    );
    let text = format!("{HEADER}\n0,1,2,3,4,5,6,7,-99999999999999999999999,1,2,3\n");
    assert!(matches!(
        value_error(&text, 2, "enc7"),
        ValueProblem::CountOutOfRange(_)
    ));
    let text = format!("{HEADER}\n0,1,2,3,4,5,6,7,2147483648.0,1,2,3\n");
    assert_eq!(
        value_error(&text, 2, "enc7"),
        ValueProblem::CountOutOfRange("2147483648.0".into())
    );
    let text = format!("{HEADER}\n0,1.5,2,3,4,5,6,7,8,1,2,3\n");
    assert_eq!(
        value_error(&text, 2, "enc0"),
        ValueProblem::NotAnInteger("1.5".into())
    );
    let text = format!("{HEADER}\n0,x1,2,3,4,5,6,7,8,1,2,3\n");
    assert_eq!(
        value_error(&text, 2, "enc0"),
        ValueProblem::NotANumber("x1".into())
    );
}

#[test]
fn error_missing_file_names_it() {
    let err = Session::load("/nonexistent/dir/s.csv").unwrap_err();
    assert!(err.to_string().contains("/nonexistent/dir/s.csv"));
    let err = Geometry::load("/nonexistent/dir/g.toml").unwrap_err();
    assert!(err.to_string().contains("/nonexistent/dir/g.toml"));
}

#[test]
fn writing_rejects_what_reading_would_reject() {
    let s = Session {
        strings: 8,
        samples: vec![Sample {
            t_s: 0.0,
            counts: [0; 8],
            tracker: Some([0.0, f64::NAN, 0.0]),
            orientation: None,
            legacy: None,
            tension_n: None,
            since_home_s: None,
            home: None,
        }],
        ignored_columns: vec![],
        unread_columns: Vec::new(),
        tracker_z: true,
    };
    let err = s.write(tmp("bad.csv")).unwrap_err();
    assert!(
        matches!(err, DatasetError::Value { line: 2, ref column, .. } if column == "ots_y"),
        "{err}"
    );
}

const GEOMETRY: &str = "counts_per_rev = 4096\npulley_radius_mm = 7.5\nhome_mm = [0, 0, 0]\n\
anchors_mm = [[-1100, -1100, -1100], [1100, -1100, -1100], [1100, 1100, -1100], [-1100, 1100, -1100],\n\
[-1100, -1100, 1100], [1100, -1100, 1100], [1100, 1100, 1100], [-1100, 1100, 1100]]\n\
room_from_device_translation_mm = [0, 0, 1500]\n";

fn geometry(text: &str) -> Result<Geometry, DatasetError> {
    Geometry::from_toml_str(text, Path::new("mem/geometry.toml"))
}

#[test]
fn geometry_accepts_integers() {
    let g = geometry(GEOMETRY).unwrap();
    assert_eq!(g, Geometry::load(shared("geometry.toml")).unwrap());
}

/// The tension the strings held at the home capture: optional (the shared
/// example has none), kept through a round trip, and a value that is no
/// tension names the key.
#[test]
fn geometry_home_tension_is_optional_kept_and_checked() {
    assert_eq!(geometry(GEOMETRY).unwrap().home_tension_n, None);
    let g = geometry(&format!("{GEOMETRY}home_tension_n = 1.5\n")).unwrap();
    assert_eq!(g.home_tension_n, Some(1.5));
    let path = tmp("geometry-tension.toml");
    g.write(&path).unwrap();
    assert_eq!(Geometry::load(&path).unwrap(), g);
    for bad in ["0", "-1.0", "nan", "80"] {
        let msg = geometry(&format!("{GEOMETRY}home_tension_n = {bad}\n"))
            .unwrap_err()
            .to_string();
        assert!(
            msg.contains("mem/geometry.toml") && msg.contains("home_tension_n"),
            "{bad}: {msg}"
        );
    }
}

#[test]
fn geometry_error_unknown_key_names_it() {
    let err = geometry(&format!("{GEOMETRY}pulley_radius = 7\n")).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("mem/geometry.toml") && msg.contains("pulley_radius"),
        "{msg}"
    );
    assert!(msg.contains("line 7"), "{msg}");
}

#[test]
fn geometry_error_missing_key_and_bad_values() {
    let text = GEOMETRY.replace("counts_per_rev = 4096\n", "");
    let msg = geometry(&text).unwrap_err().to_string();
    assert!(msg.contains("counts_per_rev"), "{msg}");

    let text = GEOMETRY.replace("pulley_radius_mm = 7.5", "pulley_radius_mm = [7.5, 7.5]");
    let err = geometry(&text).unwrap_err();
    assert!(
        matches!(err, DatasetError::GeometryField { ref field, .. } if field == "pulley_radius_mm")
    );

    let text = GEOMETRY.replace("pulley_radius_mm = 7.5", "pulley_radius_mm = -1.0");
    let err = geometry(&text).unwrap_err();
    assert!(err.to_string().contains("pulley_radius_mm[0]"), "{err}");

    let text = GEOMETRY.replace("home_mm = [0, 0, 0]", "home_mm = [0, nan, 0]");
    let err = geometry(&text).unwrap_err();
    assert!(err.to_string().contains("home_mm[1]"), "{err}");

    // 7 anchors are a 7-string device; 2 are too few, 9 too many.
    let text = GEOMETRY.replace("[-1100, 1100, 1100]]", "]");
    assert_eq!(geometry(&text).unwrap().strings(), 7);
    let two = "counts_per_rev = 4096\npulley_radius_mm = 7.5\nhome_mm = [0, 0, 0]\n\
               anchors_mm = [[1, 0, 0], [0, 1, 0]]\nroom_from_device_translation_mm = [0, 0, 0]\n";
    let err = geometry(two).unwrap_err();
    assert!(matches!(err, DatasetError::GeometryField { ref field, .. } if field == "anchors_mm"));
    assert!(err.to_string().contains("2 anchors given"), "{err}");

    let text = GEOMETRY.replace("counts_per_rev = 4096", "counts_per_rev = \"many\"");
    let msg = geometry(&text).unwrap_err().to_string();
    assert!(
        msg.contains("counts_per_rev") || msg.contains("line 1"),
        "{msg}"
    );
}

// ---------------------------------------------------------------------------
// Devices with 3 to 8 strings, planar devices, doubled lines
// ---------------------------------------------------------------------------

const FOUR_LINES: &str = "\
counts_per_rev = [459000, 459000, 459000, 1000]
pulley_radius_mm = 75.0
mechanical_advantage = [2, 2, 2, 4]
home_mm = [0.0, 0.0, 0.0]
anchors_mm = [
  [0.0, -1620.0, -150.0],
  [1272.792, 1272.792, -150.0],
  [-1402.961, 810.0, -150.0],
  [0.0, 0.0, 2350.0],
]
room_from_device_translation_mm = [0.0, 0.0, 0.0]
";

#[test]
fn n_string_geometry_per_string_keys_and_round_trip() {
    let g = geometry(FOUR_LINES).unwrap();
    assert_eq!(g.strings(), 4);
    assert_eq!(g.layout, spidar_core::model::StringLayout::first(4, false));
    assert_eq!(&g.counts_per_rev[..4], &[459_000, 459_000, 459_000, 1000]);
    assert_eq!(&g.mechanical_advantage[..4], &[2.0, 2.0, 2.0, 4.0]);
    // Channels without a string repeat the last string's values.
    assert_eq!(g.anchors_mm[7], g.anchors_mm[3]);
    assert_eq!(g.counts_per_rev[7], 1000);
    let frame = g.nominal_frame();
    assert_eq!(frame.layout.count(), 4);
    assert_eq!(g.nominal_string_laws()[3].winding_mm[0], 18.75);
    let back = geometry(&g.to_toml_string()).unwrap();
    assert_eq!(back, g);
    assert!(g
        .to_toml_string()
        .contains("mechanical_advantage = [2.0, 2.0, 2.0, 4.0]"));
}

#[test]
fn n_string_geometry_errors_name_the_key() {
    for (from, to, field, words) in [
        (
            "mechanical_advantage = [2, 2, 2, 4]",
            "mechanical_advantage = [2, 2]",
            "mechanical_advantage",
            "2 values given, 4 expected",
        ),
        (
            "mechanical_advantage = [2, 2, 2, 4]",
            "mechanical_advantage = [2, 2, 0, 4]",
            "mechanical_advantage[2]",
            "positive",
        ),
        (
            "[0.0, 0.0, 2350.0],",
            "[-1402.961, 810.0, -150.0],",
            "anchors_mm[3]",
            "0.000 mm from anchors_mm[2]: two strings cannot leave one point",
        ),
        (
            "room_from_device_translation_mm = [",
            "room_from_device_translation_mm = [1, ",
            "room_from_device_translation_mm",
            "4 values: [x, y, z]",
        ),
        (
            "counts_per_rev = [459000, 459000, 459000, 1000]",
            "counts_per_rev = [1, 2, 3]",
            "counts_per_rev",
            "3 values given",
        ),
        (
            "[0.0, 0.0, 2350.0],",
            "[0.0, 2350.0],",
            "anchors_mm[3]",
            "planar = true",
        ),
    ] {
        let text = FOUR_LINES.replace(from, to);
        assert_ne!(text, FOUR_LINES, "{from}");
        let err = geometry(&text).unwrap_err();
        let msg = err.to_string();
        assert!(
            matches!(err, DatasetError::GeometryField { field: ref f, .. } if f == field),
            "{field}: {msg}"
        );
        assert!(msg.contains(words), "{msg}");
    }
}

#[test]
fn planar_geometry_takes_2d_points_in_one_plane() {
    let text = "counts_per_rev = 4096\npulley_radius_mm = 10\nplanar = true\n\
                home_mm = [0, 0]\nanchors_mm = [[-500, -400], [500, -400], [500, 400], [-500, 400]]\n\
                room_from_device_translation_mm = [0, 0, 900]\n";
    let g = geometry(text).unwrap();
    assert!(g.layout.planar);
    assert_eq!(g.strings(), 4);
    assert_eq!(g.anchors_mm[2], [500.0, 400.0, 0.0]);
    assert_eq!(geometry(&g.to_toml_string()).unwrap(), g);
    // 3-D anchors of a planar device share one z.
    let tilted = text.replace("[500, 400]", "[500, 400, 30]");
    let err = geometry(&tilted).unwrap_err().to_string();
    assert!(
        err.contains("anchors_mm[2]") && err.contains("one plane"),
        "{err}"
    );
}

#[test]
fn n_string_sessions_follow_their_encoder_columns() {
    let text = "t_s,enc0,enc1,enc2,enc3,ots_x,ots_y,ots_z,tension0,tension1,tension2,tension3\n\
                0,1,2,3,4,1.5,2.5,3.5,10,11,12,13\n\
                1,5,6,7,8,,,,10,11,12,13\n";
    let s = read(text).unwrap();
    assert_eq!(s.strings, 4);
    assert_eq!(s.samples[0].counts, [1, 2, 3, 4, 0, 0, 0, 0]);
    assert_eq!(
        s.samples[0].tension_n.unwrap()[..4],
        [10.0, 11.0, 12.0, 13.0]
    );
    assert_eq!(s.samples[1].tracker, None);
    // Written back with the same columns, read back the same.
    let mut out = Vec::new();
    s.write_to(&mut out, Path::new("mem/out.csv")).unwrap();
    let written = String::from_utf8(out).unwrap();
    assert!(
        written.starts_with("t_s,enc0,enc1,enc2,enc3,ots_x,ots_y,ots_z,tension0,"),
        "{written}"
    );
    assert_eq!(read(&written).unwrap(), s);
    // A tension column beyond the strings, a gap, or too few strings.
    let err = read("t_s,enc0,enc1,enc2,ots_x,ots_y,ots_z,tension0,tension1,tension2,tension3\n")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("tension3") && err.contains("3 strings"),
        "{err}"
    );
    let err = read("t_s,enc0,enc1,enc3,ots_x,ots_y,ots_z\n").unwrap_err();
    assert!(
        matches!(err, DatasetError::MissingColumn { ref column, .. } if column == "enc2"),
        "{err}"
    );
    let err = read("t_s,enc0,enc1,ots_x,ots_y,ots_z\n")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("enc2") && err.contains("at least 3 strings"),
        "{err}"
    );
    // A planar device's tracker may leave out ots_z ...
    let s = read("t_s,enc0,enc1,enc2,ots_x,ots_y\n0,1,2,3,4.5,5.5\n").unwrap();
    assert_eq!(s.samples[0].tracker, Some([4.5, 5.5, 0.0]));
    assert!(!s.tracker_z);
    let planar = geometry(
        "counts_per_rev = 4096\npulley_radius_mm = 10\nplanar = true\nhome_mm = [0, 0]\n\
         anchors_mm = [[-500, -400], [500, -400], [0, 400]]\n\
         room_from_device_translation_mm = [0, 0, 900]\n",
    )
    .unwrap();
    let (file, geometry_file) = (Path::new("s.csv"), Path::new("g.toml"));
    s.check_strings(file, &planar, geometry_file).unwrap();
    // ... a 3-D device's may not: z would read 0 everywhere.
    let cube = geometry(
        "counts_per_rev = 4096\npulley_radius_mm = 10\nhome_mm = [0, 0, 0]\n\
         anchors_mm = [[-500, -400, 0], [500, -400, 0], [0, 400, 0], [0, 0, 600]]\n\
         room_from_device_translation_mm = [0, 0, 900]\n",
    )
    .unwrap();
    let err = s.check_strings(file, &cube, geometry_file).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DatasetError::StringCount { .. }), "{msg}");
    let s4 = read("t_s,enc0,enc1,enc2,enc3,ots_x,ots_y\n0,1,2,3,4,4.5,5.5\n").unwrap();
    let err = s4.check_strings(file, &cube, geometry_file).unwrap_err();
    let msg = err.to_string();
    assert!(
        matches!(err, DatasetError::NoTrackerZ { .. })
            && msg.contains("s.csv")
            && msg.contains("g.toml")
            && msg.contains("ots_z")
            && msg.contains("3-D"),
        "{msg}"
    );
    let with_z =
        read("t_s,enc0,enc1,enc2,enc3,ots_x,ots_y,ots_z\n0,1,2,3,4,4.5,5.5,6.5\n").unwrap();
    assert!(with_z.tracker_z);
    with_z.check_strings(file, &cube, geometry_file).unwrap();
}

#[test]
fn degenerate_anchors_are_an_error_that_says_so() {
    let one_point = "counts_per_rev = 4096\npulley_radius_mm = 7.5\nhome_mm = [0, 0, 0]\n\
                     anchors_mm = [[1, 1, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]]\n\
                     room_from_device_translation_mm = [0, 0, 0]\n";
    let e = geometry(one_point).unwrap_err().to_string();
    assert!(e.contains("anchors_mm") && e.contains("one point"), "{e}");
    let line = one_point.replace(
        "[[1, 1, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]]",
        "[[1, 0, 0], [2, 0, 0], [3, 0, 0], [5, 0, 0]]",
    );
    let e = geometry(&line).unwrap_err().to_string();
    assert!(e.contains("one line"), "{e}");
}

// ---------------------------------------------------------------------------
// The tracked body's orientation (ots_qw, ots_qx, ots_qy, ots_qz)
// ---------------------------------------------------------------------------

const ORIENTED: &str = "t_s,enc0,enc1,enc2,ots_x,ots_y,ots_z,ots_qw,ots_qx,ots_qy,ots_qz";

fn oriented(t_s: f64, tracker: Option<[f64; 3]>, orientation: Option<[f64; 4]>) -> Sample {
    Sample {
        t_s,
        counts: [1, -2, 3, 0, 0, 0, 0, 0],
        tracker,
        orientation,
        legacy: None,
        tension_n: Some([1.5, 2.0, 2.5, 0.0, 0.0, 0.0, 0.0, 0.0]),
        since_home_s: None,
        home: None,
    }
}

#[test]
fn orientation_round_trip_is_lossless_with_rows_without_one() {
    // A sixth of a turn about z rounded to 1e-6 as the simulator writes it, an
    // awkward exact unit quaternion, a position without orientation (the
    // rigid body lost, a marker kept), an occluded row.
    let s = Session {
        strings: 3,
        samples: vec![
            oriented(0.0, Some([1.0, 2.0, 3.0]), Some([0.866025, 0.0, 0.0, 0.5])),
            oriented(0.5, Some([1.5, -2.0, 1.0 / 3.0]), None),
            oriented(1.0, None, None),
            oriented(
                1.5,
                Some([0.0, 0.0, 0.0]),
                Some([0.1 + 0.2, -0.5, 0.5, (1.0f64 - 0.09 - 0.5).sqrt()]),
            ),
            oriented(2.0, Some([4.0, 5.0, 6.0]), Some([-1.0, 0.0, -0.0, 0.0])),
        ],
        ignored_columns: vec![],
        unread_columns: Vec::new(),
        tracker_z: true,
    };
    assert!(s.has_orientation());
    let path = tmp("oriented.csv");
    s.write(&path).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some(format!("{ORIENTED},tension0,tension1,tension2").as_str())
    );
    assert_eq!(
        lines.next(),
        Some("0,1,-2,3,1,2,3,0.866025,0,0,0.5,1.5,2,2.5")
    );
    assert_eq!(
        lines.next(),
        Some("0.5,1,-2,3,1.5,-2,0.3333333333333333,,,,,1.5,2,2.5")
    );
    assert_eq!(lines.next(), Some("1,1,-2,3,,,,,,,,1.5,2,2.5"));
    assert_eq!(Session::load(&path).unwrap(), s);
}

#[test]
fn a_session_without_orientation_reads_none_and_is_written_as_before() {
    let s = Session::load(shared("session-head.csv")).unwrap();
    assert!(s.samples.iter().all(|x| x.orientation.is_none()));
    assert!(!s.has_orientation());
    // Written byte for byte as before the orientation existed.
    let text = format!(
        "{HEADER},dev_x,dev_y,dev_z\n\
         0.25,1,2,3,4,5,6,7,8,1.5,-2.5,1000.125,0.1,0.2,0.3\n\
         0.5,1,2,3,4,5,6,7,8,,,,0.1,0.2,0.3\n"
    );
    let s = read(&text).unwrap();
    assert!(s.samples.iter().all(|x| x.orientation.is_none()));
    let mut out = Vec::new();
    s.write_to(&mut out, Path::new("mem/out.csv")).unwrap();
    assert_eq!(String::from_utf8(out).unwrap(), text);
    // Orientation columns left empty on every row: nothing to write back.
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,,,,\n1,1,2,3,,,,,,,\n");
    let s = read(&text).unwrap();
    assert!(s.samples.iter().all(|x| x.orientation.is_none()));
    assert!(s.ignored_columns.is_empty());
    let mut out = Vec::new();
    s.write_to(&mut out, Path::new("mem/out.csv")).unwrap();
    assert_eq!(
        String::from_utf8(out).unwrap(),
        "t_s,enc0,enc1,enc2,ots_x,ots_y,ots_z\n0,1,2,3,1,2,3\n1,1,2,3,,,\n"
    );
}

#[test]
fn orientation_columns_in_any_order_and_a_planar_session() {
    let text = "ots_qz,t_s,ots_qy,enc0,enc1,ots_qx,enc2,ots_x,ots_qw,ots_y\n\
                0.8,0.5,0,1,2,0,3,10,0.6,20\n";
    let s = read(text).unwrap();
    assert!(!s.tracker_z);
    assert_eq!(s.samples[0].tracker, Some([10.0, 20.0, 0.0]));
    assert_eq!(s.samples[0].orientation, Some([0.6, 0.0, 0.0, 0.8]));
}

#[test]
fn error_incomplete_orientation_header() {
    let text = format!("{HEADER},ots_qw,ots_qx,ots_qy\n");
    let err = read(&text).unwrap_err();
    let msg = err.to_string();
    assert!(
        matches!(err, DatasetError::IncompleteGroup { ref present, ref missing, .. }
            if present == "ots_qw" && missing == "ots_qz"),
        "{msg}"
    );
    assert!(
        msg.contains("mem/session.csv") && msg.contains("line 1") && msg.contains("`ots_qz`"),
        "{msg}"
    );
    // A misspelt column is ignored, and its group is then incomplete.
    let text = format!("{HEADER},ots_qw,ots_qx,ots_qy,ots_gz\n");
    let err = read(&text).unwrap_err();
    assert!(
        matches!(err, DatasetError::IncompleteGroup { ref missing, .. } if missing == "ots_qz"),
        "{err}"
    );
}

#[test]
fn error_partially_empty_orientation() {
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,1,0,0,0\n1,1,2,3,1,2,3,1,0,,0\n");
    let p = value_error(&text, 3, "ots_qy");
    assert_eq!(
        p,
        ValueProblem::PartialGroup {
            filled: "ots_qw".into(),
            group: "ots_qw, ots_qx, ots_qy, ots_qz".into()
        }
    );
}

#[test]
fn error_orientation_not_a_unit_quaternion() {
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,1,0,0,0\n1,1,2,3,1,2,3,0.8,0,0,0\n");
    let p = value_error(&text, 3, "ots_qw");
    assert_eq!(p, ValueProblem::NotUnitQuaternion(0.8));
    let msg = read(&text).unwrap_err().to_string();
    assert!(
        msg.contains("norm 0.8") && msg.contains("unit quaternion"),
        "{msg}"
    );
    // Zero, and just outside the tolerance; just inside it is read as given.
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,0,0,0,0\n");
    assert_eq!(
        value_error(&text, 2, "ots_qw"),
        ValueProblem::NotUnitQuaternion(0.0)
    );
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,0,0,-1.0011,0\n");
    assert_eq!(
        value_error(&text, 2, "ots_qw"),
        ValueProblem::NotUnitQuaternion(1.0011)
    );
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,0,0,-0.9991,0\n");
    assert_eq!(
        read(&text).unwrap().samples[0].orientation,
        Some([0.0, 0.0, -0.9991, 0.0])
    );
}

#[test]
fn error_orientation_not_finite_or_not_a_number() {
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,1,NaN,0,0\n");
    assert_eq!(
        value_error(&text, 2, "ots_qx"),
        ValueProblem::NotFinite("NaN".into())
    );
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,1,0,0,-inf\n");
    assert_eq!(
        value_error(&text, 2, "ots_qz"),
        ValueProblem::NotFinite("-inf".into())
    );
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,1,0,one,0\n");
    assert_eq!(
        value_error(&text, 2, "ots_qy"),
        ValueProblem::NotANumber("one".into())
    );
}

#[test]
fn error_orientation_without_position() {
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,1,0,0,0\n1,1,2,3,,,,1,0,0,0\n");
    let p = value_error(&text, 3, "ots_qw");
    assert_eq!(p, ValueProblem::OrientationWithoutPosition);
    let msg = read(&text).unwrap_err().to_string();
    assert!(msg.contains("occluded") && msg.contains("`ots_x`"), "{msg}");
    // A position without orientation is a marker seen, its body's
    // orientation lost: allowed.
    let text = format!("{ORIENTED}\n0,1,2,3,1,2,3,,,,\n");
    let s = read(&text).unwrap();
    assert_eq!(s.samples[0].tracker, Some([1.0, 2.0, 3.0]));
    assert_eq!(s.samples[0].orientation, None);
}

#[test]
fn writing_rejects_an_orientation_reading_would_reject() {
    for (tracker, orientation, column, problem) in [
        (
            Some([1.0, 2.0, 3.0]),
            [0.5, 0.0, 0.0, 0.0],
            "ots_qw",
            ValueProblem::NotUnitQuaternion(0.5),
        ),
        (
            Some([1.0, 2.0, 3.0]),
            [1.0, 0.0, f64::NAN, 0.0],
            "ots_qy",
            ValueProblem::NotFinite("NaN".into()),
        ),
        (
            None,
            [1.0, 0.0, 0.0, 0.0],
            "ots_qw",
            ValueProblem::OrientationWithoutPosition,
        ),
    ] {
        let s = Session {
            strings: 3,
            samples: vec![
                oriented(0.0, Some([1.0, 2.0, 3.0]), Some([1.0, 0.0, 0.0, 0.0])),
                oriented(1.0, tracker, Some(orientation)),
            ],
            ignored_columns: vec![],
            unread_columns: Vec::new(),
            tracker_z: true,
        };
        let path = tmp("bad-orientation.csv");
        let err = s.write(&path).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("bad-orientation.csv"), "{msg}");
        match err {
            DatasetError::Value {
                line,
                column: c,
                problem: p,
                ..
            } => assert_eq!((line, c.as_str(), p), (3, column, problem), "{msg}"),
            other => panic!("expected a value error, got {other:?}"),
        }
    }
}

/// `since_home_s` and `home`: read, written back, and checked as the
/// device's clock and home captures allow.
#[test]
fn time_since_home_and_home_ids_read_back_and_are_checked() {
    let header = "t_s,enc0,enc1,enc2,enc3,enc4,enc5,enc6,enc7,ots_x,ots_y,ots_z,since_home_s,home";
    let row =
        |t: &str, since: &str, home: &str| format!("{t},0,0,0,0,0,0,0,0,1,2,3,{since},{home}");
    let text = [
        header.to_string(),
        row("10", "5", "7"),
        row("11", "6", "7"),
        // A new home capture: the time since home starts again.
        row("12", "0.5", "8"),
        row("13", "", ""),
    ]
    .join("\n");
    let s = read(&text).unwrap();
    let got: Vec<(Option<f64>, Option<u64>)> =
        s.samples.iter().map(|r| (r.since_home_s, r.home)).collect();
    assert_eq!(
        got,
        [
            (Some(5.0), Some(7)),
            (Some(6.0), Some(7)),
            (Some(0.5), Some(8)),
            (None, None)
        ]
    );
    let mut written = Vec::new();
    s.write_to(&mut written, Path::new("mem/out.csv")).unwrap();
    let written = String::from_utf8(written).unwrap();
    assert!(written.starts_with(header), "{written}");
    assert_eq!(read(&written).unwrap(), s);

    let back = [header.to_string(), row("10", "5", "7"), row("11", "4", "7")].join("\n");
    assert!(matches!(
        value_error(&back, 3, "since_home_s"),
        ValueProblem::SinceHomeDecreasing {
            previous_line: 2,
            home: 7,
            ..
        }
    ));
    let negative = [header.to_string(), row("10", "-1", "7")].join("\n");
    assert!(matches!(
        value_error(&negative, 2, "since_home_s"),
        ValueProblem::NegativeSinceHome(_)
    ));
    let not_an_id = [header.to_string(), row("10", "1", "7.5")].join("\n");
    assert!(matches!(
        value_error(&not_an_id, 2, "home"),
        ValueProblem::NotAHomeId(_)
    ));
    // The writer refuses what the reader would.
    let mut bad =
        read(&[header.to_string(), row("10", "5", "7"), row("11", "6", "7")].join("\n")).unwrap();
    bad.samples[1].since_home_s = Some(1.0);
    let e = bad
        .write_to(Vec::new(), Path::new("mem/bad.csv"))
        .unwrap_err();
    assert!(
        e.to_string().contains("line 3, column `since_home_s`"),
        "{e}"
    );
}
