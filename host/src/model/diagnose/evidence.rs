//! The evidence diagnosis reads: every (row, string) residual of the
//! current fit with what it depends on ([`Row`]), and the model's span the
//! candidates are tested off ([`Evidence`]).

use nalgebra::{DMatrix, DVector};
use spidar_core::model::{Frame, StringLayout};
use spidar_core::string_law::{payout_f64, EffectContext};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::model::identify::{
    data_jacobian, device_position, inputs_at, DataJacobian, Identification, Structure,
};

/// What one (row, string) residual depends on.
#[derive(Clone, Copy, Debug)]
pub(super) struct Row {
    /// Index into the observations.
    pub(super) obs: usize,
    pub(super) string: usize,
    /// Weight of the robust fit (0 for rejected residuals).
    pub(super) weight: f64,
    /// Residual (geometric minus model), mm, unweighted.
    pub(super) residual: f64,
    pub(super) ctx: EffectContext,
    /// Geometric length from the tracker, mm.
    pub(super) length: f64,
    /// String speed `d payout / dt` since the previous row, mm/s.
    pub(super) speed: f64,
    /// Device-frame position from the tracker, mm.
    pub(super) position: [f64; 3],
    /// How the string's length reads a move of the tracked body's origin
    /// from the meeting point (body frame, per mm of each axis), when the
    /// tracker gives the body's orientation: a marker offset's columns.
    pub(super) marker_column: Option<[f64; 3]>,
    /// `d residual / d room_scale` (frame-wide geometry regressor).
    pub(super) scale_gradient: f64,
}

/// Everything diagnosis needs about the current fit.
pub(super) struct Evidence {
    /// Which channels carry a string (rows of the others have weight 0).
    pub(super) layout: StringLayout,
    pub(super) rows: Vec<Row>,
    /// Orthonormal basis of the model's (weighted) Jacobian columns.
    pub(super) basis: DMatrix<f64>,
    /// `basis` transposed, made once: every candidate's projection
    /// multiplies by it, and transposing the basis (a row per residual)
    /// anew for each candidate takes a tenth of the loop's time.
    pub(super) basis_t: DMatrix<f64>,
    /// Weighted residual with the model's directions projected out.
    pub(super) residual: DVector<f64>,
    /// Residual variance per unit weight, mm^2.
    pub(super) sigma2: f64,
    /// Weighted residual sum of squares, mm^2.
    pub(super) rss: f64,
}

/// A column whose part off the model's span (or off the other columns')
/// is under this share of its norm lies (almost) in it: the model already
/// absorbs it and the data cannot show it.
pub(super) const MIN_OUTSIDE_SPAN: f64 = 1e-2;

/// A direction of unit columns off the model's span with a singular value
/// under this is (numerically) in the span ([`Evidence::explained_by_span`]).
const NUMERICALLY_IN_SPAN: f64 = 1e-6;

pub(super) fn pulley_turn_angle(theta: f64) -> f64 {
    theta.rem_euclid(2.0 * std::f64::consts::PI)
}

impl Evidence {
    pub(super) fn gather(
        id: &Identification,
        observations: &[Observation],
        nominal: &Frame<f64>,
        structure: &Structure,
    ) -> Option<Evidence> {
        let DataJacobian {
            jacobian: jac,
            residuals: weighted,
            weights,
        } = data_jacobian(id, observations, nominal, structure)?;
        let used: Vec<usize> = observations
            .iter()
            .enumerate()
            .filter(|(_, o)| o.tracker.is_some())
            .map(|(k, _)| k)
            .collect();
        let mut rows = Vec::with_capacity(used.len() * STRINGS);
        for (u, &k) in used.iter().enumerate() {
            let o = &observations[k];
            o.tracker?;
            let p = device_position(&id.frame, o);
            let inputs = inputs_at(&id.frame, o, &p);
            let prev = k.checked_sub(1).map(|j| &observations[j]);
            // The body's turn as the device frame sees it, once per row.
            let body_in_device = o
                .tracker_rotation
                .map(|body| body_in_device(&id.frame, &body));
            for i in 0..STRINGS {
                let ctx = EffectContext::for_string(&id.frame, &id.laws, &inputs, i)?;
                let d = [
                    p[0] - id.frame.anchors[i][0],
                    p[1] - id.frame.anchors[i][1],
                    p[2] - id.frame.anchors[i][2],
                ];
                let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let up = [d[0] / length, d[1] / length, d[2] / length];
                let speed = match prev {
                    Some(q) if o.t_s > q.t_s => {
                        let before = payout_f64(&id.laws[i], q.inputs.counts[i]);
                        (ctx.payout_mm - before) / (o.t_s - q.t_s)
                    }
                    _ => 0.0,
                };
                let w = weights[u][i];
                rows.push(Row {
                    obs: k,
                    string: i,
                    weight: w,
                    residual: if w > 0.0 {
                        weighted[u * STRINGS + i] / w.sqrt()
                    } else {
                        0.0
                    },
                    ctx,
                    length,
                    speed,
                    position: p,
                    marker_column: body_in_device.map(|m| marker_column(&m, &up)),
                    scale_gradient: -(up[0] * p[0] + up[1] * p[1] + up[2] * p[2])
                        / id.frame.room_scale,
                });
            }
        }
        // Orthonormal basis of the column space from the eigenvectors of J^T J
        // (the data Jacobian alone is rank deficient: the gauge is fixed by priors).
        let gram = jac.transpose() * &jac;
        let eig = gram.symmetric_eigen();
        let max = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
        let keep: Vec<usize> = (0..eig.eigenvalues.len())
            .filter(|&j| eig.eigenvalues[j] > 1e-10 * max)
            .collect();
        let mut basis = DMatrix::zeros(jac.nrows(), keep.len());
        for (c, &j) in keep.iter().enumerate() {
            let v = eig.eigenvectors.column(j);
            let u = &jac * v / eig.eigenvalues[j].sqrt();
            basis.set_column(c, &u);
        }
        let basis_t = basis.transpose();
        let residual = &weighted - &basis * (&basis_t * &weighted);
        let rss = residual.norm_squared();
        let effective = weights.iter().flatten().filter(|&&w| w > 0.0).count();
        let dof = (effective as f64 - keep.len() as f64).max(1.0);
        Some(Evidence {
            layout: nominal.layout,
            rows,
            basis,
            basis_t,
            residual,
            sigma2: rss / dof,
            rss,
        })
    }

