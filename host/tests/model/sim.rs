//! The simulator: paper-sized raw error, the lattice protocol, occlusions,
//! tensions, injected effects with exactly the model's definitions, and
//! byte-for-byte reproducibility.

use std::path::PathBuf;
use std::time::Instant;

use spidar::data::dataset::{Geometry, Session};
use spidar::data::stats::ErrorStats;
use spidar::sim::{
    legacy_raw_errors, run_simulate, simulate_session, simulate_session_with_truth, InjectedEffect,
    SampleTruth, SessionKind, SessionPath, SimConfig, SimError, SimulateRequest, SimulatedDevice,
    Truth,
};
use spidar_core::model::Effect;
use spidar_core::string_law::string_lengths_f64;
use spidar_core::STRINGS;

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spidar-sim-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn args(out: PathBuf, seed: u64, kind: SessionPath) -> SimulateRequest {
    SimulateRequest {
        out,
        seed,
        config: None,
        preset: None,
        kind,
        points: None,
        effects: vec![],
        name: None,
        session_seed: None,
        physics: Default::default(),
    }
}

/// A quiet device: no abnormal motor, so every string follows its law.
fn quiet_config(effects: &[&str]) -> SimConfig {
    let mut c = SimConfig::default();
    c.abnormal_motor.enabled = false;
    c.effects = effects.iter().map(|s| s.to_string()).collect();
    c
}

/// Half a count of string at the largest winding radius, plus float slack.
const QUANTIZATION_MM: f64 = 0.015;

#[test]
fn legacy_raw_error_is_paper_sized() {
    let device = SimulatedDevice::new(&SimConfig::default(), 1).unwrap();
    let lattice = simulate_session(&device, SessionKind::Lattice, 2).unwrap();
    let errors = legacy_raw_errors(&lattice, &device.nominal);
    let s = ErrorStats::of(&errors);
    println!("lattice raw error: {s:?}");
    assert!(errors.len() > 2000);
    assert!(s.mean_mm >= 150.0 && s.mean_mm < 400.0, "{s:?}");
    assert!(s.sd_mm > 30.0 && s.max_mm > 300.0, "{s:?}");

    let test = simulate_session(&device, SessionKind::Random { points: 500 }, 3).unwrap();
    let s = ErrorStats::of(&legacy_raw_errors(&test, &device.nominal));
    println!("random raw error: {s:?}");
    assert!(s.mean_mm >= 120.0, "{s:?}");
}

#[test]
fn lattice_is_2197_cells_plane_by_plane_from_the_front() {
    let device = SimulatedDevice::new(&SimConfig::default(), 4).unwrap();
    let (session, truth) = simulate_session_with_truth(&device, SessionKind::Lattice, 5).unwrap();
    assert_eq!(session.samples.len(), 2197);
    let n = 13u32;
    let cell = 1000.0 / f64::from(n);
    let centre = device.volume_centre_room();
    let mut seen = std::collections::HashSet::new();
    for (k, t) in truth.iter().enumerate() {
        let c = t.cell.unwrap();
        assert!(seen.insert(c), "cell {c:?} captured twice");
        // Plane by plane along y, from the front (-y).
        assert_eq!(c[1], k as u32 / (n * n), "row {k}");
        // The capture lies inside its cell, not at its centre.
        for axis in 0..3 {
            let lo = centre[axis] - 500.0 + f64::from(c[axis]) * cell;
            assert!(
                t.room_mm[axis] > lo && t.room_mm[axis] < lo + cell,
                "row {k} axis {axis}"
            );
        }
        if k > 0 {
            let p = truth[k - 1].cell.unwrap();
            let steps: u32 = (0..3).map(|a| p[a].abs_diff(c[a])).sum();
            assert_eq!(steps, 1, "consecutive cells share a face (row {k})");
        }
        // The tracker agrees with the cell along y (noise 0.2 mm).
        if let Some(o) = session.samples[k].tracker {
            let lo = centre[1] - 500.0 + f64::from(c[1]) * cell;
            assert!(o[1] > lo - 2.0 && o[1] < lo + cell + 2.0, "row {k}");
        }
    }
    let off_centre = truth
        .iter()
        .filter(|t| {
            let c = t.cell.unwrap();
            (0..3).any(|a| {
                let mid = centre[a] - 500.0 + (f64::from(c[a]) + 0.5) * cell;
                (t.room_mm[a] - mid).abs() > 5.0
            })
        })
        .count();
    assert!(
        off_centre > 2000,
        "captures are where the marker entered, not at centres"
    );
    // About 80 minutes, time increasing.
    let last = session.samples.last().unwrap().t_s;
    assert!((4700.0..4900.0).contains(&last), "{last}");
    assert!(session.samples.windows(2).all(|w| w[0].t_s <= w[1].t_s));
}

