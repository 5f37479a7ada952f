//! One session of the independent simulator, capture by capture: the
//! hand's path (lattice, random points or a stream), the commanded tensions,
//! the strings' slips and drift, the encoders' readings (with the abnormal
//! motor and the latency) and what the tracker sees on its own clock, each
//! from the session's own random streams.

use rand::rngs::ChaCha8Rng;
use rand::RngExt;
use rand_distr::Distribution;
use spidar_core::model::Vec3;

use super::build::uniform;
use super::{
    config, rows_to_session, PhysicsAbnormalMotor, PhysicsDevice, PhysicsEffect, PhysicsRow,
    PhysicsTruth, StreamConfig,
};
use crate::data::dataset::Session;
use crate::sim::simulated_device::{normal, stream};
use crate::sim::{trajectory, SessionKind, SimError, StreamArea};
use spidar_core::geometry::{mat_vec, rotation_from_vector};

/// The tracker's reading of the body's orientation: the room rotation after
/// the body's turn `omega` (device frame), then a measurement error `error`
/// (rotation vector, room frame), written as a tracker's rotation is
/// ([`crate::data::observe::orientation_of_rotation`]).
fn body_to_room_quaternion(
    room_rotation: &[[f64; 3]; 3],
    omega: &Vec3<f64>,
    error: &Vec3<f64>,
) -> Option<[f64; 4]> {
    use nalgebra::{Matrix3, Rotation3, Vector3};
    // The room rotation is one (drawn as an axis and an angle), taken as it
    // is: `from_matrix`'s search misses some exact half turns.
    let room = Rotation3::from_matrix_unchecked(Matrix3::from_fn(|r, c| room_rotation[r][c]));
    let body = Rotation3::new(Vector3::new(omega[0], omega[1], omega[2]));
    let noise = Rotation3::new(Vector3::new(error[0], error[1], error[2]));
    let m = (noise * room * body).into_inner();
    crate::data::observe::orientation_of_rotation(&core::array::from_fn(|r| {
        core::array::from_fn(|c| m[(r, c)])
    }))
}

fn round_to(x: f64, per_unit: f64) -> f64 {
    (x * per_unit).round() / per_unit
}

/// Slip events of a session: `(time s, string, mm)`.
fn slip_events(
    effects: &[PhysicsEffect],
    strings: usize,
    duration_s: f64,
    rng: &mut ChaCha8Rng,
) -> Vec<(f64, usize, f64)> {
    let mut events = Vec::new();
    for e in effects {
        if let PhysicsEffect::Slip { per_h, mm } = *e {
            if per_h <= 0.0 {
                continue;
            }
            let mut t = 0.0;
            loop {
                let u: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
                t += -u.ln() * 3600.0 / per_h;
                if t >= duration_s {
                    break;
                }
                let string = rng.random_range(0..strings);
                let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
                events.push((t, string, sign * mm * rng.random_range(0.5..=1.0)));
            }
        }
    }
    events
}

/// Simulate one session of `device`; `seed` draws the path, the tensions,
/// the posture jitter, the tracker noise, the occlusions, the slips and the
/// abnormal motor (each from its own stream). Times are whole
/// milliseconds, tensions whole millinewtons, positions whole micrometres.
pub fn simulate_session(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
) -> Result<(Session, Vec<PhysicsTruth>), SimError> {
    let (rows, truths) = simulate_rows(device, kind, seed)?;
    Ok((rows_to_session(rows)?, truths))
}

/// An earlier session of the same home capture, which a later one
/// continues ([`simulate_session_after`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EarlierSession {
    /// Its seed (its slip events are drawn again from it).
    pub seed: u64,
    /// Its last capture's time since home, s.
    pub end_s: f64,
}

