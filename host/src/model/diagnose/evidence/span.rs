//! The model's span a row at a time, and the sums over the rows that test
//! columns off it.
//!
//! ## The same sums as the dense products
//! The span's orthonormal basis is `B = J V / sqrt(lambda)` (`J` the data
//! Jacobian, `V` the kept eigenvectors of `J^T J`), and every test is a
//! product with it: `B^T x` and `x - B (B^T x)` for the columns `x`, then
//! their norms, Gram matrix and right-hand side. Held whole, `B` has a row
//! per row and a column per parameter (0.3 GB for a 100,000-row session);
//! here each of its rows is made when read, and the sums are taken in the
//! order and with the rounding of nalgebra's products over the whole
//! matrices: a matrix-vector product's entry is its products added one
//! after another from the first (over the rows for `B^T x`, over the
//! parameters for a row of `B c` and of `J v`), unfused; a column's squared
//! norm is eight interleaved partial sums over the full blocks of eight
//! rows, then the rest ([`SquaresSum`]). A product that is zero leaves such
//! a sum as it is, so the zeros skipped (other strings' columns of a row,
//! rows a column is zero on) change nothing. The findings, their fitted
//! values (where a new term's fit starts) and so the loop's choices are
//! those of the dense products to the bit.

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

/// Rows whose [`dots_in_turn`] are summed side by side: enough
/// independent sums to keep the CPU's adders busy while each waits on its
/// last addition (measured on 2048 rows of 110 values: 56 us at eight, 137
/// at four, 102 one row after another).
const DOTS_SIDE_BY_SIDE: usize = 8;

