//! The normal equations `J^T J` and `J^T r` of the identification's
//! least-squares problem ([`crate::model::identify`]), summed row by row
//! without forming the Jacobian `J`.
//!
//! ## Why
//! A string residual's row touches only its own string's columns (anchor,
//! winding radius, spool rate, the terms on that string) and the shared
//! ones (home, tracker frame, the shared thinning rate, every-string terms):
//! `J^T J` is block-arrow shaped. On a 2197-point lattice with a few
//! effects the dense product multiplied ~55 x 55 pairs per row where ~220
//! are not zero, and zeroing, transposing and packing the 17,576 x 55
//! Jacobian (7.7 MB) at every LM iteration cost as much again: together
//! half of the diagnosis loop's time.
//!
//! ## The same sums as the dense product
//! The sums are taken in the order and with the rounding of the dense
//! products the fit used before, so fits come out bit for bit the same:
//! `J^T J` as matrixmultiply's f64 product (nalgebra's for large matrices)
//! sums it, each entry a chain of multiply-adds over blocks of
//! [`DENSE_BLOCK_ROWS`] rows from zero, the blocks' sums added in order,
//! fused where its kernels fuse them (x86-64 with FMA and AVX2, aarch64);
//! `J^T r` as nalgebra's matrix-vector product, each row's product added in
//! turn. A zero product leaves such a sum as it is, so the zeros the block
//! structure skips change nothing. Any other order would be as accurate;
//! this one keeps every figure of the calibration where it was.
//!
//! ## Blocks on every core, the same sums
//! Each block's sums start from zero and are added to the total in block
//! order, so the blocks can be summed on any thread ([`BlockSums`]) and
//! added in order ([`NormalEquations::add_block`]): the same figures to the
//! bit whatever the number of threads. `J^T r` is one chain per column over
//! every row, so a block keeps each row's rounded products and they are
//! added in row order.

use std::sync::{Mutex, PoisonError};

use nalgebra::{DMatrix, DVector};
use spidar_core::STRINGS;

/// Rows per block of matrixmultiply's f64 matrix product (its `D_KC`): each
/// block's products are summed from zero, then added to the running sum.
const DENSE_BLOCK_ROWS: usize = 256;

/// Observations per block of string rows (each observation has one row per
/// channel, [`STRINGS`]).
pub(crate) const BLOCK_OBSERVATIONS: usize = DENSE_BLOCK_ROWS / STRINGS;
const _: () = assert!(DENSE_BLOCK_ROWS % STRINGS == 0);

/// The columns a string's rows touch: its own and the shared ones.
pub(crate) struct ArrowColumns {
    /// Number of columns of `J`.
    pub n: usize,
    /// Columns every string's rows touch.
    pub shared: Vec<usize>,
    /// Columns only string `i`'s rows touch.
    pub own: [Vec<usize>; STRINGS],
}

/// `J^T J` and `J^T r` summed so far. The string rows come first, in row
/// order ([`Self::add_string_row`]); then any general rows
/// ([`Self::add_row`]).
pub(crate) struct NormalEquations<'a> {
    columns: &'a ArrowColumns,
    /// Whether the products are fused multiply-adds (those of the dense
    /// product on this CPU).
    fused: bool,
    /// `J^T J` over the blocks done, once general rows come (or at the
    /// end); zero before.
    total: DMatrix<f64>,
    /// The string rows' `J^T J` over the blocks done, in the arrow's
    /// layout ([`ArrowBlock`]), while string rows come: each entry of the
    /// dense matrix is one of its entries (or that entry's mirror), so the
    /// blocks add as they would there, a contiguous sum each instead of an
    /// indexed one.
    arrow_total: ArrowBlock,
    /// The current block (its index) and its sums, while string rows come.
    block: usize,
    block_sums: ArrowBlock,
    /// The current block's sums as a full matrix, once general rows come.
    block_full: Option<DMatrix<f64>>,
    /// `J^T r` on the shared columns and on each string's own, while string
    /// rows come; on every column once general rows come.
    gradient_shared: Vec<f64>,
    gradient_own: [Vec<f64>; STRINGS],
    gradient: DVector<f64>,
}

