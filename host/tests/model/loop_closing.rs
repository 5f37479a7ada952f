//! The loop on data with an undeclared effect: the simulator injects an effect
//! the calibration model does not start with; diagnosis must name the right
//! family, strings and variable, and after adding it the held-out error must
//! fall to within 1.3 times that of the same device without the effect.

use spidar::model::diagnose::{Family, LoopResult, Variable};
use spidar_core::kinematics::residual_weights;
use spidar_core::model::{Effect, EVERY_STRING};

use crate::lattice_loop as run;

/// The held-out error of the same device without any injected effect.
fn baseline(seed: u64) -> f64 {
    run(seed, &[]).1
}

fn assert_found(result: &LoopResult, family: Family, strings: &[u8], variable: Variable) {
    let found = result
        .findings
        .iter()
        .any(|f| f.family == family && f.strings == strings && f.variable == variable);
    assert!(
        found,
        "expected {family:?} on strings {strings:?} following {variable:?}; findings: {:#?}",
        result
            .findings
            .iter()
            .map(|f| (f.family, f.strings.clone(), f.variable, f.added))
            .collect::<Vec<_>>()
    );
}

fn check_family(spec: &str, family: Family, strings: &[u8], variable: Variable) {
    let seed = 1;
    let (result, after) = run(seed, &[spec]);
    assert_found(&result, family, strings, variable);
    let base = baseline(seed);
    assert!(
        after <= 1.3 * base,
        "{spec}: held-out mean {after:.3} mm after the loop, {base:.3} mm without the effect"
    );
}

#[test]
fn offset() {
    check_family("offset:3:mm=8", Family::Offset, &[3], Variable::Length);
}

/// A payout scale error is the base model's own parameters since each
/// spool has its own thinning rate: the identification moves string 5's
/// winding radius by the injected 3 % (and no other string's), the loop adds
/// nothing for it, and the held-out error is that of the device without it.
#[test]
fn scale_is_carried_by_the_base_model() {
    let seed = 1;
    let (result, after) = run(seed, &["scale:5:relative=0.03"]);
    let (clean, base) = run(seed, &[]);
    for i in 0..8 {
        let ratio = result.base.winding.r_home_mm[i] / clean.base.winding.r_home_mm[i];
        let expected = if i == 5 { 1.03 } else { 1.0 };
        assert!(
            (ratio - expected).abs() < 0.003,
            "string {i}: r_home {ratio:.4} x the clean device's, expected {expected}"
        );
    }
    assert!(
        !result.stages.iter().any(|s| s.finding.strings == [5]),
        "nothing should be added on string 5: {:?}",
        result.stages.iter().map(|s| &s.name).collect::<Vec<_>>()
    );
    assert!(
        after <= 1.3 * base,
        "held-out mean {after:.3} mm after the loop, {base:.3} mm without the effect"
    );
}

#[test]
fn winding_order() {
    check_family(
        "winding:2:power=3,mm_per_rad_pow=0.00002",
        Family::Winding,
        &[2],
        Variable::WoundLength,
    );
}

#[test]
fn eccentricity() {
    check_family(
        "eccentricity:1:sin_mm=0.8,cos_mm=0.5",
        Family::Eccentricity,
        &[1],
        Variable::PulleyAngle,
    );
}

#[test]
fn elasticity() {
    check_family(
        "elasticity:6:per_newton=0.0003",
        Family::Elasticity,
        &[6],
        Variable::Tension,
    );
}

#[test]
fn backlash() {
    check_family(
        "backlash:0:half_width_mm=1.0",
        Family::Backlash,
        &[0],
        Variable::Direction,
    );
}

#[test]
fn drift() {
    check_family(
        "drift:7:mm_per_s=0.001",
        Family::Drift,
        &[7],
        Variable::Time,
    );
}

/// One drift on every string (issue 10, point 4): found as one shared term
/// (no per-string drifts one at a time), and the held-out error back to
/// the clean device's.
#[test]
fn drift_of_every_string_is_one_shared_term() {
    let (result, after) = run(1, &["drift:*:mm_per_s=0.0002"]);
    let added: Vec<&str> = result.stages.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(added, ["drift (every string)"]);
    assert_found(&result, Family::Drift, &[], Variable::Time);
    let term = result.identification.effects[0];
    assert_eq!(term.string, spidar_core::model::EVERY_STRING);
    let spidar_core::model::Effect::Drift { mm_per_s } = term.effect else {
        panic!("{term:?}");
    };
    assert!((mm_per_s - 0.0002).abs() < 0.00002, "{mm_per_s}");
    let base = baseline(1);
    assert!(after <= 1.05 * base, "{after:.3} mm after, {base:.3} clean");
}

