//! The fixed-point form of one string's base law ([`CompiledStringLaw`]):
//! its home length, the winding polynomial in `x = counts / 2^COUNTS_SHIFT`
//! and the layer table ([`CompiledLayerTable`]); how a [`StringLaw`] is
//! compiled to it and how a compiled one read from a blob is checked.

use core::f64::consts::TAU;

use serde::{Deserialize, Serialize};

use super::{
    check_counts_per_rev, cos2_inclination_q16, finite, home_length_f64, mul_i32_shr,
    polynomial_slope_f64, q16_to_q32, rad_per_x, to_fixed, StringLawCompileError, COUNTS_SHIFT,
    MAX_SAG_LENGTH_MM, WINDING_FIELDS,
};
use crate::model::{
    locate_knot, Frame, Knots, StringLaw, LAYER_KNOTS, MAX_LAYER_MM, MAX_LAYER_STEP_LOG2,
    WINDING_ORDER,
};
use crate::STRINGS;

/// The fixed-point form of one string's base law: home length plus the
/// winding polynomial in `x = counts / 2^COUNTS_SHIFT`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompiledStringLaw {
    /// `|home - anchor|`, Q47.16 mm.
    pub home_length_q16: i64,
    /// Quadrature counts per pulley revolution (for reference; the
    /// coefficients already include it).
    pub counts_per_rev: u32,
    /// Coefficient of `x^k` at index `k-1`, Q31.32 mm:
    /// `round(winding_mm[k-1] (2 pi 2^18 / counts_per_rev)^k 2^32)`.
    pub winding_q32: [i64; WINDING_ORDER],
    /// The layer table ([`LayerTable`](crate::model::LayerTable)), knots in Q47.16 mm.
    pub layers: CompiledLayerTable,
    /// What a sag term's home part scales with: `cos^2(a_home) (home_length
    /// / 4096 mm)^3` in Q·30 (`cos^2` quantized to Q0.16 as the device's,
    /// the length clamped to [`MAX_SAG_LENGTH_MM`]: below 2^33).
    pub home_sag_q30: i64,
}

/// The fixed-point form of a [`LayerTable`](crate::model::LayerTable): the same knots (counts), their
/// values in Q47.16 mm, `|value| <= MAX_LAYER_MM`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompiledLayerTable {
    pub start_counts: i32,
    pub step_log2: u8,
    pub knots_q16: Knots<i64>,
}

impl Eq for Knots<i64> {}

impl Default for CompiledLayerTable {
    fn default() -> Self {
        Self::NONE
    }
}

impl CompiledLayerTable {
    /// No table.
    pub const NONE: CompiledLayerTable = CompiledLayerTable {
        start_counts: 0,
        step_log2: 0,
        knots_q16: Knots::EMPTY_I64,
    };

    /// Departure at `counts`, Q47.16 mm: linear interpolation between the
    /// two knots around `counts`, `v_k + round_half_up((v_{k+1} - v_k)
    /// along / 2^step_log2)`, held at the end knots outside them. With
    /// `|v| <= MAX_LAYER_MM` (checked when compiled and when read) the
    /// product is below `2^25 2^30`: no overflow.
    #[inline]
    pub fn departure_q16(&self, counts: i32) -> i64 {
        let Some((k, along)) = self.locate(counts) else {
            return 0;
        };
        let v = self.knots_q16.as_slice();
        let (Some(&a), Some(&b)) = (v.get(k), v.get(k + 1)) else {
            return v.get(k).copied().unwrap_or(0);
        };
        if along == 0 {
            return a;
        }
        let s = u32::from(self.step_log2.min(MAX_LAYER_STEP_LOG2));
        let product = b.saturating_sub(a).saturating_mul(i64::from(along));
        a.saturating_add(product.saturating_add(1i64 << (s - 1)) >> s)
    }

    #[inline]
    fn locate(&self, counts: i32) -> Option<(usize, u32)> {
        locate_knot(
            self.start_counts,
            self.step_log2,
            self.knots_q16.len(),
            counts,
        )
    }
}

