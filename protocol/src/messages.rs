//! The messages: [`Request`] (host -> device) and [`DeviceMessage`]
//! (device -> host: replies, the [`State`] stream and [`Event`]s).
//!
//! All types are plain serde types encoded with postcard (varints for
//! integers, 4-byte little-endian `f32`, enum tags as varints). Their
//! worst-case encoded sizes are listed in the crate documentation and checked
//! by the tests against [`crate::MAX_FRAME`].
//!
//! **Frozen layout.** So that a protocol version mismatch is always reported
//! as such and never as an undecodable frame, these never change between
//! protocol versions: `Request::Hello` is variant 0 of [`Request`] and its only
//! field is `protocol_version: u16`; `DeviceMessage::Reply` is variant 0 of
//! [`DeviceMessage`], `Response::HelloAck` is variant 0 of [`Response`] and
//! `protocol_version: u16` is the first field of [`HelloAck`]. Everything else
//! may change when [`crate::PROTOCOL_VERSION`] changes.

use core::fmt;

use serde::{Deserialize, Serialize};

use crate::blob::{BlobError, ModelHeader};
use crate::{MAX_CHUNK, MAX_NAME, STRINGS};

/// A short name sent on the wire (a field name in an error), at most
/// [`MAX_NAME`] bytes of UTF-8.
pub type Name = heapless::String<MAX_NAME>;

/// Builds a [`Name`], cutting `s` at a character boundary if it is longer
/// than [`MAX_NAME`] bytes.
pub fn name(s: &str) -> Name {
    let mut n = Name::new();
    for c in s.chars() {
        if n.push(c).is_err() {
            break;
        }
    }
    n
}

// ---------------------------------------------------------------------------
// Host -> device
// ---------------------------------------------------------------------------

