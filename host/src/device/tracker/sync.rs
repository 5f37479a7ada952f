//! Time shift between the tracker and device streams.
//!
//! The tracker stamps frames with its own clock (DTrack `ts`, the camera
//! flash); the device with the host's or the MCU's. Pairing them for
//! calibration needs the map between the two clocks:
//!
//! ```text
//! tracker_ts = device_t + offset_s + drift * (device_t - reference_t_s)
//! ```
//!
//! Two steps:
//!
//! 1. **Coarse**: both streams resampled on a common grid (step = the median
//!    tracker interval unless given), speed profiles (central differences,
//!    invariant to the unknown room transform), normalized cross-correlation
//!    over lags `prior_offset_s ± max_shift_s`, parabolic refinement of the
//!    peak.
//! 2. **Fine**: least squares of the position differences
//!    `P_tracker(s_i) - p_device(t_i) - b` over the offset (and the drift if
//!    asked), where `s_i` is the device time mapped to tracker time, `P_tracker`
//!    the tracker positions interpolated (cubic Hermite, sub-frame) and `b`
//!    a constant vector that absorbs a static room-transform error. `b` is
//!    eliminated in closed form (variable projection); the offset and drift
//!    are solved by Levenberg-Marquardt. The tracker is never interpolated
//!    across an occlusion (a gap longer than `max_gap_s`).
//!
//! **Uncertainty**: the Gauss-Newton covariance `sigma^2 (J^T J)^-1`, inflated
//! by `sqrt((1 + rho) / (1 - rho))` where `rho` is the lag-1 correlation of
//! the residuals (which are far from independent at device rates), i.e. an
//! effective number of independent pairs. A remaining error of the device
//! positions that varies with position (an uncalibrated model) is not white
//! noise; it widens the residuals and with them the reported uncertainty.

use super::TrackerFrame;
use rayon::prelude::*;
use spidar_core::geometry::{dot, norm, scale, sub};

/// A position at a time on one stream's clock.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedPosition {
    pub t_s: f64,
    pub position_mm: [f64; 3],
}

impl TimedPosition {
    /// The visible frames of a tracker stream (occluded ones left out).
    pub fn from_frames(frames: &[TrackerFrame]) -> Vec<TimedPosition> {
        frames
            .iter()
            .filter_map(|f| {
                f.body.as_ref().map(|b| TimedPosition {
                    t_s: f.ts_s,
                    position_mm: b.position_mm,
                })
            })
            .collect()
    }
}

/// Settings of [`estimate_time_shift`].
#[derive(Clone, Debug, PartialEq)]
pub struct ShiftConfig {
    /// Expected `tracker_ts - device_t` (s): the centre of the search. For
    /// DTrack's seconds-since-midnight against a session clock, e.g. the
    /// `ts` of the frame received when the session started.
    pub prior_offset_s: f64,
    /// Half-width of the search around the prior (s).
    pub max_shift_s: f64,
    /// Step of the coarse grid (s); `None`: the median tracker interval.
    pub grid_step_s: Option<f64>,
    /// Samples further apart than this are not interpolated across (s).
    pub max_gap_s: f64,
    /// Fit a clock-rate difference too.
    pub estimate_drift: bool,
    /// Iterations of the fine fit.
    pub max_iterations: usize,
}

impl Default for ShiftConfig {
    /// Prior 0, search +-0.5 s, grid from the data, gaps over 0.1 s not
    /// bridged, no drift, 50 iterations.
    fn default() -> Self {
        ShiftConfig {
            prior_offset_s: 0.0,
            max_shift_s: 0.5,
            grid_step_s: None,
            max_gap_s: 0.1,
            estimate_drift: false,
            max_iterations: 50,
        }
    }
}