impl<'a> NormalEquations<'a> {
    pub fn new(columns: &'a ArrowColumns) -> Self {
        let s = columns.shared.len();
        NormalEquations {
            columns,
            fused: dense_product_fuses(),
            total: DMatrix::zeros(columns.n, columns.n),
            arrow_total: ArrowBlock::zeros(columns),
            block: 0,
            block_sums: ArrowBlock::zeros(columns),
            block_full: None,
            gradient_shared: vec![0.0; s],
            gradient_own: core::array::from_fn(|i| vec![0.0; columns.own[i].len()]),
            gradient: DVector::zeros(columns.n),
        }
    }

    /// Adds row `row` of `J` (string `string`'s: `own` on its own columns,
    /// `shared` on the shared ones, zero elsewhere) with residual
    /// `residual`.
    pub fn add_string_row(
        &mut self,
        row: usize,
        string: usize,
        own: &[f64],
        shared: &[f64],
        residual: f64,
    ) {
        debug_assert!(self.block_full.is_none(), "string rows come first");
        if row / DENSE_BLOCK_ROWS != self.block {
            self.flush_arrow();
            self.block = row / DENSE_BLOCK_ROWS;
        }
        self.block_sums.add_row(self.fused, string, own, shared);
        // nalgebra's gemv: each product rounded, then added.
        for (g, &v) in self.gradient_shared.iter_mut().zip(shared) {
            *g += v * residual;
        }
        for (g, &v) in self.gradient_own[string].iter_mut().zip(own) {
            *g += v * residual;
        }
    }

    /// Adds a block's string rows, summed on their own
    /// ([`BlockSums`]): the same sums as adding its rows one by one with
    /// [`Self::add_string_row`]. Blocks come in block order. Gives back
    /// the buffer of the block's products (empty), for another block
    /// ([`BlockSums::with_buffers`]).
    pub fn add_block(&mut self, sums: BlockSums) -> Vec<f64> {
        debug_assert!(self.block_full.is_none(), "string rows come first");
        let mut sums = sums.sum_rows();
        if sums.rows.is_empty() {
            return Vec::new();
        }
        if sums.block != self.block {
            self.flush_arrow();
            self.block = sums.block;
        }
        // The current block's sums are zero here (a new block, or the
        // first), and the block's own sums started from zero.
        debug_assert!(self.block_sums.shared.iter().all(|&v| v == 0.0));
        self.block_sums = sums.arrow;
        // Each row's products: its own columns', then the shared ones'.
        let mut products = sums.products.as_slice();
        for &string in &sums.rows {
            let own = &mut self.gradient_own[usize::from(string)];
            let (row_own, rest) = products.split_at(own.len().min(products.len()));
            let (row_shared, rest) = rest.split_at(self.gradient_shared.len().min(rest.len()));
            for (g, p) in own.iter_mut().zip(row_own) {
                *g += p;
            }
            for (g, p) in self.gradient_shared.iter_mut().zip(row_shared) {
                *g += p;
            }
            products = rest;
        }
        let mut buffer = core::mem::take(&mut sums.products);
        buffer.clear();
        buffer
    }

    /// Adds row `row` of `J`, `values` on every column (a prior row: few
    /// are not zero), with residual `residual`. After the string rows.
    pub fn add_row(&mut self, row: usize, values: &[f64], residual: f64) {
        let block = row / DENSE_BLOCK_ROWS;
        let mut full = match self.block_full.take() {
            // The first: the string rows' sums go on, in this block's sums
            // when the row falls in it, else in the total first.
            None => {
                let mut full = DMatrix::zeros(self.columns.n, self.columns.n);
                if block == self.block {
                    self.scatter(&self.block_sums, &mut full);
                } else {
                    self.flush_arrow();
                }
                self.settle_total();
                self.gradient = self.scatter_gradient();
                full
            }
            Some(mut full) => {
                if block != self.block {
                    self.total += &full;
                    full.fill(0.0);
                }
                full
            }
        };
        self.block = block;
        let touched: Vec<usize> = (0..values.len()).filter(|&c| values[c] != 0.0).collect();
        for &a in &touched {
            for &b in &touched {
                full[(a, b)] = multiply_add(self.fused, values[a], values[b], full[(a, b)]);
            }
            self.gradient[a] += values[a] * residual;
        }
        self.block_full = Some(full);
    }

