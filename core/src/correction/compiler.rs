//! The host side (alloc): f64 reference evaluation and compilation of the
//! corrections into their bytes.

use super::*;
use crate::fixed::to_q_i32;
use alloc::vec::Vec;

/// Why a model does not compile. Each variant names the parameter.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CorrectionCompileError {
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
    /// More neurons or support vectors than the device evaluates within its
    /// control loop's tick ([`MAX_HIDDEN_NEURONS`], [`MAX_SUPPORT_VECTORS`]).
    OverBudget {
        field: &'static str,
        found: usize,
        most: usize,
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

impl core::fmt::Display for CorrectionCompileError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            CorrectionCompileError::Dimension {
                field,
                found,
                expected,
            } => write!(
                f,
                "correction parameter `{field}` has {found} entries, expected {expected}"
            ),
            CorrectionCompileError::OverBudget { field, found, most } => write!(
                f,
                "correction parameter `{field}` has {found} entries: the device evaluates at most {most} within its control loop's tick"
            ),
            CorrectionCompileError::NotFinite { field, index } => {
                write!(f, "correction parameter `{field}`[{index}] is not finite")
            }
            CorrectionCompileError::NotPositive {
                field,
                index,
                value,
            } => write!(
                f,
                "correction parameter `{field}`[{index}] = {value} must be strictly positive"
            ),
            CorrectionCompileError::OutOfRange {
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

impl core::error::Error for CorrectionCompileError {}

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

fn check_finite(field: &'static str, values: &[f64]) -> Result<(), CorrectionCompileError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(CorrectionCompileError::NotFinite { field, index }),
        None => Ok(()),
    }
}

fn check_standardization(s: &Standardization, side: u8) -> Result<(), CorrectionCompileError> {
    let (mean, std) = if side == 0 {
        ("input.mean", "input.std")
    } else {
        ("output.mean", "output.std")
    };
    check_finite(mean, &s.mean)?;
    check_finite(std, &s.std)?;
    for (index, &value) in s.std.iter().enumerate() {
        if value <= 0.0 {
            return Err(CorrectionCompileError::NotPositive {
                field: std,
                index,
                value,
            });
        }
    }
    Ok(())
}

fn q16(field: &'static str, index: usize, v: f64) -> Result<i32, CorrectionCompileError> {
    to_q_i32(v, POSITION_FRAC as u32).ok_or(CorrectionCompileError::OutOfRange {
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
) -> CorrectionCompileError {
    let (index, value) = values.enumerate().fold((0, 0f64), |(bi, bv), (i, v)| {
        if libm::fabs(v) > libm::fabs(bv) {
            (i, v)
        } else {
            (bi, bv)
        }
    });
    CorrectionCompileError::OutOfRange {
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

/// The NN's output weights per axis (`w2[axis]`), by name.
const W2: [&str; 3] = ["w2[0]", "w2[1]", "w2[2]"];
/// The SVR's coefficients per axis (`coef[axis]`), by name.
const COEF: [&str; 3] = ["coef[0]", "coef[1]", "coef[2]"];

/// The output parameters of each axis (NN `w2`, SVR `coef`, named
/// `fields`): `expected` entries each, all finite.
fn check_axes(
    fields: [&'static str; 3],
    axes: &[Vec<f64>; 3],
    expected: usize,
) -> Result<(), CorrectionCompileError> {
    for (a, values) in axes.iter().enumerate() {
        if values.len() != expected {
            return Err(CorrectionCompileError::Dimension {
                field: fields[a],
                found: values.len(),
                expected,
            });
        }
        check_finite(fields[a], values)?;
    }
    Ok(())
}

/// The input mean in Q15.16 and the rounding residual (mm) that the first
/// layer (NN) or the support vectors (SVR) absorb.
fn input_mean_q16(input: &Standardization) -> Result<([i32; 3], [f64; 3]), CorrectionCompileError> {
    let mut mean = [0i32; 3];
    let mut mean_residual = [0f64; 3];
    for i in 0..3 {
        mean[i] = q16("input.mean", i, input.mean[i])?;
        mean_residual[i] = input.mean[i] - mean[i] as f64 / 65536.0;
    }
    Ok((mean, mean_residual))
}

/// The output parameters of each axis with the output scale folded in (mm)
/// and the fractional bits `frac` picks for each axis; an axis that does
/// not fit is an error naming its largest parameter and `format`.
fn fold_output_scale(
    fields: [&'static str; 3],
    axes: &[Vec<f64>; 3],
    output: &Standardization,
    frac: fn(&[f64]) -> Option<u8>,
    format: &'static str,
) -> Result<([Vec<f64>; 3], [u8; 3]), CorrectionCompileError> {
    let mut fracs = [0u8; 3];
    let mut folded: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for a in 0..3 {
        folded[a] = axes[a].iter().map(|w| w * output.std[a]).collect();
        fracs[a] = frac(&folded[a])
            .ok_or_else(|| largest(fields[a], folded[a].iter().copied(), format))?;
    }
    Ok((folded, fracs))
}

/// The output offsets in Q15.16 mm: `bias * output.std + output.mean` per
/// axis (`field`: NN `b2`, SVR `bias`).
fn output_offset_q16(
    field: &'static str,
    bias: &[f64; 3],
    output: &Standardization,
) -> Result<[i32; 3], CorrectionCompileError> {
    let mut offset = [0i32; 3];
    for (a, o) in offset.iter_mut().enumerate() {
        *o = q16(field, a, bias[a] * output.std[a] + output.mean[a])?;
    }
    Ok(offset)
}

/// The start of the NN and SVR bytes: output mode, input fractional bits,
/// output fractional bits per axis, padding, input mean; room for
/// `capacity` bytes in all.
fn correction_head(
    capacity: usize,
    mode: OutputMode,
    input_frac: u8,
    output_frac: [u8; 3],
    mean: [i32; 3],
) -> Vec<u8> {
    let mut out = Vec::with_capacity(capacity);
    out.push(mode_byte(mode));
    out.push(input_frac);
    out.extend_from_slice(&output_frac);
    out.extend_from_slice(&[0, 0, 0]);
    mean.iter().for_each(|&v| push_i32(&mut out, v));
    out
}

/// The output parameters of neuron or support vector `j`, each axis in its
/// fractional bits.
fn push_output_weights(out: &mut Vec<u8>, axes: &[Vec<f64>; 3], frac: [u8; 3], j: usize) {
    for a in 0..3 {
        push_i32(out, libm::round(axes[a][j] * pow2(frac[a] as u32)) as i32);
    }
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
    pub fn compile(&self) -> Result<Vec<u8>, CorrectionCompileError> {
        let hidden = self.check_parameters()?;
        // Input mean in Q15.16; the rounding residual goes into b1.
        let (mean, mean_residual) = input_mean_q16(&self.input)?;
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
        let (w2, w2_frac) = fold_output_scale(
            W2,
            &self.w2,
            &self.output,
            output_frac,
            "i32 Q(0) mm, sum of magnitudes within 2^32 (w2 * output.std)",
        )?;
        let offset = output_offset_q16("b2", &self.b2, &self.output)?;

        let mut out = correction_head(
            NN_HEADER_LEN + NN_NEURON_LEN * hidden,
            self.mode,
            w1_frac,
            w2_frac,
            mean,
        );
        offset.iter().for_each(|&v| push_i32(&mut out, v));
        let s1 = pow2(w1_frac as u32);
        for (h, w1h) in w1.iter().enumerate() {
            for &w in w1h {
                // |w * 2^w1_frac| <= 2^29 by the choice of w1_frac.
                push_i32(&mut out, libm::round(w * s1) as i32);
            }
            // x = w1 . (p - mean_q) + b1 - w1 . mean_residual.
            let b1 = self.b1[h]
                - (w1h[0] * mean_residual[0]
                    + w1h[1] * mean_residual[1]
                    + w1h[2] * mean_residual[2]);
            let b1q =
                to_q_i32(b1, PREACTIVATION_FRAC).ok_or(CorrectionCompileError::OutOfRange {
                    field: "b1",
                    index: h,
                    value: self.b1[h],
                    format: "i32 Q4.27",
                })?;
            push_i32(&mut out, b1q);
            push_output_weights(&mut out, &w2, w2_frac, h);
        }
        Ok(out)
    }

    /// The parameters' counts (1 to [`MAX_HIDDEN_NEURONS`], the same in every
    /// vector) and that they are finite, standard deviations positive;
    /// the neuron count.
    fn check_parameters(&self) -> Result<usize, CorrectionCompileError> {
        let hidden = self.w1.len();
        if hidden == 0 {
            return Err(CorrectionCompileError::Dimension {
                field: "w1",
                found: hidden,
                expected: 1,
            });
        }
        if hidden > MAX_HIDDEN_NEURONS as usize {
            return Err(CorrectionCompileError::OverBudget {
                field: "w1",
                found: hidden,
                most: MAX_HIDDEN_NEURONS as usize,
            });
        }
        if self.b1.len() != hidden {
            return Err(CorrectionCompileError::Dimension {
                field: "b1",
                found: self.b1.len(),
                expected: hidden,
            });
        }
        check_axes(W2, &self.w2, hidden)?;
        check_standardization(&self.input, 0)?;
        check_standardization(&self.output, 1)?;
        check_finite("w1", self.w1.as_flattened())?;
        check_finite("b1", &self.b1)?;
        check_finite("b2", &self.b2)?;
        Ok(hidden)
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
    pub fn compile(&self) -> Result<Vec<u8>, CorrectionCompileError> {
        let n = self.check_parameters()?;
        let r = libm::sqrt(self.gamma * LOG2_E);
        let g = [
            r / self.input.std[0],
            r / self.input.std[1],
            r / self.input.std[2],
        ];
        let (mean, mean_residual) = input_mean_q16(&self.input)?;
        let g_max = g.iter().fold(0f64, |m, v| m.max(*v));
        let scale_frac = best_frac(g_max, i32::MAX as f64, INPUT_FRAC_RANGE).ok_or_else(|| {
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
        let (coef, coef_frac) = fold_output_scale(
            COEF,
            &self.coef,
            &self.output,
            svr_coef_frac,
            "i32 Q(0) mm, sum of magnitudes per block of 64 within 2^33 (coef * output.std)",
        )?;
        let offset = output_offset_q16("bias", &self.bias, &self.output)?;

        let mut out = correction_head(
            SVR_HEADER_LEN + SVR_RECORD_LEN * n,
            self.mode,
            scale_frac,
            coef_frac,
            mean,
        );
        scale.iter().for_each(|&v| push_i32(&mut out, v));
        offset.iter().for_each(|&v| push_i32(&mut out, v));
        let space = pow2(SVR_SPACE_FRAC);
        for (j, sv) in self.support.iter().enumerate() {
            for i in 0..3 {
                let s = sv[i] * r + mean_residual[i] * g[i];
                let sq = libm::round(s * space);
                if !(-(SUPPORT_MAX as f64)..=SUPPORT_MAX as f64).contains(&sq) {
                    return Err(CorrectionCompileError::OutOfRange {
                        field: "support",
                        index: 3 * j + i,
                        value: sv[i],
                        format: "Q4.27 within 8.0 after scaling by sqrt(gamma log2 e)",
                    });
                }
                push_i32(&mut out, sq as i32);
            }
            push_output_weights(&mut out, &coef, coef_frac, j);
        }
        Ok(out)
    }

    /// The parameters' counts (as many coefficients per axis as support
    /// vectors, at most [`MAX_SUPPORT_VECTORS`]) and that they are finite,
    /// standard deviations and `gamma` positive; the support-vector count.
    fn check_parameters(&self) -> Result<usize, CorrectionCompileError> {
        let n = self.support.len();
        if n > MAX_SUPPORT_VECTORS as usize {
            return Err(CorrectionCompileError::OverBudget {
                field: "support",
                found: n,
                most: MAX_SUPPORT_VECTORS as usize,
            });
        }
        check_axes(COEF, &self.coef, n)?;
        check_standardization(&self.input, 0)?;
        check_standardization(&self.output, 1)?;
        check_finite("support", self.support.as_flattened())?;
        check_finite("bias", &self.bias)?;
        if !self.gamma.is_finite() {
            return Err(CorrectionCompileError::NotFinite {
                field: "gamma",
                index: 0,
            });
        }
        if self.gamma <= 0.0 {
            return Err(CorrectionCompileError::NotPositive {
                field: "gamma",
                index: 0,
                value: self.gamma,
            });
        }
        Ok(n)
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
    pub fn compile(&self) -> Result<CompiledCorrection, CorrectionCompileError> {
        let (kind, hidden, support_vectors, bytes) = match self {
            CorrectionModel::None => (CorrectionKind::None, 0, 0, Vec::new()),
            CorrectionModel::Nn(nn) => (CorrectionKind::Nn, nn.w1.len() as u16, 0, nn.compile()?),
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
