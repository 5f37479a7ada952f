//! Physical simulator of an 8-string Scalable-SPIDAR and an optical tracker.
//!
//! A [`SimulatedDevice`] is one device as built: true anchors (a few mm off the
//! design), true home (the built-in initialization is a few cm off), true
//! pulleys (shared machining error) on which the string winds in level
//! layers (the winding radius shrinks linearly as string is paid out), the
//! true room-from-device transform of the tracker (small rotation, eq. 6
//! translation), the paper's abnormal motor, and any injected effects
//! ([`effects`]). [`simulate_session`] moves the end-effector along a path
//! ([`SessionKind`]) and records one [`Sample`] per
//! capture: quantized encoder counts from the true winding law, commanded
//! tensions, the tracker position (noisy, sometimes occluded) and what a
//! legacy controller would report.
//!
//! The same device gives a train and a test session with the same as-built
//! errors: build it once, call [`simulate_session`] twice with other seeds.
//!
//! `spidar simulate` ([`run_simulate`]) writes `geometry.toml` (the NOMINAL
//! geometry, never the true one), the session CSV and `truth.toml` (the true
//! parameters, for tests and benchmarks only).

pub mod config;
pub mod effects;
pub mod lattice;
mod legacy;
pub mod measure;
pub mod operator;
pub mod physics;
pub mod plant;
pub mod simulated_device;
pub mod tracker;
mod tracker_noise;
mod trajectory;
pub mod truth;
pub mod virtual_device;

use std::path::PathBuf;

use rand::RngExt;
use spidar_core::model::{StringInputs, Vec3};
use spidar_core::string_law::{cos2_inclinations, guide_elevations};
use spidar_core::STRINGS;

pub use config::SimConfig;
pub use effects::{parse_effect, parse_effects, InjectedEffect};
pub use lattice::{Lattice, LatticeError};
pub use simulated_device::SimulatedDevice;
pub use truth::Truth;

use crate::data::dataset::{DatasetError, Sample, Session};
use simulated_device::stream;
use spidar_core::geometry::{dot, norm, sub};

/// Any failure of the simulator; each names the file, field or string concerned.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{}: {action}: {source}", file.display())]
    Io {
        file: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
    /// The configuration TOML does not parse (the message names the key and line).
    #[error("{}: {message}", file.display())]
    ConfigFile { file: PathBuf, message: String },
    #[error("simulator configuration: {0}")]
    Config(#[from] crate::ConfigError),
    #[error("effect `{spec}`: {problem}")]
    EffectSpec { spec: String, problem: String },
    #[error("string {string}: its pulley would run empty at a length of {length_mm:.1} mm (t = {t_s} s)")]
    StringExhausted {
        string: usize,
        length_mm: f64,
        t_s: f64,
    },
    #[error("string {string}: the injected effects are too strong to solve for the encoder angle (t = {t_s} s)")]
    NoConvergence { string: usize, t_s: f64 },
    #[error("{0}")]
    Dataset(#[from] DatasetError),
}

/// Which path the end-effector follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SessionKind {
    /// The paper's lattice protocol (`[lattice]` of the configuration):
    /// 13^3 = 2197 cells over a 1 m cube, plane by plane from the front.
    Lattice,
    /// Random trajectories of sequential points through the same volume.
    Random { points: usize },
    /// A stream of the independent simulator (`[stream]` of its
    /// configuration): `rows` captures at `stream.rate_hz` of a continuous
    /// path at about `stream.speed_mm_s`, over the training part of the
    /// workspace or the whole of it.
    Stream { rows: usize, area: StreamArea },
}

/// Where a stream goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StreamArea {
    /// The central part of the workspace a training session covers
    /// (`stream.training_span` of each side).
    Training,
    /// The whole workspace (`stream.area_mm`): a test session that reaches
    /// beyond the training area.
    Whole,
}

impl SessionKind {
    /// Default file stem of the session.
    pub fn name(&self) -> &'static str {
        match self {
            SessionKind::Lattice => "lattice",
            SessionKind::Random { .. } => "random",
            SessionKind::Stream {
                area: StreamArea::Training,
                ..
            } => "stream",
            SessionKind::Stream {
                area: StreamArea::Whole,
                ..
            } => "wide-stream",
        }
    }
}