    /// `J^T J` and `J^T r`.
    pub fn finish(mut self) -> (DMatrix<f64>, DVector<f64>) {
        match self.block_full.take() {
            Some(full) => {
                self.total += full;
                (self.total, self.gradient)
            }
            None => {
                self.flush_arrow();
                self.settle_total();
                let gradient = self.scatter_gradient();
                (self.total, gradient)
            }
        }
    }

    /// Adds the current block's string sums to the total and clears them.
    fn flush_arrow(&mut self) {
        self.arrow_total.add(&self.block_sums);
        self.block_sums.shared.fill(0.0);
        for sums in &mut self.block_sums.own {
            sums.fill(0.0);
        }
    }

    /// Puts the string rows' sums over the blocks done into the dense
    /// total (zero until then, and the sums never -0, so each entry is
    /// the sum itself).
    fn settle_total(&mut self) {
        let mut total = core::mem::replace(&mut self.total, DMatrix::zeros(0, 0));
        self.scatter(&self.arrow_total, &mut total);
        self.total = total;
    }

    /// Adds string sums `block` to `into` (symmetric: the dense product's
    /// entries `(a, b)` and `(b, a)` are the same sums).
    fn scatter(&self, block: &ArrowBlock, into: &mut DMatrix<f64>) {
        let shared = &self.columns.shared;
        let s = shared.len();
        for (ai, &a) in shared.iter().enumerate() {
            for (bi, &b) in shared.iter().enumerate().skip(ai) {
                let sum = block.shared[ai * s + bi];
                into[(a, b)] += sum;
                if bi != ai {
                    into[(b, a)] += sum;
                }
            }
        }
        for (own, sums) in self.columns.own.iter().zip(&block.own) {
            let width = own.len() + s;
            for (ai, &a) in own.iter().enumerate() {
                for (bi, &b) in own.iter().chain(shared).enumerate() {
                    let sum = sums[ai * width + bi];
                    into[(a, b)] += sum;
                    if bi >= own.len() {
                        into[(b, a)] += sum;
                    }
                }
            }
        }
    }

    /// `J^T r` so far on every column.
    fn scatter_gradient(&self) -> DVector<f64> {
        let mut g = DVector::zeros(self.columns.n);
        for (&c, &v) in self.columns.shared.iter().zip(&self.gradient_shared) {
            g[c] = v;
        }
        for (own, sums) in self.columns.own.iter().zip(&self.gradient_own) {
            for (&c, &v) in own.iter().zip(sums) {
                g[c] = v;
            }
        }
        g
    }
}

/// One block's sums of string rows from zero: the shared columns' products
/// (shared x shared, row-major, the upper triangle only: an entry below the
/// diagonal is its mirror's sum, the same products in the same order, and
/// stays zero here) and each string's (own x (own, shared), row-major).
pub(crate) struct ArrowBlock {
    shared: Vec<f64>,
    own: [Vec<f64>; STRINGS],
    /// One row's values on (own, shared), reused.
    row: Vec<f64>,
}

impl ArrowBlock {
    fn zeros(columns: &ArrowColumns) -> Self {
        let s = columns.shared.len();
        ArrowBlock {
            shared: vec![0.0; s * s],
            own: core::array::from_fn(|i| {
                let t = columns.own[i].len();
                vec![0.0; t * (t + s)]
            }),
            row: Vec::with_capacity(columns.n),
        }
    }

    /// Adds `other`'s sums, entry by entry.
    fn add(&mut self, other: &ArrowBlock) {
        for (sum, &v) in self.shared.iter_mut().zip(&other.shared) {
            *sum += v;
        }
        for (sums, other) in self.own.iter_mut().zip(&other.own) {
            for (sum, &v) in sums.iter_mut().zip(other) {
                *sum += v;
            }
        }
    }

