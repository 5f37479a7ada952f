//! Calibration on measured data from a real cable robot, not made by any of
//! the project's simulators: the judge of whether the model holds on reality.
//!
//! Data: `../shared/data/hangprinter-hp4-2022/` — Hangprinter v4 prototype
//! "force series 2" (April 2022) by Torbjørn Ludvigsen, from
//! github.com/tobbelobb/auto-calibration-simulation-for-hangprinter
//! (commit eff69f9e6522a526ed2dce2d83eed9bc3843a5cc, `simulation.py`), MIT
//! licence (see that folder's LICENSE and README). 4 lines doubled through
//! pulley blocks (mechanical advantage 2, 2, 2, 4), 44 static poses, a
//! camera-based position reference (hp-mark) with ~2 mm of its own scatter;
//! split by its README: 34 training rows, 10 held-out test rows.
//!
//! Honesty rules: the model is fitted on `train.csv` only; no parameter is
//! tuned on the test rows; the figure asserted is the held-out test error.

use std::path::{Path, PathBuf};
use std::process::Command;

use spidar::data::dataset::{DatasetError, Geometry, Session};
use spidar::procedures::calibrate::report::{Choice, StageKind};
use spidar::procedures::calibrate::{calibrate, CalibrateConfig, Calibrated, NamedSession};

/// The issues' target for the held-out mean (mm): issue 11's 2.9 (a careful
/// fit of anchors, per-string radius and spool build-up reaches 2.85),
/// issue 32's 2.7; the nominal geometry is at ~16 mm.
const HELD_OUT_MEAN_TARGET_MM: f64 = 2.7;

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/hangprinter-hp4-2022")
}

fn load() -> (Geometry, Session, Session) {
    let d = data_dir();
    (
        Geometry::load(d.join("geometry.toml")).expect("geometry"),
        Session::load(d.join("train.csv")).expect("train"),
        Session::load(d.join("test.csv")).expect("test"),
    )
}

/// The quick calibration of the Hangprinter's geometry from a training and
/// a test session (path, session).
fn calibrate_quick(g: &Geometry, train: (&Path, &Session), test: (&Path, &Session)) -> Calibrated {
    calibrate_quick_with(&data_dir().join("geometry.toml"), g, train, test)
}

/// The Hangprinter's geometry and its quick calibration on its own split
/// (`train.csv`, `test.csv`).
fn calibrate_own_split() -> (Geometry, Calibrated) {
    let (g, train, test) = load();
    let d = data_dir();
    let c = calibrate_quick(
        &g,
        (&d.join("train.csv"), &train),
        (&d.join("test.csv"), &test),
    );
    (g, c)
}

/// [`calibrate_quick`] with the geometry read from `geometry_path`.
fn calibrate_quick_with(
    geometry_path: &Path,
    g: &Geometry,
    train: (&Path, &Session),
    test: (&Path, &Session),
) -> Calibrated {
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    calibrate(
        g,
        geometry_path,
        NamedSession {
            path: train.0,
            session: train.1,
        },
        NamedSession {
            path: test.0,
            session: test.1,
        },
        &cfg,
    )
    .expect("calibrate the Hangprinter")
}

#[test]
fn the_n_string_formats_read_the_hangprinter_files() {
    let (g, train, test) = load();
    assert_eq!(g.strings(), 4);
    assert!(!g.layout.planar);
    assert_eq!(&g.mechanical_advantage[..4], &[2.0, 2.0, 2.0, 4.0]);
    assert_eq!(&g.counts_per_rev[..4], &[459_000; 4]);
    // The nominal law is the spool radius over the mechanical advantage.
    let laws = g.nominal_string_laws();
    assert_eq!(laws[0].winding_mm[0], 37.5);
    assert_eq!(laws[3].winding_mm[0], 18.75);
    assert_eq!((train.strings, test.strings), (4, 4));
    assert_eq!((train.samples.len(), test.samples.len()), (34, 10));
    assert!(train.has_tension());
    // 3 poses of the training file were not tracked: kept, as occluded rows.
    assert_eq!(
        train.samples.iter().filter(|s| s.tracker.is_none()).count(),
        3
    );
}

