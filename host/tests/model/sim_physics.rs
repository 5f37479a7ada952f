//! The independent simulator (`sim::physics`): deterministic per seed,
//! physically sane (counts follow the string, the exit point moves, the
//! spool winds in layers), its effects selectable by name, bad input named,
//! and what today's calibration pipeline reaches on it.

use std::path::PathBuf;

use super::slips_of;
use spidar::data::dataset::Session;
use spidar::procedures::calibrate::CalibrateConfig;
use spidar::sim::physics::{
    rows_to_session, simulate_rows, simulate_session, PhysicsConfig, PhysicsDevice, PhysicsRow,
    EFFECT_NAMES,
};
use spidar::sim::{run_simulate, Physics, SessionKind, SessionPath, SimulateRequest};

fn quiet_config() -> PhysicsConfig {
    let mut c = PhysicsConfig::default();
    c.abnormal_motor.enabled = false;
    c
}

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

/// `calibrate` (quick, quiet) of an independent device's two sessions.
fn calibrate_quick(
    device: &PhysicsDevice,
    train: &spidar::data::dataset::Session,
    test: &spidar::data::dataset::Session,
) -> spidar::procedures::calibrate::Calibrated {
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    crate::calibrate_in_memory(&device.nominal, train, test, &cfg)
}

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

/// The diagnosis loop on a clean independent device (issue 10, point 6).
fn clean_loop(seed: u64) -> spidar::model::diagnose::LoopResult {
    loop_on(seed, &[])
}

/// The diagnosis loop on an independent device with undeclared `effects`,
/// its lattice (session seed + 1) for training, 500 random points (+ 2) for
/// the test.
fn loop_on(seed: u64, effects: &[&str]) -> spidar::model::diagnose::LoopResult {
    loop_with(
        seed,
        effects,
        &spidar::model::diagnose::LoopConfig::default(),
    )
    .0
}

/// [`loop_on`] with `loop_config`, and the training session and the nominal
/// frame it ran on.
pub(crate) fn loop_with(
    seed: u64,
    effects: &[&str],
    loop_config: &spidar::model::diagnose::LoopConfig,
) -> (
    spidar::model::diagnose::LoopResult,
    Vec<spidar::data::observe::Observation>,
    spidar_core::model::Frame<f64>,
) {
    let config = PhysicsConfig {
        effects: effects.iter().map(|e| e.to_string()).collect(),
        ..PhysicsConfig::default()
    };
    loop_of_device(seed, &config, loop_config)
}

/// [`loop_with`] on the device `config` makes.
pub(crate) fn loop_of_device(
    seed: u64,
    config: &PhysicsConfig,
    loop_config: &spidar::model::diagnose::LoopConfig,
) -> (
    spidar::model::diagnose::LoopResult,
    Vec<spidar::data::observe::Observation>,
    spidar_core::model::Frame<f64>,
) {
    use spidar::data::observe::observations;
    use spidar::model::diagnose::close_loop;
    use spidar::model::identify::Start;
    let device = PhysicsDevice::new(config, seed).unwrap();
    let (train, _) = simulate_session(&device, SessionKind::Lattice, seed + 1).unwrap();
    let (test, _) =
        simulate_session(&device, SessionKind::Random { points: 500 }, seed + 2).unwrap();
    let train = observations(&train.samples);
    let nominal = device.nominal.nominal_frame();
    let result = close_loop(
        &train,
        Some(&observations(&test.samples)),
        &nominal,
        &Start::from_geometry(&device.nominal),
        // What the device's geometry declares (the home tension), as
        // `calibrate` does.
        &spidar::model::diagnose::LoopConfig {
            home_tension_n: device.nominal.home_tension_n,
            ..*loop_config
        },
    )
    .unwrap();
    (result, train, nominal)
}

