//! Position corrections learned on the host (paper section 5): a 3-H-3 neural
//! network (tanh hidden layer, linear output) and an RBF epsilon-SVR with three
//! outputs, both with the input/output standardization of eq. 10.
//!
//! The f64 models here are what the host trains (`alloc` feature); the
//! fixed-point evaluators the device runs are compiled from them
//! ([`NnModel::compile`], [`SvrModel::compile`]) into a compact little-endian
//! byte encoding (the correction part of the model blob body), which the
//! device evaluates in place, zero-copy, with [`NnView`] and [`SvrView`].
//!
//! # Fixed-point scheme (integer only; see `docs/fixed-point.md`)
//!
//! Positions in and out: `i32` Q15.16 mm ([`POSITION_FRAC`], header
//! `q_position`). Every weight multiplies a Q1.30 quantity (a `tanh` output or
//! an RBF kernel value, [`ACTIVATION_FRAC`], header `q_weight`); the weights
//! themselves are block floating point: each layer (each output axis for the
//! output weights) carries its own number of fractional bits in the body,
//! chosen by the compiler to use the full `i32` range.
//!
//! NN, per hidden neuron `h`:
//! `x_h = sat((sum_i (p_i - mean_i) * w1[h][i]) >> (w1_frac - 11)) + b1[h]` (saturating), with
//! `p - mean` saturated to `i32` Q15.16, `w1 = W1 / std_in` in Q(`w1_frac`) per
//! mm, an `i64` accumulator, `x_h` and `b1` in Q4.27 ([`PREACTIVATION_FRAC`]);
//! `t_h = tanh(x_h)` in Q1.30 ([`crate::fixed::tanh_q27`]); output
//! `out_a = round((sum_h w2[a][h] * t_h) >> (w2_frac[a] + 14)) + offset[a]`
//! (`+ p_a` in residual mode), `w2 = W2 * std_out` in Q(`w2_frac[a]`) mm,
//! `offset = b2 * std_out + mean_out` in Q15.16 mm, `i64` accumulator.
//!
//! SVR: the inputs are mapped once into a scaled space where the kernel
//! exponent is in base 2: `q_i = (p_i - mean_i) * g_i`, `g_i =
//! sqrt(gamma log2 e) / std_in_i`, `q` in Q4.27 ([`SVR_SPACE_FRAC`]); the
//! support vectors are stored in the same space, so per support vector
//! `u = sum_i (q_i - s_i)^2` is three `32x32->64` multiply-accumulates, its
//! high word is `u` in Q10.22, and the kernel is `2^-u` in Q1.30
//! ([`crate::fixed::exp2_neg_q22`]: a least-squares line per segment of the
//! fraction, one `smlawb`, shifted right by the integer part; 0 for
//! `u >= 30`, below the Q1.30 resolution). The kernel is shared by the three
//! axes. Support vectors are taken in blocks of [`SVR_BLOCK`]: within a block
//! each axis sums `round(coef[a][j] K_j / 2^32)` in an `i32` (in mm with
//! `coef_frac[a] - 2` fractional bits), the block sums are added in `i64`,
//! and `out_a = round(acc_a >> (coef_frac[a] - 18)) + offset[a]` (`+ p_a` in
//! residual mode), `coef =
//! alpha * std_out` in Q(`coef_frac[a]`) mm, the fractional bits chosen so
//! that every block's `sum |coef|` stays within [`SVR_BLOCK_ABS_SUM_MAX`].
//! In a blob of format version 2 the correction bytes start 4-byte aligned
//! (`crate::blob::CORRECTION_ALIGN`): in an aligned buffer [`SvrView`] reads
//! the records as words, elsewhere as bytes, with the same results.

use serde::{Deserialize, Serialize};

/// How a correction's output is used.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum OutputMode {
    /// The output is the corrected position (paper, black-box mode).
    Absolute,
    /// The output is added to the input position (on top of an identified model).
    Residual,
}

/// Per-axis affine standardization of eq. 10: `n = (p - mean) / std`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Standardization {
    pub mean: [f64; 3],
    pub std: [f64; 3],
}

#[cfg(feature = "alloc")]
pub use f64_models::*;

#[cfg(feature = "alloc")]
mod f64_models {
    use super::*;
    use alloc::vec::Vec;

    /// 3-H-3 network: `y = W2 tanh(W1 x + b1) + b2` on standardized x and y.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct NnModel {
        pub input: Standardization,
        pub output: Standardization,
        /// Hidden-layer weights, `w1[h] = [w_hx, w_hy, w_hz]`.
        pub w1: Vec<[f64; 3]>,
        pub b1: Vec<f64>,
        /// Output weights, `w2[axis][h]`.
        pub w2: [Vec<f64>; 3],
        pub b2: [f64; 3],
        pub mode: OutputMode,
    }

    /// RBF epsilon-SVR, one regressor per output axis sharing the support
    /// vectors: `y_axis = sum_j coef[axis][j] exp(-gamma |x - sv_j|^2) + bias[axis]`
    /// on standardized x and y. A support vector unused by an axis has
    /// coefficient 0 there.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct SvrModel {
        pub input: Standardization,
        pub output: Standardization,
        pub gamma: f64,
        /// Support vectors in standardized input space.
        pub support: Vec<[f64; 3]>,
        /// Dual coefficients (alpha_i - alpha_i^*), `coef[axis][j]`.
        pub coef: [Vec<f64>; 3],
        pub bias: [f64; 3],
        pub mode: OutputMode,
    }

    /// The optional position correction of a calibration.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub enum CorrectionModel {
        None,
        Nn(NnModel),
        Svr(SvrModel),
    }
}

use crate::fixed::{
    exp2_neg_q22_below_2p31_with, exp2_neg_q22_with, le_i32, read_i32, sat_i32, shr_i64,
    shr_round_i64, shr_sat_i64_to_i32, tanh_q27, EXP2_BASE, EXP2_FRACTION_ENTRIES, EXP2_SLOPE,
};
use spidar_protocol::blob::{BlobError, CorrectionKind};

// ---------------------------------------------------------------------------
// Q formats and the byte layout of the compiled corrections.

/// Fractional bits of positions in and out of the evaluators (Q15.16 mm). The
/// blob header's `q_position` must equal it.
pub const POSITION_FRAC: u8 = 16;
/// Fractional bits of the quantities the correction weights multiply: hidden
/// activations `tanh` (Q1.30) and RBF kernel values (Q1.30). The blob header's
/// `q_weight` must equal it; the weights' own fractional bits are per layer /
/// per axis in the body.
pub const ACTIVATION_FRAC: u8 = 30;
/// Fractional bits of NN pre-activations and first-layer biases (Q4.27).
pub const PREACTIVATION_FRAC: u32 = 27;
/// Fractional bits of the SVR's scaled input space (Q4.27): inputs `q` and
/// support vectors `s`, so that `|q - s|^2` is the kernel exponent in base 2.
pub const SVR_SPACE_FRAC: u32 = 27;

/// Largest magnitude of a stored first-layer weight (`2^29`), so that the sum
/// of three `i32 x i32` products never overflows `i64`.
pub const W1_MAX: i32 = 1 << 29;
/// Largest sum over one axis of the magnitudes of stored output weights or SVR
/// coefficients, so that the `i64` accumulator of `weight x Q1.30` products
/// never overflows.
pub const OUTPUT_ABS_SUM_MAX: u64 = (1 << 33) - 2;
/// Range of `w1_frac` (fractional bits of NN first-layer weights, per mm): the
/// pre-activation shift `w1_frac - 11` stays within `1..=31`, a cheap 32-bit
/// shift pair on the device.
pub const W1_FRAC_RANGE: core::ops::RangeInclusive<u8> = 12..=42;
/// Range of `scale_frac` (fractional bits of the SVR input scales, per mm).
pub const INPUT_FRAC_RANGE: core::ops::RangeInclusive<u8> = 11..=60;
/// Range of `w2_frac` / `coef_frac` (fractional bits of output weights and SVR
/// coefficients, mm).
pub const OUTPUT_FRAC_RANGE: core::ops::RangeInclusive<u8> = 0..=48;
/// Largest magnitude of a stored SVR support-vector coordinate (`2^30`, i.e.
/// 8.0 in Q4.27): with inputs saturated at ±16, a saturated input is at least
/// 8 away from every support vector, whose kernel then underflows as it should.
pub const SUPPORT_MAX: i32 = 1 << 30;

/// Bytes of the NN body before the neurons.
///
/// ```text
/// offset size  field
///  0     1     mode          0 absolute, 1 residual
///  1     1     w1_frac       fractional bits of w1 (per mm), 12..=42
///  2     3     w2_frac[3]    fractional bits of w2 per output axis (mm), 0..=48
///  5     3     reserved      0
///  8     12    mean[3]       i32 Q15.16 mm: input mean
/// 20     12    offset[3]     i32 Q15.16 mm: b2 * std_out + mean_out
/// 32     28*H  neurons       per neuron: w1[3] i32 Q(w1_frac) per mm,
///                            b1 i32 Q4.27, w2[3] i32 Q(w2_frac[a]) mm
/// ```
pub const NN_HEADER_LEN: usize = 32;
/// Bytes per hidden neuron in the NN body.
pub const NN_NEURON_LEN: usize = 28;
/// Bytes of the SVR body before the support vectors.
///
/// ```text
/// offset size  field
///  0     1     mode          0 absolute, 1 residual
///  1     1     scale_frac    fractional bits of the input scales (per mm), 11..=60
///  2     3     coef_frac[3]  fractional bits of the coefficients per axis (mm), 0..=48
///  5     3     reserved      0
///  8     12    mean[3]       i32 Q15.16 mm: input mean
/// 20     12    scale[3]      i32 Q(scale_frac) per mm: sqrt(gamma log2 e) / std_in
/// 32     12    offset[3]     i32 Q15.16 mm: bias * std_out + mean_out
/// 44     24*N  support       per support vector: s[3] i32 Q4.27 (scaled space),
///                            coef[3] i32 Q(coef_frac[a]) mm
/// ```
pub const SVR_HEADER_LEN: usize = 44;
/// Bytes per support vector in the SVR body.
pub const SVR_RECORD_LEN: usize = 24;
/// Support vectors per block of the SVR evaluation: within a block each axis
/// accumulates in an `i32` (one rounding multiply-accumulate per term), and
/// the block sums are added in `i64`.
pub const SVR_BLOCK: usize = 64;
/// Largest sum, over one axis and one block of [`SVR_BLOCK`] consecutive
/// support vectors, of the magnitudes of the stored coefficients: each term
/// `round(coef K / 2^32)` is at most `|coef| / 4 + 1` (`K <= 2^30`), so the
/// block's `i32` accumulator stays within `2^31 - 1`.
pub const SVR_BLOCK_ABS_SUM_MAX: u64 = (1 << 33) - 4 * SVR_BLOCK as u64 - 4;