/// The estimated map between the clocks.
#[derive(Clone, Debug, PartialEq)]
pub struct TimeShift {
    /// `tracker_ts - device_t` at `reference_t_s` (s).
    pub offset_s: f64,
    /// One standard deviation of `offset_s` (s).
    pub offset_std_s: f64,
    /// Clock-rate difference (s per s; 0 when not estimated).
    pub drift: f64,
    /// One standard deviation of `drift` (0 when not estimated).
    pub drift_std: f64,
    /// Device time the offset refers to (the middle of the device stream).
    pub reference_t_s: f64,
    /// The cross-correlation estimate the fit started from (s).
    pub coarse_offset_s: f64,
    /// Peak normalized correlation of the speed profiles (-1..1).
    pub correlation: f64,
    /// Constant `tracker - device` position difference (mm).
    pub bias_mm: [f64; 3],
    /// RMS length of the residual vectors (mm).
    pub rms_residual_mm: f64,
    /// Device samples paired with the tracker in the fit.
    pub pairs: usize,
    /// Of those, the effective number of independent ones.
    pub effective_pairs: f64,
}

impl TimeShift {
    /// Tracker time of a device time.
    pub fn tracker_time(&self, device_t_s: f64) -> f64 {
        device_t_s + self.offset_s + self.drift * (device_t_s - self.reference_t_s)
    }

    /// Device time of a tracker time (inverse of [`TimeShift::tracker_time`]).
    pub fn device_time(&self, tracker_ts_s: f64) -> f64 {
        (tracker_ts_s - self.offset_s + self.drift * self.reference_t_s) / (1.0 + self.drift)
    }
}

/// Why no shift could be estimated.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SyncError {
    #[error("{stream} stream: {have} samples, at least {need} needed")]
    TooFewSamples {
        stream: &'static str,
        have: usize,
        need: usize,
    },
    #[error("{stream} stream, sample {index}, field `{field}`: {value} is not finite")]
    NotFinite {
        stream: &'static str,
        index: usize,
        field: &'static str,
        value: f64,
    },
    #[error("{stream} stream, sample {index}, field `t_s`: {value} s is before the previous {previous} s")]
    TimeDecreasing {
        stream: &'static str,
        index: usize,
        value: f64,
        previous: f64,
    },
    #[error("configuration field {0}")]
    Config(#[from] crate::ConfigError),
    #[error("the streams overlap in {pairs} samples within the search range, {need} needed")]
    NoOverlap { pairs: usize, need: usize },
    #[error("the {stream} stream shows no motion: move the end-effector while recording")]
    NoMotion { stream: &'static str },
}

const MIN_SAMPLES: usize = 10;
const MIN_LAG_PAIRS: usize = 20;
const MAX_GRID: usize = 4_000_000;
/// Fewest samples per task when samples are interpolated on every core.
const EVAL_MIN_TASK: usize = 1024;

fn check_stream(stream: &'static str, s: &[TimedPosition]) -> Result<(), SyncError> {
    if s.len() < MIN_SAMPLES {
        return Err(SyncError::TooFewSamples {
            stream,
            have: s.len(),
            need: MIN_SAMPLES,
        });
    }
    let mut previous: Option<f64> = None;
    for (index, p) in s.iter().enumerate() {
        let fields = [
            ("t_s", p.t_s),
            ("position_mm[0]", p.position_mm[0]),
            ("position_mm[1]", p.position_mm[1]),
            ("position_mm[2]", p.position_mm[2]),
        ];
        for (field, value) in fields {
            if !value.is_finite() {
                return Err(SyncError::NotFinite {
                    stream,
                    index,
                    field,
                    value,
                });
            }
        }
        if let Some(prev) = previous {
            if p.t_s < prev {
                return Err(SyncError::TimeDecreasing {
                    stream,
                    index,
                    value: p.t_s,
                    previous: prev,
                });
            }
        }
        previous = Some(p.t_s);
    }
    Ok(())
}

/// A stream interpolated by cubic Hermite segments, never across a gap.
struct Series<'a> {
    s: &'a [TimedPosition],
    max_gap: f64,
}

type V3 = [f64; 3];