/// What really happened at one capture (for tests and benchmarks).
#[derive(Clone, Debug, PartialEq)]
pub struct SampleTruth {
    /// True end-effector position, device frame, mm.
    pub device_mm: Vec3<f64>,
    /// True marker position, room (tracker) frame, mm.
    pub room_mm: Vec3<f64>,
    /// True velocity, device frame, mm/s.
    pub velocity_device_mm_s: Vec3<f64>,
    /// True geometric string lengths `|p - anchor_i|`, mm.
    pub lengths_mm: [f64; STRINGS],
    /// `dL_i/dt`, mm/s.
    pub string_speed_mm_s: [f64; STRINGS],
    /// The string-law inputs with the TRUE direction of motion of each string.
    pub inputs: StringInputs,
    /// Length error of the abnormal motor at this capture (0 outside its region), mm.
    pub abnormal_mm: f64,
    /// Lattice cell `[ix, iy, iz]` (lattice sessions).
    pub cell: Option<[u32; 3]>,
}

/// A model-simulator device of `seed` with `effects` injected, its lattice
/// (session seed `seed + 100`) and a `points`-point random test session
/// (`seed + 200`): the loop's benchmark and tests run on these.
pub fn device_with_lattice_and_test(
    seed: u64,
    effects: &[&str],
    points: usize,
) -> Result<(SimulatedDevice, Session, Session), SimError> {
    let config = SimConfig {
        effects: effects.iter().map(|s| s.to_string()).collect(),
        ..SimConfig::default()
    };
    let device = SimulatedDevice::new(&config, seed)?;
    let lattice = simulate_session(&device, SessionKind::Lattice, seed + 100)?;
    let test = simulate_session(&device, SessionKind::Random { points }, seed + 200)?;
    Ok((device, lattice, test))
}

/// How long after an earlier session of the same home capture a session
/// that continues it starts (s): the operator takes a minute between them.
pub const CONTINUATION_GAP_S: f64 = 60.0;

/// A session of `device` that continues `earlier` under the same home
/// capture, [`CONTINUATION_GAP_S`] after its last row: its clock goes on,
/// so the effects that read the time since home (a slip that happened, a
/// drift) are in it as they were at the end of `earlier`.
pub fn simulate_session_after(
    device: &SimulatedDevice,
    kind: SessionKind,
    seed: u64,
    earlier: &Session,
) -> Result<(Session, Vec<SampleTruth>), SimError> {
    let start_s = earlier.samples.last().map_or(0.0, |s| s.t_s) + CONTINUATION_GAP_S;
    simulate_session_from(device, kind, seed, start_s)
}

/// Simulate one session of `device` (see [`simulate_session_with_truth`]).
pub fn simulate_session(
    device: &SimulatedDevice,
    kind: SessionKind,
    seed: u64,
) -> Result<Session, SimError> {
    simulate_session_with_truth(device, kind, seed).map(|(s, _)| s)
}

fn round_to(x: f64, per_unit: f64) -> f64 {
    (x * per_unit).round() / per_unit
}

/// Simulate one session of `device`; `seed` draws the path, the tensions,
/// the tracker noise, the occlusions and the abnormal motor's jitter (each
/// from its own stream). Times are whole milliseconds, tensions whole
/// millinewtons, positions whole micrometres, as written to the CSV.
pub fn simulate_session_with_truth(
    device: &SimulatedDevice,
    kind: SessionKind,
    seed: u64,
) -> Result<(Session, Vec<SampleTruth>), SimError> {
    simulate_session_from(device, kind, seed, 0.0)
}

