//! Creep (issue 33, point 2): a string whose natural length grows by a
//! share of itself with time since home is counted short by that share of
//! its whole length, `per_s * t * (home_length + payout)`. The loop names
//! it on the model simulator where it is injected (one string's, or one
//! rate on every string), at its size, closes the held-out error, and adds
//! none to a clean device.

use crate::{added, lattice_loop as run};
use spidar::model::diagnose::{Family, LoopResult, Variable};
use spidar_core::model::{Effect, EVERY_STRING};

fn creeps_of(result: &LoopResult) -> Vec<(u8, f64)> {
    result
        .identification
        .effects
        .iter()
        .filter_map(|t| match t.effect {
            Effect::Creep { per_s } => Some((t.string, per_s)),
            _ => None,
        })
        .collect()
}

/// 720 ppm/h on string 2 (0.8 mm on a metre of string by the lattice's
/// end): a creep on string 2 within 25 % of its rate, found against time,
/// and the held-out error within 1.3 times the same device's without it.
#[test]
fn a_creep_on_one_string_is_found_at_its_rate_and_closed() {
    let rate = 2e-7;
    let (result, after) = run(1, &["creep:2:per_s=2e-7"]);
    let (_, clean) = run(1, &[]);
    let found = added(&result);
    let creeps = creeps_of(&result);
    println!("added {found:?}; creeps {creeps:?}; after {after:.3} mm, clean {clean:.3} mm");
    assert!(
        found.contains(&(Family::Creep, vec![2], Variable::Time)),
        "{found:?}"
    );
    assert!(
        creeps
            .iter()
            .all(|&(s, r)| s == 2 && (r / rate - 1.0).abs() < 0.25),
        "{creeps:?}"
    );
    assert!(
        after <= 1.3 * clean,
        "after {after:.3} mm, clean {clean:.3} mm"
    );
}

/// 540 ppm/h on every string: one shared creep within 25 % of its rate,
/// and the held-out error within 1.3 times the clean device's.
#[test]
fn a_creep_of_every_string_is_one_shared_rate() {
    let rate = 1.5e-7;
    let (result, after) = run(2, &["creep:*:per_s=1.5e-7"]);
    let (_, clean) = run(2, &[]);
    let found = added(&result);
    let creeps = creeps_of(&result);
    println!("added {found:?}; creeps {creeps:?}; after {after:.3} mm, clean {clean:.3} mm");
    assert!(
        found.contains(&(Family::Creep, vec![], Variable::Time)),
        "{found:?}"
    );
    let shared: Vec<f64> = creeps
        .iter()
        .filter(|(s, _)| *s == EVERY_STRING)
        .map(|(_, r)| *r)
        .collect();
    assert!(
        shared.len() == 1 && (shared[0] / rate - 1.0).abs() < 0.25,
        "{creeps:?}"
    );
    assert!(
        after <= 1.3 * clean,
        "after {after:.3} mm, clean {clean:.3} mm"
    );
}

/// Clean model-simulator devices (no creep in their physics): no creep
/// term.
#[test]
fn a_clean_device_gains_no_creep() {
    for seed in [1, 2, 3] {
        let (result, _) = run(seed, &[]);
        assert!(
            creeps_of(&result).is_empty(),
            "seed {seed}: {:?}",
            added(&result)
        );
    }
}

/// The independent simulator's thermal creep (`drift-all`, 300 ppm/h of
/// every string, 0.4 mm on a metre over the lattice), device 2: where the
/// lattice comes back to a place the creep as fitted on every row would
/// explain 13.6 (chi-square), under the 40 the revisits hold a term to;
/// they fit it there at 12.2, 0.95x the every-row rate, and confirm it
/// (decision record 0062). The shared creep is added at its size and the
/// test session ends within 1.05x the same device's without the creep
/// (0.424 mm before, 0.350 with it, the clean device 0.343).
#[test]
fn the_independent_devices_thermal_creep_is_confirmed_where_revisited_and_closed() {
    use crate::last_test_mean;
    use crate::sim_physics::loop_with;
    use spidar::model::diagnose::LoopConfig;
    let (creeping, _, _) = loop_with(2, &["drift-all"], &LoopConfig::default());
    let (clean, _, _) = loop_with(2, &[], &LoopConfig::default());
    let (after, baseline) = (last_test_mean(&creeping), last_test_mean(&clean));
    let creeps = creeps_of(&creeping);
    println!("creeps {creeps:?}; after {after:.3} mm, the clean device {baseline:.3} mm");
    let truth = 300e-6 / 3600.0;
    assert!(
        creeps.len() == 1
            && creeps[0].0 == EVERY_STRING
            && (0.5..2.0).contains(&(creeps[0].1 / truth)),
        "{creeps:?} against {truth:.3e}"
    );
    assert!(after <= 1.05 * baseline, "{after:.3} against {baseline:.3}");
    assert!(creeps_of(&clean).is_empty());
}