    /// Adds string `string`'s row (`own` on its own columns, `shared` on
    /// the shared ones): shared x shared, and own x (own, shared).
    fn add_row(&mut self, fused: bool, string: usize, own: &[f64], shared: &[f64]) {
        self.row.clear();
        self.row.extend_from_slice(own);
        self.row.extend_from_slice(shared);
        add_outer_products(fused, &mut self.shared, shared, shared, Entries::Upper);
        add_outer_products(fused, &mut self.own[string], own, &self.row, Entries::All);
    }
}

/// One block's string rows (block `block`: rows `block *
/// DENSE_BLOCK_ROWS ..`), summed from zero on their own: a thread's share
/// of [`NormalEquations`], added to it with
/// [`NormalEquations::add_block`].
///
/// The rows are held until the block is summed ([`Self::sum_rows`]), so
/// that each entry of `J^T J` takes four rows' products a pass
/// ([`add_outer_pairs`]) where one row at a time loaded and stored the
/// entry for each multiply-add: 1.8 times as fast (decision record 0079).
pub(crate) struct BlockSums {
    block: usize,
    fused: bool,
    arrow: ArrowBlock,
    /// Each row's string, in row order.
    rows: Vec<u8>,
    /// Each row's `J^T r` products, rounded: its own columns', then the
    /// shared ones'.
    products: Vec<f64>,
    /// The rows not yet in `arrow`: each one's values on its own columns,
    /// then on the shared ones, one row after another (`rows` says whose).
    values: Vec<f64>,
    /// Number of own columns of each string.
    own_widths: [usize; STRINGS],
    shared_width: usize,
}

impl BlockSums {
    #[cfg(test)]
    pub fn new(columns: &ArrowColumns, block: usize) -> Self {
        Self::with_buffers(columns, block, [Vec::new(), Vec::new()])
    }

    /// [`Self::new`], holding its rows and products in `buffers` (their
    /// values dropped): buffers a block gave back
    /// ([`Self::take_rows_buffer`], [`NormalEquations::add_block`];
    /// [`SpareBuffers`]).
    pub fn with_buffers(columns: &ArrowColumns, block: usize, buffers: [Vec<f64>; 2]) -> Self {
        let [mut values, mut products] = buffers;
        let s = columns.shared.len();
        let block_values =
            BLOCK_OBSERVATIONS * columns.own.iter().map(|own| own.len() + s).sum::<usize>();
        BlockSums {
            block,
            fused: dense_product_fuses(),
            arrow: ArrowBlock::zeros(columns),
            rows: Vec::with_capacity(DENSE_BLOCK_ROWS),
            // Room for a block's rows at once (a row per string of each
            // observation), not reallocated as they come.
            products: {
                products.clear();
                products.reserve(block_values);
                products
            },
            values: {
                values.clear();
                values.reserve(block_values);
                values
            },
            own_widths: core::array::from_fn(|i| columns.own[i].len()),
            shared_width: s,
        }
    }

    /// Adds a row of this block, as [`NormalEquations::add_string_row`].
    pub fn add_string_row(&mut self, string: usize, own: &[f64], shared: &[f64], residual: f64) {
        debug_assert_eq!(own.len(), self.own_widths[string]);
        debug_assert_eq!(shared.len(), self.shared_width);
        self.rows.push(string as u8);
        self.values.extend_from_slice(own);
        self.values.extend_from_slice(shared);
        self.products.extend(own.iter().map(|&v| v * residual));
        self.products.extend(shared.iter().map(|&v| v * residual));
    }