/// A request from the host. The device answers every request with exactly one
/// [`DeviceMessage::Reply`] carrying the request's sequence number.
///
/// Any valid request also counts as a heartbeat (see [`Limits`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Request<'a> {
    /// Opens a session. Frozen: variant 0, one field. The device answers
    /// [`Response::HelloAck`] with its own version whatever the host's; if the
    /// versions differ it answers every other request with
    /// [`DeviceError::VersionMismatch`] until a matching `Hello`.
    Hello {
        /// [`crate::PROTOCOL_VERSION`] of the host.
        protocol_version: u16,
    },
    /// Keeps the device armed: without a valid request for
    /// [`Limits::heartbeat_timeout_ms`] an armed device drops every tension to
    /// [`Limits::pre_tension_n`], raises [`Faults::HEARTBEAT_LOST`] and sends
    /// [`Event::HeartbeatLost`]. Answered by [`Response::Ack`].
    Heartbeat,
    /// Describes the active model: answered by [`Response::Info`].
    GetInfo,
    /// Link and loop counters: answered by [`Response::Stats`].
    GetStats,
    /// Nominal geometry and string law, used when no model blob is loaded (a
    /// loaded blob's calibration takes precedence). Refused while armed.
    SetNominalGeometry(NominalGeometry),
    /// Safety limits. Refused while armed.
    SetLimits(Limits),
    /// Force mode: render this force at the end-effector. Answered by `Ack`.
    SetForceTarget {
        /// Force on the end-effector, device frame, newtons.
        force_n: [f32; 3],
    },
    /// Guidance mode: pull the end-effector towards a target point.
    SetGuidanceTarget {
        /// Target point, room frame (after correction), millimetres.
        target_mm: [f32; 3],
        /// Dead zone: no force closer than this to the target, millimetres (>= 0).
        d_min_mm: f32,
        /// Largest guidance force, newtons (>= 0).
        f_max_n: f32,
    },
    /// Enables the motors (at pre-tension until a target is set).
    Arm,
    /// Disables the motors.
    Disarm,
    /// Clears latched [`Faults`] whose cause has gone.
    ClearFaults,
    /// Starts the [`State`] stream.
    StreamOn {
        /// One state frame every `decimation` control-loop iterations (>= 1);
        /// the loop period is [`HelloAck::loop_period_us`].
        decimation: u16,
    },
    /// Stops the [`State`] stream.
    StreamOff,
    /// Starts (or resumes) a model upload into the staging slot. If an upload
    /// with the same `total_len`, `crc32` and `model_id` is in progress the
    /// device keeps what it has; otherwise it starts over. Answered by
    /// [`Response::ChunkAck`] with the offset to send next (0 for a new upload).
    UploadBegin {
        /// Length of the whole blob (header + body), bytes.
        total_len: u32,
        /// CRC-32 ([`crate::blob::CRC32`]) of the whole blob.
        crc32: u32,
        /// `model_id` of the blob's header.
        model_id: u32,
    },
    /// Bytes `offset..offset + data.len()` of the blob. `offset` must be the
    /// device's `next_offset`; a chunk that lies wholly before it (a resend
    /// after a lost ack) is acknowledged without effect; anything else gets
    /// [`DeviceError::OutOfOrder`]. Answered by [`Response::ChunkAck`].
    UploadChunk {
        /// Byte offset of `data` in the blob.
        offset: u32,
        /// At most [`MAX_CHUNK`] bytes (and at most [`HelloAck::max_chunk`]).
        data: &'a [u8],
    },
    /// Checks the staged blob (length, whole-blob CRC, header, body CRC,
    /// dimensions) and makes it the active model atomically: answered by
    /// [`Response::Committed`], or by an error and the old model stays.
    UploadCommit {
        /// CRC-32 of the whole blob, as in `UploadBegin`.
        crc32: u32,
    },
    /// Drops the staged upload. Answered by `Ack`.
    UploadAbort,
    /// Where the upload stands: answered by [`Response::UploadStatus`].
    UploadStatus,
    /// Erases the active model (the device falls back to [`NominalGeometry`]).
    /// Refused while armed.
    ClearModel,
    /// Declares home now: the current encoder readings become the zero of
    /// every string and the end-effector is taken to be at the active
    /// calibration's home point (the operator holds it there; see the guided
    /// initialization of the host, `spidar init`). Allowed while armed: the
    /// target drops to idle (pre-tension), so that a force computed from the
    /// old position is not rendered from the new one. Refused with
    /// `BadState(NoGeometry)` without a calibration. Answered by `Ack` and
    /// [`Event::Homed`] in the stream.
    Home,
}

/// Nominal geometry and string law of the device. Arrays are indexed by
/// encoder channel; entries of channels that carry no string
/// (`active_strings`) are ignored and not checked.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct NominalGeometry {
    /// Quadrature encoder counts per pulley revolution, per string (> 0).
    pub counts_per_rev: [u32; STRINGS],
    /// Pulley winding radius per string, millimetres (> 0).
    pub pulley_radius_mm: [f32; STRINGS],
    /// String exit points, device frame, millimetres; index = encoder index.
    pub anchors_mm: [[f32; 3]; STRINGS],
    /// End-effector position at initialization, device frame, millimetres.
    pub home_mm: [f32; 3],
    /// Bit `i` set: channel `i` carries a string (`0xFF`: all 8, a
    /// Scalable-SPIDAR). At least as many strings as degrees of freedom.
    pub active_strings: u8,
    /// The end-effector moves in the anchors' plane (2 degrees of freedom);
    /// `false`: in space (3).
    pub planar: bool,
}

impl NominalGeometry {
    /// Whether channel `i` carries a string.
    pub const fn is_active(&self, i: usize) -> bool {
        i < STRINGS && self.active_strings & (1 << i) != 0
    }

    /// Degrees of freedom of the end-effector's position: 2 planar, 3.
    pub const fn dof(&self) -> u8 {
        if self.planar {
            2
        } else {
            3
        }
    }
}