#[test]
fn occluded_rows_have_empty_tracker_fields_and_tensions_are_written() {
    let out = tmp("occlusion");
    run_simulate(&args(out.clone(), 9, SessionPath::Lattice)).unwrap();
    let text = std::fs::read_to_string(out.join("lattice.csv")).unwrap();
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    for name in ["ots_x", "dev_x", "tension0", "tension7"] {
        assert!(header.contains(&name), "{name} in {header:?}");
    }
    let ix: Vec<usize> = ["ots_x", "ots_y", "ots_z"]
        .iter()
        .map(|n| header.iter().position(|h| h == n).unwrap())
        .collect();
    let mut occluded = 0;
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let empty = ix.iter().filter(|&&i| f[i].is_empty()).count();
        assert!(empty == 0 || empty == 3, "{line}");
        occluded += usize::from(empty == 3);
    }
    assert!(occluded > 10 && occluded < 300, "{occluded} occluded rows");

    let session = Session::load(out.join("lattice.csv")).unwrap();
    assert_eq!(
        session
            .samples
            .iter()
            .filter(|s| s.tracker.is_none())
            .count(),
        occluded
    );
    // Runs of occlusion, not only isolated rows.
    let runs = session
        .samples
        .windows(2)
        .filter(|w| w[0].tracker.is_none() && w[1].tracker.is_none())
        .count();
    assert!(runs > 0);
    let c = SimConfig::default().tension;
    let mut varied = 0;
    for s in &session.samples {
        let t = s.tension_n.expect("tensions in every row");
        assert!(s.legacy.is_some());
        for x in t {
            assert!(x >= c.pretension_n && x <= c.pretension_n + c.jitter_n + c.active_max_n);
            varied += usize::from(x > c.pretension_n + c.jitter_n);
        }
    }
    assert!(varied > 2197, "a varying tension component is present");
}

#[test]
fn outputs_nominal_geometry_and_a_loadable_truth() {
    let out = tmp("outputs");
    let mut a = args(out.clone(), 11, SessionPath::Random);
    a.points = Some(120);
    a.effects = vec!["offset:3:mm=10".into(), "anchor:2:dz=-5".into()];
    let report = run_simulate(&a).unwrap();
    assert_eq!(report.rows, 120);
    let g = Geometry::load(out.join("geometry.toml")).unwrap();
    // The design, and the pretension its initialization declares.
    assert_eq!(
        g,
        Geometry {
            home_tension_n: Some(1.0),
            anchor_sd_mm: None,
            home_sd_mm: None,
            ..SimConfig::default().nominal.geometry()
        }
    );
    assert_eq!(g.anchors_mm[4], [-1100.0, -1100.0, 1100.0]);
    let truth = Truth::load(out.join("truth.toml")).unwrap();
    let config = SimConfig {
        effects: a.effects.clone(),
        ..SimConfig::default()
    };
    let device = SimulatedDevice::new(&config, 11).unwrap();
    assert_eq!(truth, Truth::of(&device));
    assert_ne!(
        truth.frame.anchors, g.anchors_mm,
        "the truth is the as-built device"
    );
    assert_eq!(truth.effects.len(), 1);
    assert!(Session::load(out.join("random.csv")).unwrap().samples.len() == 120);
}

