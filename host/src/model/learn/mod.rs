//! Model-less position corrections learned from (device position, tracker
//! position) pairs, as in the paper (sections 4.3.2 and 5):
//!
//! - [`standardize`]: eq. 10, per-axis mean / standard deviation;
//! - [`outliers`]: Tukey box plot on the absolute position error (section 5.1);
//! - [`nn`]: a 3-H-3 network (tanh hidden layer, linear output) trained by
//!   Levenberg-Marquardt the `trainlm` way, with restarts and early stopping;
//! - [`svr`]: an RBF epsilon-SVR per axis (our own SMO solver, see there why);
//! - [`search`]: the hidden-size sweep of figure 13 and the SVR
//!   hyperparameter search;
//! - [`synthetic`]: a smooth distortion field for tests and benchmarks;
//! - [`thin`]: a large session thinned evenly through its volume.
//!
//! Trainers output the f64 model types of `spidar_core::correction`, which the
//! fixed-point compiler reads.

pub mod nn;
pub mod outliers;
pub mod search;
pub mod standardize;
pub mod svr;
pub mod synthetic;
pub mod thin;

use std::fmt;
use std::time::{Duration, Instant};

use crate::progress::Step;
pub use spidar_core::correction::{NnModel, OutputMode, Standardization, SvrModel};

/// What went wrong while learning a correction. Every variant names the
/// offending input so a report can say what to fix.
#[derive(Clone, Debug, PartialEq)]
pub enum LearnError {
    /// Inputs and targets do not pair up.
    LengthMismatch { inputs: usize, targets: usize },
    /// Not enough points for the requested operation.
    TooFewPoints {
        what: &'static str,
        got: usize,
        need: usize,
    },
    /// A NaN or infinite coordinate.
    NonFinite {
        what: &'static str,
        index: usize,
        axis: usize,
    },
    /// An axis with (numerically) zero spread cannot be standardized.
    ZeroSpread { what: &'static str, axis: usize },
    /// A parameter outside its valid range.
    InvalidParameter {
        name: &'static str,
        value: f64,
        expected: &'static str,
    },
    /// A model whose shape is inconsistent (e.g. `w1` and `b1` lengths differ).
    MalformedModel { what: &'static str },
    /// Nothing could be trained within the time budget.
    OutOfTime { what: &'static str, budget_s: f64 },
    /// The dense kernel matrix would not fit in the allowed memory.
    TooLarge {
        what: &'static str,
        points: usize,
        max: usize,
    },
}

impl fmt::Display for LearnError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LearnError::LengthMismatch { inputs, targets } => write!(
                f,
                "{inputs} input positions but {targets} target positions: they must pair up"
            ),
            LearnError::TooFewPoints { what, got, need } => {
                write!(f, "{what}: {got} points, need at least {need}")
            }
            LearnError::NonFinite { what, index, axis } => write!(
                f,
                "{what}: point {index} has a non-finite {} coordinate",
                ["x", "y", "z"][(*axis).min(2)]
            ),
            LearnError::ZeroSpread { what, axis } => write!(
                f,
                "{what}: the {} coordinate has zero spread, cannot standardize",
                ["x", "y", "z"][(*axis).min(2)]
            ),
            LearnError::InvalidParameter {
                name,
                value,
                expected,
            } => write!(f, "parameter {name} = {value}: expected {expected}"),
            LearnError::MalformedModel { what } => write!(f, "malformed model: {what}"),
            LearnError::OutOfTime { what, budget_s } => {
                write!(f, "{what}: nothing finished within the {budget_s} s budget")
            }
            LearnError::TooLarge { what, points, max } => write!(
                f,
                "{what}: {points} points exceed the dense-kernel limit of {max}"
            ),
        }
    }
}

impl std::error::Error for LearnError {}

/// The one error statistic (eq. 7), as every report uses it.
pub use crate::data::stats::ErrorStats;

pub(crate) fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let dx = a[0] - b[0];
    let dy = a[1] - b[1];
    let dz = a[2] - b[2];
    (dx * dx + dy * dy + dz * dz).sqrt()
}

