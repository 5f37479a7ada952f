//! Guided initialization (paper, section 4.1; `spidar init`).
//!
//! The built-in homing leaves the end-effector a few centimetres from the
//! frame centre. With the optical tracker watching the marker, the host
//! guides the operator's hand to the centre (the target, room frame) and
//! declares home there:
//!
//! 1. the device runs its nominal string model (`SetNominalGeometry` from the
//!    geometry) unless it has a calibration blob, and is armed;
//! 2. for every tracker frame with the marker visible: `v = target -
//!    marker`, `d = |v|`; the haptic cue `F = guidance_force(v, d_min,
//!    F_max)` (eqs. 2, 4, 5: [`spidar_core::guidance`], the same function
//!    the device runs for `SetGuidanceTarget`) goes to the device as a force
//!    target (device frame); the audio cue plays `f(d) = 1000 h(d)` Hz
//!    (eq. 3). Guidance is computed from the **tracker**, not from the
//!    device's own position, which is what is being initialized. Each force
//!    target is also the heartbeat;
//! 3. the marker *holds* once every frame for `hold` (tracker time) lies
//!    within `tolerance` of the target; a frame outside restarts the hold,
//!    and so does the marker occluded for longer than `occlusion_timeout`
//!    (a single occluded frame says nothing against the hold, and is not
//!    counted in it);
//! 4. then `Home` (the encoder readings become zero at the nominal home),
//!    the force drops, and the room-to-device transform is recorded:
//!    `t = mean(marker during the hold) - home_device` (eq. 6: `p_room =
//!    p_device + t`), with its standard deviation.
//!
//! The marker lost for longer than `occlusion_timeout` drops the force to
//! zero until it is back (no guidance from a stale position); the tracker
//! silent for `tracker_timeout` and the whole procedure running past
//! `timeout` are errors that disarm the device.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use spidar_core::guidance::{beep_frequency_hz, guidance_force};
use spidar_protocol::Limits;

use super::arm_watch::{ArmWatch, ArmWatchError};
use crate::data::dataset::{DatasetError, Geometry};
use crate::device::cues::{CueSink, Cues};
use crate::device::link::{Client, LinkError};
use crate::device::tracker::{Next, TrackerError, TrackerSource};
use spidar_core::geometry::distance;

/// Settings of guided initialization.
#[derive(Clone, Debug, PartialEq)]
pub struct InitConfig {
    /// The initialization point (frame centre), room frame, mm.
    pub target_room_mm: [f64; 3],
    /// The nominal home in the device frame (where the device puts the
    /// end-effector when home is declared), mm.
    pub home_device_mm: [f64; 3],
    /// Cue radius `d_min` of eqs. 2-5, mm.
    pub d_min_mm: f32,
    /// Largest guidance force `F_max`, N.
    pub f_max_n: f32,
    /// The marker must stay this close to the target, mm.
    pub tolerance_mm: f64,
    /// ... for this long (tracker time).
    pub hold: Duration,
    /// DTrack body id of the marker.
    pub body_id: u32,
    /// Drop the force after the marker is occluded this long.
    pub occlusion_timeout: Duration,
    /// Fail when the tracker sends nothing for this long.
    pub tracker_timeout: Duration,
    /// Fail when home is not declared within this long.
    pub timeout: Duration,
    /// Device state frames per control-loop iterations (the stream read for
    /// the report).
    pub decimation: u16,
    /// Safety limits for the procedure: the heartbeat timeout must exceed
    /// the tracker's frame period (every frame sends the force target).
    pub limits: Limits,
}

impl InitConfig {
    /// The paper's procedure for `geometry`: the frame centre (the nominal
    /// home) seen through the nominal eq. 6 translation, `d_min` 150 mm,
    /// 3 N, 2 mm held for 0.5 s.
    pub fn for_geometry(geometry: &Geometry) -> InitConfig {
        let home = geometry.home_mm;
        let t = geometry.room_from_device_translation_mm;
        InitConfig {
            target_room_mm: core::array::from_fn(|k| home[k] + t[k]),
            home_device_mm: home,
            d_min_mm: 150.0,
            f_max_n: 3.0,
            tolerance_mm: 2.0,
            hold: Duration::from_millis(500),
            body_id: 0,
            occlusion_timeout: Duration::from_millis(200),
            tracker_timeout: Duration::from_secs(2),
            timeout: Duration::from_secs(120),
            decimation: 10,
            limits: Limits {
                pre_tension_n: 1.0,
                max_tension_n: 20.0,
                heartbeat_timeout_ms: 100,
            },
        }
    }