/// [`simulate_session_with_truth`] of a session whose clock starts
/// `start_s` after the home capture.
fn simulate_session_from(
    device: &SimulatedDevice,
    kind: SessionKind,
    seed: u64,
    start_s: f64,
) -> Result<(Session, Vec<SampleTruth>), SimError> {
    let cfg = &device.config;
    let centre = device.volume_centre_room();
    let start = device.room_from_device(&device.frame.home);
    let mut path_rng = stream(seed, 10);
    let captures = trajectory::captures(
        kind,
        &cfg.lattice,
        &cfg.random,
        &cfg.tracker,
        centre,
        start,
        &mut path_rng,
    )?;

    let captures = trajectory::starting_at(captures, start_s)?;
    let mut session = ModelSession::new(device, seed)?;
    let captures = onto_the_plane(device, captures);
    let mut samples = Vec::with_capacity(captures.len());
    let mut truths = Vec::with_capacity(captures.len());
    for c in &captures {
        let (sample, truth) = session.capture(c, &captures)?;
        samples.push(sample);
        truths.push(truth);
    }
    Ok((
        Session {
            strings: device.frame.layout.count(),
            samples,
            ignored_columns: Vec::new(),
            unread_columns: Vec::new(),
            tracker_z: true,
        },
        truths,
    ))
}

/// A planar device's end-effector moves in the anchors' plane: the path
/// is projected onto it (a 3-D device's path as it is).
fn onto_the_plane(
    device: &SimulatedDevice,
    captures: Vec<trajectory::Capture>,
) -> Vec<trajectory::Capture> {
    if !device.frame.layout.planar {
        return captures;
    }
    let plane_z = device.frame.anchors[0][2];
    captures
        .into_iter()
        .map(|mut c| {
            let mut p = device.device_from_room(&c.room);
            p[2] = plane_z;
            let mut v = device.device_velocity_from_room(&c.velocity);
            v[2] = 0.0;
            c.room = device.room_from_device(&p);
            c.velocity = device.room_velocity_from_device(&v);
            c
        })
        .collect()
}

/// Where the marker was `offset_s` before `t_s` (linear between captures;
/// None before the first).
fn marker_at(captures: &[trajectory::Capture], offset_s: f64, t_s: f64) -> Option<Vec3<f64>> {
    let t = t_s - offset_s;
    let k = captures.partition_point(|c| f64::from(c.t_ms) / 1000.0 <= t);
    if k == 0 || k > captures.len() {
        return None;
    }
    let a = &captures[k - 1];
    let ta = f64::from(a.t_ms) / 1000.0;
    match captures.get(k) {
        Some(b) => {
            let tb = f64::from(b.t_ms) / 1000.0;
            let f = if tb > ta { (t - ta) / (tb - ta) } else { 0.0 };
            Some(core::array::from_fn(|i| {
                a.room[i] + f * (b.room[i] - a.room[i])
            }))
        }
        None => (t == ta).then_some(a.room),
    }
}

/// One session of the model simulator under way: each part of the world's
/// own random stream, the legacy controller, and what carries over from one
/// capture to the next (each string's direction of motion, the tracker's
/// occlusion).
struct ModelSession<'a> {
    device: &'a SimulatedDevice,
    tension_rng: rand::rngs::ChaCha8Rng,
    noise_rng: rand::rngs::ChaCha8Rng,
    occlusion_rng: rand::rngs::ChaCha8Rng,
    abnormal_rng: rand::rngs::ChaCha8Rng,
    noise: tracker_noise::TrackerNoise,
    legacy: legacy::LegacyController,
    direction: [i8; STRINGS],
    occluded: bool,
}

/// Every string at one capture.
struct StringReadings {
    counts: [i32; STRINGS],
    /// True geometric lengths, mm.
    lengths: [f64; STRINGS],
    /// `dL_i/dt`, mm/s.
    speeds: [f64; STRINGS],
    /// Length error of the abnormal motor, mm.
    abnormal_mm: f64,
}

