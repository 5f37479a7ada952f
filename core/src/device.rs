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

use heapless::Deque;
use spidar_protocol::blob::{BlobError, CorrectionKind, ModelHeader, FORMAT_VERSION};
use spidar_protocol::messages::name;
use spidar_protocol::{
    encode_device_message, BadState, Capabilities, DecodeStats, DeviceError, DeviceMessage, Event,
    Faults, FrameDecoder, FrameError, HelloAck, Limits, LinkStats, ModelInfo, NominalGeometry,
    Packet, Request, Response, State, UploadState, MAX_CHUNK, MAX_FRAME, PROTOCOL_VERSION,
};

use crate::blob::{split_body, BlobHead, CompiledCalibration, LENGTH_FRAC};
use crate::control::{ControlConfig, Controller, LoopInput, LoopOutput, Target};
use crate::correction::{Correction, CorrectionSummary, ACTIVATION_FRAC, POSITION_FRAC};
use crate::kinematics::FkStatus;
use crate::model::{Frame, StringLaw, StringLayout};
use crate::model_store::{CommitError, ModelFlash, ModelStore, StoreError, StoredModel};
use crate::safety::{SafetyConfig, SafetyConfigError, SafetyFaults, SafetyMonitor};
use crate::string_law::{compile_string_law, CompiledStringLaw, StringLawCompileError};
use crate::tension::{force_closure, TensionStatus};
use crate::STRINGS;

/// A model RAM buffer (`model_ram`, `spare_ram` of [`Device::new`]) of `N`
/// bytes, 8-byte aligned: a blob copied to its start has its correction
/// 4-byte aligned (blob format version 2), so the SVR records are read as
/// aligned words (fewer loads per support vector). Any `&mut [u8]` works as
/// a model buffer; an unaligned one gives the same results, more slowly.
#[repr(C, align(8))]
pub struct ModelBuffer<const N: usize>(pub [u8; N]);

impl<const N: usize> ModelBuffer<N> {
    /// A zeroed buffer (usable in a `static` initializer).
    pub const fn new() -> Self {
        ModelBuffer([0; N])
    }

    /// The buffer's bytes, to hand to [`Device::new`].
    pub fn bytes(&mut self) -> &mut [u8] {
        &mut self.0
    }
}

impl<const N: usize> Default for ModelBuffer<N> {
    fn default() -> Self {
        Self::new()
    }
}

/// `DeviceError::Storage` code of a commit record that did not read back.
pub const STORAGE_RECORD_VERIFY: u32 = 0x8000_0010;

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

/// The parsed active model: owned part plus where its correction bytes are.
#[derive(Clone, Debug)]
struct ActiveModel {
    stored: StoredModel,
    /// Header, frame, laws, effects; `correction` is always `None` here.
    calibration: CompiledCalibration<'static>,
    /// The correction as checked at load; its view is rebuilt over
    /// `model_ram[correction_at..len]` every tick in O(1).
    correction: CorrectionSummary,
    /// The blob's correction bytes are `model_ram[correction_at..len]`.
    correction_at: usize,
    len: usize,
}

/// A blob checked by `from_blob`, before it is active.
struct ParsedModel {
    calibration: CompiledCalibration<'static>,
    /// The correction as checked at load; the view is rebuilt from it over
    /// the RAM copy every tick in O(1).
    correction: CorrectionSummary,
    correction_at: usize,
    len: usize,
}

/// Parses a whole blob once: every check of [`CompiledCalibration::from_blob`],
/// then keeps the owned part.
fn parse_model(bytes: &[u8]) -> Result<ParsedModel, BlobError> {
    let c = CompiledCalibration::from_blob(bytes)?;
    // `from_blob` accepted it, so this re-split cannot fail; it only finds
    // where the correction bytes start (after the string model's padding).
    let (_, body) = spidar_protocol::blob::split_blob(bytes)?;
    let (_, rest) = split_body(body)?;
    Ok(ParsedModel {
        correction: c.correction.summary(),
        calibration: CompiledCalibration {
            header: c.header,
            head: c.head,
            correction: Correction::None,
        },
        correction_at: bytes.len() - rest.len(),
        len: bytes.len(),
    })
}

