//! A simulated operator: a hand on the virtual device's end-effector that
//! follows the cues of a procedure, and the optical tracker that watches its
//! marker.
//!
//! One thread, one step per tracker frame (`frame_rate_hz`, real time):
//! 1. read the latest [`Cues`] (what a person would see and hear);
//! 2. move the [`Hand`] (device frame):
//!    - a visible target (lattice collection): reach for it, speed
//!      `min(reach_speed, reach_gain * distance)`;
//!    - else, a beep at or above `hold_beep_hz` (the audio cue says "there"):
//!      hold still;
//!    - else, with [`FreeMotion::FollowForce`]: a pull the operator can feel
//!      (at least `feel_n`) is followed (`compliance * F`); a weaker one is
//!      resisted (a human arm is stiff for a few tenths of a newton) and,
//!      while it beeps, the operator searches by ear: keeps a direction while
//!      the pitch rises (compared over `listen` windows: nobody hears a 1 Hz
//!      change within one frame), turns to a random new one when it falls,
//!      at `search_speed * (1 - h)` (slower near the target). Near the
//!      target the force alone cannot finish the job: before home is
//!      declared the device renders its force with the geometry it has
//!      (homed centimetres off), so the pre-tensions leave a net force of a
//!      few tenths of a newton, as large as the cue's own pull there (the
//!      paper's "low sensitivity of the haptic device in small distance");
//!    - [`FreeMotion::Wander`]: from one random point to the next (someone
//!      using the device while runtime recalibration watches);
//!
//!    and tremor on top (`tremor_mm` per frame, Gaussian);
//! 3. send one DTrack2 datagram (`fr`, `ts`, `6d`) of the marker: the true
//!    room position of the end-effector (the simulated device's true
//!    room-from-device transform) plus tracker noise, with occlusion
//!    (empty `6d` record) and datagram loss at the configured rates.
//!
//! The virtual device's plant reads the hand at every tick and writes back
//! the string force, so the haptic cue the device renders is what moves the
//! hand: the loop is closed through the device's own control code.

use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};

use crate::device::cues::{Cues, SharedCues};
use crate::device::tracker::dtrack::{format_datagram, BodyPose, DtrackFrame};
use crate::device::tracker::ReadProgress;
use crate::device::tracker::TrackerError;
use crate::sim::virtual_device::Hand;
use crate::sim::SimulatedDevice;
use spidar_core::geometry::distance;

/// What the hand does when no target is shown and no beep says "hold".
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FreeMotion {
    /// Yield to the string force: `velocity = compliance * force`.
    FollowForce,
    /// Go from one random point to the next inside a box (device frame).
    Wander {
        centre_mm: [f64; 3],
        half_size_mm: f64,
        speed_mm_s: f64,
    },
    /// Stay put (tremor only).
    Still,
}