/// Safety limits.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    /// Tension every string keeps when armed and idle, and drops to on
    /// heartbeat loss, newtons (>= 0).
    pub pre_tension_n: f32,
    /// Largest tension of any string, newtons (>= `pre_tension_n`).
    pub max_tension_n: f32,
    /// Longest silence from the host while armed, milliseconds (> 0).
    pub heartbeat_timeout_ms: u16,
}

// ---------------------------------------------------------------------------
// Device -> host
// ---------------------------------------------------------------------------

/// Everything the device sends.
///
/// The frame's sequence number is the request's for `Reply`; `State` and
/// `Event` share one counter of their own, incremented per frame sent, so the
/// host counts lost stream frames from its gaps ([`crate::SeqTracker`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum DeviceMessage {
    /// The answer to a request. Frozen: variant 0.
    Reply(Response),
    /// One sample of the device state (while the stream is on).
    State(State),
    /// Something the host did not ask about.
    Event(Event),
}

/// The answer to a [`Request`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Response {
    /// Answer to `Hello`. Frozen: variant 0.
    HelloAck(HelloAck),
    /// The request was carried out.
    Ack,
    /// Answer to `GetInfo`: the active model, or `None` if there is none.
    Info(Option<ModelInfo>),
    /// Answer to `GetStats`.
    Stats(LinkStats),
    /// Answer to `UploadBegin` and `UploadChunk`: the device holds bytes
    /// `0..next_offset` of the blob; send from there.
    ChunkAck { next_offset: u32 },
    /// The blob passed every check and is now the active model.
    Committed { model_id: u32 },
    /// Answer to `UploadStatus`.
    UploadStatus(UploadState),
    /// The request was refused; nothing changed.
    Error(DeviceError),
}

/// Answer to `Hello`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HelloAck {
    /// [`crate::PROTOCOL_VERSION`] of the device. Frozen: first field.
    pub protocol_version: u16,
    /// Firmware version, `[major, minor, patch]`.
    pub firmware_version: [u16; 3],
    /// Unique device id (the STM32 96-bit UID, little-endian words).
    pub device_id: [u8; 12],
    /// What this firmware supports.
    pub capabilities: Capabilities,
    /// Largest `UploadChunk::data` the device accepts, bytes (1..=[`MAX_CHUNK`]).
    pub max_chunk: u16,
    /// Largest model blob the device can store, bytes.
    pub max_blob_len: u32,
    /// Control-loop period, microseconds.
    pub loop_period_us: u32,
}

/// Feature bits of [`HelloAck::capabilities`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Capabilities(pub u32);

impl Capabilities {
    /// Force rendering (`SetForceTarget`).
    pub const FORCE: Self = Self(1 << 0);
    /// Guidance (`SetGuidanceTarget`).
    pub const GUIDANCE: Self = Self(1 << 1);
    /// Evaluates NN position corrections.
    pub const MODEL_NN: Self = Self(1 << 2);
    /// Evaluates SVR position corrections.
    pub const MODEL_SVR: Self = Self(1 << 3);
    /// Keeps an interrupted upload across a reconnect (`UploadBegin` resumes).
    pub const UPLOAD_RESUME: Self = Self(1 << 4);

    /// `true` if every bit of `other` is set.
    pub const fn contains(self, other: Self) -> bool {
        self.0 & other.0 == other.0
    }
    /// Both sets of bits.
    pub const fn union(self, other: Self) -> Self {
        Self(self.0 | other.0)
    }
}

/// The active model, as stored on the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModelInfo {
    /// Storage slot the model was loaded from (A/B slots: 0 or 1).
    pub slot: u8,
    /// The blob's checked header (kind, dimensions, Q formats, body CRC, model id).
    pub header: ModelHeader,
    /// CRC-32 of the whole blob (header + body), as given to `UploadCommit`.
    pub blob_crc32: u32,
}