fn len_u32(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

fn mode_from_byte(b: u8, field: &'static str) -> Result<OutputMode, BlobError> {
    match b {
        0 => Ok(OutputMode::Absolute),
        1 => Ok(OutputMode::Residual),
        _ => Err(BlobError::Body { field }),
    }
}

#[cfg(feature = "alloc")]
fn mode_byte(mode: OutputMode) -> u8 {
    match mode {
        OutputMode::Absolute => 0,
        OutputMode::Residual => 1,
    }
}

fn read3(bytes: &[u8], at: usize, field: &'static str) -> Result<[i32; 3], BlobError> {
    let mut v = [0i32; 3];
    for (i, x) in v.iter_mut().enumerate() {
        *x = read_i32(bytes, at + 4 * i).ok_or(BlobError::Body { field })?;
    }
    Ok(v)
}

/// Checks the blob header's Q-format fields against this evaluator.
pub fn check_header_formats(q_position: u8, q_weight: u8) -> Result<(), BlobError> {
    if q_position != POSITION_FRAC {
        return Err(BlobError::Dimension {
            field: "q_position",
            found: q_position as u32,
            expected: POSITION_FRAC as u32,
        });
    }
    if q_weight != ACTIVATION_FRAC {
        return Err(BlobError::Dimension {
            field: "q_weight",
            found: q_weight as u32,
            expected: ACTIVATION_FRAC as u32,
        });
    }
    Ok(())
}

/// Final output step shared by both evaluators: accumulator in
/// Q(30 + frac) mm to Q15.16, plus offset, plus the input in residual mode,
/// saturated.
#[inline(always)]
fn finish(acc: i64, frac: u8, offset: i32, mode: OutputMode, p: i32) -> i32 {
    let y = shr_round_i64(acc, frac as u32 + (ACTIVATION_FRAC - POSITION_FRAC) as u32);
    let base = match mode {
        OutputMode::Absolute => 0,
        OutputMode::Residual => p as i64,
    };
    sat_i32(y.saturating_add(offset as i64).saturating_add(base))
}

// ---------------------------------------------------------------------------
// NN view.

/// A compiled 3-H-3 network, read in place from its bytes (see
/// [`NN_HEADER_LEN`] for the layout). Positions in and out are Q15.16 mm.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NnView<'a> {
    summary: NnSummary,
    /// `hidden * NN_NEURON_LEN` bytes.
    neurons: &'a [u8],
}

/// Checks that `bytes` is a network of `hidden` neurons, header included.
fn nn_body_len(bytes: &[u8], hidden: u16) -> Result<(), BlobError> {
    let expected = NN_HEADER_LEN + NN_NEURON_LEN * hidden as usize;
    if bytes.len() == expected {
        Ok(())
    } else {
        Err(BlobError::Dimension {
            field: "nn.body_len",
            found: len_u32(bytes.len()),
            expected: len_u32(expected),
        })
    }
}

/// The checked, borrow-free part of an [`NnView`] (see
/// [`NnView::from_summary`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NnSummary {
    mode: OutputMode,
    /// Fractional bits of the first-layer weights (per mm).
    w1_frac: u8,
    /// Fractional bits of the output weights (mm), per axis.
    w2_frac: [u8; 3],
    /// Input mean, Q15.16 mm.
    mean: [i32; 3],
    /// `b2 * std_out + mean_out`, Q15.16 mm.
    offset: [i32; 3],
    hidden: u16,
}

impl<'a> NnView<'a> {
    /// Checks and wraps a compiled network of `hidden` neurons: exact length,
    /// mode, Q formats in range, every first-layer weight within [`W1_MAX`],
    /// every axis' output weights within [`OUTPUT_ABS_SUM_MAX`] (so that the
    /// evaluation cannot overflow). O(hidden), done once at load.
    pub fn parse(bytes: &'a [u8], hidden: u16) -> Result<NnView<'a>, BlobError> {
        if hidden == 0 {
            return Err(BlobError::Dimension {
                field: "hidden",
                found: 0,
                expected: 1,
            });
        }
        nn_body_len(bytes, hidden)?;
        let mode = mode_from_byte(bytes[0], "nn.mode")?;
        let w1_frac = bytes[1];
        if !W1_FRAC_RANGE.contains(&w1_frac) {
            return Err(BlobError::Body {
                field: "nn.w1_frac",
            });
        }
        let w2_frac = [bytes[2], bytes[3], bytes[4]];
        if w2_frac.iter().any(|f| !OUTPUT_FRAC_RANGE.contains(f)) {
            return Err(BlobError::Body {
                field: "nn.w2_frac",
            });
        }
        if bytes[5..8] != [0, 0, 0] {
            return Err(BlobError::Body {
                field: "nn.reserved",
            });
        }
        let mean = read3(bytes, 8, "nn.mean")?;
        let offset = read3(bytes, 20, "nn.offset")?;
        let neurons = &bytes[NN_HEADER_LEN..];
        let mut sums = [0u64; 3];
        for rec in neurons.chunks_exact(NN_NEURON_LEN) {
            for i in 0..3 {
                let w = read_i32(rec, 4 * i).ok_or(BlobError::Body { field: "nn.w1" })?;
                if w.unsigned_abs() > W1_MAX as u32 {
                    return Err(BlobError::Body { field: "nn.w1" });
                }
            }
            for (a, sum) in sums.iter_mut().enumerate() {
                let w = read_i32(rec, 16 + 4 * a).ok_or(BlobError::Body { field: "nn.w2" })?;
                *sum += w.unsigned_abs() as u64;
                if *sum > OUTPUT_ABS_SUM_MAX {
                    return Err(BlobError::Body { field: "nn.w2" });
                }
            }
        }
        Ok(NnView {
            summary: NnSummary {
                mode,
                w1_frac,
                w2_frac,
                mean,
                offset,
                hidden,
            },
            neurons,
        })
    }

    /// The borrow-free part of this view.
    pub fn summary(&self) -> NnSummary {
        self.summary
    }

    /// The view again over bytes that [`parse`](Self::parse) checked into
    /// `summary` and that have not changed since: O(1) (the length is
    /// checked, the weights' bounds are not read again). A device tick
    /// rebuilds its view this way; re-parsing cost ~1,150 instructions of
    /// the 25,000-cycle tick.
    pub fn from_summary(summary: &NnSummary, bytes: &'a [u8]) -> Result<NnView<'a>, BlobError> {
        nn_body_len(bytes, summary.hidden)?;
        Ok(NnView {
            summary: *summary,
            neurons: &bytes[NN_HEADER_LEN..],
        })
    }

    /// Number of hidden neurons.
    pub fn hidden(&self) -> usize {
        self.neurons.len() / NN_NEURON_LEN
    }

    /// Output mode of the network.
    pub fn mode(&self) -> OutputMode {
        self.summary.mode
    }

    /// Corrected position (Q15.16 mm) of a position `p` (Q15.16 mm). Integer
    /// only, saturating, never panics.
    pub fn evaluate(&self, p: [i32; 3]) -> [i32; 3] {
        let d0 = p[0].saturating_sub(self.summary.mean[0]) as i64;
        let d1 = p[1].saturating_sub(self.summary.mean[1]) as i64;
        let d2 = p[2].saturating_sub(self.summary.mean[2]) as i64;
        // Q(16 + w1_frac) -> Q27.
        let sh =
            (self.summary.w1_frac as u32).wrapping_sub(PREACTIVATION_FRAC - POSITION_FRAC as u32);
        let mut acc = [0i64; 3];
        for rec in self.neurons.chunks_exact(NN_NEURON_LEN) {
            let Ok(rec) = <&[u8; NN_NEURON_LEN]>::try_from(rec) else {
                continue;
            };
            let pre = (d0 * le_i32::<NN_NEURON_LEN, 0>(rec) as i64)
                .wrapping_add(d1 * le_i32::<NN_NEURON_LEN, 4>(rec) as i64)
                .wrapping_add(d2 * le_i32::<NN_NEURON_LEN, 8>(rec) as i64);
            let x = shr_sat_i64_to_i32(pre, sh).saturating_add(le_i32::<NN_NEURON_LEN, 12>(rec));
            let t = tanh_q27(x) as i64;
            acc[0] = acc[0].wrapping_add(le_i32::<NN_NEURON_LEN, 16>(rec) as i64 * t);
            acc[1] = acc[1].wrapping_add(le_i32::<NN_NEURON_LEN, 20>(rec) as i64 * t);
            acc[2] = acc[2].wrapping_add(le_i32::<NN_NEURON_LEN, 24>(rec) as i64 * t);
        }
        let s = &self.summary;
        [
            finish(acc[0], s.w2_frac[0], s.offset[0], s.mode, p[0]),
            finish(acc[1], s.w2_frac[1], s.offset[1], s.mode, p[1]),
            finish(acc[2], s.w2_frac[2], s.offset[2], s.mode, p[2]),
        ]
    }
}

// ---------------------------------------------------------------------------
// SVR view.

/// The support-vector records of an [`SvrView`], as the evaluator reads them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum SvrRecords<'a> {
    /// The records start at a 4-byte aligned address (a version-2 blob in a
    /// 4-aligned buffer) on a little-endian target: viewed as words
    /// `[s0, s1, s2, coef0, coef1, coef2]`, read with word-pair loads.
    Words(&'a [[i32; 6]]),
    /// Any other placement: `support_vectors * SVR_RECORD_LEN` bytes, read
    /// with single (unaligned) word loads. Same results, bit for bit.
    Bytes(&'a [u8]),
}

impl<'a> SvrRecords<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        #[cfg(target_endian = "little")]
        if let Ok(words) = bytemuck::try_cast_slice::<u8, [i32; 6]>(bytes) {
            return SvrRecords::Words(words);
        }
        SvrRecords::Bytes(bytes)
    }

    fn len(&self) -> usize {
        match self {
            SvrRecords::Words(w) => w.len(),
            SvrRecords::Bytes(b) => b.len() / SVR_RECORD_LEN,
        }
    }
}

/// A compiled RBF SVR with three outputs sharing their support vectors, read
/// in place from its bytes (see [`SVR_HEADER_LEN`] for the layout). Positions
/// in and out are Q15.16 mm.
/// The checked, borrow-free part of an [`SvrView`] (see
/// [`SvrView::from_summary`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SvrSummary {
    mode: OutputMode,
    scale_frac: u8,
    coef_frac: [u8; 3],
    mean: [i32; 3],
    scale: [i32; 3],
    offset: [i32; 3],
    support_abs_max: [u32; 3],
    support_vectors: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SvrView<'a> {
    mode: OutputMode,
    /// Fractional bits of the input scales (per mm).
    scale_frac: u8,
    /// Fractional bits of the coefficients (mm), per axis.
    coef_frac: [u8; 3],
    /// Input mean, Q15.16 mm.
    mean: [i32; 3],
    /// `sqrt(gamma log2 e) / std_in`, Q(`scale_frac`) per mm.
    scale: [i32; 3],
    /// `bias * std_out + mean_out`, Q15.16 mm.
    offset: [i32; 3],
    /// Largest `|s_i|` over the support vectors, per axis (Q4.27, at most
    /// [`SUPPORT_MAX`]): bounds the kernel exponent of an input.
    support_abs_max: [u32; 3],
    records: SvrRecords<'a>,
}

