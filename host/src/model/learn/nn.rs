//! 3-H-3 network (tanh hidden layer, linear output) trained by
//! Levenberg-Marquardt the way MATLAB's `trainlm` does (paper section 5.2).
//!
//! Each epoch forms the Jacobian of the 3N outputs with respect to the 7H+3
//! weights analytically and solves `(J^T J + mu I) dw = J^T e` by Cholesky;
//! `mu` is divided by 10 after a step that lowers the training error and
//! multiplied by 10 (retrying the step) otherwise. The notes measured this at
//! about 9 ms per epoch for H = 20 against 42 ms for a QR of J, so the normal
//! equations are the fast path for networks this small.
//!
//! J^T J is assembled by blocks rather than from a dense J: an output-k row is
//! zero outside the first-layer block and the output-k block, and the
//! output-layer blocks of all three outputs are the same `A^T A` (A = hidden
//! activations plus a 1 column). That cuts the dominant product to
//! `(4H)^2 * 3N` multiply-adds instead of `(7H+3)^2 * 3N`.
//!
//! Training runs several restarts (Nguyen-Widrow init, seeded) in parallel and
//! keeps the weights with the lowest validation error (early stopping as
//! `trainlm`: stop after `max_fail` epochs without a validation improvement).

use std::time::{Duration, Instant};

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::standardize::{self, apply, mode_targets, output_position};
use super::{
    check_range, progress, split_indices, validate_pairs, Deadline, ErrorStats, LearnError,
    NnModel, OutputMode, Rng, Standardization,
};

/// Levenberg-Marquardt settings (defaults are `trainlm`'s).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LmConfig {
    pub max_epochs: usize,
    pub mu_init: f64,
    pub mu_dec: f64,
    pub mu_inc: f64,
    /// Stop when no step lowers the error even with this damping.
    pub mu_max: f64,
    /// Stop when the gradient norm of the mean squared error falls below this.
    pub min_grad: f64,
    /// Early stopping: consecutive epochs without validation improvement.
    pub max_fail: usize,
}

impl Default for LmConfig {
    fn default() -> Self {
        LmConfig {
            max_epochs: 1000,
            mu_init: 1e-3,
            mu_dec: 0.1,
            mu_inc: 10.0,
            mu_max: 1e10,
            min_grad: 1e-7,
            max_fail: 6,
        }
    }
}

/// Training settings for one hidden size.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NnConfig {
    pub hidden: usize,
    pub mode: OutputMode,
    pub lm: LmConfig,
    /// Independent initializations; the best on validation wins.
    pub restarts: usize,
    /// Share of the points held out for early stopping (0 disables it).
    pub validation_fraction: f64,
    pub seed: u64,
    /// Wall-clock budget; epochs stop when it is spent (results then depend on
    /// timing, so leave it `None` where determinism matters).
    pub time_limit: Option<Duration>,
    /// Hide the progress bar.
    pub quiet: bool,
}

impl Default for NnConfig {
    fn default() -> Self {
        NnConfig {
            hidden: 20,
            mode: OutputMode::Absolute,
            lm: LmConfig::default(),
            restarts: 2,
            validation_fraction: 0.15,
            seed: 1,
            time_limit: None,
            quiet: true,
        }
    }
}

/// Why a training run stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum StopReason {
    MaxEpochs,
    /// `max_fail` epochs without validation improvement.
    ValidationFail,
    /// No damping up to `mu_max` gave a lower training error.
    MuMax,
    MinGradient,
    TimeLimit,
}

/// A trained network and how it did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NnFit {
    pub model: NnModel,
    /// Position error on the training split, mm.
    pub train: ErrorStats,
    /// Position error on the validation split, mm (n = 0 without one).
    pub validation: ErrorStats,
    /// Epochs run by the winning restart.
    pub epochs: usize,
    pub stop: StopReason,
    pub restarts: usize,
    pub seconds: f64,
}