/// Where a model upload stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum UploadState {
    /// No upload in progress.
    Idle,
    /// An upload was begun and not committed or aborted.
    InProgress {
        model_id: u32,
        /// Announced blob length, bytes.
        total_len: u32,
        /// Announced whole-blob CRC-32.
        crc32: u32,
        /// Bytes `0..next_offset` are staged.
        next_offset: u32,
    },
}

/// Counters of the device's side of the link and of its control loop. All
/// counters wrap.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LinkStats {
    /// The device's frame decoder: frames accepted and rejected, by reason.
    pub rx: crate::frame::DecodeStats,
    /// Frames sent.
    pub tx_frames: u32,
    /// Stream frames dropped because the link was busy.
    pub tx_dropped: u32,
    /// Control-loop iterations that overran their period.
    pub loop_overruns: u32,
    /// Times the heartbeat was lost while armed.
    pub heartbeat_losses: u32,
    /// Time since boot, microseconds.
    pub uptime_us: u64,
}

/// Why the device refused a request. Each variant names what was wrong.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum DeviceError {
    /// The host's `Hello` named another protocol version.
    VersionMismatch {
        /// The device's [`crate::PROTOCOL_VERSION`].
        device: u16,
        /// The version the host announced.
        host: u16,
    },
    /// The request is not allowed in the device's present state.
    BadState(BadState),
    /// The request was well formed but an argument is out of the device's range.
    InvalidArgument { field: Name },
    /// The device does not implement this request (see [`Capabilities`]).
    Unsupported,
    /// The blob does not fit the device's storage.
    TooLarge {
        /// Announced blob length, bytes.
        total_len: u32,
        /// Largest blob the device stores, bytes.
        capacity: u32,
    },
    /// A chunk that does not start at the device's `next_offset`.
    OutOfOrder {
        /// Where the next chunk must start.
        expected_offset: u32,
    },
    /// A chunk that ends past the announced `total_len`.
    PastEnd { end: u32, total_len: u32 },
    /// `UploadCommit` before all bytes arrived.
    Incomplete { next_offset: u32, total_len: u32 },
    /// The whole-blob CRC-32 of what was staged (or of `UploadCommit`) is not
    /// the announced one.
    CrcMismatch { expected: u32, computed: u32 },
    /// The blob's header or body failed a check.
    BlobRejected(BlobRejection),
    /// `Arm` refused: the active strings cannot pull the end-effector in
    /// every direction (of the plane, for a planar device), so forces cannot
    /// be rendered. Position tracking and the state stream go on unarmed.
    NotForceClosed {
        /// Strings of the device's layout.
        strings: u8,
        /// Degrees of freedom of the end-effector: 2 planar, 3 in space.
        dof: u8,
        /// `true`: fewer than `dof + 1` strings, never enough (strings only
        /// pull). `false`: enough strings, but from where the end-effector
        /// is their directions do not positively span (it is outside the
        /// anchors' convex hull, e.g. below every anchor of a hanging
        /// design, which relies on gravity to pull down).
        too_few_strings: bool,
    },
    /// Writing or erasing flash failed.
    Storage {
        /// Flash controller status bits.
        code: u32,
    },
}

/// Which state forbids a request.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum BadState {
    /// The request needs the motors disarmed (geometry, limits, model changes).
    Armed,
    /// The request needs the device armed.
    NotArmed,
    /// A latched fault must be cleared first.
    Faulted,
    /// `UploadChunk`/`UploadCommit` without `UploadBegin`.
    NoUpload,
    /// The request needs a geometry (`SetNominalGeometry` or a model blob).
    NoGeometry,
}

impl fmt::Display for BadState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            BadState::Armed => {
                "Armed: the motors are on (armed, or holding pre-tension after a fault such as \
                 HEARTBEAT_LOST); disarm first"
            }
            BadState::NotArmed => "NotArmed: the request needs the device armed",
            BadState::Faulted => "Faulted: a latched fault must be cleared first",
            BadState::NoUpload => "NoUpload: no upload was begun",
            BadState::NoGeometry => {
                "NoGeometry: the device has no geometry yet (flash a model or send the nominal \
                 geometry)"
            }
        })
    }
}