impl<'a> SvrView<'a> {
    /// Checks and wraps a compiled SVR of `support_vectors` support vectors
    /// (the blob header's count): exact length, mode, Q formats in range,
    /// support vectors within [`SUPPORT_MAX`], every axis' coefficients
    /// within [`SVR_BLOCK_ABS_SUM_MAX`] per block of [`SVR_BLOCK`].
    /// O(support_vectors), done once at load. The records are read as words
    /// when they start at a 4-byte aligned address (see `docs/fixed-point.md`),
    /// else as bytes; the results are the same.
    pub fn parse(bytes: &'a [u8], support_vectors: u32) -> Result<SvrView<'a>, BlobError> {
        let expected = (SVR_HEADER_LEN as u64)
            .saturating_add((SVR_RECORD_LEN as u64).saturating_mul(support_vectors as u64));
        if bytes.len() as u64 != expected {
            return Err(BlobError::Dimension {
                field: "svr.body_len",
                found: len_u32(bytes.len()),
                expected: u32::try_from(expected).unwrap_or(u32::MAX),
            });
        }
        let mode = mode_from_byte(bytes[0], "svr.mode")?;
        let scale_frac = bytes[1];
        if !INPUT_FRAC_RANGE.contains(&scale_frac) {
            return Err(BlobError::Body {
                field: "svr.scale_frac",
            });
        }
        let coef_frac = [bytes[2], bytes[3], bytes[4]];
        if coef_frac.iter().any(|f| !OUTPUT_FRAC_RANGE.contains(f)) {
            return Err(BlobError::Body {
                field: "svr.coef_frac",
            });
        }
        if bytes[5..8] != [0, 0, 0] {
            return Err(BlobError::Body {
                field: "svr.reserved",
            });
        }
        let mean = read3(bytes, 8, "svr.mean")?;
        let scale = read3(bytes, 20, "svr.scale")?;
        let offset = read3(bytes, 32, "svr.offset")?;
        let records = SvrRecords::new(&bytes[SVR_HEADER_LEN..]);
        let support_abs_max = match records {
            SvrRecords::Words(words) => check_svr_records(words.chunks(SVR_BLOCK), |r| *r),
            SvrRecords::Bytes(b) => check_svr_records(
                b.chunks(SVR_RECORD_LEN * SVR_BLOCK)
                    .map(|block| block.chunks_exact(SVR_RECORD_LEN)),
                |r| core::array::from_fn(|i| read_i32(r, 4 * i).unwrap_or(i32::MIN)),
            ),
        }?;
        Ok(SvrView {
            mode,
            scale_frac,
            coef_frac,
            mean,
            scale,
            offset,
            support_abs_max,
            records,
        })
    }

    /// Number of support vectors.
    pub fn support_vectors(&self) -> usize {
        self.records.len()
    }

    /// What [`parse`](Self::parse) established, without the borrow.
    pub fn summary(&self) -> SvrSummary {
        SvrSummary {
            mode: self.mode,
            scale_frac: self.scale_frac,
            coef_frac: self.coef_frac,
            mean: self.mean,
            scale: self.scale,
            offset: self.offset,
            support_abs_max: self.support_abs_max,
            support_vectors: self.records.len() as u32,
        }
    }

    /// The view again over the same bytes, in O(1): for a caller that parsed
    /// these bytes once and has not changed them since (the device keeps the
    /// active blob in RAM and rebuilds the view every control-loop tick;
    /// re-running [`parse`](Self::parse) would scan every support vector).
    /// Only the length is checked; different bytes give different (still
    /// saturated, never panicking) results, not an error.
    pub fn from_summary(summary: &SvrSummary, bytes: &'a [u8]) -> Result<SvrView<'a>, BlobError> {
        let expected = (SVR_HEADER_LEN as u64)
            .saturating_add((SVR_RECORD_LEN as u64).saturating_mul(summary.support_vectors as u64));
        if bytes.len() as u64 != expected {
            return Err(BlobError::Dimension {
                field: "svr.body_len",
                found: len_u32(bytes.len()),
                expected: u32::try_from(expected).unwrap_or(u32::MAX),
            });
        }
        Ok(SvrView {
            mode: summary.mode,
            scale_frac: summary.scale_frac,
            coef_frac: summary.coef_frac,
            mean: summary.mean,
            scale: summary.scale,
            offset: summary.offset,
            support_abs_max: summary.support_abs_max,
            records: SvrRecords::new(&bytes[SVR_HEADER_LEN..]),
        })
    }

    /// Output mode of the regressor.
    pub fn mode(&self) -> OutputMode {
        self.mode
    }

    /// Whether the records are read as aligned words (else as bytes; the
    /// results are the same, only the speed differs).
    pub fn reads_words(&self) -> bool {
        matches!(self.records, SvrRecords::Words(_))
    }

    /// Maps a Q15.16 mm position into the scaled space (Q4.27, saturated).
    #[inline(always)]
    fn scaled(&self, p: [i32; 3]) -> [i32; 3] {
        // Q(16 + scale_frac) -> Q27.
        let sh = (self.scale_frac as u32).wrapping_sub(SVR_SPACE_FRAC - POSITION_FRAC as u32);
        let mut q = [0i32; 3];
        for i in 0..3 {
            let d = p[i] as i64 - self.mean[i] as i64; // |d| < 2^32
            q[i] = sat_i32(shr_i64(d * self.scale[i] as i64, sh)); // |d * scale| < 2^63
        }
        q
    }

    /// Whether every kernel exponent of the scaled input `q` is below `2^31`
    /// in Q10.22 (i.e. `|q - s|^2 < 512`): then [`exp2_neg_q22_below_2p31_with`]
    /// is exact. `|sat(q_i - s_i)| <= |q_i| + max_j |s_ji|`, and the sum of
    /// the three squares of these bounds is below `2^63` in Q54.
    #[inline(always)]
    fn exponents_below_2p31(&self, q: [i32; 3]) -> bool {
        // |q_i| <= 2^31 and max |s_i| <= 2^30: the bound fits a u32.
        let d = |i: usize| (q[i].unsigned_abs() + self.support_abs_max[i]) as u64;
        (d(0) * d(0))
            .checked_add(d(1) * d(1))
            .and_then(|s| s.checked_add(d(2) * d(2)))
            .is_some_and(|s| s < 1 << 63)
    }

    /// Corrected position (Q15.16 mm) of a position `p` (Q15.16 mm). Integer
    /// only, saturating, never panics.
    pub fn evaluate(&self, p: [i32; 3]) -> [i32; 3] {
        let pass = SvrPass {
            q: self.scaled(p),
            base: core::hint::black_box(&EXP2_BASE),
            slope: core::hint::black_box(&EXP2_SLOPE),
        };
        let mut acc = [0i64; 3];
        match self.records {
            SvrRecords::Words(records) => {
                // Whole blocks, then the rest (a constant length per call).
                let blocks = records.chunks_exact(SVR_BLOCK);
                let rest = blocks.remainder();
                if self.exponents_below_2p31(pass.q) {
                    for block in blocks.chain(core::iter::once(rest)) {
                        svr_block_words::<true>(block, &pass.q, pass.base, pass.slope, &mut acc);
                    }
                } else {
                    for block in blocks.chain(core::iter::once(rest)) {
                        svr_block_words::<false>(block, &pass.q, pass.base, pass.slope, &mut acc);
                    }
                }
            }
            SvrRecords::Bytes(records) => {
                for block in records.chunks(SVR_RECORD_LEN * SVR_BLOCK) {
                    svr_block_bytes(block, &pass.q, pass.base, pass.slope, &mut acc);
                }
            }
        }
        [
            svr_finish(acc[0], self.coef_frac[0], self.offset[0], self.mode, p[0]),
            svr_finish(acc[1], self.coef_frac[1], self.offset[1], self.mode, p[1]),
            svr_finish(acc[2], self.coef_frac[2], self.offset[2], self.mode, p[2]),
        ]
    }
}

/// What every support vector of one SVR evaluation needs besides its record:
/// the scaled input and the exp2 tables (always [`EXP2_BASE`], [`EXP2_SLOPE`],
/// passed in so that LLVM keeps their addresses in registers or reloads them,
/// instead of rebuilding each from a `movw`/`movt` pair per use). One
/// pointer argument: the block functions take all their arguments in
/// registers.
struct SvrPass<'t> {
    q: [i32; 3],
    base: &'t [i32; EXP2_FRACTION_ENTRIES],
    slope: &'t [i32; EXP2_FRACTION_ENTRIES],
}

/// Adds a block's `i32` sums to the `i64` totals.
#[inline(always)]
fn add_block(total: &mut [i64; 3], block: [i32; 3]) {
    for a in 0..3 {
        total[a] = total[a].wrapping_add(block[a] as i64);
    }
}

/// The record checks of [`SvrView::parse`] over blocks of [`SVR_BLOCK`]
/// records (`record` reads one as `[s0, s1, s2, coef0, coef1, coef2]`):
/// `|s| <= SUPPORT_MAX`, per axis and block `sum |coef| <=
/// SVR_BLOCK_ABS_SUM_MAX`. Returns the largest `|s|` per axis.
fn check_svr_records<R, B, I>(
    blocks: B,
    record: impl Fn(R) -> [i32; 6],
) -> Result<[u32; 3], BlobError>
where
    B: Iterator<Item = I>,
    I: IntoIterator<Item = R>,
{
    let mut support_abs_max = [0u32; 3];
    for block in blocks {
        let mut sums = [0u64; 3];
        for rec in block {
            let rec = record(rec);
            for i in 0..3 {
                let s = rec[i].unsigned_abs();
                if s > SUPPORT_MAX as u32 {
                    return Err(BlobError::Body {
                        field: "svr.support",
                    });
                }
                support_abs_max[i] = support_abs_max[i].max(s);
                sums[i] += rec[3 + i].unsigned_abs() as u64;
            }
            if sums.iter().any(|&sum| sum > SVR_BLOCK_ABS_SUM_MAX) {
                return Err(BlobError::Body { field: "svr.coef" });
            }
        }
    }
    Ok(support_abs_max)
}

/// `acc + round(a b / 2^32)` (wrapping), one `smmlar` on the Cortex-M7.
#[inline(always)]
fn mul_hi_round_acc(acc: i32, a: i32, b: i32) -> i32 {
    ((((acc as i64) << 32)
        .wrapping_add(a as i64 * b as i64)
        .wrapping_add(1 << 31))
        >> 32) as i32
}

/// One block of at most [`SVR_BLOCK`] support vectors read as aligned words:
/// adds to `total[a]` the block's `sum_j round(coef_a K_j / 2^32)`, `K_j =
/// 2^-|q - s_j|^2` (Q1.30), in Q(`coef_frac_a` - 2) mm, summed in an `i32`.
/// One pass: q (3), three `i32` accumulators, the record pointer and count
/// and the two table addresses (one reloaded per support vector: 14
/// registers for 13). `NARROW`: the caller checked that every exponent is
/// below `2^31` (`SvrView::exponents_below_2p31`), so the saturated shift of
/// the kernel is one `usat`; the results are the same as without. Not
/// inlined, so that the register allocation of this loop does not depend on
/// the caller.
#[inline(never)]
fn svr_block_words<const NARROW: bool>(
    block: &[[i32; 6]],
    q: &[i32; 3],
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
    total: &mut [i64; 3],
) {
    let q = *q;
    let mut acc = [0i32; 3];
    // An index loop: LLVM counts down and steps the pointer in the first
    // load (2 instructions of loop control; an iterator compares pointers, 3).
    #[allow(clippy::needless_range_loop)]
    for i in 0..block.len() {
        // An empty barrier (no instruction: an empty `asm` with a memory
        // clobber): LLVM does not unroll a loop containing it. Unrolled (and
        // interleaved), this loop no longer fits the registers and spills.
        core::hint::black_box(());
        let [s0, s1, s2, c0, c1, c2] = block[i];
        acc = svr_term::<NARROW>([s0, s1, s2], [c0, c1, c2], q, acc, base, slope);
    }
    add_block(total, acc);
}

/// [`svr_block_words`] for records at any address (`block` holds whole
/// [`SVR_RECORD_LEN`]-byte records; a trailing partial record adds nothing),
/// read with single little-endian word loads. Always the general saturated
/// shift: the same results as the word path, bit for bit.
#[inline(never)]
fn svr_block_bytes(
    block: &[u8],
    q: &[i32; 3],
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
    total: &mut [i64; 3],
) {
    let q = *q;
    let mut acc = [0i32; 3];
    for rec in block.chunks_exact(SVR_RECORD_LEN) {
        core::hint::black_box(());
        let Ok(rec) = <&[u8; SVR_RECORD_LEN]>::try_from(rec) else {
            continue;
        };
        let s = [
            le_i32::<SVR_RECORD_LEN, 0>(rec),
            le_i32::<SVR_RECORD_LEN, 4>(rec),
            le_i32::<SVR_RECORD_LEN, 8>(rec),
        ];
        let c = [
            le_i32::<SVR_RECORD_LEN, 12>(rec),
            le_i32::<SVR_RECORD_LEN, 16>(rec),
            le_i32::<SVR_RECORD_LEN, 20>(rec),
        ];
        acc = svr_term::<false>(s, c, q, acc, base, slope);
    }
    add_block(total, acc);
}

/// Adds one support vector's terms (support vector `s`, coefficients `c`)
/// to the block accumulators. `NARROW`: see [`svr_block_words`].
#[inline(always)]
fn svr_term<const NARROW: bool>(
    s: [i32; 3],
    c: [i32; 3],
    q: [i32; 3],
    acc: [i32; 3],
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
) -> [i32; 3] {
    let d0 = q[0].saturating_sub(s[0]) as i64;
    let d1 = q[1].saturating_sub(s[1]) as i64;
    let d2 = q[2].saturating_sub(s[2]) as i64;
    // Each square <= 2^62; the sum < 2^64 as an unsigned bit pattern. Its
    // high word is u in Q10.22 (truncated).
    let u = ((d0 * d0) as u64)
        .wrapping_add((d1 * d1) as u64)
        .wrapping_add((d2 * d2) as u64);
    let u = (u >> 32) as u32;
    // K = 0 from u >= 30 on (the saturated shift).
    let k = if NARROW {
        exp2_neg_q22_below_2p31_with(u, base, slope)
    } else {
        exp2_neg_q22_with(u, base, slope)
    };
    [
        mul_hi_round_acc(acc[0], c[0], k),
        mul_hi_round_acc(acc[1], c[1], k),
        mul_hi_round_acc(acc[2], c[2], k),
    ]
}

/// SVR output step: accumulator in Q(`frac` - 2) mm to Q15.16 (a rounding
/// right shift, or a saturating left shift for `frac < 18`), plus offset,
/// plus the input in residual mode, saturated.
#[inline(always)]
fn svr_finish(acc: i64, frac: u8, offset: i32, mode: OutputMode, p: i32) -> i32 {
    const ACC_FRAC_BELOW_COEF: u32 = 32 - ACTIVATION_FRAC as u32; // 2
    let acc_frac = frac as i32 - ACC_FRAC_BELOW_COEF as i32;
    let sh = acc_frac - POSITION_FRAC as i32; // -18..=30
    let y = if sh >= 0 {
        shr_round_i64(acc, sh as u32)
    } else {
        let l = sh.unsigned_abs();
        // |acc| < 2^47 (at most 2^26 blocks of 2^31): no overflow below 2^16.
        if acc.unsigned_abs() >> (62 - l) != 0 {
            if acc < 0 {
                i64::MIN
            } else {
                i64::MAX
            }
        } else {
            acc << l
        }
    };
    let base = match mode {
        OutputMode::Absolute => 0,
        OutputMode::Residual => p as i64,
    };
    sat_i32(y.saturating_add(offset as i64).saturating_add(base))
}

// ---------------------------------------------------------------------------
// Either correction.

/// The position correction of a loaded blob, evaluated in place.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Correction<'a> {
    /// No correction: positions pass through.
    None,
    Nn(NnView<'a>),
    Svr(SvrView<'a>),
}

/// What parsing a correction established, without the borrow of its bytes:
/// kept by a caller that holds the bytes unchanged and rebuilds the view
/// often ([`Correction::from_summary`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CorrectionSummary {
    None,
    Nn(NnSummary),
    Svr(SvrSummary),
}

impl<'a> Correction<'a> {
    /// The borrow-free summary of this view.
    pub fn summary(&self) -> CorrectionSummary {
        match self {
            Correction::None => CorrectionSummary::None,
            Correction::Nn(nn) => CorrectionSummary::Nn(nn.summary()),
            Correction::Svr(svr) => CorrectionSummary::Svr(svr.summary()),
        }
    }