impl<'a> ModelSession<'a> {
    /// The streams of the session `seed` (11..14).
    fn new(device: &'a SimulatedDevice, seed: u64) -> Result<ModelSession<'a>, SimError> {
        let cfg = &device.config;
        let tension_rng = stream(seed, 11);
        let noise_rng = stream(seed, 12);
        let occlusion_rng = stream(seed, 13);
        let abnormal_rng = stream(seed, 14);
        let noise = tracker_noise::TrackerNoise::new(&cfg.tracker, stream(seed, 15))?;
        let legacy = legacy::LegacyController::new(&device.nominal);
        Ok(ModelSession {
            device,
            tension_rng,
            noise_rng,
            occlusion_rng,
            abnormal_rng,
            noise,
            legacy,
            direction: [0i8; STRINGS],
            occluded: false,
        })
    }

    /// One capture `c` of the session's `captures`: the commanded tensions,
    /// the encoders, the tracker and the legacy controller's position.
    fn capture(
        &mut self,
        c: &trajectory::Capture,
        captures: &[trajectory::Capture],
    ) -> Result<(Sample, SampleTruth), SimError> {
        let device = self.device;
        let cfg = &device.config;
        let t_s = f64::from(c.t_ms) / 1000.0;
        let p = device.device_from_room(&c.room);
        let v = device.device_velocity_from_room(&c.velocity);
        let tension_mn = self.draw_tension_mn();
        let strings = self.read_encoders(&p, &v, &tension_mn, t_s)?;
        let counts = strings.counts;
        let tracker = self.track(c, captures, t_s);

        let legacy_position = if cfg.legacy.enabled {
            self.legacy
                .position(&counts)
                .map(|q| q.map(|x| round_to(x, 1000.0)))
        } else {
            None
        };

        let sample = Sample {
            t_s,
            counts,
            tracker,
            orientation: None,
            legacy: legacy_position,
            tension_n: Some(tension_mn.map(|t| f64::from(t) / 1000.0)),
            since_home_s: None,
            home: None,
        };
        let truth = SampleTruth {
            device_mm: p,
            room_mm: c.room,
            velocity_device_mm_s: v,
            lengths_mm: strings.lengths,
            string_speed_mm_s: strings.speeds,
            inputs: StringInputs {
                counts,
                direction: self.direction,
                tension_mn,
                time_ms: c.t_ms,
                cos2_inclination_q16: cos2_inclinations(&device.frame.anchors, &p),
                guide_elevation_q32: guide_elevations(
                    &device.frame.anchors,
                    &device.frame.home,
                    &p,
                ),
                // The truth has the string speeds (`string_speed_mm_s`); a
                // count rate is what the device or the host estimates.
                count_rate_cps: [0; STRINGS],
            },
            abnormal_mm: strings.abnormal_mm,
            cell: c.cell,
        };
        Ok((sample, truth))
    }

    /// The commanded tension of every channel, mN.
    fn draw_tension_mn(&mut self) -> [u16; STRINGS] {
        let ts = &self.device.config.tension;
        let rng = &mut self.tension_rng;
        core::array::from_fn(|_| {
            let mut t = ts.pretension_n + ts.jitter_n * rng.random_range(0.0..1.0);
            if rng.random_bool(ts.active_probability) {
                t += ts.active_max_n * rng.random_range(0.0..1.0);
            }
            (t * 1000.0).round().clamp(0.0, f64::from(u16::MAX)) as u16
        })
    }

    /// Every active string's encoder counts with the end-effector at `p`
    /// moving at `v` under `tension_mn` at `t_s`: the true length, its
    /// direction of motion, the injected speed effects, the abnormal motor
    /// and the string's conditions.
    fn read_encoders(
        &mut self,
        p: &Vec3<f64>,
        v: &Vec3<f64>,
        tension_mn: &[u16; STRINGS],
        t_s: f64,
    ) -> Result<StringReadings, SimError> {
        let device = self.device;
        let cfg = &device.config;
        let layout = device.frame.layout;
        let total_tension_n = spidar_core::string_law::total_tension_n(layout.active, tension_mn);
        let mut r = StringReadings {
            counts: [0i32; STRINGS],
            lengths: [0.0; STRINGS],
            speeds: [0.0; STRINGS],
            abnormal_mm: 0.0,
        };
        for i in layout.indices() {
            let to_anchor = sub(*p, device.frame.anchors[i]);
            let length = norm(to_anchor);
            let speed = if length > 0.0 {
                dot(*v, to_anchor) / length
            } else {
                0.0
            };
            if speed.abs() > 1e-9 {
                self.direction[i] = if speed > 0.0 { 1 } else { -1 };
            }
            let mut extra = 0.0;
            for e in &device.injected {
                if let InjectedEffect::Speed { string, latency_s } = *e {
                    if usize::from(string) == i {
                        extra += latency_s * speed;
                    }
                }
            }
            let am = &cfg.abnormal_motor;
            if am.enabled && usize::from(am.string) == i && length < am.region_length_mm {
                let spread = 1.0 - am.jitter * self.abnormal_rng.random_range(0.0..1.0);
                r.abnormal_mm = -(am.step_mm + am.gain * (am.region_length_mm - length)) * spread;
                extra += r.abnormal_mm;
            }
            let tension_n = f64::from(tension_mn[i]) / 1000.0;
            let conditions =
                device.conditions(i, p, self.direction[i], tension_n, total_tension_n, t_s);
            r.counts[i] = device.counts_for_length(i, length, extra, conditions)?;
            r.lengths[i] = length;
            r.speeds[i] = speed;
        }
        Ok(r)
    }

    /// The tracker's reading of the marker at capture `c` (noisy, whole
    /// micrometres; `tracker.clock_offset_s` late, and later by
    /// `tracker.clock_drift_ppm` each second), unless occluded.
    fn track(
        &mut self,
        c: &trajectory::Capture,
        captures: &[trajectory::Capture],
        t_s: f64,
    ) -> Option<Vec3<f64>> {
        let tr = &self.device.config.tracker;
        self.occluded = if self.occluded {
            !self.occlusion_rng.random_bool(1.0 / tr.occlusion_mean_rows)
        } else {
            self.occlusion_rng.random_bool(tr.occlusion_probability)
        };
        let offset_s = tr.clock_offset_s + 1e-6 * tr.clock_drift_ppm * t_s;
        let marker = if offset_s == 0.0 {
            Some(c.room)
        } else {
            marker_at(captures, offset_s, t_s)
        };
        let (noise, noise_rng) = (&mut self.noise, &mut self.noise_rng);
        let measured = marker.map(|m| -> Vec3<f64> {
            let offset = noise.offset(noise_rng);
            core::array::from_fn(|k| round_to(m[k] + offset[k], 1000.0))
        });
        measured.filter(|_| !self.occluded)
    }
}

/// What `spidar simulate` is asked for: which simulator, which device, which
/// session, and where to write them (the command line's `--` options).
#[derive(Clone, Debug)]
pub struct SimulateRequest {
    /// Output directory (created if missing).
    pub out: PathBuf,
    /// Device seed: the same seed gives the same device (as-built errors)
    /// whatever the session kind.
    pub seed: u64,
    /// Simulator configuration TOML (every key optional).
    pub config: Option<PathBuf>,
    /// A named device of the independent simulator instead of a
    /// configuration file ([`physics::PRESET_NAMES`]).
    pub preset: Option<String>,
    /// Path of the end-effector.
    pub kind: SessionPath,
    /// Number of captures of a random session or a stream (default:
    /// `random.points`, `stream.rows`).
    pub points: Option<usize>,
    /// Injected effects, `KIND:STRING:KEY=VALUE,...` (model simulator,
    /// [`effects::parse_effect`]) or `NAME[:KEY=VALUE,...]` (independent
    /// physics).
    pub effects: Vec<String>,
    /// File stem of the session CSV (default: `lattice` or `random`).
    pub name: Option<String>,
    /// Session seed (default: the device seed + 1 for lattice, + 2 for random).
    pub session_seed: Option<u64>,
    /// Which simulator.
    pub physics: Physics,
}

/// Which simulator makes a session.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Physics {
    /// The calibration model's own equations.
    #[default]
    Model,
    /// Other physics ([`physics`]): layered spools, guide pulleys, elastic
    /// sagging strings, frame flex, an offset marker.
    Independent,
}

