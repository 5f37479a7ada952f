//! Tests of the calibration's checks and warnings.

use std::path::Path;

use super::*;
use crate::data::dataset::Sample;
use crate::data::observe::observations;
use crate::data::stats::ErrorStats;
use crate::model::reference;
use crate::procedures::calibrate::evaluate::stage;
use spidar_core::STRINGS;

/// A row at `t_s` whose tracker reads `tracker` (room frame), counts 0.
fn tracked_at(t_s: f64, tracker: [f64; 3]) -> Sample {
    Sample {
        t_s,
        counts: [0; STRINGS],
        tracker: Some(tracker),
        orientation: None,
        legacy: None,
        tension_n: None,
        since_home_s: None,
        home: None,
    }
}

fn stage_at(kind: report::StageKind, name: &str, test_mean: f64) -> report::Stage {
    let mut test = ErrorStats::of(&[test_mean]);
    test.mean_mm = test_mean;
    stage(name, kind, test, test)
}

/// A final model worse than the plain fit held out is named with the
/// part that lost, read off the stages.
#[test]
fn a_final_model_worse_than_the_reference_names_what_lost() {
    use report::StageKind::*;
    let stages = |identified, effect, fin| {
        vec![
            stage_at(Raw, "raw", 20.0),
            stage_at(Reference, reference::STAGE_NAME, 1.0),
            stage_at(Identified, "identified", identified),
            stage_at(Effect, "offset string 1", effect),
            stage_at(Final, "final (svr)", fin),
        ]
    };
    assert_eq!(reference_warning(&stages(1.2, 1.1, 0.9), 2.0), None);
    let w = |s: Vec<report::Stage>, plain| reference_warning(&s, plain).expect("a warning");
    assert!(w(stages(1.2, 0.9, 1.1), 2.0).contains("learned correction"));
    assert!(w(stages(1.2, 1.1, 1.1), 0.95).contains("kinematics' rule"));
    assert!(w(stages(0.95, 1.1, 1.1), 2.0).contains("loop's terms"));
    assert!(w(stages(1.2, 1.1, 1.1), 2.0).contains("robust weights and priors"));
}

/// The final model above the reference by less than the report's
/// micrometre (the survey's 0.37577 against 0.37569 mm) is one figure, as
/// in the selection: no warning; and a stage within it of the reference
/// holds as the reference does when the warning names what lost.
#[test]
fn a_final_model_above_the_reference_by_less_than_the_reports_micrometre_is_no_loss() {
    use report::StageKind::*;
    let stages = |identified, fin| {
        vec![
            stage_at(Reference, reference::STAGE_NAME, 0.37569),
            stage_at(Identified, "identified", identified),
            stage_at(Effect, "offset string 1", 0.378),
            stage_at(Final, "final (identified)", fin),
        ]
    };
    assert_eq!(reference_warning(&stages(0.37577, 0.37577), 2.0), None);
    let tie = crate::procedures::calibrate::corrections::SELECTION_TIE_MM;
    let w = reference_warning(&stages(0.37569 + tie / 2.0, 0.378), 2.0).expect("a warning");
    assert!(w.contains("loop's terms"), "{w}");
    let w = reference_warning(&stages(0.377, 0.378), 0.37569 + tie / 2.0).expect("a warning");
    assert!(w.contains("kinematics' rule"), "{w}");
}

