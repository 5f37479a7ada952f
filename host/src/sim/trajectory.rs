//! Paths of the end-effector (room frame, the tracker's coordinates) and the
//! captures along them. Each capture carries the position and the velocity
//! of the hand at that instant; the path between two captures is a straight
//! segment travelled at that speed, so the direction of motion of every
//! string and its speed agree with the positions.

use rand::rngs::ChaCha8Rng;
use rand::RngExt;
use rand_distr::{Distribution, Exp1};
use spidar_core::model::Vec3;

use super::config::{LatticeConfig, RandomConfig, TrackerConfig};
use super::lattice::Lattice;
use super::SimError;
use spidar_core::geometry::{norm, sub};

/// One capture on the path.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Capture {
    /// Time since the session started (= since initialization), ms.
    pub t_ms: u32,
    /// True marker position, room frame, mm.
    pub room: Vec3<f64>,
    /// True marker velocity, room frame, mm/s.
    pub velocity: Vec3<f64>,
    /// Lattice cell `[ix, iy, iz]` of the capture (lattice sessions only).
    pub cell: Option<[u32; 3]>,
}

/// `captures` of a session whose clock starts `start_s` after the home
/// capture (0: at it).
pub(crate) fn starting_at(
    mut captures: Vec<Capture>,
    start_s: f64,
) -> Result<Vec<Capture>, SimError> {
    if start_s != 0.0 {
        let start_ms = to_ms(start_s)?;
        for c in &mut captures {
            c.t_ms = c.t_ms.checked_add(start_ms).ok_or_else(|| {
                SimError::Config(crate::ConfigError::new(
                    "session start",
                    format!("a session {start_s} s after home does not fit the 49-day counter"),
                ))
            })?;
        }
    }
    Ok(captures)
}

fn to_ms(t_s: f64) -> Result<u32, SimError> {
    let ms = (t_s * 1000.0).round();
    if !(0.0..=f64::from(u32::MAX)).contains(&ms) {
        return Err(SimError::Config(crate::ConfigError::new(
            "session duration",
            format!("{t_s} s does not fit the 49-day time-since-home counter"),
        )));
    }
    Ok(ms as u32)
}

/// Smallest `s` in `[0, 1]` with `p + s (q - p)` inside the box `[lo, hi]`
/// (`q` is inside the box).
fn entry_parameter(p: &Vec3<f64>, q: &Vec3<f64>, lo: &Vec3<f64>, hi: &Vec3<f64>) -> f64 {
    let mut s_in: f64 = 0.0;
    for k in 0..3 {
        let d = q[k] - p[k];
        if d > 0.0 && p[k] < lo[k] {
            s_in = s_in.max((lo[k] - p[k]) / d);
        } else if d < 0.0 && p[k] > hi[k] {
            s_in = s_in.max((hi[k] - p[k]) / d);
        }
    }
    s_in.clamp(0.0, 1.0)
}