    /// The columns as a matrix, each row scaled by the square root of its
    /// robust weight (as the residual is).
    fn weighted(&self, columns: &[Vec<f64>]) -> DMatrix<f64> {
        let mut x = DMatrix::zeros(self.rows.len(), columns.len());
        for (c, col) in columns.iter().enumerate() {
            for (r, row) in self.rows.iter().enumerate() {
                x[(r, c)] = col[r] * row.weight.sqrt();
            }
        }
        x
    }

    /// Projects weighted regressor columns (one value per row) off the model.
    /// `None` when a column lies (almost) in the model's span: the current
    /// model already absorbs that effect, so the data cannot show it.
    pub(super) fn project(&self, columns: &[Vec<f64>]) -> Option<DMatrix<f64>> {
        let x = self.weighted(columns);
        let coef = &self.basis_t * &x;
        let projected = &x - &self.basis * coef;
        for c in 0..columns.len() {
            let before = x.column(c).norm();
            if before == 0.0 || projected.column(c).norm() < MIN_OUTSIDE_SPAN * before {
                return None;
            }
        }
        Some(projected)
    }

    /// The residual's sum of squares explained by the span of `columns`
    /// off the model's, dropping the directions numerically in the model's
    /// span or in that of the other columns: a rival's columns may be
    /// degenerate on a session (a planar device's tracked z is one value:
    /// its position columns in z repeat the others), which [`project`]
    /// and [`fit`] would refuse as a whole. With full rank it is `fit`'s
    /// explained sum of squares.
    ///
    /// [`project`]: Self::project
    /// [`fit`]: Self::fit
    pub(super) fn explained_by_span(&self, columns: &[Vec<f64>]) -> f64 {
        // Unit columns: the tolerance is a share of each column, whatever
        // its units (a sag's home column is far smaller than the stretch's).
        // Only the directions numerically in the span are dropped: a rival
        // explains with everything it spans (with the 1 % of
        // MIN_OUTSIDE_SPAN, correlated position columns lose directions and
        // a drift stands in for them).
        let mut x = self.weighted(columns);
        for mut column in x.column_iter_mut() {
            let norm = column.norm();
            if norm > 0.0 {
                column /= norm;
            }
        }
        let projected = &x - &self.basis * (&self.basis_t * &x);
        let svd = projected.svd(true, false);
        let Some(u) = svd.u else {
            return 0.0;
        };
        svd.singular_values
            .iter()
            .enumerate()
            .filter(|(_, &s)| s > NUMERICALLY_IN_SPAN)
            .map(|(k, _)| u.column(k).dot(&self.residual).powi(2))
            .sum()
    }

    /// Least-squares fit of projected regressors to the projected residual:
    /// (coefficients, explained sum of squares).
    pub(super) fn fit(&self, projected: &DMatrix<f64>) -> Option<(Vec<f64>, f64)> {
        let gram = projected.transpose() * projected;
        let rhs = projected.transpose() * &self.residual;
        let beta = gram.clone().cholesky()?.solve(&rhs);
        let explained = beta.dot(&rhs);
        (explained.is_finite() && explained >= 0.0)
            .then(|| (beta.iter().copied().collect(), explained))
    }
}

/// `R^T R_body / s` (`R`, `s`: the room transform), the rows of a planar
/// device's normal zeroed (its meeting point stays in its plane): how the
/// meeting point, `device_from_room(p - R_body d)`, moves against the
/// tracked body's origin `d` (body frame).
fn body_in_device(frame: &Frame<f64>, body: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let r = &frame.room_rotation;
    core::array::from_fn(|k| {
        core::array::from_fn(|j| {
            if frame.layout.planar && k == 2 {
                0.0
            } else {
                (0..3).map(|m| r[m][k] * body[m][j]).sum::<f64>() / frame.room_scale
            }
        })
    })
}

/// `d length / d marker` of a string whose unit direction (anchor to
/// end-effector) is `up`, for the body's turn `body_in_device`
/// ([`body_in_device`]): the string shortens by `up . M d`.
fn marker_column(body_in_device: &[[f64; 3]; 3], up: &[f64; 3]) -> [f64; 3] {
    core::array::from_fn(|j| (0..3).map(|k| up[k] * body_in_device[k][j]).sum::<f64>())
}