impl Series<'_> {
    fn step_ok(&self, dt: f64) -> bool {
        dt > 0.0 && dt <= self.max_gap
    }

    /// Position and velocity at `t`, if `t` lies within a gap-free span.
    fn eval(&self, t: f64) -> Option<(V3, V3)> {
        let s = self.s;
        let n = s.len();
        if n < 2 || !(t >= s[0].t_s && t <= s[n - 1].t_s) {
            return None;
        }
        let k = s
            .partition_point(|p| p.t_s <= t)
            .saturating_sub(1)
            .min(n - 2);
        let (a, b) = (&s[k], &s[k + 1]);
        let dt = b.t_s - a.t_s;
        if !self.step_ok(dt) {
            return None;
        }
        let chord = scale(1.0 / dt, sub(b.position_mm, a.position_mm));
        let m0 = if k >= 1 && self.step_ok(a.t_s - s[k - 1].t_s) {
            scale(
                1.0 / (b.t_s - s[k - 1].t_s),
                sub(b.position_mm, s[k - 1].position_mm),
            )
        } else {
            chord
        };
        let m1 = if k + 2 < n && self.step_ok(s[k + 2].t_s - b.t_s) {
            scale(
                1.0 / (s[k + 2].t_s - a.t_s),
                sub(s[k + 2].position_mm, a.position_mm),
            )
        } else {
            chord
        };
        let x = (t - a.t_s) / dt;
        let (x2, x3) = (x * x, x * x * x);
        let h00 = 2.0 * x3 - 3.0 * x2 + 1.0;
        let h10 = x3 - 2.0 * x2 + x;
        let h01 = -2.0 * x3 + 3.0 * x2;
        let h11 = x3 - x2;
        let d00 = 6.0 * x2 - 6.0 * x;
        let d10 = 3.0 * x2 - 4.0 * x + 1.0;
        let d01 = -6.0 * x2 + 6.0 * x;
        let d11 = 3.0 * x2 - 2.0 * x;
        let p = core::array::from_fn(|i| {
            h00 * a.position_mm[i] + h10 * dt * m0[i] + h01 * b.position_mm[i] + h11 * dt * m1[i]
        });
        let v = core::array::from_fn(|i| {
            (d00 * a.position_mm[i] + d01 * b.position_mm[i]) / dt + d10 * m0[i] + d11 * m1[i]
        });
        Some((p, v))
    }

    /// Speed at `t` by a central difference over `+-h`.
    fn speed(&self, t: f64, h: f64) -> Option<f64> {
        let (a, _) = self.eval(t - h)?;
        let (b, _) = self.eval(t + h)?;
        Some(norm(sub(b, a)) / (2.0 * h))
    }
}

fn median_interval(s: &[TimedPosition]) -> Option<f64> {
    let mut d: Vec<f64> = s
        .windows(2)
        .map(|w| w[1].t_s - w[0].t_s)
        .filter(|d| *d > 0.0)
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

fn pearson(pairs: &[(f64, f64)]) -> Option<f64> {
    let n = pairs.len() as f64;
    let (mx, my) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), (x, y)| (a + x / n, b + y / n));
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (x, y) in pairs {
        sxy += (x - mx) * (y - my);
        sxx += (x - mx) * (x - mx);
        syy += (y - my) * (y - my);
    }
    let den = (sxx * syy).sqrt();
    (den > 0.0 && den.is_finite()).then(|| sxy / den)
}

fn variance(v: impl Iterator<Item = f64>) -> f64 {
    let v: Vec<f64> = v.collect();
    if v.len() < 2 {
        return 0.0;
    }
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / n
}