/// Evaluate a network at a device position (mm); returns the corrected
/// position (mm) in either output mode.
pub fn predict(model: &NnModel, p: &[f64; 3]) -> [f64; 3] {
    let x = apply(&model.input, p);
    let mut y = model.b2;
    for (h, (w, b)) in model.w1.iter().zip(&model.b1).enumerate() {
        let a = (w[0] * x[0] + w[1] * x[1] + w[2] * x[2] + b).tanh();
        for (k, yk) in y.iter_mut().enumerate() {
            *yk += model.w2[k].get(h).copied().unwrap_or(0.0) * a;
        }
    }
    output_position(model.mode, &model.output, p, &y)
}

pub fn predict_all(model: &NnModel, points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    points.iter().map(|p| predict(model, p)).collect()
}

/// Check that a model's arrays agree with each other and are finite.
pub fn check_model(model: &NnModel) -> Result<(), LearnError> {
    let h = model.w1.len();
    if h == 0 || model.b1.len() != h || model.w2.iter().any(|w| w.len() != h) {
        return Err(LearnError::MalformedModel {
            what: "NnModel: w1, b1 and w2 rows must have the same non-zero length",
        });
    }
    let finite = model.w1.iter().flatten().all(|v| v.is_finite())
        && model.b1.iter().all(|v| v.is_finite())
        && model.w2.iter().flatten().all(|v| v.is_finite())
        && model.b2.iter().all(|v| v.is_finite())
        && model.input.std.iter().all(|s| s.is_finite() && *s > 0.0)
        && model.output.std.iter().all(|s| s.is_finite() && *s > 0.0);
    if finite {
        Ok(())
    } else {
        Err(LearnError::MalformedModel {
            what: "NnModel: non-finite weight or non-positive std",
        })
    }
}

/// Train a network of `cfg.hidden` neurons on (device position, target
/// position) pairs in mm.
pub fn train(
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    cfg: &NnConfig,
) -> Result<NnFit, LearnError> {
    let start = Instant::now();
    check_config(cfg)?;
    let data = Prepared::new(inputs, targets, cfg.mode, cfg.validation_fraction, cfg.seed)?;
    let deadline = Deadline::after(cfg.time_limit);
    let pb = progress(
        (cfg.restarts * cfg.lm.max_epochs) as u64,
        "NN LM",
        cfg.quiet,
    );
    let runs: Vec<Run> = (0..cfg.restarts)
        .into_par_iter()
        .map(|r| {
            let init = Init::Random(Rng::derive(cfg.seed, (cfg.hidden as u64) << 32 | r as u64));
            train_run(&data, cfg.hidden, init, &cfg.lm, deadline, &|| pb.inc(1))
        })
        .collect();
    pb.finish_and_clear();
    let best = best_run(&data, runs).ok_or(LearnError::OutOfTime {
        what: "NN training",
        budget_s: cfg.time_limit.map_or(0.0, |d| d.as_secs_f64()),
    })?;
    Ok(data.fit_of(best, cfg.restarts, start.elapsed().as_secs_f64()))
}

pub(crate) fn check_config(cfg: &NnConfig) -> Result<(), LearnError> {
    check_range("hidden", cfg.hidden as f64, 1.0, 4096.0, "1..=4096 neurons")?;
    check_range("restarts", cfg.restarts as f64, 1.0, 1e6, ">= 1")?;
    check_lm(&cfg.lm)?;
    check_range(
        "validation_fraction",
        cfg.validation_fraction,
        0.0,
        0.9,
        "0 <= fraction <= 0.9",
    )
}

pub(crate) fn check_lm(lm: &LmConfig) -> Result<(), LearnError> {
    check_range("mu_init", lm.mu_init, 1e-300, 1e300, "> 0")?;
    check_range("mu_dec", lm.mu_dec, 1e-300, 0.999_999, "0 < mu_dec < 1")?;
    check_range("mu_inc", lm.mu_inc, 1.000_001, 1e300, "> 1")?;
    check_range("mu_max", lm.mu_max, lm.mu_init, f64::MAX, ">= mu_init")?;
    check_range("min_grad", lm.min_grad, 0.0, f64::MAX, ">= 0")?;
    check_range("max_fail", lm.max_fail as f64, 1.0, 1e9, ">= 1")
}

