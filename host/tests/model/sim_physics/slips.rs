//! Slips: found on their strings, at their times, sized, and told from
//! errors that come and go.

use super::fixtures::{clean_loop, loop_on, names};
use crate::slips_of;

/// The abnormal motor's string off its groove while the walk crosses its
/// region jumps and falls back: no slip. On clean independent seed 11 the
/// jump of string 4 at 1759 s (-1.9 mm over 15 rows, -0.2 mm beyond them)
/// had been added as a slip, raising the test error from 0.351 to 0.366 mm.
#[test]
fn an_error_that_comes_and_goes_is_not_a_slip() {
    use spidar::model::diagnose::Family;
    let r = clean_loop(11);
    assert!(
        r.findings
            .iter()
            .all(|f| !(f.family == Family::Slip && f.added)),
        "stages: {:?}",
        names(&r)
    );
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.36, "{test:?}");
}

/// A string that slipped 419 s into a 4800 s lattice (independent device of
/// seed 2: one slip, string 6, 4.6 mm, a few rows into the lattice's second
/// plane) is a slip, not an offset: 91 % of its rows read the slipped
/// length, and the blocked folds alone could not tell a constant from a
/// step there (the fold that fits the later half never sees the string
/// before the slip), so a step in time is judged on the interleaved folds
/// and the blocked folds whose fit rows straddle it. The test session (a
/// new session from home, no slip) then follows the string as it was
/// before the slip: with an offset it was off by the slip's 4.6 mm (2.05
/// mm test mean before this rule, 0.72 after).
#[test]
fn a_slip_early_in_a_session_is_added_as_a_slip_not_an_offset() {
    use spidar::model::diagnose::Family;
    let r = loop_on(2, &["slip"]);
    let slip = r
        .stages
        .iter()
        .find(|s| s.name == "slip string 6")
        .unwrap_or_else(|| panic!("stages: {:?}", names(&r)));
    assert_eq!(slip.finding.family, Family::Slip);
    let reason = &slip.finding.validation.as_ref().unwrap().reason;
    assert!(
        reason.contains("interleaved folds (a step in time)")
            && reason.contains("without the earlier half"),
        "{reason}"
    );
    assert!(
        !r.stages.iter().any(|s| s.name == "offset string 6"),
        "{:?}",
        names(&r)
    );
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 1.0, "{test:?}");
}

/// Two early slips (independent seed 3: string 3 at row 39 of 2197, -4.19
/// mm; string 6 at row 230, +4.66 mm): both found and sized. The rows
/// before them are few and in one corner of the lattice; the layer tables,
/// functions of the counts, were fitted on residuals with the steps in them
/// and took part of them, so the slips came out at 2.26 and 3.56 mm (the
/// test session, which starts before them, at 1.03 mm). A slip is now
/// fitted together with the tables (`layers::fit_table_with_slips`) and
/// judged with every string in the kinematics.
#[test]
fn early_slips_are_sized_with_the_layer_tables() {
    use spidar_core::model::Effect;
    let r = loop_on(3, &["slip"]);
    let slip = |string: u8| {
        r.identification
            .effects
            .iter()
            .find_map(|t| match t.effect {
                Effect::Slip { mm, .. } if t.string == string => Some(mm),
                _ => None,
            })
            .unwrap_or_else(|| panic!("no slip on string {string}: {:?}", names(&r)))
    };
    // The model's length steps the other way from what the spool gave out.
    let (s3, s6) = (slip(3), slip(6));
    assert!((s3.abs() - 4.19).abs() < 0.15 * 4.19, "string 3: {s3} mm");
    assert!((s6.abs() - 4.66).abs() < 0.15 * 4.66, "string 6: {s6} mm");
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.45, "{test:?}");
}

/// Asserts that `slips` holds each of `truth` (string, time, mm: the
/// simulator's) on its string within 10 s of its time and 15 % of its size,
/// and nothing else.
fn assert_slips(slips: &[(u8, f64, f64)], truth: &[(u8, f64, f64)]) {
    for &(string, at_s, mm) in truth {
        let found = slips
            .iter()
            .find(|s| s.0 == string && (s.1 - at_s).abs() < 10.0)
            .unwrap_or_else(|| panic!("no slip on string {string} at {at_s} s: {slips:?}"));
        // The model's length steps the other way from what the spool gave out.
        assert!(
            (found.2.abs() - mm).abs() < 0.15 * mm,
            "string {string} at {at_s} s: {} mm for {mm}",
            found.2
        );
    }
    assert_eq!(slips.len(), truth.len(), "{slips:?}");
}

/// Five strings slipped during one lattice (independent seed 1: strings 7,
/// 0, 3, 4, 2 at rows 620, 1153, 1322, 1578, 1825 of 2197). Each step alone
/// left the four others to the rest of the model and raised the held-out
/// p95, and the layer tables, bent by the steps, were refused: the loop
/// stopped with three found, two of them at the wrong time (test mean 0.73
/// mm). The steps are now placed off the model, tried together when none
/// helps alone, and looked for again once the tables are in.
#[test]
fn five_slips_of_one_session_are_found_on_their_strings() {
    let r = loop_on(1, &["slip"]);
    assert_slips(
        &slips_of(&r),
        &[
            (7, 1388.6, 2.69),
            (0, 2572.8, 2.71),
            (3, 2931.9, 4.25),
            (4, 3502.5, 3.41),
            (2, 4021.1, 3.58),
        ],
    );
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.45, "{test:?}");
}

/// One string slipped twice (independent seed 4: string 5 at rows 126 and
/// 704, -4.72 and +3.15 mm): both steps are found, the second off the model
/// that holds the first (one slip a string was all the loop tried: test
/// mean 0.93 mm), and both are in the report.
#[test]
fn a_string_that_slipped_twice_gets_both_steps() {
    let r = loop_on(4, &["slip"]);
    assert_slips(&slips_of(&r), &[(5, 288.0, 4.72), (5, 1548.8, 3.15)]);
    // The report keeps both: the second did not replace the first.
    let reported = r
        .findings
        .iter()
        .filter(|f| f.added && f.family == spidar::model::diagnose::Family::Slip)
        .count();
    assert_eq!(reported, 2, "{:?}", r.findings);
    let test = r.stages.last().unwrap().test.unwrap();
    assert!(test.mean_mm < 0.45, "{test:?}");
}