/// Coarse offset from the speed profiles: (offset, peak correlation).
fn coarse(
    device: &Series,
    tracker: &Series,
    cfg: &ShiftConfig,
    h: f64,
) -> Result<(f64, f64), SyncError> {
    let d = device.s;
    let t0 = d[0].t_s;
    let span = d[d.len() - 1].t_s - t0;
    let n = (span / h).floor() as usize + 1;
    let lmax = (cfg.max_shift_s / h).ceil() as usize;
    let sd: Vec<Option<f64>> = (0..n)
        .into_par_iter()
        .with_min_len(EVAL_MIN_TASK)
        .map(|j| device.speed(t0 + j as f64 * h, h))
        .collect();
    let base = t0 + cfg.prior_offset_s;
    let st: Vec<Option<f64>> = (0..n + 2 * lmax)
        .into_par_iter()
        .with_min_len(EVAL_MIN_TASK)
        .map(|k| tracker.speed(base + (k as f64 - lmax as f64) * h, h))
        .collect();
    let valid = |v: &[Option<f64>]| v.iter().flatten().count();
    if valid(&sd) < MIN_LAG_PAIRS || valid(&st) < MIN_LAG_PAIRS {
        // Nothing to correlate: the tracker stream lies outside the search
        // range, or the streams are all gaps.
        return Err(SyncError::NoOverlap {
            pairs: valid(&sd).min(valid(&st)),
            need: MIN_LAG_PAIRS,
        });
    }
    if variance(sd.iter().flatten().copied()) <= 1e-12 {
        return Err(SyncError::NoMotion { stream: "device" });
    }
    if variance(st.iter().flatten().copied()) <= 1e-12 {
        return Err(SyncError::NoMotion { stream: "tracker" });
    }
    // Each lag's correlation is its own: the lags are worked out on every
    // core.
    let (mut corr, counts): (Vec<Option<f64>>, Vec<usize>) = (0..=2 * lmax)
        .into_par_iter()
        .map_init(
            || Vec::with_capacity(n),
            |pairs, lag| {
                pairs.clear();
                pairs.extend(
                    sd.iter()
                        .zip(&st[lag..lag + n])
                        .filter_map(|(a, b)| Some(((*a)?, (*b)?))),
                );
                let corr = if pairs.len() >= MIN_LAG_PAIRS {
                    pearson(pairs)
                } else {
                    None
                };
                (corr, pairs.len())
            },
        )
        .unzip();
    // A lag whose overlap is a sliver of the streams correlates by chance:
    // only lags pairing at least half as many samples as the best-paired
    // one compete (a 10 s stream 4.5 s off, centred on its true offset,
    // peaked at +9.2 s on 76 pairs against 550 at 4.5 s).
    let most_pairs = counts.iter().copied().max().unwrap_or(0);
    for (c, &k) in corr.iter_mut().zip(&counts) {
        if 2 * k < most_pairs {
            *c = None;
        }
    }
    let best = corr
        .iter()
        .enumerate()
        .filter_map(|(i, c)| c.map(|c| (i, c)))
        .max_by(|a, b| a.1.total_cmp(&b.1));
    let Some((i, c0)) = best else {
        return Err(SyncError::NoOverlap {
            pairs: most_pairs,
            need: MIN_LAG_PAIRS,
        });
    };
    let mut delta = 0.0;
    if i > 0 {
        if let (Some(Some(cm)), Some(Some(cp))) = (corr.get(i - 1), corr.get(i + 1)) {
            let den = cm - 2.0 * c0 + cp;
            if den < 0.0 {
                delta = (0.5 * (cm - cp) / den).clamp(-0.5, 0.5);
            }
        }
    }
    let lag = i as f64 - lmax as f64 + delta;
    Ok((cfg.prior_offset_s + lag * h, c0))
}

/// One linearization of the fine problem.
struct Linear {
    /// Indices of the device samples paired.
    used: Vec<usize>,
    /// Centred residual vectors (bias removed), per used sample.
    residuals: Vec<V3>,
    /// Centred Jacobian columns (offset, drift), per used sample.
    jac: Vec<[V3; 2]>,
    bias: V3,
    rss: f64,
}

struct Fine<'a> {
    device: &'a [TimedPosition],
    tracker: Series<'a>,
    reference: f64,
}