/// The end-effector's path through a session, as asked for (a random
/// session's number of points comes with the request).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SessionPath {
    /// The paper's lattice.
    Lattice,
    /// Random test points.
    Random,
    /// A stream over the training part of the workspace (independent
    /// simulator).
    Stream,
    /// A stream over the whole workspace (independent simulator).
    WideStream,
}

/// What [`run_simulate`] wrote, and the legacy controller's raw error.
#[derive(Clone, Debug)]
pub struct SimulateReport {
    pub geometry: PathBuf,
    pub session: PathBuf,
    pub truth: PathBuf,
    pub rows: usize,
    pub occluded_rows: usize,
    /// Eq. 7 error of the legacy position (mapped to the room by eq. 6) against
    /// the tracker, over rows with both.
    pub legacy_raw_error: Option<crate::data::stats::ErrorStats>,
    /// What the user should know of the session written (a static session
    /// whose tracker clock is further off than its captures are apart).
    pub warnings: Vec<String>,
}

impl std::fmt::Display for SimulateReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "wrote {}", self.geometry.display())?;
        writeln!(
            f,
            "wrote {} ({} rows, {} occluded)",
            self.session.display(),
            self.rows,
            self.occluded_rows
        )?;
        writeln!(
            f,
            "wrote {} (ground truth: not for calibration)",
            self.truth.display()
        )?;
        if let Some(s) = &self.legacy_raw_error {
            writeln!(
                f,
                "legacy controller vs tracker (eq. 7): mean {:.1} mm, sd {:.1} mm, max {:.1} mm over {} rows",
                s.mean_mm, s.sd_mm, s.max_mm, s.n
            )?;
        }
        for w in &self.warnings {
            writeln!(f, "warning: {w}")?;
        }
        Ok(())
    }
}

