//! A tracker's glitches in the lattice, set aside.

use spidar::sim::physics::{simulate_session, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;

/// A tracker's glitches in the lattice (a reflection thrown 60 to 200 mm,
/// a lost marker written as `0, 0, 0`): the loop sets exactly those rows
/// aside, and judges and fits as on the lattice with those rows occluded. (Left
/// in, 2 % of them made the held-out mean the loop judged by 5.3 mm and it
/// added two effects fewer; 10 % at `0, 0, 0` ended at 0.789 mm held out
/// against 0.343.)
#[test]
fn a_tracker_s_glitches_are_set_aside_and_the_loop_runs_as_without_them() {
    use spidar::data::observe::observations;
    use spidar::model::diagnose::{close_loop, LoopConfig, LoopResult};
    use spidar::model::identify::Start;
    let device = PhysicsDevice::new(&PhysicsConfig::default(), 2).unwrap();
    let (lattice, _) = simulate_session(&device, SessionKind::Lattice, 3).unwrap();
    let (test, _) = simulate_session(&device, SessionKind::Random { points: 500 }, 4).unwrap();
    let test = observations(&test.samples);
    let nominal = device.nominal.nominal_frame();
    let run = |train: &[spidar::data::observe::Observation]| {
        close_loop(
            train,
            Some(&test),
            &nominal,
            &Start::from_geometry(&device.nominal),
            &LoopConfig {
                home_tension_n: device.nominal.home_tension_n,
                ..LoopConfig::default()
            },
        )
        .unwrap()
    };
    let test_after = |r: &LoopResult| {
        r.stages
            .last()
            .and_then(|s| s.test)
            .or(r.base_test)
            .unwrap()
            .mean_mm
    };
    let clean = observations(&lattice.samples);
    let clean_result = run(&clean);
    assert!(clean_result.tracker_outliers.rows.is_empty());
    // Every 25th tracked row thrown 60 to 200 mm (directions turning), every
    // 40th other one at the tracker's origin.
    let mut glitched = clean.clone();
    let mut thrown = Vec::new();
    let tracked: Vec<usize> = (0..clean.len())
        .filter(|&k| clean[k].tracker.is_some())
        .collect();
    for (n, &k) in tracked.iter().enumerate() {
        let t = glitched[k].tracker.as_mut().unwrap();
        if n % 25 == 7 {
            let a = n as f64 * 0.7;
            let size = 60.0 + (n % 8) as f64 * 20.0;
            let d = [
                a.cos() * 0.6,
                a.sin() * 0.6,
                0.8 * if n % 2 == 0 { 1.0 } else { -1.0 },
            ];
            for i in 0..3 {
                t[i] += size * d[i];
            }
            thrown.push(k);
        } else if n % 40 == 11 {
            *t = [0.0; 3];
            thrown.push(k);
        }
    }
    thrown.sort_unstable();
    let result = run(&glitched);
    assert_eq!(result.tracker_outliers.rows, thrown);
    assert_eq!(
        result.tracker_outliers.lines,
        thrown.iter().map(|&k| clean[k].row + 2).collect::<Vec<_>>()
    );
    assert!(result
        .tracker_outliers
        .errors_mm
        .iter()
        .all(|&e| e > result.tracker_outliers.threshold_mm));
    // The loop then runs as on the lattice with those rows occluded.
    let mut occluded = clean.clone();
    for &k in &thrown {
        occluded[k].tracker = None;
        occluded[k].tracker_rotation = None;
    }
    let occluded_result = run(&occluded);
    assert!(occluded_result.tracker_outliers.rows.is_empty());
    let names = |r: &LoopResult| r.stages.iter().map(|s| s.name.clone()).collect::<Vec<_>>();
    assert_eq!(names(&result), names(&occluded_result));
    assert_eq!(
        result.identification.effects,
        occluded_result.identification.effects
    );
    assert_eq!(test_after(&result), test_after(&occluded_result));
    // 6.5 % fewer rows: within 15 % of the whole clean lattice (0.389
    // against 0.346 mm: the marker offset is not added on fewer rows).
    let (a, b) = (test_after(&result), test_after(&clean_result));
    assert!(a < 1.15 * b, "with glitches {a} mm, clean {b} mm");
}
