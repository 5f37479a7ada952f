//! The device behind the link: what a SPIDAR controller does with each host
//! request, each control-loop iteration and each state frame. The firmware
//! and the virtual device both run exactly this code; they only bring the
//! clock, the encoders, the motors, the flash and the byte stream.
//!
//! - [`Device::handle`]: one [`Request`] in, its [`Response`] out (every
//!   request of the protocol, see the match in `handle` and the crate docs of
//!   `spidar_protocol` for the rules);
//! - [`Device::tick`]: one control-loop iteration ([`Controller::step`] on
//!   the active calibration);
//! - [`Device::state_frame`], [`Device::take_event`]: the stream;
//! - [`DeviceLink`]: bytes in (COBS frames, [`FrameDecoder`]), reply frames
//!   out ([`encode_device_message`]), stream frames with their own sequence
//!   numbers.
//!
//! # Which calibration runs
//!
//! The committed model blob if there is one (it takes precedence), else the
//! nominal one built from `SetNominalGeometry` (anchors, home, linear string law
//! `payout = r theta`, no effects, no correction), else none: no geometry,
//! the loop idles and `Arm` is refused with `BadState(NoGeometry)`.
//!
//! **Home** (counts 0, end-effector at the calibration's home point) is
//! declared when the controller is created: at boot if a stored model loads,
//! else when the first geometry arrives (`SetNominalGeometry` or a commit), and
//! again at each `Home` request (the host's guided initialization). A
//! later change of calibration keeps the counts (same physical home) and
//! the home capture's id; `ClearModel` without a nominal model drops the
//! geometry, and the next one homes again.
//!
//! A blob may carry the training session's slips with the id of their home
//! capture ([`crate::blob::CompiledHomeSlips`]): the loop adds them while
//! the device's [`Device::home_id`] is that one, so a model flashed under
//! the training's home capture keeps its slipped strings slipped, and a
//! `Home` or a reboot (a new boot id) ends them. Drifts and every other
//! term that reads time read the time since home, which starts again at
//! each capture.
//!
//! # The model bytes and their borrow
//!
//! [`CompiledCalibration<'a>`] borrows its correction (NN/SVR parameters)
//! from the blob bytes. The device owns no flash mapping: it copies the
//! active blob into a RAM buffer it was given (`model_ram`) and parses it
//! **once**, at boot or commit, with [`CompiledCalibration::from_blob`]
//! (header, CRCs, every field). It keeps the owned part (header, frame,
//! string laws, effects: a `CompiledCalibration<'static>` with
//! `Correction::None`) and where the correction bytes start. Each tick:
//! - no correction: the cached calibration is passed as it is (no work);
//! - NN/SVR: a `Correction<'_>` view over the RAM copy is rebuilt from the
//!   `CorrectionSummary` taken when it was checked at load
//!   (`Correction::from_summary`: O(1) for an SVR, O(hidden) for an NN; the
//!   bytes cannot change between commits) and passed with the owned string
//!   model to `Controller::step_with`; nothing is copied. Measured on the host: see the
//!   test `tick_cost` (`cargo test -p spidar-core --release --lib
//!   device::tests::tick_cost -- --ignored --nocapture`) and
//!   `docs/hardware.md`.
//!
//! Re-running `from_blob` every tick would CRC the whole blob and decode the
//! body with postcard each time (the test measures it too); reading the
//! correction from flash in place would tie the device to a memory-mapped
//! flash (the virtual device has none) and, on the H7 with its data cache
//! off, read slow flash every iteration. Uploads are staged through a second
//! buffer (`spare_ram`): the commit reads the staged blob back from flash
//! into it, validates it there, and only then the two buffers swap (a swap of
//! two `&mut [u8]`, no copy, no unsafe). The loop never sees a half-written
//! model and keeps running the previous one during an upload.
//!
//! [`FrameDecoder`]: spidar_protocol::FrameDecoder
//! [`Request`]: spidar_protocol::Request
//! [`Response`]: spidar_protocol::Response
//! [`encode_device_message`]: spidar_protocol::encode_device_message

use heapless::Deque;
use spidar_protocol::{
    Capabilities, DecodeStats, Event, Faults, HelloAck, LinkStats, MAX_CHUNK, PROTOCOL_VERSION,
};

use crate::blob::CompiledCalibration;
use crate::control::{ControlConfig, Controller, LoopOutput, Target};
use crate::model_store::{ModelFlash, ModelStore};
use crate::safety::{SafetyConfig, SafetyConfigError, SafetyMonitor};
use crate::STRINGS;

mod calibration;
mod control_loop;
mod link;
mod requests;

pub use calibration::{nominal_calibration, ModelBuffer};
pub use control_loop::protocol_faults;
pub use link::DeviceLink;
pub use requests::STORAGE_RECORD_VERIFY;

use calibration::{parse_model, ActiveModel};
use control_loop::idle_output;

/// Stream events kept until the link sends them.
const EVENT_QUEUE: usize = 8;