impl Fine<'_> {
    /// Evaluate at `theta = (offset, drift)` over `only` (or every sample).
    fn linearize(&self, theta: [f64; 2], only: Option<&[usize]>) -> Linear {
        let all: Vec<usize>;
        let indices = match only {
            Some(i) => i,
            None => {
                all = (0..self.device.len()).collect();
                &all
            }
        };
        // Each sample's interpolation is its own (on every core); the sums
        // below go over them in order, so the fit is the same to the bit.
        let evaluated: Vec<Option<(V3, V3, f64)>> = indices
            .par_iter()
            .with_min_len(EVAL_MIN_TASK)
            .map(|&i| {
                let d = &self.device[i];
                let u = d.t_s - self.reference;
                let s = d.t_s + theta[0] + theta[1] * u;
                self.tracker
                    .eval(s)
                    .map(|(p, v)| (sub(p, d.position_mm), v, u))
            })
            .collect();
        let mut used = Vec::with_capacity(indices.len());
        let mut raw: Vec<(V3, V3, f64)> = Vec::with_capacity(indices.len());
        for (&i, e) in indices.iter().zip(evaluated) {
            if let Some(e) = e {
                used.push(i);
                raw.push(e);
            }
        }
        let n = raw.len().max(1) as f64;
        let mut bias = [0.0; 3];
        let mut mean_v = [0.0; 3];
        let mut mean_vu = [0.0; 3];
        for (e, v, u) in &raw {
            for k in 0..3 {
                bias[k] += e[k] / n;
                mean_v[k] += v[k] / n;
                mean_vu[k] += v[k] * u / n;
            }
        }
        let mut residuals = Vec::with_capacity(raw.len());
        let mut jac = Vec::with_capacity(raw.len());
        let mut rss = 0.0;
        for (e, v, u) in &raw {
            let r = sub(*e, bias);
            rss += dot(r, r);
            residuals.push(r);
            jac.push([sub(*v, mean_v), sub(scale(*u, *v), mean_vu)]);
        }
        Linear {
            used,
            residuals,
            jac,
            bias,
            rss,
        }
    }
}

/// Normal equations `A delta = -g` of the first `p` parameters.
fn normal(lin: &Linear, p: usize) -> ([[f64; 2]; 2], [f64; 2]) {
    let mut a = [[0.0; 2]; 2];
    let mut g = [0.0; 2];
    for (j, r) in lin.jac.iter().zip(&lin.residuals) {
        for x in 0..p {
            g[x] += dot(j[x], *r);
            for y in 0..p {
                a[x][y] += dot(j[x], j[y]);
            }
        }
    }
    (a, g)
}

/// Solve a 1x1 or 2x2 symmetric system; `None` if singular.
fn solve(a: [[f64; 2]; 2], b: [f64; 2], p: usize) -> Option<[f64; 2]> {
    if p == 1 {
        return (a[0][0] > 0.0).then(|| [b[0] / a[0][0], 0.0]);
    }
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    if !det.is_finite() || det.abs() <= 1e-300 {
        return None;
    }
    Some([
        (b[0] * a[1][1] - b[1] * a[0][1]) / det,
        (a[0][0] * b[1] - a[1][0] * b[0]) / det,
    ])
}

fn invert(a: [[f64; 2]; 2], p: usize) -> Option<[[f64; 2]; 2]> {
    let c0 = solve(a, [1.0, 0.0], p)?;
    if p == 1 {
        return Some([[c0[0], 0.0], [0.0, 0.0]]);
    }
    let c1 = solve(a, [0.0, 1.0], p)?;
    Some([[c0[0], c1[0]], [c0[1], c1[1]]])
}

/// Estimate the map from device time to tracker time.
///
/// `device`: device-derived positions (e.g. forward kinematics mapped to the
/// room) on the device clock; `tracker`: tracker positions on the tracker
/// clock (e.g. [`TimedPosition::from_frames`]). Both in time order, in mm, in
/// (roughly) the same frame. The motion must vary in speed within the
/// overlap (a still end-effector carries no timing information).
pub fn estimate_time_shift(
    device: &[TimedPosition],
    tracker: &[TimedPosition],
    config: &ShiftConfig,
) -> Result<TimeShift, SyncError> {
    let coarse = CoarseShift::of(device, tracker, config)?;
    coarse.refined(config.estimate_drift)
}

