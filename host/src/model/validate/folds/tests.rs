//! Tests of the folds.

use super::*;

#[test]
fn small_sessions_hold_out_a_tenth_and_leave_enough_to_fit() {
    // 12 rows, 10 to fit: 10 folds of 1 or 2 held-out rows, every row
    // held out once.
    let f = small_session_folds(12, 10).unwrap();
    assert_eq!(f.len(), 10);
    for (fit, held) in &f {
        assert!(
            fit.len() >= 10 && (1..=2).contains(&held.len()),
            "{fit:?} {held:?}"
        );
    }
    let mut held: Vec<usize> = f.iter().flat_map(|(_, h)| h.clone()).collect();
    held.sort_unstable();
    assert_eq!(held, (0..12).collect::<Vec<_>>());
    // Below ten rows, leave-one-out.
    assert_eq!(small_session_folds(9, 8).unwrap().len(), 9);
    // As many rows as the fit needs: nothing can be held out.
    assert!(small_session_folds(10, 10).is_none());
}

/// A choice beside the model is judged on the blocked folds from
/// [`MIN_BLOCKED_ROWS`] tracked rows, on ten interleaved ones below, and on
/// none when no row can be spared; each named.
#[test]
fn choices_are_judged_on_folds_the_session_can_spare() {
    use crate::data::dataset::Sample;
    use crate::data::observe::observations;
    let rows = |n: usize| {
        let samples: Vec<Sample> = (0..n)
            .map(|k| Sample {
                t_s: k as f64,
                counts: [0; spidar_core::STRINGS],
                tracker: Some([(k % 7) as f64, (k % 11) as f64, (k % 13) as f64]),
                orientation: None,
                legacy: None,
                tension_n: None,
                since_home_s: None,
                home: None,
            })
            .collect();
        observations(&samples)
    };
    let names = |n: usize, needed: usize| {
        let obs = rows(n);
        let tracked: Vec<&crate::data::observe::Observation> = obs.iter().collect();
        let (name, folds) = choice_folds(&tracked, needed);
        (name, folds.len())
    };
    assert_eq!(names(12, 10), ("10 interleaved folds".to_string(), 10));
    assert_eq!(names(10, 10), ("none".to_string(), 0));
    let (blocked, k) = names(MIN_BLOCKED_ROWS, 40);
    assert!(
        blocked.starts_with("blocked folds") && k >= 2,
        "{blocked} {k}"
    );
}
