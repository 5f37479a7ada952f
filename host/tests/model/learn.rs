//! Learned corrections on a synthetic smooth distortion field, and the SVR
//! solver (libsvm's plain SMO path and the default conjugate one) against
//! libsvm (fixture written by scripts/reference/svr_reference.py).

use spidar::model::learn::nn::{self, LmConfig, NnConfig};
use spidar::model::learn::search::{self, Scoring, SvrSearchConfig, SweepConfig};
use spidar::model::learn::svr::{self, KernelMatrix, SolverConfig, SvrConfig, SvrParams};
use spidar::model::learn::synthetic::{self, Dataset};
use spidar::model::learn::{outliers, standardize, Deadline, ErrorStats, LearnError, OutputMode};

const HALF: f64 = 500.0;

/// 13^3 lattice over a 1 m cube (the paper's protocol) and 500 random test
/// points, 0.2 mm tracker noise.
fn data() -> (Dataset, Dataset) {
    (
        synthetic::lattice(13, HALF, 1.0, 0.2, 11),
        synthetic::random(500, HALF, 1.0, 0.2, 12),
    )
}

fn raw(d: &Dataset) -> ErrorStats {
    ErrorStats::between(&d.inputs, &d.targets)
}

// ---------------------------------------------------------------- libsvm --

#[derive(serde::Deserialize)]
struct Fixture {
    x_train: Vec<[f64; 3]>,
    y_train: Vec<[f64; 3]>,
    x_test: Vec<[f64; 3]>,
    cases: Vec<Case>,
}

#[derive(serde::Deserialize)]
struct Case {
    name: String,
    c: f64,
    epsilon: f64,
    gamma: f64,
    tol: f64,
    axes: Vec<Axis>,
}

#[derive(serde::Deserialize)]
struct Axis {
    coef: Vec<f64>,
    intercept: f64,
    objective: f64,
    n_support: usize,
    pred_train: Vec<f64>,
    pred_test: Vec<f64>,
}

fn rbf_predict(x: &[[f64; 3]], coef: &[f64], bias: f64, gamma: f64, at: &[f64; 3]) -> f64 {
    x.iter()
        .zip(coef)
        .map(|(xi, c)| {
            let d: f64 = (0..3).map(|a| (xi[a] - at[a]).powi(2)).sum();
            c * (-gamma * d).exp()
        })
        .sum::<f64>()
        + bias
}

/// `0.5 c^T K c - z^T c + epsilon sum |c|`, libsvm's dual objective when
/// `alpha_i alpha*_i = 0`.
fn dual_objective(x: &[[f64; 3]], z: &[f64], coef: &[f64], epsilon: f64, gamma: f64) -> f64 {
    let mut quad = 0.0;
    for (i, ci) in coef.iter().enumerate().filter(|(_, c)| **c != 0.0) {
        quad += ci * rbf_predict(x, coef, 0.0, gamma, &x[i]);
    }
    let lin: f64 = z.iter().zip(coef).map(|(a, b)| a * b).sum();
    let l1: f64 = coef.iter().map(|c| c.abs()).sum();
    0.5 * quad - lin + epsilon * l1
}