/// The paper's lattice protocol ([`Lattice`], in its order): the user moves the marker, cell after cell,
/// towards a point near the highlighted cell's centre; the capture is taken
/// at the first tracker frame after the marker enters the cell, so it lies
/// inside the cell on the side the marker came from. Times are scaled to the
/// configured session duration with random pauses (searching the next cell).
pub(crate) fn lattice(
    cfg: &LatticeConfig,
    tracker: &TrackerConfig,
    centre: Vec3<f64>,
    start: Vec3<f64>,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Capture>, SimError> {
    let grid = Lattice::new(centre, cfg.size_mm, cfg.cells_per_axis).map_err(|e| {
        SimError::Config(crate::ConfigError::new(
            format!("lattice.{}", e.field),
            e.problem,
        ))
    })?;
    let cell = grid.cell_mm();
    let margin = (0.5f64).min(cell / 10.0);
    let frame_dt = 1.0 / tracker.frame_rate_hz;

    let mut previous = start;
    let mut points = Vec::new(); // (position, speed, travel time, cell)
    for c in grid.order() {
        let (lo, hi) = grid.bounds(c);
        let target: Vec3<f64> = core::array::from_fn(|k| {
            lo[k] + cell * (0.5 + cfg.target_jitter * rng.random_range(-1.0..=1.0))
        });
        let speed = rng.random_range(cfg.speed_mm_s[0]..=cfg.speed_mm_s[1]);
        let s = entry_parameter(&previous, &target, &lo, &hi);
        let d = sub(target, previous);
        let len = norm(d);
        let unit = if len > 0.0 {
            d.map(|x| x / len)
        } else {
            [0.0; 3]
        };
        // Marker travel between entering the cell and the next tracker frame.
        let depth = (margin + rng.random_range(0.0..1.0) * speed * frame_dt).min(len * (1.0 - s));
        let p: Vec3<f64> = core::array::from_fn(|k| {
            (previous[k] + s * d[k] + depth * unit[k]).clamp(lo[k] + margin, hi[k] - margin)
        });
        let travel = norm(sub(p, previous));
        points.push((p, speed, travel / speed, c, sub(p, previous)));
        previous = p;
    }

    let travel_total: f64 = points.iter().map(|p| p.2).sum();
    let pause_total = (cfg.duration_s - travel_total).max(0.0);
    let weights: Vec<f64> = points.iter().map(|_| Exp1.sample(rng)).collect();
    let weight_total: f64 = weights.iter().sum();

    let mut t = 0.0;
    let mut captures = Vec::with_capacity(points.len());
    for ((p, speed, travel_s, c, step), w) in points.into_iter().zip(weights) {
        t += travel_s + pause_total * w / weight_total.max(f64::MIN_POSITIVE);
        let len = norm(step);
        let velocity = if len > 0.0 {
            step.map(|x| x * speed / len)
        } else {
            [0.0; 3]
        };
        captures.push(Capture {
            t_ms: to_ms(t)?,
            room: p,
            velocity,
            cell: Some(c),
        });
    }
    Ok(captures)
}

/// Test sessions: the hand moves along straight legs between random
/// waypoints in the lattice's volume, each leg at its own speed; a capture is
/// taken every `capture_interval_s`.
pub(crate) fn random(
    cfg: &RandomConfig,
    lattice: &LatticeConfig,
    centre: Vec3<f64>,
    start: Vec3<f64>,
    points: usize,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Capture>, SimError> {
    let half = lattice.size_mm / 2.0;
    let waypoint = |rng: &mut ChaCha8Rng| -> Vec3<f64> {
        core::array::from_fn(|k| centre[k] + rng.random_range(-half..=half))
    };
    let mut from = start;
    let mut to = waypoint(rng);
    let mut speed = rng.random_range(cfg.speed_mm_s[0]..=cfg.speed_mm_s[1]);
    let mut leg_start_s = 0.0;
    let mut captures = Vec::with_capacity(points);
    for k in 1..=points {
        let t = k as f64 * cfg.capture_interval_s;
        let mut leg = sub(to, from);
        let mut len = norm(leg);
        while leg_start_s + len / speed < t {
            leg_start_s += len / speed;
            from = to;
            to = waypoint(rng);
            speed = rng.random_range(cfg.speed_mm_s[0]..=cfg.speed_mm_s[1]);
            leg = sub(to, from);
            len = norm(leg);
        }
        let unit = if len > 0.0 {
            leg.map(|x| x / len)
        } else {
            [0.0; 3]
        };
        let along = (t - leg_start_s) * speed;
        captures.push(Capture {
            t_ms: to_ms(t)?,
            room: core::array::from_fn(|i| from[i] + along * unit[i]),
            velocity: unit.map(|x| x * speed),
            cell: None,
        });
    }
    Ok(captures)
}

/// A stream's path: waypoints in a box, the hand's speed, the capture rate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct StreamPath {
    /// Captures.
    pub rows: usize,
    /// Captures per second.
    pub rate_hz: f64,
    /// Range of each leg's mean speed, mm/s.
    pub speed_mm_s: [f64; 2],
    /// Half the sides of the box the waypoints fill (room axes, centred on
    /// the volume's centre), mm.
    pub half_extent_mm: Vec3<f64>,
}

/// The hand's position and velocity a fraction `tau` (0..1) along a
/// minimum-jerk stroke from `from` to `to` that lasts `duration_s`: the
/// stroke a hand (or a trajectory planner) makes between two points,
/// starting and ending at rest, `s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5`.
fn minimum_jerk(
    from: &Vec3<f64>,
    to: &Vec3<f64>,
    duration_s: f64,
    tau: f64,
) -> (Vec3<f64>, Vec3<f64>) {
    let t2 = tau * tau;
    let s = t2 * tau * (10.0 - 15.0 * tau + 6.0 * t2);
    let ds = 30.0 * t2 * (1.0 - tau) * (1.0 - tau) / duration_s;
    let d = sub(*to, *from);
    (
        core::array::from_fn(|k| from[k] + s * d[k]),
        d.map(|x| x * ds),
    )
}

/// A stream (a dynamic session, captured at `rate_hz`): the hand moves from
/// waypoint to waypoint, random in the box `half_extent_mm` around
/// `centre`, each leg a minimum-jerk stroke at its own mean speed (drawn in
/// `speed_mm_s`), so position and velocity are continuous and the speed
/// rises and falls along every leg, as the speed profiles a clock alignment
/// compares need.
pub(crate) fn stream(
    path: &StreamPath,
    centre: Vec3<f64>,
    start: Vec3<f64>,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Capture>, SimError> {
    let h = path.half_extent_mm;
    let waypoint = |rng: &mut ChaCha8Rng| -> Vec3<f64> {
        core::array::from_fn(|k| centre[k] + rng.random_range(-h[k]..=h[k]))
    };
    let leg = |from: &Vec3<f64>, rng: &mut ChaCha8Rng| {
        let to = waypoint(rng);
        let speed = rng.random_range(path.speed_mm_s[0]..=path.speed_mm_s[1]);
        // A leg of (almost) no length still takes a frame: the hand pauses.
        let duration_s = (norm(sub(to, *from)) / speed).max(1.0 / path.rate_hz);
        (to, duration_s)
    };
    let mut from = start;
    let (mut to, mut duration_s) = leg(&from, rng);
    let mut leg_start_s = 0.0;
    let mut captures = Vec::with_capacity(path.rows);
    for k in 0..path.rows {
        // The pose at the time the row is stamped with (whole milliseconds).
        let t_ms = to_ms(k as f64 / path.rate_hz)?;
        let t = f64::from(t_ms) / 1000.0;
        while t > leg_start_s + duration_s {
            leg_start_s += duration_s;
            from = to;
            (to, duration_s) = leg(&from, rng);
        }
        let tau = ((t - leg_start_s) / duration_s).clamp(0.0, 1.0);
        let (room, velocity) = minimum_jerk(&from, &to, duration_s, tau);
        captures.push(Capture {
            t_ms,
            room,
            velocity,
            cell: None,
        });
    }
    Ok(captures)
}

/// The captures of a session of `kind` (both simulators' path): the
/// lattice protocol, or `points` random captures.
pub(crate) fn captures(
    kind: super::SessionKind,
    lattice_cfg: &LatticeConfig,
    random_cfg: &RandomConfig,
    tracker: &TrackerConfig,
    centre: Vec3<f64>,
    start: Vec3<f64>,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Capture>, SimError> {
    match kind {
        super::SessionKind::Lattice => lattice(lattice_cfg, tracker, centre, start, rng),
        super::SessionKind::Random { points: 0 } => Err(SimError::Config(crate::ConfigError::new(
            "random.points",
            "must be positive",
        ))),
        super::SessionKind::Random { points } => {
            random(random_cfg, lattice_cfg, centre, start, points, rng)
        }
        super::SessionKind::Stream { .. } => Err(SimError::Config(crate::ConfigError::new(
            "--kind",
            "a stream is a session of the independent simulator (--physics independent); \
             the model simulator's streams are random sessions with random.capture_interval_s \
             = 0.01",
        ))),
    }
}