/// The layer tables' own check fits each fold's tables on the fold's rows;
/// the changes after them are validated with the tables held. The first of
/// them is judged against the tables' model validated that same way, not
/// against the tables' check (0.670 mm there, 0.567 held, on this device:
/// an offset on string 4 was taken on the 15 % between the two).
#[test]
fn the_change_after_the_layer_tables_is_judged_against_them_validated_as_it_is() {
    use spidar::model::diagnose::LoopConfig;
    use spidar::model::validate::{validate, FoldScope};
    let (full, train, nominal) = loop_with(1, &[], &LoopConfig::default());
    let (tables, _, _) = loop_with(
        1,
        &[],
        &LoopConfig {
            max_effects: 2,
            ..LoopConfig::default()
        },
    );
    assert_eq!(tables.stages.len(), 2);
    assert_eq!(
        tables.stages[1].name,
        "layers strings [0, 1, 2, 3, 4, 5, 6, 7]"
    );
    let held = validate(
        &train,
        &nominal,
        &tables.identification,
        &tables.structure,
        FoldScope::Judged,
    )
    .unwrap();
    let next = full.findings.iter().find(|f| {
        f.family != spidar::model::diagnose::Family::Layers
            && f.family != spidar::model::diagnose::Family::Winding
            && f.validation.is_some()
    });
    let check = next.unwrap().validation.as_ref().unwrap();
    assert_eq!(check.before.held.mean_mm, held.held.mean_mm);
    let own = tables.stages[1].finding.validation.as_ref().unwrap();
    assert!(
        held.held.mean_mm < own.after.held.mean_mm,
        "held {} vs the tables' check {}",
        held.held.mean_mm,
        own.after.held.mean_mm
    );
    assert!(tables.stages[1]
        .finding
        .description
        .contains(&format!("judged against {:.3} mm", held.held.mean_mm)));
}

/// A clean independent device: its spools differ in width and are layered
/// (declared physics), so the loop frees each spool's thinning rate and
/// adds layer tables first, each checked on blocked folds; whatever it adds
/// after them lowered the blocked-fold error by the loop's minimum gain, and
/// every candidate it tested and refused is reported `added: false` with
/// the check that refused it.
#[test]
fn a_clean_independent_device_gets_spool_rates_and_layer_tables_first_and_each_decision_says_why() {
    use spidar::model::diagnose::{Family, LoopConfig};
    use spidar::model::validate::Folds;
    let r = clean_loop(1);
    assert_eq!(
        r.stages[0].name,
        "spool rates strings [0, 1, 2, 3, 4, 5, 6, 7]"
    );
    let rates = &r.stages[0].finding;
    assert_eq!(rates.family, Family::Winding);
    assert!(rates.validation.as_ref().unwrap().accepted);
    assert!(r
        .identification
        .winding
        .kappa_each_mm
        .iter()
        .any(|k| k.abs() > 1e-4));
    assert_eq!(r.stages[1].name, "layers strings [0, 1, 2, 3, 4, 5, 6, 7]");
    let layers = &r.stages[1].finding;
    assert_eq!(layers.family, Family::Layers);
    let check = layers.validation.as_ref().unwrap();
    assert!(
        check.accepted && check.reason.starts_with("added"),
        "{}",
        check.reason
    );
    assert_eq!(check.after.folds, Folds::Blocked);
    assert!(check.after.held.mean_mm < 0.8 * check.before.held.mean_mm);
    let min_gain = LoopConfig::default().min_relative_gain;
    for stage in &r.stages[2..] {
        let gain = 1.0 - stage.validation_after_mm / stage.validation_before_mm;
        assert!(gain >= min_gain, "{}: {gain}", stage.name);
        assert!(stage.finding.added && stage.finding.family != Family::Layers);
    }
    // Every string got a spacing that lowered its held-out residual, and
    // the final model's laws carry the tables.
    assert_eq!(r.layers.len(), 8);
    for (i, c) in r.layers.iter().enumerate() {
        assert!(c.step_counts.is_some(), "string {i}: {c:?}");
        assert!(c.held_rms_with_mm < c.held_rms_without_mm, "{c:?}");
        assert!(!r.identification.laws[i].layers.is_empty());
        assert!(c.peak_to_peak_mm > 1.0 && c.peak_to_peak_mm < 8.0, "{c:?}");
    }
    let tested: Vec<_> = r
        .findings
        .iter()
        .filter(|f| f.family != Family::Layers && f.validation.is_some() && !f.added)
        .collect();
    assert!(!tested.is_empty(), "findings: {:#?}", r.findings);
    for f in &tested {
        let check = f.validation.as_ref().unwrap();
        assert!(!f.added && !check.accepted, "{f:#?}");
        assert!(check.reason.starts_with("not added: "), "{}", check.reason);
        assert_eq!(check.after.folds, Folds::Blocked);
        // The blocked folds hold out every row once in time and the outer
        // shell once more; the interleaved folds are fitted only for a
        // step in time.
        assert!(check.before.held.n > r.base_train.n, "{check:#?}");
        assert_eq!(
            check.after.interleaved.is_some(),
            f.family == Family::Slip,
            "{f:#?}"
        );
    }
    // In the JSON report: `validation` with its reason.
    let json = serde_json::to_value(tested[0]).unwrap();
    assert_eq!(json["added"], false);
    assert!(json["validation"]["reason"]
        .as_str()
        .unwrap()
        .contains("not added"));
}