    /// The view again over bytes that were parsed into `summary` and have not
    /// changed since; O(1) ([`NnView::from_summary`], [`SvrView::from_summary`]).
    pub fn from_summary(
        summary: &CorrectionSummary,
        bytes: &'a [u8],
    ) -> Result<Correction<'a>, BlobError> {
        match summary {
            CorrectionSummary::None => Ok(Correction::None),
            CorrectionSummary::Nn(s) => Ok(Correction::Nn(NnView::from_summary(s, bytes)?)),
            CorrectionSummary::Svr(s) => Ok(Correction::Svr(SvrView::from_summary(s, bytes)?)),
        }
    }

    /// Checks and wraps the correction bytes of a blob given the header's
    /// `kind`, `hidden` and `support_vectors` (which must be 0 for the kinds
    /// that do not use them; `None` must have no bytes).
    pub fn parse(
        kind: CorrectionKind,
        hidden: u16,
        support_vectors: u32,
        bytes: &'a [u8],
    ) -> Result<Correction<'a>, BlobError> {
        let zero = |field: &'static str, found: u32| {
            if found == 0 {
                Ok(())
            } else {
                Err(BlobError::Dimension {
                    field,
                    found,
                    expected: 0,
                })
            }
        };
        match kind {
            CorrectionKind::None => {
                zero("hidden", hidden as u32)?;
                zero("support_vectors", support_vectors)?;
                zero("correction.body_len", len_u32(bytes.len()))?;
                Ok(Correction::None)
            }
            CorrectionKind::Nn => {
                zero("support_vectors", support_vectors)?;
                Ok(Correction::Nn(NnView::parse(bytes, hidden)?))
            }
            CorrectionKind::Svr => {
                zero("hidden", hidden as u32)?;
                Ok(Correction::Svr(SvrView::parse(bytes, support_vectors)?))
            }
        }
    }

    /// Which correction this is.
    pub fn kind(&self) -> CorrectionKind {
        match self {
            Correction::None => CorrectionKind::None,
            Correction::Nn(_) => CorrectionKind::Nn,
            Correction::Svr(_) => CorrectionKind::Svr,
        }
    }

    /// Corrected position (Q15.16 mm) of `p` (Q15.16 mm); `p` itself for
    /// [`Correction::None`].
    pub fn evaluate(&self, p: [i32; 3]) -> [i32; 3] {
        match self {
            Correction::None => p,
            Correction::Nn(nn) => nn.evaluate(p),
            Correction::Svr(svr) => svr.evaluate(p),
        }
    }
}

// ---------------------------------------------------------------------------
// The host side (alloc): f64 reference evaluation and compilation.

#[cfg(feature = "alloc")]
pub use compiler::{CompileError, CompiledCorrection};

#[cfg(feature = "alloc")]
mod compiler {
    use super::*;
    use crate::fixed::to_q_i32;
    use alloc::vec::Vec;

    /// Why a model does not compile. Each variant names the parameter.
    #[cfg_attr(feature = "defmt", derive(defmt::Format))]
    #[derive(Clone, Copy, Debug, PartialEq)]
    pub enum CompileError {
        /// Parameter vectors of inconsistent lengths, or a count beyond what
        /// the blob can carry.
        Dimension {
            field: &'static str,
            found: usize,
            expected: usize,
        },
        /// A parameter is NaN or infinite (`index` into the flattened field).
        NotFinite { field: &'static str, index: usize },
        /// A standard deviation or `gamma` that is not strictly positive.
        NotPositive {
            field: &'static str,
            index: usize,
            value: f64,
        },
        /// A parameter (after folding the standardization into it) that does
        /// not fit its Q format.
        OutOfRange {
            field: &'static str,
            index: usize,
            value: f64,
            format: &'static str,
        },
    }

    impl core::fmt::Display for CompileError {
        fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
            match *self {
                CompileError::Dimension {
                    field,
                    found,
                    expected,
                } => write!(
                    f,
                    "correction parameter `{field}` has {found} entries, expected {expected}"
                ),
                CompileError::NotFinite { field, index } => {
                    write!(f, "correction parameter `{field}`[{index}] is not finite")
                }
                CompileError::NotPositive {
                    field,
                    index,
                    value,
                } => write!(
                    f,
                    "correction parameter `{field}`[{index}] = {value} must be strictly positive"
                ),
                CompileError::OutOfRange {
                    field,
                    index,
                    value,
                    format,
                } => write!(
                    f,
                    "correction parameter `{field}`[{index}] = {value} does not fit {format}"
                ),
            }
        }
    }

    impl core::error::Error for CompileError {}

    /// A compiled correction: the blob header fields it sets and the
    /// correction bytes of the blob body.
    #[derive(Clone, Debug, PartialEq, Eq)]
    pub struct CompiledCorrection {
        pub kind: CorrectionKind,
        /// Header `hidden` (NN), else 0.
        pub hidden: u16,
        /// Header `support_vectors` (SVR), else 0.
        pub support_vectors: u32,
        /// Header `q_position`: [`POSITION_FRAC`].
        pub q_position: u8,
        /// Header `q_weight`: [`ACTIVATION_FRAC`].
        pub q_weight: u8,
        /// The bytes [`Correction::parse`] reads.
        pub bytes: Vec<u8>,
    }

