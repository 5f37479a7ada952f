//! What the tests share: a quiet device, `calibrate` of an independent
//! device's sessions, the diagnosis loop on one, and their checks.

use spidar::data::dataset::Session;
use spidar::procedures::calibrate::CalibrateConfig;
use spidar::sim::physics::{simulate_session, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;

pub(super) fn quiet_config() -> PhysicsConfig {
    let mut c = PhysicsConfig::default();
    c.abnormal_motor.enabled = false;
    c
}

/// `calibrate` (quick, quiet) of an independent device's two sessions.
pub(super) fn calibrate_quick(
    device: &PhysicsDevice,
    train: &spidar::data::dataset::Session,
    test: &spidar::data::dataset::Session,
) -> spidar::procedures::calibrate::Calibrated {
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    crate::calibrate_in_memory(&device.nominal, train, test, &cfg)
}

/// The diagnosis loop on a clean independent device (issue 10, point 6).
pub(super) fn clean_loop(seed: u64) -> spidar::model::diagnose::LoopResult {
    loop_on(seed, &[])
}

/// The diagnosis loop on an independent device with undeclared `effects`,
/// its lattice (session seed + 1) for training, 500 random points (+ 2) for
/// the test.
pub(super) fn loop_on(seed: u64, effects: &[&str]) -> spidar::model::diagnose::LoopResult {
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

pub(super) fn names(r: &spidar::model::diagnose::LoopResult) -> Vec<&str> {
    r.stages.iter().map(|s| s.name.as_str()).collect()
}

/// Device `seed` of `config`, its lattice (session seed + 1, with the
/// truth of each row) and a test session of `points` random points (+ 2),
/// as `spidar simulate` makes them.
pub(super) fn device_and_sessions(
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
pub(super) fn assert_final_test_below(
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