#[test]
fn a_model_fitted_on_train_meets_the_held_out_target() {
    let (g, c) = calibrate_own_split();
    let d = data_dir();
    let r = &c.report;
    let test_mean = |name: &str| {
        r.stages
            .iter()
            .find(|s| s.name == name)
            .unwrap_or_else(|| panic!("stage {name}"))
            .test
            .mean_mm
    };
    let raw = test_mean("raw");
    let identified = test_mean("identified");
    let last = r.stages.last().unwrap();
    assert_eq!(last.kind, StageKind::Final);
    assert_eq!(last.test.n, 10);
    // Nominal geometry: ~16 mm (hand-measured anchors 27-68 mm off).
    assert!((12.0..20.0).contains(&raw), "raw {raw}");
    // Measured 2.51 mm with the identified model (anchors, home, tracker
    // frame, per-string radius, shared spool build-up; the anchors'
    // tolerance chosen on ten folds: 60 mm).
    assert!(
        identified <= HELD_OUT_MEAN_TARGET_MM,
        "identified {identified}"
    );
    assert!(
        last.test.mean_mm <= HELD_OUT_MEAN_TARGET_MM,
        "final {}",
        last.test.mean_mm
    );
    // The anchors' tolerance was chosen on held-out folds (the geometry gives
    // none): the hand-measured anchors are tens of mm off, a looser prior
    // than the drawing's 15 mm won.
    let tolerance = &r.anchor_tolerance;
    assert_eq!(tolerance.scores.len(), 3, "{tolerance:?}");
    assert!(tolerance.anchor_sd_mm[0] > 15.0, "{tolerance:?}");
    // The spool build-up has the author's sign and size: kappa = Q / 4,
    // Q ~ 0.07-0.08 mm from a free fit.
    let kappa = c.loop_result.identification.winding.kappa_mm;
    assert!((0.005..0.03).contains(&kappa), "kappa {kappa}");
    // Per-string effective radii: spool (~75 mm) over the mechanical advantage.
    let r_home = c.loop_result.identification.winding.r_home_mm;
    for (i, m) in [2.0, 2.0, 2.0, 4.0].iter().enumerate() {
        assert!(
            (r_home[i] * m - 75.5).abs() < 2.0,
            "string {i}: {}",
            r_home[i]
        );
    }
    // What 4 strings in 3-D mean is said.
    assert_eq!(r.device.strings, 4);
    assert_eq!(r.device.redundancy, 1);
    assert!(!r.device.fault_rejection);
    assert!(r.device.limits.iter().any(|l| l.contains("spare")));
    // The runtime monitor takes this calibration of a device whose lines are
    // doubled and quadrupled (issue 11): its laws are of the identified form
    // with the geometry's mechanical advantage, and read back as the same
    // shared spool build-up.
    use spidar::procedures::monitor::{check_calibration, identification_of};
    check_calibration(&c.calibration, &g, 100.0, &d.join("calibration.json"))
        .expect("the monitor accepts a calibration of a device with mechanical advantage");
    let back = identification_of(&c.calibration, &g.mechanical_advantage);
    assert!((back.winding.kappa_mm - kappa).abs() < 1e-12 * kappa.abs().max(1.0));
    assert_eq!(back.laws, c.calibration.strings);
    // 31 tracked training rows: too few to choose a learned correction.
    assert!(
        r.warnings.iter().any(|w| w.contains("selection split")),
        "{:?}",
        r.warnings
    );
    // The plain least-squares reference (unweighted, no priors, every string
    // alike): 2.85 mm held out, as a careful fit by hand; the final model is
    // not worse on the selection split, nor held out.
    let reference = test_mean(spidar::model::reference::STAGE_NAME);
    assert!((2.5..3.2).contains(&reference), "reference {reference}");
    assert_eq!(r.stages[1].kind, StageKind::Reference);
    let s = &r.selection;
    let chosen = match s.choice {
        Choice::Identified => s.validation_mean_mm.identified,
        Choice::Reference => s.validation_mean_mm.reference,
        Choice::Nn => s.validation_mean_mm.nn,
        Choice::Svr => s.validation_mean_mm.svr,
    };
    assert!(
        chosen <= s.validation_mean_mm.reference,
        "selection split: final {chosen} vs reference {}",
        s.validation_mean_mm.reference
    );
    assert!(
        last.test.mean_mm <= reference,
        "final {} vs reference {reference}",
        last.test.mean_mm
    );
}