/// [`dot_in_turn`] of each of `rows` rows of `basis` (one after another,
/// `c.len()` values each) with `c`: [`DOTS_SIDE_BY_SIDE`] rows' sums at a
/// time, each one's products added in its own order (the same figures as
/// one row after another).
pub(super) fn dots_in_turn(basis: &[f64], rows: usize, c: &[f64]) -> Vec<f64> {
    const N: usize = DOTS_SIDE_BY_SIDE;
    let d = c.len();
    if d == 0 {
        return vec![0.0; rows];
    }
    let mut out = Vec::with_capacity(rows);
    let mut groups = basis[..rows * d].chunks_exact(N * d);
    for group in &mut groups {
        let row: [&[f64]; N] = core::array::from_fn(|r| &group[r * d..(r + 1) * d]);
        let mut sums: [f64; N] = core::array::from_fn(|r| row[r][0] * c[0]);
        // Indexed: measured faster than zipped iterators here (82 us).
        for t in 1..d {
            let ct = c[t];
            for r in 0..N {
                sums[r] += row[r][t] * ct;
            }
        }
        out.extend_from_slice(&sums);
    }
    out.extend(
        groups
            .remainder()
            .chunks_exact(d)
            .map(|b| dot_in_turn(b, c)),
    );
    out
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

/// An [`OffSpan`]'s sums while the rows come.
struct OffSpanSums {
    before: Vec<SquaresSum>,
    after: Vec<SquaresSum>,
    gram: Vec<f64>,
    rhs: Vec<f64>,
}

impl OffSpanSums {
    fn new(columns: usize, rows: usize) -> OffSpanSums {
        OffSpanSums {
            before: (0..columns).map(|_| SquaresSum::new(rows)).collect(),
            after: (0..columns).map(|_| SquaresSum::new(rows)).collect(),
            gram: vec![0.0; columns * columns],
            rhs: vec![0.0; columns],
        }
    }

    /// Row `k`: the columns' weighted values `x`, projected `p`, and the
    /// projected residual `r`.
    fn add(&mut self, k: usize, x: &[f64], p: &[f64], r: f64) {
        let m = p.len();
        for (j, (&x, &p)) in x.iter().zip(p).enumerate() {
            self.before[j].add(k, x);
            self.after[j].add(k, p);
        }
        for (a, &pa) in p.iter().enumerate() {
            for (g, &pb) in self.gram[a * m..(a + 1) * m].iter_mut().zip(p) {
                *g += pa * pb;
            }
            self.rhs[a] += pa * r;
        }
    }

    fn finish(self) -> OffSpan {
        let m = self.rhs.len();
        OffSpan {
            before: self.before.into_iter().map(|s| s.total().sqrt()).collect(),
            after: self.after.into_iter().map(|s| s.total().sqrt()).collect(),
            gram: DMatrix::from_fn(m, m, |a, b| self.gram[a * m + b]),
            rhs: DVector::from_column_slice(&self.rhs),
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
    /// the sums that test it ([`OffSpan`]): two passes over the rows
    /// (`B^T X` of every set, then `P X = X - B (B^T X)` row by row).
    pub(in crate::model::diagnose) fn off_span(&self, sets: &[Columns<'_>]) -> Vec<OffSpan> {
        use rayon::prelude::*;
        let dims = self.dims();
        let mut coefs: Vec<Vec<Vec<f64>>> = sets
            .iter()
            .map(|s| vec![vec![0.0; dims]; s.columns.len()])
            .collect();
        // Each set's weighted values on the rows it is on, in row order:
        // worked out in the first pass and read again in the second (a
        // column can cost a few transcendental functions a row), when the
        // rows are few enough to keep them.
        let keep = self.keeps_passes();
        let mut values: Vec<Vec<f64>> = vec![Vec::new(); sets.len()];
        self.for_each_chunk_with_basis(|chunk, basis| {
            coefs
                .par_iter_mut()
                .zip(&mut values)
                .zip(sets)
                .for_each(|((coef, values), set)| {
                    for (j, (_, row)) in chunk.iter().enumerate() {
                        if !set.on(row) {
                            continue;
                        }
                        let b = &basis[j * dims..(j + 1) * dims];
                        let sw = row.weight.sqrt();
                        for (f, coef) in set.columns.iter().zip(coef.iter_mut()) {
                            let x = f(row) * sw;
                            if keep {
                                values.push(x);
                            }
                            if x != 0.0 {
                                for (c, &bc) in coef.iter_mut().zip(b) {
                                    *c += bc * x;
                                }
                            }
                        }
                    }
                });
        });
        let rows = self.rows();
        let mut sums: Vec<OffSpanSums> = sets
            .iter()
            .map(|s| OffSpanSums::new(s.columns.len(), rows))
            .collect();
        let mut read: Vec<usize> = vec![0; sets.len()];
        self.for_each_chunk_with_basis(|chunk, basis| {
            sums.par_iter_mut()
                .zip(&mut read)
                .zip(sets)
                .zip(&coefs)
                .zip(&values)
                .for_each(|((((sums, read), set), coef), values)| {
                    let (mut x, mut p) = (Vec::new(), Vec::new());
                    // `B c` on the chunk's rows, for each column's `c`.
                    let projected: Vec<Vec<f64>> = coef
                        .iter()
                        .map(|c| dots_in_turn(basis, chunk.len(), c))
                        .collect();
                    for (j, (k, row)) in chunk.iter().enumerate() {
                        let sw = row.weight.sqrt();
                        let on = set.on(row);
                        x.clear();
                        p.clear();
                        for (f, projected) in set.columns.iter().zip(&projected) {
                            let value = match (on, keep) {
                                (false, _) => 0.0,
                                (true, true) => {
                                    *read += 1;
                                    values[*read - 1]
                                }
                                (true, false) => f(row) * sw,
                            };
                            x.push(value);
                            p.push(value - projected[j]);
                        }
                        sums.add(*k, &x, &p, self.residual[*k]);
                    }
                });
        });
        sums.into_iter().map(OffSpanSums::finish).collect()
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
    use super::{dot_in_turn, dots_in_turn};

    proptest::proptest! {
        /// Rows side by side give each row's [`dot_in_turn`] to the bit,
        /// whatever the number of rows and of values a row.
        #[test]
        fn dots_side_by_side_are_each_rows_dot(
            dims in 0usize..12,
            rows in 0usize..27,
            seed in proptest::prelude::any::<u64>(),
        ) {
            let mut state = seed;
            let mut next = move || {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 1e3
            };
            let basis: Vec<f64> = (0..rows * dims).map(|_| next()).collect();
            let c: Vec<f64> = (0..dims).map(|_| next()).collect();
            let dots = dots_in_turn(&basis, rows, &c);
            proptest::prop_assert_eq!(dots.len(), rows);
            for (j, dot) in dots.iter().enumerate() {
                let one = dot_in_turn(&basis[j * dims..(j + 1) * dims], &c);
                proptest::prop_assert_eq!(dot.to_bits(), one.to_bits());
            }
        }
    }
}