    const LOG2_E: f64 = core::f64::consts::LOG2_E;

    fn pow2(e: u32) -> f64 {
        libm::ldexp(1.0, e as i32)
    }

    fn check_finite(field: &'static str, values: &[f64]) -> Result<(), CompileError> {
        match values.iter().position(|v| !v.is_finite()) {
            Some(index) => Err(CompileError::NotFinite { field, index }),
            None => Ok(()),
        }
    }

    fn check_standardization(s: &Standardization, side: u8) -> Result<(), CompileError> {
        let (mean, std) = if side == 0 {
            ("input.mean", "input.std")
        } else {
            ("output.mean", "output.std")
        };
        check_finite(mean, &s.mean)?;
        check_finite(std, &s.std)?;
        for (index, &value) in s.std.iter().enumerate() {
            if value <= 0.0 {
                return Err(CompileError::NotPositive {
                    field: std,
                    index,
                    value,
                });
            }
        }
        Ok(())
    }

    fn q16(field: &'static str, index: usize, v: f64) -> Result<i32, CompileError> {
        to_q_i32(v, POSITION_FRAC as u32).ok_or(CompileError::OutOfRange {
            field,
            index,
            value: v,
            format: "i32 Q15.16 mm",
        })
    }

    /// Largest fractional bits in `range` with `max_abs * 2^frac <= limit`
    /// (after rounding); `None` if even the smallest does not fit.
    fn best_frac(max_abs: f64, limit: f64, range: core::ops::RangeInclusive<u8>) -> Option<u8> {
        range
            .rev()
            .find(|&f| libm::round(max_abs * pow2(f as u32)) <= limit)
    }

    /// Fractional bits for one axis of output weights (`i32` each, the sum of
    /// magnitudes within [`OUTPUT_ABS_SUM_MAX`] after rounding).
    fn output_frac(w: &[f64]) -> Option<u8> {
        let max = w.iter().fold(0f64, |m, v| m.max(libm::fabs(*v)));
        let sum: f64 = w.iter().map(|v| libm::fabs(*v)).sum();
        OUTPUT_FRAC_RANGE.rev().find(|&f| {
            let s = pow2(f as u32);
            libm::round(max * s) <= i32::MAX as f64
                && sum * s + w.len() as f64 <= OUTPUT_ABS_SUM_MAX as f64
        })
    }

    /// Fractional bits for one axis of SVR coefficients (`i32` each, the sum
    /// of magnitudes of every block of [`SVR_BLOCK`] within
    /// [`SVR_BLOCK_ABS_SUM_MAX`] after rounding).
    fn svr_coef_frac(c: &[f64]) -> Option<u8> {
        let max = c.iter().fold(0f64, |m, v| m.max(libm::fabs(*v)));
        let block_sum = c
            .chunks(SVR_BLOCK)
            .map(|b| b.iter().map(|v| libm::fabs(*v)).sum::<f64>())
            .fold(0f64, f64::max);
        OUTPUT_FRAC_RANGE.rev().find(|&f| {
            let s = pow2(f as u32);
            libm::round(max * s) <= i32::MAX as f64
                && block_sum * s + SVR_BLOCK as f64 <= SVR_BLOCK_ABS_SUM_MAX as f64
        })
    }

    fn largest(
        field: &'static str,
        values: impl Iterator<Item = f64>,
        format: &'static str,
    ) -> CompileError {
        let (index, value) = values.enumerate().fold((0, 0f64), |(bi, bv), (i, v)| {
            if libm::fabs(v) > libm::fabs(bv) {
                (i, v)
            } else {
                (bi, bv)
            }
        });
        CompileError::OutOfRange {
            field,
            index,
            value,
            format,
        }
    }

    fn standardize(s: &Standardization, p: [f64; 3]) -> [f64; 3] {
        [
            (p[0] - s.mean[0]) / s.std[0],
            (p[1] - s.mean[1]) / s.std[1],
            (p[2] - s.mean[2]) / s.std[2],
        ]
    }

    fn destandardize(s: &Standardization, mode: OutputMode, p: [f64; 3], y: [f64; 3]) -> [f64; 3] {
        let mut out = [0.0; 3];
        for a in 0..3 {
            out[a] = y[a] * s.std[a] + s.mean[a];
            if mode == OutputMode::Residual {
                out[a] += p[a];
            }
        }
        out
    }

    fn push_i32(out: &mut Vec<u8>, v: i32) {
        out.extend_from_slice(&v.to_le_bytes());
    }

    impl NnModel {
        /// Reference evaluation in f64 (eq. 10 standardization, tanh hidden
        /// layer via libm, linear output, de-standardization, output mode):
        /// position in mm to corrected position in mm. Parameter vectors of
        /// inconsistent lengths are truncated to the shortest (see
        /// [`NnModel::compile`] for the checked form).
        pub fn evaluate(&self, p_mm: [f64; 3]) -> [f64; 3] {
            let x = standardize(&self.input, p_mm);
            let mut y = self.b2;
            for (h, (w1, b1)) in self.w1.iter().zip(&self.b1).enumerate() {
                let t = libm::tanh(w1[0] * x[0] + w1[1] * x[1] + w1[2] * x[2] + b1);
                for (a, ya) in y.iter_mut().enumerate() {
                    *ya += self.w2[a].get(h).copied().unwrap_or(0.0) * t;
                }
            }
            destandardize(&self.output, self.mode, p_mm, y)
        }

        /// Compiles the network into its fixed-point bytes (layout at
        /// [`NN_HEADER_LEN`]). Folds the input scale into the first-layer
        /// weights, the rounding of the input mean into the first-layer biases,
        /// and the output scale and mean into the output weights and offsets;
        /// picks the fractional bits of each layer (each output axis) to use
        /// the full `i32` range.
        pub fn compile(&self) -> Result<Vec<u8>, CompileError> {
            let hidden = self.w1.len();
            if hidden == 0 || hidden > u16::MAX as usize {
                return Err(CompileError::Dimension {
                    field: "w1",
                    found: hidden,
                    expected: if hidden == 0 { 1 } else { u16::MAX as usize },
                });
            }
            if self.b1.len() != hidden {
                return Err(CompileError::Dimension {
                    field: "b1",
                    found: self.b1.len(),
                    expected: hidden,
                });
            }
            const W2: [&str; 3] = ["w2[0]", "w2[1]", "w2[2]"];
            for (a, w2) in self.w2.iter().enumerate() {
                if w2.len() != hidden {
                    return Err(CompileError::Dimension {
                        field: W2[a],
                        found: w2.len(),
                        expected: hidden,
                    });
                }
                check_finite(W2[a], w2)?;
            }
            check_standardization(&self.input, 0)?;
            check_standardization(&self.output, 1)?;
            check_finite("w1", self.w1.as_flattened())?;
            check_finite("b1", &self.b1)?;
            check_finite("b2", &self.b2)?;

            // Input mean in Q15.16; the rounding residual goes into b1.
            let mut mean = [0i32; 3];
            let mut mean_residual = [0f64; 3];
            for i in 0..3 {
                mean[i] = q16("input.mean", i, self.input.mean[i])?;
                mean_residual[i] = self.input.mean[i] - mean[i] as f64 / 65536.0;
            }
            // First layer with the input scale folded in (per mm).
            let w1: Vec<[f64; 3]> = self
                .w1
                .iter()
                .map(|w| {
                    [
                        w[0] / self.input.std[0],
                        w[1] / self.input.std[1],
                        w[2] / self.input.std[2],
                    ]
                })
                .collect();
            let w1_max = w1
                .as_flattened()
                .iter()
                .fold(0f64, |m, v| m.max(libm::fabs(*v)));
            let w1_frac = best_frac(w1_max, W1_MAX as f64, W1_FRAC_RANGE).ok_or_else(|| {
                largest(
                    "w1",
                    w1.as_flattened().iter().copied(),
                    "i32 Q(12) per mm within 2^29 (w1 / input.std)",
                )
            })?;
            // Output weights with the output scale folded in (mm).
            let mut w2_frac = [0u8; 3];
            let mut w2: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
            for a in 0..3 {
                w2[a] = self.w2[a].iter().map(|w| w * self.output.std[a]).collect();
                w2_frac[a] = output_frac(&w2[a]).ok_or_else(|| {
                    largest(
                        W2[a],
                        w2[a].iter().copied(),
                        "i32 Q(0) mm, sum of magnitudes within 2^32 (w2 * output.std)",
                    )
                })?;
            }
            let mut offset = [0i32; 3];
            for (a, o) in offset.iter_mut().enumerate() {
                *o = q16(
                    "b2",
                    a,
                    self.b2[a] * self.output.std[a] + self.output.mean[a],
                )?;
            }

            let mut out = Vec::with_capacity(NN_HEADER_LEN + NN_NEURON_LEN * hidden);
            out.push(mode_byte(self.mode));
            out.push(w1_frac);
            out.extend_from_slice(&w2_frac);
            out.extend_from_slice(&[0, 0, 0]);
            mean.iter().for_each(|&v| push_i32(&mut out, v));
            offset.iter().for_each(|&v| push_i32(&mut out, v));
            let s1 = pow2(w1_frac as u32);
            for h in 0..hidden {
                for &w in &w1[h] {
                    // |w * 2^w1_frac| <= 2^29 by the choice of w1_frac.
                    push_i32(&mut out, libm::round(w * s1) as i32);
                }
                // x = w1 . (p - mean_q) + b1 - w1 . mean_residual.
                let b1 = self.b1[h]
                    - (w1[h][0] * mean_residual[0]
                        + w1[h][1] * mean_residual[1]
                        + w1[h][2] * mean_residual[2]);
                let b1q = to_q_i32(b1, PREACTIVATION_FRAC).ok_or(CompileError::OutOfRange {
                    field: "b1",
                    index: h,
                    value: self.b1[h],
                    format: "i32 Q4.27",
                })?;
                push_i32(&mut out, b1q);
                for a in 0..3 {
                    push_i32(
                        &mut out,
                        libm::round(w2[a][h] * pow2(w2_frac[a] as u32)) as i32,
                    );
                }
            }
            Ok(out)
        }
    }

    impl SvrModel {
        /// Reference evaluation in f64 (eq. 10 standardization, RBF kernel
        /// `exp(-gamma |x - sv|^2)` via libm, de-standardization, output mode):
        /// position in mm to corrected position in mm. Parameter vectors of
        /// inconsistent lengths are truncated to the shortest.
        pub fn evaluate(&self, p_mm: [f64; 3]) -> [f64; 3] {
            let x = standardize(&self.input, p_mm);
            let mut y = self.bias;
            for (j, sv) in self.support.iter().enumerate() {
                let d2 = (x[0] - sv[0]) * (x[0] - sv[0])
                    + (x[1] - sv[1]) * (x[1] - sv[1])
                    + (x[2] - sv[2]) * (x[2] - sv[2]);
                let k = libm::exp(-self.gamma * d2);
                for (a, ya) in y.iter_mut().enumerate() {
                    *ya += self.coef[a].get(j).copied().unwrap_or(0.0) * k;
                }
            }
            destandardize(&self.output, self.mode, p_mm, y)
        }