#[test]
fn seeds_reproduce_files_byte_for_byte() {
    let read = |dir: &PathBuf| {
        ["geometry.toml", "lattice.csv", "truth.toml"].map(|f| std::fs::read(dir.join(f)).unwrap())
    };
    let (a, b, c) = (tmp("seed-a"), tmp("seed-b"), tmp("seed-c"));
    run_simulate(&args(a.clone(), 5, SessionPath::Lattice)).unwrap();
    run_simulate(&args(b.clone(), 5, SessionPath::Lattice)).unwrap();
    run_simulate(&args(c.clone(), 6, SessionPath::Lattice)).unwrap();
    let (fa, fb, fc) = (read(&a), read(&b), read(&c));
    assert_eq!(fa, fb);
    assert_eq!(
        fa[0], fc[0],
        "the nominal geometry does not depend on the seed"
    );
    assert_ne!(fa[1], fc[1]);
    assert_ne!(fa[2], fc[2]);
}

#[test]
fn train_and_test_sessions_of_one_device_are_fast() {
    let start = Instant::now();
    let device = SimulatedDevice::new(&SimConfig::default(), 21).unwrap();
    let train = simulate_session(&device, SessionKind::Lattice, 1).unwrap();
    let test = simulate_session(&device, SessionKind::Random { points: 500 }, 2).unwrap();
    let elapsed = start.elapsed();
    println!("lattice + 500-point test session: {elapsed:?}");
    assert_eq!((train.samples.len(), test.samples.len()), (2197, 500));
    assert!(elapsed.as_secs_f64() < 5.0, "{elapsed:?}");
    assert_ne!(train.samples[0].counts, test.samples[0].counts);
}

/// True length minus the base law's length from the counts, per string.
fn residuals(device: &SimulatedDevice, truth: &[SampleTruth], string: usize) -> Vec<f64> {
    truth
        .iter()
        .map(|t| t.lengths_mm[string] - device.base_length_mm(string, t.inputs.counts[string]))
        .collect()
}

fn quiet_session(effects: &[&str]) -> (SimulatedDevice, Vec<SampleTruth>) {
    let device = SimulatedDevice::new(&quiet_config(effects), 31).unwrap();
    let (_, truth) =
        simulate_session_with_truth(&device, SessionKind::Random { points: 400 }, 32).unwrap();
    (device, truth)
}

#[test]
fn without_effects_the_true_law_explains_every_string() {
    let (device, truth) = quiet_session(&[]);
    for i in 0..STRINGS {
        for r in residuals(&device, &truth, i) {
            assert!(r.abs() <= QUANTIZATION_MM, "string {i}: {r}");
        }
    }
}