/// Settings of a [`SimOperator`].
#[derive(Clone, Debug, PartialEq)]
pub struct SimOperatorConfig {
    /// Where the tracker datagrams go (a loopback address).
    pub tracker: SocketAddr,
    pub frame_rate_hz: f64,
    /// DTrack body id of the marker.
    pub body_id: u32,
    /// The marker body's rotation body -> room the tracker reports
    /// (row-major, sent column-wise in the `6d` record as DTrack does); the
    /// hand holds it fixed. Not checked: a test may send one that is not a
    /// rotation.
    pub body_rotation: [[f64; 3]; 3],
    /// Tracker `ts` at simulated time 0 (the virtual device's first boot),
    /// s since midnight.
    pub ts_start_s: f64,
    /// How much faster the tracker's clock runs than the device's, parts
    /// per million (two crystals never agree).
    pub clock_drift_ppm: f64,
    /// Tracker noise, standard deviation per axis, mm.
    pub tracker_noise_mm: f64,
    /// Probability that a frame has the marker occluded.
    pub occlusion: f64,
    /// Probability that a datagram is lost.
    pub loss: f64,
    /// Probability that a frame's marker position is a glitch (a
    /// reflection, a swapped marker): thrown 50 to 300 mm in a random
    /// direction. Drawn from its own random stream, so that 0 leaves every
    /// other draw as it was.
    pub glitch: f64,
    /// Hand velocity per newton of string force it follows, mm/s/N.
    pub compliance_mm_s_per_n: f64,
    /// Weakest force the operator follows, N.
    pub feel_n: f64,
    /// Top speed toward a shown target, mm/s.
    pub reach_speed_mm_s: f64,
    /// Approach rate toward a shown target, 1/s (speed = gain x distance
    /// near it).
    pub reach_gain_per_s: f64,
    /// Beep frequency at and above which the hand holds still, Hz.
    pub hold_beep_hz: f32,
    /// Once holding, the hand moves again only when the beep falls this far
    /// below `hold_beep_hz` (a person does not chase every wobble), Hz.
    pub release_hz: f32,
    /// Speed of the search by ear far out (times `1 - h`), mm/s.
    pub search_speed_mm_s: f64,
    /// Slowest search speed, mm/s.
    pub search_min_speed_mm_s: f64,
    /// How long the operator listens before comparing pitches.
    pub listen: Duration,
    /// Tremor: Gaussian step per frame, per axis, mm.
    pub tremor_mm: f64,
    pub free_motion: FreeMotion,
    /// Stop after this long whatever happens.
    pub max_duration: Duration,
    pub seed: u64,
}

impl SimOperatorConfig {
    /// A steady operator and a clean 100 Hz tracker sending to `tracker`.
    pub fn new(tracker: SocketAddr) -> SimOperatorConfig {
        SimOperatorConfig {
            tracker,
            frame_rate_hz: 100.0,
            body_id: 0,
            body_rotation: crate::device::tracker::dtrack::IDENTITY,
            ts_start_s: 36_000.0,
            clock_drift_ppm: 30.0,
            tracker_noise_mm: 0.1,
            occlusion: 0.0,
            loss: 0.0,
            glitch: 0.0,
            compliance_mm_s_per_n: 40.0,
            feel_n: 0.4,
            reach_speed_mm_s: 600.0,
            reach_gain_per_s: 8.0,
            hold_beep_hz: 990.0,
            release_hz: 10.0,
            search_speed_mm_s: 60.0,
            search_min_speed_mm_s: 4.0,
            listen: Duration::from_millis(100),
            tremor_mm: 0.02,
            free_motion: FreeMotion::FollowForce,
            max_duration: Duration::from_secs(60),
            seed: 0,
        }
    }

    /// The tracker's `ts` of an instant of simulated time.
    pub fn tracker_ts_s(&self, sim_us: u64) -> f64 {
        self.ts_start_s + sim_us as f64 / 1e6 * (1.0 + self.clock_drift_ppm * 1e-6)
    }

    fn validate(&self) -> Result<(), TrackerError> {
        if !self.tracker.ip().is_loopback() {
            return Err(TrackerError::NotLoopback(self.tracker));
        }
        let bad = |field: &'static str, problem: String| {
            TrackerError::Config(crate::ConfigError::new(field, problem))
        };
        if !(self.frame_rate_hz.is_finite() && self.frame_rate_hz > 0.0) {
            return Err(bad(
                "frame_rate_hz",
                format!("{} is not a positive rate", self.frame_rate_hz),
            ));
        }
        for (field, p) in [
            ("occlusion", self.occlusion),
            ("loss", self.loss),
            ("glitch", self.glitch),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(bad(field, format!("{p} is not a probability")));
            }
        }
        for (field, v) in [
            ("tracker_noise_mm", self.tracker_noise_mm),
            ("compliance_mm_s_per_n", self.compliance_mm_s_per_n),
            ("feel_n", self.feel_n),
            ("reach_speed_mm_s", self.reach_speed_mm_s),
            ("reach_gain_per_s", self.reach_gain_per_s),
            ("tremor_mm", self.tremor_mm),
            ("search_speed_mm_s", self.search_speed_mm_s),
            ("search_min_speed_mm_s", self.search_min_speed_mm_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(field, format!("{v} is not a finite value >= 0")));
            }
        }
        if !(self.clock_drift_ppm.is_finite() && self.clock_drift_ppm.abs() < 1000.0) {
            return Err(bad(
                "clock_drift_ppm",
                format!("{} is not a drift within 1000 ppm", self.clock_drift_ppm),
            ));
        }
        if !self.ts_start_s.is_finite() {
            return Err(bad("ts_start_s", "not finite".into()));
        }
        Ok(())
    }
}

