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
//! nominal one built from `SetStringModel` (anchors, home, linear string law
//! `payout = r theta`, no effects, no correction), else none: no geometry,
//! the loop idles and `Arm` is refused with `BadState(NoGeometry)`.
//!
//! **Home** (counts 0, end-effector at the calibration's home point) is
//! declared when the controller is created: at boot if a stored model loads,
//! else when the first geometry arrives (`SetStringModel` or a commit), and
//! again at each `Home` request (the host's guided initialization). A
//! later change of calibration keeps the counts (same physical home);
//! `ClearModel` without a nominal model drops the geometry, and the next one
//! homes again.
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
    Faults, FrameDecoder, FrameError, HelloAck, Limits, LinkStats, ModelInfo, Packet, Request,
    Response, State, StringModel, UploadState, MAX_CHUNK, MAX_FRAME, PROTOCOL_VERSION,
};

use crate::blob::{split_body, BlobHead, CompiledCalibration, LENGTH_FRAC};
use crate::control::{ControlConfig, Controller, LoopInput, LoopOutput, Target};
use crate::correction::{Correction, CorrectionSummary, ACTIVATION_FRAC, POSITION_FRAC};
use crate::kinematics::FkStatus;
use crate::model::{Frame, StringLaw, StringLayout};
use crate::model_store::{CommitError, ModelFlash, ModelStore, StoreError, StoredModel};
use crate::safety::{Faults as SafetyFaults, SafetyConfig, SafetyConfigError, SafetyMonitor};
use crate::string_law::{compile_string_law, CompileError, CompiledStringLaw};
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

/// The nominal calibration of a [`StringModel`]: its string layout, anchors
/// and home, the device frame as room frame, a linear string law
/// `payout = r theta` per string (`winding_mm = [r, 0, 0, 0]`), no effects,
/// no correction. Channels without a string get a zero anchor and law
/// (never read). Built directly in its compiled form (no blob, no
/// allocation). `Err` names the field of the request that is out of range.
pub fn nominal_calibration(
    model: &StringModel,
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
            CompileError::NotFinite { field, .. }
            | CompileError::DoesNotFit { field, .. }
            | CompileError::OutOfRange { field, .. } => match field {
                "counts_per_rev" => "counts_per_rev",
                "anchor" => "anchors_mm",
                "home" => "home_mm",
                _ => "pulley_radius_mm",
            },
            CompileError::StringOutOfRange { .. } => "anchors_mm",
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
        },
        correction: Correction::None,
    })
}