/// Standardized training and validation data shared by all runs.
pub(crate) struct Prepared {
    pub mode: OutputMode,
    pub input: Standardization,
    pub output: Standardization,
    x: Vec<[f64; 3]>,
    y: Vec<[f64; 3]>,
    xv: Vec<[f64; 3]>,
    yv: Vec<[f64; 3]>,
    /// mm positions for error reports.
    in_mm: Vec<[f64; 3]>,
    tgt_mm: Vec<[f64; 3]>,
    in_mm_v: Vec<[f64; 3]>,
    tgt_mm_v: Vec<[f64; 3]>,
    /// Input range per axis (standardized) for Nguyen-Widrow.
    lo: [f64; 3],
    hi: [f64; 3],
}

/// Fewest training points: the split must leave more residuals than weights
/// of the smallest network, and quartiles etc. need a handful anyway.
const MIN_POINTS: usize = 10;

impl Prepared {
    pub fn new(
        inputs: &[[f64; 3]],
        targets: &[[f64; 3]],
        mode: OutputMode,
        validation_fraction: f64,
        seed: u64,
    ) -> Result<Self, LearnError> {
        validate_pairs("NN training data", inputs, targets, MIN_POINTS)?;
        let outs = mode_targets(mode, inputs, targets);
        // Statistics over all points (train + validation), as MATLAB's mapstd
        // on the whole set: the split is for early stopping only.
        let input = standardize::fit("NN inputs", inputs)?;
        let output = standardize::fit("NN targets", &outs)?;
        let (tr, va) = split_indices(inputs.len(), validation_fraction, seed);
        let pick = |idx: &[usize], v: &[[f64; 3]]| idx.iter().map(|&i| v[i]).collect::<Vec<_>>();
        let x = standardize::apply_all(&input, &pick(&tr, inputs));
        let y = standardize::apply_all(&output, &pick(&tr, &outs));
        let xv = standardize::apply_all(&input, &pick(&va, inputs));
        let yv = standardize::apply_all(&output, &pick(&va, &outs));
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &x {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        Ok(Prepared {
            mode,
            input,
            output,
            x,
            y,
            xv,
            yv,
            in_mm: pick(&tr, inputs),
            tgt_mm: pick(&tr, targets),
            in_mm_v: pick(&va, inputs),
            tgt_mm_v: pick(&va, targets),
            lo,
            hi,
        })
    }

    /// The network of weights `w`. An input axis that is constant over the
    /// training points (z of a planar device) is 0 after standardization:
    /// nothing constrains its weights, which LM's damping lets wander to
    /// any size (1e9 seen), beyond what the device's fixed point holds.
    /// They are written as 0, which changes no prediction on that plane.
    pub fn model(&self, h: usize, w: &[f64]) -> NnModel {
        let l = Layout { h };
        let weight = |j: usize, a: usize| {
            if self.lo[a] == self.hi[a] {
                0.0
            } else {
                w[l.w1(j, a)]
            }
        };
        NnModel {
            input: self.input,
            output: self.output,
            w1: (0..h)
                .map(|j| [weight(j, 0), weight(j, 1), weight(j, 2)])
                .collect(),
            b1: (0..h).map(|j| w[l.b1(j)]).collect(),
            w2: [0, 1, 2].map(|k| (0..h).map(|j| w[l.w2(k, j)]).collect()),
            b2: [0, 1, 2].map(|k| w[l.b2(k)]),
            mode: self.mode,
        }
    }

    pub fn stats(&self, model: &NnModel) -> (ErrorStats, ErrorStats) {
        let tr = ErrorStats::between(&predict_all(model, &self.in_mm), &self.tgt_mm);
        let va = ErrorStats::between(&predict_all(model, &self.in_mm_v), &self.tgt_mm_v);
        (tr, va)
    }

    pub fn fit_of(&self, run: Run, restarts: usize, seconds: f64) -> NnFit {
        let model = self.model(run.h, &run.w);
        let (train, validation) = self.stats(&model);
        NnFit {
            model,
            train,
            validation,
            epochs: run.epochs,
            stop: run.stop,
            restarts,
            seconds,
        }
    }
}

/// Weight layout: per hidden neuron `[w_x, w_y, w_z, b]` (4H), then per output
/// k `[w2[k][0..H], b2[k]]`.
#[derive(Clone, Copy)]
struct Layout {
    h: usize,
}

impl Layout {
    fn len(self) -> usize {
        7 * self.h + 3
    }
    fn w1(self, j: usize, i: usize) -> usize {
        4 * j + i
    }
    fn b1(self, j: usize) -> usize {
        4 * j + 3
    }
    fn out(self, k: usize) -> usize {
        4 * self.h + k * (self.h + 1)
    }
    fn w2(self, k: usize, j: usize) -> usize {
        self.out(k) + j
    }
    fn b2(self, k: usize) -> usize {
        self.out(k) + self.h
    }
}

pub(crate) enum Init {
    Random(Rng),
    Warm(Vec<f64>),
}

/// Result of one LM run: the weights with the best validation error.
#[derive(Clone, Debug)]
pub(crate) struct Run {
    pub h: usize,
    pub w: Vec<f64>,
    /// Score the runs are ranked by: validation SSE, or training SSE without a
    /// validation split (standardized units).
    pub score: f64,
    pub epochs: usize,
    pub stop: StopReason,
}

/// Lowest score among the runs whose network the device can hold (its
/// fixed-point form compiles: a first-layer bias beyond Q4.27's +-16, say,
/// does not), else among every run; ties go to the earlier run so parallel
/// order cannot matter. A run the device cannot hold is a calibration
/// `spidar compile` refuses, however well it scores.
pub(crate) fn best_run(data: &Prepared, runs: Vec<Run>) -> Option<Run> {
    let (held, not_held): (Vec<Run>, Vec<Run>) = runs
        .into_iter()
        .filter(|r| r.score.is_finite())
        .partition(|r| data.model(r.h, &r.w).compile().is_ok());
    let lowest = |runs: Vec<Run>| {
        runs.into_iter()
            .reduce(|a, b| if b.score < a.score { b } else { a })
    };
    lowest(held).or_else(|| lowest(not_held))
}

/// Nguyen-Widrow initialization for tanh, with the input range mapped as
/// MATLAB's `initnw` does: each neuron's active region gets a slice of the
/// data range, so no neuron starts saturated everywhere.
fn nguyen_widrow(data: &Prepared, h: usize, rng: &mut Rng) -> Vec<f64> {
    let l = Layout { h };
    let mut w = vec![0.0; l.len()];
    let beta = 0.7 * (h as f64).powf(1.0 / 3.0);
    for j in 0..h {
        let mut v = [rng.normal(), rng.normal(), rng.normal()];
        let norm = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
        for c in &mut v {
            *c *= beta / norm;
        }
        let mut b = rng.range(-beta, beta);
        // Weights were drawn for inputs in [-1, 1]; x' = s x + o maps the data
        // range there, so w x' + b = (w s) x + (b + w o).
        for a in 0..3 {
            let span = (data.hi[a] - data.lo[a]).max(1e-9);
            let s = 2.0 / span;
            let o = -1.0 - s * data.lo[a];
            b += v[a] * o;
            w[l.w1(j, a)] = v[a] * s;
        }
        w[l.b1(j)] = b;
    }
    for k in 0..3 {
        for j in 0..h {
            w[l.w2(k, j)] = rng.range(-0.5, 0.5);
        }
        w[l.b2(k)] = 0.0;
    }
    w
}

/// Sum of squared errors (standardized) of weights `w` on (x, y).
fn sse(l: Layout, w: &[f64], x: &[[f64; 3]], y: &[[f64; 3]]) -> f64 {
    let mut s = 0.0;
    let mut act = vec![0.0; l.h];
    for (p, t) in x.iter().zip(y) {
        for (j, a) in act.iter_mut().enumerate() {
            *a = fast_tanh(
                w[l.w1(j, 0)] * p[0] + w[l.w1(j, 1)] * p[1] + w[l.w1(j, 2)] * p[2] + w[l.b1(j)],
            );
        }
        for (k, tk) in t.iter().enumerate() {
            let o = l.out(k);
            let f: f64 = w[o..o + l.h]
                .iter()
                .zip(&act)
                .map(|(a, b)| a * b)
                .sum::<f64>()
                + w[o + l.h];
            let e = tk - f;
            s += e * e;
        }
    }
    s
}

/// Per-run buffers for the Jacobian factors and normal equations.
struct Work {
    l: Layout,
    n: usize,
    /// Hidden activations, column-major N x H.
    act: Vec<f64>,
    /// `V[n, 4j+i] = (1 - a_nj^2) x~_ni`, column-major N x 4H: the
    /// first-layer Jacobian of output k is `V` with column block j scaled by
    /// `w2[k][j]`.
    v: Vec<f64>,
    /// Activations plus a 1 column, column-major N x (H+1).
    a: Vec<f64>,
    /// Residuals y - f, output-major (3N).
    e: Vec<f64>,
    /// `sum_k w2[k][j] e_k[n]`, column-major N x H.
    r: Vec<f64>,
    vtv: Vec<f64>,
    vta: Vec<f64>,
    ata: Vec<f64>,
    jtj: DMatrix<f64>,
    g: DVector<f64>,
}

impl Work {
    fn new(l: Layout, n: usize) -> Self {
        let h = l.h;
        let q = 4 * h;
        let mut a = vec![0.0; n * (h + 1)];
        a[n * h..].fill(1.0);
        Work {
            l,
            n,
            act: vec![0.0; n * h],
            v: vec![0.0; n * q],
            a,
            e: vec![0.0; 3 * n],
            r: vec![0.0; n * h],
            vtv: vec![0.0; q * q],
            vta: vec![0.0; q * (h + 1)],
            ata: vec![0.0; (h + 1) * (h + 1)],
            jtj: DMatrix::zeros(l.len(), l.len()),
            g: DVector::zeros(l.len()),
        }
    }

