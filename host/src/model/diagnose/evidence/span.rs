//! The model's span a row at a time, and the sums over the rows that test
//! columns off it.
//!
//! ## The sums
//! The span's orthonormal basis is `B = J V / sqrt(lambda)` (`J` the data
//! Jacobian, `V` the kept eigenvectors of `J^T J`), and every test is a
//! product with it: `B^T x` for the columns `x`, then the norms, Gram
//! matrix and right-hand side of their parts off the span, `x - B (B^T
//! x)`, which follow from `B^T x`, `x^T x` and `x^T r` ([`Evidence::off_span`]).
//! Held whole, `B` has a row per row and a column per parameter (0.3 GB
//! for a 100,000-row session); here each of its rows is made when read.
//! The residual's projection and the sums of squares are taken in the
//! order and with the rounding of nalgebra's products over the whole
//! matrices: a matrix-vector product's entry is its products added one
//! after another from the first (over the rows for `B^T x`, over the
//! parameters for a row of `J v`), unfused; a column's squared norm is
//! eight interleaved partial sums over the full blocks of eight rows, then
//! the rest ([`SquaresSum`]). A product that is zero leaves such a sum as
//! it is, so the zeros skipped (other strings' columns of a row, rows a
//! column is zero on) change nothing.

use std::ops::Range;

use nalgebra::{DMatrix, DVector, Dyn, SymmetricEigen};
use spidar_core::STRINGS;

use super::{Evidence, Row, RowColumn, MIN_OUTSIDE_SPAN};
use crate::model::identify::DataJacobian;

/// A direction of unit columns off the model's span with a singular value
/// under this is (numerically) in the span
/// ([`OffSpan::explained_by_span`]).
const NUMERICALLY_IN_SPAN: f64 = 1e-6;

/// The model's span: the kept eigenvectors of `J^T J` on each string's
/// columns, and the square roots of their eigenvalues, from which a row of
/// the orthonormal basis is made ([`Span::basis_row`]).
pub(super) struct Span {
    roots: Vec<f64>,
    strings: [StringSpan; STRINGS],
}

/// One string's rows' part of the span.
struct StringSpan {
    /// Positions of the row's values (its own columns', then the shared
    /// ones': [`DataJacobian::row_columns`]) in ascending column order.
    order: Vec<usize>,
    /// The kept eigenvectors on those columns in that order, one
    /// eigenvector after another.
    vectors: Vec<f64>,
}

impl Span {
    pub(super) fn new(
        jacobian: &DataJacobian<'_>,
        eig: &SymmetricEigen<f64, Dyn>,
        keep: &[usize],
    ) -> Span {
        let strings = core::array::from_fn(|i| {
            let columns: Vec<usize> = jacobian.row_columns(i).collect();
            let mut order: Vec<usize> = (0..columns.len()).collect();
            order.sort_by_key(|&t| columns[t]);
            let columns = &columns;
            let vectors = keep
                .iter()
                .flat_map(|&j| {
                    order
                        .iter()
                        .map(move |&t| eig.eigenvectors[(columns[t], j)])
                })
                .collect();
            StringSpan { order, vectors }
        });
        Span {
            roots: keep.iter().map(|&j| eig.eigenvalues[j].sqrt()).collect(),
            strings,
        }
    }

    /// Number of the basis's directions.
    pub(super) fn dims(&self) -> usize {
        self.roots.len()
    }

    /// The basis's row of string `i`'s row of `J` (`own` then `shared`
    /// values) into `out`: `(J v_c) / sqrt(lambda_c)` for each direction
    /// `c`, summed over the columns in order as `J v` sums it.
    pub(super) fn basis_row(&self, i: usize, own: &[f64], shared: &[f64], out: &mut [f64]) {
        let string = &self.strings[i];
        let len = string.order.len();
        let value = |t: usize| {
            let at = string.order[t];
            if at < own.len() {
                own[at]
            } else {
                shared[at - own.len()]
            }
        };
        for ((b, vector), root) in out
            .iter_mut()
            .zip(string.vectors.chunks_exact(len.max(1)))
            .zip(&self.roots)
        {
            let mut sum = 0.0;
            for (t, &v) in vector.iter().enumerate() {
                sum += value(t) * v;
            }
            *b = sum / root;
        }
    }
}