/// A session that continues `earlier` under the same home capture, a
/// minute ([`crate::sim::CONTINUATION_GAP_S`]) after its last capture: its
/// clock goes on, and the earlier session's slips and drift stay in the
/// strings (its own slips add to them).
pub fn simulate_session_after(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
    earlier: EarlierSession,
) -> Result<(Session, Vec<PhysicsTruth>), SimError> {
    let (rows, truths) = simulate_rows_from(device, kind, seed, Some(earlier))?;
    Ok((rows_to_session(rows)?, truths))
}

/// [`simulate_session`] before the rows become a dataset session (any
/// number of strings).
pub fn simulate_rows(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
) -> Result<(Vec<PhysicsRow>, Vec<PhysicsTruth>), SimError> {
    simulate_rows_from(device, kind, seed, None)
}

/// [`simulate_rows`] of a session that starts at a home capture
/// (`earlier` None) or continues `earlier`.
fn simulate_rows_from(
    device: &PhysicsDevice,
    kind: SessionKind,
    seed: u64,
    earlier: Option<EarlierSession>,
) -> Result<(Vec<PhysicsRow>, Vec<PhysicsTruth>), SimError> {
    let cfg = &device.config;
    let centre = device.volume_centre_room();
    let home_omega = device.posture.rotation_vector(&device.home_mm);
    let start = device.room_from_device(&device.marker_of(&device.home_mm, &home_omega));
    let mut path_rng = stream(seed, 110);
    let captures = match kind {
        SessionKind::Stream { rows, area } => {
            config::stream_rows("stream rows (--points or stream.rows)", rows)?;
            trajectory::stream(
                &stream_path(&cfg.stream, rows, area),
                centre,
                start,
                &mut path_rng,
            )?
        }
        _ => trajectory::captures(
            kind,
            &cfg.lattice,
            &cfg.random,
            &cfg.tracker,
            centre,
            start,
            &mut path_rng,
        )?,
    };
    let duration_s = captures.last().map_or(0.0, |c| f64::from(c.t_ms) / 1000.0);
    let start_s = earlier.map_or(0.0, |e| e.end_s + crate::sim::CONTINUATION_GAP_S);
    let captures = crate::sim::trajectory::starting_at(captures, start_s)?;

    let mut session = PhysicsSession::new(device, seed, duration_s)?;
    if let Some(e) = earlier {
        session.continue_after(e, start_s);
    }
    // The hand's whole path first: the tracker, whose clock may run apart
    // from the device's, sees the marker where it was at another capture's time.
    let poses: Vec<HandPose> = captures.iter().map(|c| session.hand_pose(c)).collect();
    let tracker_clock = TrackerClock::new(&cfg.tracker, &captures, &poses);
    let mut rows = Vec::with_capacity(captures.len());
    let mut truths = Vec::with_capacity(captures.len());
    for (c, pose) in captures.iter().zip(&poses) {
        let seen = tracker_clock.seen(f64::from(c.t_ms) / 1000.0, pose);
        let (row, truth) = session.capture(c, pose, seen)?;
        rows.push(row);
        truths.push(truth);
    }
    Ok((rows, truths))
}

/// The path of a stream of `rows` captures over `area` of the workspace.
fn stream_path(cfg: &StreamConfig, rows: usize, area: StreamArea) -> trajectory::StreamPath {
    let span = match area {
        StreamArea::Training => cfg.training_span,
        StreamArea::Whole => 1.0,
    };
    trajectory::StreamPath {
        rows,
        rate_hz: cfg.rate_hz,
        speed_mm_s: cfg.speed_mm_s,
        half_extent_mm: cfg.area_mm.map(|x| x * span / 2.0),
    }
}

/// The tracker's clock against the device's: the row stamped `t` (device
/// time) holds the marker where it was at `t - offset`, with `offset =
/// tracker.clock_offset_s + 1e-6 tracker.clock_drift_ppm t` (as the model
/// simulator's tracker), between captures by linear interpolation.
struct TrackerClock<'a> {
    offset_s: f64,
    drift_ppm: f64,
    times_s: Vec<f64>,
    poses: &'a [HandPose],
}