/// Each model-family effect on string 3 shifts string 3's true length minus
/// its base-law length by the term's value, and leaves the others alone.
#[test]
fn each_injected_effect_changes_its_string_by_the_expected_amount() {
    type Expect = fn(&SimulatedDevice, &SampleTruth) -> f64;
    let cases: [(&str, Expect); 9] = [
        ("offset:3:mm=10", |_, _| 10.0),
        ("scale:3:relative=0.01", |d, t| {
            0.01 * d.payout_mm(3, d.theta(t.inputs.counts[3]))
        }),
        ("winding:3:power=3,mm_per_rad_pow=0.0001", |d, t| {
            1e-4 * d.theta(t.inputs.counts[3]).powi(3)
        }),
        ("eccentricity:3:sin_mm=0.5,cos_mm=0.3", |d, t| {
            let th = d.theta(t.inputs.counts[3]);
            0.5 * th.sin() + 0.3 * (th.cos() - 1.0)
        }),
        ("elasticity:3:per_newton=0.001", |d, t| {
            let tension = f64::from(t.inputs.tension_mn[3]) / 1000.0;
            0.001 * tension * (d.home_length_mm(3) + d.payout_mm(3, d.theta(t.inputs.counts[3])))
        }),
        ("backlash:3:half_width_mm=0.8", |_, t| {
            0.8 * f64::from(t.inputs.direction[3])
        }),
        ("drift:3:mm_per_s=0.01", |_, t| {
            0.01 * f64::from(t.inputs.time_ms) / 1000.0
        }),
        ("slip:3:at_s=50,mm=5", |_, t| {
            if t.inputs.time_ms >= 50_000 {
                5.0
            } else {
                0.0
            }
        }),
        ("speed:3:latency_s=0.05", |_, t| {
            0.05 * t.string_speed_mm_s[3]
        }),
    ];
    let (_, plain) = quiet_session(&[]);
    for (spec, expect) in cases {
        let (device, truth) = quiet_session(&[spec]);
        let mut largest: f64 = 0.0;
        for (k, t) in truth.iter().enumerate() {
            assert_eq!(
                t.lengths_mm, plain[k].lengths_mm,
                "{spec}: the path does not depend on effects"
            );
            let r = t.lengths_mm[3] - device.base_length_mm(3, t.inputs.counts[3]);
            let e = expect(&device, t);
            largest = largest.max(e.abs());
            assert!(
                (r - e).abs() <= 0.03,
                "{spec}, row {k}: residual {r} vs term {e}"
            );
            for i in (0..STRINGS).filter(|&i| i != 3) {
                assert_eq!(
                    t.inputs.counts[i], plain[k].inputs.counts[i],
                    "{spec}: string {i} untouched"
                );
            }
        }
        assert!(
            largest > 0.25,
            "{spec}: the effect is visible ({largest} mm)"
        );
        // The core's own f64 string law with the true model gives the true
        // lengths: what identification fits is exactly what was injected.
        if !spec.starts_with("speed") {
            for t in &truth {
                let model =
                    string_lengths_f64(&device.frame, &device.laws, &device.effects, &t.inputs);
                for (i, (m, l)) in model.iter().zip(&t.lengths_mm).enumerate() {
                    assert!((m - l).abs() <= 0.03, "{spec}, string {i}");
                }
            }
        }
    }
}

#[test]
fn wildcard_and_geometry_effects() {
    let device = SimulatedDevice::new(&quiet_config(&["backlash:*:half_width_mm=0.4"]), 1).unwrap();
    assert_eq!(device.effects.len(), 8);
    assert!(device
        .effects
        .iter()
        .all(|t| t.effect == Effect::Backlash { half_width_mm: 0.4 }));

    let plain = SimulatedDevice::new(&quiet_config(&[]), 1).unwrap();
    let moved = SimulatedDevice::new(
        &quiet_config(&["anchor:2:dx=10,dz=-4", "tracker_scale:relative=0.002"]),
        1,
    )
    .unwrap();
    let (a, b) = (plain.frame.anchors[2], moved.frame.anchors[2]);
    assert!((b[0] - a[0] - 10.0).abs() < 1e-9 && b[1] == a[1] && (b[2] - a[2] + 4.0).abs() < 1e-9);
    assert_eq!(plain.frame.anchors[1], moved.frame.anchors[1]);
    assert!((moved.frame.room_scale - 1.002 * plain.frame.room_scale).abs() < 1e-12);
    assert!(
        matches!(moved.injected[1], InjectedEffect::TrackerScale { relative } if relative == 0.002)
    );

    // The anchor shift is seen in the string lengths of string 2 only.
    let (_, tp) =
        simulate_session_with_truth(&plain, SessionKind::Random { points: 50 }, 4).unwrap();
    let (_, tm) =
        simulate_session_with_truth(&moved, SessionKind::Random { points: 50 }, 4).unwrap();
    assert!(tp
        .iter()
        .zip(&tm)
        .any(|(p, m)| (p.lengths_mm[2] - m.lengths_mm[2]).abs() > 1.0));
}