/// `spidar calibrate --quick` of the Hangprinter's geometry on `train` and
/// `test`, written to `out`.
fn calibrate_cli(train: &Path, test: &Path, out: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args([
            "calibrate",
            "--quick",
            "--quiet",
            "--no-figures",
            "--geometry",
        ])
        .arg(data_dir().join("geometry.toml"))
        .arg("--train")
        .arg(train)
        .arg("--test")
        .arg(test)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

/// `n` of the training session's tracked rows, spread evenly over it (a
/// smaller session of the same robot).
fn every_kth_tracked(train: &Session, n: usize) -> Session {
    let tracked: Vec<_> = train
        .samples
        .iter()
        .filter(|s| s.tracker.is_some())
        .cloned()
        .collect();
    let step = tracked.len() as f64 / n as f64;
    let mut small = train.clone();
    small.samples = (0..n)
        .map(|k| tracked[(k as f64 * step) as usize].clone())
        .collect();
    small
}

#[test]
fn twelve_and_sixteen_training_rows_are_identified_alone_with_their_sds() {
    let (g, train, test) = load();
    let d = data_dir();
    for (n, held_out_max_mm) in [(12, 3.8), (16, 3.2)] {
        let small = every_kth_tracked(&train, n);
        let path = d.join(format!("train-{n}-rows.csv"));
        let c = calibrate_quick(&g, (&path, &small), (&d.join("test.csv"), &test));
        let r = &c.report;
        let stage = |kind: StageKind| r.stages.iter().find(|s| s.kind == kind).unwrap();
        let fin = stage(StageKind::Final);
        let reference = stage(StageKind::Reference);
        // Measured: 12 rows 3.54 mm (reference 3.83), 16 rows 2.70 (3.87).
        assert!(
            fin.test.mean_mm <= held_out_max_mm,
            "{n} rows: final {}",
            fin.test.mean_mm
        );
        assert!(fin.test.mean_mm <= reference.test.mean_mm, "{n} rows");
        // Identification only: no loop, no learned correction, and the
        // warning says how many rows would enable them.
        assert!(r.corrections.is_none(), "{n} rows");
        assert!(r.effects.is_empty(), "{n} rows");
        assert!(
            r.warnings
                .iter()
                .any(|w| w.contains("identification only") && w.contains("more tracked poses")),
            "{n} rows: {:?}",
            r.warnings
        );
        // The kinematics' rule chosen on the folds the anchors' tolerance
        // is chosen on (a tenth held out each), not the device's by default.
        assert!(
            r.kinematics.reason.contains("10 interleaved folds")
                && r.kinematics.candidates.len() >= 2,
            "{n} rows: {}",
            r.kinematics.reason
        );
        // Every free parameter with its sd.
        let params = &r.identification.parameters;
        assert!(params.iter().any(|p| p.name == "anchor0.x"), "{n} rows");
        assert!(
            params.iter().all(|p| p.sd.is_finite() && p.sd > 0.0),
            "{n} rows: {params:?}"
        );
    }
}

/// The other sessions of the same robot (`data/hangprinter-hp4-sessions/`,
/// MIT licence, Torbjørn Ludvigsen; see that folder's README).
fn sessions_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/hangprinter-hp4-sessions")
}

