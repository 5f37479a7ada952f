//! The identification's analytic Jacobian against finite differences of
//! its residuals, with the effect families the diagnosis loop adds; and
//! the evaluations a warm refit takes.

use levenberg_marquardt::LeastSquaresProblem;
use spidar_core::model::{Effect, EffectTerm, EVERY_STRING};
use spidar_core::STRINGS;

use super::fit::Fit;
use super::layout::{parameter_names, Layout};
use super::{Start, Structure};
use crate::data::observe::{observations, Observation};
use crate::sim::{simulate_session, SessionKind, SimConfig, SimulatedDevice};

fn term(string: u8, effect: Effect) -> EffectTerm {
    EffectTerm { string, effect }
}

/// Device 3 of `config` and the observations of its session of `points`
/// random points (session seed 5).
fn random_session(config: &SimConfig, points: usize) -> (SimulatedDevice, Vec<Observation>) {
    let device = SimulatedDevice::new(config, 3).unwrap();
    let session = simulate_session(&device, SessionKind::Random { points }, 5).unwrap();
    let obs = observations(&session.samples);
    (device, obs)
}

/// Each column's disagreement between the analytic Jacobian and central
/// differences of the residuals, relative to the column's size, at the
/// start's state. The steps are a thousandth of each scaled variable: a
/// sag or a guide reads its position through quantized inputs, which
/// smaller steps would see as jumps.
fn jacobian_disagreement(
    structure: &Structure,
    used: &[&Observation],
    start: &Start,
) -> Vec<(String, f64)> {
    let nominal = start.frame;
    let layout = Layout::new(structure);
    let fit = Fit {
        used,
        structure,
        nominal: &nominal,
        layout: &layout,
        start,
        spare: Default::default(),
    };
    let (state, _) = fit.start_state();
    let weights = vec![[1.0; STRINGS]; used.len()];
    let mut problem = fit.problem(&state, &weights, 0.3);
    let x0 = problem.params();
    let analytic = problem.jacobian().expect("finite Jacobian");
    let names = parameter_names(&layout, structure, nominal.layout);
    let mut columns = Vec::new();
    for c in 0..x0.len() {
        let h = 1e-3 * (1.0 + x0[c].abs());
        let mut plus = x0.clone();
        plus[c] += h;
        problem.set_params(&plus);
        let r_plus = problem.residuals().expect("finite residuals");
        let mut minus = x0.clone();
        minus[c] -= h;
        problem.set_params(&minus);
        let r_minus = problem.residuals().expect("finite residuals");
        problem.set_params(&x0);
        let numeric = (r_plus - r_minus) / (2.0 * h);
        let column = analytic.column(c);
        let scale = numeric.amax().max(column.amax()).max(1e-9);
        let off = (&numeric - column).amax() / scale;
        columns.push((names[c].0.clone(), off));
    }
    columns
}

/// The tolerance the analytic Jacobian meets on every column but those
/// whose names hold one of `approximate`, which it meets within `loose`.
struct Expect {
    approximate: &'static [&'static str],
    loose: f64,
}

const EXACT: Expect = Expect {
    approximate: &[],
    loose: 0.0,
};