/// What the simulated operator did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SimOperatorReport {
    /// Tracker frames simulated (sent or lost).
    pub frames: u32,
    /// Datagrams sent.
    pub sent: u32,
    /// Frames with the marker occluded.
    pub occluded: u32,
    /// Frames sent with a glitch ([`SimOperatorConfig::glitch`]).
    pub glitches: u32,
    /// Path length of the hand, mm.
    pub path_mm: f64,
}

/// A history entry: where the hand was at a tracker frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HandSample {
    pub frame: u32,
    /// Host time of the frame.
    pub at: Instant,
    /// Capture time on the simulated clock (the plant's: device time since
    /// the virtual device's first boot), µs.
    pub t_us: u64,
    /// The tracker's stamp of the frame (`ts`, s).
    pub ts_s: f64,
    /// True marker position, room frame, mm.
    pub room_mm: [f64; 3],
    /// True end-effector position, device frame, mm.
    pub device_mm: [f64; 3],
    /// The plant's encoder counts since its boot at `t_us`: what a device
    /// state sampled at the capture instant reads (until a `Home`).
    pub counts: [i32; spidar_core::STRINGS],
}

/// A running simulated operator. Dropping it stops the thread.
pub struct SimOperator {
    stop: Arc<AtomicBool>,
    history: Arc<Mutex<Vec<HandSample>>>,
    thread: Option<JoinHandle<Result<SimOperatorReport, TrackerError>>>,
}

impl SimOperator {
    /// Starts the operator: it holds `hand` (the virtual device's
    /// end-effector, see [`crate::sim::virtual_device::Trajectory::Held`]) of the
    /// simulated `device` and reads its cues from `cues`.
    pub fn spawn(
        config: SimOperatorConfig,
        device: SimulatedDevice,
        hand: Hand,
        cues: SharedCues,
    ) -> Result<SimOperator, TrackerError> {
        Self::spawn_in_step(config, device, hand, cues, None)
    }

    /// [`SimOperator::spawn`], in step with the procedure: with `progress`
    /// (the receiver's [`crate::device::tracker::DtrackReceiver::progress`]),
    /// each frame is sent once the procedure has taken every frame sent
    /// before it, and the hand moves on (the simulated world goes past the
    /// frame's instant) once it has taken this one. The world waits for a
    /// procedure that has not read yet or said it is busy (refitting,
    /// flashing) as long as it takes; one that stops reading without
    /// saying so (finished) lets the world go one frame further per
    /// [`PROCEDURE_PATIENCE`]. The simulated world then waits for the host
    /// however the machine schedules it.
    pub fn spawn_in_step(
        config: SimOperatorConfig,
        device: SimulatedDevice,
        hand: Hand,
        cues: SharedCues,
        progress: Option<ReadProgress>,
    ) -> Result<SimOperator, TrackerError> {
        config.validate()?;
        let local = SocketAddr::from(([127, 0, 0, 1], 0));
        let socket = UdpSocket::bind(local).map_err(|source| TrackerError::Socket {
            action: "cannot bind",
            addr: local,
            source,
        })?;
        let stop = Arc::new(AtomicBool::new(false));
        let history = Arc::new(Mutex::new(Vec::new()));
        let (thread_stop, thread_history) = (stop.clone(), history.clone());
        let thread = std::thread::Builder::new()
            .name("sim-operator".into())
            .spawn(move || {
                let links = HostLinks {
                    socket: &socket,
                    stop: &thread_stop,
                    history: &thread_history,
                    progress: progress.as_ref(),
                };
                run(&config, &device, &hand, &cues, &links)
            })
            .map_err(|source| TrackerError::Socket {
                action: "cannot start the operator thread for",
                addr: local,
                source,
            })?;
        Ok(SimOperator {
            stop,
            history,
            thread: Some(thread),
        })
    }

