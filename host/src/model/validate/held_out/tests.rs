use super::*;

/// A step is judged on the interleaved folds and the blocked folds kept.
#[test]
fn a_step_is_judged_on_the_interleaved_folds_and_the_folds_that_straddle_it() {
    let v = Validation {
        folds: Folds::Blocked,
        held: ErrorStats::of(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
        interleaved: Some(ErrorStats::of(&[0.5, 0.5])),
        noise_p95_mm: 0.0,
        noise_max_mm: 0.0,
        held_errors: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        fold_sizes: vec![1, 2, 3],
        interleaved_errors: vec![0.5, 0.5],
        held_inconsistent: vec![false, false, true, false, false, false],
        interleaved_inconsistent: vec![true, false],
    };
    let step = v.for_step(&[true, false, true]);
    assert_eq!(step.held_errors, vec![0.5, 0.5, 1.0, 4.0, 5.0, 6.0]);
    assert_eq!(
        step.held_inconsistent,
        vec![true, false, false, false, false, false]
    );
    assert_eq!(step.fold_sizes, vec![2, 1, 3]);
    assert_eq!(step.held.n, 6);
    let means: Vec<f64> = fold_means(&step).collect();
    assert_eq!(means, vec![0.5, 1.0, 5.0]);
    assert!((step.held.mean_mm - 17.0 / 6.0).abs() < 1e-12);
    // Interleaved-only validations have nothing else to drop.
    let small = Validation {
        folds: Folds::Interleaved,
        ..v.clone()
    };
    assert_eq!(small.for_step(&[false]).held_errors, v.held_errors);
}

/// Forward chaining: every fit is earlier than the rows it predicts, in the
/// session's time (not its row order), and a small session has none.
#[test]
fn forward_folds_fit_the_past_and_predict_the_future() {
    use super::super::folds::{forward_folds, MIN_BLOCKED_ROWS};
    let rows: Vec<Observation> = (0..400)
        .map(|k| Observation {
            row: k,
            // Rows not in time order: the folds follow t_s.
            t_s: ((k * 7919) % 400) as f64,
            inputs: Default::default(),
            tension_n: [0.0; spidar_core::STRINGS],
            tracker: Some([0.0; 3]),
            tracker_rotation: None,
            legacy: None,
            new_home: false,
        })
        .collect();
    let tracked: Vec<&Observation> = rows.iter().collect();
    let folds = forward_folds(&tracked);
    assert_eq!(folds.len(), 2);
    let t = |k: &usize| tracked[*k].t_s;
    for (fit, held) in &folds {
        let latest_fit = fit.iter().map(t).fold(f64::MIN, f64::max);
        let earliest_held = held.iter().map(t).fold(f64::MAX, f64::min);
        assert!(
            latest_fit < earliest_held,
            "{latest_fit} >= {earliest_held}"
        );
    }
    assert_eq!((folds[0].0.len(), folds[0].1.len()), (200, 100));
    assert_eq!((folds[1].0.len(), folds[1].1.len()), (300, 100));
    assert!(forward_folds(&tracked[..MIN_BLOCKED_ROWS - 1]).is_empty());
}