/// A [`BlobError`] as it travels on the wire: field names are carried as
/// [`Name`]s instead of `&'static str`, so the host can decode it from a
/// transient buffer. Same variants, same messages.
pub type BlobRejection = BlobError<Name>;

impl From<BlobError> for BlobRejection {
    fn from(e: BlobError) -> Self {
        match e {
            BlobError::Truncated { needed, got } => Self::Truncated { needed, got },
            BlobError::TrailingBytes { extra } => Self::TrailingBytes { extra },
            BlobError::BadMagic => Self::BadMagic,
            BlobError::UnsupportedVersion { found, supported } => {
                Self::UnsupportedVersion { found, supported }
            }
            BlobError::UnknownKind { found } => Self::UnknownKind { found },
            BlobError::HeaderCrc { stored, computed } => Self::HeaderCrc { stored, computed },
            BlobError::BodyCrc { stored, computed } => Self::BodyCrc { stored, computed },
            BlobError::Dimension {
                field,
                found,
                expected,
            } => Self::Dimension {
                field: name(field),
                found,
                expected,
            },
            BlobError::Body { field } => Self::Body { field: name(field) },
            BlobError::TooFewStrings { strings, dof } => Self::TooFewStrings { strings, dof },
            BlobError::InactiveString { field, string } => Self::InactiveString {
                field: name(field),
                string,
            },
            BlobError::OverBudget { field, found, most } => Self::OverBudget {
                field: name(field),
                found,
                most,
            },
        }
    }
}

impl fmt::Display for DeviceError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::VersionMismatch { device, host } => write!(
                f,
                "protocol version mismatch: device speaks {device}, host speaks {host}"
            ),
            Self::BadState(s) => write!(f, "refused in this state: {s}"),
            Self::InvalidArgument { field } => write!(f, "invalid argument `{field}`"),
            Self::Unsupported => write!(f, "request not supported by this firmware"),
            Self::TooLarge {
                total_len,
                capacity,
            } => write!(
                f,
                "model blob of {total_len} bytes does not fit the device's {capacity} bytes"
            ),
            Self::OutOfOrder { expected_offset } => {
                write!(
                    f,
                    "upload chunk out of order: device expects offset {expected_offset}"
                )
            }
            Self::PastEnd { end, total_len } => write!(
                f,
                "upload chunk ends at {end}, past the announced length {total_len}"
            ),
            Self::Incomplete {
                next_offset,
                total_len,
            } => write!(
                f,
                "upload incomplete: {next_offset} of {total_len} bytes received"
            ),
            Self::CrcMismatch { expected, computed } => write!(
                f,
                "model blob CRC mismatch: expected {expected:#010x}, computed {computed:#010x}"
            ),
            Self::BlobRejected(r) => write!(f, "model blob rejected: {r}"),
            Self::NotForceClosed {
                strings,
                dof,
                too_few_strings: true,
            } => write!(
                f,
                "not armed: {strings} strings cannot render force in every direction of {dof} degrees of freedom (strings only pull: that needs at least {}); position tracking goes on",
                u16::from(*dof) + 1
            ),
            Self::NotForceClosed { strings, .. } => write!(
                f,
                "not armed: from where the end-effector is, its {strings} strings cannot pull it in every direction (it is outside the anchors' convex hull); position tracking goes on"
            ),
            Self::Storage { code } => write!(f, "flash storage error (status {code:#010x})"),
        }
    }
}

impl core::error::Error for DeviceError {}