/// What the device says about itself, and its loop settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeviceConfig {
    /// `[major, minor, patch]` for `HelloAck`.
    pub firmware_version: [u16; 3],
    /// Unique id for `HelloAck` (the STM32 UID on hardware).
    pub device_id: [u8; 12],
    /// Control-loop period, µs (overrun threshold, `HelloAck`).
    pub loop_period_us: u32,
    /// This boot's id, a number that differs from one boot to the next (the
    /// RNG on hardware): the upper half of every home capture's id
    /// ([`State::home_id`]).
    ///
    /// [`State::home_id`]: spidar_protocol::State::home_id
    pub boot_id: u32,
    /// Loop and safety parameters (`SetLimits` changes the safety part).
    pub control: ControlConfig,
}

/// Inputs of one tick, read from the peripherals.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TickInput {
    /// Raw 16-bit encoder counters, sign-corrected (paying out counts up).
    pub raw_counts: [u16; STRINGS],
    /// Monotonic device time, µs since boot (the same clock as `handle`'s).
    pub now_us: u64,
    /// Hardware emergency-stop input active.
    pub estop: bool,
}

/// Counters of the link layer, handed to the device with each request (for
/// `GetStats`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkCounters {
    pub rx: DecodeStats,
    pub tx_frames: u32,
}

fn ms(now_us: u64) -> u32 {
    (now_us / 1000) as u32
}

/// The state stream's settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Stream {
    decimation: u16,
    /// Ticks since the last frame.
    count: u16,
}

/// A SPIDAR controller: the model store, the control loop and the session
/// with the host. `'m` is the lifetime of the two model RAM buffers.
pub struct Device<'m, F: ModelFlash> {
    config: DeviceConfig,
    store: ModelStore<F>,
    /// The active blob (valid up to `active.len`).
    model_ram: &'m mut [u8],
    /// Where a commit reads the staged blob back to; swapped with
    /// `model_ram` on success.
    spare_ram: &'m mut [u8],
    active: Option<ActiveModel>,
    /// The stored model failed its checks (at boot, or its view at a tick).
    model_invalid: bool,
    nominal: Option<CompiledCalibration<'static>>,
    controller: Option<Controller>,
    /// Safety limits waiting for the latched faults to be cleared.
    pending_safety: Option<SafetyConfig>,
    target: Target,
    /// The host armed the motors and did not disarm them: the drivers stay
    /// enabled (at pre-tension after a fault) until `Disarm` or the e-stop.
    energized: bool,
    host_version: Option<u16>,
    last_heartbeat_ms: Option<u32>,
    last_raw: [u16; STRINGS],
    last_now_us: u64,
    /// Device time at which home was last declared (boot or `Home`), µs.
    home_us: u64,
    /// Home captures declared since boot (the lower half of
    /// [`State::home_id`]).
    homes_declared: u32,
    estop: bool,
    last_out: LoopOutput,
    stream: Option<Stream>,
    frame_due: bool,
    loop_us: u16,
    loop_max_us: u16,
    loop_overrun: bool,
    prev_faults: Faults,
    prev_armed: bool,
    stats: LinkStats,
    events: Deque<Event, EVENT_QUEUE>,
}

impl<'m, F: ModelFlash> Device<'m, F> {
    /// Boots the device: opens the model store (the newest valid slot),
    /// copies the active blob into `model_ram` and parses it (a blob that
    /// fails raises `MODEL_INVALID`), and homes the controller at
    /// `raw_counts` if there is a model. `model_ram` and `spare_ram` bound
    /// the largest blob (the smaller of the two and of a slot). Fails only
    /// for invalid safety limits in `config`.
    pub fn new(
        config: DeviceConfig,
        flash: F,
        model_ram: &'m mut [u8],
        spare_ram: &'m mut [u8],
        raw_counts: [u16; STRINGS],
        now_us: u64,
    ) -> Result<Self, SafetyConfigError> {
        SafetyMonitor::new(config.control.safety)?;
        let mut store = ModelStore::open(flash);
        let mut model_invalid = false;
        let mut active = None;
        if let Some(stored) = store.active() {
            let loaded = store
                .read_active(model_ram)
                .ok()
                .and_then(|bytes| parse_model(bytes).ok());
            match loaded {
                Some(p) => {
                    active = Some(ActiveModel {
                        stored,
                        correction: p.correction,
                        calibration: p.calibration,
                        correction_at: p.correction_at,
                        len: p.len,
                    })
                }
                None => model_invalid = true,
            }
        }
        let mut d = Device {
            config,
            store,
            model_ram,
            spare_ram,
            active,
            model_invalid,
            nominal: None,
            controller: None,
            pending_safety: None,
            target: Target::Idle,
            energized: false,
            host_version: None,
            last_heartbeat_ms: None,
            last_raw: raw_counts,
            last_now_us: now_us,
            home_us: now_us,
            homes_declared: 0,
            estop: false,
            last_out: idle_output(false, model_invalid),
            stream: None,
            frame_due: false,
            loop_us: 0,
            loop_max_us: 0,
            loop_overrun: false,
            prev_faults: Faults::default(),
            prev_armed: false,
            stats: LinkStats::default(),
            events: Deque::new(),
        };
        d.ensure_controller();
        Ok(d)
    }