/// What the tracker sees at one row: the marker (room frame, mm) and the
/// body's turn (rotation vector, device frame).
type Seen = (Vec3<f64>, Vec3<f64>);

impl<'a> TrackerClock<'a> {
    fn new(
        tracker: &crate::sim::config::TrackerConfig,
        captures: &[trajectory::Capture],
        poses: &'a [HandPose],
    ) -> TrackerClock<'a> {
        TrackerClock {
            offset_s: tracker.clock_offset_s,
            drift_ppm: tracker.clock_drift_ppm,
            times_s: captures
                .iter()
                .map(|c| f64::from(c.t_ms) / 1000.0)
                .collect(),
            poses,
        }
    }

    /// What the row at device time `t_s` (the hand at `pose`) holds; None
    /// before the session's first instant or after its last.
    fn seen(&self, t_s: f64, pose: &HandPose) -> Option<Seen> {
        let offset_s = self.offset_s + 1e-6 * self.drift_ppm * t_s;
        if offset_s == 0.0 {
            return Some((pose.marker_room, pose.omega));
        }
        let t = t_s - offset_s;
        let k = self.times_s.partition_point(|&s| s <= t);
        let a = &self.poses[k.checked_sub(1)?];
        let ta = self.times_s[k - 1];
        if ta == t {
            return Some((a.marker_room, a.omega));
        }
        let (b, tb) = (self.poses.get(k)?, self.times_s[k]);
        let f = (t - ta) / (tb - ta);
        let lerp = |x: &Vec3<f64>, y: &Vec3<f64>| -> Vec3<f64> {
            core::array::from_fn(|i| x[i] + f * (y[i] - x[i]))
        };
        Some((
            lerp(&a.marker_room, &b.marker_room),
            lerp(&a.omega, &b.omega),
        ))
    }
}

/// One session of the independent simulator under way: each part of the
/// world's own random stream, the session's slips and drift, and what
/// carries over from one capture to the next (the abnormal motor's state,
/// the tracker's occlusion).
struct PhysicsSession<'a> {
    device: &'a PhysicsDevice,
    tension_rng: ChaCha8Rng,
    noise_rng: ChaCha8Rng,
    occlusion_rng: ChaCha8Rng,
    posture_rng: ChaCha8Rng,
    orientation_rng: ChaCha8Rng,
    orientation_noise: rand_distr::Normal<f64>,
    noise: crate::sim::tracker_noise::TrackerNoise,
    jitter: rand_distr::Normal<f64>,
    /// `(time s, string, mm)`.
    slips: Vec<(f64, usize, f64)>,
    /// Each string's thermal strain per second (`drift-all`, `drift-each`).
    strain_per_s: Vec<f64>,
    /// Each string's encoder latency, s (`latency`).
    latency_s: Vec<f64>,
    abnormal: AbnormalMotor<'a>,
    occluded: bool,
}

/// The abnormal motor and its state: inside its region at the last capture,
/// off the groove since wound = `w0` on a radius `1 + g` larger, the counts
/// of the last capture (what a jammed encoder repeats).
struct AbnormalMotor<'a> {
    config: &'a PhysicsAbnormalMotor,
    /// Its string (None: disabled, or not on this device).
    string: Option<usize>,
    rng: ChaCha8Rng,
    in_region: bool,
    /// `(w0, g)`.
    off_groove: Option<(f64, f64)>,
    previous_counts: Option<Vec<i32>>,
}

/// Where the hand holds the end-effector at one capture.
struct HandPose {
    /// Strings' meeting point, device frame, mm.
    meeting: Vec3<f64>,
    /// The marker, room frame, mm.
    marker_room: Vec3<f64>,
    /// The end-effector's turn (rotation vector, device frame).
    omega: Vec3<f64>,
    /// The meeting point's velocity (device frame, mm/s): the marker's,
    /// the turn's rate left out.
    velocity: Vec3<f64>,
}