const IDENTITY: [[f32; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// The nominal calibration of a [`NominalGeometry`]: its string layout, anchors
/// and home, the device frame as room frame, a linear string law
/// `payout = r theta` per string (`winding_mm = [r, 0, 0, 0]`), no effects,
/// no correction. Channels without a string get a zero anchor and law
/// (never read). Built directly in its compiled form (no blob, no
/// allocation). `Err` names the field of the request that is out of range.
pub fn nominal_calibration(
    model: &NominalGeometry,
) -> Result<CompiledCalibration<'static>, &'static str> {
    let layout = StringLayout {
        active: model.active_strings,
        planar: model.planar,
    };
    if layout.count() < layout.dof() {
        return Err("active_strings");
    }
    let mut anchors = [[0.0f32; 3]; STRINGS];
    for i in layout.indices() {
        if !model.anchors_mm[i].iter().all(|x| x.is_finite()) {
            return Err("anchors_mm");
        }
        anchors[i] = model.anchors_mm[i];
    }
    if !model.home_mm.iter().all(|x| x.is_finite()) {
        return Err("home_mm");
    }
    let frame64 = Frame::<f64> {
        layout,
        anchors: anchors.map(|a| a.map(f64::from)),
        home: model.home_mm.map(f64::from),
        room_rotation: IDENTITY.map(|r| r.map(f64::from)),
        room_translation: [0.0; 3],
        room_scale: 1.0,
    };
    let mut laws = [CompiledStringLaw::default(); STRINGS];
    for (i, law) in laws.iter_mut().enumerate() {
        if !layout.is_active(i) {
            continue;
        }
        let r = model.pulley_radius_mm[i];
        if !(r.is_finite() && r > 0.0) {
            return Err("pulley_radius_mm");
        }
        let nominal = StringLaw::polynomial(model.counts_per_rev[i], [f64::from(r), 0.0, 0.0, 0.0]);
        *law = compile_string_law(&frame64, i, &nominal).map_err(|e| match e {
            StringLawCompileError::NotFinite { field, .. }
            | StringLawCompileError::DoesNotFit { field, .. }
            | StringLawCompileError::OutOfRange { field, .. } => match field {
                "counts_per_rev" => "counts_per_rev",
                "anchor" => "anchors_mm",
                "home" => "home_mm",
                _ => "pulley_radius_mm",
            },
            StringLawCompileError::StringOutOfRange { .. } => "anchors_mm",
        })?;
    }
    let header = ModelHeader {
        format_version: FORMAT_VERSION,
        kind: CorrectionKind::None,
        strings: layout.count() as u8,
        effects: 0,
        q_length: LENGTH_FRAC,
        q_position: POSITION_FRAC,
        q_weight: ACTIVATION_FRAC,
        hidden: 0,
        support_vectors: 0,
        body_len: 0,
        body_crc32: 0,
        model_id: 0,
        created_unix_s: 0,
    };
    let nominal_rule = crate::kinematics::KinematicsRule::default();
    Ok(CompiledCalibration {
        header,
        head: BlobHead {
            frame: Frame {
                layout,
                anchors,
                home: model.home_mm,
                room_rotation: IDENTITY,
                room_translation: [0.0; 3],
                room_scale: 1.0,
            },
            laws,
            effects: heapless::Vec::new(),
            // Nothing measured yet: every string weighs alike, and the
            // thresholds are the device's defaults.
            residual_weight: [1.0; STRINGS],
            exclusion_threshold_mm: nominal_rule.exclusion_threshold_mm as f32,
            fault_threshold_mm: nominal_rule.fault_threshold_mm as f32,
            home: None,
        },
        correction: Correction::None,
    })
}

/// The protocol's fault bits for the loop's faults.
///
/// The faults the wire names share its bits and pass as they are
/// ([`SafetyFaults::ON_THE_WIRE`]); `SLACK`, `FK_FAULT` and `NON_FINITE`
/// all report as `KINEMATICS` (the protocol has no bit of their own;
/// `State::slack` says which strings are slack); `OVERFORCE` is not
/// reported. `TENSION_CLAMPED` is present (not latched) while armed and the
/// tension distribution had to scale the force down.
pub fn protocol_faults(out: &LoopOutput, loop_overrun: bool) -> Faults {
    let f = out.faults;
    let mut bits = f.bits() & SafetyFaults::ON_THE_WIRE.bits();
    let mut set = |cond: bool, bit: Faults| {
        if cond {
            bits |= bit.0;
        }
    };
    set(
        f.intersects(SafetyFaults::SLACK | SafetyFaults::FK_FAULT | SafetyFaults::NON_FINITE),
        Faults::KINEMATICS,
    );
    set(
        out.armed && out.tension_status == TensionStatus::Scaled,
        Faults::TENSION_CLAMPED,
    );
    set(loop_overrun, Faults::LOOP_OVERRUN);
    Faults(bits)
}

/// What the loop outputs while there is no geometry: nothing moves.
fn idle_output(estop: bool, model_invalid: bool) -> LoopOutput {
    let mut faults = SafetyFaults::NONE;
    if estop {
        faults.insert(SafetyFaults::ESTOP);
    }
    if model_invalid {
        faults.insert(SafetyFaults::MODEL_INVALID);
    }
    LoopOutput {
        counts: [0; STRINGS],
        direction: [0; STRINGS],
        string_lengths_mm: [0.0; STRINGS],
        position_mm: [0.0; 3],
        fk_status: FkStatus::InvalidInput,
        excluded: None,
        room_q16: [0; 3],
        corrected_q16: [0; 3],
        force_n: [0.0; 3],
        tension_status: TensionStatus::Exact,
        rendered_fraction: 0.0,
        tensions_n: [0.0; STRINGS],
        faults,
        warnings: SafetyFaults::NONE,
        slack_mask: 0,
        armed: false,
    }
}

fn ms(now_us: u64) -> u32 {
    (now_us / 1000) as u32
}

fn store_error(e: StoreError) -> DeviceError {
    match e {
        StoreError::Flash(f) => DeviceError::Storage { code: f.code() },
        StoreError::EmptyBlob => DeviceError::InvalidArgument {
            field: name("total_len"),
        },
        StoreError::TooLarge {
            total_len,
            capacity,
        } => DeviceError::TooLarge {
            total_len,
            capacity,
        },
        StoreError::NoUpload => DeviceError::BadState(BadState::NoUpload),
        StoreError::OutOfOrder { expected_offset } => DeviceError::OutOfOrder { expected_offset },
        StoreError::PastEnd { end, total_len } => DeviceError::PastEnd { end, total_len },
        StoreError::Incomplete {
            next_offset,
            total_len,
        } => DeviceError::Incomplete {
            next_offset,
            total_len,
        },
        StoreError::CrcMismatch { expected, computed } => {
            DeviceError::CrcMismatch { expected, computed }
        }
        StoreError::RecordVerify => DeviceError::Storage {
            code: STORAGE_RECORD_VERIFY,
        },
    }
}

fn safety_config_field(e: SafetyConfigError) -> &'static str {
    match e {
        SafetyConfigError::Pretension => "pre_tension_n",
        SafetyConfigError::HeartbeatTimeout => "heartbeat_timeout_ms",
        SafetyConfigError::NonFinite
        | SafetyConfigError::TensionLimits
        | SafetyConfigError::ForceLimit
        | SafetyConfigError::SlackThreshold => "max_tension_n",
    }
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

    /// Installs pending safety limits once no fault is latched (installing
    /// them replaces the monitor, which must not clear a latched fault).
    fn apply_pending_safety(&mut self) {
        let (Some(cfg), Some(c)) = (self.pending_safety, self.controller.as_mut()) else {
            return;
        };
        if !c.safety().faults().is_empty() || c.safety().is_armed() {
            return;
        }
        if let Ok(mut m) = SafetyMonitor::new(cfg) {
            if let Some(t) = self.last_heartbeat_ms {
                m.heartbeat(t);
            }
            m.set_estop(self.estop);
            m.set_model_valid(!self.model_invalid);
            *c.safety() = m;
            c.set_tension_limits(
                crate::tension::TensionLimits {
                    t_min: cfg.t_min,
                    t_max: cfg.t_max,
                },
                cfg.pretension_n,
            );
        }
        self.pending_safety = None;
    }

    fn heartbeat(&mut self, now_ms: u32) {
        self.last_heartbeat_ms = Some(now_ms);
        if let Some(c) = self.controller.as_mut() {
            c.safety().heartbeat(now_ms);
        }
    }

    /// Geometry, limits and model changes need the motors off: not armed, and
    /// not holding pre-tension after a fault (a flash erase stalls the loop).
    fn refuse_if_armed(&mut self) -> Result<(), DeviceError> {
        if self.energized || self.armed() {
            Err(DeviceError::BadState(BadState::Armed))
        } else {
            Ok(())
        }
    }

    /// Answers one request at `now_us` (µs since boot, the clock of `tick`).
    ///
    /// Every request other than `Hello` is refused with `VersionMismatch`
    /// after a `Hello` that named another protocol version (until a matching
    /// `Hello`); every request that is not refused for the version counts as
    /// a heartbeat. Requests that change geometry, limits or the stored model
    /// are refused while armed.
    pub fn handle(&mut self, request: &Request<'_>, now_us: u64) -> Response {
        match self.handle_inner(request, now_us) {
            Ok(r) => r,
            Err(e) => Response::Error(e),
        }
    }

    fn handle_inner(
        &mut self,
        request: &Request<'_>,
        now_us: u64,
    ) -> Result<Response, DeviceError> {
        let now_ms = ms(now_us);
        if let Request::Hello { protocol_version } = *request {
            return Ok(self.hello(protocol_version, now_ms));
        }
        self.check_host_version()?;
        self.heartbeat(now_ms);
        match *request {
            Request::Hello { .. } | Request::Heartbeat => Ok(Response::Ack),
            Request::GetInfo => Ok(Response::Info(self.model_info())),
            Request::GetStats => {
                let mut s = self.stats;
                s.uptime_us = now_us;
                Ok(Response::Stats(s))
            }
            Request::SetNominalGeometry(ref m) => self.set_string_model(m),
            Request::SetLimits(limits) => {
                self.refuse_if_armed()?;
                self.set_limits(&limits)?;
                Ok(Response::Ack)
            }
            Request::SetForceTarget { force_n } => self.set_force_target(force_n),
            Request::SetGuidanceTarget {
                target_mm,
                d_min_mm,
                f_max_n,
            } => self.set_guidance_target(target_mm, d_min_mm, f_max_n),
            Request::Arm => self.arm(),
            Request::Disarm => self.disarm(),
            Request::ClearFaults => self.clear_faults(),
            Request::StreamOn { decimation } => self.stream_on(decimation),
            Request::StreamOff => {
                self.stream = None;
                self.frame_due = false;
                Ok(Response::Ack)
            }
            Request::UploadBegin {
                total_len,
                crc32,
                model_id,
            } => self.upload_begin(total_len, crc32, model_id),
            Request::UploadChunk { offset, data } => {
                self.refuse_if_armed()?;
                let next_offset = self.store.chunk(offset, data).map_err(store_error)?;
                Ok(Response::ChunkAck { next_offset })
            }
            Request::UploadCommit { crc32 } => {
                self.refuse_if_armed()?;
                self.commit(crc32)
            }
            Request::UploadAbort => {
                self.store.abort();
                Ok(Response::Ack)
            }
            Request::UploadStatus => Ok(Response::UploadStatus(self.upload_state())),
            Request::Home => self.home(now_us),
            Request::ClearModel => self.clear_model(),
        }
    }

    /// `Hello`: records the host's protocol version (a heartbeat if it is
    /// ours) and answers with what the device is.
    fn hello(&mut self, protocol_version: u16, now_ms: u32) -> Response {
        self.host_version = Some(protocol_version);
        if protocol_version == PROTOCOL_VERSION {
            self.heartbeat(now_ms);
        }
        Response::HelloAck(self.hello_ack())
    }

    /// `VersionMismatch` while the last `Hello` named another protocol
    /// version.
    fn check_host_version(&self) -> Result<(), DeviceError> {
        match self.host_version.filter(|&v| v != PROTOCOL_VERSION) {
            Some(host) => Err(DeviceError::VersionMismatch {
                device: PROTOCOL_VERSION,
                host,
            }),
            None => Ok(()),
        }
    }

    /// `GetInfo`: the committed model, if there is one.
    fn model_info(&self) -> Option<ModelInfo> {
        self.active.as_ref().map(|a| ModelInfo {
            slot: a.stored.slot.index(),
            header: a.calibration.header,
            blob_crc32: a.stored.record.blob_crc32,
        })
    }

    /// `SetNominalGeometry`: the nominal calibration (used while no model is
    /// committed); homes the controller if it is the first geometry.
    fn set_string_model(&mut self, m: &NominalGeometry) -> Result<Response, DeviceError> {
        self.refuse_if_armed()?;
        let cal = nominal_calibration(m)
            .map_err(|field| DeviceError::InvalidArgument { field: name(field) })?;
        self.nominal = Some(cal);
        self.ensure_controller();
        Ok(Response::Ack)
    }

    /// `SetForceTarget`: a finite force, N.
    fn set_force_target(&mut self, force_n: [f32; 3]) -> Result<Response, DeviceError> {
        if !force_n.iter().all(|f| f.is_finite()) {
            return Err(DeviceError::InvalidArgument {
                field: name("force_n"),
            });
        }
        self.target = Target::Force(force_n);
        Ok(Response::Ack)
    }

    /// `SetGuidanceTarget`: a finite target (mm), a finite non-negative
    /// `d_min_mm` and `f_max_n`.
    fn set_guidance_target(
        &mut self,
        target_mm: [f32; 3],
        d_min_mm: f32,
        f_max_n: f32,
    ) -> Result<Response, DeviceError> {
        if !target_mm.iter().all(|v| v.is_finite()) {
            return Err(DeviceError::InvalidArgument {
                field: name("target_mm"),
            });
        }
        if !(d_min_mm.is_finite() && d_min_mm >= 0.0) {
            return Err(DeviceError::InvalidArgument {
                field: name("d_min_mm"),
            });
        }
        if !(f_max_n.is_finite() && f_max_n >= 0.0) {
            return Err(DeviceError::InvalidArgument {
                field: name("f_max_n"),
            });
        }
        self.target = Target::Guidance {
            target_mm,
            d_min_mm,
            f_max_n,
        };
        Ok(Response::Ack)
    }

    /// `Disarm`: the loop stops rendering, the motor drivers are released.
    fn disarm(&mut self) -> Result<Response, DeviceError> {
        if let Some(c) = self.controller.as_mut() {
            c.safety().disarm();
        }
        self.energized = false;
        self.target = Target::Idle;
        Ok(Response::Ack)
    }

    /// `ClearFaults`: clears the latched faults and installs pending safety
    /// limits.
    fn clear_faults(&mut self) -> Result<Response, DeviceError> {
        if let Some(c) = self.controller.as_mut() {
            c.safety().clear();
        }
        self.loop_overrun = false;
        self.apply_pending_safety();
        Ok(Response::Ack)
    }

    /// `StreamOn`: a state frame every `decimation` ticks (not 0).
    fn stream_on(&mut self, decimation: u16) -> Result<Response, DeviceError> {
        if decimation == 0 {
            return Err(DeviceError::InvalidArgument {
                field: name("decimation"),
            });
        }
        self.stream = Some(Stream {
            decimation,
            count: 0,
        });
        self.frame_due = false;
        self.loop_max_us = 0;
        Ok(Response::Ack)
    }

    /// `UploadBegin`: starts (or resumes) an upload of at most
    /// [`Device::blob_capacity`] bytes.
    fn upload_begin(
        &mut self,
        total_len: u32,
        crc32: u32,
        model_id: u32,
    ) -> Result<Response, DeviceError> {
        self.refuse_if_armed()?;
        let capacity = self.blob_capacity();
        let next_offset = self
            .store
            .begin(total_len, crc32, model_id, capacity)
            .map_err(store_error)?;
        Ok(Response::ChunkAck { next_offset })
    }

    /// `UploadStatus`: the upload in progress, if any.
    fn upload_state(&self) -> UploadState {
        match self.store.upload() {
            None => UploadState::Idle,
            Some(u) => UploadState::InProgress {
                model_id: u.model_id,
                total_len: u.total_len,
                crc32: u.crc32,
                next_offset: u.received,
            },
        }
    }

    /// `Home`: the end-effector is at the calibration's home point now (the
    /// host's guided initialization); the target goes back to idle.
    fn home(&mut self, now_us: u64) -> Result<Response, DeviceError> {
        let cal = match (&self.active, &self.nominal) {
            (Some(a), _) => &a.calibration,
            (None, Some(n)) => n,
            (None, None) => return Err(DeviceError::BadState(BadState::NoGeometry)),
        };
        let Some(c) = self.controller.as_mut() else {
            return Err(DeviceError::BadState(BadState::NoGeometry));
        };
        c.home(cal, self.last_raw, ms(now_us));
        c.set_target(Target::Idle);
        self.declare_home(now_us);
        // A new capture: the blob's training slips (of the previous one)
        // no longer apply.
        let home_id = self.home_id();
        if let Some(c) = self.controller.as_mut() {
            c.set_home_id(Some(home_id));
        }
        self.target = Target::Idle;
        self.push_event(Event::Homed);
        Ok(Response::Ack)
    }

    /// `ClearModel`: erases the committed model; the nominal one (if any)
    /// runs again.
    fn clear_model(&mut self) -> Result<Response, DeviceError> {
        self.refuse_if_armed()?;
        self.store.clear().map_err(store_error)?;
        self.active = None;
        self.set_model_invalid(false);
        self.ensure_controller();
        Ok(Response::Ack)
    }

    fn set_model_invalid(&mut self, invalid: bool) {
        self.model_invalid = invalid;
        if let Some(c) = self.controller.as_mut() {
            c.safety().set_model_valid(!invalid);
        }
    }

    /// `SetLimits`: the safety part of the loop configuration. Takes effect
    /// at once unless a fault is latched, then at the `ClearFaults`/`Arm`
    /// that clears it.
    fn set_limits(&mut self, limits: &Limits) -> Result<(), DeviceError> {
        let mut cfg = self.config.control.safety;
        cfg.pretension_n = limits.pre_tension_n;
        cfg.t_max = limits.max_tension_n;
        cfg.t_min = cfg.t_min.min(limits.max_tension_n);
        cfg.heartbeat_timeout_ms = u32::from(limits.heartbeat_timeout_ms);
        cfg.validate().map_err(|e| DeviceError::InvalidArgument {
            field: name(safety_config_field(e)),
        })?;
        self.config.control.safety = cfg;
        self.pending_safety = Some(cfg);
        self.apply_pending_safety();
        Ok(())
    }

    /// `Arm`: clear the faults whose cause has gone, then arm, if the
    /// strings can pull the end-effector in every direction from where it
    /// is ([`crate::tension::force_closure`]); else `NotForceClosed`, and the
    /// loop goes on tracking unarmed.
    fn arm(&mut self) -> Result<Response, DeviceError> {
        self.loop_overrun = false;
        let Some(c) = self.controller.as_mut() else {
            return Err(DeviceError::BadState(BadState::NoGeometry));
        };
        c.safety().clear();
        self.apply_pending_safety();
        let frame = match (&self.active, &self.nominal) {
            (Some(a), _) => a.calibration.head.frame,
            (None, Some(n)) => n.head.frame,
            (None, None) => return Err(DeviceError::BadState(BadState::NoGeometry)),
        };
        let Some(c) = self.controller.as_mut() else {
            return Err(DeviceError::BadState(BadState::NoGeometry));
        };
        if self.estop {
            return Err(DeviceError::BadState(BadState::Faulted));
        }
        let config = c.config();
        let closure = force_closure(
            &frame.anchors,
            frame.layout,
            c.position(),
            config.tension_limits,
            &config.tension,
        );
        if let Err(
            status @ (TensionStatus::TooFewStrings { .. } | TensionStatus::OutsideAnchorHull),
        ) = closure
        {
            return Err(DeviceError::NotForceClosed {
                strings: frame.layout.count() as u8,
                dof: frame.layout.dof() as u8,
                too_few_strings: matches!(status, TensionStatus::TooFewStrings { .. }),
            });
        }
        c.safety()
            .arm()
            .map_err(|_| DeviceError::BadState(BadState::Faulted))?;
        self.energized = true;
        self.target = Target::Idle;
        Ok(Response::Ack)
    }

    /// `UploadCommit`: read back, check, validate with `from_blob`, commit,
    /// then swap the RAM buffers and switch the loop to the new model.
    fn commit(&mut self, crc32: u32) -> Result<Response, DeviceError> {
        let expected_id = self.store.upload().map(|u| u.model_id);
        let validate = |bytes: &[u8]| -> Result<ParsedModel, DeviceError> {
            let p = parse_model(bytes).map_err(|e| DeviceError::BlobRejected(e.into()))?;
            if Some(p.calibration.header.model_id) != expected_id {
                return Err(DeviceError::InvalidArgument {
                    field: name("model_id"),
                });
            }
            Ok(p)
        };
        let (stored, parsed) = match self.store.commit(crc32, self.spare_ram, validate) {
            Ok(ok) => ok,
            Err(CommitError::Store(e)) => return Err(store_error(e)),
            Err(CommitError::Rejected(e)) => return Err(e),
        };
        core::mem::swap(&mut self.model_ram, &mut self.spare_ram);
        let model_id = parsed.calibration.header.model_id;
        self.active = Some(ActiveModel {
            stored,
            correction: parsed.correction,
            calibration: parsed.calibration,
            correction_at: parsed.correction_at,
            len: parsed.len,
        });
        self.set_model_invalid(false);
        self.ensure_controller();
        Ok(Response::Committed { model_id })
    }

    /// One control-loop iteration: [`Controller::step`] on the active
    /// calibration (or idle without geometry), events, stream decimation.
    pub fn tick(&mut self, input: &TickInput) -> LoopOutput {
        self.last_raw = input.raw_counts;
        self.last_now_us = input.now_us;
        self.estop = input.estop;
        if input.estop {
            self.energized = false;
        }
        let loop_input = LoopInput {
            raw_counts: input.raw_counts,
            now_ms: ms(input.now_us),
            now_us: input.now_us as u32,
            estop: input.estop,
        };
        let Device {
            controller,
            active,
            nominal,
            model_ram,
            model_invalid,
            target,
            ..
        } = self;
        let out = match controller.as_mut() {
            None => idle_output(input.estop, *model_invalid),
            Some(c) => {
                c.set_target(*target);
                // Only a flashed model's string law is calibrated.
                c.set_lengths_calibrated(active.is_some());
                match (active.as_ref(), nominal.as_ref()) {
                    (Some(a), _) => {
                        let kind = a.calibration.header.kind;
                        if kind == CorrectionKind::None {
                            c.step(&a.calibration, &loop_input)
                        } else {
                            let bytes = model_ram.get(a.correction_at..a.len).unwrap_or(&[]);
                            match Correction::from_summary(&a.correction, bytes) {
                                Ok(correction) => {
                                    c.step_with(&a.calibration.head, &correction, &loop_input)
                                }
                                Err(_) => {
                                    // The RAM copy no longer checks: fault,
                                    // pre-tension, no correction.
                                    *model_invalid = true;
                                    c.safety().set_model_valid(false);
                                    c.step(&a.calibration, &loop_input)
                                }
                            }
                        }
                    }
                    (None, Some(n)) => c.step(n, &loop_input),
                    (None, None) => idle_output(input.estop, *model_invalid),
                }
            }
        };
        self.after_tick(&out);
        self.last_out = out;
        out
    }

    fn after_tick(&mut self, out: &LoopOutput) {
        let faults = protocol_faults(out, self.loop_overrun);
        // Latched faults only: TENSION_CLAMPED comes and goes with the force.
        let raised = Faults(faults.0 & !self.prev_faults.0 & !Faults::TENSION_CLAMPED.0);
        if raised.0 != 0 {
            self.push_event(Event::Fault { raised });
        }
        if self.prev_armed && !out.armed && !out.faults.is_empty() {
            if raised.contains(Faults::HEARTBEAT_LOST) {
                self.stats.heartbeat_losses = self.stats.heartbeat_losses.wrapping_add(1);
                self.push_event(Event::HeartbeatLost);
            }
            self.push_event(Event::Disarmed { faults });
        }
        self.prev_faults = faults;
        self.prev_armed = out.armed;
        if let Some(s) = self.stream.as_mut() {
            s.count = s.count.saturating_add(1);
            if s.count >= s.decimation {
                s.count = 0;
                self.frame_due = true;
            }
        }
    }

    /// Records the duration of the last loop iteration (µs, measured by the
    /// caller around `tick` and the I/O); one longer than the loop period
    /// counts an overrun and latches `LOOP_OVERRUN` (cleared by
    /// `ClearFaults`/`Arm`; it does not disarm).
    pub fn record_loop_time(&mut self, loop_us: u16) {
        self.loop_us = loop_us;
        self.loop_max_us = self.loop_max_us.max(loop_us);
        if u32::from(loop_us) > self.config.loop_period_us {
            self.stats.loop_overruns = self.stats.loop_overruns.wrapping_add(1);
            self.loop_overrun = true;
        }
    }

    /// The state frame due after the last tick, if streaming and the
    /// decimation says so (at most one per `decimation` ticks).
    pub fn state_frame(&mut self) -> Option<State> {
        if !core::mem::take(&mut self.frame_due) {
            return None;
        }
        let out = &self.last_out;
        let state = State {
            time_us: self.last_now_us,
            since_home_us: self.last_now_us.saturating_sub(self.home_us),
            home_id: self.home_id(),
            counts: out.counts,
            position_mm: out.position_mm,
            corrected_mm: out.corrected_q16,
            tensions_n: out.tensions_n,
            rendered_force_n: if out.armed {
                out.force_n.map(|f| f * out.rendered_fraction)
            } else {
                [0.0; 3]
            },
            faults: protocol_faults(out, self.loop_overrun),
            slack: out.slack_mask,
            excluded: out.excluded.filter(|&i| usize::from(i) < STRINGS),
            loop_us: self.loop_us,
            loop_max_us: self.loop_max_us,
            armed: out.armed,
            motors_on: self.motors_enabled(),
            model_id: self.active.as_ref().map(|a| a.calibration.header.model_id),
        };
        self.loop_max_us = 0;
        Some(state)
    }
}

/// The device's side of the byte stream: decodes request frames, gets each
/// answered, encodes the reply; encodes stream frames with their own
/// sequence counter. Holds no device state, so the firmware keeps it in its
/// link task and locks the [`Device`] only for `handle`.
pub struct DeviceLink {
    rx: FrameDecoder,
    tx: [u8; MAX_FRAME],
    stream_seq: u16,
    tx_frames: u32,
}

impl Default for DeviceLink {
    fn default() -> Self {
        Self::new()
    }
}

impl DeviceLink {
    pub const fn new() -> Self {
        DeviceLink {
            rx: FrameDecoder::new(),
            tx: [0; MAX_FRAME],
            stream_seq: 0,
            tx_frames: 0,
        }
    }

    /// Drops a half-received frame (reconnect); keeps the counters.
    pub fn reset(&mut self) {
        self.rx.reset();
    }

    /// Counters of the link layer.
    pub fn counters(&self) -> LinkCounters {
        LinkCounters {
            rx: self.rx.stats(),
            tx_frames: self.tx_frames,
        }
    }

    /// Consumes `input` up to the end of the first frame in it and returns
    /// the bytes consumed (at least 1 for non-empty input) and the reply
    /// frame to send, if that frame needs one. `handle` answers a request
    /// (e.g. `device.set_link_counters(c); device.handle(req, now)`).
    ///
    /// Corrupt frames (COBS, CRC, undecodable) are counted and get no reply;
    /// a frame with an out-of-range field gets `InvalidArgument` naming it; a
    /// `Hello` of another protocol version that does not decode gets the
    /// device's `HelloAck` (through `handle`).
    pub fn push(
        &mut self,
        input: &[u8],
        handle: impl FnOnce(&Request<'_>, LinkCounters) -> Response,
    ) -> (usize, Option<&[u8]>) {
        let mut counters = self.counters();
        let (used, result) = self.rx.push::<Request<'_>>(input);
        let Some(result) = result else {
            return (used, None);
        };
        let (seq, response) = match result {
            Ok(Packet { seq, msg }) => {
                counters.rx.ok = counters.rx.ok.wrapping_add(1);
                (seq, handle(&msg, counters))
            }
            Err(FrameError::Invalid { field, seq }) => (
                seq,
                Response::Error(DeviceError::InvalidArgument { field: name(field) }),
            ),
            Err(FrameError::VersionMismatch { peer, seq, .. }) => (
                seq,
                handle(
                    &Request::Hello {
                        protocol_version: peer,
                    },
                    counters,
                ),
            ),
            Err(_) => return (used, None),
        };
        match encode_device_message(seq, &DeviceMessage::Reply(response), &mut self.tx) {
            Ok(frame) => {
                self.tx_frames = self.tx_frames.wrapping_add(1);
                (used, Some(frame))
            }
            Err(_) => (used, None),
        }
    }

    fn stream_frame(&mut self, msg: &DeviceMessage) -> Option<&[u8]> {
        let seq = self.stream_seq;
        let frame = encode_device_message(seq, msg, &mut self.tx).ok()?;
        self.stream_seq = seq.wrapping_add(1);
        self.tx_frames = self.tx_frames.wrapping_add(1);
        Some(frame)
    }

    /// A state frame, with the next stream sequence number.
    pub fn encode_state(&mut self, state: &State) -> Option<&[u8]> {
        self.stream_frame(&DeviceMessage::State(*state))
    }

    /// An event frame, with the next stream sequence number.
    pub fn encode_event(&mut self, event: &Event) -> Option<&[u8]> {
        self.stream_frame(&DeviceMessage::Event(*event))
    }
}

#[cfg(all(test, feature = "alloc"))]
mod tests;
