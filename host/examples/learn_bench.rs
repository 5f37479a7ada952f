//! Timings and accuracies of the learned corrections on the synthetic field
//! (13^3 lattice over a 1 m cube for training, 500 random test points, 0.2 mm
//! tracker noise).
//!
//! ```text
//! cargo run --release -p spidar --example learn_bench -- [--quiet] [--long]
//!     [--amplitude A] [--csv DIR] [--json FILE]
//! ```
//! `--csv DIR` writes DIR/train.csv and DIR/test.csv for
//! `scripts/reference/reference.py`; `--long` adds a 1000-epoch H = 20 run
//! (the notes' 9.4 s reference) and the SVR without shrinking.

use std::time::Instant;

use spidar::model::learn::nn::{self, LmConfig, NnConfig};
use spidar::model::learn::search::{self, SvrSearchConfig, SweepConfig};
use spidar::model::learn::svr::{self, SolverConfig, SvrConfig, SvrParams};
use spidar::model::learn::{synthetic, ErrorStats, OutputMode};

/// Process CPU seconds (user + system) from /proc, to tell contention from
/// work on a shared machine; None where /proc is missing.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let fields: Vec<&str> = stat.rsplit(')').next()?.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

fn cpu_since(c0: Option<f64>) -> String {
    match (c0, cpu_seconds()) {
        (Some(a), Some(b)) => format!("{:.2} s CPU", b - a),
        _ => "CPU n/a".into(),
    }
}

fn line(name: &str, s: &ErrorStats) {
    println!(
        "  {name:<28} mean {:7.3} mm  sd {:7.3}  max {:8.3}  (n = {})",
        s.mean_mm, s.sd_mm, s.max_mm, s.n
    );
}

/// The synthetic sessions and what every part of the bench shares.
struct Bench {
    train: synthetic::Dataset,
    test: synthetic::Dataset,
    quiet: bool,
    /// The figures `--json` writes.
    json: serde_json::Map<String, serde_json::Value>,
}

/// SVR at the notes' reference point; returns its fit seconds.
fn svr_reference(b: &mut Bench) -> f64 {
    let (train, test, quiet, json) = (&b.train, &b.test, b.quiet, &mut b.json);
    println!("\nSVR C = 100, gamma = 1/3, epsilon = 0.01 (standardized), tol 1e-3:");
    let cfg = SvrConfig {
        quiet,
        ..SvrConfig::default()
    };
    let c0 = cpu_seconds();
    let fit = svr::train(&train.inputs, &train.targets, &cfg).expect("svr");
    println!("  ({})", cpu_since(c0));
    let t = search::evaluate(|p| svr::predict(&fit.model, p), &test.inputs, &test.targets);
    println!(
        "  fit {:.3} s (kernel {:.3} s), support vectors {} (union), per axis {:?}, iterations {:?}, converged {:?}",
        fit.seconds,
        fit.kernel_seconds,
        fit.model.support.len(),
        fit.axes.map(|a| a.support_vectors),
        fit.axes.map(|a| a.iterations),
        fit.axes.map(|a| a.converged),
    );
    line("SVR train", &fit.train);
    line("SVR test", &t);
    json.insert("svr_fit_s".into(), fit.seconds.into());
    json.insert("svr_test_mean_mm".into(), t.mean_mm.into());
    fit.seconds
}

/// `--long`: the reference fit without shrinking, and with epsilon 0.003.
fn svr_variants(b: &Bench) {
    let (train, test) = (&b.train, &b.test);
    let cfg = SvrConfig {
        solver: SolverConfig {
            shrinking: false,
            ..SolverConfig::default()
        },
        ..SvrConfig::default()
    };
    let fit = svr::train(&train.inputs, &train.targets, &cfg).expect("svr");
    let t = search::evaluate(|p| svr::predict(&fit.model, p), &test.inputs, &test.targets);
    println!(
        "  without shrinking: fit {:.3} s, iterations {:?}, test mean {:.3} mm",
        fit.seconds,
        fit.axes.map(|a| a.iterations),
        t.mean_mm
    );
    let cfg = SvrConfig {
        params: SvrParams {
            epsilon: 0.003,
            ..SvrConfig::default().params
        },
        ..SvrConfig::default()
    };
    let fit = svr::train(&train.inputs, &train.targets, &cfg).expect("svr");
    let t = search::evaluate(|p| svr::predict(&fit.model, p), &test.inputs, &test.targets);
    println!(
        "  epsilon 0.003: fit {:.3} s, SVs {:?}, test mean {:.3} mm",
        fit.seconds,
        fit.axes.map(|a| a.support_vectors),
        t.mean_mm
    );
}

