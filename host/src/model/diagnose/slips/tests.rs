use nalgebra::{DMatrix, DVector};

use super::*;

/// [`StepSearch`] over `rows` (key, row) in key order, their weights,
/// projected residual and the model's orthonormal basis (a row per row).
fn best_step_off_model(
    rows: &[(f64, usize)],
    weights: &[f64],
    residual: &DVector<f64>,
    basis: &DMatrix<f64>,
) -> Option<(f64, f64)> {
    let mut search = StepSearch::new(rows.len());
    for &(key, k) in rows.iter().rev() {
        let b: Vec<f64> = basis.row(k).iter().copied().collect();
        search.add(key, weights[k], residual[k], &b);
    }
    search.best()
}

/// The best step of a residual off the model: where the residual steps,
/// though a model direction that turns over around that time (a
/// coordinate of a lattice walked plane by plane) absorbed most of it and
/// a slow ramp the model lacks moved the raw residual's largest mean
/// difference elsewhere; none with too few rows, nor on the edge of the
/// allowed range.
#[test]
fn the_best_step_is_found_off_the_model_where_the_residual_steps() {
    let n = 500;
    let keys: Vec<f64> = (0..n).map(|k| k as f64).collect();
    let orthonormal = |columns: Vec<DVector<f64>>| {
        DMatrix::from_columns(&columns)
            .qr()
            .q()
            .columns(0, 2)
            .into_owned()
    };
    let basis = orthonormal(vec![
        DVector::from_element(n, 1.0),
        DVector::from_iterator(n, keys.iter().map(|k| ((k - 125.0) / 50.0).tanh())),
    ]);
    let truth = DVector::from_iterator(
        n,
        keys.iter()
            .map(|&k| if k >= 125.0 { -3.0 } else { 0.0 } + 2.0 * k / n as f64),
    );
    let residual = &truth - &basis * (basis.transpose() * &truth);
    let rows: Vec<(f64, usize)> = keys.iter().copied().zip(0..n).collect();
    let weights = vec![1.0; n];
    let (_, at) = best_step_off_model(&rows, &weights, &residual, &basis).unwrap();
    assert!((at - 124.5).abs() < 1e-9, "{at}");
    // The raw residual's largest mean difference lies far from the step.
    let mean_difference = |j: usize| {
        let (a, b) = (residual.rows(0, j).mean(), residual.rows(j, n - j).mean());
        (a - b).powi(2) * (j * (n - j)) as f64
    };
    let raw = (20..n - 20)
        .max_by(|&a, &b| mean_difference(a).total_cmp(&mean_difference(b)))
        .unwrap();
    assert!(raw.abs_diff(125) > 100, "{raw}");
    assert!(best_step_off_model(&rows[..39], &weights, &residual, &basis).is_none());
    // The first rows alone off: the best split is on the edge, no step.
    let start = DVector::from_iterator(n, (0..n).map(|k| if k < 10 { 2.0 } else { 0.0 }));
    let basis = orthonormal(vec![
        DVector::from_element(n, 1.0),
        DVector::from_iterator(n, keys.iter().map(|k| k / n as f64)),
    ]);
    let residual = &start - &basis * (basis.transpose() * &start);
    assert_eq!(
        best_step_off_model(&rows, &weights, &residual, &basis),
        None
    );
}

/// A slip's jump stands out among the string's jumps at every row; a
/// bump the first rows make (a position error of their corner), a jump
/// of the other sign or of a fraction of the step, and a jammed
/// encoder's single far row do not.
#[test]
fn a_slip_jumps_where_it_slipped_and_a_bump_does_not() {
    // Rows a path apart: a residual that follows position, plus noise.
    let path = |k: usize| 0.6 * (k as f64 / 23.0).sin() + 0.2 * ((k * 7919) % 13) as f64 / 13.0;
    let slipped: Vec<f64> = (0..400)
        .map(|k| path(k) + if k >= 200 { 3.0 } else { 0.0 })
        .collect();
    assert!(jumps_where_it_slipped(&slipped, 200, 3.0));
    assert!(!jumps_where_it_slipped(&slipped, 200, -3.0));
    assert!(!jumps_where_it_slipped(&slipped, 200, 7.0));
    assert!(!jumps_where_it_slipped(&slipped, 120, 3.0));
    // The first 25 rows rise and fall by 1.2 mm, as the first rows of a
    // lattice in their corner did: their mean differs from the rest,
    // but they do not jump.
    let bump: Vec<f64> = (0..400)
        .map(|k| {
            let b = if k < 25 {
                1.2 * (std::f64::consts::PI * k as f64 / 25.0).sin()
            } else {
                0.0
            };
            path(k) + b
        })
        .collect();
    assert!(!jumps_where_it_slipped(&bump, 21, -0.8));
    // The first 96 rows swing by 1.6 mm every 16 rows (a region the
    // model fits worse): a jump there stands out among the quiet rest
    // but not among its neighbours'.
    let swinging: Vec<f64> = (0..400)
        .map(|k| {
            let swing = if k < 96 && (k / 16) % 2 == 1 {
                1.6
            } else {
                0.0
            };
            path(k) + swing
        })
        .collect();
    assert!(!jumps_where_it_slipped(&swinging, 48, 1.6));
    // A jammed encoder: one row 10 mm off.
    let mut jammed: Vec<f64> = (0..400).map(path).collect();
    jammed[200] = -10.0;
    assert!(!jumps_where_it_slipped(&jammed, 200, -3.0));
    assert!(!jumps_where_it_slipped(&jammed, 201, 3.0));
    // An error that comes and goes: the abnormal motor's string off its
    // groove for 40 rows, then back. It jumps where it starts, but the
    // rows beyond the jump's window are back where they were: no slip.
    let visit: Vec<f64> = (0..400)
        .map(|k| path(k) + if (200..240).contains(&k) { 2.0 } else { 0.0 })
        .collect();
    assert!(!jumps_where_it_slipped(&visit, 200, 2.0));
    // A slip 20 rows from the end: no rows beyond its window to hold
    // it against, its jump alone decides.
    let late: Vec<f64> = (0..400)
        .map(|k| path(k) + if k >= 380 { 3.0 } else { 0.0 })
        .collect();
    assert!(jumps_where_it_slipped(&late, 380, 3.0));
}