/// A declared anchor tolerance the data contradict is named with the
/// anchor, its distance from the drawing in sds and both figures; not
/// when the identified model beats the reference, when the anchor is
/// within the tolerance's 0.1 % chi-square, or when nothing is declared.
#[test]
fn a_declared_anchor_tolerance_the_data_contradict_is_named() {
    use report::StageKind::*;
    let drawing = crate::sim::SimConfig::default()
        .nominal
        .geometry()
        .nominal_frame();
    let mut fitted = drawing;
    fitted.anchors[2][0] += 4.5;
    let stages = |identified| {
        vec![
            stage_at(Reference, reference::STAGE_NAME, 0.5),
            stage_at(Identified, "identified", identified),
        ]
    };
    let one = [1.0; STRINGS];
    let w =
        declared_tolerance_warning(Some(&one), &drawing, &fitted, &stages(3.0)).expect("a warning");
    assert!(
        w.contains("anchor 2 4.5 mm from the drawing (4 sds)") && w.contains("3.000 mm"),
        "{w}"
    );
    // 4.5 sds in space is beyond the 0.1 % chi-square (16.27, 4.03 sds);
    // 3.9 is not.
    fitted.anchors[2][0] = drawing.anchors[2][0] + 3.9;
    assert_eq!(
        declared_tolerance_warning(Some(&one), &drawing, &fitted, &stages(3.0)),
        None
    );
    fitted.anchors[2][0] = drawing.anchors[2][0] + 4.5;
    assert_eq!(
        declared_tolerance_warning(Some(&one), &drawing, &fitted, &stages(0.4)),
        None
    );
    // Above the reference's 0.5 mm by less than the report's micrometre:
    // one figure, no contradiction shown.
    assert_eq!(
        declared_tolerance_warning(Some(&one), &drawing, &fitted, &stages(0.50008)),
        None
    );
    assert_eq!(
        declared_tolerance_warning(None, &drawing, &fitted, &stages(3.0)),
        None
    );
}

/// The warnings name the lines (CSV line = row + 2) with their
/// disagreement, the first 12 and how many more.
#[test]
fn tracker_outlier_warnings_name_their_lines() {
    use crate::model::diagnose::TrackerOutliers;
    let outliers = TrackerOutliers {
        rows: (0..13).collect(),
        lines: (12..25).collect(),
        errors_mm: (0..13).map(|k| 50.0 + k as f64).collect(),
        median_mm: 0.9,
        threshold_mm: 18.0,
        kept_too_many: 0,
    };
    let w = tracker_outlier_warning(Path::new("train.csv"), &outliers).unwrap();
    assert!(w.starts_with("train.csv: the tracker of 13 rows"), "{w}");
    assert!(w.contains("lines 12 (50 mm), 13 (51 mm)"), "{w}");
    assert!(
        w.contains("23 (61 mm) and 1 more (the JSON report's"),
        "{w}"
    );
    let t = test_outlier_warning(Path::new("test.csv"), &outliers).unwrap();
    assert!(
        t.contains("the held-out figures include them: lines 12 (50 mm)"),
        "{t}"
    );
    assert!(t.ends_with("23 (61 mm) and 1 more"), "{t}");
    let none = TrackerOutliers::default();
    assert_eq!(tracker_outlier_warning(Path::new("t"), &none), None);
    assert_eq!(test_outlier_warning(Path::new("t"), &none), None);
    let too_many = TrackerOutliers {
        kept_too_many: 40,
        ..none
    };
    let w = tracker_outlier_warning(Path::new("t"), &too_many).unwrap();
    assert!(w.contains("40 rows") && w.contains("all are kept"), "{w}");
}

/// One row is one row: "the tracker of 1 row disagrees with most of its
/// strings ... line 7", never "1 rows" (a survey's finding).
#[test]
fn one_tracker_outlier_is_one_row() {
    use crate::model::diagnose::TrackerOutliers;
    let one = TrackerOutliers {
        rows: vec![5],
        lines: vec![7],
        errors_mm: vec![50.0],
        median_mm: 0.9,
        threshold_mm: 18.0,
        kept_too_many: 0,
    };
    let w = tracker_outlier_warning(Path::new("train.csv"), &one).unwrap();
    assert!(
        w.contains("the tracker of 1 row disagrees with most of its strings")
            && w.contains("it is read as an occluded row")
            && w.contains(": line 7 (50 mm)"),
        "{w}"
    );
    let t = test_outlier_warning(Path::new("test.csv"), &one).unwrap();
    assert!(
        t.contains("the tracker of 1 row disagrees with most of its strings")
            && t.contains("include it: line 7 (50 mm)"),
        "{t}"
    );
}

