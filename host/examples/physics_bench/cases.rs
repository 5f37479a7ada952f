//! The cases of both simulators, one table row per seed.

use super::notes::{creep_against_truth, home_judged, not_added, slip_steps, test_session_slips};
use super::options::Options;
use super::runs::{model_run, physics_device, physics_run, run_calibration, Run, Sessions};
use super::table::{print_row, CaseRows};
use spidar::procedures::calibrate::{CalibrateConfig, Calibrated};
use spidar::sim::physics::{PhysicsDevice, PhysicsTruth};

/// A clean independent device with its lattice run, truths and calibration,
/// for the analysis after the tables.
pub(super) type CleanPhysics = (PhysicsDevice, Run, Vec<PhysicsTruth>, Calibrated);

/// The model simulator's `drift-each` case: every string drifts at its
/// own rate around a shared one (0.0004-0.0008 mm/s), as issue 33's hidden
/// simulator's strings do (its shared drift took most, a string's own
/// took the rest).
const DRIFT_EACH: [&str; 8] = [
    "drift:0:mm_per_s=0.0006",
    "drift:1:mm_per_s=0.0004",
    "drift:2:mm_per_s=0.0008",
    "drift:3:mm_per_s=0.0005",
    "drift:4:mm_per_s=0.0007",
    "drift:5:mm_per_s=0.0004",
    "drift:6:mm_per_s=0.0006",
    "drift:7:mm_per_s=0.0008",
];

/// The `drift-mixed` case: rates of either sign, -0.0005 to 0.0012 mm/s.
const DRIFT_MIXED: [&str; 8] = [
    "drift:0:mm_per_s=0.0008",
    "drift:1:mm_per_s=-0.0005",
    "drift:2:mm_per_s=0.0012",
    "drift:3:mm_per_s=0.0003",
    "drift:4:mm_per_s=0.0009",
    "drift:5:mm_per_s=-0.0002",
    "drift:6:mm_per_s=0.0006",
    "drift:7:mm_per_s=0.001",
];

/// The model simulator's cases, one row per seed: (name, injected
/// effects); a name ending in `-continuing` has its test session continue
/// the lattice's home (its clock, drifts and slips go on into it).
pub(super) fn model_cases(
    options: &Options,
    config: &CalibrateConfig,
    summary: &mut Vec<CaseRows>,
) {
    let drift: &[&str] = &["drift:*:mm_per_s=0.0002"];
    let slip: &[&str] = &["slip:3:at_s=2400,mm=5"];
    for (name, effects) in [
        ("clean", &[][..]),
        ("drift", drift),
        ("drift-continuing", drift),
        ("slip", slip),
        ("slip-continuing", slip),
        ("drift-each", &DRIFT_EACH[..]),
        ("drift-each-continuing", &DRIFT_EACH[..]),
        ("drift-mixed-continuing", &DRIFT_MIXED[..]),
    ] {
        if !options.wanted("model", (name != "clean").then_some(name)) {
            continue;
        }
        let continuing = name.ends_with("-continuing");
        let mut rows = Vec::new();
        for seed in 1..=options.seeds {
            let run = model_run(seed, effects, continuing);
            options.write_run("model", name, seed, &run);
            let c = run_calibration(&run, config);
            rows.push(print_row("model", name, seed, &c));
        }
        summary.push(("model", name, rows));
    }
}

/// The independent simulator's cases, one row per seed; what the loop left
/// out and where sessions slipped go to `notes`.
pub(super) fn physics_cases(
    options: &Options,
    config: &CalibrateConfig,
    summary: &mut Vec<CaseRows>,
    notes: &mut Vec<String>,
) -> Vec<CleanPhysics> {
    let mut clean_physics = Vec::new();
    for effect in [
        None,
        Some("drift-all"),
        // The test session continuing the training's home: the drift goes
        // on into it.
        Some("drift-all-continuing"),
        // Every string creeping at its own rate (100-500 ppm/h), and the
        // same with the test session continuing the training's home.
        Some("drift-each"),
        Some("drift-each-continuing"),
        // The same at three times the rates (900 +- 600 ppm/h).
        Some("drift-each-fast"),
        Some("drift-each-fast-continuing"),
        Some("frame-flex"),
        Some("marker-offset"),
        Some("slip"),
        // The same slips, the test session continuing the training's home.
        Some("slip-continuing"),
        Some("heavy-string"),
        // Guide pulleys of 12 mm on every string, and of none (the clean
        // device's are 6-12 mm).
        Some("guides-12"),
        Some("point-guides"),
        // Streams (100 Hz) of the clean device, and with 6 ms of encoder
        // latency on two strings.
        Some("stream"),
        Some("stream-latency"),
    ] {
        if !options.wanted("independent", effect) {
            continue;
        }
        let name = effect.unwrap_or("clean");
        let continuing = effect.is_some_and(|e| e.ends_with("-continuing"));
        let sessions = if continuing {
            Sessions::LatticeContinuing
        } else if effect.is_some_and(|e| e.starts_with("stream")) {
            Sessions::Streams
        } else {
            Sessions::Lattice
        };
        let mut rows = Vec::new();
        for seed in 1..=options.seeds {
            let device = physics_device(seed, effect.map(|e| e.trim_end_matches("-continuing")));
            let (run, truths, test_truths) = physics_run(&device, seed, sessions);
            options.write_run("independent", name, seed, &run);
            let c = run_calibration(&run, config);
            let steps = slip_steps(&truths);
            if !steps.is_empty() {
                notes.push(format!(
                    "independent {name} seed {seed}: the lattice slipped (row, string, mm) {steps:?} of {} rows",
                    truths.len()
                ));
            }
            if let Some(slips) = test_session_slips(&test_truths, &c) {
                notes.push(format!("independent {name} seed {seed}: {slips}"));
            }
            if continuing {
                notes.push(format!(
                    "independent {name} seed {seed}: {}",
                    home_judged(&c)
                ));
            }
            rows.push(print_row("independent", name, seed, &c));
            if let Some(creep) = creep_against_truth(&device, &c) {
                notes.push(format!("independent {name} seed {seed}: {creep}"));
            }
            let n = not_added(&c);
            if !n.is_empty() {
                notes.push(format!("independent {name} seed {seed}: {n}"));
            }
            if effect.is_none() {
                clean_physics.push((device, run, truths, c));
            }
        }
        summary.push(("independent", name, rows));
    }
    clean_physics
}
