//! What `calibrate` reaches on independent devices: the clean one, devices
//! of six and five strings with a faulty one, a planar one.

use super::fixtures::{assert_final_test_below, calibrate_quick, device_and_sessions};
use spidar::sim::physics::{simulate_session, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;

/// Held-out error today's pipeline reaches on the independent simulator
/// (device seed 1, lattice session seed 2, 500-point test session seed 3,
/// `CalibrateConfig::quick`), measured 2026-11-24: identified (smooth
/// winding law) 1.142 mm mean, 3.85 max; with the layer tables 0.665 mean,
/// 2.86 max; final (nn) 0.477 mean, 1.01 p95, 3.01 max. The target
/// (0.45 mean, 3 max, over seeds 1-3: 0.437 mean, worst max 3.01) is met
/// on the mean over seeds, not on this seed alone: the bounds are today's
/// figures plus a margin, to catch regressions.
const IDENTIFIED_MEAN_MAX_MM: f64 = 1.3;
const LAYERS_MEAN_MAX_MM: f64 = 0.75;
const LAYERS_MAX_MAX_MM: f64 = 3.3;
const FINAL_MEAN_MAX_MM: f64 = 0.53;
const FINAL_MAX_MAX_MM: f64 = 3.5;

#[test]
fn calibration_on_the_independent_simulator() {
    let device = PhysicsDevice::new(&PhysicsConfig::default(), 1).unwrap();
    let (train, _) = simulate_session(&device, SessionKind::Lattice, 2).unwrap();
    let (test, _) = simulate_session(&device, SessionKind::Random { points: 500 }, 3).unwrap();
    let c = calibrate_quick(&device, &train, &test);
    let stages = &c.report.stages;
    for s in stages {
        println!(
            "{:<24} test mean {:.3} p95 {:.3} max {:.3}",
            s.name, s.test.mean_mm, s.test.p95_mm, s.test.max_mm
        );
    }
    let identified = stages.iter().find(|s| s.name == "identified").unwrap();
    let layers = stages
        .iter()
        .find(|s| s.name.starts_with("layers strings"))
        .expect("layer tables added");
    assert!(
        layers.test.mean_mm <= LAYERS_MEAN_MAX_MM && layers.test.max_mm <= LAYERS_MAX_MAX_MM,
        "{:?}",
        layers.test
    );
    // The tables hold on the test session, which reaches a little beyond
    // the lattice: the max does not rise over the smooth law's.
    assert!(
        layers.test.max_mm <= identified.test.max_mm,
        "{:?}",
        layers.test
    );
    let last = stages.last().unwrap();
    // The raw error is large, the calibration removes nearly all of it...
    assert!(stages[0].test.mean_mm > 50.0, "{:?}", stages[0].test);
    assert!(
        identified.test.mean_mm <= IDENTIFIED_MEAN_MAX_MM,
        "identified {:?}",
        identified.test
    );
    assert!(
        last.test.mean_mm <= FINAL_MEAN_MAX_MM && last.test.max_mm <= FINAL_MAX_MAX_MM,
        "{}: {:?}",
        last.name,
        last.test
    );
    // The smooth law alone is far from the tracker's noise (0.32 mm mean):
    // what the tables bring is the layering.
    assert!(identified.test.mean_mm > 0.9, "{:?}", identified.test);
}

/// Six strings (3 spares) with the abnormal motor on string 4: rows where
/// it is off its groove or jammed are solved without it, also where leaving
/// a good string out fits too but clearly worse. Before that rule, 4 test
/// rows were inconsistent and the all-string compromise 5.0 mm off (seed
/// 3, full calibration: final 0.454 / 5.03 mm -> 0.360 / 1.24).
#[test]
fn a_six_string_device_leaves_its_faulty_string_out() {
    let mut config = PhysicsConfig::default();
    config.nominal.strings = 6;
    let (device, train, _, test) = device_and_sessions(&config, 3, 500);
    let c = calibrate_quick(&device, &train, &test);
    assert_eq!(c.report.device.redundancy, 3);
    let rejections = &c.report.device.rejections.test;
    assert!(rejections.excluded_by_channel[4] > 0, "{rejections:?}");
    assert_eq!(rejections.inconsistent, 0, "{rejections:?}");
    assert_final_test_below(&c, 0.42, 2.0);
}

/// Five strings (2 spares) with the abnormal motor on string 4: where it
/// is far off its groove another exclusion can fit by chance, so none is
/// trusted, and the row took the all-string compromise, up to 31 mm off the
/// tracker. It now takes the exclusion that fits clearly best (still
/// inconsistent: force off), and the loop's judge counts such rows instead
/// of refusing changes whose error flips on them (seed 2, full
/// calibration: final 0.849 / 31.6 mm -> 0.442 / 7.9).
#[test]
fn a_five_string_device_places_its_inconsistent_rows_without_its_faulty_string() {
    let mut config = PhysicsConfig::default();
    config.nominal.strings = 5;
    let (device, train, _, test) = device_and_sessions(&config, 2, 500);
    let c = calibrate_quick(&device, &train, &test);
    assert_eq!(c.report.device.redundancy, 2);
    let limits = &c.report.device.limits;
    assert!(
        limits.iter().any(|l| l.starts_with("two spare strings")),
        "{limits:?}"
    );
    let rejections = &c.report.device.rejections.test;
    let placed = rejections.inconsistent_excluded_by_channel;
    assert!(placed[4] > 0, "{rejections:?}");
    assert_eq!(placed.iter().sum::<usize>(), placed[4], "{rejections:?}");
    assert_final_test_below(&c, 0.6, 12.0);
}

/// A planar device on the independent physics (issue 11): the strings meet
/// in the anchors' plane (the marker, held off the meeting point, may not),
/// and the calibration reaches the tracker's noise there.
#[test]
fn a_planar_device_of_other_physics_calibrates() {
    let mut config = PhysicsConfig::default();
    config.nominal.strings = 4;
    config.nominal.planar = true;
    config.abnormal_motor.enabled = false;
    let (device, train, truth, test) = device_and_sessions(&config, 1, 300);
    let plane_z = device.nominal.home_mm[2];
    for t in &truth {
        assert!(
            (t.meeting_mm[2] - plane_z).abs() < 1e-9,
            "{:?}",
            t.meeting_mm
        );
    }
    let c = calibrate_quick(&device, &train, &test);
    assert!(c.report.device.redundancy == 2);
    // Measured 0.315 mm mean, 0.96 max on a 500-point test (seed 1).
    assert_final_test_below(&c, 0.5, 2.0);
}