/// Rows whose sets of columns are worked out at once, each set on its own
/// core ([`Evidence::off_span`]).
const OFF_SPAN_CHUNK: usize = 2048;

/// `b . c` with the products added one after another from the first, as a
/// row of the matrix-vector product `B c` sums them (0 when empty).
pub(super) fn dot_in_turn(b: &[f64], c: &[f64]) -> f64 {
    let mut products = b.iter().zip(c).map(|(b, c)| b * c);
    let first = products.next().unwrap_or(0.0);
    products.fold(first, |sum, p| p + sum)
}

/// A sum of squares over the rows in order, as nalgebra's `norm_squared`
/// of a column takes it: eight interleaved partial sums over the rows in
/// full blocks of eight, added pairwise, then each remaining row in turn.
pub(super) struct SquaresSum {
    partial: [f64; 8],
    blocked: usize,
    total: f64,
    closed: bool,
}

impl SquaresSum {
    /// A sum over `rows` rows.
    pub(super) fn new(rows: usize) -> SquaresSum {
        SquaresSum {
            partial: [0.0; 8],
            blocked: rows - rows % 8,
            total: 0.0,
            closed: false,
        }
    }

    /// Adds row `k`'s `v^2`; rows come in order.
    pub(super) fn add(&mut self, k: usize, v: f64) {
        if k < self.blocked {
            self.partial[k % 8] += v * v;
        } else {
            self.close();
            self.total += v * v;
        }
    }

    fn close(&mut self) {
        if !self.closed {
            let p = &self.partial;
            self.total += p[0] + p[4];
            self.total += p[1] + p[5];
            self.total += p[2] + p[6];
            self.total += p[3] + p[7];
            self.closed = true;
        }
    }

    pub(super) fn total(mut self) -> f64 {
        self.close();
        self.total
    }
}

/// Columns tested together off the model's span: each one's value on a
/// row (unweighted) and the string whose rows alone they are not zero on,
/// if one.
pub(in crate::model::diagnose) struct Columns<'c> {
    pub(in crate::model::diagnose) columns: Vec<&'c RowColumn>,
    pub(in crate::model::diagnose) string: Option<usize>,
}

impl Columns<'_> {
    /// Whether the columns may be other than zero on `row`.
    fn on(&self, row: &Row) -> bool {
        self.string.is_none_or(|s| s == row.string)
    }
}

/// Columns `X` weighted as the residual is (each row by the square root of
/// its robust weight), projected off the model's span (`P X`), and the
/// sums that test them.
pub(in crate::model::diagnose) struct OffSpan {
    /// `|x|` of each column.
    before: Vec<f64>,
    /// `|P x|` of each column.
    after: Vec<f64>,
    /// `(P X)^T (P X)`.
    gram: DMatrix<f64>,
    /// `(P X)^T r`, `r` the projected weighted residual.
    rhs: DVector<f64>,
}

/// The sums of one set of columns [`Evidence::off_span`] takes as the
/// rows come: each column's `B^T x` and squared norm, and the columns'
/// products with one another and with the residual.
struct ColumnSums {
    basis: Vec<Vec<f64>>,
    squares: Vec<SquaresSum>,
    products: Vec<f64>,
    residual: Vec<f64>,
}

impl ColumnSums {
    fn new(columns: usize, dims: usize, rows: usize) -> ColumnSums {
        ColumnSums {
            basis: vec![vec![0.0; dims]; columns],
            squares: (0..columns).map(|_| SquaresSum::new(rows)).collect(),
            products: vec![0.0; columns * columns],
            residual: vec![0.0; columns],
        }
    }

    /// Row `k`: the columns' weighted values `x`, the row of the basis `b`
    /// and the projected residual `r`.
    fn add(&mut self, k: usize, x: &[f64], b: &[f64], r: f64) {
        let m = x.len();
        for (a, &xa) in x.iter().enumerate() {
            self.squares[a].add(k, xa);
            if xa != 0.0 {
                for (c, &bc) in self.basis[a].iter_mut().zip(b) {
                    *c += bc * xa;
                }
            }
            for (g, &xb) in self.products[a * m..(a + 1) * m].iter_mut().zip(x) {
                *g += xa * xb;
            }
            self.residual[a] += xa * r;
        }
    }

