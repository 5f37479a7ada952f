//! The physical side of the virtual device: a simulated SPIDAR
//! ([`crate::sim::SimulatedDevice`]: true anchors, home, winding laws and injected
//! effects) whose end-effector follows a [`Trajectory`], motors whose string
//! tension follows the commanded tension with a first-order lag, and 16-bit
//! encoder counters that read the true string lengths (and wrap).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use spidar_core::STRINGS;

pub use crate::device::tracker::clock::SimClock;
use crate::sim::{InjectedEffect, SampleTruth, SimulatedDevice};
use spidar_core::geometry::{norm, sub};

/// A point of a [`Trajectory::Waypoints`] path.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Waypoint {
    /// Device time, µs since boot.
    pub t_us: u64,
    /// End-effector position, device frame, mm.
    pub device_mm: [f64; 3],
}

/// An end-effector in someone's hand (a simulated operator): whoever holds
/// the handle moves it ([`Hand::move_to`]); the plant reads its position at
/// every tick and writes back the net force the strings put on it
/// ([`Hand::string_force_n`]), which is what the holder feels. Clones share
/// the same hand.
///
/// **Simulated clock.** Free (as built), the plant reads wherever the hand
/// is when it ticks: the path then depends on how the host schedules the
/// two threads. Clocked ([`Hand::attach`]), the hand's path is a function
/// of simulated time (the plant's: device time since its first boot): the
/// holder commits the next point of a piecewise-linear path
/// ([`Hand::commit`]) and the plant does not tick past the last committed
/// point until the next one is there ([`Hand::wait_plant`] is the
/// holder's side). The plant's physics, the device's sample times and the
/// holder's captures then share one timeline whatever the host does, and
/// the truth at any simulated instant is well defined.
#[derive(Clone, Debug)]
pub struct Hand {
    inner: Arc<(Mutex<HandState>, Condvar)>,
    clock: SimClock,
}

/// A straight piece of a clocked hand's path: (µs, device mm) at each end.
type Segment = ((u64, [f64; 3]), (u64, [f64; 3]));

#[derive(Clone, Copy, Debug)]
struct HandState {
    device_mm: [f64; 3],
    force_n: [f64; 3],
    /// Committed path segment (from, to) while clocked.
    path: Option<Segment>,
    /// Simulated time of the plant's last tick, µs.
    plant_us: u64,
    /// The plant's counts (since its boot) at `plant_us`.
    plant_counts: [i32; STRINGS],
}

impl Hand {
    /// A hand holding the end-effector at `device_mm` (device frame, mm).
    pub fn at(device_mm: [f64; 3]) -> Hand {
        Hand {
            inner: Arc::new((
                Mutex::new(HandState {
                    device_mm,
                    force_n: [0.0; 3],
                    path: None,
                    plant_us: 0,
                    plant_counts: [0; STRINGS],
                }),
                Condvar::new(),
            )),
            clock: SimClock::default(),
        }
    }

