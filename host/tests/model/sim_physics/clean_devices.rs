//! The loop on clean devices: spool rates and layer tables first, how the
//! changes after them are judged, the folds of a small session.

use super::fixtures::{calibrate_quick, clean_loop, loop_with, names, quiet_config};
use spidar::sim::physics::{simulate_session, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;

/// The layer tables' own check fits each fold's tables on the fold's rows;
/// the changes after them are validated with the tables held. The first of
/// them is judged against the tables' model validated that same way, not
/// against the tables' check (0.670 mm there, 0.567 held, on this device:
/// an offset on string 4 was taken on the 15 % between the two).
#[test]
fn the_change_after_the_layer_tables_is_judged_against_them_validated_as_it_is() {
    use spidar::model::diagnose::LoopConfig;
    use spidar::model::validate::{validate, FoldScope};
    let (full, train, nominal) = loop_with(1, &[], &LoopConfig::default());
    let (tables, _, _) = loop_with(
        1,
        &[],
        &LoopConfig {
            max_effects: 2,
            ..LoopConfig::default()
        },
    );
    assert_eq!(tables.stages.len(), 2);
    assert_eq!(
        tables.stages[1].name,
        "layers strings [0, 1, 2, 3, 4, 5, 6, 7]"
    );
    let held = validate(
        &train,
        &nominal,
        &tables.identification,
        &tables.structure,
        FoldScope::Judged,
    )
    .unwrap();
    let next = full.findings.iter().find(|f| {
        f.family != spidar::model::diagnose::Family::Layers
            && f.family != spidar::model::diagnose::Family::Winding
            && f.validation.is_some()
    });
    let check = next.unwrap().validation.as_ref().unwrap();
    assert_eq!(check.before.held.mean_mm, held.held.mean_mm);
    let own = tables.stages[1].finding.validation.as_ref().unwrap();
    assert!(
        held.held.mean_mm < own.after.held.mean_mm,
        "held {} vs the tables' check {}",
        held.held.mean_mm,
        own.after.held.mean_mm
    );
    assert!(tables.stages[1]
        .finding
        .description
        .contains(&format!("judged against {:.3} mm", held.held.mean_mm)));
}

/// A clean independent device: its spools differ in width and are layered
/// (declared physics), so the loop frees each spool's thinning rate and
/// adds layer tables first, each checked on blocked folds; whatever it adds
/// after them lowered the blocked-fold error by the loop's minimum gain, and
/// every candidate it tested and refused is reported `added: false` with
/// the check that refused it.
#[test]
fn a_clean_independent_device_gets_spool_rates_and_layer_tables_first_and_each_decision_says_why() {
    use spidar::model::diagnose::{Family, LoopConfig};
    use spidar::model::validate::Folds;
    let r = clean_loop(1);
    assert_eq!(
        r.stages[0].name,
        "spool rates strings [0, 1, 2, 3, 4, 5, 6, 7]"
    );
    let rates = &r.stages[0].finding;
    assert_eq!(rates.family, Family::Winding);
    assert!(rates.validation.as_ref().unwrap().accepted);
    assert!(r
        .identification
        .winding
        .kappa_each_mm
        .iter()
        .any(|k| k.abs() > 1e-4));
    assert_eq!(r.stages[1].name, "layers strings [0, 1, 2, 3, 4, 5, 6, 7]");
    let layers = &r.stages[1].finding;
    assert_eq!(layers.family, Family::Layers);
    let check = layers.validation.as_ref().unwrap();
    assert!(
        check.accepted && check.reason.starts_with("added"),
        "{}",
        check.reason
    );
    assert_eq!(check.after.folds, Folds::Blocked);
    assert!(check.after.held.mean_mm < 0.8 * check.before.held.mean_mm);
    let min_gain = LoopConfig::default().min_relative_gain;
    for stage in &r.stages[2..] {
        let gain = 1.0 - stage.validation_after_mm / stage.validation_before_mm;
        assert!(gain >= min_gain, "{}: {gain}", stage.name);
        assert!(stage.finding.added && stage.finding.family != Family::Layers);
    }
    // Every string got a spacing that lowered its held-out residual, and
    // the final model's laws carry the tables.
    assert_eq!(r.layers.len(), 8);
    for (i, c) in r.layers.iter().enumerate() {
        assert!(c.step_counts.is_some(), "string {i}: {c:?}");
        assert!(c.held_rms_with_mm < c.held_rms_without_mm, "{c:?}");
        assert!(!r.identification.laws[i].layers.is_empty());
        assert!(c.peak_to_peak_mm > 1.0 && c.peak_to_peak_mm < 8.0, "{c:?}");
    }
    let tested: Vec<_> = r
        .findings
        .iter()
        .filter(|f| f.family != Family::Layers && f.validation.is_some() && !f.added)
        .collect();
    assert!(!tested.is_empty(), "findings: {:#?}", r.findings);
    for f in &tested {
        let check = f.validation.as_ref().unwrap();
        assert!(!f.added && !check.accepted, "{f:#?}");
        assert!(check.reason.starts_with("not added: "), "{}", check.reason);
        assert_eq!(check.after.folds, Folds::Blocked);
        // The blocked folds hold out every row once in time and the outer
        // shell once more; the interleaved folds are fitted only for a
        // step in time.
        assert!(check.before.held.n > r.base_train.n, "{check:#?}");
        assert_eq!(
            check.after.interleaved.is_some(),
            f.family == Family::Slip,
            "{f:#?}"
        );
    }
    // In the JSON report: `validation` with its reason.
    let json = serde_json::to_value(tested[0]).unwrap();
    assert_eq!(json["added"], false);
    assert!(json["validation"]["reason"]
        .as_str()
        .unwrap()
        .contains("not added"));
}

/// A term of the whole frame or the tracked body below the three strongest
/// proposals is tried when they are refused: on clean independent seed 6
/// the marker offset (the independent device's marker sits 8..15 mm off
/// the strings' meeting point) was left under per-string proposals the
/// loop refused (test 0.391 mm); tried, it lowers the blocked folds' mean
/// by 30 % and the test error to 0.370.
#[test]
fn a_frame_wide_term_below_the_three_strongest_is_tried() {
    use spidar::model::diagnose::Family;
    let r = clean_loop(6);
    let stage = r
        .stages
        .iter()
        .find(|s| s.finding.family == Family::Marker)
        .unwrap_or_else(|| panic!("stages: {:?}", names(&r)));
    assert!(stage.finding.added);
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.38, "{test:?}");
}