#[test]
fn slip() {
    check_family("slip:2:at_s=2000,mm=5", Family::Slip, &[2], Variable::Time);
}

/// Four slips on three strings, two on string 2 (model simulator, seed 3):
/// every step on its string at its time and size, two strings' first
/// steps tried together, string 2's second step found off the model that
/// holds its first; the test error back at the clean device's.
#[test]
fn slips_of_several_strings_and_a_second_slip_of_one() {
    let (result, after) = run(
        3,
        &[
            "slip:2:at_s=1500,mm=4",
            "slip:2:at_s=3300,mm=-3",
            "slip:5:at_s=2500,mm=3",
            "slip:6:at_s=600,mm=-2.5",
        ],
    );
    let mut slips = super::slips_of(&result);
    slips.sort_by(|a, b| a.1.total_cmp(&b.1));
    let truth = [
        (6, 600.0, -2.5),
        (2, 1500.0, 4.0),
        (5, 2500.0, 3.0),
        (2, 3300.0, -3.0),
    ];
    assert_eq!(slips.len(), truth.len(), "{slips:?}");
    for (found, (string, at_s, mm)) in slips.iter().zip(truth) {
        assert!(
            found.0 == string && (found.1 - at_s).abs() < 5.0 && (found.2 - mm).abs() < 0.1,
            "{found:?} for {:?}",
            (string, at_s, mm)
        );
    }
    assert_back_to_clean(after, 3);
}

/// The fitted parameters (`Effect::parameters` order) of the one term
/// shared by every string that `family` matches.
fn shared_parameters(result: &LoopResult, family: fn(&Effect) -> bool) -> Vec<f64> {
    let shared: Vec<_> = result
        .identification
        .effects
        .iter()
        .filter(|t| t.string == EVERY_STRING && family(&t.effect))
        .collect();
    assert_eq!(shared.len(), 1, "{:?}", result.identification.effects);
    shared[0].effect.parameters().to_vec()
}

/// The test error after the loop is back at the clean device's (seed).
fn assert_back_to_clean(after: f64, seed: u64) {
    let base = baseline(seed);
    assert!(after <= 1.05 * base, "{after:.3} mm after, {base:.3} clean");
}

/// Heavy strings (20 g/m: 1.6 mm at 1 m and 1 N, captured at home at
/// 1.1 N: 1.32 mm at 1 m), all of one kind: one shared term, its weight and
/// the home tension recovered.
#[test]
fn sag() {
    let (result, after) = run(1, &["sag:*:mm_at_1m_1n=1.6,home_mm_at_1m=1.32"]);
    assert_found(&result, Family::Sag, &[], Variable::Tension);
    let p = shared_parameters(&result, |e| matches!(e, Effect::Sag { .. }));
    let (c, h) = (p[0], p[1]);
    assert!((c - 1.6).abs() < 0.02 && (h - 1.32).abs() < 0.05, "{c} {h}");
    assert_back_to_clean(after, 1);
}

/// Strings of one kind that stretch over their whole length from the spool
/// (free span and a lead of 200 mm, 1/EA = 3e-4 per N) and were captured at
/// home at 1.1 N: one shared stretch, its stiffness and lead recovered.
#[test]
fn stretch() {
    let (result, after) = run(
        1,
        &["stretch:*:per_newton=0.0003,mm_per_newton=0.06,home_tension_n=1.1"],
    );
    assert_found(&result, Family::Elasticity, &[], Variable::Tension);
    let p = shared_parameters(&result, |e| matches!(e, Effect::Stretch { .. }));
    let (k, m, t_home) = (p[0], p[1], p[2]);
    assert!(
        (k - 3e-4).abs() < 3e-5 && (m - 0.06).abs() < 0.03 && (t_home - 1.1).abs() < 0.3,
        "1/EA {k:.3e} per N, lead {m:.3} mm/N, home tension {t_home:.2} N"
    );
    assert_back_to_clean(after, 1);
}

