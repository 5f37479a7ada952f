//! Sessions in time (issue 33, point 1): a slip found in the training
//! session is still in a test session of the same home capture, and gone
//! from one after a new home capture. The calibration tells which from the
//! sessions (here their clocks: the continuing test session's `t_s` goes
//! on from the training's, the re-homed one's starts again) and judges the
//! test session with the slips of its home.

use spidar::data::home::HomeBasis;
use spidar::procedures::calibrate::report::StageKind;
use spidar::procedures::calibrate::{CalibrateConfig, Calibrated};
use spidar::sim::{
    simulate_session, simulate_session_after, SessionKind, SimConfig, SimulatedDevice,
};

const SLIP: &str = "slip:2:at_s=2000,mm=8";

fn calibrated(effects: &[&str], continuing: bool) -> Calibrated {
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
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    crate::calibrate_in_memory(&device.nominal, &train, &test, &cfg)
}

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
