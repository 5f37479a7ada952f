//! Position corrections learned on the host (paper section 5): a 3-H-3 neural
//! network (tanh hidden layer, linear output) and an RBF epsilon-SVR with three
//! outputs, both with the input/output standardization of eq. 10.
//!
//! The f64 models here are what the host trains (`alloc` feature); the
//! fixed-point evaluators the device runs are compiled from them.

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