/// The coarse search of [`estimate_time_shift`] (the speed profiles'
/// correlation peak), which the fine fit with a drift and the one without
/// share: [`CoarseShift::refined`] gives each.
pub struct CoarseShift<'a> {
    device: &'a [TimedPosition],
    tracker: Series<'a>,
    config: ShiftConfig,
    grid_step_s: f64,
    offset_s: f64,
    correlation: f64,
}

impl<'a> CoarseShift<'a> {
    /// The coarse search on `device` and `tracker` (as
    /// [`estimate_time_shift`] reads them) with `config` (its
    /// `estimate_drift` is [`refined`](Self::refined)'s to say).
    pub fn of(
        device: &'a [TimedPosition],
        tracker: &'a [TimedPosition],
        config: &ShiftConfig,
    ) -> Result<CoarseShift<'a>, SyncError> {
        check_stream("device", device)?;
        check_stream("tracker", tracker)?;
        let h = grid_step(device, tracker, config)?;
        let device_series = Series {
            s: device,
            max_gap: config.max_gap_s,
        };
        let tracker_series = Series {
            s: tracker,
            max_gap: config.max_gap_s,
        };
        let (offset_s, correlation) = coarse(&device_series, &tracker_series, config, h)?;
        Ok(CoarseShift {
            device,
            tracker: tracker_series,
            config: config.clone(),
            grid_step_s: h,
            offset_s,
            correlation,
        })
    }

    /// The fine fit from the coarse peak: the offset, and the clocks' rate
    /// difference with `drift`.
    pub fn refined(&self, drift: bool) -> Result<TimeShift, SyncError> {
        let (device, config, h) = (self.device, &self.config, self.grid_step_s);
        let fine = Fine {
            device,
            tracker: Series {
                s: self.tracker.s,
                max_gap: self.tracker.max_gap,
            },
            reference: 0.5 * (device[0].t_s + device[device.len() - 1].t_s),
        };
        let p = if drift { 2 } else { 1 };
        let (theta, lin) = refine(&fine, [self.offset_s, 0.0], config, h, p);
        let n = lin.used.len();
        if n < MIN_SAMPLES {
            return Err(SyncError::NoOverlap {
                pairs: n,
                need: MIN_SAMPLES,
            });
        }
        let (a, _) = normal(&lin, p);
        let dof = (3 * n).saturating_sub(3 + p).max(1) as f64;
        let sigma2 = lin.rss / dof;
        let rho = residual_correlation(&lin);
        let inflation = (1.0 + rho) / (1.0 - rho);
        let cov = invert(a, p).ok_or(SyncError::NoMotion { stream: "tracker" })?;
        let std = |k: usize| (sigma2 * cov[k][k].max(0.0) * inflation).sqrt();
        Ok(TimeShift {
            offset_s: theta[0],
            offset_std_s: std(0),
            drift: theta[1],
            drift_std: if p == 2 { std(1) } else { 0.0 },
            reference_t_s: fine.reference,
            coarse_offset_s: self.offset_s,
            correlation: self.correlation,
            bias_mm: lin.bias,
            rms_residual_mm: (lin.rss / n as f64).sqrt(),
            pairs: n,
            effective_pairs: n as f64 / inflation,
        })
    }
}