#[test]
fn the_jacobian_is_the_residuals_derivative_with_the_loops_families() {
    let (device, obs) = random_session(&SimConfig::default(), 120);
    let used: Vec<&Observation> = obs.iter().filter(|o| o.tracker.is_some()).collect();
    let mut start = Start::from_geometry(&device.nominal);
    start.winding.kappa_mm = 0.004;
    let stretch = Effect::Stretch {
        per_newton: 1e-3,
        mm_per_newton: 0.03,
        home_tension_n: 3.0,
    };
    // Where the Jacobian is knowingly approximate: a held spool rate's
    // string rows are left out (its tight prior holds it); a sag's and a
    // guide's terms are differentiated over their own parameters only,
    // not over the position they read (their inclination and elevation).
    let held_rates = Expect {
        approximate: &["kappa_each"],
        loose: 1e-2,
    };
    let cases: Vec<(&str, Vec<EffectTerm>, bool, Expect)> = vec![
        ("base", vec![], true, held_rates),
        ("spool rates free", vec![], false, EXACT),
        (
            "scale, per-string stretch, spool rates",
            (0..STRINGS as u8)
                .map(|s| term(s, stretch))
                .chain([term(2, Effect::Scale { relative: 1e-3 })])
                .collect(),
            false,
            EXACT,
        ),
        (
            "shared stretch",
            vec![term(EVERY_STRING, stretch)],
            false,
            EXACT,
        ),
        (
            "frame flex, creep",
            vec![
                term(
                    EVERY_STRING,
                    Effect::FrameFlex {
                        mm_per_newton: 0.01,
                        home_mm: 0.2,
                    },
                ),
                term(4, Effect::Creep { per_s: 1e-7 }),
            ],
            false,
            EXACT,
        ),
        (
            "latency",
            vec![
                term(2, Effect::Latency { latency_s: 0.004 }),
                term(EVERY_STRING, Effect::Latency { latency_s: 0.002 }),
            ],
            false,
            EXACT,
        ),
        (
            "sag, guide",
            vec![
                term(
                    EVERY_STRING,
                    Effect::Sag {
                        mm_at_1m_1n: 0.5,
                        home_mm_at_1m: 0.1,
                    },
                ),
                term(EVERY_STRING, Effect::Guide { radius_mm: 8.0 }),
            ],
            false,
            Expect {
                approximate: &["anchor", "home", "room_"],
                loose: 0.1,
            },
        ),
    ];
    for (name, effects, hold_kappa_each, expect) in cases {
        let structure = Structure {
            effects,
            hold_kappa_each,
            ..Structure::default()
        };
        for (column, off) in jacobian_disagreement(&structure, &used, &start) {
            let loose = expect.approximate.iter().any(|a| column.contains(a));
            let tolerance = if loose { expect.loose } else { 1e-4 };
            assert!(
                off < tolerance,
                "{name}: column {column} off by {off:.1e} of its size"
            );
        }
    }
}

/// A warm refit whose structure gained a term starts near its minimum:
/// Gauss-Newton's steps reach it in a few evaluations per robust round
/// ([`DAMPING_NEAR`](super::solver::DAMPING_NEAR)). Marquardt's `1e-3`
/// held back the valley a shared stretch's stiffness and home tension
/// make together, and the same refit crept (decision record 0078). The
/// counts do not depend on the machine: the sums are the same in any
/// thread order.
#[test]
fn a_warm_refit_that_gains_a_stretch_takes_gauss_newtons_steps() {
    let config = SimConfig {
        effects: vec!["stretch:*:per_newton=0.0003,mm_per_newton=0.06,home_tension_n=1.1".into()],
        ..SimConfig::default()
    };
    let (device, obs) = random_session(&config, 400);
    let nominal = device.nominal.nominal_frame();
    let base = super::identify(
        &obs,
        &nominal,
        &Start::from_geometry(&device.nominal),
        &Structure::default(),
    )
    .unwrap();
    let stretched = Structure {
        effects: vec![term(
            EVERY_STRING,
            Effect::Stretch {
                per_newton: 1e-4,
                mm_per_newton: 0.0,
                home_tension_n: 1.0,
            },
        )],
        ..Structure::default()
    };
    let refit = super::identify(
        &obs,
        &nominal,
        &Start::from_identification(&base),
        &stretched,
    )
    .unwrap();
    // The stretch explains the device's: the residuals fall to the
    // tracker's noise.
    assert!(
        refit.residual_scale_mm < 0.6 * base.residual_scale_mm,
        "{} -> {} mm",
        base.residual_scale_mm,
        refit.residual_scale_mm
    );
    // 8 and 18 evaluations; 13 and 31 when every round started at 1e-3.
    assert!(refit.evaluations <= 10, "refit: {}", refit.evaluations);
    assert!(base.evaluations <= 24, "cold fit: {}", base.evaluations);
}
