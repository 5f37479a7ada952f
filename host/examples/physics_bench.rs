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
//! `--only=independent:wall-robot`: the wall robot alone)
//! (default 3 seeds).

use std::path::Path;

use spidar::data::dataset::{Geometry, Session};
use spidar::data::observe::observations;
use spidar::data::observe::Observation;
use spidar::data::stats::{position_error, ErrorStats};
use spidar::model::diagnose::{family_name, variable_name, Family};
use spidar::model::identify::inputs_at;
use spidar::model::validate::{later_session_errors, model_errors};
use spidar::procedures::calibrate::align::{repaired_at, tracked_interval_s, SessionTiming};
use spidar::procedures::calibrate::report::{Stage, StageKind};
use spidar::procedures::calibrate::{calibrate, CalibrateConfig, Calibrated, NamedSession};
use spidar::procedures::report_page::DeviceData;
use spidar::sim::physics::{self, PhysicsConfig, PhysicsDevice, PhysicsTruth};
use spidar::sim::{
    simulate_session, simulate_session_after, SessionKind, SimConfig, SimulatedDevice, StreamArea,
};
use spidar_core::geometry::device_from_room;
use spidar_core::model::{Effect, EVERY_STRING};
use spidar_core::string_law::string_lengths_f64;
use spidar_core::STRINGS;

const TEST_POINTS: usize = 500;

/// The `stream` cases' sessions: a training stream of the simulator's
/// default 6000 rows (60 s at 100 Hz) over the central part of the
/// workspace, a test stream of this many rows over the whole of it.
const STREAM_TEST_ROWS: usize = 3000;

/// The `stream-latency` case: 6 ms of encoder latency on two strings, as
/// issue 33's hidden simulator has it.
const STREAM_LATENCY: [&str; 2] = ["latency:string=2,ms=6", "latency:string=5,ms=6"];

struct Run {
    geometry: Geometry,
    train: Session,
    test: Session,
}