/// Compiles string `string`'s base law (home length from `frame`).
pub fn compile_string_law(
    frame: &Frame<f64>,
    string: usize,
    law: &StringLaw,
) -> Result<CompiledStringLaw, StringLawCompileError> {
    let anchor = frame
        .anchors
        .get(string)
        .ok_or(StringLawCompileError::StringOutOfRange { string })?;
    for v in anchor {
        finite(string, "anchor", *v)?;
    }
    for v in &frame.home {
        finite(string, "home", *v)?;
    }
    let home =
        home_length_f64(frame, string).ok_or(StringLawCompileError::StringOutOfRange { string })?;
    let home_length_q16 = to_fixed(string, "home", home, 16, "Q47.16 mm")?;
    check_counts_per_rev(string, law.counts_per_rev)?;
    let r = rad_per_x(law.counts_per_rev);
    let mut winding_q32 = [0i64; WINDING_ORDER];
    let mut scale = 1.0;
    for k in 0..WINDING_ORDER {
        scale *= r;
        let a = finite(string, WINDING_FIELDS[k], law.winding_mm[k])?;
        winding_q32[k] = to_fixed(
            string,
            WINDING_FIELDS[k],
            a * scale,
            32,
            "Q31.32 mm per x^k",
        )?;
    }
    let home_cos2 = f64::from(cos2_inclination_q16(anchor, &frame.home)) / 65536.0;
    let a = home.clamp(0.0, MAX_SAG_LENGTH_MM) / 4096.0;
    Ok(CompiledStringLaw {
        home_length_q16,
        counts_per_rev: law.counts_per_rev,
        winding_q32,
        layers: compile_layer_table(string, law)?,
        home_sag_q30: libm::round(home_cos2 * a * a * a * (1u64 << 30) as f64) as i64,
    })
}

fn check_layer_step(string: usize, step_log2: u8) -> Result<(), StringLawCompileError> {
    if step_log2 > MAX_LAYER_STEP_LOG2 {
        return Err(StringLawCompileError::OutOfRange {
            string,
            field: "layers.step_log2",
            value: f64::from(step_log2),
            min: 0.0,
            max: f64::from(MAX_LAYER_STEP_LOG2),
        });
    }
    Ok(())
}

/// Compiles a law's layer table, refusing one that would make the payout
/// decrease where the polynomial's increases (the law must stay monotone: a
/// non-monotone law has one string length for two counts, and the fit that
/// made it followed noise). Checked on every segment at both ends against
/// the polynomial's slope there.
fn compile_layer_table(
    string: usize,
    law: &StringLaw,
) -> Result<CompiledLayerTable, StringLawCompileError> {
    let table = &law.layers;
    check_layer_step(string, table.step_log2)?;
    let values = table.knots_mm.as_slice();
    let mut knots_q16 = [0i64; LAYER_KNOTS];
    for (k, &v) in values.iter().enumerate() {
        let v = finite(string, "layers.knots_mm", v)?;
        if v.abs() > MAX_LAYER_MM {
            return Err(StringLawCompileError::OutOfRange {
                string,
                field: "layers.knots_mm",
                value: v,
                min: -MAX_LAYER_MM,
                max: MAX_LAYER_MM,
            });
        }
        knots_q16[k] = to_fixed(string, "layers.knots_mm", v, 16, "Q47.16 mm")?;
    }
    let rad_per_count = TAU / f64::from(law.counts_per_rev);
    let step_rad = libm::exp2(f64::from(table.step_log2)) * rad_per_count;
    for k in 1..values.len() {
        let slope = (values[k] - values[k - 1]) / step_rad;
        for end in [k - 1, k] {
            let theta = table.knot_counts(end) as f64 * rad_per_count;
            let polynomial = polynomial_slope_f64(law, theta);
            let total = polynomial + slope;
            if polynomial > 0.0 && total <= 0.0 {
                return Err(StringLawCompileError::OutOfRange {
                    string,
                    field: "layers (payout slope, mm/rad)",
                    value: total,
                    min: 0.0,
                    max: f64::INFINITY,
                });
            }
        }
    }
    Ok(CompiledLayerTable {
        start_counts: table.start_counts,
        step_log2: table.step_log2,
        knots_q16: Knots::from_slice(&knots_q16[..values.len()]).unwrap_or(Knots::EMPTY_I64),
    })
}

impl CompiledStringLaw {
    /// Base winding law output (payout since home) at `counts`, Q31.32 mm,
    /// by Horner in `x = counts / 2^18`, saturating.
    #[inline]
    pub fn payout_q32(&self, counts: i32) -> i64 {
        let mut acc: i64 = 0;
        for k in (0..WINDING_ORDER).rev() {
            acc = acc.saturating_add(self.winding_q32[k]);
            acc = mul_i32_shr(acc, counts, COUNTS_SHIFT);
        }
        acc.saturating_add(q16_to_q32(self.layers.departure_q16(counts)))
    }

    /// Checks a compiled law read from a blob.
    pub fn validate(&self, string: usize) -> Result<(), StringLawCompileError> {
        if string >= STRINGS {
            return Err(StringLawCompileError::StringOutOfRange { string });
        }
        check_counts_per_rev(string, self.counts_per_rev)?;
        check_layer_step(string, self.layers.step_log2)?;
        let limit = (MAX_LAYER_MM * 65536.0) as i64;
        for &v in self.layers.knots_q16.as_slice() {
            if !(-limit..=limit).contains(&v) {
                return Err(StringLawCompileError::OutOfRange {
                    string,
                    field: "layers.knots_mm",
                    value: v as f64 / 65536.0,
                    min: -MAX_LAYER_MM,
                    max: MAX_LAYER_MM,
                });
            }
        }
        Ok(())
    }
}