/// A term of the whole frame or the tracked body below the three strongest
/// proposals is tried when they are refused: on clean independent seed 6
/// the marker offset (the independent device's marker sits 8..15 mm off
/// the strings' meeting point) was left under per-string proposals the
/// loop refused (test 0.391 mm); tried, it lowers the blocked folds' mean
/// by 30 % and the test error to 0.370.
#[test]
fn a_frame_wide_term_below_the_three_strongest_is_tried() {
    use spidar::model::diagnose::Family;
    let r = clean_loop(6);
    let stage = r
        .stages
        .iter()
        .find(|s| s.finding.family == Family::Marker)
        .unwrap_or_else(|| panic!("stages: {:?}", names(&r)));
    assert!(stage.finding.added);
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.38, "{test:?}");
}

/// The abnormal motor's string off its groove while the walk crosses its
/// region jumps and falls back: no slip. On clean independent seed 11 the
/// jump of string 4 at 1759 s (-1.9 mm over 15 rows, -0.2 mm beyond them)
/// had been added as a slip, raising the test error from 0.351 to 0.366 mm.
#[test]
fn an_error_that_comes_and_goes_is_not_a_slip() {
    use spidar::model::diagnose::Family;
    let r = clean_loop(11);
    assert!(
        r.findings
            .iter()
            .all(|f| !(f.family == Family::Slip && f.added)),
        "stages: {:?}",
        names(&r)
    );
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.36, "{test:?}");
}

/// A string that slipped 419 s into a 4800 s lattice (independent device of
/// seed 2: one slip, string 6, 4.6 mm, a few rows into the lattice's second
/// plane) is a slip, not an offset: 91 % of its rows read the slipped
/// length, and the blocked folds alone could not tell a constant from a
/// step there (the fold that fits the later half never sees the string
/// before the slip), so a step in time is judged on the interleaved folds
/// and the blocked folds whose fit rows straddle it. The test session (a
/// new session from home, no slip) then follows the string as it was
/// before the slip: with an offset it was off by the slip's 4.6 mm (2.05
/// mm test mean before this rule, 0.72 after).
#[test]
fn a_slip_early_in_a_session_is_added_as_a_slip_not_an_offset() {
    use spidar::model::diagnose::Family;
    let r = loop_on(2, &["slip"]);
    let slip = r
        .stages
        .iter()
        .find(|s| s.name == "slip string 6")
        .unwrap_or_else(|| panic!("stages: {:?}", names(&r)));
    assert_eq!(slip.finding.family, Family::Slip);
    let reason = &slip.finding.validation.as_ref().unwrap().reason;
    assert!(
        reason.contains("interleaved folds (a step in time)")
            && reason.contains("without the earlier half"),
        "{reason}"
    );
    assert!(
        !r.stages.iter().any(|s| s.name == "offset string 6"),
        "{:?}",
        names(&r)
    );
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 1.0, "{test:?}");
}

/// Two early slips (independent seed 3: string 3 at row 39 of 2197, -4.19
/// mm; string 6 at row 230, +4.66 mm): both found and sized. The rows
/// before them are few and in one corner of the lattice; the layer tables,
/// functions of the counts, were fitted on residuals with the steps in them
/// and took part of them, so the slips came out at 2.26 and 3.56 mm (the
/// test session, which starts before them, at 1.03 mm). A slip is now
/// fitted together with the tables (`layers::fit_table_with_slips`) and
/// judged with every string in the kinematics.
#[test]
fn early_slips_are_sized_with_the_layer_tables() {
    use spidar_core::model::Effect;
    let r = loop_on(3, &["slip"]);
    let slip = |string: u8| {
        r.identification
            .effects
            .iter()
            .find_map(|t| match t.effect {
                Effect::Slip { mm, .. } if t.string == string => Some(mm),
                _ => None,
            })
            .unwrap_or_else(|| panic!("no slip on string {string}: {:?}", names(&r)))
    };
    // The model's length steps the other way from what the spool gave out.
    let (s3, s6) = (slip(3), slip(6));
    assert!((s3.abs() - 4.19).abs() < 0.15 * 4.19, "string 3: {s3} mm");
    assert!((s6.abs() - 4.66).abs() < 0.15 * 4.66, "string 6: {s6} mm");
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.45, "{test:?}");
}