    /// Sums the rows held into the block's `J^T J` (on the thread that
    /// made them, before [`NormalEquations::add_block`]): shared x shared
    /// over every row, own x (own, shared) over each string's, each entry's
    /// products in row order.
    pub fn sum_rows(mut self) -> Self {
        if self.values.is_empty() {
            return self;
        }
        let s = self.shared_width;
        let mut rows: Vec<(usize, &[f64])> = Vec::with_capacity(self.rows.len());
        let mut at = 0;
        for &string in &self.rows {
            let string = usize::from(string);
            let width = self.own_widths[string] + s;
            rows.push((string, &self.values[at..at + width]));
            at += width;
        }
        let shared = rows.iter().map(|(string, row)| {
            let shared = &row[self.own_widths[*string]..];
            (shared, shared)
        });
        add_outer_pairs(self.fused, &mut self.arrow.shared, shared, Entries::Upper);
        for (string, sums) in self.arrow.own.iter_mut().enumerate() {
            let own = rows
                .iter()
                .filter(|(i, _)| *i == string)
                .map(|(_, row)| (&row[..self.own_widths[string]], *row));
            add_outer_pairs(self.fused, sums, own, Entries::All);
        }
        self.values.clear();
        self
    }

    /// The buffer the rows were held in (empty) once summed, for another
    /// block ([`Self::with_buffers`]).
    pub fn take_rows_buffer(&mut self) -> Vec<f64> {
        let mut buffer = core::mem::take(&mut self.values);
        buffer.clear();
        buffer
    }
}

/// Buffers for [`BlockSums`]' rows and products, given back when a block
/// is done with them and taken by the next, across the passes of a fit: a
/// new buffer's pages are mapped as rows first fill them (a long stream's
/// calibration took 730,000 page faults with a new buffer every block,
/// 290,000 with these: decision record 0079).
#[derive(Default)]
pub(crate) struct SpareBuffers(Mutex<Vec<Vec<f64>>>);

impl SpareBuffers {
    /// A buffer given back, or a new one.
    pub fn take(&self) -> Vec<f64> {
        self.0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .pop()
            .unwrap_or_default()
    }

    /// Gives `buffer` back for another block.
    pub fn give(&self, buffer: Vec<f64>) {
        self.0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(buffer);
    }
}

/// Whether matrixmultiply's f64 kernel on this CPU fuses its multiply-adds:
/// its AVX-512 and FMA+AVX2 kernels do, its AVX and SSE2 ones do not.
fn dense_product_fuses() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("fma") && std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        true
    }
}

/// `a b + sum`, fused or rounded twice.
#[inline(always)]
fn multiply_add(fused: bool, a: f64, b: f64, sum: f64) -> f64 {
    if fused {
        a.mul_add(b, sum)
    } else {
        a * b + sum
    }
}

/// Which entries of a product's sums are taken.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Entries {
    All,
    /// `b >= a` only, of a square product of a row with itself: an entry
    /// below the diagonal is its mirror's sum (a product rounds, or fuses,
    /// alike whichever factor comes first) and is left as it is.
    Upper,
}

impl Entries {
    /// The first column of row `a` taken.
    #[inline(always)]
    fn first(self, a: usize) -> usize {
        match self {
            Entries::All => 0,
            Entries::Upper => a,
        }
    }
}

/// `sums[a][b] += u[a] v[b]` (`sums` row-major, `u.len()` x `v.len()`) on
/// the `entries` taken.
#[inline(always)]
fn add_outer<const FUSED: bool>(sums: &mut [f64], u: &[f64], v: &[f64], entries: Entries) {
    for (a, (row, &ua)) in sums.chunks_exact_mut(v.len()).zip(u).enumerate() {
        let first = entries.first(a);
        for (sum, &vb) in row[first..].iter_mut().zip(&v[first..]) {
            *sum = multiply_add(FUSED, ua, vb, *sum);
        }
    }
}

/// [`add_outer`] with fused multiply-adds when `fused`.
fn add_outer_products(fused: bool, sums: &mut [f64], u: &[f64], v: &[f64], entries: Entries) {
    #[cfg(target_arch = "x86_64")]
    if fused {
        // SAFETY: `fused` comes from `dense_product_fuses`, true only when
        // the CPU has FMA. The binary targets x86-64 without FMA, where
        // `f64::mul_add` is a call into libm per product (several times
        // slower than the dense product this replaces); compiling this one
        // loop for FMA and choosing it at run time is the only safe way
        // the language offers to the instruction in a portable binary.
        unsafe { add_outer_fma(sums, u, v, entries) };
        return;
    }
    add_outer::<{ cfg!(not(target_arch = "x86_64")) }>(sums, u, v, entries);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "fma")]
