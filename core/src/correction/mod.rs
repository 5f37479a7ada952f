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
//! `x_h = 2 (sat((sum_i (p_i - mean_i) * w1[h][i]) >> (w1_frac - 10)) + (b1[h] >> 1))`
//! (each step saturating: the sum in Q5.26, so that `w1 . d` saturated at
//! +-32 stays beyond +-16 whatever the bias), with
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
/// pre-activation shift `w1_frac - 10` (to Q5.26) stays within `2..=31`, a
/// cheap 32-bit shift pair on the device.
pub const W1_FRAC_RANGE: core::ops::RangeInclusive<u8> = 12..=41;
/// Range of `scale_frac` (fractional bits of the SVR input scales, per mm).
pub const INPUT_FRAC_RANGE: core::ops::RangeInclusive<u8> = 11..=60;
/// Range of `w2_frac` / `coef_frac` (fractional bits of output weights and SVR
/// coefficients, mm).
pub const OUTPUT_FRAC_RANGE: core::ops::RangeInclusive<u8> = 0..=48;
/// Largest magnitude of a stored SVR support-vector coordinate (`2^30`, i.e.
/// 8.0 in Q4.27): with inputs saturated at ±16, a saturated input is at least
/// 8 away from every support vector, whose kernel then underflows as it should.
pub const SUPPORT_MAX: i32 = 1 << 30;

/// Most support vectors of an SVR correction the device takes. The device
/// evaluates its correction in every 100 µs tick of its 10 kHz control
/// loop: with 1,000 support vectors the tick measures 52,597 instructions
/// under QEMU against its budget of 55,000 (`scripts/qemu-bench`, decision
/// record 0002), and each support vector costs 24 more. The host's SVR
/// learns from at most this many points, so it never has more; a blob with
/// more is refused ([`BlobError::OverBudget`]).
pub const MAX_SUPPORT_VECTORS: u32 = 1000;

/// Most hidden neurons of an NN correction the device takes: at the
/// measured 63 instructions a neuron (`docs/fixed-point.md`), 400 cost what
/// the largest SVR does ([`MAX_SUPPORT_VECTORS`]), the correction's share
/// of the tick. The host's sweep goes to 24.
pub const MAX_HIDDEN_NEURONS: u16 = 400;

/// Bytes of the NN body before the neurons.
///
/// ```text
/// offset size  field
///  0     1     mode          0 absolute, 1 residual
///  1     1     w1_frac       fractional bits of w1 (per mm), 12..=41
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

mod nn;
mod svr;

pub use nn::{NnSummary, NnView};
pub use svr::{SvrSummary, SvrView};

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
pub use compiler::{CompiledCorrection, CorrectionCompileError};

#[cfg(feature = "alloc")]
mod compiler;

#[cfg(test)]
mod tests;