/// The tracker's spread against the nominal model's: at a factor of 3
/// a warning, at 5 a refusal naming the unit it looks like, both ways;
/// the paper-sized factor of 2 passes; too few rows say nothing.
#[test]
fn a_tracker_spread_off_the_nominal_model_is_warned_or_refused() {
    let nominal: Vec<[f64; 3]> = (0..20)
        .map(|k| {
            [
                k as f64 * 30.0,
                (k % 4) as f64 * 50.0,
                (k % 3) as f64 * 70.0,
            ]
        })
        .collect();
    let obs = |scale: f64| -> Vec<Observation> {
        let samples: Vec<Sample> = nominal
            .iter()
            .map(|p| tracked_at(0.0, p.map(|x| x * scale + 5.0)))
            .collect();
        observations(&samples)
    };
    let check = |scale: f64| {
        check_tracker_scale(
            Path::new("train.csv"),
            Path::new("geometry.toml"),
            &obs(scale),
            &nominal,
        )
    };
    for scale in [1.0, 2.0, 0.5, 2.9] {
        assert!(matches!(check(scale), Ok(None)), "{scale}");
    }
    let warned = check(4.0).unwrap().unwrap();
    assert!(
        warned.contains("train.csv") && warned.contains("4.0000 times"),
        "{warned}"
    );
    let refused = |scale: f64| check(scale).unwrap_err().to_string();
    assert!(refused(0.001).contains("`ots_*` columns look like metres"));
    assert!(refused(0.1).contains("look like centimetres"));
    assert!(refused(1.0 / 25.4).contains("look like inches"));
    assert!(refused(1000.0).contains("the geometry's lengths"));
    let other = refused(6.0);
    assert!(
        other.contains("pulley_radius_mm") && other.contains("geometry.toml"),
        "{other}"
    );
    // Two tracked rows: no spread to judge.
    assert!(matches!(
        check_tracker_scale(
            Path::new("t"),
            Path::new("g"),
            &obs(0.001)[..2],
            &nominal[..2]
        ),
        Ok(None)
    ));
}

/// Test points beyond the training box are counted, with the final
/// model's error outside and inside, and the plain least-squares
/// reference's on the same points beside it (not when the reference is
/// the final model); none outside, no warning.
#[test]
fn test_points_beyond_the_training_box_are_warned_with_the_plain_fit_beside() {
    use crate::procedures::calibrate::evaluate::PointErrors;
    let frame = crate::sim::SimConfig::default()
        .nominal
        .geometry()
        .nominal_frame();
    let room = |p: [f64; 3]| spidar_core::geometry::room_from_device(&frame, p);
    let samples: Vec<Sample> = (0..8)
        .map(|k| {
            let corner = [k & 1, k >> 1 & 1, k >> 2].map(|b| b as f64 * 100.0);
            tracked_at(k as f64, room(corner))
        })
        .collect();
    let train = observations(&samples);
    // Two test points inside the training box, one 50 mm beyond it.
    let tracker = vec![
        room([50.0, 50.0, 50.0]),
        room([10.0, 90.0, 20.0]),
        room([150.0, 50.0, 50.0]),
    ];
    let points = |name: &str, errors: Vec<f64>| StagePoints {
        name: name.into(),
        train: PointErrors {
            rows: Vec::new(),
            tracker: Vec::new(),
            distance_mm: Vec::new(),
            errors: Vec::new(),
        },
        test: PointErrors {
            rows: vec![0, 1, 2],
            tracker: tracker.clone(),
            distance_mm: vec![0.0; 3],
            errors,
        },
    };
    let fin = points("final (nn)", vec![0.2, 0.4, 1.5]);
    let plain = points(reference::STAGE_NAME, vec![0.5, 0.7, 2.5]);
    let warnings = trust_warnings(&frame, &train, Some(&fin), Some(&plain));
    let w = warnings
        .iter()
        .find(|w| w.contains("outside the volume"))
        .expect("an extrapolation warning");
    assert!(w.starts_with("1 of 3 test points"), "{w}");
    assert!(
        w.contains("final error outside 1.500 mm mean, 1.500 max, inside 0.300 mean, 0.400 max"),
        "{w}"
    );
    assert!(
        w.ends_with("(the plain least-squares reference: outside 2.500 mean, inside 0.600)"),
        "{w}"
    );
    // The reference as the final model: no figure beside itself.
    let alone = trust_warnings(&frame, &train, Some(&plain), Some(&plain));
    let w = alone
        .iter()
        .find(|w| w.contains("outside the volume"))
        .unwrap();
    assert!(!w.contains("the plain least-squares reference:"), "{w}");
    // Every test point inside: no warning.
    let inside = points("final (nn)", vec![0.2, 0.4, 1.5]);
    let inside = StagePoints {
        test: PointErrors {
            tracker: vec![tracker[0]; 3],
            ..inside.test
        },
        ..inside
    };
    let none = trust_warnings(&frame, &train, Some(&inside), Some(&plain));
    assert!(
        !none.iter().any(|w| w.contains("outside the volume")),
        "{none:?}"
    );
}