    /// The projected sums, `basis_residual` the residual's `B^T r`.
    fn finish(self, basis_residual: &[f64]) -> OffSpan {
        let m = self.residual.len();
        let dot = |u: &[f64], v: &[f64]| -> f64 { u.iter().zip(v).map(|(a, b)| a * b).sum() };
        let gram = DMatrix::from_fn(m, m, |a, b| {
            self.products[a * m + b] - dot(&self.basis[a], &self.basis[b])
        });
        let rhs = DVector::from_fn(m, |a, _| {
            self.residual[a] - dot(&self.basis[a], basis_residual)
        });
        OffSpan {
            before: self.squares.into_iter().map(|s| s.total().sqrt()).collect(),
            // Rounding may leave a column in the span a square a hair
            // below zero.
            after: (0..m).map(|a| gram[(a, a)].max(0.0).sqrt()).collect(),
            gram,
            rhs,
        }
    }
}

impl OffSpan {
    /// Whether every column lies off the model's span: its part off it is
    /// at least [`MIN_OUTSIDE_SPAN`] of its norm. A column that does not
    /// is one the current model already absorbs: the data cannot show it.
    pub(in crate::model::diagnose) fn outside(&self) -> bool {
        self.before
            .iter()
            .zip(&self.after)
            .all(|(&before, &after)| before != 0.0 && after >= MIN_OUTSIDE_SPAN * before)
    }

    /// Least-squares fit of the projected columns to the projected
    /// residual: (coefficients, explained sum of squares).
    pub(in crate::model::diagnose) fn fit(&self) -> Option<(Vec<f64>, f64)> {
        let beta = self.gram.clone().cholesky()?.solve(&self.rhs);
        let explained = beta.dot(&self.rhs);
        (explained.is_finite() && explained >= 0.0)
            .then(|| (beta.iter().copied().collect(), explained))
    }

    /// The residual's sum of squares explained by the span of the columns
    /// `which` off the model's, dropping the directions numerically in the
    /// model's span or in that of the other columns: a rival's columns may
    /// be degenerate on a session (a planar device's tracked z is one
    /// value: its position columns in z repeat the others), which
    /// [`fit`](Self::fit) would refuse as a whole. With full rank it is
    /// `fit`'s explained sum of squares. From the Gram matrix of the unit
    /// columns (the tolerance is a share of each column, whatever its
    /// units: a sag's home column is far smaller than the stretch's): each
    /// of its eigenvectors `w` with eigenvalue `s^2` is a singular
    /// direction of the projected columns, explaining `(w . X^T r)^2 /
    /// s^2`. Only the directions numerically in the span are dropped: a
    /// rival explains with everything it spans (with the 1 % of
    /// [`MIN_OUTSIDE_SPAN`], correlated position columns lose directions
    /// and a drift stands in for them).
    pub(in crate::model::diagnose) fn explained_by_span(&self, which: Range<usize>) -> f64 {
        let m = which.len();
        if m == 0 {
            return 0.0;
        }
        let from = which.start;
        let unit: Vec<f64> = which
            .map(|c| {
                if self.before[c] > 0.0 {
                    1.0 / self.before[c]
                } else {
                    1.0
                }
            })
            .collect();
        let gram = DMatrix::from_fn(m, m, |a, b| {
            self.gram[(from + a, from + b)] * unit[a] * unit[b]
        });
        let rhs = DVector::from_fn(m, |a, _| self.rhs[from + a] * unit[a]);
        let eig = gram.symmetric_eigen();
        eig.eigenvalues
            .iter()
            .enumerate()
            .filter(|(_, &s2)| s2 > NUMERICALLY_IN_SPAN * NUMERICALLY_IN_SPAN)
            .map(|(k, &s2)| eig.eigenvectors.column(k).dot(&rhs).powi(2) / s2)
            .sum()
    }
}