/// A frame whose guides move with the strings' total pull (0.1 mm per N):
/// one shared term against tension, its compliance and its home part
/// recovered.
#[test]
fn frame_flex() {
    let (result, after) = run(1, &["frame_flex:*:mm_per_newton=0.1,home_mm=0.9"]);
    assert_found(&result, Family::FrameFlex, &[], Variable::Tension);
    let p = shared_parameters(&result, |e| matches!(e, Effect::FrameFlex { .. }));
    let (k, home_mm) = (p[0], p[1]);
    assert!(
        (k - 0.1).abs() < 0.01 && (home_mm - 0.9).abs() < 0.15,
        "{k:.4} mm/N, home {home_mm:.3} mm"
    );
    assert_back_to_clean(after, 1);
}

#[test]
fn geometry_anchor_off_its_drawing() {
    check_family(
        "anchor:3:dx=80,dy=-60,dz=30",
        Family::Geometry,
        &[3],
        Variable::Position,
    );
}

#[test]
fn two_effects_at_once() {
    let seed = 2;
    let (result, after) = run(seed, &["offset:3:mm=8", "backlash:6:half_width_mm=0.8"]);
    assert_found(&result, Family::Offset, &[3], Variable::Length);
    assert_found(&result, Family::Backlash, &[6], Variable::Direction);
    let added: Vec<_> = result.stages.iter().map(|s| s.finding.family).collect();
    assert_eq!(added, [Family::Offset, Family::Backlash]);
    let base = baseline(seed);
    assert!(
        after <= 1.3 * base,
        "after {after:.3} mm, baseline {base:.3} mm"
    );
}

/// Encoder latency: an error proportional to the string's speed, which no
/// family covers. It is reported by its variable, and the lagging string,
/// weighed by its measured scale (with the unexplained structure counted
/// once more: the device moves faster in use than at the lattice's
/// captures), pulls the position less: the held-out error stays within 1.3
/// times the clean device's (measured 1.13 and 1.05; 2.05 times when every
/// string weighed alike, 1.29 without the structure counted again).
#[test]
fn structure_no_family_explains_is_reported_by_variable() {
    for seed in [1, 2] {
        let (result, after) = run(seed, &["speed:3:latency_s=0.02"]);
        assert_found(&result, Family::Unexplained, &[3], Variable::Speed);
        let model = &result.identification;
        let w = residual_weights(model.frame.layout, &model.length_scale_mm);
        assert!(
            w[3] < 0.5 && (0..8).filter(|&i| i != 3).all(|i| w[i] > 0.7),
            "seed {seed}: weights {w:?}"
        );
        assert!(
            model
                .warnings
                .iter()
                .any(|w| w.starts_with("string 3's residual follows speed")),
            "seed {seed}: {:?}",
            model.warnings
        );
        let base = baseline(seed);
        println!(
            "seed {seed}: string 3 weighs {:.2}; after {after:.3} mm, clean {base:.3}",
            w[3]
        );
        assert!(
            after <= 1.3 * base,
            "seed {seed}: after {after:.3} mm, baseline {base:.3} mm"
        );
    }
}

#[test]
fn clean_sessions_add_nothing() {
    for seed in 1..=3 {
        let (result, _) = run(seed, &[]);
        assert!(
            result.stages.is_empty(),
            "seed {seed}: added {:?}",
            result.stages.iter().map(|s| &s.name).collect::<Vec<_>>()
        );
    }
}

/// The loop on the lattice of the model simulator's device of `seed` with
/// `effects`, judged on a test session that continues the lattice's home
/// (its clock goes on, the drifts with it): the result and the test mean.
fn continuing_loop(seed: u64, effects: &[&str]) -> (LoopResult, f64) {
    use spidar::sim::{simulate_session, simulate_session_after, SessionKind, SimConfig};
    let config = SimConfig {
        effects: effects.iter().map(|s| s.to_string()).collect(),
        ..SimConfig::default()
    };
    let device = spidar::sim::SimulatedDevice::new(&config, seed).expect("device");
    // The session seeds of `physics_bench`'s model cases.
    let lattice = simulate_session(&device, SessionKind::Lattice, seed + 1).expect("lattice");
    let kind = SessionKind::Random { points: 500 };
    let (test, _) = simulate_session_after(&device, kind, seed + 2, &lattice).expect("test");
    crate::loop_on(&device.nominal, &lattice, &test)
}