/// Asserts that `slips` holds each of `truth` (string, time, mm: the
/// simulator's) on its string within 10 s of its time and 15 % of its size,
/// and nothing else.
fn assert_slips(slips: &[(u8, f64, f64)], truth: &[(u8, f64, f64)]) {
    for &(string, at_s, mm) in truth {
        let found = slips
            .iter()
            .find(|s| s.0 == string && (s.1 - at_s).abs() < 10.0)
            .unwrap_or_else(|| panic!("no slip on string {string} at {at_s} s: {slips:?}"));
        // The model's length steps the other way from what the spool gave out.
        assert!(
            (found.2.abs() - mm).abs() < 0.15 * mm,
            "string {string} at {at_s} s: {} mm for {mm}",
            found.2
        );
    }
    assert_eq!(slips.len(), truth.len(), "{slips:?}");
}

/// Five strings slipped during one lattice (independent seed 1: strings 7,
/// 0, 3, 4, 2 at rows 620, 1153, 1322, 1578, 1825 of 2197). Each step alone
/// left the four others to the rest of the model and raised the held-out
/// p95, and the layer tables, bent by the steps, were refused: the loop
/// stopped with three found, two of them at the wrong time (test mean 0.73
/// mm). The steps are now placed off the model, tried together when none
/// helps alone, and looked for again once the tables are in.
#[test]
fn five_slips_of_one_session_are_found_on_their_strings() {
    let r = loop_on(1, &["slip"]);
    assert_slips(
        &slips_of(&r),
        &[
            (7, 1388.6, 2.69),
            (0, 2572.8, 2.71),
            (3, 2931.9, 4.25),
            (4, 3502.5, 3.41),
            (2, 4021.1, 3.58),
        ],
    );
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.45, "{test:?}");
}

/// One string slipped twice (independent seed 4: string 5 at rows 126 and
/// 704, -4.72 and +3.15 mm): both steps are found, the second off the model
/// that holds the first (one slip a string was all the loop tried: test
/// mean 0.93 mm), and both are in the report.
#[test]
fn a_string_that_slipped_twice_gets_both_steps() {
    let r = loop_on(4, &["slip"]);
    assert_slips(&slips_of(&r), &[(5, 288.0, 4.72), (5, 1548.8, 3.15)]);
    // The report keeps both: the second did not replace the first.
    let reported = r
        .findings
        .iter()
        .filter(|f| f.added && f.family == spidar::model::diagnose::Family::Slip)
        .count();
    assert_eq!(reported, 2, "{:?}", r.findings);
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.45, "{test:?}");
}

/// Heavy strings (20 g/m on every string, other physics: its sag is
/// `w^2 cos^2(a) l^3 / (24 T^2)` and the string already sagged at the home
/// capture, 1.1 N) are named one shared sag, against tension, with the
/// string's weight and the home tension recovered from their ratio, and
/// the error falls to the clean device's level.
#[test]
fn heavy_strings_are_one_shared_sag_with_the_home_capture_s_tension() {
    use spidar::model::diagnose::{Family, Variable};
    use spidar_core::model::{Effect, EVERY_STRING};
    let r = loop_on(2, &["heavy-string"]);
    let stage = r
        .stages
        .iter()
        .find(|s| s.name == "sag (every string)")
        .unwrap_or_else(|| panic!("stages: {:?}", names(&r)));
    assert_eq!(stage.finding.family, Family::Sag);
    assert_eq!(stage.finding.variable, Variable::Tension);
    // The report says it in the device's terms: 20 g/m, 1.1 N at home.
    let said = &stage.finding.description;
    assert!(
        said.contains("strings of 20.") && said.contains("home capture 1.1"),
        "{said}"
    );
    let (c, h) = r
        .identification
        .effects
        .iter()
        .find_map(|t| match t.effect {
            Effect::Sag {
                mm_at_1m_1n,
                home_mm_at_1m,
            } if t.string == EVERY_STRING => Some((mm_at_1m_1n, home_mm_at_1m)),
            _ => None,
        })
        .expect("the shared sag term");
    // w^2 / 24 of 20 g/m = 1.603 mm at 1 m and 1 N.
    assert!((c - 1.603).abs() < 0.1 * 1.603, "mm_at_1m_1n {c}");
    // The home tension is asserted as the stage said it (above, fitted
    // with the sag): a stretch added later has a home part too, and the two
    // home parts, both nearly one constant on every string, share it in the
    // final model (0.76 N here); their ratio stays a tension.
    let home_tension_n = (c / h).sqrt();
    assert!(
        home_tension_n > 0.5 && home_tension_n < 1.5,
        "home tension {home_tension_n} N"
    );
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.6, "{test:?}");
}

