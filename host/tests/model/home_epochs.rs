//! Sessions in time (issue 33, point 1): a slip found in the training
//! session is still in a test session of the same home capture, and gone
//! from one after a new home capture. The calibration tells which from the
//! sessions (here their clocks: the continuing test session's `t_s` goes
//! on from the training's, the re-homed one's starts again) and judges the
//! test session with the slips of its home.

use spidar::data::dataset::Session;
use spidar::data::home::HomeBasis;
use spidar::procedures::calibrate::report::StageKind;
use spidar::procedures::calibrate::{CalibrateConfig, Calibrated};
use spidar::sim::{
    simulate_session, simulate_session_after, SessionKind, SimConfig, SimulatedDevice,
};

const SLIP: &str = "slip:2:at_s=2000,mm=8";

fn calibrated(effects: &[&str], continuing: bool) -> Calibrated {
    calibrated_under(effects, continuing, None)
}

/// `calibrated`, the sessions recording `home_id` as their home capture
/// (and their `t_s` as the time since it), as `spidar collect` writes them.
fn calibrated_under(effects: &[&str], continuing: bool, home_id: Option<u64>) -> Calibrated {
    let (device, train, test) = sessions_under(effects, continuing, home_id);
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    crate::calibrate_in_memory(&device.nominal, &train, &test, &cfg)
}

/// The device of `calibrated_under`, its lattice and its test session.
fn sessions_under(
    effects: &[&str],
    continuing: bool,
    home_id: Option<u64>,
) -> (SimulatedDevice, Session, Session) {
    let seed = 1;
    let config = SimConfig {
        effects: effects.iter().map(|s| s.to_string()).collect(),
        ..SimConfig::default()
    };
    let device = SimulatedDevice::new(&config, seed).expect("device");
    let train = simulate_session(&device, SessionKind::Lattice, seed + 100).expect("lattice");
    let kind = SessionKind::Random { points: 400 };
    let test = if continuing {
        simulate_session_after(&device, kind, seed + 200, &train)
            .expect("continuing test")
            .0
    } else {
        simulate_session(&device, kind, seed + 200).expect("re-homed test")
    };
    let with_home = |mut s: Session| {
        for row in s.samples.iter_mut().filter(|_| home_id.is_some()) {
            row.since_home_s = Some(row.t_s);
            row.home = home_id;
        }
        s
    };
    let (train, test) = (with_home(train), with_home(test));
    (device, train, test)
}

/// [`calibrated_under`] of the slip, continuing, under [`CARRIED_HOME`]:
/// one calibration for the tests that read it.
fn carried() -> &'static Calibrated {
    static C: std::sync::OnceLock<Calibrated> = std::sync::OnceLock::new();
    C.get_or_init(|| calibrated_under(&[SLIP], true, Some(CARRIED_HOME)))
}

const CARRIED_HOME: u64 = 0x5eed_0000_0003;

/// The identified model's (with its effects) held-out mean, mm.
fn identified_test_mean_mm(c: &Calibrated) -> f64 {
    c.report
        .stages
        .iter()
        .rev()
        .find(|s| matches!(s.kind, StageKind::Effect | StageKind::Identified))
        .expect("an identified stage")
        .test
        .mean_mm
}

#[test]
fn a_slip_carries_into_a_session_of_the_same_home_and_not_past_a_new_one() {
    let clean = identified_test_mean_mm(&calibrated(&[], true));
    for continuing in [true, false] {
        let c = calibrated(&[SLIP], continuing);
        let home = c.report.inputs.test.home.as_ref().expect("the test's home");
        assert_eq!(home.basis, HomeBasis::Clock);
        assert_eq!(home.shares_home(), continuing, "{}", home.reason);
        assert!(
            c.report.summary().contains(&home.reason),
            "the summary says which home it assumed"
        );
        let slips = crate::slips_of(&c.loop_result);
        assert!(
            slips
                .iter()
                .any(|&(s, _, mm)| s == 2 && (mm - 8.0).abs() < 1.0),
            "{slips:?}"
        );
        let after = identified_test_mean_mm(&c);
        assert!(
            after <= 1.3 * clean,
            "continuing {continuing}: held-out {after:.3} mm, clean device {clean:.3} mm"
        );
    }
}