/// A run of the model simulator's device of `seed` with `effects`: its
/// lattice, and a random test session after a new home capture or, when
/// `continuing`, under the lattice's (its clock, drifts and slips go on).
fn model_run(seed: u64, effects: &[&str], continuing: bool) -> Run {
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
fn physics_device(seed: u64, effect: Option<&str>) -> PhysicsDevice {
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
enum Sessions {
    Lattice,
    LatticeContinuing,
    Streams,
}

/// A run of `device` and the truths of its training and test sessions.
fn physics_run(
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

/// The slips of a session from its truths: (row, string, mm) of each step
/// (each string starts unslipped at home).
fn slip_steps(truths: &[PhysicsTruth]) -> Vec<(usize, usize, f64)> {
    let mut steps = Vec::new();
    let mut before: Vec<f64> = Vec::new();
    for (row, t) in truths.iter().enumerate() {
        before.resize(t.slipped_mm.len(), 0.0);
        for (i, (a, b)) in before.iter().zip(&t.slipped_mm).enumerate() {
            if a != b {
                steps.push((row, i, ((b - a) * 100.0).round() / 100.0));
            }
        }
        before.clone_from(&t.slipped_mm);
    }
    steps
}

/// The test session's own slips (a calibration made before them cannot
/// know them) and the final model's test error before and after the first.
fn test_session_slips(test_truths: &[PhysicsTruth], c: &Calibrated) -> Option<String> {
    let steps = slip_steps(test_truths);
    let first = steps.first()?.0;
    let fin = c
        .points
        .iter()
        .rev()
        .find(|p| p.name.starts_with("final"))
        .or(c.points.last())?;
    let (mut before, mut after) = (Vec::new(), Vec::new());
    for (&row, &e) in fin.test.rows.iter().zip(&fin.test.errors) {
        if row < first {
            before.push(e)
        } else {
            after.push(e)
        }
    }
    let (before, after) = (ErrorStats::of(&before), ErrorStats::of(&after));
    Some(format!(
        "the test session slipped (row, string, mm) {steps:?} of {} rows: final test mean \
         {:.3} mm on the {} rows before its first slip, {:.3} mm on the {} after",
        test_truths.len(),
        before.mean_mm,
        before.n,
        after.mean_mm,
        after.n
    ))
}

/// The identified model's (with its effects) held-out mean on a test
/// session of the training's home, judged with the training session's
/// slips (as the calibration now does) and without them (as if the test
/// followed a new home capture, the rule before sessions knew their home).
fn home_judged(c: &Calibrated) -> String {
    let id = &c.loop_result.identification;
    let with_slips = later_session_errors(id, &c.test_rows).mean_mm;
    let without = model_errors(&id.for_a_new_session(), &c.test_rows).mean_mm;
    format!(
        "test session of the training's home ({}): identified with effects {with_slips:.3} mm \
         judged with the training's slips, {without:.3} mm judged as after a new home capture",
        c.report
            .inputs
            .test
            .home
            .as_ref()
            .map_or("?", |h| if h.shares_home() {
                "shared"
            } else {
                "not shared"
            })
    )
}

/// On a device whose strings creep (`drift-all`): the creep terms of the
/// final model against the strings' thermal strain per second (a shared
/// one names that physics within 2x of it), or why the loop added none;
/// `None` on a device without creep.
fn creep_against_truth(device: &PhysicsDevice, c: &Calibrated) -> Option<String> {
    let truth = device.creep_per_s();
    if truth == 0.0 {
        return None;
    }
    let found: Vec<String> = c
        .loop_result
        .identification
        .effects
        .iter()
        .filter_map(|t| match t.effect {
            Effect::Creep { per_s } if t.string == EVERY_STRING => {
                Some(format!("every string x{:.2}", per_s / truth))
            }
            Effect::Creep { per_s } => Some(format!("string {} x{:.2}", t.string, per_s / truth)),
            _ => None,
        })
        .collect();
    let truth_ppm_h = truth * 3.6e9;
    if !found.is_empty() {
        return Some(format!(
            "creep (size / the strings' {truth_ppm_h:.0} ppm/h): {}",
            found.join(", ")
        ));
    }
    let why: Vec<String> = c
        .report
        .effects
        .iter()
        .filter(|f| f.family == Family::Creep)
        .map(|f| {
            format!(
                "{:?}: {}",
                f.strings,
                f.validation.as_ref().map_or_else(
                    // Why it was not tested, when the finding says.
                    || match f.description.find("not proposed:") {
                        Some(k) => &f.description[k..],
                        None => "not tested",
                    },
                    |v| v.reason.as_str(),
                )
            )
        })
        .collect();
    Some(format!(
        "no creep term (the strings creep {truth_ppm_h:.0} ppm/h); proposed: {}",
        if why.is_empty() {
            "none".to_string()
        } else {
            why.join("; ")
        }
    ))
}

/// The calibration of `run`; a line says so when the device cannot run it
/// as reported (it does not compile, its blob does not fit, or its fixed
/// point is over the budget on the test session).
fn run_calibration(run: &Run, config: &CalibrateConfig) -> Calibrated {
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

fn three(s: &ErrorStats) -> String {
    format!("{:.3} / {:.3} / {:.2}", s.mean_mm, s.p95_mm, s.max_mm)
}

/// The first stage of `kind` (every calibration has a reference, an
/// identified and a final stage).
fn stage_of(c: &Calibrated, kind: StageKind) -> &Stage {
    c.report
        .stages
        .iter()
        .find(|s| s.kind == kind)
        .expect("a stage of every calibration")
}

/// One table row: the stages of one calibration, held-out.
fn print_row(simulator: &str, effect: &str, seed: u64, c: &Calibrated) -> (f64, f64, f64, f64) {
    let stages = &c.report.stages;
    let raw = &stages[0].test;
    let identified = &stage_of(c, StageKind::Identified).test;
    let reference = &stage_of(c, StageKind::Reference).test;
    let added: Vec<String> = stages
        .iter()
        .filter(|s| s.kind == StageKind::Effect)
        .map(|s| format!("{} ({:.3})", s.name, s.test.mean_mm))
        .collect();
    let last = stages.last().expect("final stage");
    println!(
        "| {simulator} | {effect} | {seed} | {:.1} | {} | {} | {} | {} | {} |",
        raw.mean_mm,
        three(reference),
        three(identified),
        if added.is_empty() {
            "none".to_string()
        } else {
            added.join(", ")
        },
        last.name,
        three(&last.test)
    );
    (
        identified.mean_mm,
        last.test.mean_mm,
        last.test.p95_mm,
        last.test.max_mm,
    )
}

/// The loop's findings that were not added (significant but no help, or
/// unexplained), one line.
fn not_added(c: &Calibrated) -> String {
    c.report
        .effects
        .iter()
        .filter(|f| !f.added)
        .map(|f| {
            format!(
                "{} {:?} vs {} ({:.0} %)",
                family_name(f.family),
                f.strings,
                variable_name(f.variable),
                100.0 * f.explained
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

/// Spread (max - min) of the bin means of `r` in 8 quantile bins of `x`.
fn bin_spread(x: &[f64], r: &[f64]) -> f64 {
    let mut idx: Vec<usize> = (0..x.len()).collect();
    idx.sort_by(|&a, &b| x[a].total_cmp(&x[b]));
    let bins = 8;
    let means: Vec<f64> = (0..bins)
        .map(|b| {
            let part = &idx[b * idx.len() / bins..(b + 1) * idx.len() / bins];
            part.iter().map(|&i| r[i]).sum::<f64>() / part.len().max(1) as f64
        })
        .collect();
    means.iter().cloned().fold(f64::MIN, f64::max) - means.iter().cloned().fold(f64::MAX, f64::min)
}

/// String residuals of the final identified model (no correction) on the
/// training lattice, against the physics' own variables.
fn residual_analysis(device: &PhysicsDevice, run: &Run, truths: &[PhysicsTruth], c: &Calibrated) {
    let cal = &c.calibration;
    let obs = observations(&run.train.samples);
    println!(
        "| string | rms | vs payout | vs layer phase | vs tension | vs free length | vs exit travel | vs time | arc + sag range |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for i in 0..STRINGS {
        let (mut r, mut payout, mut phase, mut tension, mut free, mut exit, mut time, mut sag) = (
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
        );
        let spool = device.spool(i);
        let changes = spool.layer_changes_rad();
        let home_exit = truths[0].exit_mm[i];
        for (o, t) in obs.iter().zip(truths) {
            let Some(tracker) = o.tracker else { continue };
            if t.abnormal {
                continue;
            }
            let p = device_from_room(&cal.frame, tracker);
            let inputs = inputs_at(&cal.frame, o, &p);
            let lengths = string_lengths_f64(&cal.frame, &cal.strings, &cal.effects, &inputs);
            let a = cal.frame.anchors[i];
            let geometric = position_error(p, a);
            let res = geometric - lengths[i];
            if res.abs() > 25.0 {
                continue; // gross (the abnormal motor)
            }
            r.push(res);
            payout.push(f64::from(o.inputs.counts[i]));
            // Where in its layer the spool is: 0 at a layer change, 1 at the next.
            let phi = t.spool_rad[i];
            let k = changes.partition_point(|c| *c <= phi);
            let lo = if k == 0 { 0.0 } else { changes[k - 1] };
            let hi = changes.get(k).copied().unwrap_or(spool.max_angle_rad());
            phase.push((phi - lo) / (hi - lo));
            tension.push(o.tension_n[i]);
            free.push(t.free_mm[i]);
            exit.push(position_error(t.exit_mm[i], home_exit));
            time.push(o.t_s);
            let chord = t.free_mm[i];
            sag.push(t.geometric_mm[i] - chord);
        }
        let rms = (r.iter().map(|x| x * x).sum::<f64>() / r.len() as f64).sqrt();
        let sag_range = sag.iter().cloned().fold(f64::MIN, f64::max)
            - sag.iter().cloned().fold(f64::MAX, f64::min);
        println!(
            "| {i} | {rms:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.1} |",
            bin_spread(&payout, &r),
            bin_spread(&phase, &r),
            bin_spread(&tension, &r),
            bin_spread(&free, &r),
            bin_spread(&exit, &r),
            bin_spread(&time, &r),
            sag_range
        );
    }
}

/// Error of the final model on random points of a 1.2 m cube around the
/// 1 m training lattice: inside the training cube and outside it.
fn extrapolation(
    c: &Calibrated,
    test: &Session,
    centre: [f64; 3],
    half: f64,
) -> (ErrorStats, ErrorStats) {
    let cal = &c.calibration;
    let obs = observations(&test.samples);
    let model = spidar::model::predict::KinematicModel::of(cal);
    let predicted = spidar::model::predict::predict(model, &obs);
    let (mut inside, mut outside) = (vec![], vec![]);
    for (o, p) in obs.iter().zip(&predicted) {
        let Some(t) = o.tracker else { continue };
        let room = cal.correction.evaluate(p.room);
        let e = position_error(room, t);
        if (0..3).all(|k| (t[k] - centre[k]).abs() <= half) {
            inside.push(e);
        } else {
            outside.push(e);
        }
    }
    (ErrorStats::of(&inside), ErrorStats::of(&outside))
}

/// The clean independent device of seed 1 with one part of its physics
/// switched off at a time.
fn ablation(quick: bool) {
    let mut config = if quick {
        CalibrateConfig::quick()
    } else {
        CalibrateConfig::full()
    };
    config.quiet = true;
    type Switch = fn(&mut PhysicsConfig);
    let parts: [(&str, Switch); 10] = [
        ("all physics (clean device)", |_| {}),
        ("no abnormal motor", |c| c.abnormal_motor.enabled = false),
        ("point guides (rho 0.001 mm)", |c| {
            c.as_built.guide_radius_mm = [0.001, 0.001]
        }),
        (
            "near-continuous spool (1.5 turns a layer, no cross-over)",
            |c| {
                c.as_built.spool_width_mm = [0.75, 0.75];
                c.as_built.crossover_rise_mm = [0.0, 0.0];
            },
        ),
        ("no cross-over only", |c| {
            c.as_built.crossover_rise_mm = [0.0, 0.0]
        }),
        ("rigid strings (EA 1e9 N)", |c| {
            c.as_built.string_stiffness_n = [1e9, 1e9]
        }),
        ("weightless strings (no sag)", |c| {
            c.as_built.string_mass_g_per_m = [0.0, 0.0]
        }),
        ("rigid frame", |c| {
            c.as_built.frame_compliance_mm_per_n = [0.0, 0.0]
        }),
        ("marker at the meeting point", |c| {
            c.as_built.marker_offset_mm = [0.0, 0.0]
        }),
        ("everything above off", |c| {
            c.abnormal_motor.enabled = false;
            c.as_built.guide_radius_mm = [0.001, 0.001];
            c.as_built.spool_width_mm = [0.75, 0.75];
            c.as_built.crossover_rise_mm = [0.0, 0.0];
            c.as_built.string_stiffness_n = [1e9, 1e9];
            c.as_built.string_mass_g_per_m = [0.0, 0.0];
            c.as_built.frame_compliance_mm_per_n = [0.0, 0.0];
            c.as_built.marker_offset_mm = [0.0, 0.0];
        }),
    ];
    println!(
        "ablation, independent device seed 1, held-out mean / p95 / max, mm; config {}",
        if quick { "quick" } else { "full" }
    );
    println!();
    println!("| physics | identified | added by the loop | final stage | final |");
    println!("|---|---|---|---|---|");
    for (name, switch) in parts {
        let mut c = PhysicsConfig::default();
        switch(&mut c);
        let device = PhysicsDevice::new(&c, 1).expect("independent device");
        let (run, _, _) = physics_run(&device, 1, Sessions::Lattice);
        let cal = run_calibration(&run, &config);
        let stages = &cal.report.stages;
        let added: Vec<&str> = stages
            .iter()
            .filter(|s| s.kind == StageKind::Effect)
            .map(|s| s.name.as_str())
            .collect();
        let last = stages.last().expect("final stage");
        println!(
            "| {name} | {} | {} | {} | {} |",
            three(&stage_of(&cal, StageKind::Identified).test),
            if added.is_empty() {
                "none".to_string()
            } else {
                added.join(", ")
            },
            last.name,
            three(&last.test)
        );
    }
}

/// What the command line asked for.
struct Options {
    seeds: u64,
    quick: bool,
    analysis: bool,
    /// `--only=independent:slip,model:clean`: just these cases.
    only: Option<Vec<String>>,
    ablation: bool,
    /// `--no-forward`: drifts judged on the blocked folds alone (to
    /// measure what forward chaining does).
    no_forward: bool,
    /// `--write=DIR`: each case's geometry and sessions written to
    /// `DIR/SIM-EFFECT-SEED/`, for `spidar calibrate` to reproduce a row.
    write: Option<std::path::PathBuf>,
}

impl Options {
    fn parse() -> Options {
        let mut o = Options {
            seeds: 3,
            quick: false,
            analysis: true,
            only: None,
            ablation: false,
            no_forward: false,
            write: None,
        };
        for a in std::env::args().skip(1) {
            if let Some(list) = a.strip_prefix("--only=") {
                o.only = Some(list.split(',').map(str::to_string).collect());
                continue;
            }
            if let Some(dir) = a.strip_prefix("--write=") {
                o.write = Some(dir.into());
                continue;
            }
            match a.as_str() {
                "--quick" => o.quick = true,
                "--no-analysis" => o.analysis = false,
                "--ablation" => o.ablation = true,
                "--no-forward" => o.no_forward = true,
                s => {
                    o.seeds = s.parse().expect(
                        "usage: physics_bench [SEEDS] [--quick] [--no-analysis] [--no-forward] \
                     [--only=SIM:EFFECT,..] [--write=DIR]",
                    )
                }
            }
        }
        o
    }

    /// Writes `run`'s geometry and sessions to `--write`'s
    /// `DIR/SIMULATOR-EFFECT-SEED/` (`geometry.toml`, `train.csv`,
    /// `test.csv`), when asked for.
    fn write_run(&self, simulator: &str, effect: &str, seed: u64, run: &Run) {
        let Some(dir) = &self.write else { return };
        let dir = dir.join(format!("{simulator}-{effect}-{seed}"));
        std::fs::create_dir_all(&dir).expect("--write: the case's folder");
        run.geometry
            .write(dir.join("geometry.toml"))
            .expect("--write: geometry");
        run.train
            .write(dir.join("train.csv"))
            .expect("--write: training session");
        run.test
            .write(dir.join("test.csv"))
            .expect("--write: test session");
    }

    /// Whether the case `simulator:effect` is to run.
    fn wanted(&self, simulator: &str, effect: Option<&str>) -> bool {
        self.only.as_ref().is_none_or(|o| {
            o.iter()
                .any(|c| *c == format!("{simulator}:{}", effect.unwrap_or("clean")))
        })
    }
}

/// The final-test figures of one case's seeds, for the summary table.
type CaseRows = (&'static str, &'static str, Vec<(f64, f64, f64, f64)>);

/// A clean independent device with its lattice run, truths and calibration,
/// for the analysis after the tables.
type CleanPhysics = (PhysicsDevice, Run, Vec<PhysicsTruth>, Calibrated);

/// The model simulator's `drift-each` case: every string drifts at its
/// own rate around a shared one (0.0004-0.0008 mm/s), as issue 33's hidden
/// simulator's strings do (its shared drift took most, a string's own
/// took the rest).
const DRIFT_EACH: [&str; 8] = [
    "drift:0:mm_per_s=0.0006",
    "drift:1:mm_per_s=0.0004",
    "drift:2:mm_per_s=0.0008",
    "drift:3:mm_per_s=0.0005",
    "drift:4:mm_per_s=0.0007",
    "drift:5:mm_per_s=0.0004",
    "drift:6:mm_per_s=0.0006",
    "drift:7:mm_per_s=0.0008",
];

/// The `drift-mixed` case: rates of either sign, -0.0005 to 0.0012 mm/s.
const DRIFT_MIXED: [&str; 8] = [
    "drift:0:mm_per_s=0.0008",
    "drift:1:mm_per_s=-0.0005",
    "drift:2:mm_per_s=0.0012",
    "drift:3:mm_per_s=0.0003",
    "drift:4:mm_per_s=0.0009",
    "drift:5:mm_per_s=-0.0002",
    "drift:6:mm_per_s=0.0006",
    "drift:7:mm_per_s=0.001",
];

/// The model simulator's cases, one row per seed: (name, injected
/// effects); a name ending in `-continuing` has its test session continue
/// the lattice's home (its clock, drifts and slips go on into it).
fn model_cases(options: &Options, config: &CalibrateConfig, summary: &mut Vec<CaseRows>) {
    let drift: &[&str] = &["drift:*:mm_per_s=0.0002"];
    let slip: &[&str] = &["slip:3:at_s=2400,mm=5"];
    for (name, effects) in [
        ("clean", &[][..]),
        ("drift", drift),
        ("drift-continuing", drift),
        ("slip", slip),
        ("slip-continuing", slip),
        ("drift-each", &DRIFT_EACH[..]),
        ("drift-each-continuing", &DRIFT_EACH[..]),
        ("drift-mixed-continuing", &DRIFT_MIXED[..]),
    ] {
        if !options.wanted("model", (name != "clean").then_some(name)) {
            continue;
        }
        let continuing = name.ends_with("-continuing");
        let mut rows = Vec::new();
        for seed in 1..=options.seeds {
            let run = model_run(seed, effects, continuing);
            options.write_run("model", name, seed, &run);
            let c = run_calibration(&run, config);
            rows.push(print_row("model", name, seed, &c));
        }
        summary.push(("model", name, rows));
    }
}

/// The independent simulator's cases, one row per seed; what the loop left
/// out and where sessions slipped go to `notes`.
fn physics_cases(
    options: &Options,
    config: &CalibrateConfig,
    summary: &mut Vec<CaseRows>,
    notes: &mut Vec<String>,
) -> Vec<CleanPhysics> {
    let mut clean_physics = Vec::new();
    for effect in [
        None,
        Some("drift-all"),
        // The test session continuing the training's home: the drift goes
        // on into it.
        Some("drift-all-continuing"),
        // Every string creeping at its own rate (100-500 ppm/h), and the
        // same with the test session continuing the training's home.
        Some("drift-each"),
        Some("drift-each-continuing"),
        // The same at three times the rates (900 +- 600 ppm/h).
        Some("drift-each-fast"),
        Some("drift-each-fast-continuing"),
        Some("frame-flex"),
        Some("marker-offset"),
        Some("slip"),
        // The same slips, the test session continuing the training's home.
        Some("slip-continuing"),
        Some("heavy-string"),
        // Guide pulleys of 12 mm on every string, and of none (the clean
        // device's are 6-12 mm).
        Some("guides-12"),
        Some("point-guides"),
        // Streams (100 Hz) of the clean device, and with 6 ms of encoder
        // latency on two strings.
        Some("stream"),
        Some("stream-latency"),
    ] {
        if !options.wanted("independent", effect) {
            continue;
        }
        let name = effect.unwrap_or("clean");
        let continuing = effect.is_some_and(|e| e.ends_with("-continuing"));
        let sessions = if continuing {
            Sessions::LatticeContinuing
        } else if effect.is_some_and(|e| e.starts_with("stream")) {
            Sessions::Streams
        } else {
            Sessions::Lattice
        };
        let mut rows = Vec::new();
        for seed in 1..=options.seeds {
            let device = physics_device(seed, effect.map(|e| e.trim_end_matches("-continuing")));
            let (run, truths, test_truths) = physics_run(&device, seed, sessions);
            options.write_run("independent", name, seed, &run);
            let c = run_calibration(&run, config);
            let steps = slip_steps(&truths);
            if !steps.is_empty() {
                notes.push(format!(
                    "independent {name} seed {seed}: the lattice slipped (row, string, mm) {steps:?} of {} rows",
                    truths.len()
                ));
            }
            if let Some(slips) = test_session_slips(&test_truths, &c) {
                notes.push(format!("independent {name} seed {seed}: {slips}"));
            }
            if continuing {
                notes.push(format!(
                    "independent {name} seed {seed}: {}",
                    home_judged(&c)
                ));
            }
            rows.push(print_row("independent", name, seed, &c));
            if let Some(creep) = creep_against_truth(&device, &c) {
                notes.push(format!("independent {name} seed {seed}: {creep}"));
            }
            let n = not_added(&c);
            if !n.is_empty() {
                notes.push(format!("independent {name} seed {seed}: {n}"));
            }
            if effect.is_none() {
                clean_physics.push((device, run, truths, c));
            }
        }
        summary.push(("independent", name, rows));
    }
    clean_physics
}

/// The averages of every case, and the notes.
fn print_summary(summary: &[CaseRows], notes: &[String]) {
    println!();
    println!("| simulator | effect | identified mean (avg) | final mean (avg) | final p95 (worst) | final max (worst) |");
    println!("|---|---|---:|---:|---:|---:|");
    for (sim, effect, rows) in summary {
        let n = rows.len() as f64;
        println!(
            "| {sim} | {effect} | {:.3} | {:.3} | {:.3} | {:.2} |",
            rows.iter().map(|r| r.0).sum::<f64>() / n,
            rows.iter().map(|r| r.1).sum::<f64>() / n,
            rows.iter().map(|r| r.2).fold(0.0, f64::max),
            rows.iter().map(|r| r.3).fold(0.0, f64::max),
        );
    }
    println!();
    println!("significant but not added, and unexplained (independent simulator):");
    for n in notes {
        println!("- {n}");
    }
}

/// Trained on the 1 m lattice, tested on a 1.2 m cube: the error inside and
/// outside the training volume, on both simulators.
fn print_extrapolation(seeds: u64, config: &CalibrateConfig, clean_physics: &[CleanPhysics]) {
    println!();
    println!("extrapolation: trained on the 1 m lattice, tested on 500 random points of a 1.2 m cube (final model)");
    println!();
    println!("| simulator | seed | inside the training cube: mean / p95 / max (n) | outside: mean / p95 / max (n) |");
    println!("|---|---:|---|---|");
    for seed in 1..=seeds {
        // Model simulator.
        let run = model_run(seed, &[], false);
        let c = run_calibration(&run, config);
        let mut wide = SimConfig::default();
        wide.lattice.size_mm = 1200.0;
        let device = SimulatedDevice::new(&wide, seed).expect("model device");
        let test = simulate_session(
            &device,
            SessionKind::Random {
                points: TEST_POINTS,
            },
            seed + 2,
        )
        .expect("wide test");
        let centre = device.volume_centre_room();
        let (i, o) = extrapolation(&c, &test, centre, 500.0);
        println!(
            "| model | {seed} | {} ({}) | {} ({}) |",
            three(&i),
            i.n,
            three(&o),
            o.n
        );
    }
    for (device, _, _, c) in clean_physics {
        let mut wide = device.clone();
        wide.config.lattice.size_mm = 1200.0;
        let (test, _) = physics::simulate_session(
            &wide,
            SessionKind::Random {
                points: TEST_POINTS,
            },
            device.seed + 2,
        )
        .expect("wide test");
        let centre = device.volume_centre_room();
        let (i, o) = extrapolation(c, &test, centre, 500.0);
        println!(
            "| independent | {} | {} ({}) | {} ({}) |",
            device.seed,
            three(&i),
            i.n,
            three(&o),
            o.n
        );
    }
}

/// The wall robot's parameters in a plain least-squares fit: per string
/// the anchor (x, y) and the effective radius, then home (x, y) and the
/// tracker's yaw and translation (x, y): `p_room = R(yaw) p + t` in the plane.
struct PlainModel {
    anchors: Vec<[f64; 2]>,
    radii: Vec<f64>,
    home: [f64; 2],
    yaw: f64,
    translation: [f64; 2],
}

impl PlainModel {
    fn of(x: &[f64], n: usize) -> PlainModel {
        PlainModel {
            anchors: (0..n).map(|i| [x[2 * i], x[2 * i + 1]]).collect(),
            radii: x[2 * n..3 * n].to_vec(),
            home: [x[3 * n], x[3 * n + 1]],
            yaw: x[3 * n + 2],
            translation: [x[3 * n + 3], x[3 * n + 4]],
        }
    }

    /// The device-plane position of a room position.
    fn device_of(&self, room: &[f64; 3]) -> [f64; 2] {
        let (s, c) = self.yaw.sin_cos();
        let (dx, dy) = (room[0] - self.translation[0], room[1] - self.translation[1]);
        [c * dx + s * dy, -s * dx + c * dy]
    }

    fn room_of(&self, p: &[f64; 2], plane_z: f64) -> [f64; 3] {
        let (s, c) = self.yaw.sin_cos();
        [
            c * p[0] - s * p[1] + self.translation[0],
            s * p[0] + c * p[1] + self.translation[1],
            plane_z,
        ]
    }

    /// String `i`'s length from its counts: home length + radius x angle.
    fn length(&self, i: usize, counts: i32, counts_per_rev: u32) -> f64 {
        let theta = std::f64::consts::TAU * f64::from(counts) / f64::from(counts_per_rev);
        distance2(&self.home, &self.anchors[i]) + self.radii[i] * theta
    }
}

fn distance2(a: &[f64; 2], b: &[f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// The rows of `session` paired as the calibration paired them (its
/// report's offset and drift for that session), the tracker's z put in the
/// device's plane as the calibration does (the errors are in the plane).
fn paired_rows(session: &Session, timing: &SessionTiming, plane_z: f64) -> Vec<Observation> {
    let obs = observations(&session.samples);
    let mut rows = match timing {
        SessionTiming::Aligned(a) => {
            let gap = 4.0 * tracked_interval_s(&obs).unwrap_or(0.1);
            let at = |t: f64| t + a.offset_s + 1e-6 * a.drift_ppm * (t - a.reference_t_s);
            repaired_at(&obs, at, gap).0
        }
        SessionTiming::Static { .. } => obs,
    };
    for o in rows.iter_mut() {
        if let Some(t) = o.tracker.as_mut() {
            t[2] = plane_z;
        }
    }
    rows
}

/// Every string's residual (tracker geometry minus counts' length) of every
/// tracked row.
fn plain_residuals(x: &[f64], rows: &[Observation], n: usize, cpr: &[u32]) -> Vec<f64> {
    let m = PlainModel::of(x, n);
    let mut r = Vec::with_capacity(rows.len() * n);
    for o in rows {
        let Some(t) = o.tracker else { continue };
        let p = m.device_of(&t);
        for (i, (anchor, &c)) in m.anchors.iter().zip(cpr).enumerate() {
            r.push(distance2(&p, anchor) - m.length(i, o.inputs.counts[i], c));
        }
    }
    r
}

/// Unweighted Levenberg-Marquardt on the string residuals, numeric
/// Jacobian; `held` parameters stay at their start (the plane's rigid
/// motions, which the tracker's transform undoes: anchor 0's x, y and
/// anchor 1's y).
fn plain_fit(
    start: Vec<f64>,
    held: &[usize],
    rows: &[Observation],
    n: usize,
    cpr: &[u32],
) -> Vec<f64> {
    use nalgebra::{DMatrix, DVector};
    let free: Vec<usize> = (0..start.len()).filter(|k| !held.contains(k)).collect();
    let cost = |x: &[f64]| {
        plain_residuals(x, rows, n, cpr)
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
    };
    let mut x = start;
    let mut c = cost(&x);
    let mut lambda = 1e-3;
    for _ in 0..200 {
        let r = DVector::from_vec(plain_residuals(&x, rows, n, cpr));
        let mut j = DMatrix::zeros(r.len(), free.len());
        for (col, &k) in free.iter().enumerate() {
            let h = 1e-6 * x[k].abs().max(1.0);
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[k] += h;
            xm[k] -= h;
            let d = DVector::from_vec(plain_residuals(&xp, rows, n, cpr))
                - DVector::from_vec(plain_residuals(&xm, rows, n, cpr));
            j.set_column(col, &(d / (2.0 * h)));
        }
        let jtj = j.transpose() * &j;
        let g = j.transpose() * &r;
        let mut improved = false;
        while lambda < 1e12 {
            let mut a = jtj.clone();
            for k in 0..free.len() {
                a[(k, k)] += lambda * jtj[(k, k)].max(1e-12);
            }
            let Some(step) = a.lu().solve(&(-&g)) else {
                lambda *= 10.0;
                continue;
            };
            let mut trial = x.clone();
            for (col, &k) in free.iter().enumerate() {
                trial[k] += step[col];
            }
            let ct = cost(&trial);
            if ct < c {
                let settled = (c - ct) <= 1e-12 * c;
                x = trial;
                c = ct;
                lambda = (lambda / 10.0).max(1e-9);
                improved = !settled;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    x
}

/// Forward kinematics of the plain model: every tracked row placed by all
/// strings equally weighted (Gauss-Newton in the plane from the previous
/// row's position); its error against the tracker, mm.
fn plain_errors(m: &PlainModel, rows: &[Observation], cpr: &[u32], plane_z: f64) -> Vec<f64> {
    let n = m.anchors.len();
    let mut p = m.home;
    let mut errors = Vec::new();
    for o in rows {
        let lengths: Vec<f64> = (0..n)
            .map(|i| m.length(i, o.inputs.counts[i], cpr[i]))
            .collect();
        for _ in 0..50 {
            let (mut a, mut b) = ([[0.0; 2]; 2], [0.0; 2]);
            for (anchor, length) in m.anchors.iter().zip(&lengths) {
                let d = [p[0] - anchor[0], p[1] - anchor[1]];
                let l = d[0].hypot(d[1]);
                let u = [d[0] / l, d[1] / l];
                let r = l - length;
                for (row, u_row) in a.iter_mut().zip(u) {
                    row[0] += u_row * u[0];
                    row[1] += u_row * u[1];
                }
                b[0] += u[0] * r;
                b[1] += u[1] * r;
            }
            let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
            let dx = -(a[1][1] * b[0] - a[0][1] * b[1]) / det;
            let dy = -(-a[1][0] * b[0] + a[0][0] * b[1]) / det;
            p = [p[0] + dx, p[1] + dy];
            if dx.hypot(dy) < 1e-9 {
                break;
            }
        }
        if let Some(t) = o.tracker {
            errors.push(position_error(m.room_of(&p, plane_z), t));
        }
    }
    errors
}

/// The wall robot: `calibrate`'s stage table, and the plain least-squares
/// fit's held-out error beside it.
fn wall_robot(seeds: u64, config: &CalibrateConfig) {
    let preset = PhysicsConfig::preset("wall-robot").expect("the wall-robot preset");
    let rows = preset.stream.rows;
    println!();
    println!(
        "wall robot (preset `wall-robot`): train a {rows}-row stream over the central {:.0} % of \
         each side of the workspace (seed + 3), test a {rows}-row stream over the whole of it \
         (seed + 4); tracker clock {} s ahead; held-out mean / p95 / max, mm",
        100.0 * preset.stream.training_span,
        preset.tracker.clock_offset_s
    );
    for seed in 1..=seeds {
        let device = PhysicsDevice::new(&preset, seed).expect("wall robot");
        let stream = |area, session_seed| {
            physics::simulate_session(&device, SessionKind::Stream { rows, area }, session_seed)
                .expect("stream")
                .0
        };
        let run = Run {
            geometry: device.nominal.clone(),
            train: stream(StreamArea::Training, seed + 3),
            test: stream(StreamArea::Whole, seed + 4),
        };
        let c = run_calibration(&run, config);
        let offset = |t: &SessionTiming| match t {
            SessionTiming::Aligned(a) => {
                format!("{:+.4} s (sd {:.1} ms)", a.offset_s, 1e3 * a.offset_sd_s)
            }
            SessionTiming::Static { .. } => "static".to_string(),
        };
        println!();
        println!(
            "seed {seed}: clock offset found, train {}, test {}",
            offset(&c.report.timing.train),
            offset(&c.report.timing.test)
        );
        println!();
        println!("| stage | train mean / p95 / max | held-out mean / p95 / max |");
        println!("|---|---|---|");
        for s in &c.report.stages {
            println!("| {} | {} | {} |", s.name, three(&s.train), three(&s.test));
        }

        let n = device.string_count();
        let nominal = device.nominal.nominal_frame();
        let plane_z = nominal.room_translation[2] + nominal.anchors[0][2];
        let cpr = device.nominal.counts_per_rev[..n].to_vec();
        let train = paired_rows(&run.train, &c.report.timing.train, plane_z);
        let test = paired_rows(&run.test, &c.report.timing.test, plane_z);
        let g = &device.nominal;
        let mut start: Vec<f64> = (0..n)
            .flat_map(|i| [g.anchors_mm[i][0], g.anchors_mm[i][1]])
            .collect();
        start.extend((0..n).map(|i| g.pulley_radius_mm[i]));
        start.extend([g.home_mm[0], g.home_mm[1], 0.0]);
        start.extend([
            g.room_from_device_translation_mm[0],
            g.room_from_device_translation_mm[1],
        ]);
        let x = plain_fit(start, &[0, 1, 3], &train, n, &cpr);
        let m = PlainModel::of(&x, n);
        let fit = ErrorStats::of(&plain_errors(&m, &train, &cpr, plane_z));
        let held_out = ErrorStats::of(&plain_errors(&m, &test, &cpr, plane_z));
        println!(
            "| plain least squares (this bench) | {} | {} |",
            three(&fit),
            three(&held_out)
        );
        println!();
        println!(
            "plain fit: radii {} mm (nominal {} mm); rows train {} / test {} (paired by the \
             report's offsets)",
            m.radii
                .iter()
                .map(|r| format!("{r:.3}"))
                .collect::<Vec<_>>()
                .join(", "),
            g.pulley_radius_mm[0],
            fit.n,
            held_out.n
        );
        let last = c.report.stages.last().expect("final stage");
        println!(
            "{} / plain held-out mean: {:.2}x",
            last.name,
            last.test.mean_mm / held_out.mean_mm
        );
    }
}

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