fn add_outer_fma(sums: &mut [f64], u: &[f64], v: &[f64], entries: Entries) {
    add_outer::<true>(sums, u, v, entries);
}

/// Rows whose products [`add_outer_pairs`] adds to each entry a pass.
const PAIRS_A_PASS: usize = 4;

/// `sums[a][b] += u[a] v[b]` for each `(u, v)` of `pairs` in turn (`sums`
/// row-major, `u.len()` x `v.len()`, the same lengths for every pair):
/// each entry's multiply-adds in the pairs' order, as [`add_outer`] one
/// pair after another adds them, four pairs a pass over `sums`; on the
/// `entries` taken.
fn add_outer_pairs<'v>(
    fused: bool,
    sums: &mut [f64],
    pairs: impl Iterator<Item = (&'v [f64], &'v [f64])>,
    entries: Entries,
) {
    let mut pending: [(&[f64], &[f64]); PAIRS_A_PASS] = [(&[], &[]); PAIRS_A_PASS];
    let mut held = 0;
    for pair in pairs {
        pending[held] = pair;
        held += 1;
        if held == PAIRS_A_PASS {
            add_outer_four(fused, sums, &pending, entries);
            held = 0;
        }
    }
    for &(u, v) in &pending[..held] {
        add_outer_products(fused, sums, u, v, entries);
    }
}

/// [`add_outer_pairs`] of four pairs, with fused multiply-adds when
/// `fused` (as [`add_outer_products`] chooses them).
fn add_outer_four(
    fused: bool,
    sums: &mut [f64],
    pairs: &[(&[f64], &[f64]); PAIRS_A_PASS],
    entries: Entries,
) {
    #[cfg(target_arch = "x86_64")]
    if fused {
        // SAFETY: as in `add_outer_products`: `fused` is true only when
        // the CPU has FMA.
        unsafe { add_outer_four_fma(sums, pairs, entries) };
        return;
    }
    add_outer_four_with::<{ cfg!(not(target_arch = "x86_64")) }>(sums, pairs, entries);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "fma")]
fn add_outer_four_fma(
    sums: &mut [f64],
    pairs: &[(&[f64], &[f64]); PAIRS_A_PASS],
    entries: Entries,
) {
    add_outer_four_with::<true>(sums, pairs, entries);
}