#[test]
fn svr_matches_libsvm() {
    let fx: Fixture =
        serde_json::from_str(include_str!("fixtures/svr_libsvm.json")).expect("fixture parses");
    // Both formulations (libsvm's 2n variables, and one per point, the
    // default), each with libsvm's plain steps and with conjugate ones.
    let variants = [(false, false), (true, false), (false, true), (true, true)];
    for (case, (conjugate, per_point)) in fx
        .cases
        .iter()
        .flat_map(|c| variants.iter().map(move |v| (c, *v)))
    {
        let k = KernelMatrix::rbf(&fx.x_train, case.gamma, 10_000).unwrap();
        let solver = SolverConfig {
            tol: case.tol,
            conjugate,
            per_point,
            ..SolverConfig::default()
        };
        // The solutions agree to the accuracy the KKT tolerance buys. At the
        // default tol (1e-3) both solvers stop a little short of the optimum;
        // where their paths part (a one-ulp kernel difference is enough) they
        // stop at different points of the tolerance region: measured 3.2e-3
        // on the ill-conditioned "paper" case (C = 100, coefficients up to C,
        // large cancellations; 1.9e-3 when the fixture's numbers were read a
        // unit in the last place off, while libsvm's own steps now agree
        // with libsvm to 2e-13), 8e-4 on "bounded", and 4e-6 at tol 1e-6.
        let (pred_tol, obj_tol) = match case.name.as_str() {
            "tight" => (1e-5, 1e-8),
            "paper" => (4e-3, 2e-4),
            _ => (1e-3, 1e-5),
        };
        for (a, ax) in case.axes.iter().enumerate() {
            let z: Vec<f64> = fx.y_train.iter().map(|y| y[a]).collect();
            let sol =
                svr::solve_epsilon_svr(&k, &z, case.c, case.epsilon, &solver, Deadline::none())
                    .unwrap();
            assert!(sol.converged, "{} axis {a} did not converge", case.name);
            let mut worst: f64 = 0.0;
            for (x, p) in fx
                .x_train
                .iter()
                .zip(&ax.pred_train)
                .chain(fx.x_test.iter().zip(&ax.pred_test))
            {
                let ours = rbf_predict(&fx.x_train, &sol.coef, sol.bias, case.gamma, x);
                worst = worst.max((ours - p).abs());
            }
            // Both objectives from the coefficients with an f64 kernel, as
            // the fixture computes libsvm's.
            let obj = dual_objective(&fx.x_train, &z, &sol.coef, case.epsilon, case.gamma);
            let rel_obj = (obj - ax.objective).abs() / ax.objective.abs();
            let coef_diff = sol
                .coef
                .iter()
                .zip(&ax.coef)
                .map(|(u, v)| (u - v).abs())
                .fold(0.0, f64::max);
            eprintln!(
                "libsvm {:>8} conjugate {conjugate} per point {per_point} axis {a}: max |pred diff| {worst:.2e}, objective {:.6} vs {:.6} (rel {rel_obj:.1e}), \
                 SVs {} vs {}, bias diff {:.1e}, max coef diff {coef_diff:.2e}, iters {}",
                case.name,
                obj,
                ax.objective,
                sol.support_vectors,
                ax.n_support,
                (sol.bias - ax.intercept).abs(),
                sol.iterations
            );
            // The conjugate solver (the default) takes another path through
            // the same tolerance region: at tol 1e-6 it agrees with libsvm as
            // tightly as the plain one; at the default tol 1e-3 its
            // predictions differ by up to 3.1e-3 on "paper" and 1.0e-3 on
            // "bounded" (measured), with an objective lower than libsvm's on
            // "paper" (by up to 3e-4 relative) and equal to 2e-8 on
            // "bounded": it stops at another point of the region, often
            // closer to the optimum, so predictions are held to 4 tol and the
            // objective to "not worse".
            let pred_tol = if conjugate {
                f64::max(pred_tol, 4.0 * case.tol)
            } else {
                pred_tol
            };
            assert!(
                worst < pred_tol,
                "{} axis {a}: prediction differs by {worst}",
                case.name
            );
            assert!(
                rel_obj < obj_tol || (conjugate && obj < ax.objective),
                "{} axis {a}: objective rel diff {rel_obj}",
                case.name
            );
            // Ours is a minimization to the same tolerance: never much worse.
            assert!(obj <= ax.objective + obj_tol * ax.objective.abs());
        }
    }
}