    /// Where the hand was at every tracker frame so far (the truth a test
    /// compares with).
    pub fn history(&self) -> Vec<HandSample> {
        match self.history.lock() {
            Ok(h) => h.clone(),
            Err(poisoned) => poisoned.into_inner().clone(),
        }
    }

    /// The operator's thread has ended (stopped, out of time, or failed:
    /// [`SimOperator::stop`] says which).
    pub fn is_finished(&self) -> bool {
        self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Stops the operator and reports what it did.
    pub fn stop(mut self) -> Result<SimOperatorReport, TrackerError> {
        self.stop.store(true, Ordering::SeqCst);
        match self.thread.take() {
            Some(t) => t.join().map_err(|_| TrackerError::SenderPanicked)?,
            None => Ok(SimOperatorReport::default()),
        }
    }
}

impl Drop for SimOperator {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// What the operator remembers from frame to frame.
#[derive(Clone, Debug, Default)]
struct Memory {
    wander_goal: Option<[f64; 3]>,
    /// Search by ear: the direction kept, the pitches heard in the current
    /// window, the mean pitch of the previous window.
    search_dir: Option<[f64; 3]>,
    heard: Vec<f32>,
    previous_pitch: Option<f64>,
    holding: bool,
}

fn random_direction(rng: &mut ChaCha8Rng) -> [f64; 3] {
    loop {
        let v: [f64; 3] = core::array::from_fn(|_| 2.0 * rng.random::<f64>() - 1.0);
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if n > 0.1 && n <= 1.0 {
            return v.map(|x| x / n);
        }
    }
}

/// Velocity of the hand for these cues, device frame, mm/s.
fn velocity(
    config: &SimOperatorConfig,
    device: &SimulatedDevice,
    cues: &Cues,
    hand_mm: &[f64; 3],
    force_n: &[f64; 3],
    memory: &mut Memory,
    rng: &mut ChaCha8Rng,
) -> [f64; 3] {
    let toward = |goal: &[f64; 3], top: f64| -> [f64; 3] {
        let d = distance(*goal, *hand_mm);
        if d < 1e-9 {
            return [0.0; 3];
        }
        let speed = top.min(config.reach_gain_per_s * d);
        core::array::from_fn(|k| (goal[k] - hand_mm[k]) / d * speed)
    };
    if let Some(target) = cues.target_room_mm {
        return toward(&device.device_from_room(&target), config.reach_speed_mm_s);
    }
    let threshold = if memory.holding {
        config.hold_beep_hz - config.release_hz
    } else {
        config.hold_beep_hz
    };
    memory.holding = cues.beep_hz >= threshold;
    if memory.holding {
        memory.search_dir = None;
        memory.heard.clear();
        memory.previous_pitch = None;
        return [0.0; 3];
    }
    match config.free_motion {
        FreeMotion::FollowForce => {
            let felt = (force_n[0].powi(2) + force_n[1].powi(2) + force_n[2].powi(2)).sqrt();
            if felt >= config.feel_n || cues.beep_hz.is_nan() || cues.beep_hz <= 0.0 {
                memory.search_dir = None;
                memory.heard.clear();
                memory.previous_pitch = None;
                return force_n.map(|f| f * config.compliance_mm_s_per_n);
            }
            memory.heard.push(cues.beep_hz);
            let window = (config.listen.as_secs_f64() * config.frame_rate_hz).ceil() as usize;
            if memory.heard.len() >= window.max(1) {
                let pitch = memory.heard.iter().map(|&f| f64::from(f)).sum::<f64>()
                    / memory.heard.len() as f64;
                memory.heard.clear();
                let falling = memory.previous_pitch.is_some_and(|p| pitch < p);
                if falling || memory.search_dir.is_none() {
                    memory.search_dir = Some(random_direction(rng));
                }
                memory.previous_pitch = Some(pitch);
            }
            let h = f64::from(cues.beep_hz) / 1000.0;
            let speed = (config.search_speed_mm_s * (1.0 - h)).max(config.search_min_speed_mm_s);
            let dir = memory.search_dir.unwrap_or([0.0; 3]);
            dir.map(|x| speed * x)
        }
        FreeMotion::Still => [0.0; 3],
        FreeMotion::Wander {
            centre_mm,
            half_size_mm,
            speed_mm_s,
        } => {
            let goal = match memory.wander_goal {
                Some(g) if distance(g, *hand_mm) > 1.0 => g,
                _ => {
                    let g = core::array::from_fn(|k| {
                        centre_mm[k] + half_size_mm * (2.0 * rng.random::<f64>() - 1.0)
                    });
                    memory.wander_goal = Some(g);
                    g
                }
            };
            toward(&goal, speed_mm_s)
        }
    }
}

/// How long a simulated operator in step with a procedure waits for it to
/// take a frame before the world goes one frame on without it (wall time:
/// only a procedure that reads, then stops reading the tracker without
/// saying it is busy, waits this long; one that has not started or said
/// [`crate::device::tracker::TrackerSource::busy`] is waited for).
pub const PROCEDURE_PATIENCE: Duration = Duration::from_secs(1);

/// Waits until the procedure has taken `sent` frames (or `stop`, or
/// [`PROCEDURE_PATIENCE`] without progress while it is not busy).
fn wait_taken(progress: &ReadProgress, sent: u64, stop: &AtomicBool) {
    let mut last = progress.taken();
    let mut since = Instant::now();
    while last < sent && !stop.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_micros(100));
        let now = progress.taken();
        if now != last || progress.busy() {
            last = now;
            since = Instant::now();
        } else if since.elapsed() > PROCEDURE_PATIENCE {
            return;
        }
    }
}