/// The 35-pose session of the HP4pt2 configuration (the 18-pose and the
/// bed sessions of one commit): issue 32's "35 poses" (2.89 mm held out,
/// a careful fit 3.34). The loop runs on its 27 training rows and takes
/// each spool's own rate; the final model holds out below the plain
/// least-squares reference. Measured: reference 3.336, identified 2.936,
/// final 2.824 mm.
#[test]
fn the_thirty_five_pose_session_holds_out_below_the_plain_fit() {
    let d = sessions_dir().join("hp4pt2-session18-and-bed");
    let g = Geometry::load(d.join("geometry.toml")).expect("geometry");
    let train = Session::load(d.join("train.csv")).expect("train");
    let test = Session::load(d.join("test.csv")).expect("test");
    let c = calibrate_quick_with(
        &d.join("geometry.toml"),
        &g,
        (&d.join("train.csv"), &train),
        (&d.join("test.csv"), &test),
    );
    let stage = |kind: StageKind| c.report.stages.iter().find(|s| s.kind == kind).unwrap();
    let (fin, reference) = (stage(StageKind::Final), stage(StageKind::Reference));
    assert!(fin.test.mean_mm <= 3.0, "final {}", fin.test.mean_mm);
    assert!(
        fin.test.mean_mm < reference.test.mean_mm,
        "final {} against the reference {}",
        fin.test.mean_mm,
        reference.test.mean_mm
    );
    assert!(
        c.report.effects.iter().any(|e| e.added),
        "the loop ran and took a term: {:?}",
        c.report
            .effects
            .iter()
            .map(|e| &e.description)
            .collect::<Vec<_>>()
    );
}

/// A session with no row to spare for held-out folds (11 tracked rows; the
/// model needs 10 in every fold) places its rows with the rule that stays
/// unless held-out data choose another, every string alike, not with the
/// device's thresholds and the strings' weights, which are set on our
/// simulators and which nothing here could judge (decision record 0083).
#[test]
fn a_session_without_folds_places_its_rows_with_every_string_alike() {
    let (g, train, test) = load();
    let d = data_dir();
    let small = every_kth_tracked(&train, 11);
    let c = calibrate_quick(
        &g,
        (&d.join("train-11-rows.csv"), &small),
        (&d.join("test.csv"), &test),
    );
    // The identified model as the calibration finishes it (here the plain
    // least-squares reference then holds lower on the selection split and
    // is the final model: it too places every string alike).
    let id = &c.loop_result.identification;
    assert_eq!(
        id.kinematics.exclusion_threshold_mm, id.kinematics.fault_threshold_mm,
        "no string left out below the fault threshold"
    );
    assert_eq!(
        id.length_scale_mm,
        spidar::model::predict::UNMEASURED_SCALES,
        "its strings weigh alike"
    );
    let k = c.calibration.kinematics;
    assert_eq!(k.exclusion_threshold_mm, k.fault_threshold_mm);
    assert_eq!(
        c.calibration.length_scale_mm,
        spidar::model::predict::UNMEASURED_SCALES
    );
}