    fn validate(&self) -> Result<(), InitError> {
        let bad = |field: &'static str, problem: String| {
            Err(InitError::Config(crate::ConfigError::new(field, problem)))
        };
        if !self
            .target_room_mm
            .iter()
            .chain(&self.home_device_mm)
            .all(|v| v.is_finite())
        {
            return bad("target", "not finite".into());
        }
        if !(self.d_min_mm.is_finite() && self.d_min_mm > 0.0) {
            return bad(
                "d_min_mm",
                format!("{} is not a positive distance", self.d_min_mm),
            );
        }
        if !(self.f_max_n.is_finite() && self.f_max_n >= 0.0) {
            return bad("f_max_n", format!("{} is not a force >= 0", self.f_max_n));
        }
        if !(self.tolerance_mm.is_finite() && self.tolerance_mm > 0.0) {
            return bad(
                "tolerance_mm",
                format!("{} is not a positive distance", self.tolerance_mm),
            );
        }
        Ok(())
    }
}

/// Why initialization failed (the device is disarmed in every case).
#[derive(Debug, thiserror::Error)]
pub enum InitError {
    #[error("init: {0}")]
    Config(#[from] crate::ConfigError),
    #[error("init: {0}")]
    Link(#[from] LinkError),
    #[error("init: tracker: {0}")]
    Tracker(#[from] TrackerError),
    #[error("init: {0}")]
    Dataset(#[from] DatasetError),
    #[error(
        "init: the tracker sent nothing for {seconds:.1} s (is DTrack sending to this host and port?)"
    )]
    TrackerSilent { seconds: f64 },
    #[error("init: the tracker source ended before home was declared")]
    TrackerEnded,
    #[error(
        "init: no hold within {seconds:.0} s (closest approach {closest_mm:.1} mm, tolerance {tolerance_mm} mm); the device is disarmed"
    )]
    Timeout {
        seconds: f64,
        closest_mm: f64,
        tolerance_mm: f64,
    },
    #[error("init: the device did not confirm home (no state after Home within 5 s)")]
    NotConfirmed,
    #[error("init: the device keeps disarming itself ({events}); the last event: {last}")]
    KeepsDisarming { events: u32, last: String },
    #[error("init: cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// What initialization measured; written as TOML by `spidar init --out`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InitRecord {
    /// The initialization point, room frame, mm.
    pub target_room_mm: [f64; 3],
    /// Mean marker position while it held, room frame, mm: where home is.
    pub home_room_mm: [f64; 3],
    /// Standard deviation of the marker during the hold, per axis, mm.
    pub home_room_sd_mm: [f64; 3],
    /// Distance from the mean hold position to the target, mm.
    pub home_error_mm: f64,
    /// Tracker frames in the hold.
    pub hold_frames: usize,
    pub tolerance_mm: f64,
    pub hold_s: f64,
    /// Nominal home, device frame, mm.
    pub home_device_mm: [f64; 3],
    /// Eq. 6: `p_room = p_device + t`, measured.
    pub room_from_device_translation_mm: [f64; 3],
    /// Tracker `ts` when home was declared, s.
    pub declared_at_ts_s: f64,
    /// Where the device put the end-effector after `Home` (its forward
    /// kinematics, device frame), mm: the nominal home up to the encoder
    /// quantization.
    pub device_position_after_home_mm: [f64; 3],
    /// Device id (from `Hello`).
    pub device_id: String,
    /// The pretension every string held when home was declared, N (the
    /// procedure's `Limits::pre_tension_n`); records written before it was
    /// kept read the firmware's default, 1 N.
    #[serde(default = "default_home_tension_n")]
    pub home_tension_n: f64,
}