/// What the operator's thread shares with the host side: the socket its
/// tracker frames go out on, the stop flag, the hand's history and (in step
/// with a procedure) the procedure's read progress.
struct HostLinks<'a> {
    socket: &'a UdpSocket,
    stop: &'a AtomicBool,
    history: &'a Mutex<Vec<HandSample>>,
    progress: Option<&'a ReadProgress>,
}

impl HostLinks<'_> {
    /// In step: wait until the procedure has taken `sent` frames.
    fn wait_in_step(&self, sent: u32) {
        if let Some(progress) = self.progress {
            wait_taken(progress, u64::from(sent), self.stop);
        }
    }
}

/// `N(0, sigma)` of the operator's `field` (a zero sigma: a tiny one).
fn operator_normal(field: &'static str, sigma: f64) -> Result<Normal<f64>, TrackerError> {
    Normal::new(0.0, sigma.max(1e-12))
        .map_err(|e| TrackerError::Config(crate::ConfigError::new(field, e.to_string())))
}

/// Send one DTrack2 datagram of the marker seen at `seen` (None: occluded,
/// an empty `6d` record), frame `frame` taken at `t_us`.
fn send_frame(
    config: &SimOperatorConfig,
    socket: &UdpSocket,
    frame: u32,
    t_us: u64,
    seen: Option<[f64; 3]>,
) -> Result<(), TrackerError> {
    let datagram = format_datagram(&DtrackFrame {
        frame,
        ts_s: Some(config.tracker_ts_s(t_us)),
        calibrated_bodies: Some(1),
        bodies: match seen {
            None => Vec::new(),
            Some(seen) => vec![BodyPose {
                rotation: Some(config.body_rotation),
                ..BodyPose::at(config.body_id, seen)
            }],
        },
        has_6d: true,
    });
    socket
        .send_to(datagram.as_bytes(), config.tracker)
        .map_err(|source| TrackerError::Socket {
            action: "cannot send to",
            addr: config.tracker,
            source,
        })?;
    Ok(())
}

