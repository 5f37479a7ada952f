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
//! With `--ablation`, only this: the clean independent device of seed 1
//! with one part of its physics switched off at a time (the identified and
//! final held-out error tell what each part costs the model).
//!
//! `cargo run --release -p spidar --example physics_bench -- [SEEDS] [--quick] [--no-analysis] [--ablation] [--only=SIM:EFFECT,..]`
//! (`--only=independent:slip,model:clean`: just those cases)
//! (default 3 seeds).

use std::path::Path;

use spidar::data::dataset::{Geometry, Session};
use spidar::data::observe::observations;
use spidar::data::stats::{position_error, ErrorStats};
use spidar::model::diagnose::{family_name, variable_name};
use spidar::model::identify::inputs_at;
use spidar::procedures::calibrate::{calibrate, CalibrateConfig, Calibrated, NamedSession};
use spidar::sim::physics::{self, PhysicsConfig, PhysicsDevice, PhysicsTruth};
use spidar::sim::{simulate_session, SessionKind, SimConfig, SimDevice};
use spidar_core::geometry::device_from_room;
use spidar_core::string_law::string_lengths_f64;
use spidar_core::STRINGS;

const TEST_POINTS: usize = 500;

struct Run {
    geometry: Geometry,
    train: Session,
    test: Session,
}

fn model_run(seed: u64, effect: Option<&str>) -> Run {
    let config = SimConfig {
        effects: effect.map(|e| vec![e.to_string()]).unwrap_or_default(),
        ..SimConfig::default()
    };
    let device = SimDevice::new(&config, seed).expect("model device");
    Run {
        geometry: device.nominal.clone(),
        train: simulate_session(&device, SessionKind::Lattice, seed + 1).expect("lattice"),
        test: simulate_session(
            &device,
            SessionKind::Random {
                points: TEST_POINTS,
            },
            seed + 2,
        )
        .expect("test"),
    }
}

fn physics_device(seed: u64, effect: Option<&str>) -> PhysicsDevice {
    let config = PhysicsConfig {
        effects: effect.map(|e| vec![e.to_string()]).unwrap_or_default(),
        ..PhysicsConfig::default()
    };
    PhysicsDevice::new(&config, seed).expect("independent device")
}

/// A run of `device` and the truths of its training and test sessions.
fn physics_run(device: &PhysicsDevice, seed: u64) -> (Run, Vec<PhysicsTruth>, Vec<PhysicsTruth>) {
    let (train, truths) =
        physics::simulate_session(device, SessionKind::Lattice, seed + 1).expect("lattice");
    let (test, test_truths) = physics::simulate_session(
        device,
        SessionKind::Random {
            points: TEST_POINTS,
        },
        seed + 2,
    )
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

fn run_calibration(run: &Run, config: &CalibrateConfig) -> Calibrated {
    calibrate(
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
    .expect("calibrate")
}

fn three(s: &ErrorStats) -> String {
    format!("{:.3} / {:.3} / {:.2}", s.mean_mm, s.p95_mm, s.max_mm)
}

/// One table row: the stages of one calibration, held-out.
fn print_row(simulator: &str, effect: &str, seed: u64, c: &Calibrated) -> (f64, f64, f64, f64) {
    let stages = &c.report.stages;
    let raw = &stages[0].test;
    let identified = &stages[1].test;
    let added: Vec<String> = stages
        .iter()
        .skip(2)
        .filter(|s| !matches!(s.name.as_str(), "nn" | "svr") && !s.name.starts_with("final"))
        .map(|s| format!("{} ({:.3})", s.name, s.test.mean_mm))
        .collect();
    let last = stages.last().expect("final stage");
    println!(
        "| {simulator} | {effect} | {seed} | {:.1} | {} | {} | {} | {} |",
        raw.mean_mm,
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
        let (run, _, _) = physics_run(&device, 1);
        let cal = run_calibration(&run, &config);
        let stages = &cal.report.stages;
        let added: Vec<&str> = stages
            .iter()
            .skip(2)
            .filter(|s| !matches!(s.name.as_str(), "nn" | "svr") && !s.name.starts_with("final"))
            .map(|s| s.name.as_str())
            .collect();
        let last = stages.last().expect("final stage");
        println!(
            "| {name} | {} | {} | {} | {} |",
            three(&stages[1].test),
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
}

impl Options {
    fn parse() -> Options {
        let mut o = Options {
            seeds: 3,
            quick: false,
            analysis: true,
            only: None,
            ablation: false,
        };
        for a in std::env::args().skip(1) {
            if let Some(list) = a.strip_prefix("--only=") {
                o.only = Some(list.split(',').map(str::to_string).collect());
                continue;
            }
            match a.as_str() {
                "--quick" => o.quick = true,
                "--no-analysis" => o.analysis = false,
                "--ablation" => o.ablation = true,
                s => o.seeds = s.parse().expect(
                    "usage: physics_bench [SEEDS] [--quick] [--no-analysis] [--only=SIM:EFFECT,..]",
                ),
            }
        }
        o
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

/// The model simulator's cases, one row per seed.
fn model_cases(options: &Options, config: &CalibrateConfig, summary: &mut Vec<CaseRows>) {
    for effect in [
        None,
        Some("drift:*:mm_per_s=0.0002"),
        Some("slip:3:at_s=2400,mm=5"),
    ] {
        if !options.wanted("model", effect) {
            continue;
        }
        let mut rows = Vec::new();
        for seed in 1..=options.seeds {
            let c = run_calibration(&model_run(seed, effect), config);
            rows.push(print_row("model", effect.unwrap_or("clean"), seed, &c));
        }
        summary.push(("model", effect.unwrap_or("clean"), rows));
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
        Some("frame-flex"),
        Some("marker-offset"),
        Some("slip"),
        Some("heavy-string"),
    ] {
        if !options.wanted("independent", effect) {
            continue;
        }
        let name = effect.unwrap_or("clean");
        let mut rows = Vec::new();
        for seed in 1..=options.seeds {
            let device = physics_device(seed, effect);
            let (run, truths, test_truths) = physics_run(&device, seed);
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
            rows.push(print_row("independent", name, seed, &c));
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
        let run = model_run(seed, None);
        let c = run_calibration(&run, config);
        let mut wide = SimConfig::default();
        wide.lattice.size_mm = 1200.0;
        let device = SimDevice::new(&wide, seed).expect("model device");
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

    println!(
        "held-out (test session, {TEST_POINTS} points) eq. 7 error, mm: mean / p95 / max; config {}",
        if options.quick { "quick" } else { "full" }
    );
    println!();
    println!("| simulator | effect | seed | raw mean | identified | added by the loop (test mean after) | final stage | final |");
    println!("|---|---|---:|---:|---|---|---|---|");
    let mut summary = Vec::new();
    let mut notes = Vec::new();
    model_cases(&options, &config, &mut summary);
    let clean_physics = physics_cases(&options, &config, &mut summary, &mut notes);
    print_summary(&summary, &notes);
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