/// One sample of the device state, taken at the end of a control-loop
/// iteration.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct State {
    /// When the sample was taken: the control loop's timer at the start of
    /// the iteration whose outputs this frame reports, microseconds since
    /// boot. The host maps it to the tracker's clock (offset and drift) and
    /// pairs by it, never by arrival time.
    pub time_us: u64,
    /// The same instant, microseconds since home was declared (boot, or the
    /// last `Request::Home`): the time the string law's time-dependent terms
    /// (drift, slip) read. Protocol v3.
    pub since_home_us: u64,
    /// The home capture the counts are from: the boot's id (upper 32 bits,
    /// a new random number at each boot) and the number of home captures
    /// declared since that boot (lower 32). Two states with the same id
    /// count from the same home; a session that records it (`spidar
    /// collect`'s `home` column) tells the calibration which of its
    /// sessions share a home. Protocol v7.
    pub home_id: u64,
    /// Encoder counts since home, per string (extended to 32 bits).
    pub counts: [i32; STRINGS],
    /// End-effector position from forward kinematics, device frame, millimetres.
    pub position_mm: [f32; 3],
    /// Corrected end-effector position, room frame, **Q15.16 millimetres**
    /// (divide by 65536, see [`q16_to_mm`]). This is the bit-exact output of
    /// the fixed-point correction (or the room transform alone when the model
    /// has no correction), so the host can compare it bit for bit with its
    /// own evaluation; Q15.16 is also finer than `f32` beyond 512 mm and no
    /// longer on the wire (varint: 4 bytes up to ±2048 mm).
    pub corrected_mm: [i32; 3],
    /// Commanded tension per string after the safety clamp, newtons.
    pub tensions_n: [f32; STRINGS],
    /// Force those tensions render, device frame, newtons: the force asked
    /// for after the safety limit, scaled by the share of it the tension
    /// distribution reaches; 0 when disarmed. Protocol v5.
    pub rendered_force_n: [f32; 3],
    /// Latched and present faults.
    pub faults: Faults,
    /// Bit `i` set: string `i` is slack.
    pub slack: u8,
    /// String left out of forward kinematics by fault detection, `0..STRINGS`.
    pub excluded: Option<u8>,
    /// Duration of the last control-loop iteration, microseconds (saturating).
    pub loop_us: u16,
    /// Longest iteration since the previous state frame, microseconds (saturating).
    pub loop_max_us: u16,
    /// The loop renders forces: armed by the host, no fault latched since.
    pub armed: bool,
    /// The motor drivers are on: armed by the host and not disarmed since,
    /// no emergency stop. They stay on, every string at pre-tension, after a
    /// fault disarmed the loop (`armed` false), and while they are on the
    /// device refuses geometry, limit and model changes
    /// ([`BadState::Armed`]) until `Disarm`. Protocol v6.
    pub motors_on: bool,
    /// `model_id` of the active model blob, `None` without one.
    pub model_id: Option<u32>,
}

/// Converts a Q15.16 millimetre value (as in [`State::corrected_mm`]) to millimetres.
pub fn q16_to_mm(v: i32) -> f64 {
    f64::from(v) / 65536.0
}

/// Fault bits of [`State::faults`]. Faults latch until `ClearFaults`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Faults(pub u16);

impl Faults {
    /// No valid request for `heartbeat_timeout_ms` while armed; tensions are at pre-tension.
    pub const HEARTBEAT_LOST: Self = Self(1 << 0);
    /// An encoder count jumped by more than is physically possible.
    pub const ENCODER: Self = Self(1 << 1);
    /// Forward kinematics did not converge.
    pub const KINEMATICS: Self = Self(1 << 2);
    /// A tension was clamped at `max_tension_n`.
    pub const TENSION_CLAMPED: Self = Self(1 << 3);
    /// A control-loop iteration overran its period.
    pub const LOOP_OVERRUN: Self = Self(1 << 4);
    /// The stored model failed its checks at boot and is not used.
    pub const MODEL_INVALID: Self = Self(1 << 5);
    /// A motor driver reported a fault.
    pub const DRIVER: Self = Self(1 << 6);
    /// The emergency stop input is active.
    pub const ESTOP: Self = Self(1 << 7);
    /// The end-effector left the workspace spanned by the anchors.
    pub const WORKSPACE: Self = Self(1 << 8);