/// The operator's thread: one step per tracker frame (see the module
/// documentation) until `stop` or `max_duration`.
fn run(
    config: &SimOperatorConfig,
    device: &SimulatedDevice,
    hand: &Hand,
    cues: &SharedCues,
    links: &HostLinks<'_>,
) -> Result<SimOperatorReport, TrackerError> {
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let mut glitches = ChaCha8Rng::seed_from_u64(config.seed ^ 0x6C17_C4E5);
    let noise = operator_normal("tracker_noise_mm", config.tracker_noise_mm)?;
    let tremor = operator_normal("tremor_mm", config.tremor_mm)?;
    let dt = 1.0 / config.frame_rate_hz;
    let dt_us = ((1e6 / config.frame_rate_hz).round() as u64).max(1);
    // On the simulated clock: the plant waits for each next point of the
    // hand's path, and each frame is taken at a simulated instant.
    struct Release<'a>(&'a Hand);
    impl Drop for Release<'_> {
        fn drop(&mut self) {
            self.0.detach();
        }
    }
    let t0_us = hand.attach();
    let _release = Release(hand);
    let max_us = config.max_duration.as_micros().min(u128::from(u64::MAX)) as u64;
    let mut report = SimOperatorReport::default();
    let mut memory = Memory::default();
    let mut k: u32 = 0;
    loop {
        let t_us = t0_us + u64::from(k) * dt_us;
        if links.stop.load(Ordering::SeqCst) || t_us - t0_us >= max_us {
            break;
        }
        // The plant has ticked at the frame's instant: the marker is where
        // the path says, the force is what the strings pulled with.
        let Some((_, counts)) = hand.wait_plant(t_us, links.stop) else {
            break;
        };
        let p = hand.position_mm();
        // 1: the tracker's frame of the marker at `t_us`.
        let room = device.room_from_device(&p);
        let frame = k.wrapping_add(1);
        if let Ok(mut h) = links.history.lock() {
            h.push(HandSample {
                frame,
                at: Instant::now(),
                t_us,
                ts_s: config.tracker_ts_s(t_us),
                room_mm: room,
                device_mm: p,
                counts,
            });
        }
        let occluded = rng.random::<f64>() < config.occlusion;
        let lost = rng.random::<f64>() < config.loss;
        report.frames += 1;
        if occluded {
            report.occluded += 1;
        }
        if !lost {
            // In step: the procedure has read everything sent so far.
            links.wait_in_step(report.sent);
            let mut seen = room.map(|x| x + noise.sample(&mut rng));
            if config.glitch > 0.0 && glitches.random::<f64>() < config.glitch {
                let d: [f64; 3] = core::array::from_fn(|_| glitches.random::<f64>() - 0.5);
                let size = glitches.random_range(50.0..300.0) / distance(d, [0.0; 3]).max(1e-9);
                seen = core::array::from_fn(|k| seen[k] + size * d[k]);
                report.glitches += 1;
            }
            send_frame(
                config,
                links.socket,
                frame,
                t_us,
                (!occluded).then_some(seen),
            )?;
            report.sent += 1;
            // ... and this frame, read at its own instant.
            links.wait_in_step(report.sent);
        }
        // 2-3: cues, then the hand's next point, one frame on.
        // The procedure's answer to the frames before this one (a cue it
        // shows while working on this frame comes one frame later: a
        // 1/frame_rate reaction, the same whatever the machine does).
        let shown = cues.shown_before(u64::from(report.sent));
        let v = velocity(
            config,
            device,
            &shown,
            &p,
            &hand.string_force_n(),
            &mut memory,
            &mut rng,
        );
        let next: [f64; 3] = core::array::from_fn(|i| p[i] + v[i] * dt + tremor.sample(&mut rng));
        report.path_mm += distance(next, p);
        hand.commit(t_us, t_us + dt_us, next);
        k = k.wrapping_add(1);
    }
    Ok(report)
}

