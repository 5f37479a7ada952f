//! Levenberg-Marquardt on the problem's normal equations.

use super::problem::Problem;

/// The first damping of a fit that starts far from its minimum (from the
/// design geometry): Marquardt's usual `1e-3`, steps held short until the
/// cost falls.
pub(super) const DAMPING_FAR: f64 = 1e-3;

/// The first damping of a fit that starts near its minimum (a robust
/// round after the first, a refit, a fold warm from the session's model):
/// Gauss-Newton's step, damped only if it raises the cost (a refused step
/// raises `lambda` fourfold). `lambda D` damps each direction whose
/// curvature is below `lambda` of its diagonal entry: at `1e-3` the valleys
/// two parameters make together (a stretch's stiffness and its home
/// tension, a latency and a spool rate) were held back, each step went a
/// fraction along them, and a warm fold fit of a streamed session took
/// 15-30 evaluations where Gauss-Newton's steps take 6-8. From `1e-5` down
/// to `1e-12` the evaluations hardly change (record 0078).
pub(super) const DAMPING_NEAR: f64 = 1e-8;

/// Levenberg-Marquardt on the normal equations: `(J^T J + lambda D) dx =
/// -J^T r` by Cholesky, with Marquardt's diagonal scaling `D = diag(J^T J)`.
///
/// Written here rather than using the `levenberg-marquardt` crate's driver
/// (which this module still uses for the problem trait) because the crate
/// takes a QR of the whole Jacobian (17,576 x 45 for a lattice) at every
/// step; the 45 x 45 normal equations are several times faster and are well
/// conditioned here (parameters are scaled to their typical size, priors keep
/// every direction determined).
///
/// `first_damping` is the first `lambda`: [`DAMPING_FAR`] where the fit
/// starts far from its minimum, [`DAMPING_NEAR`] where it starts near it.
pub(super) fn minimize(
    mut problem: Problem<'_>,
    first_damping: f64,
) -> Result<(Problem<'_>, usize), String> {
    use levenberg_marquardt::LeastSquaresProblem;
    const MAX_ITERATIONS: usize = 60;
    let mut evaluations = 1;
    let mut x = problem.params();
    let mut r = problem
        .residuals()
        .ok_or("residuals not finite at the start")?;
    let mut cost = r.norm_squared();
    // Settled when a step lowers the cost by less than 1e-2 of one
    // residual's share of it (a chi-square change of 0.01, where a
    // parameter's change by one sd moves it by 1): a relative gain of 6e-7
    // on a 2197-point lattice. Iterating further costs time and moves no
    // decision: at 1e-4 the fits took a fifth more evaluations for
    // held-out figures within 1.2 um (the final ones the same to 0.1 um) on
    // a lattice and two 30,000-row sessions.
    let settled = 1e-2 / r.len().max(1) as f64;
    let mut lambda = first_damping;
    for _ in 0..MAX_ITERATIONS {
        let (normal, gradient) = problem.normal_equations(&r).ok_or("Jacobian not finite")?;
        // Settled, too, when the full Gauss-Newton step promises less than
        // that: the linearized cost falls by `g^T (J^T J)^-1 g` at most.
        // Near the minimum the cost's own rounding (the inputs are the
        // device's quantized values) is of that size, and damped steps
        // tried there are refused one after another, each a pass over the
        // rows; a warm fit whose weights barely moved stops here at once.
        if let Some(chol) = normal.clone().cholesky() {
            if gradient.dot(&chol.solve(&gradient)) < settled * cost {
                return Ok((problem, evaluations));
            }
        }
        let mut improved = false;
        while lambda < 1e12 {
            let mut damped = normal.clone();
            for j in 0..damped.nrows() {
                damped[(j, j)] += lambda * normal[(j, j)].max(1e-12);
            }
            let Some(chol) = damped.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = -chol.solve(&gradient);
            let trial = &x + &step;
            problem.set_params(&trial);
            evaluations += 1;
            match problem.residuals() {
                Some(r_trial) if r_trial.norm_squared() < cost => {
                    let new_cost = r_trial.norm_squared();
                    let relative_gain = (cost - new_cost) / cost.max(1e-300);
                    let small_step = step.amax() <= 1e-10 * (1.0 + x.amax());
                    x = trial;
                    r = r_trial;
                    cost = new_cost;
                    lambda = (lambda / 3.0).max(1e-12);
                    improved = true;
                    if relative_gain < settled || small_step {
                        return Ok((problem, evaluations));
                    }
                    break;
                }
                _ => {
                    problem.set_params(&x);
                    lambda *= 4.0;
                }
            }
        }
        if !improved {
            // No step lowers the cost: at the minimum (to rounding).
            problem.set_params(&x);
            return Ok((problem, evaluations));
        }
    }
    Ok((problem, evaluations))
}