    /// Every fault bit with its name, in bit order.
    pub const NAMED: [(Faults, &'static str); 9] = [
        (Self::HEARTBEAT_LOST, "HEARTBEAT_LOST"),
        (Self::ENCODER, "ENCODER"),
        (Self::KINEMATICS, "KINEMATICS"),
        (Self::TENSION_CLAMPED, "TENSION_CLAMPED"),
        (Self::LOOP_OVERRUN, "LOOP_OVERRUN"),
        (Self::MODEL_INVALID, "MODEL_INVALID"),
        (Self::DRIVER, "DRIVER"),
        (Self::ESTOP, "ESTOP"),
        (Self::WORKSPACE, "WORKSPACE"),
    ];

    /// Names of the bits set, in bit order (bits without a name are left
    /// out: see [`Faults::unnamed`]).
    pub fn names(self) -> impl Iterator<Item = &'static str> {
        Self::NAMED
            .into_iter()
            .filter(move |(f, _)| self.contains(*f))
            .map(|(_, n)| n)
    }

    /// The bits set that have no name (a newer firmware's).
    pub const fn unnamed(self) -> u16 {
        let mut known = 0;
        let mut k = 0;
        while k < Self::NAMED.len() {
            known |= Self::NAMED[k].0 .0;
            k += 1;
        }
        self.0 & !known
    }

    /// No fault.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }
    /// `true` if every bit of `other` is set.
    pub const fn contains(self, other: Self) -> bool {
        self.0 & other.0 == other.0
    }
    /// Both sets of bits.
    pub const fn union(self, other: Self) -> Self {
        Self(self.0 | other.0)
    }
}

/// Unsolicited news from the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Event {
    /// The heartbeat was lost while armed; tensions dropped to pre-tension.
    HeartbeatLost,
    /// New fault bits were raised.
    Fault { raised: Faults },
    /// The device disarmed itself because of these faults.
    Disarmed { faults: Faults },
    /// Home was declared (`Request::Home`): state frames from here on count
    /// from the new zero.
    Homed,
}

// ---------------------------------------------------------------------------
// Validation
// ---------------------------------------------------------------------------

/// A message type that can travel in a frame. The encoder and decoder call
/// [`Message::validate`], so a frame that decodes also carries sane values
/// (else [`crate::FrameError::Invalid`]).
pub trait Message: Serialize {
    /// Checks the invariants postcard cannot express (finite floats where a
    /// command needs them, string indices, chunk lengths); `Err` names the
    /// first field out of range.
    fn validate(&self) -> Result<(), &'static str>;

    /// If `payload` (a frame's postcard bytes after the sequence number) is
    /// this direction's frozen `Hello`/`HelloAck` prefix, the protocol version
    /// it names. Used to report a version mismatch instead of an undecodable
    /// frame.
    fn peek_protocol_version(payload: &[u8]) -> Option<u16>;
}

fn finite(v: &[f32], field: &'static str) -> Result<(), &'static str> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(field)
    }
}

impl Request<'_> {
    /// The variant's name, for errors and logs. No wildcard arm: a new
    /// variant must be named here.
    pub fn name(&self) -> &'static str {
        match self {
            Request::Hello { .. } => "Hello",
            Request::Heartbeat => "Heartbeat",
            Request::GetInfo => "GetInfo",
            Request::GetStats => "GetStats",
            Request::SetNominalGeometry(_) => "SetNominalGeometry",
            Request::SetLimits(_) => "SetLimits",
            Request::SetForceTarget { .. } => "SetForceTarget",
            Request::SetGuidanceTarget { .. } => "SetGuidanceTarget",
            Request::Arm => "Arm",
            Request::Disarm => "Disarm",
            Request::ClearFaults => "ClearFaults",
            Request::StreamOn { .. } => "StreamOn",
            Request::StreamOff => "StreamOff",
            Request::UploadBegin { .. } => "UploadBegin",
            Request::UploadChunk { .. } => "UploadChunk",
            Request::UploadCommit { .. } => "UploadCommit",
            Request::UploadAbort => "UploadAbort",
            Request::UploadStatus => "UploadStatus",
            Request::ClearModel => "ClearModel",
            Request::Home => "Home",
        }
    }
}