/// A warm start (from a smaller C, on a subset of the kernel's rows) ends on
/// the same optimum as a cold start, to the solver's tolerance; a warm start
/// that is not feasible and rows outside the kernel are typed errors.
#[test]
fn svr_warm_start_reaches_the_cold_optimum() {
    let fx: Fixture =
        serde_json::from_str(include_str!("fixtures/svr_libsvm.json")).expect("fixture parses");
    let k = KernelMatrix::rbf(&fx.x_train, 0.5, 10_000).unwrap();
    // Every other point trains, as a search fold does.
    let points: Vec<usize> = (0..fx.x_train.len()).step_by(2).collect();
    let z: Vec<f64> = points.iter().map(|&i| fx.y_train[i][0]).collect();
    let solver = SolverConfig {
        tol: 1e-6,
        ..SolverConfig::default()
    };
    let problem = |c: f64| svr::Problem {
        kernel: &k,
        points: &points,
        z: &z,
        c,
        epsilon: 0.01,
        warm: None,
    };
    let with_warm = |warm| svr::Problem {
        warm: Some(warm),
        ..problem(100.0)
    };
    let small = svr::solve(&problem(10.0), &solver, Deadline::none()).unwrap();
    let cold = svr::solve(&problem(100.0), &solver, Deadline::none()).unwrap();
    let scaled: Vec<f64> = small.coef.iter().map(|c| c * 10.0).collect();
    for warm in [&small.coef, &scaled] {
        let w = svr::solve(&with_warm(warm), &solver, Deadline::none()).unwrap();
        assert!(w.converged && cold.converged);
        let rel = (w.objective - cold.objective).abs() / cold.objective.abs();
        assert!(
            rel < 1e-8,
            "warm objective {} vs cold {}",
            w.objective,
            cold.objective
        );
        let pred = |coef: &[f64], bias: f64, x: &[f64; 3]| {
            let xs: Vec<[f64; 3]> = points.iter().map(|&i| fx.x_train[i]).collect();
            rbf_predict(&xs, coef, bias, 0.5, x)
        };
        for x in &fx.x_test {
            let d = (pred(&w.coef, w.bias, x) - pred(&cold.coef, cold.bias, x)).abs();
            assert!(d < 1e-4, "warm and cold predictions differ by {d}");
        }
    }
    let mut unbalanced = small.coef.clone();
    unbalanced[0] += 1.0;
    assert!(matches!(
        svr::solve(&with_warm(&unbalanced), &solver, Deadline::none()),
        Err(LearnError::InvalidParameter {
            name: "warm start",
            ..
        })
    ));
    let outside = [0, k.len()];
    assert!(matches!(
        svr::solve(
            &svr::Problem {
                points: &outside,
                z: &[0.0, 1.0],
                ..problem(1.0)
            },
            &solver,
            Deadline::none()
        ),
        Err(LearnError::InvalidParameter { name: "points", .. })
    ));
}

// ------------------------------------------------------- synthetic field --

#[test]
fn svr_corrects_synthetic_field() {
    let (train, test) = data();
    let fit = svr::train(&train.inputs, &train.targets, &SvrConfig::default()).unwrap();
    assert!(fit.axes.iter().all(|a| a.converged));
    svr::check_model(&fit.model).unwrap();
    let t = search::evaluate(|p| svr::predict(&fit.model, p), &test.inputs, &test.targets);
    let r = raw(&test);
    eprintln!(
        "SVR absolute: raw {:.2} mm -> test {:.3} ± {:.3} (max {:.2}) mm, {} SVs",
        r.mean_mm,
        t.mean_mm,
        t.sd_mm,
        t.max_mm,
        fit.model.support.len()
    );
    // Measured 2.52 mm: epsilon = 0.01 of the output spread (~290 mm) is a
    // 2.9 mm tube, which bounds what the absolute mode can do.
    assert!(r.mean_mm > 25.0);
    assert!(t.mean_mm < 3.0, "SVR test mean {}", t.mean_mm);
    assert!(t.max_mm < 8.0, "SVR test max {}", t.max_mm);

    // Residual mode: epsilon now scales with the residual's spread (~15 mm
    // here), so 0.05 is a 0.75 mm tube. (0.01 would be 0.15 mm, below the
    // noise: measured 34 s of SMO for no gain; 0.02 took 9 s for 0.33 mm.)
    let cfg = SvrConfig {
        mode: OutputMode::Residual,
        params: SvrParams {
            epsilon: 0.05,
            ..SvrConfig::default().params
        },
        ..SvrConfig::default()
    };
    let fit = svr::train(&train.inputs, &train.targets, &cfg).unwrap();
    let t = search::evaluate(|p| svr::predict(&fit.model, p), &test.inputs, &test.targets);
    eprintln!(
        "SVR residual: test {:.3} ± {:.3} (max {:.2}) mm",
        t.mean_mm, t.sd_mm, t.max_mm
    );
    // Measured 0.54 mm.
    assert!(t.mean_mm < 0.8, "SVR residual test mean {}", t.mean_mm);
}