impl Evidence<'_> {
    /// Number of the span's directions.
    fn dims(&self) -> usize {
        match &self.source {
            super::Source::Fit(fit) => fit.span.dims(),
            #[cfg(test)]
            super::Source::Given { basis, .. } => basis.ncols(),
        }
    }

    /// Each set of columns weighted and projected off the model's span,
    /// the sums that test it ([`OffSpan`]), in one pass over the rows: `c =
    /// B^T x`, `x^T x` and `x^T r` of every set's columns `x`, from which
    /// the projected sums follow, the basis `B` being orthonormal: `(P
    /// x_a)^T (P x_b) = x_a^T x_b - c_a^T c_b` and `(P x_a)^T r = x_a^T r -
    /// c_a^T (B^T r)` (`r` is projected off the span already: `B^T r` is
    /// its rounding), with no pass forming `P x` row by row (decision record
    /// 0086). The subtraction loses no more than `1e-12` of a column's
    /// squared norm wherever the column counts as off the span
    /// ([`MIN_OUTSIDE_SPAN`]).
    pub(in crate::model::diagnose) fn off_span(&self, sets: &[Columns<'_>]) -> Vec<OffSpan> {
        use rayon::prelude::*;
        let dims = self.dims();
        let rows = self.rows();
        let mut sums: Vec<ColumnSums> = sets
            .iter()
            .map(|s| ColumnSums::new(s.columns.len(), dims, rows))
            .collect();
        let mut basis_residual = vec![0.0; dims];
        self.for_each_chunk_with_basis(|chunk, basis| {
            for (j, (k, _)) in chunk.iter().enumerate() {
                let r = self.residual[*k];
                for (c, &b) in basis_residual
                    .iter_mut()
                    .zip(&basis[j * dims..(j + 1) * dims])
                {
                    *c += b * r;
                }
            }
            sums.par_iter_mut().zip(sets).for_each(|(sums, set)| {
                let mut x = vec![0.0; set.columns.len()];
                for (j, (k, row)) in chunk.iter().enumerate() {
                    if !set.on(row) {
                        continue;
                    }
                    let sw = row.weight.sqrt();
                    for (x, f) in x.iter_mut().zip(&set.columns) {
                        *x = f(row) * sw;
                    }
                    sums.add(*k, &x, &basis[j * dims..(j + 1) * dims], self.residual[*k]);
                }
            });
        });
        sums.into_iter()
            .map(|s| s.finish(&basis_residual))
            .collect()
    }

    /// Calls `visit(rows, basis)` on the rows in order, a chunk of
    /// [`OFF_SPAN_CHUNK`] at a time: each `(k, row)` with its row of the
    /// span's basis at `basis[j * dims..]` for the `j`-th of the chunk (so
    /// that the sets of columns can take a chunk on every core, each set's
    /// sums over the rows in order).
    fn for_each_chunk_with_basis(&self, mut visit: impl FnMut(&[(usize, Row)], &[f64])) {
        let mut rows: Vec<(usize, Row)> = Vec::with_capacity(OFF_SPAN_CHUNK);
        let mut basis: Vec<f64> = Vec::with_capacity(OFF_SPAN_CHUNK * self.dims());
        self.for_each_row_with_basis(|k, row, b| {
            rows.push((k, *row));
            basis.extend_from_slice(b);
            if rows.len() == OFF_SPAN_CHUNK {
                visit(&rows, &basis);
                rows.clear();
                basis.clear();
            }
        });
        if !rows.is_empty() {
            visit(&rows, &basis);
        }
    }

    /// Each set's largest contribution `|sum_j beta_j x_j|` (unweighted)
    /// over the rows the fit does not reject (weight above 0.1).
    pub(in crate::model::diagnose) fn amplitudes(
        &self,
        sets: &[(Columns<'_>, &[f64])],
    ) -> Vec<f64> {
        let mut amplitudes = vec![0.0; sets.len()];
        self.for_each_row(None, |_, row| {
            if row.weight > 0.1 {
                for ((set, beta), amplitude) in sets.iter().zip(&mut amplitudes) {
                    if set.on(row) {
                        let v = set
                            .columns
                            .iter()
                            .zip(beta.iter())
                            .map(|(f, b)| f(row) * b)
                            .sum::<f64>()
                            .abs();
                        *amplitude = f64::max(*amplitude, v);
                    }
                }
            }
        });
        amplitudes
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Evidence, Row, RowColumn};
    use super::Columns;
    use nalgebra::{DMatrix, DVector};

    /// A row of string `string` at `position`, weighed `weight`.
    fn row(obs: usize, string: usize, weight: f64, position: [f64; 3]) -> Row {
        Row {
            obs,
            string,
            weight,
            ctx: Evidence::still_context(obs as f64),
            length: 1000.0,
            speed: 0.0,
            position,
            marker_column: None,
            scale_gradient: 0.0,
        }
    }

    /// The one pass's sums are those of the columns projected off the span
    /// row by row (`P X = X - B B^T X`, dense): every norm, Gram entry and
    /// right-hand side within 1e-9 of the largest, and the fit the same,
    /// for columns on every row, on one string's rows, and one almost in
    /// the span.
    #[test]
    fn one_pass_gives_the_projected_columns_sums() {
        let n = 3000;
        let mut state = 11u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let rows: Vec<Row> = (0..n)
            .map(|k| {
                let weight = if k % 17 == 0 { 0.0 } else { 0.5 + next() };
                row(
                    k / 8,
                    k % 8,
                    weight,
                    [next() * 900.0, next() * 900.0, next() * 900.0],
                )
            })
            .collect();
        let residuals: Vec<f64> = rows
            .iter()
            .map(|r| 0.3 * r.position[0] / 900.0 + 0.1 * next())
            .collect();
        // An orthonormal basis of 6 directions: a constant, the position,
        // and two of the string's rows alone.
        let raw = DMatrix::from_fn(n, 6, |k, c| match c {
            0 => 1.0,
            1..=3 => rows[k].position[c - 1],
            4 => f64::from(u8::from(rows[k].string == 2)),
            _ => rows[k].position[0] * rows[k].position[1] / 900.0,
        });
        let weighted = DMatrix::from_fn(n, 6, |k, c| raw[(k, c)] * rows[k].weight.sqrt());
        let basis = weighted.qr().q();
        let ev = Evidence::of_rows(rows.clone(), residuals, basis.clone(), 0.01);
        let columns: Vec<RowColumn> = vec![
            Box::new(|r: &Row| r.position[2] * r.position[2] / 900.0),
            Box::new(|r: &Row| r.ctx.time_s),
            Box::new(|r: &Row| r.position[0] + 1e-3 * r.position[1] * r.position[2] / 900.0),
            Box::new(|r: &Row| (r.position[1] / 300.0).sin()),
        ];
        let sets = [
            Columns {
                columns: vec![&columns[0], &columns[1]],
                string: None,
            },
            Columns {
                columns: vec![&columns[3], &columns[1]],
                string: Some(3),
            },
            Columns {
                columns: vec![&columns[2], &columns[0], &columns[3]],
                string: None,
            },
        ];
        let off = ev.off_span(&sets);
        for (set, off) in sets.iter().zip(&off) {
            let m = set.columns.len();
            let x = DMatrix::from_fn(n, m, |k, c| {
                let r = &rows[k];
                if set.on(r) {
                    (set.columns[c])(r) * r.weight.sqrt()
                } else {
                    0.0
                }
            });
            let projected = &x - &basis * (basis.transpose() * &x);
            let gram = projected.transpose() * &projected;
            let rhs = projected.transpose() * DVector::from_column_slice(ev.residual.as_slice());
            let scale = gram.amax();
            assert!(
                (&off.gram - &gram).amax() <= 1e-9 * scale,
                "{} {}",
                off.gram,
                gram
            );
            let rhs_scale = rhs.amax().max(1e-300);
            assert!((&off.rhs - &rhs).amax() <= 1e-9 * rhs_scale.max(scale.sqrt()));
            for c in 0..m {
                let before = x.column(c).norm();
                let after = projected.column(c).norm();
                assert!((off.before[c] - before).abs() <= 1e-12 * before);
                assert!(
                    (off.after[c] - after).abs() <= 1e-6 * before,
                    "{c}: {} {after}",
                    off.after[c]
                );
            }
        }
        // The column almost in the span (the position's x and a thousandth
        // of a product) is counted as in it, as the dense sums count it.
        assert!(!off[2].outside());
        assert!(off[0].outside());
    }
}