        /// Compiles the regressor into its fixed-point bytes (layout at
        /// [`SVR_HEADER_LEN`]): support vectors mapped into the scaled space
        /// `sqrt(gamma log2 e) * standardized` (Q4.27, the input mean's
        /// rounding folded in), coefficients with the output scale folded in,
        /// fractional bits per axis. The support-vector count (header
        /// `support_vectors`) is `self.support.len()`.
        pub fn compile(&self) -> Result<Vec<u8>, CompileError> {
            let n = self.support.len();
            if n > (u32::MAX as usize - SVR_HEADER_LEN) / SVR_RECORD_LEN {
                return Err(CompileError::Dimension {
                    field: "support",
                    found: n,
                    expected: (u32::MAX as usize - SVR_HEADER_LEN) / SVR_RECORD_LEN,
                });
            }
            const COEF: [&str; 3] = ["coef[0]", "coef[1]", "coef[2]"];
            for (a, c) in self.coef.iter().enumerate() {
                if c.len() != n {
                    return Err(CompileError::Dimension {
                        field: COEF[a],
                        found: c.len(),
                        expected: n,
                    });
                }
                check_finite(COEF[a], c)?;
            }
            check_standardization(&self.input, 0)?;
            check_standardization(&self.output, 1)?;
            check_finite("support", self.support.as_flattened())?;
            check_finite("bias", &self.bias)?;
            if !self.gamma.is_finite() {
                return Err(CompileError::NotFinite {
                    field: "gamma",
                    index: 0,
                });
            }
            if self.gamma <= 0.0 {
                return Err(CompileError::NotPositive {
                    field: "gamma",
                    index: 0,
                    value: self.gamma,
                });
            }

            let r = libm::sqrt(self.gamma * LOG2_E);
            let mut mean = [0i32; 3];
            let mut mean_residual = [0f64; 3];
            let g = [
                r / self.input.std[0],
                r / self.input.std[1],
                r / self.input.std[2],
            ];
            for i in 0..3 {
                mean[i] = q16("input.mean", i, self.input.mean[i])?;
                mean_residual[i] = self.input.mean[i] - mean[i] as f64 / 65536.0;
            }
            let g_max = g.iter().fold(0f64, |m, v| m.max(*v));
            let scale_frac =
                best_frac(g_max, i32::MAX as f64, INPUT_FRAC_RANGE).ok_or_else(|| {
                    largest(
                        "input.std",
                        g.iter().copied(),
                        "i32 Q(11) per mm (sqrt(gamma log2 e) / input.std)",
                    )
                })?;
            let sg = pow2(scale_frac as u32);
            let scale = [
                libm::round(g[0] * sg) as i32,
                libm::round(g[1] * sg) as i32,
                libm::round(g[2] * sg) as i32,
            ];
            // The device computes q = (p - mean_q) * scale_q; the support
            // vectors absorb the rounding of the mean and of the scale so that
            // q - s is the exact scaled difference (to Q27 rounding):
            // q_true = (p - mean) g = q_dev + (p - mean_q)(g - g_q) - mean_residual g.
            // The middle term is at most |p - mean_q| * 2^-scale_frac/2 * ... and
            // is left out (it is below 1e-9 over the workspace).
            let mut coef_frac = [0u8; 3];
            let mut coef: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
            for a in 0..3 {
                coef[a] = self.coef[a]
                    .iter()
                    .map(|c| c * self.output.std[a])
                    .collect();
                coef_frac[a] = svr_coef_frac(&coef[a]).ok_or_else(|| {
                    largest(
                        COEF[a],
                        coef[a].iter().copied(),
                        "i32 Q(0) mm, sum of magnitudes per block of 64 within 2^33 (coef * output.std)",
                    )
                })?;
            }
            let mut offset = [0i32; 3];
            for (a, o) in offset.iter_mut().enumerate() {
                *o = q16(
                    "bias",
                    a,
                    self.bias[a] * self.output.std[a] + self.output.mean[a],
                )?;
            }

            let mut out = Vec::with_capacity(SVR_HEADER_LEN + SVR_RECORD_LEN * n);
            out.push(mode_byte(self.mode));
            out.push(scale_frac);
            out.extend_from_slice(&coef_frac);
            out.extend_from_slice(&[0, 0, 0]);
            mean.iter().for_each(|&v| push_i32(&mut out, v));
            scale.iter().for_each(|&v| push_i32(&mut out, v));
            offset.iter().for_each(|&v| push_i32(&mut out, v));
            let space = pow2(SVR_SPACE_FRAC);
            for (j, sv) in self.support.iter().enumerate() {
                for i in 0..3 {
                    let s = sv[i] * r + mean_residual[i] * g[i];
                    let sq = libm::round(s * space);
                    if !(-(SUPPORT_MAX as f64)..=SUPPORT_MAX as f64).contains(&sq) {
                        return Err(CompileError::OutOfRange {
                            field: "support",
                            index: 3 * j + i,
                            value: sv[i],
                            format: "Q4.27 within 8.0 after scaling by sqrt(gamma log2 e)",
                        });
                    }
                    push_i32(&mut out, sq as i32);
                }
                for a in 0..3 {
                    push_i32(
                        &mut out,
                        libm::round(coef[a][j] * pow2(coef_frac[a] as u32)) as i32,
                    );
                }
            }
            Ok(out)
        }
    }

    impl CorrectionModel {
        /// Reference evaluation in f64 (the input itself for `None`).
        pub fn evaluate(&self, p_mm: [f64; 3]) -> [f64; 3] {
            match self {
                CorrectionModel::None => p_mm,
                CorrectionModel::Nn(nn) => nn.evaluate(p_mm),
                CorrectionModel::Svr(svr) => svr.evaluate(p_mm),
            }
        }

        /// Compiles the correction: its bytes and the header fields they need.
        pub fn compile(&self) -> Result<CompiledCorrection, CompileError> {
            let (kind, hidden, support_vectors, bytes) = match self {
                CorrectionModel::None => (CorrectionKind::None, 0, 0, Vec::new()),
                CorrectionModel::Nn(nn) => {
                    (CorrectionKind::Nn, nn.w1.len() as u16, 0, nn.compile()?)
                }
                CorrectionModel::Svr(svr) => (
                    CorrectionKind::Svr,
                    0,
                    svr.support.len() as u32,
                    svr.compile()?,
                ),
            };
            Ok(CompiledCorrection {
                kind,
                hidden,
                support_vectors,
                q_position: POSITION_FRAC,
                q_weight: ACTIVATION_FRAC,
                bytes,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed::{mm_to_q16, q16_to_mm};
    use proptest::prelude::*;

    /// splitmix64: deterministic test data without a dependency.
    struct Rng(u64);
    impl Rng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }
        /// Uniform in [lo, hi).
        fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
            lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let u1 = self.uniform(1e-12, 1.0);
            let u2 = self.uniform(0.0, 1.0);
            libm::sqrt(-2.0 * libm::log(u1)) * libm::cos(2.0 * core::f64::consts::PI * u2)
        }
    }

    /// Half the side of the workspace cube (mm): a 1 m cube around the origin.
    const HALF: f64 = 500.0;

    fn input_std() -> Standardization {
        // A uniform distribution over ±500 mm has std 1000/sqrt(12) = 288.7 mm.
        Standardization {
            mean: [3.217, -7.93, 11.4041],
            std: [288.1, 291.7, 286.9],
        }
    }

    fn output_std() -> Standardization {
        Standardization {
            mean: [1.9, -4.3, 8.77],
            std: [301.3, 297.8, 305.2],
        }
    }

    /// A 3-H-3 network shaped like an LM-trained one: first-layer weights of a
    /// few units, and pairs of neurons with close first-layer weights and
    /// large opposite output weights, so that sum |W2| * std_out is about
    /// 37,000 mm per axis while the output stays within a few hundred mm.
    fn nn_model(hidden: usize, seed: u64, mode: OutputMode) -> NnModel {
        let mut rng = Rng(seed);
        let mut w1 = Vec::new();
        let mut b1 = Vec::new();
        let mut w2: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
        for h in 0..hidden {
            if h % 2 == 1 {
                let prev: [f64; 3] = w1[h - 1];
                w1.push([
                    prev[0] * (1.0 + 0.08 * rng.normal()),
                    prev[1] * (1.0 + 0.08 * rng.normal()),
                    prev[2] * (1.0 + 0.08 * rng.normal()),
                ]);
                b1.push(b1[h - 1] + 0.1 * rng.normal());
                for (a, w) in w2.iter_mut().enumerate() {
                    let prev = w[h - 1];
                    let _ = a;
                    w.push(-prev * (1.0 + 0.05 * rng.normal()));
                }
            } else {
                w1.push([1.5 * rng.normal(), 1.5 * rng.normal(), 1.5 * rng.normal()]);
                b1.push(rng.uniform(-1.5, 1.5));
                for w in w2.iter_mut() {
                    w.push(rng.uniform(-12.0, 12.0));
                }
            }
        }
        // Scale the output weights so that sum |W2| * std_out = 37,000 mm.
        let out = output_std();
        for (a, w) in w2.iter_mut().enumerate() {
            let s: f64 = w.iter().map(|v| v.abs()).sum::<f64>() * out.std[a];
            w.iter_mut().for_each(|v| *v *= 37_000.0 / s);
        }
        NnModel {
            input: input_std(),
            output: out,
            w1,
            b1,
            w2,
            b2: [0.03, -0.02, 0.05],
            mode,
        }
    }

    /// An RBF SVR shaped like the notes' one: support vectors over the
    /// standardized workspace, gamma = 1/3, sum |coef| = 845 per axis.
    fn svr_model(n: usize, seed: u64, mode: OutputMode) -> SvrModel {
        let mut rng = Rng(seed);
        let lim = HALF / 288.7;
        let support = (0..n)
            .map(|_| {
                [
                    rng.uniform(-lim, lim),
                    rng.uniform(-lim, lim),
                    rng.uniform(-lim, lim),
                ]
            })
            .collect();
        let mut coef: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
        for c in coef.iter_mut() {
            *c = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let s: f64 = c.iter().map(|v| v.abs()).sum();
            c.iter_mut().for_each(|v| *v *= 845.0 / s);
        }
        SvrModel {
            input: input_std(),
            output: output_std(),
            gamma: 1.0 / 3.0,
            support,
            coef,
            bias: [0.01, -0.04, 0.02],
            mode,
        }
    }

    /// Positions of the 1 m workspace cube: a 21^3 grid (10 steps of 100 mm per
    /// axis... 50 mm) and 2,000 random points, as Q15.16.
    fn workspace_points() -> Vec<[i32; 3]> {
        let mut pts = Vec::new();
        for i in 0..21 {
            for j in 0..21 {
                for k in 0..21 {
                    let c = |n: i32| -HALF + 50.0 * n as f64;
                    pts.push([mm_to_q16(c(i)), mm_to_q16(c(j)), mm_to_q16(c(k))]);
                }
            }
        }
        let mut rng = Rng(77);
        for _ in 0..2000 {
            pts.push([
                mm_to_q16(rng.uniform(-HALF, HALF)),
                mm_to_q16(rng.uniform(-HALF, HALF)),
                mm_to_q16(rng.uniform(-HALF, HALF)),
            ]);
        }
        pts
    }