fn nn_cfg(hidden: usize, epochs: usize, mode: OutputMode) -> NnConfig {
    NnConfig {
        hidden,
        mode,
        restarts: 2,
        lm: LmConfig {
            max_epochs: epochs,
            ..LmConfig::default()
        },
        ..NnConfig::default()
    }
}

#[test]
fn nn_corrects_synthetic_field() {
    let (train, test) = data();
    let r = raw(&test);
    for mode in [OutputMode::Absolute, OutputMode::Residual] {
        let fit = nn::train(&train.inputs, &train.targets, &nn_cfg(16, 60, mode)).unwrap();
        nn::check_model(&fit.model).unwrap();
        assert_eq!(fit.model.w1.len(), 16);
        assert_eq!(fit.model.mode, mode);
        let t = search::evaluate(|p| nn::predict(&fit.model, p), &test.inputs, &test.targets);
        eprintln!(
            "NN {mode:?} H=16: raw {:.2} -> test {:.3} ± {:.3} (max {:.2}) mm, {} epochs ({:?}), {:.2} s",
            r.mean_mm, t.mean_mm, t.sd_mm, t.max_mm, fit.epochs, fit.stop, fit.seconds
        );
        // Measured about 0.5-1 mm in 60 epochs.
        assert!(t.mean_mm < 2.0, "NN {mode:?} test mean {}", t.mean_mm);
        assert!(t.max_mm < 8.0, "NN {mode:?} test max {}", t.max_mm);
        assert!((fit.validation.mean_mm - t.mean_mm).abs() < 1.0);
    }
}

/// A planar device's positions all have one z: nothing constrains the
/// weights of that input, and the network must still fit the device's
/// fixed point (they had wandered to 1e9 on the wall robot).
#[test]
fn a_planar_session_trains_a_network_the_device_can_hold() {
    let (train, test) = data();
    // A smooth error of a few mm across the plane.
    let flat = |d: &Dataset| -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let z = 2000.0;
        let inputs: Vec<[f64; 3]> = d.inputs.iter().map(|p| [p[0], p[1], z]).collect();
        let targets = inputs
            .iter()
            .map(|p| {
                [
                    p[0] + 3.0 * (p[0] / 300.0).sin(),
                    p[1] + 2.0 * (p[1] / 400.0).cos(),
                    z,
                ]
            })
            .collect();
        (inputs, targets)
    };
    let (inputs, targets) = flat(&train);
    let fit = nn::train(&inputs, &targets, &nn_cfg(10, 60, OutputMode::Residual)).unwrap();
    assert!(
        fit.model.w1.iter().all(|w| w[2] == 0.0),
        "{:?}",
        fit.model.w1
    );
    spidar_core::correction::CorrectionModel::Nn(fit.model.clone())
        .compile()
        .expect("the device holds the planar network");
    let (test_inputs, test_targets) = flat(&test);
    let t = search::evaluate(|p| nn::predict(&fit.model, p), &test_inputs, &test_targets);
    let raw = search::evaluate(|p| *p, &test_inputs, &test_targets);
    assert!(
        t.mean_mm < 0.3 * raw.mean_mm,
        "planar NN test mean {} (raw {})",
        t.mean_mm,
        raw.mean_mm
    );
}