/// A small session on which the identified model loses to the plain
/// least-squares reference on the selection split: the reference is the
/// final model end to end. 12 of the 41 tracked poses of `all.csv` (the
/// draw `scripts/real-subsets` makes for 12 rows, draw 22), the other 29
/// to test. Measured: the identified model 1.774 mm on the 2-row selection
/// split, the reference 1.567; held out 4.337 and 2.966 mm.
#[test]
fn a_small_session_whose_identified_model_loses_to_the_plain_fit_falls_back_to_it() {
    const PICKED: [usize; 12] = [0, 3, 4, 8, 10, 16, 20, 33, 34, 35, 37, 38];
    let d = data_dir();
    let all = Session::load(d.join("all.csv")).expect("all.csv");
    let tracked: Vec<_> = all
        .samples
        .iter()
        .filter(|s| s.tracker.is_some())
        .cloned()
        .collect();
    assert_eq!(tracked.len(), 41);
    let dir = std::env::temp_dir().join(format!("spidar-real-fallback-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let write = |name: &str, keep: &dyn Fn(usize) -> bool| {
        let mut s = all.clone();
        s.samples = (0..tracked.len())
            .filter(|&i| keep(i))
            .map(|i| tracked[i].clone())
            .collect();
        let path = dir.join(name);
        s.write(&path).unwrap();
        path
    };
    let train = write("train-12.csv", &|i| PICKED.contains(&i));
    let test = write("test-29.csv", &|i| !PICKED.contains(&i));
    let out = dir.join("cal");
    let o = calibrate_cli(&train, &test, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary =
        String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr);
    assert!(
        summary.contains("Final stage `final (plain least squares)`"),
        "{summary}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let selection = &report["selection"];
    assert_eq!(selection["choice"], "reference", "{selection}");
    let why = selection["reason"].as_str().unwrap();
    assert!(
        why.contains("the plain least-squares reference: string model has")
            && why.contains("identification only"),
        "{why}"
    );
    // The final stage is the reference's, to the bit, on both sessions.
    let stage = |name: &str| {
        report["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == name)
            .unwrap_or_else(|| panic!("no stage {name}"))
            .clone()
    };
    let (fin, reference) = (
        stage("final (plain least squares)"),
        stage(spidar::model::reference::STAGE_NAME),
    );
    assert_eq!(fin["train"], reference["train"]);
    assert_eq!(fin["test"], reference["test"]);
    let held_out = |s: &serde_json::Value| s["test"]["mean_mm"].as_f64().unwrap();
    assert!(
        held_out(&fin) < held_out(&stage("identified")),
        "final {} identified {}",
        held_out(&fin),
        held_out(&stage("identified"))
    );
    // What the device gets is the reference: no effect, no correction, no
    // slip to carry; it compiles, and its fixed point holds the budget on
    // the test rows.
    let calibration: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("calibration.json")).unwrap())
            .unwrap();
    assert_eq!(calibration["effects"], serde_json::json!([]));
    assert_eq!(
        calibration["correction"], "None",
        "{}",
        calibration["correction"]
    );
    assert_eq!(report["device_slips"]["slips"], serde_json::json!([]));
    let blob = dir.join("model.blob");
    let o = Command::new(env!("CARGO_BIN_EXE_spidar"))
        .arg("compile")
        .arg("--calibration")
        .arg(out.join("calibration.json"))
        .arg("--out")
        .arg(&blob)
        .arg("--test")
        .arg(&test)
        .arg("--geometry")
        .arg(d.join("geometry.toml"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(blob.exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// Ten poses on a printer's bed (`hp4pt2-bed`, every tracked pose z near
/// 0), the other seven to test, two of them 0.7 and 1.2 m above the bed:
/// the plain least-squares reference fits the two rows of the selection
/// split closer than the identified model and is the final model (issue
/// 32: the final model is not worse than it there), but the bed does not
/// determine the heights of its anchors, which the report says, naming the
/// widest against the geometry's tolerance. Measured: the ceiling anchor's
/// height 1736 +- 592 mm against the geometry's +- 15; held out 216 mm,
/// the identified model 34.
#[test]
fn a_plain_fit_the_training_poses_hardly_determine_is_named_when_it_is_final() {
    const BED_POSES: [usize; 10] = [0, 2, 5, 6, 7, 8, 9, 12, 13, 14];
    let d = sessions_dir().join("hp4pt2-bed");
    let g = Geometry::load(d.join("geometry.toml")).expect("geometry");
    let all = Session::load(d.join("all.csv")).expect("all.csv");
    assert_eq!(all.samples.len(), 17);
    let part = |keep: &dyn Fn(usize) -> bool| {
        let mut s = all.clone();
        s.samples = (0..all.samples.len())
            .filter(|&i| keep(i))
            .map(|i| all.samples[i].clone())
            .collect();
        s
    };
    let train = part(&|i| BED_POSES.contains(&i));
    let test = part(&|i| !BED_POSES.contains(&i));
    assert!(train
        .samples
        .iter()
        .all(|s| s.tracker.is_some_and(|p| p[2].abs() < 10.0)));
    let c = calibrate_quick_with(
        &d.join("geometry.toml"),
        &g,
        (&d.join("train-bed-10.csv"), &train),
        (&d.join("test-7.csv"), &test),
    );
    assert_eq!(c.report.selection.choice, Choice::Reference);
    let loose: Vec<&String> = c
        .report
        .warnings
        .iter()
        .filter(|w| w.contains("determine") && w.contains("less well than the geometry"))
        .collect();
    assert_eq!(loose.len(), 1, "{:?}", c.report.warnings);
    assert!(
        loose[0].contains("anchor3.z") && loose[0].contains("(the geometry: ± 15 mm)"),
        "{}",
        loose[0]
    );
    // What the device runs is in the report beside the identified model:
    // the reference's parameters with their sds from the data alone.
    let reference = &c.report.identification.reference_parameters;
    let ceiling = reference.iter().find(|p| p.name == "anchor3.z").unwrap();
    assert!(ceiling.sd > 100.0, "{ceiling:?}");
    let summary = c.report.summary();
    assert!(
        summary.contains("The final model's parameters: the plain least-squares reference's"),
        "{summary}"
    );
    let page =
        spidar::procedures::report_page::render(&serde_json::to_value(&c.report).unwrap(), None);
    assert!(
        page.contains("The final model is the plain least-squares reference"),
        "the page shows the final model's parameters"
    );
    // The warning is the final plain fit's: a session whose final model is
    // the identified one has none.
    let (_, c) = calibrate_own_split();
    assert_ne!(c.report.selection.choice, Choice::Reference);
    assert!(
        !c.report
            .warnings
            .iter()
            .any(|w| w.contains("less well than the geometry")),
        "{:?}",
        c.report.warnings
    );
    assert!(!c.report.summary().contains("The final model's parameters"));
}

#[test]
fn fewer_rows_than_the_identification_needs_are_refused_saying_what_to_collect() {
    let (g, train, test) = load();
    let d = data_dir();
    let small = every_kth_tracked(&train, 8);
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    let path = d.join("train-8-rows.csv");
    let e = calibrate(
        &g,
        &d.join("geometry.toml"),
        NamedSession {
            path: &path,
            session: &small,
        },
        NamedSession {
            path: &d.join("test.csv"),
            session: &test,
        },
        &cfg,
    )
    .expect_err("8 rows cannot identify a 4-string model");
    let text = e.to_string();
    assert!(
        text.contains("train-8-rows.csv")
            && text.contains("needs at least 10")
            && text.contains("collect 2 more"),
        "{text}"
    );
}

#[test]
fn a_session_with_other_strings_than_its_geometry_is_refused_naming_both() {
    let d = data_dir();
    let dir = std::env::temp_dir().join(format!("spidar-real-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // The Hangprinter's 4-string session against an 8-string geometry.
    let eight = dir.join("eight.toml");
    std::fs::write(
        &eight,
        std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/examples/geometry.toml"),
        )
        .unwrap(),
    )
    .unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(["calibrate", "--geometry"])
        .arg(&eight)
        .arg("--train")
        .arg(d.join("train.csv"))
        .arg("--test")
        .arg(d.join("test.csv"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("train.csv") && e.contains("eight.toml"), "{e}");
    assert!(
        e.contains("4 encoder columns") && e.contains("8 anchors"),
        "{e}"
    );
    // And the library error names both.
    let g = Geometry::load(&eight).unwrap();
    let s = Session::load(d.join("test.csv")).unwrap();
    let err = s
        .check_strings(&d.join("test.csv"), &g, &eight)
        .unwrap_err();
    assert!(matches!(err, DatasetError::StringCount { .. }), "{err}");
}

/// The Hangprinter's sessions with the tracker in metres: refused, naming
/// the file and the unit, where before the pulley radii shrank a
/// thousandfold and the report said 0.057 "mm".
#[test]
fn a_tracker_in_metres_is_refused_naming_the_unit() {
    let d = data_dir();
    let dir = std::env::temp_dir().join(format!("spidar-real-metres-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let in_metres = |name: &str| {
        let mut s = Session::load(d.join(name)).unwrap();
        for sample in &mut s.samples {
            if let Some(t) = sample.tracker.as_mut() {
                *t = t.map(|x| x / 1000.0);
            }
        }
        let path = dir.join(name);
        s.write(&path).unwrap();
        path
    };
    let (train, test) = (in_metres("train.csv"), in_metres("test.csv"));
    let o = calibrate_cli(&train, &test, &dir.join("out"));
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("train.csv") && e.contains("geometry.toml"),
        "{e}"
    );
    assert!(e.contains("look like metres"), "{e}");
    assert!(!dir.join("out").join("calibration.json").exists());
    // The test session alone in metres: refused naming it (it held out
    // 670 mm, exit 0, blamed on the priors).
    let o = calibrate_cli(&d.join("train.csv"), &test, &dir.join("out-test"));
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains(&format!("{}: ", test.display())) && e.contains("look like metres"),
        "{e}"
    );
    assert!(!dir.join("out-test").join("calibration.json").exists());
}

/// The warnings containing `text` of the quick calibration of the
/// Hangprinter's sessions under geometry `g` (a variant of its own).
fn warnings_of(g: &Geometry, text: &str) -> Vec<String> {
    let (_, train, test) = load();
    let d = data_dir();
    let c = calibrate_quick(
        g,
        (&d.join("train.csv"), &train),
        (&d.join("test.csv"), &test),
    );
    c.report
        .warnings
        .into_iter()
        .filter(|w| w.contains(text))
        .collect()
}

/// The Hangprinter's geometry with anchor B's x typed 500 mm off, and with
/// anchor D's height: the anchor is named (the fit held it 220 mm off the
/// truth with an sd of 9 mm, the held-out error ordinary, no warning); as
/// written, none is.
#[test]
fn an_anchor_typed_500_mm_off_is_named() {
    let g = load().0;
    let named = |g: &Geometry| warnings_of(g, "beyond what every anchor moved alike");
    assert_eq!(named(&g), Vec::<String>::new());
    for (anchor, axis) in [(1, 0), (3, 2)] {
        let mut typo = g.clone();
        typo.anchors_mm[anchor][axis] += 500.0;
        let w = named(&typo);
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with(&format!("anchor {anchor} is identified")),
            "{w:?}"
        );
    }
}

/// The Hangprinter's geometry with lines C and D's mechanical advantages
/// swapped (`[2, 2, 4, 2]` for `[2, 2, 2, 4]`): the identification takes
/// the factor into the two radii, and the report names both strings and
/// the key (nothing said so; the final model held out 44 % worse than the
/// plain fit on 12 rows, the warning blaming the kinematics' rule). The
/// geometry as written names none.
#[test]
fn a_mechanical_advantage_written_for_another_line_is_named() {
    let mut g = load().0;
    let named = |g: &Geometry| warnings_of(g, "radius at home");
    assert_eq!(named(&g), Vec::<String>::new());
    g.mechanical_advantage.swap(2, 3);
    let w = named(&g);
    assert_eq!(w.len(), 2, "{w:?}");
    assert!(
        w[0].starts_with("string 2's") && w[1].starts_with("string 3's"),
        "{w:?}"
    );
    assert!(
        w.iter().all(|w| w.contains("mechanical_advantage")),
        "{w:?}"
    );
}

/// The Hangprinter's line B (string 1) with its counts negated, as an
/// encoder wired the other way gives them: the identification follows the
/// sign (a negative radius), the held-out target is met as recorded, and
/// the report says which string counts down.
#[test]
fn a_string_whose_encoder_counts_down_is_followed_and_named() {
    let (g, mut train, mut test) = load();
    for s in train.samples.iter_mut().chain(test.samples.iter_mut()) {
        s.counts[1] = -s.counts[1];
    }
    let c = calibrate_quick(
        &g,
        (Path::new("train-b-negated.csv"), &train),
        (Path::new("test-b-negated.csv"), &test),
    );
    let last = c.report.stages.last().unwrap();
    assert!(
        last.test.mean_mm <= HELD_OUT_MEAN_TARGET_MM,
        "{}",
        last.test.mean_mm
    );
    let r_home = c.loop_result.identification.winding.r_home_mm;
    assert!(r_home[1] < 0.0 && r_home[0] > 0.0 && r_home[2] > 0.0 && r_home[3] > 0.0);
    let named: Vec<&String> = c
        .report
        .warnings
        .iter()
        .filter(|w| w.contains("counts fall as its string pays out"))
        .collect();
    assert_eq!(named.len(), 1, "{:?}", c.report.warnings);
    assert!(named[0].contains("string 1:"), "{}", named[0]);
}