    /// The simulated clock of the plant that reads this hand.
    pub fn clock(&self) -> SimClock {
        self.clock.clone()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HandState> {
        match self.inner.0.lock() {
            Ok(s) => s,
            Err(poisoned) => poisoned.into_inner(),
        }
    }

    fn state(&self) -> HandState {
        *self.lock()
    }

    fn update(&self, f: impl FnOnce(&mut HandState)) {
        f(&mut self.lock());
        self.inner.1.notify_all();
    }

    /// Where the end-effector is, device frame, mm (clocked: the last
    /// committed point).
    pub fn position_mm(&self) -> [f64; 3] {
        self.state().device_mm
    }

    /// Moves the end-effector to `device_mm` (device frame, mm) now (free
    /// hand).
    pub fn move_to(&self, device_mm: [f64; 3]) {
        self.update(|s| s.device_mm = device_mm);
    }

    /// Net force of the strings on the end-effector at the last tick, device
    /// frame, N: `sum_i tension_i (anchor_i - p) / |anchor_i - p|`.
    pub fn string_force_n(&self) -> [f64; 3] {
        self.state().force_n
    }

    fn set_string_force(&self, force_n: [f64; 3]) {
        self.update(|s| s.force_n = force_n);
    }

    /// Puts the hand on the simulated clock: the path starts where it is,
    /// at the plant's last tick, whose simulated time (µs) is returned.
    /// The plant waits for each next point from here on.
    pub fn attach(&self) -> u64 {
        let mut s = self.lock();
        let at = (s.plant_us, s.device_mm);
        s.path = Some((at, at));
        s.plant_us
    }

    /// Back to a free hand (the holder lets go): the plant no longer waits.
    pub fn detach(&self) {
        self.update(|s| {
            if let Some((_, to)) = s.path.take() {
                s.device_mm = to.1;
            }
        });
    }

    /// Commits the path's next point: the end-effector goes in a straight
    /// line from where it is at `from_us` (simulated µs; the end of the
    /// committed path) to `device_mm` at `to_us`.
    pub fn commit(&self, from_us: u64, to_us: u64, device_mm: [f64; 3]) {
        self.update(|s| {
            let from = match s.path {
                Some(p) => (from_us, segment_at(p, from_us)),
                None => (from_us, s.device_mm),
            };
            s.path = Some((from, (to_us.max(from_us), device_mm)));
            s.device_mm = device_mm;
        });
    }

    /// Waits until the plant has ticked at or past simulated time `t_us`
    /// (or `stop` is raised: `None`). Returns the plant's simulated time
    /// and its counts (since its boot) at that tick.
    pub fn wait_plant(&self, t_us: u64, stop: &AtomicBool) -> Option<(u64, [i32; STRINGS])> {
        let mut s = self.lock();
        while s.plant_us < t_us || self.clock.now_us() < t_us {
            if stop.load(Ordering::SeqCst) {
                return None;
            }
            s = match self.inner.1.wait_timeout(s, Duration::from_millis(20)) {
                Ok((g, _)) => g,
                Err(p) => p.into_inner().0,
            };
        }
        Some((s.plant_us, s.plant_counts))
    }

    /// The plant's side: the position at simulated time `t_us` (clocked:
    /// the committed path, clamped to its end; ask [`Hand::ready_until`]
    /// first).
    fn position_at_sim(&self, t_us: u64) -> [f64; 3] {
        let s = self.lock();
        match s.path {
            None => s.device_mm,
            Some(p) => segment_at(p, t_us),
        }
    }

    /// Simulated time of the plant's last tick, µs.
    pub fn plant_time_us(&self) -> u64 {
        self.lock().plant_us
    }

    /// Clocked: the simulated time up to which the path is committed (the
    /// plant must not tick past it); free: `None` (no limit).
    pub fn ready_until(&self) -> Option<u64> {
        self.lock().path.map(|p| (p.1).0)
    }

    fn note_tick(&self, t_us: u64, counts: [i32; STRINGS]) {
        self.update(|s| {
            s.plant_us = t_us;
            s.plant_counts = counts;
        });
    }

    /// The world has reached simulated time `t_us`: the clock moves there
    /// and whoever waits on the plant goes on.
    fn publish(&self, t_us: u64) {
        self.clock.set(t_us);
        self.update(|_| {});
    }
}

/// The point of a path segment at `t_us` (clamped to its ends).
fn segment_at(p: Segment, t_us: u64) -> [f64; 3] {
    let ((t0, a), (t1, b)) = p;
    if t_us <= t0 || t1 <= t0 {
        return if t_us >= t1 { b } else { a };
    }
    if t_us >= t1 {
        return b;
    }
    let w = (t_us - t0) as f64 / (t1 - t0) as f64;
    core::array::from_fn(|k| a[k] + w * (b[k] - a[k]))
}

impl PartialEq for Hand {
    /// The same hand (shared handle), not equal positions.
    fn eq(&self, other: &Hand) -> bool {
        Arc::ptr_eq(&self.inner, &other.inner)
    }
}

/// Where the end-effector is at each instant of device time (since boot; the
/// device boots with the end-effector at its true home, or where the
/// [`Hand`] holds it).
#[derive(Clone, Debug, PartialEq)]
pub enum Trajectory {
    /// Resting at home.
    Hold,
    /// Straight segments between waypoints (sorted by time), resting at the
    /// last one afterwards; before the first, between home and it.
    Waypoints(Vec<Waypoint>),
    /// A slow loop through home: `home + [r (cos wt - 1), r sin wt, r/3 sin 2wt]`.
    Orbit { radius_mm: f64, period_s: f64 },
    /// Wherever the hand holds it (device time plays no part).
    Held(Hand),
}

impl Trajectory {
    /// The path of a simulated session (its captures' true positions and
    /// times; sessions start at initialization, so times since home are
    /// device times).
    pub fn from_truth(truths: &[SampleTruth]) -> Trajectory {
        Trajectory::Waypoints(
            truths
                .iter()
                .map(|t| Waypoint {
                    t_us: u64::from(t.inputs.time_ms) * 1000,
                    device_mm: t.device_mm,
                })
                .collect(),
        )
    }