#[test]
fn hidden_sweep_gives_a_curve_and_the_best_size() {
    let (train, test) = data();
    let cfg = SweepConfig {
        sizes: vec![3, 8, 16],
        sweep_lm: LmConfig {
            max_epochs: 25,
            ..LmConfig::default()
        },
        final_lm: LmConfig {
            max_epochs: 40,
            ..LmConfig::default()
        },
        ..SweepConfig::default()
    };
    let res = search::nn_sweep(&train.inputs, &train.targets, &cfg).unwrap();
    let hs: Vec<usize> = res.curve.iter().map(|p| p.hidden).collect();
    assert_eq!(hs, vec![3, 8, 16]);
    for p in &res.curve {
        eprintln!(
            "sweep H={}: validation {:.3} mm",
            p.hidden, p.validation_mean_mm
        );
    }
    let best = res
        .curve
        .iter()
        .min_by(|a, b| a.validation_mean_mm.total_cmp(&b.validation_mean_mm))
        .unwrap();
    assert_eq!(res.best_hidden, best.hidden);
    assert_eq!(res.fit.model.w1.len(), res.best_hidden);
    // Three neurons cannot follow this field; sixteen can.
    assert!(res.curve[0].validation_mean_mm > 2.0 * res.curve[2].validation_mean_mm);
    // The final training never loses to the sweep's network.
    assert!(res.fit.validation.mean_mm <= best.validation_mean_mm + 1e-9);
    let t = search::evaluate(
        |p| nn::predict(&res.fit.model, p),
        &test.inputs,
        &test.targets,
    );
    assert!(t.mean_mm < 2.0, "swept NN test mean {}", t.mean_mm);
}

#[test]
fn svr_search_picks_the_best_candidate() {
    // A coarser lattice keeps this quick.
    let train = synthetic::lattice(9, HALF, 1.0, 0.2, 21);
    let test = synthetic::random(300, HALF, 1.0, 0.2, 22);
    let cfg = SvrSearchConfig {
        c: vec![10.0, 100.0],
        epsilon: vec![0.05, 0.01],
        gamma: vec![0.3, 1.0],
        validation: Scoring::KFold { k: 3 },
        ..SvrSearchConfig::default()
    };
    let res = search::svr_search(&train.inputs, &train.targets, &cfg).unwrap();
    assert_eq!(res.candidates.len(), 8);
    let best = res
        .candidates
        .iter()
        .filter_map(|c| c.validation_mean_mm.map(|v| (v, c.params)))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .unwrap();
    assert_eq!(best.1, res.best);
    // The wide tube is clearly worse on this field.
    assert_eq!(res.best.epsilon, 0.01);
    let t = search::evaluate(
        |p| svr::predict(&res.fit.model, p),
        &test.inputs,
        &test.targets,
    );
    eprintln!("SVR search best {:?}: test {:.3} mm", res.best, t.mean_mm);
    assert!(t.mean_mm < 4.0);
}

// -------------------------------------------------------------- outliers --

#[test]
fn tukey_removes_injected_gross_outliers() {
    let (mut train, _) = data();
    let injected = [5usize, 300, 1111, 2000, 2196];
    for (n, &i) in injected.iter().enumerate() {
        // A slipped string: hundreds of mm along one axis.
        train.targets[i][n % 3] += 400.0 + 50.0 * n as f64;
    }
    let rep = outliers::tukey(&train.inputs, &train.targets).unwrap();
    eprintln!(
        "Tukey: Q1 {:.2} Q3 {:.2} fences [{:.2}, {:.2}] removed {} ({} high)",
        rep.q1,
        rep.q3,
        rep.lower_fence,
        rep.upper_fence,
        rep.removed.len(),
        rep.removed_high()
    );
    for i in injected {
        assert!(rep.removed.contains(&i), "outlier {i} kept");
    }
    assert_eq!(rep.kept.len() + rep.removed.len(), train.inputs.len());
    // The smooth field itself is not flagged wholesale.
    assert!(rep.removed.len() < 60, "removed {}", rep.removed.len());
    let (ki, kt) = outliers::select(&rep, &train.inputs, &train.targets);
    assert_eq!(ki.len(), rep.kept.len());
    assert_eq!(kt.len(), rep.kept.len());
    assert!((rep.iqr - (rep.q3 - rep.q1)).abs() < 1e-12);
    assert!((rep.upper_fence - (rep.q3 + 1.5 * rep.iqr)).abs() < 1e-12);
}