impl<'a> PhysicsSession<'a> {
    /// The streams of the session `seed` (111..117), its slips over
    /// `duration_s` and its drift.
    fn new(
        device: &'a PhysicsDevice,
        seed: u64,
        duration_s: f64,
    ) -> Result<PhysicsSession<'a>, SimError> {
        let cfg = &device.config;
        let n = device.string_count();
        let tension_rng = stream(seed, 111);
        let noise_rng = stream(seed, 112);
        let occlusion_rng = stream(seed, 113);
        let abnormal_rng = stream(seed, 114);
        let posture_rng = stream(seed, 115);
        let mut slip_rng = stream(seed, 116);
        let orientation_rng = stream(seed, 117);
        let orientation_noise = normal(
            "orientation.sigma_deg",
            cfg.orientation.sigma_deg.to_radians(),
        )?;
        let noise = crate::sim::tracker_noise::TrackerNoise::new(&cfg.tracker, stream(seed, 118))?;
        let jitter = normal("as_built.posture_jitter_deg", device.posture.jitter_rad)?;
        let slips = slip_events(&device.effects, n, duration_s, &mut slip_rng);
        let strain_per_s = (0..n).map(|i| device.string_creep_per_s(i)).collect();
        let latency_s = (0..n).map(|i| device.encoder_latency_s(i)).collect();
        let am = &cfg.abnormal_motor;
        let abnormal = AbnormalMotor {
            config: am,
            string: (am.enabled && usize::from(am.string) < n).then_some(usize::from(am.string)),
            rng: abnormal_rng,
            in_region: false,
            off_groove: None,
            previous_counts: None,
        };
        Ok(PhysicsSession {
            device,
            tension_rng,
            noise_rng,
            occlusion_rng,
            posture_rng,
            orientation_rng,
            orientation_noise,
            noise,
            jitter,
            slips,
            strain_per_s,
            latency_s,
            abnormal,
            occluded: false,
        })
    }

    /// This session continues `earlier` from `start_s`: the earlier
    /// session's slip events (drawn again from its seed) come first, this
    /// session's own move to its start.
    fn continue_after(&mut self, earlier: EarlierSession, start_s: f64) {
        let n = self.device.string_count();
        let mut slips = slip_events(
            &self.device.effects,
            n,
            earlier.end_s,
            &mut stream(earlier.seed, 116),
        );
        slips.extend(self.slips.iter().map(|&(t, i, mm)| (t + start_s, i, mm)));
        self.slips = slips;
    }

    /// One capture: the hand at `pose`, the commanded tensions, the
    /// encoders, the tracker (which sees `seen`).
    fn capture(
        &mut self,
        c: &trajectory::Capture,
        pose: &HandPose,
        seen: Option<Seen>,
    ) -> Result<(PhysicsRow, PhysicsTruth), SimError> {
        let n = self.device.string_count();
        let t_s = f64::from(c.t_ms) / 1000.0;
        let tension_n = self.draw_tensions();
        let mut truth = PhysicsTruth {
            meeting_mm: pose.meeting,
            carriage_turn_rad: pose.omega,
            attachment_mm: Vec::with_capacity(n),
            marker_room_mm: pose.marker_room,
            exit_mm: Vec::with_capacity(n),
            free_mm: Vec::with_capacity(n),
            geometric_mm: Vec::with_capacity(n),
            natural_mm: Vec::with_capacity(n),
            spool_rad: Vec::with_capacity(n),
            slipped_mm: Vec::with_capacity(n),
            abnormal: false,
            cell: c.cell,
        };
        let counts = self.read_encoders(pose, &tension_n, t_s, &mut truth)?;
        let (tracker, orientation) = self.track(seen);
        let row = PhysicsRow {
            t_s,
            counts,
            tracker,
            orientation,
            tension_n,
        };
        Ok((row, truth))
    }

    /// The hand at the capture's marker position: the end-effector turned
    /// with the posture (and its jitter), the strings' meeting point behind
    /// the marker.
    fn hand_pose(&mut self, c: &trajectory::Capture) -> HandPose {
        let device = self.device;
        let planar = device.nominal.layout.planar;
        let mut marker = device.device_from_room(&c.room);
        let mut omega = device.posture.rotation_vector(&marker);
        for w in omega.iter_mut() {
            *w += self.jitter.sample(&mut self.posture_rng);
        }
        if planar {
            omega[0] = 0.0;
            omega[1] = 0.0;
        }
        let o = mat_vec(&rotation_from_vector(omega), device.marker_body_mm);
        let mut meeting: Vec3<f64> = core::array::from_fn(|k| marker[k] - o[k]);
        if planar {
            // The strings meet in the plane; the marker is where the hand
            // holds it from there.
            meeting[2] = device.home_mm[2];
            marker = core::array::from_fn(|k| meeting[k] + o[k]);
        }
        // Not a round trip through the device frame unless the marker moved:
        // the 3-D sessions stay bit for bit what they were.
        let marker_room = if planar {
            device.room_from_device(&marker)
        } else {
            c.room
        };
        let mut velocity = device.device_from_room_vector(&c.velocity);
        if planar {
            velocity[2] = 0.0;
        }
        HandPose {
            meeting,
            marker_room,
            omega,
            velocity,
        }
    }

    /// The commanded tension of every string, whole millinewtons.
    fn draw_tensions(&mut self) -> Vec<f64> {
        let device = self.device;
        let ts = &device.config.tension;
        let rng = &mut self.tension_rng;
        (0..device.string_count())
            .map(|_| {
                let mut t = ts.pretension_n + ts.jitter_n * rng.random_range(0.0..1.0);
                if rng.random_bool(ts.active_probability) {
                    t += ts.active_max_n * rng.random_range(0.0..1.0);
                }
                round_to(t.clamp(0.0, 65.535), 1000.0)
            })
            .collect()
    }

    /// Every string's encoder counts with the hand at `pose` (each string
    /// tied where the pose puts its end) under `tension_n` at `t_s` (slips,
    /// drift and the abnormal motor included); what really happened goes to
    /// `truth`.
    fn read_encoders(
        &mut self,
        pose: &HandPose,
        tension_n: &[f64],
        t_s: f64,
        truth: &mut PhysicsTruth,
    ) -> Result<Vec<i32>, SimError> {
        let device = self.device;
        let n = device.string_count();
        let total_tension: f64 = tension_n.iter().sum();
        let mut counts = Vec::with_capacity(n);
        for (i, &tension) in tension_n.iter().enumerate() {
            // An encoder read late holds its string as it was then: the
            // meeting point back along its velocity (the tension and the
            // turn as now).
            let tau = self.latency_s[i];
            let meeting: Vec3<f64> =
                core::array::from_fn(|k| pose.meeting[k] - tau * pose.velocity[k]);
            let end = device.string_end(i, &meeting, &pose.omega);
            let strain = self.strain_per_s[i] * t_s;
            let state = device.natural_length(i, &end, tension, total_tension, strain)?;
            truth.attachment_mm.push(end);
            let slipped: f64 = self
                .slips
                .iter()
                .filter(|(at, s, _)| *s == i && *at <= t_s)
                .map(|(_, _, mm)| mm)
                .sum();
            truth.slipped_mm.push(slipped);
            let wound = device.strings[i].total_mm - slipped - state.natural_mm;
            let phi = device.spool_angle(i, wound).map_err(|e| at_time(e, t_s))?;
            let mut read_phi = phi;
            if let Some(off) =
                self.abnormal
                    .off_groove_angle(device, i, state.path.free_mm, wound, t_s)?
            {
                read_phi = off;
                truth.abnormal = true;
            }
            let mut k = device.counts_of(i, read_phi)?;
            if let Some(previous) = self.abnormal.jammed(i) {
                k = previous;
                truth.abnormal = true;
            }
            counts.push(k);
            truth.exit_mm.push(state.path.exit_mm);
            truth.free_mm.push(state.path.free_mm);
            truth.geometric_mm.push(state.geometric_mm);
            truth.natural_mm.push(state.natural_mm);
            truth.spool_rad.push(phi);
        }
        self.abnormal.previous_counts = Some(counts.clone());
        Ok(counts)
    }

    /// The tracker's reading of what it sees (the marker and the body's
    /// turn, [`TrackerClock::seen`]): the marker's position (noisy, whole
    /// micrometres) and the body's orientation, unless occluded or outside
    /// the tracker's recording.
    fn track(&mut self, seen: Option<Seen>) -> (Option<Vec3<f64>>, Option<[f64; 4]>) {
        let device = self.device;
        let cfg = &device.config;
        let tr = &cfg.tracker;
        self.occluded = if self.occluded {
            !self.occlusion_rng.random_bool(1.0 / tr.occlusion_mean_rows)
        } else {
            self.occlusion_rng.random_bool(tr.occlusion_probability)
        };
        let occluded = self.occluded;
        // Every draw is made whatever the tracker sees, so that the clock
        // changes nothing else.
        let (marker_room, omega) = seen.unwrap_or(([0.0; 3], [0.0; 3]));
        let offset = self.noise.offset(&mut self.noise_rng);
        let measured: Vec3<f64> =
            core::array::from_fn(|k| round_to(marker_room[k] + offset[k], 1000.0));
        // The body turns with the hand (`omega`, device frame); the tracker
        // reads its orientation in the room, with its own noise.
        let (orientation_noise, orientation_rng) =
            (&self.orientation_noise, &mut self.orientation_rng);
        let orientation = (cfg.orientation.enabled && !occluded)
            .then(|| {
                let err: [f64; 3] =
                    core::array::from_fn(|_| orientation_noise.sample(orientation_rng));
                body_to_room_quaternion(&device.room_rotation, &omega, &err)
            })
            .flatten()
            .filter(|_| seen.is_some());
        let visible = !occluded && seen.is_some();
        (visible.then_some(measured), orientation)
    }
}