/// The coarse search's grid step (`grid_step_s`, else the tracker's median
/// interval), once the configuration is checked: a finite prior offset,
/// durations that are durations, and a grid of at most [`MAX_GRID`] points
/// over the device stream and the search.
fn grid_step(
    device: &[TimedPosition],
    tracker: &[TimedPosition],
    config: &ShiftConfig,
) -> Result<f64, SyncError> {
    let cfg_err = |field: &'static str, problem: String| {
        Err(SyncError::Config(crate::ConfigError::new(field, problem)))
    };
    if !config.prior_offset_s.is_finite() {
        return cfg_err(
            "prior_offset_s",
            format!("{} is not finite", config.prior_offset_s),
        );
    }
    if !(config.max_shift_s.is_finite() && config.max_shift_s >= 0.0) {
        return cfg_err(
            "max_shift_s",
            format!("{} is not a non-negative duration", config.max_shift_s),
        );
    }
    if !(config.max_gap_s.is_finite() && config.max_gap_s > 0.0) {
        return cfg_err(
            "max_gap_s",
            format!("{} is not a positive duration", config.max_gap_s),
        );
    }
    let h = match config.grid_step_s {
        Some(h) => h,
        None => median_interval(tracker).unwrap_or(0.0),
    };
    if !(h.is_finite() && h > 0.0) {
        return cfg_err("grid_step_s", format!("{h} is not a positive step"));
    }
    let span = device[device.len() - 1].t_s - device[0].t_s;
    let grid = span / h + 2.0 * config.max_shift_s / h;
    if !grid.is_finite() || grid >= MAX_GRID as f64 {
        return cfg_err(
            "grid_step_s",
            format!("{h} s gives more than {MAX_GRID} grid points over the stream and search"),
        );
    }
    Ok(h)
}

/// Levenberg-Marquardt from `theta` (offset, drift; `p` of them free),
/// each step within a grid step `h` of the last (the coarse basin): the
/// refined `theta` and the fit there.
fn refine(
    fine: &Fine,
    mut theta: [f64; 2],
    config: &ShiftConfig,
    h: f64,
    p: usize,
) -> ([f64; 2], Linear) {
    let mut lambda = 1e-3;
    let mut lin = fine.linearize(theta, None);
    for _ in 0..config.max_iterations {
        if lin.used.len() < MIN_SAMPLES {
            break;
        }
        let (a, g) = normal(&lin, p);
        let cost = lin.rss / lin.used.len() as f64;
        // Settled as the identification's fits are: when the full
        // Gauss-Newton step promises a fall of the residual sum below
        // 1e-2 of one residual's share of it (a chi-square change of 0.01,
        // a tenth of the offset's sd). Closer in, the damped steps are
        // refused one after another on the sum's rounding, each a pass
        // over the stream.
        let settled = 1e-2 * lin.rss / (3 * lin.used.len()) as f64;
        if solve(a, g, p).is_some_and(|d| d[0] * g[0] + d[1] * g[1] < settled) {
            break;
        }
        let mut improved = false;
        let mut step = [0.0; 2];
        for _ in 0..12 {
            let damped = [
                [a[0][0] * (1.0 + lambda), a[0][1]],
                [a[1][0], a[1][1] * (1.0 + lambda)],
            ];
            let Some(d) = solve(damped, [-g[0], -g[1]], p) else {
                lambda *= 10.0;
                continue;
            };
            // Stay within a grid step per iteration (the coarse basin).
            step = [d[0].clamp(-h, h), d[1]];
            let trial = [theta[0] + step[0], theta[1] + step[1]];
            let t = fine.linearize(trial, Some(&lin.used));
            if t.used.len() >= MIN_SAMPLES && t.rss / (t.used.len() as f64) < cost {
                theta = trial;
                lambda = (lambda / 10.0).max(1e-12);
                improved = true;
                break;
            }
            lambda *= 10.0;
        }
        lin = fine.linearize(theta, None);
        if !improved || (step[0].abs() < 1e-9 && step[1].abs() < 1e-12) {
            break;
        }
    }
    (theta, lin)
}

/// Lag-1 correlation of consecutive residual vectors (0..0.995).
fn residual_correlation(lin: &Linear) -> f64 {
    let mut num = 0.0;
    for (w, idx) in lin.residuals.windows(2).zip(lin.used.windows(2)) {
        if idx[1] == idx[0] + 1 {
            num += dot(w[0], w[1]);
        }
    }
    if lin.rss > 0.0 {
        (num / lin.rss).clamp(0.0, 0.995)
    } else {
        0.0
    }
}