#[test]
fn tukey_fences_match_type7_quartiles() {
    let v = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 100.0];
    let rep = outliers::tukey_values(&v, 1.5).unwrap();
    // numpy.percentile([1..8, 100], [25, 75]) = [3, 7].
    assert_eq!((rep.q1, rep.q3), (3.0, 7.0));
    assert_eq!(rep.upper_fence, 13.0);
    assert_eq!(rep.removed, vec![8]);
}

// --------------------------------------------------------- standardize --

#[test]
fn standardization_is_eq_10() {
    let (train, _) = data();
    let s = standardize::fit("t", &train.targets).unwrap();
    let n = standardize::apply_all(&s, &train.targets);
    for a in 0..3 {
        let m: f64 = n.iter().map(|p| p[a]).sum::<f64>() / n.len() as f64;
        let v: f64 = n.iter().map(|p| (p[a] - m).powi(2)).sum::<f64>() / n.len() as f64;
        assert!(m.abs() < 1e-12 && (v - 1.0).abs() < 1e-12);
    }
    let back = standardize::invert(&s, &n[17]);
    for (b, t) in back.iter().zip(&train.targets[17]) {
        assert!((b - t).abs() < 1e-9);
    }
}

// ----------------------------------------------------------- determinism --

#[test]
fn seeded_training_is_deterministic() {
    let train = synthetic::lattice(7, HALF, 1.0, 0.2, 31);
    let cfg = NnConfig {
        seed: 99,
        ..nn_cfg(8, 15, OutputMode::Absolute)
    };
    let a = nn::train(&train.inputs, &train.targets, &cfg).unwrap();
    let b = nn::train(&train.inputs, &train.targets, &cfg).unwrap();
    assert_eq!(a.model, b.model);
    let c = nn::train(
        &train.inputs,
        &train.targets,
        &NnConfig { seed: 100, ..cfg },
    )
    .unwrap();
    assert_ne!(a.model, c.model);
    let s1 = svr::train(&train.inputs, &train.targets, &SvrConfig::default()).unwrap();
    let s2 = svr::train(&train.inputs, &train.targets, &SvrConfig::default()).unwrap();
    assert_eq!(s1.model, s2.model);
}

// ------------------------------------------------------------ bad input --

#[test]
fn bad_input_gives_typed_errors() {
    let (train, _) = data();
    let mut nan = train.targets.clone();
    nan[42][1] = f64::NAN;
    let cfg = nn_cfg(4, 5, OutputMode::Absolute);
    assert_eq!(
        nn::train(&train.inputs, &nan, &cfg).unwrap_err(),
        LearnError::NonFinite {
            what: "NN training data",
            index: 42,
            axis: 1
        }
    );
    assert!(matches!(
        svr::train(&train.inputs, &nan, &SvrConfig::default()),
        Err(LearnError::NonFinite {
            index: 42,
            axis: 1,
            ..
        })
    ));
    assert!(matches!(
        outliers::tukey(&train.inputs, &nan),
        Err(LearnError::NonFinite { index: 42, .. })
    ));
    assert!(matches!(
        nn::train(&train.inputs[..5], &train.targets[..5], &cfg),
        Err(LearnError::TooFewPoints { got: 5, .. })
    ));
    assert!(matches!(
        nn::train(&train.inputs, &train.targets[..100], &cfg),
        Err(LearnError::LengthMismatch { .. })
    ));
    assert!(matches!(
        svr::train(
            &train.inputs[..2],
            &train.targets[..2],
            &SvrConfig::default()
        ),
        Err(LearnError::TooFewPoints { .. })
    ));
    let bad = SvrConfig {
        params: SvrParams {
            c: -1.0,
            ..SvrConfig::default().params
        },
        ..SvrConfig::default()
    };
    assert!(matches!(
        svr::train(&train.inputs, &train.targets, &bad),
        Err(LearnError::InvalidParameter { name: "C", .. })
    ));
    // An exactly constant axis (a planar device's z) standardizes to 0; one
    // that varies only by rounding noise is refused.
    let flat: Vec<[f64; 3]> = train.inputs.iter().map(|p| [p[0], 7.0, p[2]]).collect();
    assert!(nn::train(&flat, &train.targets, &cfg).is_ok());
    let flat: Vec<[f64; 3]> = train
        .inputs
        .iter()
        .enumerate()
        .map(|(i, p)| [p[0], 7.0 + 1e-15 * (i % 2) as f64, p[2]])
        .collect();
    assert_eq!(
        nn::train(&flat, &train.targets, &cfg).unwrap_err(),
        LearnError::ZeroSpread {
            what: "NN inputs",
            axis: 1
        }
    );
    let err = nn::train(&train.inputs, &nan, &cfg)
        .unwrap_err()
        .to_string();
    assert!(err.contains("point 42") && err.contains("y"), "{err}");
    assert!(matches!(
        search::nn_sweep(
            &train.inputs,
            &train.targets,
            &SweepConfig {
                sizes: vec![],
                ..SweepConfig::default()
            }
        ),
        Err(LearnError::InvalidParameter { name: "sizes", .. })
    ));
    assert!(matches!(
        KernelMatrix::rbf(&train.inputs, 1.0, 100),
        Err(LearnError::TooLarge { .. })
    ));
}