fn default_home_tension_n() -> f64 {
    1.0
}

impl InitRecord {
    /// Writes the record as TOML.
    pub fn write(&self, path: &Path) -> Result<(), InitError> {
        let text = toml::to_string_pretty(self).map_err(|e| InitError::Write {
            path: path.to_path_buf(),
            source: std::io::Error::other(e.to_string()),
        })?;
        crate::data::output::write_atomically(path, text.as_bytes()).map_err(|source| {
            InitError::Write {
                path: path.to_path_buf(),
                source,
            }
        })
    }

    /// `geometry` with the measured eq. 6 translation and the tension the
    /// strings held at the home capture.
    pub fn apply_to(&self, geometry: &Geometry) -> Geometry {
        let mut g = geometry.clone();
        g.room_from_device_translation_mm = self.room_from_device_translation_mm;
        g.home_tension_n = Some(self.home_tension_n);
        g
    }
}

/// Times the procedure re-arms a device that disarmed itself.
const MAX_REARMS: u32 = 5;

/// Runs guided initialization on an open device session. `geometry` is sent
/// as the nominal string model if the device has no calibration blob.
pub fn initialize(
    client: &mut Client,
    tracker: &mut dyn TrackerSource,
    geometry: &Geometry,
    config: &InitConfig,
    sink: &mut dyn CueSink,
) -> Result<InitRecord, InitError> {
    config.validate()?;
    let result = run(client, tracker, geometry, config, sink);
    // Whatever happened, leave the motors off and the stream closed.
    let _ = client.set_force([0.0; 3]);
    let _ = client.disarm();
    let _ = client.stream_off();
    sink.show(&Cues {
        message: match &result {
            Ok(r) => format!(
                "home declared {:.2} mm from the centre; motors off",
                r.home_error_mm
            ),
            Err(e) => format!("stopped: {e}"),
        },
        ..Cues::default()
    });
    result
}

fn run(
    client: &mut Client,
    tracker: &mut dyn TrackerSource,
    geometry: &Geometry,
    config: &InitConfig,
    sink: &mut dyn CueSink,
) -> Result<InitRecord, InitError> {
    if client.info()?.is_none() {
        client.set_string_model(geometry.string_model())?;
    }
    let device_id = client
        .device()
        .map(|h| String::from_utf8_lossy(&h.device_id).into_owned())
        .unwrap_or_default();
    client.set_limits(config.limits)?;
    client.clear_faults()?;
    client.arm()?;
    client.stream_on(config.decimation)?;
    let mut arm_watch = ArmWatch::new(MAX_REARMS);

    let start = Instant::now();
    let mut last_frame_at = Instant::now();
    // Tracker time of the last visible frame.
    let mut last_seen_ts: Option<f64> = None;
    let mut closest = f64::INFINITY;
    // (ts, marker) of the current hold.
    let mut hold: Vec<(f64, [f64; 3])> = Vec::new();
    loop {
        if start.elapsed() > config.timeout {
            return Err(InitError::Timeout {
                seconds: config.timeout.as_secs_f64(),
                closest_mm: closest,
                tolerance_mm: config.tolerance_mm,
            });
        }
        // Keep the state stream drained; a device that disarmed itself (a
        // late heartbeat, a slack string) is re-armed a few times, then it
        // is an error.
        let latest = client.poll_states()?.last().map(|s| (s.armed, s.faults));
        match arm_watch.check(client, latest) {
            Ok(_) => {}
            Err(ArmWatchError::Link(e)) => return Err(e.into()),
            Err(ArmWatchError::KeepsDisarming { events, last }) => {
                return Err(InitError::KeepsDisarming { events, last })
            }
        }
        let frame = match tracker.next_frame(Duration::from_millis(20))? {
            Next::Frame(f) => f,
            Next::End => return Err(InitError::TrackerEnded),
            Next::Timeout => {
                if last_frame_at.elapsed() > config.tracker_timeout {
                    return Err(InitError::TrackerSilent {
                        seconds: last_frame_at.elapsed().as_secs_f64(),
                    });
                }
                client.heartbeat()?;
                continue;
            }
        };
        last_frame_at = Instant::now();
        let marker = frame
            .body
            .as_ref()
            .filter(|b| b.id == config.body_id && b.is_visible())
            .map(|b| b.position_mm);
        let Some(marker) = marker else {
            let stale = last_seen_ts
                .is_none_or(|t| frame.ts_s - t > config.occlusion_timeout.as_secs_f64());
            if stale {
                hold.clear();
                client.set_force([0.0; 3])?;
            } else {
                client.heartbeat()?;
            }
            sink.show(&Cues {
                message: "marker occluded: bring it back into the tracker's view".into(),
                ..Cues::default()
            });
            continue;
        };
        last_seen_ts = Some(frame.ts_s);
        let v: [f64; 3] = core::array::from_fn(|k| config.target_room_mm[k] - marker[k]);
        let d = distance(config.target_room_mm, marker);
        closest = closest.min(d);
        // Eq. 6 has no rotation: a room-frame force is a device-frame force.
        let force = guidance_force(v.map(|x| x as f32), config.d_min_mm, config.f_max_n);
        let beep = beep_frequency_hz(d as f32, config.d_min_mm);
        client.set_force(force)?;
        if d <= config.tolerance_mm {
            hold.push((frame.ts_s, marker));
        } else {
            hold.clear();
        }
        let held_s = match (hold.first(), hold.last()) {
            (Some(a), Some(b)) => b.0 - a.0,
            _ => 0.0,
        };
        sink.show(&Cues {
            marker_room_mm: Some(marker),
            target_room_mm: None,
            target_half_size_mm: 0.0,
            distance_mm: Some(d),
            beep_hz: beep,
            force_n: force,
            progress: None,
            message: if hold.is_empty() {
                "follow the pull and the rising beep to the centre".into()
            } else {
                format!(
                    "hold still: {held_s:.1} of {:.1} s",
                    config.hold.as_secs_f64()
                )
            },
        });
        if held_s >= config.hold.as_secs_f64() {
            return declare_home(client, tracker, config, &hold, frame.ts_s, device_id);
        }
    }
}

