use super::*;

/// A step is judged on the interleaved folds and the blocked folds kept.
#[test]
fn a_step_is_judged_on_the_interleaved_folds_and_the_folds_that_straddle_it() {
    let v = Validation {
        folds: Folds::Blocked,
        held: ErrorStats::of(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
        interleaved: ErrorStats::of(&[0.5, 0.5]),
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