/// Why a static session (a lattice, random points: one pose per row) of a
/// tracker whose clock is `tracker.clock_offset_s` (and its drift) off the
/// device's is not one to calibrate on, when that offset is more than half
/// the time between its captures: each row holds the marker where it was
/// that long before, at another pose, and `calibrate` aligns the clock of
/// streams only (a static session has no motion to align by).
fn static_clock_warning(
    kind: SessionKind,
    session: &Session,
    tracker: &config::TrackerConfig,
) -> Option<String> {
    if matches!(kind, SessionKind::Stream { .. }) {
        return None;
    }
    let end_s = session.samples.last()?.t_s;
    let offset_s = tracker
        .clock_offset_s
        .abs()
        .max((tracker.clock_offset_s + 1e-6 * tracker.clock_drift_ppm * end_s).abs());
    let interval_s =
        crate::procedures::calibrate::align::median_step_s(session.samples.iter().map(|s| s.t_s))?;
    (offset_s > interval_s / 2.0).then(|| {
        format!(
            "the tracker's clock is {offset_s:.2} s off the device's (`tracker.clock_offset_s`, \
             `clock_drift_ppm`), more than half the {interval_s:.2} s between this {} \
             session's captures: each row holds the marker where it was at another capture, and \
             `calibrate` aligns the clock of streams only; simulate a stream (`--kind stream` \
             or `wide-stream`), or a tracker whose clock agrees (`clock_offset_s = 0`)",
            kind.name()
        )
    })
}

/// Eq. 7 error of the legacy positions (eq. 6 to the room with the nominal
/// translation) against the tracker, over the rows that have both.
pub fn legacy_raw_errors(session: &Session, geometry: &crate::data::dataset::Geometry) -> Vec<f64> {
    let t = geometry.room_from_device_translation_mm;
    session
        .samples
        .iter()
        .filter_map(|s| {
            let (d, o) = (s.legacy?, s.tracker?);
            Some(crate::data::stats::position_error(
                [d[0] + t[0], d[1] + t[1], d[2] + t[2]],
                o,
            ))
        })
        .collect()
}