    /// Device time of the end of the path (None: endless or resting).
    pub fn end_us(&self) -> Option<u64> {
        match self {
            Trajectory::Waypoints(w) => w.last().map(|p| p.t_us),
            _ => None,
        }
    }

    /// End-effector position at `t_us`, device frame, mm.
    pub fn position_at(&self, home: [f64; 3], t_us: u64) -> [f64; 3] {
        match self {
            Trajectory::Hold => home,
            Trajectory::Held(hand) => hand.position_mm(),
            Trajectory::Orbit {
                radius_mm,
                period_s,
            } => {
                let period = if period_s.is_finite() && *period_s > 0.0 {
                    *period_s
                } else {
                    1.0
                };
                let w = 2.0 * std::f64::consts::PI / period * (t_us as f64 / 1e6);
                let r = *radius_mm;
                [
                    home[0] + r * (w.cos() - 1.0),
                    home[1] + r * w.sin(),
                    home[2] + r / 3.0 * (2.0 * w).sin(),
                ]
            }
            Trajectory::Waypoints(points) => {
                let after = points.partition_point(|p| p.t_us <= t_us);
                let (a, b) = match (after.checked_sub(1).map(|i| points[i]), points.get(after)) {
                    (None, None) => return home,
                    (Some(a), None) => return a.device_mm,
                    (None, Some(b)) => (
                        Waypoint {
                            t_us: 0,
                            device_mm: home,
                        },
                        *b,
                    ),
                    (Some(a), Some(b)) => (a, *b),
                };
                let span = b.t_us.saturating_sub(a.t_us);
                if span == 0 {
                    return b.device_mm;
                }
                let s = (t_us.saturating_sub(a.t_us)) as f64 / span as f64;
                core::array::from_fn(|k| a.device_mm[k] + s * (b.device_mm[k] - a.device_mm[k]))
            }
        }
    }
}

/// The plant: strings, end-effector, motors, encoders.
#[derive(Clone, Debug)]
pub struct Plant {
    pub device: SimulatedDevice,
    pub trajectory: Trajectory,
    /// Time constant of the motors' tension response, s.
    pub motor_tau_s: f64,
    /// Raw counter readings at home (the device's zero).
    pub raw_home: [u16; STRINGS],
    tension_n: [f64; STRINGS],
    direction: [i8; STRINGS],
    prev_length: Option<[f64; STRINGS]>,
    prev_t_us: u64,
    counts: [i32; STRINGS],
    /// Counts where the end-effector was at the last boot: the counters
    /// read `raw_home` there (zero unless a hand held it away from home).
    boot_counts: [i32; STRINGS],
    /// Simulated time at the last boot, µs: device time restarts at each
    /// boot, the simulated clock (a clocked [`Hand`]'s) does not.
    sim_epoch_us: u64,
    /// Device time (µs since this boot) at which the end-effector sets off
    /// on its trajectory; `None`: it rests at the trajectory's start until
    /// [`Plant::start_path`] (see [`Plant::rest_until_started`]).
    path_start_us: Option<u64>,
    error: Option<String>,
}

impl Plant {
    /// A plant at home, motors off; counters read `raw_home` there.
    pub fn new(device: SimulatedDevice, trajectory: Trajectory) -> Plant {
        Plant {
            device,
            trajectory,
            motor_tau_s: 0.002,
            raw_home: core::array::from_fn(|i| (40_000 + 1_000 * i) as u16),
            tension_n: [0.0; STRINGS],
            direction: [0; STRINGS],
            prev_length: None,
            prev_t_us: 0,
            counts: [0; STRINGS],
            boot_counts: [0; STRINGS],
            sim_epoch_us: 0,
            path_start_us: Some(0),
            error: None,
        }
    }

