//! The host library's model side on recorded and simulated sessions: the
//! dataset reader, the identification, the learned corrections, the loop
//! that finds effects (on both simulators), devices of 3 to 8 strings. One
//! test binary (issue 14, point 7: a few links, not twelve).

mod creep;
mod dataset;
mod device_way;
mod guide;
mod home_epochs;
mod identify;
mod latency;
mod learn;
mod loop_closing;
mod loop_rows;
mod n_strings;
mod sim;
mod sim_hangprinter;
mod sim_physics;
mod sim_physics_real_robot;
mod time_before_tables;
mod whole_device_first;

/// The names of `r`'s stages, in order (time_before_tables,
/// whole_device_first).
fn stage_names(r: &spidar::model::diagnose::LoopResult) -> Vec<&str> {
    r.stages.iter().map(|s| s.name.as_str()).collect()
}

/// The test session's mean error of `r`'s last model (time_before_tables,
/// whole_device_first).
fn last_test_mean(r: &spidar::model::diagnose::LoopResult) -> f64 {
    r.stages
        .last()
        .and_then(|s| s.test.as_ref())
        .or(r.base_test.as_ref())
        .map(|t| t.mean_mm)
        .expect("a test session")
}

/// The slips of `r`'s model: (string, time, mm), in the model's order
/// (sim_physics, loop_closing).
fn slips_of(r: &spidar::model::diagnose::LoopResult) -> Vec<(u8, f64, f64)> {
    use spidar_core::model::Effect;
    r.identification
        .effects
        .iter()
        .filter_map(|t| match t.effect {
            Effect::Slip { at_s, mm } => Some((t.string, at_s, mm)),
            _ => None,
        })
        .collect()
}

/// Runs the loop on a model-simulator device of `seed` with `effects`
/// injected (its lattice and a 500-point test session); returns the result
/// and the held-out (test session) mean error of the final model
/// (loop_closing, guide, creep).
fn lattice_loop(seed: u64, effects: &[&str]) -> (spidar::model::diagnose::LoopResult, f64) {
    let (device, train, test) =
        spidar::sim::device_with_lattice_and_test(seed, effects, 500).expect("simulated sessions");
    loop_on(&device.nominal, &train, &test)
}

/// The findings `result` added: family, strings and variable (guide,
/// creep).
fn added(
    result: &spidar::model::diagnose::LoopResult,
) -> Vec<(
    spidar::model::diagnose::Family,
    Vec<u8>,
    spidar::model::diagnose::Variable,
)> {
    result
        .findings
        .iter()
        .filter(|f| f.added)
        .map(|f| (f.family, f.strings.clone(), f.variable))
        .collect()
}

/// The loop on the observations of `train` (held out: `test`) of a device
/// of `geometry`: its result and the test session's mean error after it
/// (loop_closing, latency).
fn loop_on(
    geometry: &spidar::data::dataset::Geometry,
    train: &spidar::data::dataset::Session,
    test: &spidar::data::dataset::Session,
) -> (spidar::model::diagnose::LoopResult, f64) {
    use spidar::data::observe::observations;
    use spidar::model::diagnose::{close_loop, LoopConfig};
    use spidar::model::identify::Start;
    let train = observations(&train.samples);
    let test = observations(&test.samples);
    let result = close_loop(
        &train,
        Some(&test),
        &geometry.nominal_frame(),
        &Start::from_geometry(geometry),
        &LoopConfig::for_geometry(geometry),
    )
    .expect("loop");
    let after = result
        .stages
        .last()
        .and_then(|s| s.test)
        .or(result.base_test)
        .expect("test stats")
        .mean_mm;
    (result, after)
}

/// A calibration of two sessions held in memory, named `train.csv` and
/// `test.csv` beside a `geometry.toml` as the command line would read them
/// (learn, loop_rows).
fn calibrate_in_memory(
    geometry: &spidar::data::dataset::Geometry,
    train: &spidar::data::dataset::Session,
    test: &spidar::data::dataset::Session,
    cfg: &spidar::procedures::calibrate::CalibrateConfig,
) -> spidar::procedures::calibrate::Calibrated {
    use spidar::procedures::calibrate::{calibrate, NamedSession};
    use std::path::Path;
    calibrate(
        geometry,
        Path::new("geometry.toml"),
        NamedSession {
            path: Path::new("train.csv"),
            session: train,
        },
        NamedSession {
            path: Path::new("test.csv"),
            session: test,
        },
        cfg,
    )
    .expect("calibrate")
}