/// Residual mode (on top of a kinematic model; here the raw position).
fn svr_residual(b: &Bench) {
    let (train, test) = (&b.train, &b.test);
    let cfg = SvrConfig {
        mode: OutputMode::Residual,
        params: SvrParams {
            epsilon: 0.05,
            ..SvrConfig::default().params
        },
        ..SvrConfig::default()
    };
    let fit = svr::train(&train.inputs, &train.targets, &cfg).expect("svr");
    let t = search::evaluate(|p| svr::predict(&fit.model, p), &test.inputs, &test.targets);
    println!(
        "  residual mode, epsilon 0.05: fit {:.3} s, SVs {}, iterations {:?}",
        fit.seconds,
        fit.model.support.len(),
        fit.axes.map(|a| a.iterations)
    );
    line("SVR residual test", &t);
}

/// NN: hidden-size sweep 3..=24 then the chosen size trained longer; returns
/// the sweep's and the final training's seconds.
fn nn_sweep(b: &mut Bench) -> f64 {
    let (train, test, quiet, json) = (&b.train, &b.test, b.quiet, &mut b.json);
    let sweep_cfg = SweepConfig {
        quiet,
        ..SweepConfig::default()
    };
    println!(
        "\nNN sweep H = 3..=24, {} epochs x {} restart(s) each, then {} epochs x {} candidates:",
        sweep_cfg.sweep_lm.max_epochs,
        sweep_cfg.sweep_restarts,
        sweep_cfg.final_lm.max_epochs,
        sweep_cfg.final_restarts
    );
    let c0 = cpu_seconds();
    let sweep = search::nn_sweep(&train.inputs, &train.targets, &sweep_cfg).expect("sweep");
    println!("  ({} for sweep + final)", cpu_since(c0));
    for p in &sweep.curve {
        println!(
            "    H = {:2}: validation mean {:7.3} mm, train mean {:7.3} mm, {:3} epochs ({:?})",
            p.hidden, p.validation_mean_mm, p.train_mean_mm, p.epochs, p.stop
        );
    }
    let t = search::evaluate(
        |p| nn::predict(&sweep.fit.model, p),
        &test.inputs,
        &test.targets,
    );
    println!(
        "  best H = {}, sweep {:.3} s, final {:.3} s ({} epochs, {:?})",
        sweep.best_hidden,
        sweep.sweep_seconds,
        sweep.final_seconds,
        sweep.fit.epochs,
        sweep.fit.stop
    );
    line("NN validation", &sweep.fit.validation);
    line("NN test", &t);
    json.insert("nn_sweep_s".into(), sweep.sweep_seconds.into());
    json.insert("nn_final_s".into(), sweep.final_seconds.into());
    json.insert("nn_best_hidden".into(), sweep.best_hidden.into());
    json.insert("nn_test_mean_mm".into(), t.mean_mm.into());
    sweep.sweep_seconds + sweep.final_seconds
}