#[test]
fn direction_and_speed_agree_with_the_path() {
    let (_, truth) = quiet_session(&[]);
    let mut agree = 0;
    let mut compared = 0;
    let mut same_leg = 0;
    for w in truth.windows(2) {
        for i in 0..STRINGS {
            let dc = w[1].inputs.counts[i] - w[0].inputs.counts[i];
            if dc.abs() > 200 {
                compared += 1;
                agree += usize::from(dc.signum() as i8 == w[1].inputs.direction[i]);
            }
            // On one straight leg (same velocity), the string speed at the
            // capture times the interval is the length change, up to the
            // curvature of |p - anchor| along a line (< 3 mm here).
            if w[0].velocity_device_mm_s == w[1].velocity_device_mm_s {
                same_leg += 1;
                let dt = f64::from(w[1].inputs.time_ms - w[0].inputs.time_ms) / 1000.0;
                let predicted = w[1].string_speed_mm_s[i] * dt;
                let actual = w[1].lengths_mm[i] - w[0].lengths_mm[i];
                assert!((predicted - actual).abs() < 3.0, "{predicted} vs {actual}");
            }
        }
    }
    assert!(same_leg > 1000, "{same_leg}");
    assert!(
        compared > 1000 && agree as f64 > 0.95 * compared as f64,
        "{agree}/{compared}"
    );
}

#[test]
fn abnormal_motor_gives_large_errors_in_one_corner() {
    let device = SimulatedDevice::new(&SimConfig::default(), 8).unwrap();
    let (_, truth) = simulate_session_with_truth(&device, SessionKind::Lattice, 9).unwrap();
    let hit: Vec<&SampleTruth> = truth.iter().filter(|t| t.abnormal_mm != 0.0).collect();
    let share = hit.len() as f64 / truth.len() as f64;
    assert!((0.06..0.2).contains(&share), "{share}");
    assert!(hit.iter().all(|t| t.abnormal_mm <= -100.0));
    // In the upper-left-front corner region (string 4's anchor at -x, -y, +z).
    assert!(hit.iter().all(|t| t.lengths_mm[4] < 1600.0));
    let mean: Vec<f64> = (0..3)
        .map(|a| hit.iter().map(|t| t.device_mm[a]).sum::<f64>() / hit.len() as f64)
        .collect();
    assert!(
        mean[0] < -200.0 && mean[1] < -200.0 && mean[2] > 200.0,
        "{mean:?}"
    );
    assert!(truth
        .iter()
        .filter(|t| t.lengths_mm[4] < 1600.0)
        .all(|t| t.abnormal_mm < 0.0));
    let r = residuals(&device, &truth, 4);
    assert!(r
        .iter()
        .zip(&truth)
        .all(|(r, t)| (r - t.abnormal_mm).abs() <= QUANTIZATION_MM));
}

