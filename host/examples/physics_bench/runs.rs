//! The runs: each case's device and sessions, on either simulator, and
//! their calibration.

use std::path::Path;

use spidar::data::dataset::{Geometry, Session};
use spidar::procedures::calibrate::{calibrate, CalibrateConfig, Calibrated, NamedSession};
use spidar::procedures::report_page::DeviceData;
use spidar::sim::physics::{self, PhysicsConfig, PhysicsDevice, PhysicsTruth};
use spidar::sim::{
    simulate_session, simulate_session_after, SessionKind, SimConfig, SimulatedDevice, StreamArea,
};

pub(super) const TEST_POINTS: usize = 500;

/// The `stream` cases' sessions: a training stream of the simulator's
/// default 6000 rows (60 s at 100 Hz) over the central part of the
/// workspace, a test stream of this many rows over the whole of it.
const STREAM_TEST_ROWS: usize = 3000;

/// The `stream-latency` case: 6 ms of encoder latency on two strings, as
/// issue 33's hidden simulator has it.
const STREAM_LATENCY: [&str; 2] = ["latency:string=2,ms=6", "latency:string=5,ms=6"];

pub(super) struct Run {
    pub(super) geometry: Geometry,
    pub(super) train: Session,
    pub(super) test: Session,
}

/// A run of the model simulator's device of `seed` with `effects`: its
/// lattice, and a random test session after a new home capture or, when
/// `continuing`, under the lattice's (its clock, drifts and slips go on).
pub(super) fn model_run(seed: u64, effects: &[&str], continuing: bool) -> Run {
    let config = SimConfig {
        effects: effects.iter().map(|e| e.to_string()).collect(),
        ..SimConfig::default()
    };
    let device = SimulatedDevice::new(&config, seed).expect("model device");
    let train = simulate_session(&device, SessionKind::Lattice, seed + 1).expect("lattice");
    let kind = SessionKind::Random {
        points: TEST_POINTS,
    };
    let test = if continuing {
        simulate_session_after(&device, kind, seed + 2, &train).map(|(s, _)| s)
    } else {
        simulate_session(&device, kind, seed + 2)
    }
    .expect("test");
    Run {
        geometry: device.nominal.clone(),
        train,
        test,
    }
}

/// The independent device of `seed` with `effect`: an undeclared effect
/// of the simulator, or its guide pulleys' radius set (`guides-12`: 12 mm
/// on every string, as issue 33's hidden simulator has them; `point-guides`:
/// 0.001 mm, the fixed anchors the model had before the guide family;
/// `drift-each-fast`: `drift-each` at three times its rates, 900 +- 600
/// ppm/h, about 1 mm a metre over the lattice's 80 minutes).
pub(super) fn physics_device(seed: u64, effect: Option<&str>) -> PhysicsDevice {
    let mut config = PhysicsConfig::default();
    match effect {
        Some("guides-12") => config.as_built.guide_radius_mm = [12.0, 12.0],
        Some("point-guides") => config.as_built.guide_radius_mm = [0.001, 0.001],
        Some("stream") => {}
        Some("drift-each-fast") => {
            config.effects = vec!["drift-each:ppm_per_h=900,spread_ppm_per_h=600".into()]
        }
        Some("stream-latency") => {
            config.effects = STREAM_LATENCY.iter().map(|e| e.to_string()).collect()
        }
        Some(e) => config.effects = vec![e.to_string()],
        None => {}
    }
    PhysicsDevice::new(&config, seed).expect("independent device")
}

/// How a case's sessions are made: the lattice and a random test session
/// after a new home capture, the same with the test session continuing the
/// training's home capture (its clock, slips and drift go on), or two
/// streams (the CLI's seeds: + 3 and + 4).
#[derive(Clone, Copy, PartialEq)]
pub(super) enum Sessions {
    Lattice,
    LatticeContinuing,
    Streams,
}

/// A run of `device` and the truths of its training and test sessions.
pub(super) fn physics_run(
    device: &PhysicsDevice,
    seed: u64,
    sessions: Sessions,
) -> (Run, Vec<PhysicsTruth>, Vec<PhysicsTruth>) {
    if sessions == Sessions::Streams {
        let stream = |rows, area, session_seed| {
            physics::simulate_session(device, SessionKind::Stream { rows, area }, session_seed)
                .expect("stream")
        };
        let (train, truths) = stream(device.config.stream.rows, StreamArea::Training, seed + 3);
        let (test, test_truths) = stream(STREAM_TEST_ROWS, StreamArea::Whole, seed + 4);
        let run = Run {
            geometry: device.nominal.clone(),
            train,
            test,
        };
        return (run, truths, test_truths);
    }
    let (train, truths) =
        physics::simulate_session(device, SessionKind::Lattice, seed + 1).expect("lattice");
    let kind = SessionKind::Random {
        points: TEST_POINTS,
    };
    let continuing = sessions == Sessions::LatticeContinuing;
    let (test, test_truths) = if continuing {
        let earlier = physics::EarlierSession {
            seed: seed + 1,
            end_s: train.samples.last().map_or(0.0, |s| s.t_s),
        };
        physics::simulate_session_after(device, kind, seed + 2, earlier)
    } else {
        physics::simulate_session(device, kind, seed + 2)
    }
    .expect("test");
    (
        Run {
            geometry: device.nominal.clone(),
            train,
            test,
        },
        truths,
        test_truths,
    )
}

/// The calibration of `run`; a line says so when the device cannot run it
/// as reported (it does not compile, its blob does not fit, or its fixed
/// point is over the budget on the test session).
pub(super) fn run_calibration(run: &Run, config: &CalibrateConfig) -> Calibrated {
    let c = calibrate(
        &run.geometry,
        Path::new("geometry.toml"),
        NamedSession {
            path: Path::new("lattice.csv"),
            session: &run.train,
        },
        NamedSession {
            path: Path::new("test.csv"),
            session: &run.test,
        },
        config,
    )
    .expect("calibrate");
    for w in DeviceData::of(&c).warnings() {
        println!("DEVICE: {w}");
    }
    c
}