/// Why a simulated rig could not start.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    #[error("simulated rig: {0}")]
    Sim(#[from] crate::sim::SimError),
    #[error("simulated rig: {0}")]
    Device(#[from] crate::sim::virtual_device::VirtualDeviceError),
    #[error("simulated rig: {0}")]
    Tracker(#[from] TrackerError),
}

/// Everything a procedure needs on the simulated side: a virtual device
/// whose end-effector is in a simulated operator's hand, the operator (who
/// is also the tracker), and a DTrack2 receiver on loopback that the
/// procedure reads. Used by the `--simulate` option of the operator
/// commands and by their tests.
pub struct SimulatedRig {
    pub device: SimulatedDevice,
    pub hand: Hand,
    pub cues: SharedCues,
    pub virtual_device: crate::sim::virtual_device::VirtualDevice,
    pub receiver: crate::device::tracker::DtrackReceiver,
    pub operator: SimOperator,
}

impl SimulatedRig {
    /// Starts the rig: `device` as built, the end-effector at its true home
    /// plus `offset_mm` (device frame; where the built-in homing left it),
    /// the operator configured by `configure` (its tracker address is the
    /// receiver's), the virtual device in virtual time ([`Pace::Virtual`]:
    /// the world goes as far as the operator has moved the hand, and the
    /// operator waits for the procedure to take each tracker frame).
    ///
    /// The device boots as one switched on: with a boot id of its own,
    /// random as the firmware's RNG draws it ([`DeviceConfig::boot_id`]), so
    /// that the home captures of two rigs (two runs of a `--simulate`
    /// command: a collection stopped and resumed) never share an id. With
    /// the configured id of every virtual device (1) they did: the resumed
    /// run's rows named the first run's home capture while their time since
    /// home started again at 0.
    ///
    /// [`Pace::Virtual`]: crate::sim::virtual_device::Pace::Virtual
    /// [`DeviceConfig::boot_id`]: spidar_core::device::DeviceConfig::boot_id
    pub fn start(
        device: SimulatedDevice,
        offset_mm: [f64; 3],
        configure: impl FnOnce(&mut SimOperatorConfig),
    ) -> Result<SimulatedRig, RigError> {
        Self::boot(
            device,
            offset_mm,
            rand::random::<u32>(),
            |_| Ok::<(), RigError>(()),
            configure,
        )
    }

    /// [`SimulatedRig::start`], with `prepare` run on the virtual device
    /// before the operator takes the hand (flash a model and power-cycle
    /// it, so that it homes where the hand is). The device boots with the
    /// virtual device's configured id (1, then one more at each power
    /// cycle), which a test that prepares a calibration under a home
    /// capture names.
    pub fn start_prepared<E: From<RigError>>(
        device: SimulatedDevice,
        offset_mm: [f64; 3],
        prepare: impl FnOnce(&crate::sim::virtual_device::VirtualDevice) -> Result<(), E>,
        configure: impl FnOnce(&mut SimOperatorConfig),
    ) -> Result<SimulatedRig, E> {
        let boot_id = crate::sim::virtual_device::VirtualDeviceConfig::default()
            .device
            .boot_id;
        Self::boot(device, offset_mm, boot_id, prepare, configure)
    }

    fn boot<E: From<RigError>>(
        device: SimulatedDevice,
        offset_mm: [f64; 3],
        boot_id: u32,
        prepare: impl FnOnce(&crate::sim::virtual_device::VirtualDevice) -> Result<(), E>,
        configure: impl FnOnce(&mut SimOperatorConfig),
    ) -> Result<SimulatedRig, E> {
        use crate::sim::virtual_device::{spawn, Pace, Plant, Trajectory, VirtualDeviceConfig};
        let start: [f64; 3] = core::array::from_fn(|k| device.frame.home[k] + offset_mm[k]);
        let hand = Hand::at(start);
        // On the simulated clock from the start: the device does not tick
        // before the operator moves the hand (in real time it would, and
        // where its clock stands when the operator starts would be the
        // machine's doing).
        hand.attach();
        let plant = Plant::new(device.clone(), Trajectory::Held(hand.clone()));
        let defaults = VirtualDeviceConfig::default();
        let virtual_device = spawn(
            VirtualDeviceConfig {
                pace: Pace::Virtual,
                device: spidar_core::device::DeviceConfig {
                    boot_id,
                    ..defaults.device
                },
                ..defaults
            },
            plant,
        )
        .map_err(RigError::from)?;
        prepare(&virtual_device)?;
        Ok(Self::operate(device, hand, virtual_device, configure)?)
    }

    /// The rig of `device` in `hand` on `virtual_device`, taken by a new
    /// operator configured by `configure` (its tracker address is a new
    /// receiver's): how [`SimulatedRig::start_prepared`] ends, and how a
    /// test goes on after stopping an operator (the hand brought home, a
    /// `Home` sent) with another.
    pub fn operate(
        device: SimulatedDevice,
        hand: Hand,
        virtual_device: crate::sim::virtual_device::VirtualDevice,
        configure: impl FnOnce(&mut SimOperatorConfig),
    ) -> Result<SimulatedRig, RigError> {
        let receiver = crate::device::tracker::DtrackReceiver::bind(
            crate::device::tracker::ReceiverConfig::new(SocketAddr::from(([127, 0, 0, 1], 0))),
        )?;
        let mut config = SimOperatorConfig::new(receiver.local_addr());
        configure(&mut config);
        config.tracker = receiver.local_addr();
        // In virtual time the plant ticks up to each frame's instant and
        // waits there: an instant between two ticks would never be reached.
        let tick_us = u64::from(virtual_device.config().tick_us);
        let frame_us = (1e6 / config.frame_rate_hz).round();
        if !(frame_us.is_finite() && frame_us >= 1.0) || frame_us as u64 % tick_us != 0 {
            return Err(RigError::from(TrackerError::Config(crate::ConfigError::new("frame_rate_hz", format!(
                    "{} Hz: in a simulated rig the tracker's frame period must be a whole number of the device's {tick_us} µs ticks (e.g. 100, 125, 200, 250 Hz)",
                    config.frame_rate_hz
                )))));
        }
        let cues = SharedCues::stamped_by(receiver.progress());
        let operator = SimOperator::spawn_in_step(
            config,
            device.clone(),
            hand.clone(),
            cues.clone(),
            Some(receiver.progress()),
        )?;
        Ok(SimulatedRig {
            device,
            hand,
            cues,
            virtual_device,
            receiver,
            operator,
        })
    }

    /// The clock a procedure on this rig stamps arrivals with: the
    /// simulated world's.
    pub fn host_clock(&self) -> crate::device::tracker::HostClock {
        crate::device::tracker::HostClock::Simulated(self.hand.clock())
    }

    /// Link options for a client of this rig
    /// ([`crate::device::link::ClientOptions::for_simulated_device`]).
    pub fn client_options(&self) -> crate::device::link::ClientOptions {
        crate::device::link::ClientOptions::for_simulated_device()
    }

    /// Opens a client on the rig's device with [`SimulatedRig::client_options`].
    pub fn client(&self) -> Result<crate::device::link::Client, crate::device::link::LinkError> {
        crate::device::link::Client::open_with(self.port(), self.client_options())
    }

    /// The serial port of the virtual device.
    pub fn port(&self) -> &str {
        self.virtual_device.port_path()
    }

    /// Where each part of the lock-step world stands, in one line: for a
    /// test that failed on a silent device or tracker, which part stood
    /// still (the device's ticks and frames, the hand's plant and
    /// committed path, the frames the procedure took).
    pub fn describe(&self) -> String {
        let d = self.virtual_device.status();
        let progress = self.receiver.progress();
        format!(
            "virtual device: boots {}, device time {} us, ticks {}, frames sent {}, dropped {}, \
             armed {}, power lost {}, plant error {:?}; hand: plant at {} us, path until {:?} us, \
             clock {} us; tracker: {} datagrams received, {} frames taken, busy {}; operator \
             thread ended {}",
            d.boots,
            d.device_time_us,
            d.ticks,
            d.tx_frames,
            d.tx_dropped,
            d.armed,
            d.power_lost,
            d.plant_error,
            self.hand.plant_time_us(),
            self.hand.ready_until(),
            self.hand.clock().now_us(),
            self.receiver.receiver_stats().datagrams,
            progress.taken(),
            progress.busy(),
            self.operator.is_finished(),
        )
    }
}