    /// Back to time 0, motors off (power cycle): a trajectory starts at
    /// home again, and sets off at once; a held end-effector stays where
    /// the hand holds it, and the counters read `raw_home` there (as a real
    /// controller's counters start wherever the strings are at power-on).
    pub fn reset(&mut self) {
        self.sim_epoch_us += self.prev_t_us;
        self.path_start_us = Some(0);
        self.tension_n = [0.0; STRINGS];
        self.direction = [0; STRINGS];
        self.prev_length = None;
        self.prev_t_us = 0;
        self.counts = [0; STRINGS];
        self.boot_counts = [0; STRINGS];
        if let Trajectory::Held(hand) = &self.trajectory {
            let p = hand.position_at_sim(self.sim_epoch_us);
            for i in self.device.frame.layout.indices() {
                let length = norm(sub(p, self.device.frame.anchors[i]));
                let conditions = self.device.conditions(i, &p, 0, 0.0, 0.0, 0.0);
                match self.device.counts_for_length(i, length, 0.0, conditions) {
                    Ok(c) => self.boot_counts[i] = c,
                    Err(e) => self.error = Some(e.to_string()),
                }
            }
            self.counts = self.boot_counts;
        }
    }

    /// Device time (µs since this boot) up to which the plant may tick: a
    /// clocked hand's committed path; `None`: no limit.
    pub fn ready_until_us(&self) -> Option<u64> {
        match &self.trajectory {
            Trajectory::Held(hand) => hand
                .ready_until()
                .map(|t| t.saturating_sub(self.sim_epoch_us)),
            _ => None,
        }
    }

    /// The simulated world has reached the last [`Plant::step`]: a held
    /// hand's [`SimClock`] moves to it (before the device's outputs of
    /// that tick are written, so that nothing arrives before its time).
    pub fn publish_tick(&self) {
        if let Trajectory::Held(hand) = &self.trajectory {
            hand.publish(self.sim_epoch_us + self.prev_t_us);
        }
    }

    /// The device is about to send a state stamped at the last
    /// [`Plant::step`]: a held hand's [`SimClock::last_sent_us`] moves
    /// there first (so that no state is read before it was sent).
    pub fn note_state_sent(&self) {
        if let Trajectory::Held(hand) = &self.trajectory {
            hand.clock.note_sent(self.sim_epoch_us + self.prev_t_us);
        }
    }

    /// Simulated time at this boot's device time 0, µs.
    pub fn sim_epoch_us(&self) -> u64 {
        self.sim_epoch_us
    }

    /// The end-effector rests at its trajectory's start (home, for every
    /// path but a session's that starts elsewhere) until
    /// [`Plant::start_path`]: as an operator holds it at home until the
    /// device has declared home there.
    pub fn rest_until_started(&mut self) {
        self.path_start_us = None;
    }

    /// The end-effector sets off on its trajectory at device time `t_us`
    /// (µs since this boot), unless it already has this boot.
    pub fn start_path(&mut self, t_us: u64) {
        self.path_start_us.get_or_insert(t_us);
    }

    /// Device time at which the end-effector set off on its trajectory this
    /// boot (`None`: it rests at the start).
    pub fn path_start_us(&self) -> Option<u64> {
        self.path_start_us
    }

    /// True end-effector position at `t_us`, device frame, mm.
    pub fn device_mm_at(&self, t_us: u64) -> [f64; 3] {
        self.device_mm_on_path(t_us, self.path_start_us)
    }

    /// True end-effector position at `t_us`, device frame, mm, had it set
    /// off on its trajectory at `path_start_us` (`None`: not yet).
    pub fn device_mm_on_path(&self, t_us: u64, path_start_us: Option<u64>) -> [f64; 3] {
        let path_us = path_start_us.map_or(0, |start| t_us.saturating_sub(start));
        self.trajectory.position_at(self.device.frame.home, path_us)
    }