/// Check that inputs and targets pair up, are finite and number at least `need`.
pub fn validate_pairs(
    what: &'static str,
    inputs: &[[f64; 3]],
    targets: &[[f64; 3]],
    need: usize,
) -> Result<(), LearnError> {
    if inputs.len() != targets.len() {
        return Err(LearnError::LengthMismatch {
            inputs: inputs.len(),
            targets: targets.len(),
        });
    }
    validate_points(what, inputs, need)?;
    validate_points(what, targets, need)
}

/// Check that points are finite and number at least `need`.
pub fn validate_points(
    what: &'static str,
    points: &[[f64; 3]],
    need: usize,
) -> Result<(), LearnError> {
    if points.len() < need {
        return Err(LearnError::TooFewPoints {
            what,
            got: points.len(),
            need,
        });
    }
    for (index, p) in points.iter().enumerate() {
        for (axis, v) in p.iter().enumerate() {
            if !v.is_finite() {
                return Err(LearnError::NonFinite { what, index, axis });
            }
        }
    }
    Ok(())
}

pub(crate) fn check_range(
    name: &'static str,
    value: f64,
    lo: f64,
    hi: f64,
    expected: &'static str,
) -> Result<(), LearnError> {
    if value.is_finite() && value >= lo && value <= hi {
        Ok(())
    } else {
        Err(LearnError::InvalidParameter {
            name,
            value,
            expected,
        })
    }
}

/// Small deterministic PRNG (xoshiro256++ seeded by SplitMix64). Our own so
/// that seeded results do not change when a `rand` release changes its
/// algorithms: tests assert exact reproducibility.
#[derive(Clone, Debug)]
pub struct Rng {
    s: [u64; 4],
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl Rng {
    pub fn new(seed: u64) -> Self {
        let mut st = seed;
        let s = [
            splitmix64(&mut st),
            splitmix64(&mut st),
            splitmix64(&mut st),
            splitmix64(&mut st),
        ];
        Rng { s }
    }

    /// A generator for a sub-task, independent of the order tasks run in.
    pub fn derive(seed: u64, stream: u64) -> Self {
        let mut st = seed ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03);
        Rng::new(splitmix64(&mut st))
    }

    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }

    /// Uniform index below `n` (n > 0).
    pub fn below(&mut self, n: usize) -> usize {
        // Multiply-shift: bias < n / 2^64, irrelevant here.
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }

    pub fn shuffle<T>(&mut self, v: &mut [T]) {
        for i in (1..v.len()).rev() {
            let j = self.below(i + 1);
            v.swap(i, j);
        }
    }
}

/// Split `0..n` into (train, validation) index sets, seeded; the validation
/// set gets `round(n * fraction)` points but never empties the training set.
pub fn split_indices(n: usize, fraction: f64, seed: u64) -> (Vec<usize>, Vec<usize>) {
    let mut idx: Vec<usize> = (0..n).collect();
    Rng::derive(seed, 0x5EED_5B17).shuffle(&mut idx);
    let n_val = ((n as f64 * fraction).round() as usize).min(n.saturating_sub(1));
    let val = idx[..n_val].to_vec();
    let mut train = idx[n_val..].to_vec();
    train.sort_unstable();
    let mut val = val;
    val.sort_unstable();
    (train, val)
}

/// A wall-clock deadline; `None` means no limit.
#[derive(Clone, Copy, Debug)]
pub struct Deadline(Option<Instant>);

impl Deadline {
    pub fn none() -> Self {
        Deadline(None)
    }
    pub fn after(d: Option<Duration>) -> Self {
        Deadline(d.map(|d| Instant::now() + d))
    }
    pub fn passed(&self) -> bool {
        self.0.is_some_and(|t| Instant::now() >= t)
    }
}

/// A bar of `len` steps, shown by the installed [`crate::progress`]
/// reporter unless `quiet` (tests).
pub(crate) fn progress(len: u64, msg: &'static str, quiet: bool) -> Step {
    Step::bar(len, msg, quiet)
}
