//! Where the black-box SVR search spends its time (issue 15, point 2): on the
//! pairs `spidar calibrate --export-pairs DIR` writes, every candidate of the
//! paper grid on the seeded 20 % hold-out, one axis at a time on one thread,
//! with iterations, seconds and seconds per iteration; then the whole
//! `svr_search` as `calibrate --blackbox` runs it, and its test error.
//!
//! ```text
//! cargo run --release -p spidar --example blackbox_profile -- DIR [--tol T] [--plain] [--two-n] [--search-only] [--one G,C,E,AXIS] [--warm G,AXIS]
//! ```

use std::time::Instant;

use spidar::model::learn::search::{self, SvrSearchConfig};
use spidar::model::learn::svr::{self, KernelMatrix, SolverConfig};
use spidar::model::learn::{split_indices, standardize, Deadline, ErrorStats, OutputMode};

fn read_pairs(path: &str) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let mut x = Vec::new();
    let mut t = Vec::new();
    for line in text.lines().skip(1) {
        let v: Vec<f64> = line
            .split(',')
            .map(|s| s.parse().expect("number"))
            .collect();
        x.push([v[0], v[1], v[2]]);
        t.push([v[3], v[4], v[5]]);
    }
    (x, t)
}

/// The pairs and the search settings every part reads.
struct Profile {
    x: Vec<[f64; 3]>,
    t: Vec<[f64; 3]>,
    cfg: SvrSearchConfig,
}

/// Every candidate of the grid on the seeded hold-out, one axis at a time
/// (`--one G,C,E,AXIS`: that fit only).
// The axis index picks a coordinate of every target, not an element of one list.
#[allow(clippy::needless_range_loop)]
fn profile_grid(p: &Profile, one: Option<Vec<f64>>) {
    let (x, t, cfg) = (p.x.as_slice(), p.t.as_slice(), &p.cfg);
    let (tr, _va) = split_indices(x.len(), 0.2, cfg.seed);
    let input = standardize::fit("in", x).unwrap();
    let output = standardize::fit("out", t).unwrap();
    let xs = standardize::apply_all(&input, x);
    let ys = standardize::apply_all(&output, t);
    let xtr: Vec<[f64; 3]> = tr.iter().map(|&i| xs[i]).collect();
    println!("| gamma | C | eps | axis | iterations | s | us/iter | SV | bounded SV |");
    println!("|---|---|---|---|---:|---:|---:|---:|---:|");
    for &gamma in &cfg.gamma {
        if one.as_ref().is_some_and(|o| o[0] != gamma) {
            continue;
        }
        let t0 = Instant::now();
        let k = KernelMatrix::rbf(&xtr, gamma, 16_000).unwrap();
        println!("kernel gamma {gamma}: {:.3} s", t0.elapsed().as_secs_f64());
        for &c in &cfg.c {
            for &eps in &cfg.epsilon {
                for a in 0..3 {
                    if one
                        .as_ref()
                        .is_some_and(|o| o[1] != c || o[2] != eps || o[3] != a as f64)
                    {
                        continue;
                    }
                    let z: Vec<f64> = tr.iter().map(|&i| ys[i][a]).collect();
                    let t0 = Instant::now();
                    let s = svr::solve_epsilon_svr(&k, &z, c, eps, &cfg.solver, Deadline::none())
                        .unwrap();
                    let sec = t0.elapsed().as_secs_f64();

                    println!(
                        "| {gamma} | {c} | {eps} | {a} | {} | {sec:.2} | {:.2} | {} | {} |",
                        s.iterations,
                        sec / s.iterations.max(1) as f64 * 1e6,
                        s.support_vectors,
                        s.bounded_support_vectors
                    );
                }
            }
        }
    }
}