/// The model simulator's spools follow the smooth law exactly: no string
/// gets a table (the spacing must lower the held-out residual by 3 %).
#[test]
fn a_clean_model_device_gets_no_layer_table() {
    use spidar::data::observe::observations;
    use spidar::model::diagnose::{close_loop, LoopConfig};
    use spidar::model::identify::Start;
    let device =
        spidar::sim::SimulatedDevice::new(&spidar::sim::config::SimConfig::default(), 1).unwrap();
    let train = spidar::sim::simulate_session(&device, SessionKind::Lattice, 101).unwrap();
    let r = close_loop(
        &observations(&train.samples),
        None,
        &device.nominal.nominal_frame(),
        &Start::from_geometry(&device.nominal),
        &LoopConfig::default(),
    )
    .unwrap();
    assert!(
        r.stages.is_empty(),
        "{:?}",
        r.stages.iter().map(|s| &s.name).collect::<Vec<_>>()
    );
    assert!(
        r.layers.iter().all(|c| c.step_counts.is_none()),
        "{:#?}",
        r.layers
    );
    assert!(r.identification.laws.iter().all(|l| l.layers.is_empty()));
}

#[test]
fn a_small_session_falls_back_to_interleaved_folds() {
    use spidar::data::observe::observations;
    use spidar::model::identify::{identify, Start, Structure};
    use spidar::model::validate::{validate, FoldScope, Folds, MIN_BLOCKED_ROWS};
    let device = PhysicsDevice::new(&quiet_config(), 2).unwrap();
    let (train, _) = simulate_session(&device, SessionKind::Random { points: 150 }, 3).unwrap();
    let obs = observations(&train.samples);
    assert!(obs.len() < MIN_BLOCKED_ROWS);
    let nominal = device.nominal.nominal_frame();
    let structure = Structure::default();
    let id = identify(
        &obs,
        &nominal,
        &Start::from_geometry(&device.nominal),
        &structure,
    )
    .unwrap();
    let v = validate(&obs, &nominal, &id, &structure, FoldScope::WithInterleaved).unwrap();
    assert_eq!(v.folds, Folds::Interleaved);
    assert_eq!(Some(v.held), v.interleaved);
    assert!(v.noise_p95_mm > 0.0 && v.noise_max_mm > 0.0);
}

/// A clean independent device's 60 s training stream over the central part
/// of its workspace (seed 2, as `physics_bench`'s `stream` case). Its
/// spools thin at their own rates (their layers hold 5.6 to 10.5 turns),
/// but tried first, before the layer tables, the rates are refused: the
/// outer shell's fold, fitted on the inner region, extrapolates them by
/// mm (its max 3.53 -> 5.50 mm). Tried again once the tables and the
/// effects are in, they are taken, and the finding says why they were
/// refused at first (decision record 0065).
#[test]
fn spool_rates_refused_before_the_tables_are_tried_again_after_them() {
    let device = PhysicsDevice::new(&PhysicsConfig::default(), 2).unwrap();
    let stream = |rows, area, seed| {
        simulate_session(&device, SessionKind::Stream { rows, area }, seed)
            .unwrap()
            .0
    };
    let train = stream(
        device.config.stream.rows,
        spidar::sim::StreamArea::Training,
        5,
    );
    let test = stream(1000, spidar::sim::StreamArea::Whole, 6);
    let c = calibrate_quick(&device, &train, &test);
    let rates: Vec<&spidar::model::diagnose::Finding> = c
        .report
        .effects
        .iter()
        .filter(|f| f.family == spidar::model::diagnose::Family::Winding && f.strings.len() == 8)
        .collect();
    for f in &rates {
        println!("{}: {}", f.added, f.description);
    }
    assert_eq!(rates.len(), 1, "one finding of the spool rates");
    assert!(rates[0].added, "{}", rates[0].description);
    assert!(
        rates[0].description.contains("tried again")
            && rates[0]
                .description
                .contains("first try, before them: not added"),
        "{}",
        rates[0].description
    );
}