impl AbnormalMotor<'_> {
    /// The spool angle the encoder of string `i` reads when the motor is
    /// off its groove (None: on the groove, or not the abnormal string);
    /// entering the region (free string shorter than its length) may throw
    /// the string off the groove, leaving it puts it back.
    fn off_groove_angle(
        &mut self,
        device: &PhysicsDevice,
        i: usize,
        free_mm: f64,
        wound: f64,
        t_s: f64,
    ) -> Result<Option<f64>, SimError> {
        if Some(i) != self.string {
            return Ok(None);
        }
        let am = self.config;
        let inside = free_mm < am.region_length_mm;
        if inside && !self.in_region {
            let rng = &mut self.rng;
            self.off_groove = rng
                .random_bool(am.out_of_groove_probability)
                .then(|| (wound, uniform(rng, am.radius_excess)));
        }
        if !inside {
            self.off_groove = None;
        }
        self.in_region = inside;
        if let Some((w0, g)) = self.off_groove {
            if wound > w0 {
                // Wound in off the groove, on a radius 1 + g larger:
                // the spool turned 1 + g times less.
                return device
                    .spool_angle(i, w0 + (wound - w0) / (1.0 + g))
                    .map(Some)
                    .map_err(|e| at_time(e, t_s));
            }
        }
        Ok(None)
    }

    /// The previous counts of string `i` when its spool jams at this
    /// capture (only the abnormal string, inside its region, after a first
    /// capture).
    fn jammed(&mut self, i: usize) -> Option<i32> {
        if Some(i) == self.string
            && self.in_region
            && self.rng.random_bool(self.config.jam_probability)
        {
            if let Some(prev) = &self.previous_counts {
                return Some(prev[i]);
            }
        }
        None
    }
}

fn at_time(e: SimError, t_s: f64) -> SimError {
    match e {
        SimError::Config(c) => SimError::Config(crate::ConfigError {
            problem: format!("{} (t = {t_s} s)", c.problem),
            ..c
        }),
        other => other,
    }
}