/// The protocol's fault bits for the loop's faults.
///
/// `SLACK`, `FK_FAULT` and `NON_FINITE` all report as `KINEMATICS` (the
/// protocol has no bit of their own; `State::slack` says which strings are
/// slack). `TENSION_CLAMPED` is present (not latched) while armed and the
/// tension distribution had to scale the force down.
pub fn protocol_faults(out: &LoopOutput, loop_overrun: bool) -> Faults {
    let f = out.faults;
    let mut bits = 0u16;
    let mut set = |cond: bool, bit: Faults| {
        if cond {
            bits |= bit.0;
        }
    };
    set(
        f.contains(SafetyFaults::HEARTBEAT_LOST),
        Faults::HEARTBEAT_LOST,
    );
    set(
        f.intersects(SafetyFaults::SLACK | SafetyFaults::FK_FAULT | SafetyFaults::NON_FINITE),
        Faults::KINEMATICS,
    );
    set(f.contains(SafetyFaults::ESTOP), Faults::ESTOP);
    set(
        f.contains(SafetyFaults::MODEL_INVALID),
        Faults::MODEL_INVALID,
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
            self.home_us = self.last_now_us;
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
            self.host_version = Some(protocol_version);
            if protocol_version == PROTOCOL_VERSION {
                self.heartbeat(now_ms);
            }
            return Ok(Response::HelloAck(self.hello_ack()));
        }
        if let Some(host) = self.host_version.filter(|&v| v != PROTOCOL_VERSION) {
            return Err(DeviceError::VersionMismatch {
                device: PROTOCOL_VERSION,
                host,
            });
        }
        self.heartbeat(now_ms);
        match *request {
            Request::Hello { .. } | Request::Heartbeat => Ok(Response::Ack),
            Request::GetInfo => Ok(Response::Info(self.active.as_ref().map(|a| ModelInfo {
                slot: a.stored.slot.index(),
                header: a.calibration.header,
                blob_crc32: a.stored.record.blob_crc32,
            }))),
            Request::GetStats => {
                let mut s = self.stats;
                s.uptime_us = now_us;
                Ok(Response::Stats(s))
            }
            Request::SetStringModel(ref m) => {
                self.refuse_if_armed()?;
                let cal = nominal_calibration(m)
                    .map_err(|field| DeviceError::InvalidArgument { field: name(field) })?;
                self.nominal = Some(cal);
                self.ensure_controller();
                Ok(Response::Ack)
            }
            Request::SetLimits(limits) => {
                self.refuse_if_armed()?;
                self.set_limits(&limits)?;
                Ok(Response::Ack)
            }
            Request::SetForceTarget { force_n } => {
                if !force_n.iter().all(|f| f.is_finite()) {
                    return Err(DeviceError::InvalidArgument {
                        field: name("force_n"),
                    });
                }
                self.target = Target::Force(force_n);
                Ok(Response::Ack)
            }
            Request::SetGuidanceTarget {
                target_mm,
                d_min_mm,
                f_max_n,
            } => {
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
            Request::Arm => self.arm(),
            Request::Disarm => {
                if let Some(c) = self.controller.as_mut() {
                    c.safety().disarm();
                }
                self.energized = false;
                self.target = Target::Idle;
                Ok(Response::Ack)
            }
            Request::ClearFaults => {
                if let Some(c) = self.controller.as_mut() {
                    c.safety().clear();
                }
                self.loop_overrun = false;
                self.apply_pending_safety();
                Ok(Response::Ack)
            }
            Request::StreamOn { decimation } => {
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
            Request::StreamOff => {
                self.stream = None;
                self.frame_due = false;
                Ok(Response::Ack)
            }
            Request::UploadBegin {
                total_len,
                crc32,
                model_id,
            } => {
                self.refuse_if_armed()?;
                let capacity = self.blob_capacity();
                let next_offset = self
                    .store
                    .begin(total_len, crc32, model_id, capacity)
                    .map_err(store_error)?;
                Ok(Response::ChunkAck { next_offset })
            }
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
            Request::UploadStatus => Ok(Response::UploadStatus(match self.store.upload() {
                None => UploadState::Idle,
                Some(u) => UploadState::InProgress {
                    model_id: u.model_id,
                    total_len: u.total_len,
                    crc32: u.crc32,
                    next_offset: u.received,
                },
            })),
            Request::Home => {
                let cal = match (&self.active, &self.nominal) {
                    (Some(a), _) => &a.calibration,
                    (None, Some(n)) => n,
                    (None, None) => return Err(DeviceError::BadState(BadState::NoGeometry)),
                };
                let Some(c) = self.controller.as_mut() else {
                    return Err(DeviceError::BadState(BadState::NoGeometry));
                };
                c.home(cal, self.last_raw, now_ms);
                self.home_us = now_us;
                c.set_target(Target::Idle);
                self.target = Target::Idle;
                self.push_event(Event::Homed);
                Ok(Response::Ack)
            }
            Request::ClearModel => {
                self.refuse_if_armed()?;
                self.store.clear().map_err(store_error)?;
                self.active = None;
                self.set_model_invalid(false);
                self.ensure_controller();
                Ok(Response::Ack)
            }
        }
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
mod tests {
    use super::*;
    use crate::blob::compile;
    use crate::correction::{CorrectionModel, NnModel, OutputMode, Standardization};
    use crate::kinematics::inverse_kinematics;
    use crate::model::Calibration;
    use crate::model_store::RamFlash;
    use spidar_protocol::blob::CRC32;
    use spidar_protocol::{encode, encode_request, BlobRejection, Message, SeqTracker};
    use std::vec::Vec;

    const SLOT: usize = 16 * 1024;
    type Flash = RamFlash<SLOT>;
    const CPR: u32 = 4096;
    const RADIUS: f64 = 10.0;
    const H: f64 = 1100.0;

    fn anchors() -> [[f64; 3]; STRINGS] {
        let mut anchors = [[0.0; 3]; STRINGS];
        for (i, a) in anchors.iter_mut().enumerate() {
            *a = [
                if i & 1 == 0 { -H } else { H },
                if i & 2 == 0 { -H } else { H },
                if i & 4 == 0 { -H } else { H },
            ];
        }
        anchors
    }

    fn nn(hidden: usize) -> CorrectionModel {
        let s = Standardization {
            mean: [0.0, 0.0, 1500.0],
            std: [500.0; 3],
        };
        let w = |k: usize| ((k * 37 % 17) as f64 - 8.0) / 20.0;
        CorrectionModel::Nn(NnModel {
            input: s,
            output: s,
            w1: (0..hidden).map(|h| [w(h), w(h + 1), w(h + 2)]).collect(),
            b1: (0..hidden).map(|h| w(h + 3) / 4.0).collect(),
            w2: [0, 1, 2].map(|a| (0..hidden).map(|h| w(h + a + 5) / 1000.0).collect()),
            b2: [0.0; 3],
            mode: OutputMode::Residual,
        })
    }

    fn calibration(correction: CorrectionModel) -> Calibration {
        Calibration {
            frame: Frame {
                layout: StringLayout::ALL,
                anchors: anchors(),
                home: [0.0; 3],
                room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                room_translation: [0.0, 0.0, 1500.0],
                room_scale: 1.0,
            },
            strings: [StringLaw::polynomial(CPR, [RADIUS, 0.0, 0.0, 0.0]); STRINGS],
            effects: alloc::vec![],
            correction,
        }
    }

    /// Raw counters for the end-effector at `p` (device frame), counters
    /// reading 1000 at home.
    fn raw_at(p: [f64; 3]) -> [u16; STRINGS] {
        let lengths = inverse_kinematics(&anchors(), p);
        let home = inverse_kinematics(&anchors(), [0.0; 3]);
        let mut raw = [0u16; STRINGS];
        for i in 0..STRINGS {
            let theta = (lengths[i] - home[i]) / RADIUS;
            let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
            raw[i] = (1000 + counts) as u16;
        }
        raw
    }

    fn config() -> DeviceConfig {
        DeviceConfig {
            firmware_version: [0, 1, 0],
            device_id: [7; 12],
            loop_period_us: 100,
            control: ControlConfig::default(),
        }
    }

    fn string_model() -> StringModel {
        StringModel {
            counts_per_rev: [CPR; STRINGS],
            pulley_radius_mm: [RADIUS as f32; STRINGS],
            anchors_mm: anchors().map(|a| a.map(|v| v as f32)),
            home_mm: [0.0; 3],
            active_strings: 0xFF,
            planar: false,
        }
    }

    /// A host talking to a device through encoded frames, one ms per tick.
    struct Bench<'m> {
        dev: Device<'m, Flash>,
        link: DeviceLink,
        host_rx: FrameDecoder,
        seq: u16,
        now_us: u64,
        stream: Vec<Packet<DeviceMessage>>,
        stream_seq: SeqTracker,
    }

    impl<'m> Bench<'m> {
        fn new(flash: Flash, ram: &'m mut [u8], spare: &'m mut [u8]) -> Self {
            Self::new_at(flash, ram, spare, raw_at([0.0; 3]))
        }

        /// Boots with the encoders reading `raw`.
        fn new_at(
            flash: Flash,
            ram: &'m mut [u8],
            spare: &'m mut [u8],
            raw: [u16; STRINGS],
        ) -> Self {
            Bench {
                dev: Device::new(config(), flash, ram, spare, raw, 0).unwrap(),
                link: DeviceLink::new(),
                host_rx: FrameDecoder::new(),
                seq: 0,
                now_us: 0,
                stream: Vec::new(),
                stream_seq: SeqTracker::default(),
            }
        }

        /// Feeds bytes to the device; returns the replies.
        fn feed(&mut self, bytes: &[u8]) -> Vec<Packet<DeviceMessage>> {
            let mut replies = Vec::new();
            let mut rest = bytes;
            while !rest.is_empty() {
                let dev = &mut self.dev;
                let now = self.now_us;
                let (used, reply) = self.link.push(rest, |req, c| {
                    dev.set_link_counters(c);
                    dev.handle(req, now)
                });
                if let Some(r) = reply {
                    let r = r.to_vec();
                    self.host_rx
                        .feed_device_messages(&r, |p| replies.push(p.expect("reply decodes")));
                }
                rest = &rest[used..];
            }
            replies
        }

        fn request(&mut self, req: &Request<'_>) -> Response {
            self.seq = self.seq.wrapping_add(1);
            let mut buf = [0u8; MAX_FRAME];
            let frame = encode_request(self.seq, req, &mut buf).unwrap().to_vec();
            let mut replies = self.feed(&frame);
            assert_eq!(replies.len(), 1, "one reply to {req:?}");
            let p = replies.remove(0);
            assert_eq!(p.seq, self.seq);
            match p.msg {
                DeviceMessage::Reply(r) => r,
                other => panic!("not a reply: {other:?}"),
            }
        }

        fn tick_at(&mut self, raw: [u16; STRINGS]) -> LoopOutput {
            self.now_us += 1000;
            let out = self.dev.tick(&TickInput {
                raw_counts: raw,
                now_us: self.now_us,
                estop: false,
            });
            self.dev.record_loop_time(40);
            let mut frames = Vec::new();
            while let Some(e) = self.dev.take_event() {
                frames.push(self.link.encode_event(&e).unwrap().to_vec());
            }
            if let Some(s) = self.dev.state_frame() {
                frames.push(self.link.encode_state(&s).unwrap().to_vec());
            }
            for f in frames {
                let stream = &mut self.stream;
                let tracker = &mut self.stream_seq;
                self.host_rx.feed_device_messages(&f, |p| {
                    let p = p.expect("stream frame decodes");
                    tracker.observe(p.seq);
                    stream.push(p);
                });
            }
            out
        }

        fn upload(&mut self, blob: &[u8], model_id: u32, chunk: usize) -> Response {
            let crc = CRC32.checksum(blob);
            let r = self.request(&Request::UploadBegin {
                total_len: blob.len() as u32,
                crc32: crc,
                model_id,
            });
            let Response::ChunkAck { mut next_offset } = r else {
                return r;
            };
            while (next_offset as usize) < blob.len() {
                let end = (next_offset as usize + chunk).min(blob.len());
                match self.request(&Request::UploadChunk {
                    offset: next_offset,
                    data: &blob[next_offset as usize..end],
                }) {
                    Response::ChunkAck { next_offset: n } => next_offset = n,
                    other => return other,
                }
            }
            self.request(&Request::UploadCommit { crc32: crc })
        }
    }

    fn bad_state(s: BadState) -> Response {
        Response::Error(DeviceError::BadState(s))
    }

    /// A frame whose message is not checked by `validate` (to send out-of-range
    /// fields the way a buggy host would).
    fn unchecked_frame<T: serde::Serialize>(seq: u16, msg: &T) -> Vec<u8> {
        let mut payload = postcard::to_allocvec(&(seq, msg)).unwrap();
        let crc = CRC32.checksum(&payload);
        payload.extend_from_slice(&crc.to_le_bytes());
        // COBS (the canonical algorithm), then the delimiter.
        let mut out = std::vec![0u8];
        let (mut code_at, mut code) = (0usize, 1u8);
        for &byte in &payload {
            if byte != 0 {
                out.push(byte);
                code += 1;
            }
            if byte == 0 || code == 0xFF {
                out[code_at] = code;
                code_at = out.len();
                out.push(0);
                code = 1;
            }
        }
        out[code_at] = code;
        out.push(0);
        out
    }

    /// `Hello` of a future protocol version that carries a new field.
    #[derive(serde::Serialize)]
    struct FutureHello {
        tag: u8,
        protocol_version: u16,
        new_field: u32,
    }

    impl Message for FutureHello {
        fn validate(&self) -> Result<(), &'static str> {
            Ok(())
        }
        fn peek_protocol_version(_: &[u8]) -> Option<u16> {
            None
        }
    }

    #[test]
    fn full_session_through_frames() {
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        // A host flushing the line first: a lone delimiter is ignored.
        assert!(b.feed(&[0]).is_empty());
        let Response::HelloAck(ack) = b.request(&Request::Hello {
            protocol_version: PROTOCOL_VERSION,
        }) else {
            panic!("no HelloAck")
        };
        assert_eq!(ack.protocol_version, PROTOCOL_VERSION);
        assert_eq!(ack.max_blob_len, (SLOT - 32) as u32);
        assert_eq!(usize::from(ack.max_chunk), MAX_CHUNK);
        assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
        assert_eq!(b.request(&Request::Arm), bad_state(BadState::NoGeometry));

        // Upload in chunks, with a gap, a resend, a status and a resume.
        let blob = compile(&calibration(nn(16)), 42, 1_700_000_000).unwrap();
        let crc = CRC32.checksum(&blob);
        let begin = Request::UploadBegin {
            total_len: blob.len() as u32,
            crc32: crc,
            model_id: 42,
        };
        assert_eq!(b.request(&begin), Response::ChunkAck { next_offset: 0 });
        assert_eq!(
            b.request(&Request::UploadChunk {
                offset: 0,
                data: &blob[..200]
            }),
            Response::ChunkAck { next_offset: 200 }
        );
        assert_eq!(
            b.request(&Request::UploadChunk {
                offset: 208,
                data: &blob[208..300]
            }),
            Response::Error(DeviceError::OutOfOrder {
                expected_offset: 200
            })
        );
        assert_eq!(
            b.request(&Request::UploadChunk {
                offset: 0,
                data: &blob[..200]
            }),
            Response::ChunkAck { next_offset: 200 }
        );
        assert_eq!(
            b.request(&Request::UploadStatus),
            Response::UploadStatus(UploadState::InProgress {
                model_id: 42,
                total_len: blob.len() as u32,
                crc32: crc,
                next_offset: 200
            })
        );
        // The link dropped: the host asks again and resumes where it stood.
        b.link.reset();
        assert_eq!(b.request(&begin), Response::ChunkAck { next_offset: 200 });
        let mut next = 200usize;
        while next < blob.len() {
            let end = (next + MAX_CHUNK).min(blob.len());
            assert_eq!(
                b.request(&Request::UploadChunk {
                    offset: next as u32,
                    data: &blob[next..end]
                }),
                Response::ChunkAck {
                    next_offset: end as u32
                }
            );
            next = end;
        }
        assert_eq!(
            b.request(&Request::UploadCommit { crc32: crc ^ 1 }),
            Response::Error(DeviceError::CrcMismatch {
                expected: crc,
                computed: crc ^ 1
            })
        );
        assert_eq!(
            b.request(&Request::UploadCommit { crc32: crc }),
            Response::Committed { model_id: 42 }
        );
        assert_eq!(
            b.request(&Request::UploadStatus),
            Response::UploadStatus(UploadState::Idle)
        );
        let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
            panic!("no model info")
        };
        assert_eq!(info.slot, 0);
        assert_eq!(info.header.model_id, 42);
        assert_eq!(info.header.kind, CorrectionKind::Nn);
        assert_eq!(info.blob_crc32, crc);

        // Arm, render a force, stream.
        let home = raw_at([0.0; 3]);
        b.tick_at(home);
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        assert!(b.dev.motors_enabled());
        assert_eq!(
            b.request(&Request::SetForceTarget {
                force_n: [0.0, 0.0, 2.0]
            }),
            Response::Ack
        );
        assert_eq!(
            b.request(&Request::StreamOn { decimation: 4 }),
            Response::Ack
        );
        b.stream.clear();
        let p = [100.0, -50.0, 200.0];
        let mut out = None;
        for k in 0..40 {
            if k % 5 == 0 {
                assert_eq!(b.request(&Request::Heartbeat), Response::Ack);
            }
            out = Some(b.tick_at(raw_at(p)));
        }
        let out = out.unwrap();
        assert!(out.armed && out.faults.is_empty(), "{out:?}");
        let f = crate::tension::resultant_force(
            &anchors().map(|a| a.map(|v| v as f32)),
            out.position_mm,
            &out.tensions_n,
        );
        assert!((f[2] - 2.0).abs() < 1e-2 && f[0].abs() < 1e-2, "{f:?}");
        let states: Vec<State> = b
            .stream
            .iter()
            .filter_map(|p| match p.msg {
                DeviceMessage::State(s) => Some(s),
                _ => None,
            })
            .collect();
        assert_eq!(states.len(), 10);
        assert_eq!(b.stream_seq.lost, 0);
        let last = states.last().unwrap();
        assert!(last.armed);
        assert_eq!(last.model_id, Some(42));
        assert_eq!(last.counts, out.counts);
        assert_eq!(last.corrected_mm, out.corrected_q16);
        assert_eq!(last.loop_us, 40);
        // Booted (and homed) at device time 0: both clocks agree.
        assert_eq!(last.since_home_us, last.time_us);
        for (got, want) in last.position_mm.iter().zip(p) {
            assert!((got - want as f32).abs() < 0.05);
        }
        // No model change while armed.
        assert_eq!(b.request(&begin), bad_state(BadState::Armed));
        assert_eq!(b.request(&Request::ClearModel), bad_state(BadState::Armed));
        assert_eq!(
            b.request(&Request::SetStringModel(string_model())),
            bad_state(BadState::Armed)
        );

        // Corrupted frames: rejected, counted, no reply.
        let mut buf = [0u8; MAX_FRAME];
        let mut bad = encode_request(900, &Request::Heartbeat, &mut buf)
            .unwrap()
            .to_vec();
        bad[2] ^= 0x10;
        assert!(b.feed(&bad).is_empty());
        assert!(b.feed(&[0x05, 0x01, 0x00]).is_empty()); // bad COBS / too short
        let Response::Stats(stats) = b.request(&Request::GetStats) else {
            panic!("no stats")
        };
        assert!(stats.rx.crc + stats.rx.cobs >= 1, "{stats:?}");
        assert_eq!(stats.rx.rejected(), 2);
        assert!(stats.rx.ok > 30);
        assert_eq!(stats.uptime_us, b.now_us);
        // An out-of-range field is answered, naming it.
        let frame = unchecked_frame(
            901,
            &Request::SetForceTarget {
                force_n: [f32::NAN, 0.0, 0.0],
            },
        );
        let replies = b.feed(&frame);
        assert_eq!(replies.len(), 1);
        assert_eq!(replies[0].seq, 901);
        assert_eq!(
            replies[0].msg,
            DeviceMessage::Reply(Response::Error(DeviceError::InvalidArgument {
                field: name("force_n")
            }))
        );

        // Heartbeat loss: the host goes silent.
        b.stream.clear();
        let timeout = config().control.safety.heartbeat_timeout_ms;
        let last_request_ms = (b.now_us / 1000) as u32;
        let pretension = config().control.safety.pretension_n;
        let mut dropped_at = None;
        for _ in 0..2 * timeout {
            let out = b.tick_at(raw_at(p));
            let age = (b.now_us / 1000) as u32 - last_request_ms;
            if age <= timeout {
                assert!(out.armed, "still armed {age} ms after the last request");
            } else if dropped_at.is_none() {
                dropped_at = Some(age);
                assert!(out.tensions_n.iter().all(|&t| t == pretension), "{out:?}");
                assert!(out.faults.contains(SafetyFaults::HEARTBEAT_LOST));
            }
        }
        assert_eq!(dropped_at, Some(timeout + 1));
        // Strings stay taut: drivers on at pre-tension until Disarm.
        assert!(b.dev.motors_enabled());
        let events: Vec<Event> = b
            .stream
            .iter()
            .filter_map(|p| match p.msg {
                DeviceMessage::Event(e) => Some(e),
                _ => None,
            })
            .collect();
        assert!(events.contains(&Event::HeartbeatLost), "{events:?}");
        assert!(events.contains(&Event::Fault {
            raised: Faults::HEARTBEAT_LOST
        }));
        // Still holding pre-tension: no flash work until Disarm.
        assert_eq!(b.request(&begin), bad_state(BadState::Armed));
        let last = b
            .stream
            .iter()
            .rev()
            .find_map(|p| match p.msg {
                DeviceMessage::State(s) => Some(s),
                _ => None,
            })
            .unwrap();
        assert!(!last.armed && last.faults.contains(Faults::HEARTBEAT_LOST));
        assert_eq!(last.tensions_n, [pretension; STRINGS]);
        assert_eq!(b.stream_seq.lost, 0);
        let Response::Stats(stats) = b.request(&Request::GetStats) else {
            panic!("no stats")
        };
        assert_eq!(stats.heartbeat_losses, 1);
        // Arm clears the fault and arms again.
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        assert!(b.tick_at(raw_at(p)).armed);
        assert_eq!(b.request(&Request::Disarm), Response::Ack);
        assert!(!b.dev.motors_enabled());

        // Version mismatch: typed error until a matching Hello.
        let Response::HelloAck(ack) = b.request(&Request::Hello {
            protocol_version: 99,
        }) else {
            panic!("no HelloAck")
        };
        assert_eq!(ack.protocol_version, PROTOCOL_VERSION);
        assert_eq!(
            b.request(&Request::GetInfo),
            Response::Error(DeviceError::VersionMismatch {
                device: PROTOCOL_VERSION,
                host: 99
            })
        );
        assert_eq!(
            b.request(&Request::Arm),
            Response::Error(DeviceError::VersionMismatch {
                device: PROTOCOL_VERSION,
                host: 99
            })
        );
        // A future Hello that this version cannot decode still gets a HelloAck.
        let mut buf = [0u8; MAX_FRAME];
        let future = encode(
            77,
            &FutureHello {
                tag: 0,
                protocol_version: PROTOCOL_VERSION + 1,
                new_field: 5,
            },
            &mut buf,
        )
        .unwrap()
        .to_vec();
        let replies = b.feed(&future);
        assert_eq!(replies.len(), 1);
        assert_eq!(replies[0].seq, 77);
        assert!(matches!(
            replies[0].msg,
            DeviceMessage::Reply(Response::HelloAck(HelloAck {
                protocol_version: PROTOCOL_VERSION,
                ..
            }))
        ));
        assert!(matches!(
            b.request(&Request::Hello {
                protocol_version: PROTOCOL_VERSION
            }),
            Response::HelloAck(_)
        ));
        assert!(matches!(
            b.request(&Request::GetInfo),
            Response::Info(Some(_))
        ));
    }

    #[test]
    fn models_survive_power_cycles_and_uploads_never_disturb_the_active_one() {
        let blob1 = compile(&calibration(CorrectionModel::None), 1, 0).unwrap();
        let blob2 = compile(&calibration(nn(8)), 2, 0).unwrap();
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        assert_eq!(
            b.upload(&blob1, 1, 256),
            Response::Committed { model_id: 1 }
        );
        b.request(&Request::StreamOn { decimation: 1 });
        // Half of model 2, then the loop still runs model 1.
        let crc2 = CRC32.checksum(&blob2);
        b.request(&Request::UploadBegin {
            total_len: blob2.len() as u32,
            crc32: crc2,
            model_id: 2,
        });
        b.request(&Request::UploadChunk {
            offset: 0,
            data: &blob2[..100],
        });
        b.tick_at(raw_at([0.0; 3]));
        let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
            panic!("no state")
        };
        assert_eq!(s.model_id, Some(1));
        // Power cycle mid-upload: model 1, intact, and no upload.
        let flash = b.dev.into_flash();
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
        let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
            panic!("model 1 lost")
        };
        assert_eq!(info.header.model_id, 1);
        assert_eq!(info.blob_crc32, CRC32.checksum(&blob1));
        assert_eq!(
            b.request(&Request::UploadStatus),
            Response::UploadStatus(UploadState::Idle)
        );
        // The stored model homed the controller at boot: arming works at once.
        b.tick_at(raw_at([0.0; 3]));
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        b.request(&Request::Disarm);
        // Commit model 2, power cycle: model 2 in slot B.
        assert_eq!(
            b.upload(&blob2, 2, 100),
            Response::Committed { model_id: 2 }
        );
        let flash = b.dev.into_flash();
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
        let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
            panic!("model 2 lost")
        };
        assert_eq!((info.slot, info.header.model_id), (1, 2));
        // A power loss in the middle of the next upload keeps model 2.
        let mut flash = b.dev.into_flash();
        flash.cut_after(10);
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
        let r = b.upload(&blob1, 1, 256);
        assert!(
            matches!(r, Response::Error(DeviceError::Storage { .. })),
            "{r:?}"
        );
        let mut flash = b.dev.into_flash();
        flash.power_cycle();
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
        let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
            panic!("model 2 lost")
        };
        assert_eq!(info.header.model_id, 2);
        // ClearModel: no model, no geometry.
        assert_eq!(b.request(&Request::ClearModel), Response::Ack);
        assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
        assert_eq!(b.request(&Request::Arm), bad_state(BadState::NoGeometry));
        let flash = b.dev.into_flash();
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
        assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    }

    #[test]
    fn bad_uploads_are_refused_with_the_reason() {
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        let blob = compile(&calibration(CorrectionModel::None), 5, 0).unwrap();
        assert_eq!(
            b.request(&Request::UploadChunk {
                offset: 0,
                data: &blob[..10]
            }),
            bad_state(BadState::NoUpload)
        );
        assert_eq!(
            b.request(&Request::UploadCommit { crc32: 0 }),
            bad_state(BadState::NoUpload)
        );
        assert_eq!(
            b.request(&Request::UploadBegin {
                total_len: 1 << 20,
                crc32: 0,
                model_id: 5
            }),
            Response::Error(DeviceError::TooLarge {
                total_len: 1 << 20,
                capacity: (SLOT - 32) as u32
            })
        );
        assert_eq!(
            b.request(&Request::UploadBegin {
                total_len: 0,
                crc32: 0,
                model_id: 5
            }),
            Response::Error(DeviceError::InvalidArgument {
                field: name("total_len")
            })
        );
        // A corrupted body whose whole-blob CRC matches: from_blob refuses it.
        let mut bad = blob.clone();
        let last = bad.len() - 1;
        bad[last] ^= 0x01;
        let r = b.upload(&bad, 5, 256);
        assert!(
            matches!(
                r,
                Response::Error(DeviceError::BlobRejected(BlobRejection::BodyCrc { .. }))
            ),
            "{r:?}"
        );
        // Announced model id differs from the blob's.
        assert_eq!(
            b.upload(&blob, 6, 256),
            Response::Error(DeviceError::InvalidArgument {
                field: name("model_id")
            })
        );
        // Not a blob at all.
        assert_eq!(
            b.upload(&[0x55; 100], 5, 64),
            Response::Error(DeviceError::BlobRejected(BlobRejection::BadMagic))
        );
        assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
        // Incomplete, then abort.
        let crc = CRC32.checksum(&blob);
        b.request(&Request::UploadBegin {
            total_len: blob.len() as u32,
            crc32: crc,
            model_id: 5,
        });
        assert_eq!(
            b.request(&Request::UploadChunk {
                offset: 0,
                data: &blob[..blob.len().min(200) + 56]
            }),
            Response::ChunkAck {
                next_offset: blob.len().min(200) as u32 + 56
            }
        );
        assert_eq!(
            b.request(&Request::UploadChunk {
                offset: blob.len() as u32 - 10,
                data: &[0; 20]
            }),
            Response::Error(DeviceError::PastEnd {
                end: blob.len() as u32 + 10,
                total_len: blob.len() as u32
            })
        );
        assert_eq!(
            b.request(&Request::UploadCommit { crc32: crc }),
            Response::Error(DeviceError::Incomplete {
                next_offset: blob.len().min(200) as u32 + 56,
                total_len: blob.len() as u32
            })
        );
        assert_eq!(b.request(&Request::UploadAbort), Response::Ack);
        assert_eq!(
            b.request(&Request::UploadStatus),
            Response::UploadStatus(UploadState::Idle)
        );
        assert_eq!(b.upload(&blob, 5, 64), Response::Committed { model_id: 5 });
    }

    #[test]
    fn home_rezeroes_the_strings_where_the_operator_holds_the_end_effector() {
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        // Booted with the end-effector 40 mm off the true home: the nominal
        // model homes there, so every position is off by 40 mm.
        let off = [40.0, -25.0, 10.0];
        let mut b = Bench::new_at(Flash::new(), ram.bytes(), spare.bytes(), raw_at(off));
        // No geometry yet: nothing to home.
        assert_eq!(b.request(&Request::Home), bad_state(BadState::NoGeometry));
        assert_eq!(
            b.request(&Request::SetStringModel(string_model())),
            Response::Ack
        );
        let out = b.tick_at(raw_at([0.0; 3]));
        assert!(
            (out.position_mm[0] + 40.0).abs() < 0.5,
            "{:?}",
            out.position_mm
        );
        // Armed with a force: Home is accepted, the force is dropped.
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        assert_eq!(
            b.request(&Request::SetForceTarget {
                force_n: [1.0, 0.0, 0.0]
            }),
            Response::Ack
        );
        let out = b.tick_at(raw_at([0.0; 3]));
        assert_eq!(out.force_n, [1.0, 0.0, 0.0]);
        assert_eq!(
            b.request(&Request::StreamOn { decimation: 1 }),
            Response::Ack
        );
        let homed_at_us = b.now_us;
        assert_eq!(b.request(&Request::Home), Response::Ack);
        let mut out = b.tick_at(raw_at([0.0; 3]));
        for _ in 0..5 {
            out = b.tick_at(raw_at([0.0; 3]));
        }
        // The state frame says when it was sampled, since boot and since home.
        let last = b
            .stream
            .iter()
            .rev()
            .find_map(|p| match p.msg {
                DeviceMessage::State(s) => Some(s),
                _ => None,
            })
            .unwrap();
        assert_eq!(last.time_us, b.now_us);
        assert_eq!(last.since_home_us, b.now_us - homed_at_us);
        assert_eq!(last.since_home_us, 6000);
        assert_eq!(out.counts, [0; STRINGS]);
        assert!(out.armed);
        assert_eq!(out.force_n, [0.0; 3]);
        for k in 0..3 {
            assert!(out.position_mm[k].abs() < 1e-3, "{:?}", out.position_mm);
        }
        // A move of 100 mm now reads as 100 mm.
        let out = b.tick_at(raw_at([100.0, 0.0, 0.0]));
        assert!(
            (out.position_mm[0] - 100.0).abs() < 0.5,
            "{:?}",
            out.position_mm
        );
        let homed = b
            .stream
            .iter()
            .filter(|p| matches!(p.msg, DeviceMessage::Event(Event::Homed)))
            .count();
        assert_eq!(homed, 1);
    }

    /// Raw counters for the end-effector at `p` with strings from `anchors`,
    /// reading 1000 at `home`.
    fn raw_for(anchors: &[[f64; 3]; STRINGS], home: [f64; 3], p: [f64; 3]) -> [u16; STRINGS] {
        let lengths = inverse_kinematics(anchors, p);
        let at_home = inverse_kinematics(anchors, home);
        core::array::from_fn(|i| {
            let theta = (lengths[i] - at_home[i]) / RADIUS;
            let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
            (1000 + counts) as u16
        })
    }

    /// Devices with fewer strings: the layout travels in `SetStringModel`;
    /// `Arm` is refused, saying why, when the strings cannot pull in every
    /// direction, and the device still tracks and streams; a tetrahedron of
    /// 4 strings around the end-effector arms and renders, with the unused
    /// channels at tension 0.
    #[test]
    fn string_layouts_arm_only_when_force_closed_and_track_either_way() {
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        // Fewer strings than degrees of freedom: refused, naming the field.
        let mut m = string_model();
        m.active_strings = 0b0000_0011;
        assert_eq!(
            b.dev.handle(&Request::SetStringModel(m), 0),
            Response::Error(DeviceError::InvalidArgument {
                field: name("active_strings")
            })
        );
        // Unused channels need no valid law or anchor.
        let mut m = string_model();
        m.active_strings = 0b0001_0110;
        m.counts_per_rev[0] = 0;
        m.pulley_radius_mm[3] = f32::NAN;
        m.anchors_mm[7] = [f32::NAN; 3];
        assert_eq!(b.request(&Request::SetStringModel(m)), Response::Ack);
        // Three strings in space: never force closed.
        assert_eq!(
            b.request(&Request::Arm),
            Response::Error(DeviceError::NotForceClosed {
                strings: 3,
                dof: 3,
                too_few_strings: true
            })
        );

        // Four strings from the ceiling (a hanging design): enough strings,
        // but they only pull up.
        let h = 1100.0;
        let mut hanging = [[0.0f64; 3]; STRINGS];
        for (i, (x, y)) in [(-h, -h), (h, -h), (h, h), (-h, h)].into_iter().enumerate() {
            hanging[i] = [x, y, h];
        }
        let mut m = string_model();
        m.active_strings = 0b0000_1111;
        m.anchors_mm = hanging.map(|a| a.map(|v| v as f32));
        assert_eq!(b.request(&Request::SetStringModel(m)), Response::Ack);
        assert_eq!(
            b.request(&Request::Arm),
            Response::Error(DeviceError::NotForceClosed {
                strings: 4,
                dof: 3,
                too_few_strings: false
            })
        );
        // Tracking and the stream go on unarmed.
        assert_eq!(
            b.request(&Request::StreamOn { decimation: 1 }),
            Response::Ack
        );
        let p = [120.0, -80.0, -200.0];
        let mut out = b.tick_at(raw_for(&hanging, [0.0; 3], [0.0; 3]));
        for _ in 0..20 {
            out = b.tick_at(raw_for(&hanging, [0.0; 3], p));
        }
        assert!(!out.armed);
        for (got, want) in out.position_mm.iter().zip(p) {
            assert!((got - want as f32).abs() < 0.1, "{out:?}");
        }
        let pre = config().control.safety.pretension_n;
        assert_eq!(out.tensions_n, [pre, pre, pre, pre, 0.0, 0.0, 0.0, 0.0]);
        let last_state = b
            .stream
            .iter()
            .rev()
            .find_map(|p| match &p.msg {
                DeviceMessage::State(s) => Some(*s),
                _ => None,
            })
            .expect("state frames");
        assert!(!last_state.armed);
        assert!((last_state.position_mm[0] - 120.0).abs() < 0.1);

        // A tetrahedron (cube corners 0, 3, 5, 6) around the end-effector:
        // armed, renders, unused channels at 0. Home is declared again.
        let mut m = string_model();
        m.active_strings = 0b0110_1001;
        assert_eq!(b.request(&Request::SetStringModel(m)), Response::Ack);
        assert_eq!(b.request(&Request::Home), Response::Ack);
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        assert_eq!(
            b.request(&Request::SetForceTarget {
                force_n: [1.0, -0.5, 0.5]
            }),
            Response::Ack
        );
        let home_raw = raw_for(&hanging, [0.0; 3], p);
        let shift = |q: [f64; 3]| -> [u16; STRINGS] {
            // Counters continue from where they were at Home.
            let d = raw_for(&anchors(), [0.0; 3], q);
            core::array::from_fn(|i| home_raw[i].wrapping_add(d[i].wrapping_sub(1000)))
        };
        let q = [100.0, 50.0, -60.0];
        let mut out = b.tick_at(shift([0.0; 3]));
        for _ in 0..10 {
            out = b.tick_at(shift(q));
        }
        assert!(out.armed && out.faults.is_empty(), "{out:?}");
        assert_eq!(out.tension_status, TensionStatus::Exact);
        for i in [1, 2, 4, 7] {
            assert_eq!(out.tensions_n[i], 0.0);
        }
        let f = crate::tension::resultant_force(
            &anchors().map(|a| a.map(|v| v as f32)),
            out.position_mm,
            &core::array::from_fn(|i| {
                if [0, 3, 5, 6].contains(&i) {
                    out.tensions_n[i]
                } else {
                    0.0
                }
            }),
        );
        for (got, want) in f.iter().zip([1.0, -0.5, 0.5]) {
            assert!((got - want).abs() < 1e-3, "{f:?}");
        }
    }

    #[test]
    fn nominal_string_model_limits_and_estop() {
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        let mut m = string_model();
        m.pulley_radius_mm[3] = -1.0;
        assert_eq!(
            b.dev.handle(&Request::SetStringModel(m), 0),
            Response::Error(DeviceError::InvalidArgument {
                field: name("pulley_radius_mm")
            })
        );
        m = string_model();
        m.anchors_mm[2][1] = f32::INFINITY;
        assert_eq!(
            b.dev.handle(&Request::SetStringModel(m), 0),
            Response::Error(DeviceError::InvalidArgument {
                field: name("anchors_mm")
            })
        );
        // The nominal model homes the device now (end-effector at home).
        assert_eq!(
            b.request(&Request::SetStringModel(string_model())),
            Response::Ack
        );
        assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
        let limits = Limits {
            pre_tension_n: 2.0,
            max_tension_n: 20.0,
            heartbeat_timeout_ms: 50,
        };
        assert_eq!(b.request(&Request::SetLimits(limits)), Response::Ack);
        assert_eq!(
            b.dev.handle(
                &Request::SetLimits(Limits {
                    heartbeat_timeout_ms: 0,
                    ..limits
                }),
                0
            ),
            Response::Error(DeviceError::InvalidArgument {
                field: name("heartbeat_timeout_ms")
            })
        );
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        assert_eq!(
            b.request(&Request::SetLimits(limits)),
            bad_state(BadState::Armed)
        );
        let p = [-150.0, 80.0, 30.0];
        let out = b.tick_at(raw_at(p));
        assert!(out.armed, "{out:?}");
        for (got, want) in out.position_mm.iter().zip(p) {
            assert!((got - want as f32).abs() < 0.05, "{out:?}");
        }
        // Idle: the distribution's internal tension level, within the limits.
        assert!(
            out.tensions_n.iter().all(|&t| (0.5..=20.0).contains(&t)),
            "{out:?}"
        );
        // The new heartbeat timeout: 50 ms (Arm at T, ticks at T+1..=T+50).
        for _ in 0..49 {
            assert!(b.tick_at(raw_at(p)).armed);
        }
        let out = b.tick_at(raw_at(p));
        assert!(!out.armed && out.faults.contains(SafetyFaults::HEARTBEAT_LOST));
        assert_eq!(out.tensions_n, [2.0; STRINGS]);
        // Guidance target, then the emergency stop.
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        assert_eq!(
            b.request(&Request::SetGuidanceTarget {
                target_mm: [0.0, 0.0, 0.0],
                d_min_mm: 5.0,
                f_max_n: 3.0
            }),
            Response::Ack
        );
        assert!(b.tick_at(raw_at(p)).force_n.iter().any(|f| f.abs() > 0.1));
        b.now_us += 1000;
        let out = b.dev.tick(&TickInput {
            raw_counts: raw_at(p),
            now_us: b.now_us,
            estop: true,
        });
        assert!(!out.armed && out.faults.contains(SafetyFaults::ESTOP));
        assert!(!b.dev.motors_enabled());
        assert_eq!(b.request(&Request::Arm), bad_state(BadState::Faulted));
        let out = b.tick_at(raw_at(p)); // e-stop released
        assert!(out.faults.contains(SafetyFaults::ESTOP)); // still latched
        assert_eq!(b.request(&Request::Arm), Response::Ack);
        assert!(b.tick_at(raw_at(p)).armed);
        // Overrun: latched, reported, cleared by ClearFaults.
        b.dev.record_loop_time(150);
        b.request(&Request::StreamOn { decimation: 1 });
        b.tick_at(raw_at(p));
        let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
            panic!("no state")
        };
        assert!(s.faults.contains(Faults::LOOP_OVERRUN));
        assert_eq!(b.dev.stats().loop_overruns, 1);
        b.request(&Request::ClearFaults);
        b.tick_at(raw_at(p));
        let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
            panic!("no state")
        };
        assert!(!s.faults.contains(Faults::LOOP_OVERRUN));
        assert!(s.armed);
    }

    /// Arbitrary bytes and arbitrary upload requests never panic the device.
    #[test]
    fn garbage_never_panics() {
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        let mut x = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let mut bytes = Vec::new();
        for _ in 0..20_000 {
            let v = next();
            bytes.push(if v % 7 == 0 { 0 } else { v as u8 });
        }
        for piece in bytes.chunks(61) {
            let dev = &mut b.dev;
            let mut rest = piece;
            while !rest.is_empty() {
                let (used, _) = b.link.push(rest, |req, _| dev.handle(req, 0));
                rest = &rest[used..];
            }
        }
        let data = [0xA5u8; MAX_CHUNK];
        for _ in 0..2000 {
            let v = next();
            let offset = (v >> 8) as u32 % 20_000;
            let len = 1 + (v >> 40) as usize % MAX_CHUNK;
            let req = match v % 5 {
                0 => Request::UploadBegin {
                    total_len: (v >> 20) as u32 % 20_000,
                    crc32: v as u32,
                    model_id: 1,
                },
                1 | 2 => Request::UploadChunk {
                    offset,
                    data: &data[..len],
                },
                3 => Request::UploadCommit {
                    crc32: (v >> 3) as u32,
                },
                _ => Request::UploadStatus,
            };
            b.dev.handle(&req, 0);
            b.tick_at(raw_at([0.0; 3]));
        }
    }

    /// What a tick costs with the borrow handled three ways (host timings;
    /// `cargo test -p spidar-core --release --lib device::tests::tick_cost
    /// -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn tick_cost() {
        use std::time::Instant;
        const N: u32 = 20_000;
        for hidden in [0usize, 16, 64] {
            let model = if hidden == 0 {
                CorrectionModel::None
            } else {
                nn(hidden)
            };
            let blob = compile(&calibration(model), 1, 0).unwrap();
            let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
            let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
            assert_eq!(b.upload(&blob, 1, 256), Response::Committed { model_id: 1 });
            let raw = raw_at([10.0, 20.0, 30.0]);
            let input = |k: u32| TickInput {
                raw_counts: raw,
                now_us: u64::from(k) * 100,
                estop: false,
            };
            let t = Instant::now();
            for k in 0..N {
                std::hint::black_box(b.dev.tick(&input(k)));
            }
            let device_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
            let cal = CompiledCalibration::from_blob(&blob).unwrap();
            let mut ctl = Controller::new(ControlConfig::default(), &cal, raw, 0).unwrap();
            let li = |k: u32| LoopInput {
                raw_counts: raw,
                now_ms: k / 10,
                estop: false,
            };
            let t = Instant::now();
            for k in 0..N {
                std::hint::black_box(ctl.step(&cal, &li(k)));
            }
            let step_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
            let t = Instant::now();
            for k in 0..N {
                let c = CompiledCalibration::from_blob(std::hint::black_box(&blob)).unwrap();
                std::hint::black_box(ctl.step(&c, &li(k)));
            }
            let reparse_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
            std::println!(
                "hidden {hidden:3}, blob {:5} B: step alone {step_ns:7.0} ns, Device::tick \
                 {device_ns:7.0} ns (+{:5.0}), from_blob every tick {reparse_ns:7.0} ns (+{:5.0}); \
                 BlobHead {} B",
                blob.len(),
                device_ns - step_ns,
                reparse_ns - step_ns,
                core::mem::size_of::<BlobHead>()
            );
        }
    }
}