/// The device's side: the calibration carries the training's slips and
/// its home capture when the training session records it (`home`), for
/// the device to apply while it stays under that capture; without a `home`
/// column it carries none (the model for the next home capture alone).
#[test]
fn the_calibration_carries_the_training_slips_under_its_home_capture() {
    use spidar_core::model::Effect;
    let home_id = CARRIED_HOME;
    let c = carried();
    let home = c.calibration.home.as_ref().expect("the training's slips");
    assert_eq!(home.home_id, home_id);
    assert!(
        home.slips.iter().any(|t| t.string == 2
            && matches!(t.effect, Effect::Slip { mm, .. } if (mm - 8.0).abs() < 1.0)),
        "{:?}",
        home.slips
    );
    assert!(
        !c.calibration
            .effects
            .iter()
            .any(|t| matches!(t.effect, Effect::Slip { .. })),
        "the effects stay the model for the next home capture"
    );
    let d = &c.report.device_slips;
    assert_eq!((d.home_id, &d.slips), (Some(home_id), &home.slips));
    assert!(c.report.summary().contains(&d.reason), "{}", d.reason);
    // The blob carries them, checked as the device checks it.
    let blob = spidar_core::blob::compile(&c.calibration, 1, 0).expect("compiles");
    let parsed = spidar_core::blob::CompiledCalibration::from_blob(&blob).expect("parses");
    let said = spidar::model::compile::describe_home_slips(&parsed).expect("flash says it");
    assert!(said.contains(&home_id.to_string()), "{said}");
    let carried = parsed.head.home.expect("in the blob");
    assert_eq!(
        (carried.home_id, carried.slips.len()),
        (home_id, home.slips.len())
    );

    let c = calibrated(&[SLIP], true);
    assert!(!crate::slips_of(&c.loop_result).is_empty());
    assert_eq!(c.calibration.home, None);
    let d = &c.report.device_slips;
    assert_eq!(d.home_id, None);
    assert!(d.reason.contains("`home`"), "{}", d.reason);
}

/// The drift families' findings the monitor would report on `rows` judged
/// with `calibration` as the device runs it under home capture `home_id`
/// (the monitor's rule: a drift family, large enough, explaining enough).
/// Findings, not the position error: forward kinematics leaves a string
/// 6 mm off out, so the position hardly shows it.
fn monitor_findings(
    device: &SimulatedDevice,
    calibration: &spidar_core::model::Calibration,
    rows: &spidar::data::dataset::Session,
    home_id: Option<u64>,
) -> Vec<spidar::model::diagnose::Finding> {
    use spidar::procedures::monitor::{identification_of, structure_of, under_home, MonitorConfig};
    let config = MonitorConfig::default();
    let c = under_home(calibration, home_id);
    let id = identification_of(&c, &device.nominal.mechanical_advantage);
    let obs = spidar::data::observe::observations(&rows.samples);
    spidar::model::diagnose::diagnose(
        &id,
        &obs,
        &device.nominal.nominal_frame(),
        &structure_of(&c),
        &config.loop_config,
    )
    .into_iter()
    .filter(|f| {
        config.drift_families.contains(&f.family)
            && f.amplitude_mm >= config.min_amplitude_mm
            && f.explained >= config.min_explained
    })
    .collect()
}

/// `spidar monitor` judges states as the device runs them: under the
/// calibration's home capture with the training's slips (a string slipped
/// in training is no drift; judged without it, it would read as one), after
/// a new capture without them (the string is counted as it is).
#[test]
fn the_monitor_judges_states_with_the_training_slips_only_under_their_home_capture() {
    use spidar_core::model::{Effect, HomeSlips};
    let home_id = 0x5eed_0000_0001;
    let mut config = SimConfig {
        effects: vec!["slip:2:at_s=0,mm=6".into()],
        ..SimConfig::default()
    };
    config.abnormal_motor.enabled = false;
    let slipped = SimulatedDevice::new(&config, 2).expect("device");
    // The same device, its strings counted as they are (a new home).
    let mut clean = slipped.clone();
    clean
        .effects
        .retain(|t| !matches!(t.effect, Effect::Slip { .. }));
    // The true calibration of the device before the slip, with the slip
    // carried under the training's home capture.
    let (slips, effects): (Vec<_>, Vec<_>) = slipped
        .effects
        .iter()
        .partition(|t| matches!(t.effect, Effect::Slip { .. }));
    assert_eq!(slips.len(), 1, "{slips:?}");
    let calibration = spidar_core::model::Calibration {
        frame: slipped.frame,
        strings: slipped.laws,
        effects,
        correction: spidar_core::correction::CorrectionModel::None,
        length_scale_mm: [0.0; spidar_core::STRINGS],
        kinematics: Default::default(),
        home: Some(HomeSlips { home_id, slips }),
    };
    let kind = SessionKind::Random { points: 400 };
    let under_training = simulate_session(&slipped, kind, 7).expect("states");
    let after_new_home = simulate_session(&clean, kind, 7).expect("states");
    let named = |f: &[spidar::model::diagnose::Finding]| f.iter().any(|f| f.strings == [2]);

    // Under the training's home capture: the slip is the model's, no drift.
    let found = monitor_findings(&slipped, &calibration, &under_training, Some(home_id));
    assert!(found.is_empty(), "{found:?}");
    // Without the slip (the calibration as it was before: effects alone)
    // the same states read as a drift on string 2.
    let found = monitor_findings(&slipped, &calibration, &under_training, None);
    assert!(named(&found), "{found:?}");

    // After a new home capture the string is counted as it is: the slip is
    // not applied, and nothing is found.
    let found = monitor_findings(&clean, &calibration, &after_new_home, Some(home_id + 1));
    assert!(found.is_empty(), "{found:?}");
    // The model judged is the device's: the slip only under its capture.
    let applied = |home| {
        spidar::procedures::monitor::under_home(&calibration, home)
            .effects
            .iter()
            .any(|t| matches!(t.effect, Effect::Slip { .. }))
    };
    assert!(applied(Some(home_id)));
    assert!(!applied(Some(home_id + 1)) && !applied(None));
}