/// A tracker with a tail locates its share of the captures poorly, by a
/// further normal of the tail's sd; every other capture's noise is the
/// same draw as without the tail, and a tail of no captures is no tail.
#[test]
fn a_tracker_with_a_tail_locates_its_share_of_the_captures_poorly() {
    let session = |share: f64, sigma: f64| {
        let mut config = SimConfig::default();
        config.tracker.tail_share = share;
        config.tracker.tail_sigma_mm = sigma;
        let device = SimulatedDevice::new(&config, 12).unwrap();
        simulate_session_with_truth(&device, SessionKind::Random { points: 1000 }, 14).unwrap()
    };
    let offsets = |(s, truth): &(Session, Vec<spidar::sim::SampleTruth>)| -> Vec<[f64; 3]> {
        s.samples
            .iter()
            .zip(truth)
            .filter_map(|(s, t)| {
                s.tracker
                    .map(|o| core::array::from_fn(|k| o[k] - t.room_mm[k]))
            })
            .collect()
    };
    let plain = offsets(&session(0.0, 0.0));
    assert_eq!(offsets(&session(0.0, 3.0)), plain);
    let tailed = offsets(&session(0.2, 3.0));
    assert_eq!(tailed.len(), plain.len());
    let moved: Vec<f64> = tailed
        .iter()
        .zip(&plain)
        .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt())
        .collect();
    // Rows without the tail: the very same noise (to the tracker's
    // micrometre); rows with it: 3 mm sd per axis more.
    let poor: Vec<f64> = moved.iter().copied().filter(|&d| d > 0.002).collect();
    let share = poor.len() as f64 / moved.len() as f64;
    assert!((0.16..0.24).contains(&share), "{share}");
    let sd = (poor.iter().map(|d| d * d).sum::<f64>() / (3.0 * poor.len() as f64)).sqrt();
    assert!((2.6..3.4).contains(&sd), "{sd}");

    let dir = tmp("tail");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("sim.toml");
    std::fs::write(&path, "[tracker]\ntail_share = 1.5\ntail_sigma_mm = 3.0\n").unwrap();
    let msg = SimConfig::load(&path).unwrap_err().to_string();
    assert!(msg.contains("tracker.tail_share"), "{msg}");
    std::fs::write(&path, "[tracker]\ntail_share = 0.1\ntail_sigma_mm = -1.0\n").unwrap();
    let msg = SimConfig::load(&path).unwrap_err().to_string();
    assert!(msg.contains("tracker.tail_sigma_mm"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn tracker_noise_is_as_configured() {
    let device = SimulatedDevice::new(&SimConfig::default(), 12).unwrap();
    let (session, truth) = simulate_session_with_truth(&device, SessionKind::Lattice, 13).unwrap();
    let d: Vec<f64> = session
        .samples
        .iter()
        .zip(&truth)
        .filter_map(|(s, t)| s.tracker.map(|o| o[0] - t.room_mm[0]))
        .collect();
    let sd = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
    assert!((0.17..0.23).contains(&sd), "{sd}");
}

#[test]
fn configuration_and_effect_errors_name_what_is_wrong() {
    let dir = tmp("config");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("sim.toml");
    std::fs::write(&path, "[tracker]\nnoise_sigma = 0.3\n").unwrap();
    let msg = SimConfig::load(&path).unwrap_err().to_string();
    assert!(
        msg.contains("sim.toml") && msg.contains("noise_sigma"),
        "{msg}"
    );

    std::fs::write(&path, "[tracker]\nnoise_sigma_mm = -1.0\n").unwrap();
    let msg = SimConfig::load(&path).unwrap_err().to_string();
    assert!(msg.contains("tracker.noise_sigma_mm"), "{msg}");

    std::fs::write(&path, "[lattice]\ncells_per_axis = 5\nduration_s = 100.0\n").unwrap();
    let c = SimConfig::load(&path).unwrap();
    let device = SimulatedDevice::new(&c, 1).unwrap();
    assert_eq!(
        simulate_session(&device, SessionKind::Lattice, 1)
            .unwrap()
            .samples
            .len(),
        125
    );

    for (spec, needle) in [
        ("offset:3", "KIND:STRING"),
        ("offset:8:mm=1", "`8`"),
        ("offset:3:mm=abc", "`abc`"),
        ("offset:3:mm=1,foo=2", "`foo`"),
        ("slip:3:mm=1", "`at_s`"),
        ("twist:3:mm=1", "`twist`"),
        ("winding:1:power=2.5,mm_per_rad_pow=1", "power"),
    ] {
        let c = SimConfig {
            effects: vec![spec.to_string()],
            ..SimConfig::default()
        };
        let err = SimulatedDevice::new(&c, 1).unwrap_err();
        assert!(matches!(err, SimError::EffectSpec { .. }), "{spec}: {err}");
        let msg = err.to_string();
        assert!(msg.contains(spec) && msg.contains(needle), "{spec}: {msg}");
    }

    let mut a = args(dir.join("out"), 1, SessionPath::Lattice);
    a.points = Some(10);
    assert!(run_simulate(&a)
        .unwrap_err()
        .to_string()
        .contains("--points"));
}