// ------------------------------------------- a session beyond the cap --

/// A training session larger than the corrections' learning cap: they learn
/// from an even thinning of it (at most the cap, every kept point near one
/// of them), the report says so, and the held-out error stays that of
/// corrections learned from every point. (Before the cap, a 20 000-row
/// session ran the SVR search out of its time limit and the calibration
/// failed.)
#[test]
fn corrections_learn_from_an_even_thinning_of_a_session_beyond_the_cap() {
    use spidar::procedures::calibrate::CalibrateConfig;
    use spidar::sim::{simulate_session, SessionKind, SimConfig, SimulatedDevice};

    let mut c = SimConfig::default();
    c.abnormal_motor.enabled = false;
    let device = SimulatedDevice::new(&c, 4).unwrap();
    let train = simulate_session(&device, SessionKind::Random { points: 1500 }, 5).unwrap();
    let test = simulate_session(&device, SessionKind::Random { points: 300 }, 6).unwrap();
    let run = |cap: usize| {
        let mut cfg = CalibrateConfig::quick();
        cfg.quiet = true;
        cfg.max_learning_points = cap;
        crate::calibrate_in_memory(&c.nominal.geometry(), &train, &test, &cfg)
    };
    let thinned = run(400);
    let whole = run(2500);
    let learned = |c: &spidar::procedures::calibrate::Calibrated| {
        c.report.corrections.clone().expect("learned corrections")
    };
    let (thinned_c, whole_c) = (learned(&thinned), learned(&whole));
    let points = &thinned_c.learning_points;
    assert!(
        (300..=400).contains(&points.used) && points.cell_mm.is_some(),
        "{points:?}"
    );
    assert_eq!(points.kept, whole_c.learning_points.kept);
    assert_eq!(whole_c.learning_points.cell_mm, None);
    assert_eq!(whole_c.learning_points.used, whole_c.learning_points.kept);
    // The learners saw the thinned points only: the selection split is a
    // fifth of them, and the SVR has no more support vectors than points.
    let selection = &thinned.report.selection;
    assert_eq!(
        selection.fit_points + selection.selection_points,
        points.used
    );
    assert!(thinned_c.svr.support_vectors <= selection.fit_points);
    assert!(thinned.report.summary().contains(&format!(
        "learned from {} of the {} kept training points",
        points.used, points.kept
    )));
    // Every error figure still counts every row.
    let stage = |r: &spidar::procedures::calibrate::Calibrated, name: &str| {
        r.report
            .stages
            .iter()
            .find(|s| s.name == name)
            .unwrap_or_else(|| panic!("no stage {name}"))
            .clone()
    };
    assert_eq!(stage(&thinned, "raw").train.n, stage(&whole, "raw").train.n);
    for name in ["nn", "svr"] {
        let (a, b) = (
            stage(&thinned, name).test.mean_mm,
            stage(&whole, name).test.mean_mm,
        );
        assert!(a < 1.1 * b, "{name}: thinned {a} mm, whole {b} mm");
    }
}