    /// Residuals, J^T J and J^T e at `w`; returns the SSE.
    ///
    /// With `d_kn = w2[k][j] (1 - a_nj^2)`, the first-layer rows of J are
    /// `d_kn x~_n`, so
    /// `(J^T J)[4j+i, 4j'+i'] = S_jj' (V^T V)[4j+i, 4j'+i']`, `S = W2^T W2`,
    /// and the cross block of output k is `w2[k][j] (V^T A)[4j+i, .]`. Only
    /// `V^T V`, `V^T A` and `A^T A` need products over the N samples:
    /// about 21 N H^2 multiply-adds instead of 147 N H^2 for a dense `J^T J`.
    fn linearize(&mut self, w: &[f64], x: &[[f64; 3]], y: &[[f64; 3]]) -> f64 {
        let (l, n, h) = (self.l, self.n, self.l.h);
        let q = 4 * h;
        for j in 0..h {
            let (w0, w1, w2, b) = (w[l.w1(j, 0)], w[l.w1(j, 1)], w[l.w1(j, 2)], w[l.b1(j)]);
            let act = &mut self.act[j * n..(j + 1) * n];
            for (a, p) in act.iter_mut().zip(x) {
                *a = fast_tanh(w0 * p[0] + w1 * p[1] + w2 * p[2] + b);
            }
            self.a[j * n..(j + 1) * n].copy_from_slice(act);
            for i in 0..4 {
                let col = &mut self.v[(4 * j + i) * n..(4 * j + i + 1) * n];
                for ((c, a), p) in col.iter_mut().zip(act.iter()).zip(x) {
                    let xi = if i < 3 { p[i] } else { 1.0 };
                    *c = (1.0 - a * a) * xi;
                }
            }
        }
        let mut sse = 0.0;
        for k in 0..3 {
            let o = l.out(k);
            let ek = &mut self.e[k * n..(k + 1) * n];
            for (e, t) in ek.iter_mut().zip(y) {
                *e = t[k] - w[o + h];
            }
            for j in 0..h {
                let wk = w[o + j];
                for (e, a) in ek.iter_mut().zip(&self.act[j * n..(j + 1) * n]) {
                    *e -= wk * a;
                }
            }
            sse += ek.iter().map(|e| e * e).sum::<f64>();
        }
        gemm_tn(q, q, n, &self.v, n, &self.v, n, &mut self.vtv, q);
        gemm_tn(q, h + 1, n, &self.v, n, &self.a, n, &mut self.vta, q);
        gemm_tn(
            h + 1,
            h + 1,
            n,
            &self.a,
            n,
            &self.a,
            n,
            &mut self.ata,
            h + 1,
        );
        let wdim = l.len();
        let jtj = self.jtj.as_mut_slice();
        // First-layer block.
        for jc in 0..h {
            for jr in 0..h {
                let s: f64 = (0..3).map(|k| w[l.w2(k, jr)] * w[l.w2(k, jc)]).sum();
                for ic in 0..4 {
                    let c = 4 * jc + ic;
                    for ir in 0..4 {
                        let r = 4 * jr + ir;
                        jtj[c * wdim + r] = s * self.vtv[c * q + r];
                    }
                }
            }
        }
        for k in 0..3 {
            let o = l.out(k);
            // Output-layer block: the same A^T A for every output.
            for c in 0..=h {
                jtj[(o + c) * wdim + o..(o + c) * wdim + o + h + 1]
                    .copy_from_slice(&self.ata[c * (h + 1)..(c + 1) * (h + 1)]);
            }
            // Cross blocks, mirrored.
            for c in 0..=h {
                for r in 0..q {
                    let v = w[l.w2(k, r / 4)] * self.vta[c * q + r];
                    jtj[(o + c) * wdim + r] = v;
                    jtj[r * wdim + o + c] = v;
                }
            }
        }
        // J^T e.
        for j in 0..h {
            let rj = &mut self.r[j * n..(j + 1) * n];
            rj.fill(0.0);
            for k in 0..3 {
                let wk = w[l.w2(k, j)];
                for (r, e) in rj.iter_mut().zip(&self.e[k * n..(k + 1) * n]) {
                    *r += wk * e;
                }
            }
            for i in 0..4 {
                let col = &self.v[(4 * j + i) * n..(4 * j + i + 1) * n];
                self.g[4 * j + i] = col.iter().zip(rj.iter()).map(|(a, b)| a * b).sum();
            }
        }
        for k in 0..3 {
            let o = l.out(k);
            let ek = &self.e[k * n..(k + 1) * n];
            for c in 0..=h {
                let col = &self.a[c * n..(c + 1) * n];
                self.g[o + c] = col.iter().zip(ek).map(|(a, b)| a * b).sum();
            }
        }
        sse
    }
}

/// `tanh(x) = 1 - 2 / (exp(2x) + 1)`: about twice as fast as libm's `tanh`
/// here, and the hidden layer is a large share of an epoch. Absolute error
/// stays at rounding level (1e-16), which is what training needs; it
/// saturates correctly (exp overflow gives 1, underflow gives -1). Models are
/// evaluated with the std `tanh`.
#[inline]
fn fast_tanh(x: f64) -> f64 {
    1.0 - 2.0 / ((2.0 * x).exp() + 1.0)
}

/// `C = A^T B` for column-major `A` (k x m, leading dimension `lda`), `B`
/// (k x n, `ldb`) and `C` (m x n, `ldc`), by matrixmultiply's packed kernel.
///
/// We call matrixmultiply directly rather than nalgebra's `gemm` on strided
/// views: nalgebra 0.35's small-matrix fallback (any dimension <= 5, as for
/// H <= 4) indexes out of the slice of a view whose row stride exceeds its
/// column stride (a debug build stops on `get_unchecked_mut`; release
/// segfaulted in the hidden-size sweep).
#[allow(clippy::too_many_arguments)]
fn gemm_tn(
    m: usize,
    n: usize,
    k: usize,
    a: &[f64],
    lda: usize,
    b: &[f64],
    ldb: usize,
    c: &mut [f64],
    ldc: usize,
) {
    if m == 0 || n == 0 {
        return;
    }
    // The extents matrixmultiply will touch; a violation is a bug here, and
    // asserting keeps the unsafe call sound.
    assert!(
        k <= lda && k <= ldb && m <= ldc,
        "gemm_tn: leading dimensions"
    );
    assert!(a.len() >= (m - 1) * lda + k, "gemm_tn: A too short");
    assert!(b.len() >= (n - 1) * ldb + k, "gemm_tn: B too short");
    assert!(c.len() >= (n - 1) * ldc + m, "gemm_tn: C too short");
    // SAFETY: with the asserts above every element read, A^T(i, p) =
    // a[i lda + p] and B(p, j) = b[j ldb + p] for p < k, and every element
    // written, C(i, j) = c[j ldc + i], lies inside its slice; `c` is borrowed
    // mutably, so it cannot alias `a` or `b`.
    unsafe {
        matrixmultiply::dgemm(
            m,
            k,
            n,
            1.0,
            a.as_ptr(),
            lda as isize,
            1,
            b.as_ptr(),
            1,
            ldb as isize,
            0.0,
            c.as_mut_ptr(),
            1,
            ldc as isize,
        );
    }
}

/// One Levenberg-Marquardt run from `init`; `tick` is called once per epoch.
pub(crate) fn train_run(
    data: &Prepared,
    h: usize,
    init: Init,
    lm: &LmConfig,
    deadline: Deadline,
    tick: &(dyn Fn() + Sync),
) -> Run {
    let l = Layout { h };
    let mut w = match init {
        Init::Random(mut rng) => nguyen_widrow(data, h, &mut rng),
        Init::Warm(w) if w.len() == l.len() => w,
        Init::Warm(_) => nguyen_widrow(data, h, &mut Rng::new(h as u64)),
    };
    let has_val = !data.xv.is_empty();
    let score_of = |w: &[f64], train_sse: f64| {
        if has_val {
            sse(l, w, &data.xv, &data.yv)
        } else {
            train_sse
        }
    };
    let mut work = Work::new(l, data.x.len());
    let n_res = (3 * data.x.len()) as f64;
    let mut mu = lm.mu_init;
    let mut best_w = w.clone();
    let mut best_score = score_of(&w, sse(l, &w, &data.x, &data.y));
    let mut fails = 0;
    let mut epochs = 0;
    let mut stop = StopReason::MaxEpochs;
    let mut trial = vec![0.0; l.len()];
    'epochs: while epochs < lm.max_epochs {
        if deadline.passed() {
            stop = StopReason::TimeLimit;
            break;
        }
        let cur = work.linearize(&w, &data.x, &data.y);
        // Gradient of the mean squared error, as trainlm's min_grad test.
        if 2.0 * work.g.norm() / n_res < lm.min_grad {
            stop = StopReason::MinGradient;
            break;
        }
        let accepted_sse = loop {
            let mut m = work.jtj.clone();
            for d in 0..l.len() {
                m[(d, d)] += mu;
            }
            // A failed factorization (J^T J singular to rounding, as for
            // redundant neurons with small mu) counts as a rejected step.
            let step = nalgebra::linalg::Cholesky::new(m).map(|c| c.solve(&work.g));
            if let Some(dw) = step {
                for (t, (wi, di)) in trial.iter_mut().zip(w.iter().zip(dw.iter())) {
                    *t = wi + di;
                }
                let s = sse(l, &trial, &data.x, &data.y);
                if s < cur {
                    std::mem::swap(&mut w, &mut trial);
                    mu = (mu * lm.mu_dec).max(1e-20);
                    break s;
                }
            }
            mu *= lm.mu_inc;
            if mu > lm.mu_max {
                stop = StopReason::MuMax;
                break 'epochs;
            }
        };
        epochs += 1;
        tick();
        let score = score_of(&w, accepted_sse);
        if score < best_score {
            best_score = score;
            best_w.copy_from_slice(&w);
            fails = 0;
        } else if has_val {
            fails += 1;
            if fails >= lm.max_fail {
                stop = StopReason::ValidationFail;
                break;
            }
        }
    }
    Run {
        h,
        w: best_w,
        score: best_score,
        epochs,
        stop,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The analytic Jacobian blocks against central differences.
    #[test]
    fn jacobian_matches_finite_differences() {
        let mut rng = Rng::new(3);
        let x: Vec<[f64; 3]> = (0..7)
            .map(|_| [rng.normal(), rng.normal(), rng.normal()])
            .collect();
        let y: Vec<[f64; 3]> = (0..7)
            .map(|_| [rng.normal(), rng.normal(), rng.normal()])
            .collect();
        for h in [1, 2, 5] {
            check_jacobian(&x, &y, h, &mut rng);
        }
    }

    fn check_jacobian(x: &[[f64; 3]], y: &[[f64; 3]], h: usize, rng: &mut Rng) {
        let l = Layout { h };
        let w: Vec<f64> = (0..l.len()).map(|_| rng.normal()).collect();
        let mut work = Work::new(l, x.len());
        work.linearize(&w, x, y);
        // Dense J by differences of f = y - e.
        let f = |w: &[f64]| {
            let mut wk = Work::new(l, x.len());
            wk.linearize(w, x, y);
            DVector::from_iterator(3 * x.len(), wk.e.iter().map(|v| -v))
        };
        let mut jd = DMatrix::zeros(3 * x.len(), l.len());
        for c in 0..l.len() {
            let mut wp = w.clone();
            let mut wm = w.clone();
            wp[c] += 1e-6;
            wm[c] -= 1e-6;
            jd.set_column(c, &((f(&wp) - f(&wm)) / 2e-6));
        }
        let jtj = jd.transpose() * &jd;
        let g = jd.transpose() * DVector::from_column_slice(&work.e);
        assert!((jtj - &work.jtj).amax() < 1e-6, "J^T J mismatch at H = {h}");
        assert!((g - &work.g).amax() < 1e-6, "J^T e mismatch at H = {h}");
    }

    /// A run whose network the device cannot hold (a first-layer bias of
    /// 18, beyond Q4.27's +-16: the independent simulator's stream of seed
    /// 4 refitted such a net and `spidar compile` refused the calibration)
    /// loses to one it can, whatever their scores; among runs alike the
    /// lowest score wins, and the earlier on a tie.
    #[test]
    fn the_best_run_is_one_the_device_can_hold() {
        let mut rng = Rng::new(5);
        let x: Vec<[f64; 3]> = (0..40)
            .map(|_| {
                [
                    100.0 * rng.normal(),
                    100.0 * rng.normal(),
                    100.0 * rng.normal(),
                ]
            })
            .collect();
        let y: Vec<[f64; 3]> = x
            .iter()
            .map(|p| {
                [
                    p[0] + rng.normal(),
                    p[1] + rng.normal(),
                    p[2] + rng.normal(),
                ]
            })
            .collect();
        let data = Prepared::new(&x, &y, OutputMode::Residual, 0.0, 1).unwrap();
        let l = Layout { h: 2 };
        let run = |bias: f64, score: f64| {
            let mut w: Vec<f64> = (0..l.len()).map(|k| 0.1 * (k as f64 + 1.0)).collect();
            w[l.b1(1)] = bias;
            Run {
                h: 2,
                w,
                score,
                epochs: 1,
                stop: StopReason::MaxEpochs,
            }
        };
        let held = |r: &Run| data.model(r.h, &r.w).compile().is_ok();
        assert!(!held(&run(18.0, 1.0)) && held(&run(0.5, 2.0)));
        let best = best_run(&data, vec![run(18.0, 1.0), run(0.5, 2.0), run(0.7, 2.0)]).unwrap();
        assert_eq!((best.score, best.w[l.b1(1)]), (2.0, 0.5));
        // None held: the lowest score still, for the caller to refuse.
        let best = best_run(&data, vec![run(19.0, 3.0), run(18.0, 1.0)]).unwrap();
        assert_eq!(best.score, 1.0);
        assert!(best_run(&data, vec![run(0.5, f64::NAN)]).is_none());
    }
}
