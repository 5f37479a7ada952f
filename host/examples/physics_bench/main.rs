//! The calibration pipeline on both simulators, side by side: the model
//! simulator (`sim`, the model's own equations) and the independent one
//! (`sim::physics`, other physics). For each simulator, effect and seed:
//! simulate the device, its 13^3 lattice (training) and a 500-point random
//! test session (the CLI's seed rule: lattice seed + 1, test seed + 2), run
//! `calibrate` (the library function behind `spidar calibrate`, the full
//! procedure unless `--quick`) and print the held-out stage table (raw,
//! identified, each added effect, final: mean / p95 / max) and the effects
//! the loop added. Then, on the clean independent devices, what the
//! identified model misses: its string residuals against the variables of
//! the physics, and its error beyond the training volume.
//!
//! Then the `wall-robot` preset of the independent simulator (a planar
//! 4-cable wall robot: cables tied at the corners of a yawing carriage,
//! exits tens of mm off the frame's corners, a tracker clock 1.8 s ahead):
//! a 60 s training stream over the central part of its workspace (the
//! CLI's seed rule: + 3), a 60 s test stream over the whole of it (+ 4),
//! `calibrate`'s stage table, and beside it a plain least-squares fit made
//! here, outside the project's model: anchors (in the plane), each
//! string's effective radius, home and the tracker's transform (yaw and
//! in-plane translation) fitted unweighted to the string lengths, no
//! priors, no robust weights, then every test row placed by all four
//! strings equally weighted. Both sessions' rows are paired by the clock
//! offset (and drift) the calibration's report found. The floor the
//! project's model is compared with.
//!
//! Then the `hangprinter` preset (a Hangprinter-like 3-D robot: lines
//! through pulley blocks, layered spools, anchors tens of mm off the
//! tape's, a camera whose scatter has heavy tails, static poses): per seed, training sessions
//! of 12 to 31 poses against one 300-pose test session, the reference,
//! identified and final stages held out.
//!
//! With `--ablation`, only this: the clean independent device of seed 1
//! with one part of its physics switched off at a time (the identified and
//! final held-out error tell what each part costs the model).
//!
//! `cargo run --release -p spidar --example physics_bench -- [SEEDS] [--quick] [--no-analysis] [--ablation] [--no-forward] [--only=SIM:EFFECT,..] [--write=DIR]`
//! (`--write=DIR`: each case's geometry and sessions in
//! `DIR/SIM-EFFECT-SEED/`, which `spidar calibrate` reproduces the row from)
//! (`--no-forward`: drifts judged without forward chaining, to measure it;
//! an effect `NAME-continuing`, e.g. `slip-continuing`: the test session
//! continues the training's home capture instead of following a new one)
//! (`--only=independent:slip,model:clean`: just those cases; the model
//! simulator's: `clean`, `drift` (every string alike), `slip`, and
//! `drift-each` (every string its own rate around a shared one),
//! `drift-mixed` (rates of either sign), with `-continuing` forms;
//! `--only=independent:drift-each-fast`: every string creeping at its own
//! rate, 900 +- 600 ppm/h, three times `drift-each`'s (and its
//! `-continuing` form);
//! `--only=independent:guides-12,independent:point-guides`: the guide
//! pulleys at 12 mm on every string, and at 0.001 mm;
//! `--only=independent:stream,independent:stream-latency`: a 6000-row
//! training stream and a 3000-row test stream of the clean device, and of
//! the device with 6 ms of encoder latency on strings 2 and 5;
//! `--only=independent:wall-robot`: the wall robot alone;
//! `--only=independent:hangprinter`: the Hangprinter-like robot alone)
//! (default 3 seeds).

mod ablation;
mod analysis;
mod cases;
mod hangprinter;
mod notes;
mod options;
mod runs;
mod table;
mod wall_robot;

use ablation::ablation;
use analysis::{print_extrapolation, residual_analysis};
use cases::{model_cases, physics_cases};
use hangprinter::hangprinter;
use options::Options;
use runs::TEST_POINTS;
use spidar::procedures::calibrate::CalibrateConfig;
use table::print_summary;
use wall_robot::wall_robot;

fn main() {
    let options = Options::parse();
    if options.ablation {
        ablation(options.quick);
        return;
    }
    let mut config = if options.quick {
        CalibrateConfig::quick()
    } else {
        CalibrateConfig::full()
    };
    config.quiet = true;
    config.loop_config.time_terms_forward = !options.no_forward;

    println!(
        "held-out (test session, {TEST_POINTS} points) eq. 7 error, mm: mean / p95 / max; config {}",
        if options.quick { "quick" } else { "full" }
    );
    println!();
    println!("| simulator | effect | seed | raw mean | plain least squares | identified | added by the loop (test mean after) | final stage | final |");
    println!("|---|---|---:|---:|---|---|---|---|---|");
    let mut summary = Vec::new();
    let mut notes = Vec::new();
    model_cases(&options, &config, &mut summary);
    let clean_physics = physics_cases(&options, &config, &mut summary, &mut notes);
    print_summary(&summary, &notes);
    if options.wanted("independent", Some("wall-robot")) {
        wall_robot(options.seeds, &config);
    }
    if options.wanted("independent", Some("hangprinter")) {
        hangprinter(options.seeds, &config);
    }
    if !options.analysis {
        return;
    }
    for (device, run, truths, c) in &clean_physics {
        println!();
        println!(
            "string residuals of the identified model (final loop model, no correction), clean independent device seed {}, training lattice: rms and spread of 8 quantile-bin means, mm",
            device.seed
        );
        println!();
        residual_analysis(device, run, truths, c);
    }
    print_extrapolation(options.seeds, &config, &clean_physics);
}