fn declare_home(
    client: &mut Client,
    tracker: &mut dyn TrackerSource,
    config: &InitConfig,
    hold: &[(f64, [f64; 3])],
    ts_s: f64,
    device_id: String,
) -> Result<InitRecord, InitError> {
    client.home()?;
    let n = hold.len() as f64;
    let mean: [f64; 3] = core::array::from_fn(|k| hold.iter().map(|h| h.1[k]).sum::<f64>() / n);
    let sd: [f64; 3] = core::array::from_fn(|k| {
        (hold.iter().map(|h| (h.1[k] - mean[k]).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt()
    });
    // The first state after the `Homed` event is the device's new home.
    // A device answers within milliseconds; a machine busy with other work
    // may take its time to run a simulated one.
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut homed = false;
    let mut after = None;
    while Instant::now() < deadline && after.is_none() {
        // The tracker's frames are read on (a simulated world in step with
        // this procedure waits for them to be taken).
        let _ = tracker.next_frame(Duration::from_millis(1))?;
        let states = client.poll_states()?;
        if !homed {
            homed = client
                .take_events()
                .iter()
                .any(|e| matches!(e, spidar_protocol::Event::Homed));
            continue;
        }
        after = states.last().map(|s| s.position_mm.map(f64::from));
    }
    let after = after.ok_or(InitError::NotConfirmed)?;
    Ok(InitRecord {
        target_room_mm: config.target_room_mm,
        home_room_mm: mean,
        home_room_sd_mm: sd,
        home_error_mm: distance(mean, config.target_room_mm),
        hold_frames: hold.len(),
        tolerance_mm: config.tolerance_mm,
        hold_s: config.hold.as_secs_f64(),
        home_device_mm: config.home_device_mm,
        room_from_device_translation_mm: core::array::from_fn(|k| {
            mean[k] - config.home_device_mm[k]
        }),
        declared_at_ts_s: ts_s,
        device_position_after_home_mm: after,
        device_id,
        home_tension_n: f64::from(config.limits.pre_tension_n),
    })
}