/// Each string's drift (mm/s) of `result`'s model, `None` where it has none.
fn drift_rates(result: &LoopResult) -> [Option<f64>; 8] {
    let mut rates = [None; 8];
    for t in &result.identification.effects {
        if let Effect::Drift { mm_per_s } = t.effect {
            if let Some(r) = rates.get_mut(usize::from(t.string)) {
                *r = Some(mm_per_s);
            }
        }
    }
    rates
}

/// [`continuing_loop`] of seed 1 with a drift on every string at `rates`
/// (mm/s): the result, the test mean and the names of its stages.
fn drifting_strings(rates: &[f64; 8]) -> (LoopResult, f64, Vec<String>) {
    let specs: Vec<String> = rates
        .iter()
        .enumerate()
        .map(|(i, r)| format!("drift:{i}:mm_per_s={r}"))
        .collect();
    let specs: Vec<&str> = specs.iter().map(String::as_str).collect();
    let (result, after) = continuing_loop(1, &specs);
    let names = result.stages.iter().map(|s| s.name.clone()).collect();
    (result, after, names)
}

/// Every string drifting at its own rate, two of them shortening, the test
/// session continuing the lattice's home (issue 33's hidden simulator has
/// drifts of every string, and a test session later than the lattice).
/// Added one string at a time, each drift took the others' share of what
/// time and position share on the lattice, and an offset, a spool's rate
/// and creeps stood in (test 1.4 mm against the clean device's 0.32). Now
/// one change adds a drift on every string at its rate; a term added before
/// it for what it explains is judged again without it; the test mean is
/// back within 1.3x the clean device's.
#[test]
fn drifts_of_every_string_at_their_own_rates_are_one_change() {
    let truth = [
        0.0008, -0.0005, 0.0012, 0.0003, 0.0009, -0.0002, 0.0006, 0.001,
    ];
    let (result, after, names) = drifting_strings(&truth);
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    assert!(
        names.contains(&"drift strings [0, 1, 2, 3, 4, 5, 6, 7]"),
        "{names:?}"
    );
    for (i, (found, truth)) in drift_rates(&result).iter().zip(truth).enumerate() {
        let found = found.unwrap_or_else(|| panic!("no drift on string {i}: {names:?}"));
        assert!(
            (found - truth).abs() < 0.1 * truth.abs() + 0.00005,
            "string {i}: {found:.6} mm/s against {truth}"
        );
    }
    let stand_ins: Vec<&&str> = names
        .iter()
        .filter(|n| n.starts_with("offset") || n.starts_with("creep"))
        .collect();
    assert!(stand_ins.is_empty(), "{names:?}");
    // Each spool's own thinning rate, taken before the drift (the model
    // with them predicts the test at 0.370 mm), judged again and dropped.
    assert_eq!(
        names.first(),
        Some(&"spool rates strings [0, 1, 2, 3, 4, 5, 6, 7]")
    );
    assert_eq!(
        names.last(),
        Some(&"without spool rates strings [0, 1, 2, 3, 4, 5, 6, 7]")
    );
    assert!(result.structure.hold_kappa_each, "{names:?}");
    let base = baseline(1);
    assert!(after <= 1.3 * base, "{after:.3} mm after, {base:.3} clean");
}

/// Every string drifting at its own rate around a shared one (0.0004-0.0008
/// mm/s): the strings' own rates beat the one shared rate, their rival.
/// Layer tables taken before the drift (a string's payout goes with time on
/// the lattice) are judged again from the model without them, and whatever
/// stays, the test mean is within 1.3x the clean device's.
#[test]
fn drifts_around_a_shared_rate_are_each_string_s_own() {
    let truth = [
        0.0006, 0.0004, 0.0008, 0.0005, 0.0007, 0.0004, 0.0006, 0.0008,
    ];
    let (result, after, names) = drifting_strings(&truth);
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    assert!(
        names.contains(&"drift strings [0, 1, 2, 3, 4, 5, 6, 7]"),
        "{names:?}"
    );
    assert!(!names.contains(&"drift (every string)"), "{names:?}");
    // The tables on strings 1 and 3, taken before the drift (the model with
    // them predicts the test at 0.424 mm), judged again and dropped.
    assert_eq!(names.first(), Some(&"layers strings [1, 3]"));
    assert_eq!(names.last(), Some(&"without layer tables strings [1, 3]"));
    assert!(
        spidar::model::layers::steps_in(&result.identification)
            .iter()
            .all(Option::is_none),
        "{names:?}"
    );
    let base = baseline(1);
    assert!(after <= 1.3 * base, "{after:.3} mm after, {base:.3} clean");
}