    /// Gives the flash back (power-cycling a virtual device: `Device::new`
    /// again on it).
    pub fn into_flash(self) -> F {
        self.store.into_flash()
    }

    /// What `Hello` answers.
    pub fn hello_ack(&self) -> HelloAck {
        HelloAck {
            protocol_version: PROTOCOL_VERSION,
            firmware_version: self.config.firmware_version,
            device_id: self.config.device_id,
            capabilities: Capabilities::FORCE
                .union(Capabilities::GUIDANCE)
                .union(Capabilities::MODEL_NN)
                .union(Capabilities::MODEL_SVR)
                .union(Capabilities::UPLOAD_RESUME),
            max_chunk: MAX_CHUNK as u16,
            max_blob_len: self.blob_capacity(),
            loop_period_us: self.config.loop_period_us,
        }
    }

    /// Largest blob the device takes: a slot, and each RAM buffer.
    pub fn blob_capacity(&self) -> u32 {
        let ram = self.model_ram.len().min(self.spare_ram.len());
        u32::try_from(ram)
            .unwrap_or(u32::MAX)
            .min(ModelStore::<F>::MAX_BLOB_LEN)
    }

    /// Whether the motor drivers should be enabled: armed by the host, not
    /// disarmed since, no emergency stop. Stays true after a fault disarmed
    /// the loop, so that the strings keep their pre-tension.
    pub fn motors_enabled(&self) -> bool {
        self.energized && !self.estop
    }

    /// The loop renders forces (armed, no fault latched).
    pub fn armed(&mut self) -> bool {
        self.controller
            .as_mut()
            .is_some_and(|c| c.safety().is_armed())
    }

    /// Device time (µs since boot) at which home was last declared: at boot
    /// with a stored model, when the first geometry arrived, or at the last
    /// `Home`. `None` while the device has no geometry (nothing is homed).
    pub fn home_declared_us(&self) -> Option<u64> {
        self.controller.as_ref().map(|_| self.home_us)
    }

    /// The last tick's output.
    pub fn last_output(&self) -> &LoopOutput {
        &self.last_out
    }

    /// Link and loop counters.
    pub fn stats(&self) -> LinkStats {
        self.stats
    }

    /// The link layer's counters (call before `handle` so `GetStats` is current).
    pub fn set_link_counters(&mut self, counters: LinkCounters) {
        self.stats.rx = counters.rx;
        self.stats.tx_frames = counters.tx_frames;
    }

    /// A stream frame was dropped (the link was busy).
    pub fn count_stream_dropped(&mut self) {
        self.stats.tx_dropped = self.stats.tx_dropped.wrapping_add(1);
    }

    /// The next event to send, oldest first.
    pub fn take_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    fn push_event(&mut self, e: Event) {
        if self.events.push_back(e).is_err() {
            self.stats.tx_dropped = self.stats.tx_dropped.wrapping_add(1);
        }
    }

    fn calibration_available(&self) -> bool {
        self.active.is_some() || self.nominal.is_some()
    }

    /// A home capture at `now_us`: the time since home and the home's id
    /// start again.
    fn declare_home(&mut self, now_us: u64) {
        self.home_us = now_us;
        self.homes_declared = self.homes_declared.wrapping_add(1);
    }

    /// The id of the home capture the counts are from ([`State::home_id`]).
    ///
    /// [`State::home_id`]: spidar_protocol::State::home_id
    pub fn home_id(&self) -> u64 {
        u64::from(self.config.boot_id) << 32 | u64::from(self.homes_declared)
    }

    /// Creates (and homes) the controller when a geometry is there and no
    /// controller is; drops it when the geometry is gone.
    fn ensure_controller(&mut self) {
        if !self.calibration_available() {
            self.controller = None;
            self.energized = false;
            return;
        }
        if self.controller.is_some() {
            return;
        }
        let cal = match (&self.active, &self.nominal) {
            (Some(a), _) => &a.calibration,
            (None, Some(n)) => n,
            (None, None) => return,
        };
        let now_ms = ms(self.last_now_us);
        if let Ok(mut c) = Controller::new(self.config.control, cal, self.last_raw, now_ms) {
            self.declare_home(self.last_now_us);
            c.set_home_id(Some(self.home_id()));
            if let Some(t) = self.last_heartbeat_ms {
                c.safety().heartbeat(t);
            }
            c.safety().set_model_valid(!self.model_invalid);
            self.pending_safety = None;
            self.controller = Some(c);
        }
    }
}

#[cfg(all(test, feature = "alloc"))]
mod tests;
