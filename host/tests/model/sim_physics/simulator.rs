//! The simulator itself: deterministic per seed, physically sane, its
//! effects selectable by name, bad input named, its session files.

use std::path::PathBuf;

use super::fixtures::quiet_config;
use spidar::data::dataset::Session;
use spidar::sim::physics::{
    rows_to_session, simulate_rows, simulate_session, PhysicsConfig, PhysicsDevice, PhysicsRow,
    EFFECT_NAMES,
};
use spidar::sim::{run_simulate, Physics, SessionKind, SessionPath, SimulateRequest};

fn tmp(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("spidar-physics-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn args(out: PathBuf, seed: u64, kind: SessionPath, name: &str) -> SimulateRequest {
    SimulateRequest {
        out,
        seed,
        config: None,
        preset: None,
        kind,
        points: None,
        effects: vec![],
        name: Some(name.into()),
        session_seed: None,
        physics: Physics::Independent,
    }
}

#[test]
fn the_same_seed_gives_the_same_files_and_another_seed_another_device() {
    let (a, b) = (tmp("det-a"), tmp("det-b"));
    for dir in [&a, &b] {
        run_simulate(&args(dir.clone(), 5, SessionPath::Random, "test")).unwrap();
    }
    for file in ["geometry.toml", "test.csv", "truth.toml"] {
        let x = std::fs::read(a.join(file)).unwrap();
        let y = std::fs::read(b.join(file)).unwrap();
        assert!(x == y, "{file} differs between two runs of seed 5");
    }
    let c = tmp("det-c");
    run_simulate(&args(c.clone(), 6, SessionPath::Random, "test")).unwrap();
    assert_ne!(
        std::fs::read(a.join("test.csv")).unwrap(),
        std::fs::read(c.join("test.csv")).unwrap()
    );
    // The geometry is the design: the same for every device.
    assert_eq!(
        std::fs::read(a.join("geometry.toml")).unwrap(),
        std::fs::read(c.join("geometry.toml")).unwrap()
    );
    for d in [a, b, c] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn counts_grow_with_the_string_paid_out_on_every_string() {
    let device = PhysicsDevice::new(&quiet_config(), 3).unwrap();
    let (session, truths) = simulate_session(&device, SessionKind::Lattice, 4).unwrap();
    assert_eq!(session.samples.len(), 2197);
    for i in 0..device.string_count() {
        let mut by_length: Vec<(f64, i32)> = truths
            .iter()
            .zip(&session.samples)
            .map(|(t, s)| (t.natural_mm[i], s.counts[i]))
            .collect();
        by_length.sort_by(|a, b| a.0.total_cmp(&b.0));
        for w in by_length.windows(2) {
            assert!(
                w[1].1 >= w[0].1,
                "string {i}: {} mm -> {} counts but {} mm -> {} counts",
                w[0].0,
                w[0].1,
                w[1].0,
                w[1].1
            );
        }
        // One count is well under a millimetre of string.
        let (lo, hi) = (by_length[0], by_length[by_length.len() - 1]);
        let mm_per_count = (hi.0 - lo.0) / f64::from(hi.1 - lo.1);
        assert!(
            mm_per_count > 0.005 && mm_per_count < 0.03,
            "{mm_per_count}"
        );
    }
}

#[test]
fn the_exit_point_moves_and_the_spool_winds_in_layers() {
    let device = PhysicsDevice::new(&quiet_config(), 3).unwrap();
    let (_, truths) = simulate_session(&device, SessionKind::Lattice, 4).unwrap();
    let mut strings_crossing_layers = 0;
    for i in 0..device.string_count() {
        // The exit point travels over the guide as the string turns.
        let exits: Vec<[f64; 3]> = truths.iter().map(|t| t.exit_mm[i]).collect();
        let spread = (0..3)
            .map(|k| {
                let (lo, hi) = exits.iter().fold((f64::MAX, f64::MIN), |(lo, hi), e| {
                    (lo.min(e[k]), hi.max(e[k]))
                });
                hi - lo
            })
            .fold(0.0, f64::max);
        let rho = device.strings[i].guide.radius_mm;
        assert!(
            spread > 0.3 * rho,
            "string {i}: exit spread {spread} mm, rho {rho} mm"
        );

        // The radius is a staircase: one layer rise at each layer change,
        // flat in between (away from the cross-over).
        let spool = device.spool(i);
        let p = spool.params();
        let rise = p.layer_packing * p.string_diameter_mm;
        let changes = spool.layer_changes_rad();
        assert!(
            changes.len() >= 3,
            "string {i}: {} layers",
            changes.len() + 1
        );
        for c in &changes {
            // Half a turn into a turn (past the cross-over), a turn or two
            // from the layer change.
            let tau = std::f64::consts::TAU;
            let before = (((c - 1.0) / tau).floor() - 1.0) * tau + 3.0;
            let after = ((c + 1.0) / tau).ceil() * tau + 3.0;
            let step = spool.radius_mm(after) - spool.radius_mm(before);
            assert!(
                (step - rise).abs() < 1e-9,
                "string {i} at {c} rad: {step} mm"
            );
            assert_eq!(spool.radius_mm(before), spool.radius_mm(before - 1.0));
        }
        // The lattice pays the string out across layer changes.
        let (lo, hi) = truths.iter().fold((f64::MAX, f64::MIN), |(lo, hi), t| {
            (lo.min(t.spool_rad[i]), hi.max(t.spool_rad[i]))
        });
        if changes.iter().any(|c| (lo..hi).contains(c)) {
            strings_crossing_layers += 1;
        }
    }
    assert_eq!(strings_crossing_layers, device.string_count());
}

#[test]
fn every_undeclared_effect_is_selectable_and_changes_the_counts() {
    let clean_device = PhysicsDevice::new(&quiet_config(), 7).unwrap();
    let kind = SessionKind::Random { points: 200 };
    let (clean, _) = simulate_session(&clean_device, kind, 8).unwrap();
    for name in EFFECT_NAMES {
        let mut c = quiet_config();
        c.effects = vec![name.to_string()];
        // A slip an hour would rarely fall in a 50 s session.
        if name == "slip" {
            c.effects = vec!["slip:per_h=400,mm=5".into()];
        }
        let device = PhysicsDevice::new(&c, 7).unwrap();
        let (s, _) = simulate_session(&device, kind, 8).unwrap();
        let changed = s
            .samples
            .iter()
            .zip(&clean.samples)
            .any(|(a, b)| a.counts != b.counts || a.tracker != b.tracker);
        assert!(changed, "{name} changed nothing");
    }
}

#[test]
fn bad_input_is_named() {
    let mut c = PhysicsConfig::default();
    c.as_built.guide_radius_mm = [12.0, 6.0];
    let e = PhysicsDevice::new(&c, 1).unwrap_err().to_string();
    assert!(e.contains("as_built.guide_radius_mm"), "{e}");

    let c = PhysicsConfig {
        effects: vec!["offset:3:mm=8".into()],
        ..PhysicsConfig::default()
    };
    let e = PhysicsDevice::new(&c, 1).unwrap_err().to_string();
    assert!(e.contains("unknown effect `offset`"), "{e}");

    let mut c = PhysicsConfig::default();
    c.abnormal_motor.string = 8;
    let e = PhysicsDevice::new(&c, 1).unwrap_err().to_string();
    assert!(e.contains("abnormal_motor.string"), "{e}");

    let dir = tmp("bad-config");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("physics.toml");
    std::fs::write(&file, "[as_built]\nspool_width = 3\n").unwrap();
    let e = PhysicsConfig::load(&file).unwrap_err().to_string();
    assert!(
        e.contains("physics.toml") && e.contains("spool_width"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(dir);

    // Rows of 3 to 8 strings make a session of that many; 2, or rows that
    // disagree, are refused by name.
    let row = |n: usize| PhysicsRow {
        t_s: 0.0,
        counts: vec![0; n],
        tracker: None,
        orientation: None,
        tension_n: vec![1.0; n],
    };
    assert_eq!(rows_to_session(vec![row(3)]).unwrap().strings, 3);
    let e = rows_to_session(vec![row(2)]).unwrap_err().to_string();
    assert!(e.contains("2 strings"), "{e}");
    let e = rows_to_session(vec![row(4), row(5)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("5 strings"), "{e}");
}

#[test]
fn rows_are_the_session() {
    let device = PhysicsDevice::new(&PhysicsConfig::default(), 2).unwrap();
    let kind = SessionKind::Random { points: 50 };
    let (rows, _) = simulate_rows(&device, kind, 3).unwrap();
    let (session, _) = simulate_session(&device, kind, 3).unwrap();
    assert_eq!(rows_to_session(rows).unwrap(), session);
}

#[test]
fn the_simulated_session_file_carries_the_orientation_the_model_simulator_has_none() {
    let dir = tmp("orientation");
    let report = run_simulate(&args(dir.clone(), 4, SessionPath::Random, "test")).unwrap();
    let text = std::fs::read_to_string(&report.session).unwrap();
    let header = text.lines().next().unwrap();
    assert!(
        header.contains(",ots_x,ots_y,ots_z,ots_qw,ots_qx,ots_qy,ots_qz,"),
        "{header}"
    );
    let session = Session::load(&report.session).unwrap();
    assert!(session.samples.iter().any(|s| s.tracker.is_none()));
    for (row, s) in session.samples.iter().enumerate() {
        // Seen: a position and an orientation; occluded: neither.
        assert_eq!(s.orientation.is_some(), s.tracker.is_some(), "row {row}");
        if let Some(q) = s.orientation {
            let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!((norm - 1.0).abs() < 1e-5, "row {row}: {q:?}, norm {norm}");
        }
    }

    let model_dir = tmp("orientation-model");
    let model = SimulateRequest {
        physics: Physics::Model,
        ..args(model_dir.clone(), 4, SessionPath::Random, "test")
    };
    let report = run_simulate(&model).unwrap();
    let text = std::fs::read_to_string(&report.session).unwrap();
    assert!(!text.lines().next().unwrap().contains("ots_q"), "{text}");
    let session = Session::load(&report.session).unwrap();
    assert!(session.samples.iter().all(|s| s.orientation.is_none()));
    for d in [dir, model_dir] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// `drift-each`: every string creeps at its own rate, the configured one
/// plus a draw within the spread, the same for the device whatever the
/// session; `drift-all` gives every string one rate.
#[test]
fn drift_each_gives_every_string_its_own_creep() {
    let device = |effect: &str| {
        let config = PhysicsConfig {
            effects: vec![effect.to_string()],
            ..PhysicsConfig::default()
        };
        PhysicsDevice::new(&config, 2).unwrap()
    };
    let ppm_per_h = |d: &PhysicsDevice| -> Vec<f64> {
        (0..d.string_count())
            .map(|i| d.string_creep_per_s(i) * 3.6e9)
            .collect()
    };
    let each = ppm_per_h(&device("drift-each:ppm_per_h=300,spread_ppm_per_h=200"));
    assert!(each.iter().all(|r| (100.0..=500.0).contains(r)), "{each:?}");
    let (lo, hi) = each.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &r| {
        (lo.min(r), hi.max(r))
    });
    assert!(hi - lo > 100.0, "{each:?}");
    assert_eq!(
        each,
        ppm_per_h(&device("drift-each:ppm_per_h=300,spread_ppm_per_h=200"))
    );
    let all = ppm_per_h(&device("drift-all"));
    assert!(all.iter().all(|r| (r - 300.0).abs() < 1e-9), "{all:?}");
}