    /// Mean and max Euclidean distance (mm) between the fixed-point output and
    /// the f64 output on the same (Q15.16-representable) inputs.
    fn error_stats(
        f64_eval: impl Fn([f64; 3]) -> [f64; 3],
        fixed_eval: impl Fn([i32; 3]) -> [i32; 3],
    ) -> (f64, f64) {
        let pts = workspace_points();
        let mut sum = 0.0;
        let mut max = 0f64;
        for p in &pts {
            let pf = [q16_to_mm(p[0]), q16_to_mm(p[1]), q16_to_mm(p[2])];
            let want = f64_eval(pf);
            let got = fixed_eval(*p);
            let e = (0..3)
                .map(|a| (q16_to_mm(got[a]) - want[a]).powi(2))
                .sum::<f64>()
                .sqrt();
            sum += e;
            max = max.max(e);
        }
        (sum / pts.len() as f64, max)
    }

    fn nn_view<'a>(bytes: &'a [u8], model: &NnModel) -> NnView<'a> {
        NnView::parse(bytes, model.w1.len() as u16).expect("compiled NN parses")
    }

    #[test]
    fn nn_model_is_realistic() {
        let m = nn_model(20, 1, OutputMode::Absolute);
        for a in 0..3 {
            let s: f64 = m.w2[a].iter().map(|v| v.abs()).sum::<f64>() * m.output.std[a];
            assert!((s - 37_000.0).abs() < 1.0);
        }
        // Outputs stay within a plausible range despite the large weights.
        let mut max = 0f64;
        for p in workspace_points().iter().step_by(37) {
            let y = m.evaluate([q16_to_mm(p[0]), q16_to_mm(p[1]), q16_to_mm(p[2])]);
            max = max.max(y.iter().fold(0f64, |m, v| m.max(v.abs())));
        }
        assert!(max < 20_000.0, "{max}");
    }

    #[test]
    fn nn_error_budget() {
        for (seed, mode) in [
            (1, OutputMode::Absolute),
            (2, OutputMode::Residual),
            (3, OutputMode::Absolute),
        ] {
            let m = nn_model(20, seed, mode);
            let bytes = m.compile().expect("compiles");
            assert_eq!(bytes.len(), NN_HEADER_LEN + 20 * NN_NEURON_LEN);
            let v = nn_view(&bytes, &m);
            let (mean, max) = error_stats(|p| m.evaluate(p), |p| v.evaluate(p));
            eprintln!("NN 3-20-3 seed {seed} {mode:?}: mean {mean:.6} mm, max {max:.6} mm");
            assert!(mean < 0.001, "NN mean error {mean} mm");
            assert!(max < 0.002, "NN max error {max} mm");
        }
    }

    #[test]
    fn view_rebuilt_from_its_summary_evaluates_the_same() {
        for model in [
            CorrectionModel::Svr(svr_model(200, 5, OutputMode::Residual)),
            CorrectionModel::Svr(svr_model(70, 6, OutputMode::Absolute)),
            CorrectionModel::Nn(nn_model(20, 7, OutputMode::Residual)),
            CorrectionModel::Nn(nn_model(3, 8, OutputMode::Absolute)),
        ] {
            let c = model.compile().expect("compiles");
            let parsed =
                Correction::parse(c.kind, c.hidden, c.support_vectors, &c.bytes).expect("parses");
            let rebuilt = Correction::from_summary(&parsed.summary(), &c.bytes).expect("rebuilds");
            assert_eq!(rebuilt, parsed);
            // A summary does not fit bytes of another length.
            assert!(
                Correction::from_summary(&parsed.summary(), &c.bytes[..c.bytes.len() - 1]).is_err()
            );
        }
    }

    #[test]
    fn svr_error_budget() {
        for (n, seed, mode) in [
            (350, 11, OutputMode::Absolute),
            (1000, 12, OutputMode::Residual),
        ] {
            let m = svr_model(n, seed, mode);
            let bytes = m.compile().expect("compiles");
            assert_eq!(bytes.len(), SVR_HEADER_LEN + n * SVR_RECORD_LEN);
            let v = SvrView::parse(&bytes, n as u32).expect("parses");
            let (mean, max) = error_stats(|p| m.evaluate(p), |p| v.evaluate(p));
            eprintln!("SVR {n} SV seed {seed} {mode:?}: mean {mean:.6} mm, max {max:.6} mm");
            assert!(mean < 0.001, "SVR mean error {mean} mm");
            assert!(max < 0.002, "SVR max error {max} mm");
        }
    }

    /// Records at a 4-aligned address are read as words, else as bytes; the
    /// word path with the one-`usat` shift (inputs near the support vectors)
    /// and with the general one (far inputs) and the byte path give the same
    /// bits.
    #[test]
    fn svr_word_and_byte_paths_agree() {
        let m = svr_model(1000, 12, OutputMode::Residual);
        let bytes = m.compile().expect("compiles");
        let mut words = vec![0u32; bytes.len().div_ceil(4)];
        let aligned = &mut bytemuck::cast_slice_mut::<u32, u8>(&mut words)[..bytes.len()];
        aligned.copy_from_slice(&bytes);
        let mut store = vec![0u32; bytes.len() / 4 + 2];
        let shifted = &mut bytemuck::cast_slice_mut::<u32, u8>(&mut store)[1..=bytes.len()];
        shifted.copy_from_slice(&bytes);
        let w = SvrView::parse(aligned, 1000).expect("parses");
        let b = SvrView::parse(shifted, 1000).expect("parses");
        assert!(w.reads_words());
        assert!(!b.reads_words());
        assert_eq!(w.support_vectors(), b.support_vectors());
        let mut rng = Rng(77);
        let mut points = workspace_points();
        points.truncate(3000);
        let (mut narrow, mut wide) = (0, 0);
        for k in 0..3000 {
            let far = match k % 3 {
                0 => [
                    rng.next_u64() as i32,
                    rng.next_u64() as i32,
                    rng.next_u64() as i32,
                ],
                1 => [i32::MIN, i32::MAX, (rng.next_u64() as i32) >> 8],
                _ => [(rng.next_u64() as i32) >> 4, 0, 0],
            };
            points.push(far);
        }
        for p in points {
            let q = w.scaled(p);
            if w.exponents_below_2p31(q) {
                narrow += 1;
            } else {
                wide += 1;
            }
            assert_eq!(w.evaluate(p), b.evaluate(p), "p {p:?}");
        }
        assert!(narrow > 1000 && wide > 1000, "narrow {narrow}, wide {wide}");
    }

    #[test]
    fn correction_enum_and_header_checks() {
        let nn = nn_model(4, 5, OutputMode::Absolute);
        let c = CorrectionModel::Nn(nn.clone()).compile().expect("compiles");
        assert_eq!(
            (c.kind, c.hidden, c.support_vectors),
            (CorrectionKind::Nn, 4, 0)
        );
        assert_eq!(check_header_formats(c.q_position, c.q_weight), Ok(()));
        let view =
            Correction::parse(c.kind, c.hidden, c.support_vectors, &c.bytes).expect("parses");
        let p = [mm_to_q16(10.0), mm_to_q16(-20.0), mm_to_q16(30.0)];
        assert_eq!(
            view.evaluate(p),
            NnView::parse(&c.bytes, 4).unwrap().evaluate(p)
        );
        assert_eq!(view.kind(), CorrectionKind::Nn);
        assert_eq!(
            Correction::parse(CorrectionKind::Nn, 4, 1, &c.bytes),
            Err(BlobError::Dimension {
                field: "support_vectors",
                found: 1,
                expected: 0
            })
        );
        assert_eq!(
            Correction::parse(CorrectionKind::Nn, 5, 0, &c.bytes),
            Err(BlobError::Dimension {
                field: "nn.body_len",
                found: c.bytes.len() as u32,
                expected: (NN_HEADER_LEN + 5 * NN_NEURON_LEN) as u32
            })
        );
        let none = Correction::parse(CorrectionKind::None, 0, 0, &[]).expect("parses");
        assert_eq!(none.evaluate(p), p);
        assert!(Correction::parse(CorrectionKind::None, 0, 0, &[0]).is_err());
        assert_eq!(
            check_header_formats(16, 24),
            Err(BlobError::Dimension {
                field: "q_weight",
                found: 24,
                expected: 30
            })
        );
        assert!(check_header_formats(15, 30).is_err());
        let svr = CorrectionModel::Svr(svr_model(3, 9, OutputMode::Residual))
            .compile()
            .expect("compiles");
        assert_eq!(
            (svr.kind, svr.hidden, svr.support_vectors),
            (CorrectionKind::Svr, 0, 3)
        );
        assert!(Correction::parse(svr.kind, 0, 3, &svr.bytes).is_ok());
        assert!(Correction::parse(svr.kind, 1, 3, &svr.bytes).is_err());
        // An SVR without support vectors is a constant (plus the input in residual mode).
        let mut empty = svr_model(0, 9, OutputMode::Absolute);
        empty.bias = [1.0, 2.0, 3.0];
        let b = empty.compile().expect("compiles");
        let v = SvrView::parse(&b, 0).expect("parses");
        let want = empty.evaluate([0.0; 3]);
        let got = v.evaluate([0; 3]);
        for a in 0..3 {
            assert!((q16_to_mm(got[a]) - want[a]).abs() < 1e-4);
        }
    }

    #[test]
    fn every_truncation_and_bad_field_is_refused_by_name() {
        let nn = nn_model(3, 4, OutputMode::Residual).compile().unwrap();
        for cut in 0..nn.len() {
            assert!(NnView::parse(&nn[..cut], 3).is_err(), "cut {cut}");
        }
        let mut bad = nn.clone();
        bad[0] = 2;
        assert_eq!(
            NnView::parse(&bad, 3),
            Err(BlobError::Body { field: "nn.mode" })
        );
        let mut bad = nn.clone();
        bad[1] = 61;
        assert_eq!(
            NnView::parse(&bad, 3),
            Err(BlobError::Body {
                field: "nn.w1_frac"
            })
        );
        let mut bad = nn.clone();
        bad[3] = 49;
        assert_eq!(
            NnView::parse(&bad, 3),
            Err(BlobError::Body {
                field: "nn.w2_frac"
            })
        );
        let mut bad = nn.clone();
        bad[6] = 1;
        assert_eq!(
            NnView::parse(&bad, 3),
            Err(BlobError::Body {
                field: "nn.reserved"
            })
        );
        let mut bad = nn.clone();
        bad[NN_HEADER_LEN + 4..NN_HEADER_LEN + 8].copy_from_slice(&(W1_MAX + 1).to_le_bytes());
        assert_eq!(
            NnView::parse(&bad, 3),
            Err(BlobError::Body { field: "nn.w1" })
        );
        let mut bad = nn_model(5, 4, OutputMode::Residual).compile().unwrap();
        for h in 0..5 {
            let at = NN_HEADER_LEN + h * NN_NEURON_LEN + 20;
            bad[at..at + 4].copy_from_slice(&i32::MIN.to_le_bytes());
        }
        assert_eq!(
            NnView::parse(&bad, 5),
            Err(BlobError::Body { field: "nn.w2" })
        );
        assert_eq!(
            NnView::parse(&nn, 0),
            Err(BlobError::Dimension {
                field: "hidden",
                found: 0,
                expected: 1
            })
        );

        let svr = svr_model(5, 4, OutputMode::Absolute).compile().unwrap();
        for cut in 0..svr.len() {
            assert!(SvrView::parse(&svr[..cut], 5).is_err(), "cut {cut}");
        }
        let mut long = svr.clone();
        long.push(0);
        assert_eq!(
            SvrView::parse(&long, 5),
            Err(BlobError::Dimension {
                field: "svr.body_len",
                found: long.len() as u32,
                expected: svr.len() as u32
            })
        );
        assert!(SvrView::parse(&svr, u32::MAX).is_err());
        let mut bad = svr.clone();
        bad[SVR_HEADER_LEN..SVR_HEADER_LEN + 4].copy_from_slice(&(SUPPORT_MAX + 1).to_le_bytes());
        assert_eq!(
            SvrView::parse(&bad, 5),
            Err(BlobError::Body {
                field: "svr.support"
            })
        );
        let mut bad = svr.clone();
        bad[1] = 10;
        assert_eq!(
            SvrView::parse(&bad, 5),
            Err(BlobError::Body {
                field: "svr.scale_frac"
            })
        );
    }

    #[test]
    fn compile_errors_name_the_parameter() {
        let mut m = nn_model(4, 6, OutputMode::Absolute);
        m.b1.pop();
        assert_eq!(
            m.compile(),
            Err(CompileError::Dimension {
                field: "b1",
                found: 3,
                expected: 4
            })
        );
        let mut m = nn_model(4, 6, OutputMode::Absolute);
        m.w2[1][2] = f64::NAN;
        assert_eq!(
            m.compile(),
            Err(CompileError::NotFinite {
                field: "w2[1]",
                index: 2
            })
        );
        let mut m = nn_model(4, 6, OutputMode::Absolute);
        m.input.std[2] = 0.0;
        assert!(matches!(
            m.compile(),
            Err(CompileError::NotPositive {
                field: "input.std",
                index: 2,
                ..
            })
        ));
        let mut m = nn_model(4, 6, OutputMode::Absolute);
        m.b1[3] = 20.0;
        assert!(matches!(
            m.compile(),
            Err(CompileError::OutOfRange {
                field: "b1",
                index: 3,
                ..
            })
        ));
        let mut m = nn_model(4, 6, OutputMode::Absolute);
        m.w1[1][0] = 1e9;
        assert!(matches!(
            m.compile(),
            Err(CompileError::OutOfRange {
                field: "w1",
                index: 3,
                ..
            })
        ));
        let mut m = nn_model(4, 6, OutputMode::Absolute);
        m.input.mean[0] = 40_000.0;
        assert!(matches!(
            m.compile(),
            Err(CompileError::OutOfRange {
                field: "input.mean",
                index: 0,
                ..
            })
        ));
        let mut m = svr_model(4, 6, OutputMode::Absolute);
        m.support[2][1] = 30.0;
        assert!(matches!(
            m.compile(),
            Err(CompileError::OutOfRange {
                field: "support",
                index: 7,
                ..
            })
        ));
        let mut m = svr_model(4, 6, OutputMode::Absolute);
        m.gamma = -1.0;
        assert!(matches!(
            m.compile(),
            Err(CompileError::NotPositive { field: "gamma", .. })
        ));
        let mut m = svr_model(4, 6, OutputMode::Absolute);
        m.coef[2][0] = 1e30;
        assert!(matches!(
            m.compile(),
            Err(CompileError::OutOfRange {
                field: "coef[2]",
                index: 0,
                ..
            })
        ));
        let e = CompileError::OutOfRange {
            field: "w1",
            index: 3,
            value: 1e9,
            format: "Q",
        };
        assert!(e.to_string().contains("`w1`[3]"));
    }

    fn arb_std() -> impl Strategy<Value = Standardization> {
        (
            prop::array::uniform3(-2000.0..2000.0f64),
            prop::array::uniform3(1.0..2000.0f64),
        )
            .prop_map(|(mean, std)| Standardization { mean, std })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        /// Arbitrary bytes never make parsing or evaluation panic.
        #[test]
        fn arbitrary_bytes_never_panic(
            bytes in prop::collection::vec(any::<u8>(), 0..400),
            hidden in 0u16..12,
            svs in 0u32..14,
            p in prop::array::uniform3(any::<i32>()),
        ) {
            for kind in [CorrectionKind::None, CorrectionKind::Nn, CorrectionKind::Svr] {
                if let Ok(c) = Correction::parse(kind, hidden, svs, &bytes) {
                    let _ = c.evaluate(p);
                }
            }
            // Well-sized bodies with arbitrary contents, headers made valid.
            let mut nn = bytes.clone();
            nn.resize(NN_HEADER_LEN + NN_NEURON_LEN * hidden.max(1) as usize, 0x5a);
            nn[0] &= 1;
            nn[1] = 11 + nn[1] % 50;
            for b in &mut nn[2..5] { *b %= 49; }
            nn[5..8].fill(0);
            if let Ok(v) = NnView::parse(&nn, hidden.max(1)) {
                let _ = v.evaluate(p);
            }
            let mut svr = bytes;
            svr.resize(SVR_HEADER_LEN + SVR_RECORD_LEN * svs as usize, 0xa5);
            svr[0] &= 1;
            svr[1] = 11 + svr[1] % 50;
            for b in &mut svr[2..5] { *b %= 49; }
            svr[5..8].fill(0);
            if let Ok(v) = SvrView::parse(&svr, svs) {
                // The same records at an odd address (byte path): same bits.
                let mut store = vec![0u32; svr.len() / 4 + 2];
                let shifted = &mut bytemuck::cast_slice_mut::<u32, u8>(&mut store)[1..=svr.len()];
                shifted.copy_from_slice(&svr);
                let shifted: &[u8] = shifted;
                let u = SvrView::parse(shifted, svs);
                prop_assert_eq!(u, Ok(SvrView { records: SvrRecords::Bytes(&shifted[SVR_HEADER_LEN..]), ..v }));
                if let Ok(u) = u {
                    prop_assert_eq!(v.evaluate(p), u.evaluate(p));
                }
            }
        }

        /// Arbitrary weights (any f64 bits, NaN and infinities included) either
        /// compile or give an error; compiled models evaluate any position.
        #[test]
        fn arbitrary_weights_compile_or_fail_cleanly(
            w in prop::collection::vec(any::<f64>(), 30),
            input in arb_std(),
            output in arb_std(),
            p in prop::array::uniform3(any::<i32>()),
        ) {
            let nn = NnModel {
                input, output,
                w1: vec![[w[0], w[1], w[2]], [w[3], w[4], w[5]]],
                b1: vec![w[6], w[7]],
                w2: [vec![w[8], w[9]], vec![w[10], w[11]], vec![w[12], w[13]]],
                b2: [w[14], w[15], w[16]],
                mode: OutputMode::Residual,
            };
            if let Ok(b) = nn.compile() {
                let v = NnView::parse(&b, 2);
                prop_assert!(v.is_ok());
                if let Ok(v) = v { let _ = v.evaluate(p); }
            }
            let svr = SvrModel {
                input, output, gamma: w[17],
                support: vec![[w[18], w[19], w[20]], [w[21], w[22], w[23]]],
                coef: [vec![w[24], w[25]], vec![w[26], w[27]], vec![w[28], w[29]]],
                bias: [w[0], w[1], w[2]],
                mode: OutputMode::Absolute,
            };
            if let Ok(b) = svr.compile() {
                let v = SvrView::parse(&b, 2);
                prop_assert!(v.is_ok());
                if let Ok(v) = v { let _ = v.evaluate(p); }
            }
        }

        /// Plausible but random models with extreme weights still compile and
        /// evaluate any input bits without panicking; the f64 model agrees
        /// near the workspace.
        #[test]
        fn random_models_evaluate_any_position(
            w in prop::collection::vec(-50.0..50.0f64, 30),
            gamma in 0.01..5.0f64,
            input in arb_std(),
            output in arb_std(),
            p in prop::array::uniform3(any::<i32>()),
        ) {
            let nn = NnModel {
                input, output,
                w1: vec![[w[0], w[1], w[2]], [w[3], w[4], w[5]]],
                b1: vec![w[6] / 5.0, w[7] / 5.0],
                w2: [vec![w[8], w[9]], vec![w[10], w[11]], vec![w[12], w[13]]],
                b2: [w[14] / 10.0, w[15] / 10.0, w[16] / 10.0],
                mode: OutputMode::Absolute,
            };
            let b = nn.compile();
            prop_assert!(b.is_ok(), "{:?}", b);
            if let Ok(b) = b {
                if let Ok(v) = NnView::parse(&b, 2) {
                    let _ = v.evaluate(p);
                    let pm = input.mean;
                    let q = [mm_to_q16(pm[0]), mm_to_q16(pm[1]), mm_to_q16(pm[2])];
                    let got = v.evaluate(q);
                    let want = nn.evaluate([q16_to_mm(q[0]), q16_to_mm(q[1]), q16_to_mm(q[2])]);
                    for a in 0..3 {
                        // Beyond ±32.7 m the Q15.16 output saturates by design.
                        if want[a].abs() < 30_000.0 {
                            prop_assert!((q16_to_mm(got[a]) - want[a]).abs() < 0.01);
                        }
                    }
                }
            }
            let svr = SvrModel {
                input, output, gamma,
                support: vec![[w[18] / 25.0, w[19] / 25.0, w[20] / 25.0], [w[21] / 25.0, w[22] / 25.0, w[23] / 25.0]],
                coef: [vec![w[24], w[25]], vec![w[26], w[27]], vec![w[28], w[29]]],
                bias: [w[0] / 10.0, w[1] / 10.0, w[2] / 10.0],
                mode: OutputMode::Residual,
            };
            if let Ok(b) = svr.compile() {
                if let Ok(v) = SvrView::parse(&b, 2) {
                    let _ = v.evaluate(p);
                    let pm = input.mean;
                    let q = [mm_to_q16(pm[0]), mm_to_q16(pm[1]), mm_to_q16(pm[2])];
                    let got = v.evaluate(q);
                    let want = svr.evaluate([q16_to_mm(q[0]), q16_to_mm(q[1]), q16_to_mm(q[2])]);
                    for a in 0..3 {
                        // Beyond ±32.7 m the Q15.16 output saturates by design.
                        if want[a].abs() < 30_000.0 {
                            prop_assert!((q16_to_mm(got[a]) - want[a]).abs() < 0.01);
                        }
                    }
                }
            }
        }
    }
}