/// SVR hyperparameter search (hold-out) and refit; returns their seconds.
fn svr_search(b: &mut Bench) -> f64 {
    let (train, test, quiet, json) = (&b.train, &b.test, b.quiet, &mut b.json);
    let scfg = SvrSearchConfig {
        quiet,
        ..SvrSearchConfig::default()
    };
    println!(
        "\nSVR search C {:?} x epsilon {:?} x gamma {:?}, {:?}:",
        scfg.c, scfg.epsilon, scfg.gamma, scfg.validation
    );
    let c0 = cpu_seconds();
    let s = search::svr_search(&train.inputs, &train.targets, &scfg).expect("search");
    println!("  ({} for search + refit)", cpu_since(c0));
    for c in &s.candidates {
        println!(
            "    C {:6.1} eps {:.3} gamma {:.2}: validation {:>8} mm, SVs {:4}, {:.3} s",
            c.params.c,
            c.params.epsilon,
            c.params.gamma,
            c.validation_mean_mm
                .map_or("-".to_string(), |v| format!("{v:.3}")),
            c.support_vectors,
            c.seconds
        );
    }
    let t = search::evaluate(
        |p| svr::predict(&s.fit.model, p),
        &test.inputs,
        &test.targets,
    );
    println!(
        "  best {:?}: search {:.3} s, refit {:.3} s",
        s.best, s.search_seconds, s.refit_seconds
    );
    line("SVR (searched) test", &t);
    json.insert("svr_search_s".into(), s.search_seconds.into());
    json.insert("svr_refit_s".into(), s.refit_seconds.into());
    json.insert("svr_searched_test_mean_mm".into(), t.mean_mm.into());

    s.search_seconds + s.refit_seconds
}

/// `--long`: a 20-neuron network trained 1000 epochs without early stop.
fn nn_long(b: &Bench) {
    let (train, test, quiet) = (&b.train, &b.test, b.quiet);
    let t0 = Instant::now();
    let cfg = NnConfig {
        hidden: 20,
        restarts: 1,
        lm: LmConfig {
            max_epochs: 1000,
            max_fail: 1000,
            ..LmConfig::default()
        },
        mode: OutputMode::Absolute,
        quiet,
        ..NnConfig::default()
    };
    let fit = nn::train(&train.inputs, &train.targets, &cfg).expect("nn");
    let t = search::evaluate(|p| nn::predict(&fit.model, p), &test.inputs, &test.targets);
    println!(
        "\nNN H = 20, up to 1000 epochs, no early stop: {:.2} s, {} epochs ({:?}), {:.2} ms/epoch, test mean {:.3} mm",
        t0.elapsed().as_secs_f64(),
        fit.epochs,
        fit.stop,
        1000.0 * fit.seconds / fit.epochs.max(1) as f64,
        t.mean_mm
    );
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let flag = |f: &str| args.iter().any(|a| a == f);
    let value = |f: &str| {
        args.iter()
            .position(|a| a == f)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let quiet = flag("--quiet");
    let amplitude: f64 = value("--amplitude")
        .and_then(|v| v.parse().ok())
        .unwrap_or(1.0);
    let train = synthetic::lattice(13, 500.0, amplitude, 0.2, 11);
    let test = synthetic::random(500, 500.0, amplitude, 0.2, 12);
    if let Some(dir) = value("--csv") {
        std::fs::create_dir_all(&dir).expect("create csv dir");
        std::fs::write(format!("{dir}/train.csv"), train.to_csv()).expect("write train.csv");
        std::fs::write(format!("{dir}/test.csv"), test.to_csv()).expect("write test.csv");
        println!("wrote {dir}/train.csv and {dir}/test.csv");
    }
    println!(
        "synthetic field x{amplitude}: {} train (lattice), {} test (random), rayon threads {}",
        train.inputs.len(),
        test.inputs.len(),
        rayon::current_num_threads()
    );
    line(
        "raw (train)",
        &ErrorStats::between(&train.inputs, &train.targets),
    );
    line(
        "raw (test)",
        &ErrorStats::between(&test.inputs, &test.targets),
    );
    let mut bench = Bench {
        train,
        test,
        quiet,
        json: serde_json::Map::new(),
    };
    let svr_fixed_s = svr_reference(&mut bench);
    if flag("--long") {
        svr_variants(&bench);
    }
    svr_residual(&bench);
    let nn_s = nn_sweep(&mut bench);
    let search_s = svr_search(&mut bench);
    println!(
        "\ntotals: NN sweep+final {:.2} s; + SVR fixed {:.2} s = {:.2} s; + SVR search+refit {:.2} s = {:.2} s",
        nn_s,
        svr_fixed_s,
        nn_s + svr_fixed_s,
        search_s,
        nn_s + search_s
    );
    if flag("--long") {
        nn_long(&bench);
    }
    if let Some(path) = value("--json") {
        std::fs::write(&path, serde_json::Value::Object(bench.json).to_string())
            .expect("write json");
    }
}