/// A session whose best fit leaves more than a twentieth of its tracked
/// positions' spread is one no geometry fits; under it, no warning.
#[test]
fn a_session_no_geometry_fits_is_named() {
    use report::StageKind::*;
    let samples: Vec<Sample> = (0..4)
        .map(|k| {
            tracked_at(
                k as f64,
                [if k % 2 == 0 { -100.0 } else { 100.0 }, 0.0, 0.0],
            )
        })
        .collect();
    let tr = observations(&samples);
    // Spread: 100 mm from the centroid; the bar 5 mm.
    let stages = |reference_mm, identified_mm| {
        let train = |mean: f64| {
            let mut s = ErrorStats::of(&[mean]);
            s.mean_mm = mean;
            s
        };
        vec![
            stage(
                reference::STAGE_NAME,
                Reference,
                train(reference_mm),
                train(0.0),
            ),
            stage("identified", Identified, train(identified_mm), train(0.0)),
        ]
    };
    let path = Path::new("train.csv");
    let w = unfitted_warning(path, &tr, &stages(6.0, 7.0)).expect("a warning");
    assert!(
        w.starts_with("train.csv: no geometry fits this session")
            && w.contains("6.000 mm")
            && w.contains("6.0 % of their spread (100.0 mm"),
        "{w}"
    );
    assert_eq!(unfitted_warning(path, &tr, &stages(6.0, 4.9)), None);
}

#[test]
fn a_planar_session_on_a_tilted_plane_or_off_any_plane_is_named() {
    // A 600 mm square walked in a grid; the tracker's x-y plane tilted
    // from the device's about its y axis, and `z_off` mm off the plane
    // in a checkerboard (no slope).
    let rows = |tilt_deg: f64, z_off: f64| -> Vec<Sample> {
        let slope = tilt_deg.to_radians().tan();
        (0..100)
            .map(|k| {
                let (x, y) = (
                    -300.0 + 60.0 * (k % 10) as f64,
                    -300.0 + 60.0 * (k / 10) as f64,
                );
                let off = if (k + k / 10) % 2 == 0 { z_off } else { -z_off };
                tracked_at(k as f64 * 0.1, [x, y, 500.0 + slope * x + off])
            })
            .collect()
    };
    let warn = |tilt, off| planar_session_warnings(Path::new("wall.csv"), &rows(tilt, off), 0.5);
    let w = warn(6.0, 0.0);
    assert_eq!(w.len(), 1, "{w:?}");
    assert!(w[0].starts_with("wall.csv: "), "{}", w[0]);
    assert!(w[0].contains("tilted 6.0 degrees"), "{}", w[0]);
    // 540 mm along the tilt, 1 / cos(6 deg) - 1 of it.
    assert!(
        w[0].contains("read 2.97 mm short over the session's 540 mm"),
        "{}",
        w[0]
    );
    assert!(warn(0.0, 0.0).is_empty());
    // A tilt whose shortfall stays within the strings' residual scale.
    assert!(warn(2.0, 0.0).is_empty());
    // A 3-D session: 200 mm off the plane against 2 x 257 mm in it.
    let w = warn(0.0, 200.0);
    assert_eq!(w.len(), 1, "{w:?}");
    assert!(w[0].contains("leave their plane by 200 mm"), "{}", w[0]);
    assert!(w[0].contains("a 3-D device's session"), "{}", w[0]);
    // A marker that wobbles a few mm off the plane is no 3-D session.
    assert!(warn(0.0, 5.0).is_empty());
}