/// A frame ten times as compliant as the declared one (other physics: each
/// guide moves by its own `k_i sum_j T_j`, 0.05-0.2 mm/N, along a direction
/// tilted from the frame's centre) is named one shared frame flex against
/// tension, with a compliance in the guides' range, and the error falls to
/// near the clean device's.
#[test]
fn a_flexing_frame_is_named_frame_flex() {
    use spidar::model::diagnose::{Family, Variable};
    use spidar_core::model::{Effect, EVERY_STRING};
    let r = loop_on(2, &["frame-flex"]);
    let stage = r
        .stages
        .iter()
        .find(|s| s.name == "frame flex (every string)")
        .unwrap_or_else(|| panic!("stages: {:?}", names(&r)));
    assert_eq!(stage.finding.family, Family::FrameFlex);
    assert_eq!(stage.finding.variable, Variable::Tension);
    let k = r
        .identification
        .effects
        .iter()
        .find_map(|t| match t.effect {
            Effect::FrameFlex { mm_per_newton, .. } if t.string == EVERY_STRING => {
                Some(mm_per_newton)
            }
            _ => None,
        })
        .expect("the shared frame flex term");
    assert!((0.03..0.2).contains(&k), "compliance {k} mm/N");
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.5, "{test:?}");
}

/// A marker 40 mm off the strings' meeting point on a body that turns with
/// the hand (6 degrees across the volume, 0.3 degree of jitter) is found
/// through the tracker's orientation of the body: the loop names a marker
/// offset against orientation, puts the body's origin where it is (within
/// 3 mm: the body turns by 6 degrees, so 3 mm off moves the meeting point
/// by 0.3 mm at most; 2.1 mm found here), and reads the tracker at the
/// meeting point from then on; the
/// test error falls to near the clean device's (0.354 mm on seed 3). Without
/// the orientation the loop cannot see it (1.34x of clean on this seed, a
/// stand-in refused but the turning offset left to the correction).
#[test]
fn a_marker_off_the_meeting_point_is_found_through_the_tracked_orientation() {
    use spidar::model::diagnose::{Family, Variable};
    let r = loop_on(3, &["marker-offset"]);
    let stage = r
        .stages
        .iter()
        .find(|s| s.finding.family == Family::Marker)
        .unwrap_or_else(|| panic!("stages: {:?}", names(&r)));
    assert_eq!(stage.name, "marker offset (tracked body)");
    assert_eq!(stage.finding.variable, Variable::Orientation);
    assert!(stage.finding.added);
    let found = r.structure.marker_body_mm.expect("the marker offset");
    let device = PhysicsDevice::new(
        &PhysicsConfig {
            effects: vec!["marker-offset".into()],
            ..PhysicsConfig::default()
        },
        3,
    )
    .unwrap();
    let truth = device.marker_body_mm;
    let miss = (0..3)
        .map(|k| (found[k] - truth[k]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(miss < 3.0, "found {found:?} for {truth:?}");
    assert!(stage
        .finding
        .description
        .contains("the tracker is read at the meeting point"));
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.45, "{test:?}");
}

/// Through `calibrate`: the report says where the body's origin is, and
/// the corrections and the final figures read the tracker at the meeting
/// point (final test mean 0.362 mm; 0.452 when the corrections are left to
/// learn the turning offset from the body's origin).
#[test]
fn a_calibration_reports_the_marker_offset_and_reads_the_tracker_at_the_meeting_point() {
    let config = PhysicsConfig {
        effects: vec!["marker-offset".into()],
        ..PhysicsConfig::default()
    };
    let device = PhysicsDevice::new(&config, 3).unwrap();
    let (train, _) = simulate_session(&device, SessionKind::Lattice, 4).unwrap();
    let (test, _) = simulate_session(&device, SessionKind::Random { points: 500 }, 5).unwrap();
    let c = calibrate_quick(&device, &train, &test);
    let d = c
        .report
        .identification
        .marker_body_mm
        .expect("the marker offset in the report");
    let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!((norm - 40.0).abs() < 3.0, "{d:?}");
    let json = serde_json::to_value(&c.report).unwrap();
    assert!(json["identification"]["marker_body_mm"].is_array());
    let last = c.report.stages.last().unwrap();
    assert!(last.test.mean_mm < 0.40, "{}: {:?}", last.name, last.test);
}

/// Without the tracker's orientation there is nothing to find it with: no
/// marker offset is proposed, and the sessions are read as they are.
#[test]
fn without_orientation_no_marker_offset_is_proposed() {
    let mut config = PhysicsConfig {
        effects: vec!["marker-offset".into()],
        ..PhysicsConfig::default()
    };
    config.orientation.enabled = false;
    let device = PhysicsDevice::new(&config, 3).unwrap();
    let (train, _) = simulate_session(&device, SessionKind::Lattice, 4).unwrap();
    assert!(train.samples.iter().all(|s| s.orientation.is_none()));
    let r = spidar::model::diagnose::close_loop(
        &spidar::data::observe::observations(&train.samples),
        None,
        &device.nominal.nominal_frame(),
        &spidar::model::identify::Start::from_geometry(&device.nominal),
        &spidar::model::diagnose::LoopConfig::default(),
    )
    .unwrap();
    assert!(r.structure.marker_body_mm.is_none());
    assert!(r
        .findings
        .iter()
        .all(|f| f.family != spidar::model::diagnose::Family::Marker));
}

fn names(r: &spidar::model::diagnose::LoopResult) -> Vec<&str> {
    r.stages.iter().map(|s| s.name.as_str()).collect()
}

/// The model simulator's spools follow the smooth law exactly: no string
/// gets a table (the spacing must lower the held-out residual by 3 %).
#[test]
fn a_clean_model_device_gets_no_layer_table() {
    use spidar::data::observe::observations;
    use spidar::model::diagnose::{close_loop, LoopConfig};
    use spidar::model::identify::Start;
    let device =
        spidar::sim::SimulatedDevice::new(&spidar::sim::config::SimConfig::default(), 1).unwrap();
    let train = spidar::sim::simulate_session(&device, SessionKind::Lattice, 101).unwrap();
    let r = close_loop(
        &observations(&train.samples),
        None,
        &device.nominal.nominal_frame(),
        &Start::from_geometry(&device.nominal),
        &LoopConfig::default(),
    )
    .unwrap();
    assert!(
        r.stages.is_empty(),
        "{:?}",
        r.stages.iter().map(|s| &s.name).collect::<Vec<_>>()
    );
    assert!(
        r.layers.iter().all(|c| c.step_counts.is_none()),
        "{:#?}",
        r.layers
    );
    assert!(r.identification.laws.iter().all(|l| l.layers.is_empty()));
}

#[test]
fn a_small_session_falls_back_to_interleaved_folds() {
    use spidar::data::observe::observations;
    use spidar::model::identify::{identify, Start, Structure};
    use spidar::model::validate::{validate, FoldScope, Folds, MIN_BLOCKED_ROWS};
    let device = PhysicsDevice::new(&quiet_config(), 2).unwrap();
    let (train, _) = simulate_session(&device, SessionKind::Random { points: 150 }, 3).unwrap();
    let obs = observations(&train.samples);
    assert!(obs.len() < MIN_BLOCKED_ROWS);
    let nominal = device.nominal.nominal_frame();
    let structure = Structure::default();
    let id = identify(
        &obs,
        &nominal,
        &Start::from_geometry(&device.nominal),
        &structure,
    )
    .unwrap();
    let v = validate(&obs, &nominal, &id, &structure, FoldScope::WithInterleaved).unwrap();
    assert_eq!(v.folds, Folds::Interleaved);
    assert_eq!(Some(v.held), v.interleaved);
    assert!(v.noise_p95_mm > 0.0 && v.noise_max_mm > 0.0);
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

/// A planar device whose string 1 rides out of its groove (the abnormal
/// motor, two spare strings): the model knows the other strings to ~0.8 mm
/// only, and a drift on string 3 (-0.0016 mm/s, beyond the quadratic
/// position rival) gained 5.6 % on the blocked folds while it raised the
/// error of the rows it was fitted on by 0.5 %. Added, it raised the test
/// error 1.08 -> 1.55 mm (the test session starts its own time from home).
/// Within the small cells of the lattice that the walk comes back to, the
/// rows differ by -0.00016 mm/s of their time apart (chi-square 8.7; the
/// drift as proposed would explain 898 there): it is no change with time
/// and is reported, not proposed (decision record 0054); before, the folds
/// refused it (`a_gain_only_the_folds_show_is_refused` holds the in-sample
/// rule). A creep on string 3 (decision record 0053) is a time term too
/// and is held to the same revisits.
#[test]
fn a_drift_that_raises_the_error_of_its_own_rows_is_not_added() {
    let mut config = PhysicsConfig::default();
    config.nominal.strings = 4;
    config.nominal.planar = true;
    config.abnormal_motor.string = 1;
    let (device, train, _, test) = device_and_sessions(&config, 2, 500);
    let c = calibrate_quick(&device, &train, &test);
    // The time terms: drifts and creeps.
    use spidar::model::diagnose::Family;
    let drifts: Vec<_> = c
        .report
        .effects
        .iter()
        .filter(|f| matches!(f.family, Family::Drift | Family::Creep))
        .collect();
    for d in &drifts {
        assert!(!d.added, "{d:?}");
    }
    let on_3 = drifts
        .iter()
        .find(|d| d.strings == [3])
        .expect("drift string 3");
    assert!(
        on_3.change.is_none() && on_3.description.contains("not proposed"),
        "{on_3:?}"
    );
    let identified = c
        .report
        .stages
        .iter()
        .find(|s| s.name == "identified")
        .unwrap();
    assert!(identified.test.mean_mm < 1.2, "{:?}", identified.test);
}

/// A device whose physics has no time in it (the independent simulator's
/// without the abnormal motor): the drifts of every string explain the
/// lattice's rows beyond the quadratic position rival (chi-square ~1,800
/// on every row), and within the small cells the walk comes back to they
/// showed at 210-320 against the 320 they must reach with each cell's
/// constant alone taken out: added before the layer tables, they took the
/// test session to 0.54 mm. Within the cells the rival is taken out too
/// (its slope changes from cell to cell), and there they show at 2-18:
/// no term on time (decision record 0059; 0.37 mm).
#[test]
fn a_device_whose_physics_has_no_time_takes_no_term_on_time() {
    let mut config = PhysicsConfig::default();
    config.abnormal_motor.enabled = false;
    let (device, train, _, test) = device_and_sessions(&config, 3, 500);
    let c = calibrate_quick(&device, &train, &test);
    use spidar::model::diagnose::Family;
    for f in &c.report.effects {
        if matches!(f.family, Family::Drift | Family::Creep) {
            assert!(!f.added, "{f:?}");
        }
    }
    assert_final_test_below(&c, 0.45, 3.0);
}

/// Device `seed` of `config`, its lattice (session seed + 1, with the
/// truth of each row) and a test session of `points` random points (+ 2),
/// as `spidar simulate` makes them.
fn device_and_sessions(
    config: &PhysicsConfig,
    seed: u64,
    points: usize,
) -> (
    PhysicsDevice,
    Session,
    Vec<spidar::sim::physics::PhysicsTruth>,
    Session,
) {
    let device = PhysicsDevice::new(config, seed).unwrap();
    let (train, truth) = simulate_session(&device, SessionKind::Lattice, seed + 1).unwrap();
    let (test, _) = simulate_session(&device, SessionKind::Random { points }, seed + 2).unwrap();
    (device, train, truth, test)
}

/// The final stage's held-out mean and max are under `mean_mm` and `max_mm`.
fn assert_final_test_below(
    c: &spidar::procedures::calibrate::Calibrated,
    mean_mm: f64,
    max_mm: f64,
) {
    let last = c.report.stages.last().unwrap();
    assert!(
        last.test.mean_mm < mean_mm && last.test.max_mm < max_mm,
        "{}: {:?}",
        last.name,
        last.test
    );
}

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

/// The independent simulator's encoder latency: a string read `tau` late
/// holds its counts of `tau` earlier, the hand back along its velocity
/// (`latency:string=2,ms=6`): on a stream its counts fall behind by `tau`
/// times their rate, and every other string's counts are the clean
/// device's to the count.
#[test]
fn an_encoder_read_late_holds_its_string_as_it_was_then() {
    let kind = SessionKind::Stream {
        rows: 400,
        area: spidar::sim::StreamArea::Training,
    };
    let clean = PhysicsDevice::new(&quiet_config(), 5).unwrap();
    let late = PhysicsDevice::new(
        &PhysicsConfig {
            effects: vec!["latency:string=2,ms=6".into()],
            ..quiet_config()
        },
        5,
    )
    .unwrap();
    let (a, _) = simulate_session(&clean, kind, 8).unwrap();
    let (b, _) = simulate_session(&late, kind, 8).unwrap();
    let (mut moving, mut off) = (0, Vec::new());
    for r in 1..a.samples.len() - 1 {
        let (x, y) = (&a.samples[r], &b.samples[r]);
        for i in (0..8).filter(|&i| i != 2) {
            assert_eq!(x.counts[i], y.counts[i], "row {r}, string {i}");
        }
        let dt = a.samples[r + 1].t_s - a.samples[r - 1].t_s;
        let rate = f64::from(a.samples[r + 1].counts[2] - a.samples[r - 1].counts[2]) / dt;
        if rate.abs() > 2000.0 {
            moving += 1;
            let expected = f64::from(x.counts[2]) - 0.006 * rate;
            off.push((f64::from(y.counts[2]) - expected).abs());
        }
    }
    assert!(moving > 100, "{moving} moving rows");
    off.sort_by(f64::total_cmp);
    let median = off[off.len() / 2];
    // A central difference over 20 ms of a minimum-jerk stroke against
    // the velocity at the capture: a few counts (a count is ~0.02 mm).
    assert!(median < 5.0, "median {median} counts off tau * rate");
}

/// Issue 33 point 3 on the independent simulator: 6 ms of encoder latency
/// on strings 2 and 5 of a 100 Hz stream, through `calibrate` (the
/// tracker's clock found by the alignment): a latency on each of the two
/// strings of about 6 ms and on no other string. The alignment's quick
/// model has no latency of one string and finds the clock 0.2-0.5 ms off;
/// the loop takes that as a latency every string shares, which the device
/// would apply in use. It goes into the clocks' offsets, found within
/// 0.05 ms, and the model holds no such term (decision record 0064).
#[test]
fn encoder_latency_on_an_independent_stream_is_named_on_its_strings() {
    let device = PhysicsDevice::new(
        &PhysicsConfig {
            effects: vec![
                "latency:string=2,ms=6".into(),
                "latency:string=5,ms=6".into(),
            ],
            ..PhysicsConfig::default()
        },
        1,
    )
    .unwrap();
    let stream = |rows, area, seed| {
        simulate_session(&device, SessionKind::Stream { rows, area }, seed)
            .unwrap()
            .0
    };
    let train = stream(3000, spidar::sim::StreamArea::Training, 4);
    let test = stream(1000, spidar::sim::StreamArea::Whole, 5);
    let c = calibrate_quick(&device, &train, &test);
    let latencies: Vec<(Vec<u8>, f64, String)> = c
        .report
        .effects
        .iter()
        .filter(|f| f.added && f.family == spidar::model::diagnose::Family::Latency)
        .map(|f| (f.strings.clone(), f.amplitude_mm, f.description.clone()))
        .collect();
    let terms: Vec<(u8, f64)> = c
        .calibration
        .effects
        .iter()
        .filter_map(|t| match t.effect {
            spidar_core::model::Effect::Latency { latency_s } => Some((t.string, latency_s)),
            _ => None,
        })
        .collect();
    println!("{latencies:?}\n{terms:?}");
    for s in [2u8, 5] {
        let own = terms.iter().find(|t| t.0 == s).map(|t| t.1);
        assert!(
            own.is_some_and(|tau| (0.005..0.007).contains(&tau)),
            "string {s}: {terms:?}"
        );
    }
    assert!(
        terms.iter().all(|t| [2, 5].contains(&t.0)),
        "a latency on another string, or every string's: {terms:?}"
    );
    let truth = device.config.tracker.clock_offset_s;
    for (name, timing) in [
        ("train", &c.report.timing.train),
        ("test", &c.report.timing.test),
    ] {
        let spidar::procedures::calibrate::align::SessionTiming::Aligned(a) = timing else {
            panic!("{name}: {timing:?}");
        };
        println!("{name}: {a:?}");
        assert!((a.offset_s - truth).abs() < 5e-5, "{name}: {a:?}");
    }
    for (strings, _, description) in &latencies {
        if strings.is_empty() {
            assert!(description.contains("tracker's clock"), "{description}");
        }
    }
}

/// A clean independent device's 60 s training stream over the central part
/// of its workspace (seed 2, as `physics_bench`'s `stream` case). Its
/// spools thin at their own rates (their layers hold 5.6 to 10.5 turns),
/// but tried first, before the layer tables, the rates are refused: the
/// outer shell's fold, fitted on the inner region, extrapolates them by
/// mm (its max 3.53 -> 5.50 mm). Tried again once the tables and the
/// effects are in, they are taken, and the finding says why they were
/// refused at first (decision record 0065).
#[test]
fn spool_rates_refused_before_the_tables_are_tried_again_after_them() {
    let device = PhysicsDevice::new(&PhysicsConfig::default(), 2).unwrap();
    let stream = |rows, area, seed| {
        simulate_session(&device, SessionKind::Stream { rows, area }, seed)
            .unwrap()
            .0
    };
    let train = stream(
        device.config.stream.rows,
        spidar::sim::StreamArea::Training,
        5,
    );
    let test = stream(1000, spidar::sim::StreamArea::Whole, 6);
    let c = calibrate_quick(&device, &train, &test);
    let rates: Vec<&spidar::model::diagnose::Finding> = c
        .report
        .effects
        .iter()
        .filter(|f| f.family == spidar::model::diagnose::Family::Winding && f.strings.len() == 8)
        .collect();
    for f in &rates {
        println!("{}: {}", f.added, f.description);
    }
    assert_eq!(rates.len(), 1, "one finding of the spool rates");
    assert!(rates[0].added, "{}", rates[0].description);
    assert!(
        rates[0].description.contains("tried again")
            && rates[0]
                .description
                .contains("first try, before them: not added"),
        "{}",
        rates[0].description
    );
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