    /// True end-effector position at `t_us`, room (tracker) frame, mm.
    pub fn room_mm_at(&self, t_us: u64) -> [f64; 3] {
        self.device.room_from_device(&self.device_mm_at(t_us))
    }

    /// Actual string tensions, N.
    pub fn tensions_n(&self) -> [f64; STRINGS] {
        self.tension_n
    }

    /// Why the last counts could not be computed (a pulley ran empty, ...).
    pub fn error(&self) -> Option<&str> {
        self.error.as_deref()
    }

    /// Advances to `t_us` with the motors commanded to `commanded_n` (0 when
    /// `enabled` is false) and returns the raw 16-bit counters.
    pub fn step(
        &mut self,
        t_us: u64,
        commanded_n: &[f32; STRINGS],
        enabled: bool,
    ) -> [u16; STRINGS] {
        let dt_s = t_us.saturating_sub(self.prev_t_us) as f64 / 1e6;
        let alpha = if self.motor_tau_s > 0.0 {
            1.0 - (-dt_s / self.motor_tau_s).exp()
        } else {
            1.0
        };
        for (t, c) in self.tension_n.iter_mut().zip(commanded_n) {
            let target = if enabled && c.is_finite() {
                f64::from(*c).max(0.0)
            } else {
                0.0
            };
            *t += (target - *t) * alpha;
        }
        let p = match &self.trajectory {
            Trajectory::Held(hand) => hand.position_at_sim(self.sim_epoch_us + t_us),
            _ => self.device_mm_at(t_us),
        };
        let t_s = t_us as f64 / 1e6;
        // Channels without a string (the frame's layout) keep their counter
        // still and pull nothing.
        let layout = self.device.frame.layout;
        let mut lengths = [0.0; STRINGS];
        for i in layout.indices() {
            lengths[i] = norm(sub(p, self.device.frame.anchors[i]));
        }
        for i in layout.indices() {
            let speed = match self.prev_length {
                Some(prev) if dt_s > 0.0 => (lengths[i] - prev[i]) / dt_s,
                _ => 0.0,
            };
            if speed.abs() * dt_s > 1e-9 {
                self.direction[i] = if speed > 0.0 { 1 } else { -1 };
            }
            let mut extra = 0.0;
            for e in &self.device.injected {
                if let InjectedEffect::Speed { string, latency_s } = *e {
                    if usize::from(string) == i {
                        extra += latency_s * speed;
                    }
                }
            }
            let am = &self.device.config.abnormal_motor;
            if am.enabled && usize::from(am.string) == i && lengths[i] < am.region_length_mm {
                // The session simulator draws the jitter; here its mean.
                let spread = 1.0 - am.jitter / 2.0;
                extra -= (am.step_mm + am.gain * (am.region_length_mm - lengths[i])) * spread;
            }
            let total_tension_n: f64 = self
                .device
                .frame
                .layout
                .indices()
                .map(|j| self.tension_n[j])
                .sum();
            let conditions = self.device.conditions(
                i,
                &p,
                self.direction[i],
                self.tension_n[i],
                total_tension_n,
                t_s,
            );
            match self
                .device
                .counts_for_length(i, lengths[i], extra, conditions)
            {
                Ok(c) => self.counts[i] = c,
                Err(e) => self.error = Some(e.to_string()),
            }
        }
        if let Trajectory::Held(hand) = &self.trajectory {
            let mut force = [0.0; 3];
            for (i, length) in lengths.iter().enumerate() {
                if *length > 0.0 {
                    let towards = sub(self.device.frame.anchors[i], p);
                    for k in 0..3 {
                        force[k] += self.tension_n[i] * towards[k] / length;
                    }
                }
            }
            hand.set_string_force(force);
            let counts = core::array::from_fn(|i| self.counts[i].wrapping_sub(self.boot_counts[i]));
            hand.note_tick(self.sim_epoch_us + t_us, counts);
        }
        self.prev_length = Some(lengths);
        self.prev_t_us = t_us;
        core::array::from_fn(|i| {
            let counts = self.counts[i].wrapping_sub(self.boot_counts[i]);
            (i32::from(self.raw_home[i]).wrapping_add(counts)) as u16
        })
    }
}