#[inline(always)]
fn add_outer_four_with<const FUSED: bool>(
    sums: &mut [f64],
    pairs: &[(&[f64], &[f64]); PAIRS_A_PASS],
    entries: Entries,
) {
    let [(u0, v0), (u1, v1), (u2, v2), (u3, v3)] = pairs;
    let n = v0.len();
    let (v1, v2, v3) = (&v1[..n], &v2[..n], &v3[..n]);
    for (a, row) in sums.chunks_exact_mut(n).enumerate() {
        let (a0, a1, a2, a3) = (u0[a], u1[a], u2[a], u3[a]);
        let f = entries.first(a);
        let taken = row[f..]
            .iter_mut()
            .zip(&v0[f..])
            .zip(&v1[f..])
            .zip(&v2[f..])
            .zip(&v3[f..]);
        for ((((sum, &b0), &b1), &b2), &b3) in taken {
            let mut x = multiply_add(FUSED, a0, b0, *sum);
            x = multiply_add(FUSED, a1, b1, x);
            x = multiply_add(FUSED, a2, b2, x);
            *sum = multiply_add(FUSED, a3, b3, x);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform values in [-1, 1) from `seed` (a linear congruential
    /// sequence: the tests' rows, the same on every machine).
    fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
        move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        }
    }

    /// Random block-arrow rows (string rows then general rows) give the
    /// dense products' `J^T J` and `J^T r` to the bit, whether the general
    /// rows begin in the string rows' last block or in a block of their own.
    #[test]
    fn sums_as_the_dense_products() {
        // 560 string rows: a partial third block; 512: two full blocks.
        for observations in [70, 64] {
            sums_as_the_dense_products_with(observations);
        }
    }

    fn sums_as_the_dense_products_with(observations: usize) {
        let mut next = uniform(12345);
        // 3 shared columns, string i owns columns 3 + 2i and 4 + 2i.
        let n = 3 + 2 * STRINGS;
        let columns = ArrowColumns {
            n,
            shared: vec![0, 1, 2],
            own: core::array::from_fn(|i| vec![3 + 2 * i, 4 + 2 * i]),
        };
        let general = 5;
        let rows = observations * STRINGS + general;
        let mut jac = DMatrix::zeros(rows, n);
        let r = DVector::from_fn(rows, |_, _| next());
        let mut normal = NormalEquations::new(&columns);
        for k in 0..observations {
            for i in 0..STRINGS {
                let row = k * STRINGS + i;
                let own: Vec<f64> = (0..2).map(|_| next() * 1e3).collect();
                let shared: Vec<f64> = (0..3).map(|_| next()).collect();
                for (&c, &v) in columns.own[i].iter().zip(&own) {
                    jac[(row, c)] = v;
                }
                for (&c, &v) in columns.shared.iter().zip(&shared) {
                    jac[(row, c)] = v;
                }
                normal.add_string_row(row, i, &own, &shared, r[row]);
            }
        }
        for j in 0..general {
            let row = observations * STRINGS + j;
            let values: Vec<f64> = (0..n)
                .map(|c| if (c + j) % 4 == 0 { next() } else { 0.0 })
                .collect();
            for c in 0..n {
                jac[(row, c)] = values[c];
            }
            normal.add_row(row, &values, r[row]);
        }
        let (jtj, jtr) = normal.finish();
        let jt = jac.transpose();
        assert_eq!(jtj, &jt * &jac);
        assert_eq!(jtr, &jt * &r);
    }

    /// Blocks summed on their own and added in order give the sums of the
    /// rows added one by one, to the bit, with rows of weight zero left
    /// out (a whole block of them too) and general rows after.
    #[test]
    fn blocks_sum_as_rows_one_by_one() {
        let mut next = uniform(987);
        let n = 4 + 3 * STRINGS;
        let columns = ArrowColumns {
            n,
            shared: vec![0, 1, 2, 3],
            own: core::array::from_fn(|i| vec![4 + 3 * i, 5 + 3 * i, 6 + 3 * i]),
        };
        let observations = 5 * BLOCK_OBSERVATIONS + 7;
        let skipped = |k: usize, i: usize| {
            (BLOCK_OBSERVATIONS..2 * BLOCK_OBSERVATIONS).contains(&k) || (k + i) % 5 == 0
        };
        let mut rows = Vec::new();
        for k in 0..observations {
            for i in 0..STRINGS {
                let own: Vec<f64> = (0..3).map(|_| next() * 1e2).collect();
                let shared: Vec<f64> = (0..4).map(|_| next()).collect();
                if !skipped(k, i) {
                    rows.push((k * STRINGS + i, i, own, shared, next()));
                }
            }
        }
        let general: Vec<f64> = (0..n)
            .map(|c| if c % 3 == 0 { next() } else { 0.0 })
            .collect();
        let general_row = observations * STRINGS;

        let mut one_by_one = NormalEquations::new(&columns);
        for (row, i, own, shared, r) in &rows {
            one_by_one.add_string_row(*row, *i, own, shared, *r);
        }
        one_by_one.add_row(general_row, &general, 0.5);

        let mut by_block = NormalEquations::new(&columns);
        for block in 0..observations.div_ceil(BLOCK_OBSERVATIONS) {
            let mut sums = BlockSums::new(&columns, block);
            for (row, i, own, shared, r) in &rows {
                if row / DENSE_BLOCK_ROWS == block {
                    sums.add_string_row(*i, own, shared, *r);
                }
            }
            by_block.add_block(sums);
        }
        by_block.add_row(general_row, &general, 0.5);
        assert_eq!(one_by_one.finish(), by_block.finish());
    }
}