/// `spidar compile --test` measures the blob against the f64 model as the
/// device runs it: the test rows under the blob's home capture (`home`)
/// with the training's slips on both sides, the rows after a new capture
/// without, so that the budget covers the home section's path too.
#[test]
fn the_fixed_point_error_covers_the_training_slips_under_their_home_capture() {
    use spidar::data::home::LaterHome;
    use spidar::data::observe::observations;
    use spidar::model::compile::{
        device_positions, fixed_point_error, run_compile, CompileRequest, FIXED_POINT_BUDGET_MM,
    };
    use spidar_core::blob::CompiledCalibration;
    let c = carried();
    assert!(c.calibration.home.is_some());
    let (_, _, mut test) = sessions_under(&[SLIP], true, Some(CARRIED_HOME));
    // The device is homed again at the test session's row 250.
    let rehomed = 250;
    let t0 = test.samples[rehomed].t_s;
    for row in &mut test.samples[rehomed..] {
        row.home = Some(CARRIED_HOME + 1);
        row.since_home_s = Some(row.t_s - t0);
    }
    let home = LaterHome::under(CARRIED_HOME, &test);
    assert_eq!(home.first_new_home_row, rehomed, "{}", home.reason);

    let blob = spidar_core::blob::compile(&c.calibration, 1, 0).expect("compiles");
    let parsed = CompiledCalibration::from_blob(&blob).expect("parses");
    let mut obs = observations(&test.samples);
    home.mark(&mut obs);
    let e = fixed_point_error(&c.calibration, &parsed, &obs).expect("rows");
    assert!(
        e.home_rows > rehomed * 9 / 10 && e.home_rows <= rehomed && e.rows > e.home_rows,
        "{e:?}"
    );
    assert!(e.corrected.mean_mm <= FIXED_POINT_BUDGET_MM, "{e:?}");
    // The rows under the capture took the slips' path: the device's
    // positions there are not those after a new capture, and the rows
    // after it are.
    let with = device_positions(&parsed, &obs, rehomed);
    let without = device_positions(&parsed, &obs, 0);
    let moved = |r: std::ops::Range<usize>| {
        r.filter(|&k| spidar_core::geometry::distance(with[k].0, without[k].0) > 1e-3)
            .count()
    };
    assert!(moved(0..rehomed) > rehomed / 2, "{}", moved(0..rehomed));
    assert_eq!(moved(rehomed + 20..obs.len()), 0);

    // The command says which rows it measured so, and why.
    let dir = std::env::temp_dir().join(format!("spidar-compile-home-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let calibration = dir.join("calibration.json");
    std::fs::write(&calibration, serde_json::to_string(&c.calibration).unwrap()).unwrap();
    let test_csv = dir.join("test.csv");
    test.write(&test_csv).unwrap();
    let report = run_compile(&CompileRequest {
        calibration,
        out: dir.join("model.bin"),
        test: Some(test_csv),
        geometry: None,
        model_id: None,
        budget_mm: FIXED_POINT_BUDGET_MM,
        write_over_budget: false,
    })
    .expect("compiles within the budget");
    assert_eq!(
        report.error.as_ref().map(|e| e.home_rows),
        Some(e.home_rows)
    );
    let text = report.to_string();
    eprintln!("{text}");
    assert!(
        text.contains(&format!(
            "({} with the training's slips, under their home capture)",
            e.home_rows
        )) && text.contains(&home.reason),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The lattice of `calibrated_under`'s device with a slip of string 2 at
/// `slip_at_s` of its clock, recorded as homed again at `rehome_at_s`: its
/// rows before under capture `CARRIED_HOME`, the rest under the next
/// (`since_home_s` from it), and the test session continuing the last. A
/// slip before the new capture is over after it (the strings are counted
/// from where they are): those rows are the clean device's.
fn calibrated_over_two_captures(slip_at_s: f64, rehome_at_s: f64) -> Calibrated {
    let slip = format!("slip:2:at_s={slip_at_s},mm=8");
    let (device, mut train, mut test) = sessions_under(&[&slip], true, Some(CARRIED_HOME));
    let (_, clean_train, clean_test) = sessions_under(&[], true, Some(CARRIED_HOME));
    let next = CARRIED_HOME + 1;
    for (row, clean) in train
        .samples
        .iter_mut()
        .zip(&clean_train.samples)
        .chain(test.samples.iter_mut().zip(&clean_test.samples))
    {
        assert_eq!((row.t_s, row.tracker), (clean.t_s, clean.tracker));
        if row.t_s >= rehome_at_s {
            row.home = Some(next);
            row.since_home_s = Some(row.t_s - rehome_at_s);
            if slip_at_s < rehome_at_s {
                row.counts = clean.counts;
            }
        }
    }
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    crate::calibrate_in_memory(&device.nominal, &train, &test, &cfg)
}

/// A training session homed again midway (issue 33 point 1, record 0049's
/// "Left"; the lattice runs from 16 to 4800 s): a slip after its last home
/// capture, later after it than any row of the earlier capture is after
/// its own, was fitted on the last capture's rows alone and is carried
/// under that capture; a slip of the earlier capture is over and is not
/// carried (the report says which and why).
#[test]
fn a_training_over_two_home_captures_carries_the_slips_of_its_last() {
    use spidar_core::model::Effect;
    let slip_of_8_mm = |t: &spidar_core::model::EffectTerm, since_s: f64| {
        t.string == 2
            && matches!(t.effect, Effect::Slip { at_s, mm }
                if (mm - 8.0).abs() < 1.0 && (at_s - since_s).abs() < 100.0)
    };
    // Homed again at 500 s: the slip, 1500 s after the new capture, is
    // later than any row of the first (500 s).
    let c = calibrated_over_two_captures(2000.0, 500.0);
    let d = &c.report.device_slips;
    eprintln!("{}", d.reason);
    assert_eq!(d.home_id, Some(CARRIED_HOME + 1), "{}", d.reason);
    assert!(d.not_carried.is_empty(), "{d:?}");
    assert!(d.slips.iter().any(|t| slip_of_8_mm(t, 1500.0)), "{d:?}");
    assert_eq!(c.calibration.home, d.home_slips());
    assert!(c.report.summary().contains(&d.reason));
    assert!(
        d.reason.contains("the last of the training session's 2"),
        "{}",
        d.reason
    );

    // A slip at 900 s, homed again at 4000 s: the slip is the first
    // capture's, and the last one's training rows (up to 800 s after it)
    // never reach its time since home.
    let c = calibrated_over_two_captures(900.0, 4000.0);
    let d = &c.report.device_slips;
    eprintln!("{}", d.reason);
    assert_eq!(
        (d.home_id, &c.calibration.home),
        (None, &None),
        "{}",
        d.reason
    );
    assert!(
        d.not_carried.iter().any(|t| slip_of_8_mm(t, 900.0)),
        "{d:?}"
    );
    assert!(
        d.reason
            .contains("a slip of an earlier capture, over with it"),
        "{}",
        d.reason
    );
    // The test session goes on under the last capture to 960 s after it:
    // judged with the earlier capture's slip, string 2 of its rows from
    // 900 s would be 8 mm off. They are judged as the device reads them.
    let late = c.test_rows.iter().filter(|o| o.t_s >= 4900.0).count();
    assert!(late > 100, "{late} test rows 900 s after the last capture");
    let clean = identified_test_mean_mm(&calibrated(&[], true));
    let after = identified_test_mean_mm(&c);
    assert!(
        after <= 1.3 * clean,
        "held-out {after:.3} mm, clean device {clean:.3} mm"
    );
}