impl Message for Request<'_> {
    fn validate(&self) -> Result<(), &'static str> {
        match self {
            Request::SetNominalGeometry(m) => {
                if m.active_strings.count_ones() < u32::from(m.dof()) {
                    return Err("active_strings");
                }
                let active = |i: &usize| m.is_active(*i);
                if (0..STRINGS)
                    .filter(active)
                    .any(|i| m.counts_per_rev[i] == 0)
                {
                    return Err("counts_per_rev");
                }
                if !(0..STRINGS).filter(active).all(|i| {
                    let r = m.pulley_radius_mm[i];
                    r.is_finite() && r > 0.0
                }) {
                    return Err("pulley_radius_mm");
                }
                if !(0..STRINGS)
                    .filter(active)
                    .all(|i| m.anchors_mm[i].iter().all(|v| v.is_finite()))
                {
                    return Err("anchors_mm");
                }
                finite(&m.home_mm, "home_mm")
            }
            Request::SetLimits(l) => {
                if !(l.pre_tension_n.is_finite() && l.pre_tension_n >= 0.0) {
                    return Err("pre_tension_n");
                }
                if !(l.max_tension_n.is_finite() && l.max_tension_n >= l.pre_tension_n) {
                    return Err("max_tension_n");
                }
                if l.heartbeat_timeout_ms == 0 {
                    return Err("heartbeat_timeout_ms");
                }
                Ok(())
            }
            Request::SetForceTarget { force_n } => finite(force_n, "force_n"),
            Request::SetGuidanceTarget {
                target_mm,
                d_min_mm,
                f_max_n,
            } => {
                finite(target_mm, "target_mm")?;
                if !(d_min_mm.is_finite() && *d_min_mm >= 0.0) {
                    return Err("d_min_mm");
                }
                if !(f_max_n.is_finite() && *f_max_n >= 0.0) {
                    return Err("f_max_n");
                }
                Ok(())
            }
            Request::StreamOn { decimation } if *decimation == 0 => Err("decimation"),
            Request::UploadChunk { offset, data } => {
                if data.is_empty() || data.len() > MAX_CHUNK {
                    return Err("data");
                }
                // `data.len() <= MAX_CHUNK` so the cast is exact.
                if offset.checked_add(data.len() as u32).is_none() {
                    return Err("offset");
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }

    fn peek_protocol_version(payload: &[u8]) -> Option<u16> {
        // Request::Hello = tag 0, then protocol_version.
        match postcard::take_from_bytes::<(u32, u16)>(payload) {
            Ok(((0, v), _)) => Some(v),
            _ => None,
        }
    }
}

impl Message for DeviceMessage {
    fn validate(&self) -> Result<(), &'static str> {
        match self {
            DeviceMessage::State(s) => match s.excluded {
                Some(i) if usize::from(i) >= STRINGS => Err("excluded"),
                _ => Ok(()),
            },
            DeviceMessage::Reply(Response::HelloAck(h)) => {
                if h.max_chunk == 0 || usize::from(h.max_chunk) > MAX_CHUNK {
                    Err("max_chunk")
                } else {
                    Ok(())
                }
            }
            _ => Ok(()),
        }
    }

    fn peek_protocol_version(payload: &[u8]) -> Option<u16> {
        // DeviceMessage::Reply = tag 0, Response::HelloAck = tag 0, then
        // HelloAck::protocol_version.
        match postcard::take_from_bytes::<(u32, u32, u16)>(payload) {
            Ok(((0, 0, v), _)) => Some(v),
            _ => None,
        }
    }
}
