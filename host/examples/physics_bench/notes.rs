//! The notes under the tables: where sessions slipped, the test session of
//! the training's home, creep against the truth, what the loop left out.

use spidar::data::stats::ErrorStats;
use spidar::model::diagnose::{family_name, variable_name, Family};
use spidar::model::validate::{later_session_errors, model_errors};
use spidar::procedures::calibrate::Calibrated;
use spidar::sim::physics::{PhysicsDevice, PhysicsTruth};
use spidar_core::model::{Effect, EVERY_STRING};

/// The slips of a session from its truths: (row, string, mm) of each step
/// (each string starts unslipped at home).
pub(super) fn slip_steps(truths: &[PhysicsTruth]) -> Vec<(usize, usize, f64)> {
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
pub(super) fn test_session_slips(test_truths: &[PhysicsTruth], c: &Calibrated) -> Option<String> {
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
pub(super) fn home_judged(c: &Calibrated) -> String {
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
pub(super) fn creep_against_truth(device: &PhysicsDevice, c: &Calibrated) -> Option<String> {
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

/// The loop's findings that were not added (significant but no help, or
/// unexplained), one line.
pub(super) fn not_added(c: &Calibrated) -> String {
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
