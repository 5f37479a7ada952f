//! Clean independent devices (decision record 0058): a term of one string
//! taken where a term of the whole device explains the rows better is
//! replaced by it, and a shared term's halves are judged by the rows the
//! session's errors are worth. What the loop names on these devices is
//! the physics they have: no term on time, the strings' stretch at its
//! size rather than a sag thirty times the strings' weight.

use crate::sim_physics::{loop_of_device, loop_with};
use crate::{last_test_mean, stage_names};
use spidar::model::diagnose::{Family, LoopConfig, LoopResult};
use spidar::sim::physics::{PhysicsConfig, PhysicsDevice};
use spidar_core::model::Effect;

/// Whether the model holds a term on time (a drift or a creep).
fn has_time_term(r: &LoopResult) -> bool {
    r.identification
        .effects
        .iter()
        .any(|t| matches!(t.effect, Effect::Drift { .. } | Effect::Creep { .. }))
}

/// Device 6: a creep on string 6 passed every check just before the
/// marker offset (test 0.354 -> 0.476 mm); tried from the model without
/// it, the marker offset gains more on the blocked folds (0.569 -> 0.373
/// against the creep's 0.524), and takes its place. No term on time is
/// left, and the test ends below the 0.365 mm the device reached before
/// either rule.
#[test]
fn a_clean_device_s_marker_offset_is_taken_before_a_creep_of_one_string() {
    let (r, _, _) = loop_with(6, &[], &LoopConfig::default());
    let after = last_test_mean(&r);
    println!("{:?}: {after:.3} mm", stage_names(&r));
    assert!(!has_time_term(&r), "{:?}", stage_names(&r));
    assert!(stage_names(&r).contains(&"marker offset (tracked body)"));
    assert!(after < 0.35, "{after:.3} mm");
}

/// Device 11 without the abnormal motor: a drift on string 5 before the
/// marker offset took the test session from 0.335 mm to 0.490; the marker
/// offset comes first now, and no term of one string on time is taken (a
/// drift of every string may be: 0.332 -> 0.339 mm, record 0058's limit).
#[test]
fn no_drift_of_one_string_stands_in_for_the_marker_offset() {
    let mut config = PhysicsConfig::default();
    config.abnormal_motor.enabled = false;
    let (r, _, _) = loop_of_device(11, &config, &LoopConfig::default());
    let after = last_test_mean(&r);
    println!("{:?}: {after:.3} mm", stage_names(&r));
    assert!(
        !stage_names(&r)
            .iter()
            .any(|n| n.starts_with("drift string ") || n.starts_with("creep string ")),
        "{:?}",
        stage_names(&r)
    );
    assert!(after < 0.36, "{after:.3} mm");
}

/// Devices 7 and 20: the strings' stretch (refused before by its halves,
/// whose sds counted every row as independent) is named, where a sag of 27
/// and 43 times the strings' weight stood in: each string's own stretch
/// (their stiffness 10-30 kN; decision record 0061).
#[test]
fn a_clean_device_s_stretch_is_named_and_no_sag_stands_in() {
    let stretch = "elasticity strings [0, 1, 2, 3, 4, 5, 6, 7]";
    for seed in [7, 20] {
        let (r, _, _) = loop_with(seed, &[], &LoopConfig::default());
        println!(
            "device {seed}: {:?}: {:.3} mm",
            stage_names(&r),
            last_test_mean(&r)
        );
        assert!(stage_names(&r).contains(&stretch), "{:?}", stage_names(&r));
        assert!(!stage_names(&r).contains(&"sag (every string)"));
        let ratio = compliance_against_truth(seed, &r);
        println!("device {seed}: the strings' 1/EA at {ratio:.2}x their truth");
        assert!((0.75..1.33).contains(&ratio), "{ratio:.2}x");
        // And no worse held out than the one stretch of every string.
        let (shared, _, _) = loop_with(
            seed,
            &[],
            &LoopConfig {
                stretches_of_each_string: false,
                ..LoopConfig::default()
            },
        );
        assert!(
            stage_names(&shared).contains(&"elasticity (every string)"),
            "{:?}",
            stage_names(&shared)
        );
        assert!(
            last_test_mean(&r) <= last_test_mean(&shared) + 0.005,
            "{:.3} against {:.3} mm",
            last_test_mean(&r),
            last_test_mean(&shared)
        );
    }
}

/// The strings' stretch at the size of their own: the mean of the fitted
/// 1/EA of `r`'s model against the mean of the true (one string's alone
/// can be far off where its rows say little).
fn compliance_against_truth(seed: u64, r: &LoopResult) -> f64 {
    let device = PhysicsDevice::new(&PhysicsConfig::default(), seed).unwrap();
    let (mut fitted, mut truth) = (0.0, 0.0);
    for term in &r.identification.effects {
        if let Effect::Stretch { per_newton, .. } = term.effect {
            if let Some(s) = device.strings.get(usize::from(term.string)) {
                fitted += per_newton;
                truth += 1.0 / s.stiffness_n;
            }
        }
    }
    fitted / truth
}

/// Device 5, the abnormal motor's: a shared sag of 30 times the strings'
/// weight (test 0.383 mm) was taken where each string's stretch, ranked
/// below it by its chi-square over 16 columns, was never tried. Tried
/// from the model without the sag, the stretches gain on the sag's
/// blocked folds as a change must and take its place, at the strings'
/// size; the sag is reported replaced (decision record 0063).
#[test]
fn each_string_s_stretch_replaces_a_sag_that_ranked_above_it() {
    let (r, _, _) = loop_with(5, &[], &LoopConfig::default());
    let after = last_test_mean(&r);
    println!("{:?}: {after:.3} mm", stage_names(&r));
    assert!(
        stage_names(&r).contains(&"elasticity strings [0, 1, 2, 3, 4, 5, 6, 7]"),
        "{:?}",
        stage_names(&r)
    );
    assert!(!stage_names(&r).contains(&"sag (every string)"));
    let sag = r
        .findings
        .iter()
        .find(|f| !f.added && f.family == Family::Sag)
        .and_then(|f| f.validation.as_ref())
        .expect("the sag reported");
    assert!(
        sag.reason
            .starts_with("not added: replaced by elasticity strings"),
        "{}",
        sag.reason
    );
    let ratio = compliance_against_truth(5, &r);
    println!("the strings' 1/EA at {ratio:.2}x their truth");
    assert!((0.75..1.33).contains(&ratio), "{ratio:.2}x");
    assert!(after < 0.375, "{after:.3} mm");
}