/// `--warm G,AXIS`: the chain C 30 -> 300 and eps 0.01 -> 0.005, warm
/// starts unscaled and scaled by the C ratio.
fn warm_chains(p: &Profile, spec: &str) {
    let (x, t, cfg) = (p.x.as_slice(), p.t.as_slice(), &p.cfg);
    let v: Vec<f64> = spec.split(',').map(|x| x.parse().unwrap()).collect();
    let (gamma, a) = (v[0], v[1] as usize);
    let (tr, _va) = split_indices(x.len(), 0.2, cfg.seed);
    let input = standardize::fit("in", x).unwrap();
    let output = standardize::fit("out", t).unwrap();
    let xs = standardize::apply_all(&input, x);
    let ys = standardize::apply_all(&output, t);
    let k = KernelMatrix::rbf(&xs, gamma, 16_000).unwrap();
    let z: Vec<f64> = tr.iter().map(|&i| ys[i][a]).collect();
    let run = |c: f64, eps: f64, warm: Option<&[f64]>, what: &str| {
        let t0 = Instant::now();
        let s = svr::solve(
            &svr::Problem {
                kernel: &k,
                points: &tr,
                z: &z,
                c,
                epsilon: eps,
                warm,
            },
            &cfg.solver,
            Deadline::none(),
        )
        .unwrap();
        println!(
            "C {c} eps {eps} {what}: {} iterations, {:.2} s, obj {:.6}, SV {} bounded {}",
            s.iterations,
            t0.elapsed().as_secs_f64(),
            s.objective,
            s.support_vectors,
            s.bounded_support_vectors
        );
        s.coef
    };
    let a30 = run(30.0, 0.01, None, "cold");
    let b30 = run(30.0, 0.005, Some(&a30), "warm from C 30 eps 0.01");
    let _ = run(30.0, 0.005, None, "cold");
    let a300 = run(300.0, 0.01, Some(&a30), "warm from C 30 unscaled");
    let scaled: Vec<f64> = a30.iter().map(|v| v * 10.0).collect();
    let _ = run(300.0, 0.01, Some(&scaled), "warm from C 30 scaled x10");
    let _ = run(300.0, 0.005, Some(&a300), "warm from C 300 eps 0.01");
    let scaled: Vec<f64> = b30.iter().map(|v| v * 10.0).collect();
    let b300 = run(
        300.0,
        0.005,
        Some(&scaled),
        "warm from C 30 eps 0.005 scaled x10",
    );
    let _ = run(300.0, 0.01, Some(&b300), "warm from C 300 eps 0.005");
    let _ = run(300.0, 0.005, None, "cold");
    let _ = run(300.0, 0.01, None, "cold");
    let _ = run(
        300.0,
        0.005,
        Some(&b30),
        "warm from C 30 eps 0.005 unscaled",
    );
}

/// The whole `svr_search` as `calibrate --blackbox` runs it, and its test
/// error on the held-out pairs.
fn whole_search(p: &Profile, xt: &[[f64; 3]], tt: &[[f64; 3]]) {
    let t0 = Instant::now();
    let res = search::svr_search(&p.x, &p.t, &p.cfg).unwrap();
    let total = t0.elapsed().as_secs_f64();
    for c in &res.candidates {
        println!(
            "candidate C {} eps {} gamma {}: validation {:?} mm, {:.2} s, {} SV",
            c.params.c,
            c.params.epsilon,
            c.params.gamma,
            c.validation_mean_mm,
            c.seconds,
            c.support_vectors
        );
    }
    let pred = svr::predict_all(&res.fit.model, xt);
    let s = ErrorStats::between(&pred, tt);
    println!(
        "svr_search: search {:.2} s, refit {:.2} s (kernel {:.2} s), total {total:.2} s; best {:?}; \
         refit iterations {:?}; test mean {:.4} sd {:.4} max {:.4} mm",
        res.search_seconds,
        res.refit_seconds,
        res.fit.kernel_seconds,
        res.best,
        res.fit.axes.map(|a| a.iterations),
        s.mean_mm,
        s.sd_mm,
        s.max_mm
    );
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dir = args.first().expect("usage: blackbox_profile DIR [--tol T]");
    let value = |f: &str| {
        args.iter()
            .position(|a| a == f)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let tol: f64 = value("--tol").and_then(|v| v.parse().ok()).unwrap_or(1e-3);

    let (x, t) = read_pairs(&format!("{dir}/blackbox_train.csv"));
    let (xt, tt) = read_pairs(&format!("{dir}/blackbox_test.csv"));
    let cfg = SvrSearchConfig {
        mode: OutputMode::Absolute,
        solver: SolverConfig {
            tol,
            conjugate: !args.iter().any(|a| a == "--plain"),
            per_point: !args.iter().any(|a| a == "--two-n"),
            ..SolverConfig::default()
        },
        ..SvrSearchConfig::default()
    };
    println!(
        "{} training pairs, {} test pairs, tol {tol}, rayon threads {}",
        x.len(),
        xt.len(),
        rayon::current_num_threads()
    );
    let profile = Profile { x, t, cfg };
    if !args.iter().any(|a| a == "--search-only") {
        let one = value("--one").map(|v| v.split(',').map(|x| x.parse().unwrap()).collect());
        profile_grid(&profile, one);
    }
    if args.iter().any(|a| a == "--one") {
        return;
    }
    if let Some(spec) = value("--warm") {
        warm_chains(&profile, &spec);
        return;
    }
    whole_search(&profile, &xt, &tt);
}