/// The session kind `args` ask for (`default_points`: the configuration's
/// `random.points`; `stream_rows`: its `stream.rows`, None for a simulator
/// without streams).
pub(crate) fn session_kind(
    args: &SimulateRequest,
    default_points: usize,
    stream_rows: Option<usize>,
) -> Result<SessionKind, SimError> {
    let stream = |area| match stream_rows {
        Some(rows) => Ok(SessionKind::Stream {
            rows: args.points.unwrap_or(rows),
            area,
        }),
        None => Err(SimError::Config(crate::ConfigError::new(
            "--kind",
            "a stream is a session of the independent simulator (--physics independent); \
             the model simulator's streams are random sessions with \
             random.capture_interval_s = 0.01",
        ))),
    };
    match args.kind {
        SessionPath::Stream => stream(StreamArea::Training),
        SessionPath::WideStream => stream(StreamArea::Whole),
        SessionPath::Lattice => match args.points {
            Some(_) => Err(SimError::Config(crate::ConfigError::new(
                "--points",
                "applies to --kind random only",
            ))),
            None => Ok(SessionKind::Lattice),
        },
        SessionPath::Random => Ok(SessionKind::Random {
            points: args.points.unwrap_or(default_points),
        }),
    }
}

/// The session seed of `args`: given, or the device seed + 1 (lattice),
/// + 2 (random), + 3 (stream) or + 4 (wide stream).
pub(crate) fn session_seed(args: &SimulateRequest, kind: SessionKind) -> u64 {
    args.session_seed.unwrap_or(match kind {
        SessionKind::Lattice => args.seed.wrapping_add(1),
        SessionKind::Random { .. } => args.seed.wrapping_add(2),
        SessionKind::Stream {
            area: StreamArea::Training,
            ..
        } => args.seed.wrapping_add(3),
        SessionKind::Stream {
            area: StreamArea::Whole,
            ..
        } => args.seed.wrapping_add(4),
    })
}

/// Writes what `spidar simulate` writes, for either simulator: the nominal
/// `geometry.toml`, the session CSV (`--name` or the kind's name) and
/// `truth.toml` (by `write_truth`).
pub(crate) fn write_outputs(
    args: &SimulateRequest,
    kind: SessionKind,
    nominal: &crate::data::dataset::Geometry,
    session: &Session,
    write_truth: impl FnOnce(&std::path::Path) -> Result<(), SimError>,
    legacy_raw_error: Option<crate::data::stats::ErrorStats>,
    tracker: &config::TrackerConfig,
) -> Result<SimulateReport, SimError> {
    std::fs::create_dir_all(&args.out).map_err(|source| SimError::Io {
        file: args.out.clone(),
        action: "cannot create the output directory",
        source,
    })?;
    let geometry = args.out.join("geometry.toml");
    nominal.write(&geometry)?;
    let stem = args.name.clone().unwrap_or_else(|| kind.name().to_string());
    let session_path = args.out.join(format!("{stem}.csv"));
    session.write(&session_path)?;
    let truth = args.out.join("truth.toml");
    write_truth(&truth)?;
    Ok(SimulateReport {
        geometry,
        session: session_path,
        truth,
        rows: session.samples.len(),
        occluded_rows: session
            .samples
            .iter()
            .filter(|s| s.tracker.is_none())
            .count(),
        legacy_raw_error,
        warnings: static_clock_warning(kind, session, tracker)
            .into_iter()
            .collect(),
    })
}

/// Run `spidar simulate`.
pub fn run_simulate(args: &SimulateRequest) -> Result<SimulateReport, SimError> {
    if args.physics == Physics::Independent {
        return physics::run_simulate(args);
    }
    if args.preset.is_some() {
        return Err(SimError::Config(crate::ConfigError::new(
            "--preset",
            "the presets are devices of the independent simulator: add --physics independent",
        )));
    }
    let mut config = match &args.config {
        Some(path) => SimConfig::load(path)?,
        None => SimConfig::default(),
    };
    config.effects.extend(args.effects.iter().cloned());
    let kind = session_kind(args, config.random.points, None)?;
    let device = SimulatedDevice::new(&config, args.seed)?;
    let session = simulate_session(&device, kind, session_seed(args, kind))?;
    let errors = legacy_raw_errors(&session, &device.nominal);
    write_outputs(
        args,
        kind,
        &device.nominal,
        &session,
        |truth| Truth::of(&device).write(truth),
        (!errors.is_empty()).then(|| crate::data::stats::ErrorStats::of(&errors)),
        &config.tracker,
    )
}
