//! Safety rules of the device as a latched fault state.
//!
//! The [`SafetyMonitor`] sits between the tension distribution and the motor
//! drivers. Every control-loop iteration the firmware calls
//! [`SafetyMonitor::check`] (heartbeat, slack, forward kinematics, non-finite
//! lengths), passes the commanded force through
//! [`SafetyMonitor::limit_force`] and the tensions through
//! [`SafetyMonitor::apply`].
//!
//! # Latching
//!
//! Every fault in [`SafetyFaults`] except [`SafetyFaults::OVERFORCE`] is **latched**: once
//! set it stays set, and the device is disarmed, until the host clears it
//! explicitly with [`SafetyMonitor::clear`] (the host's arm command does
//! `clear()` then `arm()`). Nothing clears a fault by itself: a heartbeat that
//! resumes, a string that becomes taut again or a consistent position do not.
//! Two faults reflect an input that is still present and survive `clear()`
//! while it is: [`SafetyFaults::ESTOP`] (while the emergency-stop input is active)
//! and [`SafetyFaults::MODEL_INVALID`] (while the calibration model is flagged
//! invalid).
//!
//! [`SafetyFaults::OVERFORCE`] is not a fault but a warning: a commanded force above
//! `f_max` is clamped (direction preserved), which is normal operation; the
//! bit reports, in [`SafetyMonitor::warnings`], whether the last
//! `limit_force` clamped.
//!
//! While any fault is latched or the device is disarmed, every string gets
//! the pre-tension only (strings stay taut, no force is rendered).
//!
//! f32 only; no allocation, no panics.

use core::ops::{BitOr, BitOrAssign};

use serde::{Deserialize, Serialize};
use spidar_protocol::messages::Faults;

use crate::real::Real;
use crate::STRINGS;

/// A set of safety faults, one bit each (see the module doc for which latch).
/// The loop's faults, in the wire's bit layout: a fault the wire names sits
/// on the wire's bit (`HEARTBEAT_LOST`, `MODEL_INVALID`, `ESTOP` are
/// `spidar_protocol::Faults`' bits), and the loop's own faults sit on bits
/// the wire leaves unnamed (checked at compile time). They never go on the
/// wire as they are: [`crate::device::protocol_faults`] maps them (`SLACK`,
/// `FK_FAULT` and `NON_FINITE` all report as `KINEMATICS`; `OVERFORCE` is a
/// warning the wire does not carry).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct SafetyFaults(u16);

impl SafetyFaults {
    /// No fault.
    pub const NONE: SafetyFaults = SafetyFaults(0);
    /// No heartbeat from the host for longer than `heartbeat_timeout_ms`.
    /// Latched. The wire's `HEARTBEAT_LOST` bit.
    pub const HEARTBEAT_LOST: SafetyFaults = SafetyFaults(Faults::HEARTBEAT_LOST.0);
    /// The calibration model is invalid (e.g. blob failed to load). Latched;
    /// survives `clear()` while the model is still flagged invalid. The
    /// wire's `MODEL_INVALID` bit.
    pub const MODEL_INVALID: SafetyFaults = SafetyFaults(Faults::MODEL_INVALID.0);
    /// Hardware emergency-stop input active. Latched; survives `clear()`
    /// while the input is still active. The wire's `ESTOP` bit.
    pub const ESTOP: SafetyFaults = SafetyFaults(Faults::ESTOP.0);
    /// A string is slack: measured longer than its geometric length by more
    /// than `slack_threshold_mm` (which strings: [`SafetyMonitor::slack_mask`]).
    /// Latched. The loop's own (reported as `KINEMATICS`).
    pub const SLACK: SafetyFaults = SafetyFaults(1 << 9);
    /// Forward kinematics found no consistent position. Latched. The loop's
    /// own (reported as `KINEMATICS`).
    pub const FK_FAULT: SafetyFaults = SafetyFaults(1 << 10);
    /// A NaN or infinity in lengths, force or tensions. Latched. The loop's
    /// own (reported as `KINEMATICS`).
    pub const NON_FINITE: SafetyFaults = SafetyFaults(1 << 11);
    /// The last commanded force exceeded `f_max` and was clamped. Warning
    /// only, never latched, not on the wire.
    pub const OVERFORCE: SafetyFaults = SafetyFaults(1 << 12);

    /// The faults the wire names, on the wire's bits.
    pub const ON_THE_WIRE: SafetyFaults =
        SafetyFaults(Self::HEARTBEAT_LOST.0 | Self::MODEL_INVALID.0 | Self::ESTOP.0);
    /// The loop's own faults, on bits the wire leaves unnamed.
    pub const LOOP_ONLY: SafetyFaults =
        SafetyFaults(Self::SLACK.0 | Self::FK_FAULT.0 | Self::NON_FINITE.0 | Self::OVERFORCE.0);
    /// Every defined bit.
    pub const ALL: SafetyFaults = SafetyFaults(Self::ON_THE_WIRE.0 | Self::LOOP_ONLY.0);

    /// The raw bits.
    pub const fn bits(self) -> u16 {
        self.0
    }

    /// From raw bits; undefined bits are dropped.
    pub const fn from_bits_truncate(bits: u16) -> SafetyFaults {
        SafetyFaults(bits & Self::ALL.0)
    }

    /// Whether no bit is set.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }

    /// Whether every bit of `other` is set in `self`.
    pub const fn contains(self, other: SafetyFaults) -> bool {
        self.0 & other.0 == other.0
    }

    /// Whether any bit of `other` is set in `self`.
    pub const fn intersects(self, other: SafetyFaults) -> bool {
        self.0 & other.0 != 0
    }

    /// Sets the bits of `other`.
    pub fn insert(&mut self, other: SafetyFaults) {
        self.0 |= other.0;
    }

    /// Clears the bits of `other`.
    pub fn remove(&mut self, other: SafetyFaults) {
        self.0 &= !other.0;
    }
}

// The loop's own faults must not sit on a bit the wire names.
const _: () = {
    let mut named = 0u16;
    let mut i = 0;
    while i < Faults::NAMED.len() {
        named |= Faults::NAMED[i].0 .0;
        i += 1;
    }
    assert!(SafetyFaults::LOOP_ONLY.0 & named == 0);
};

impl BitOr for SafetyFaults {
    type Output = SafetyFaults;
    fn bitor(self, rhs: SafetyFaults) -> SafetyFaults {
        SafetyFaults(self.0 | rhs.0)
    }
}

impl BitOrAssign for SafetyFaults {
    fn bitor_assign(&mut self, rhs: SafetyFaults) {
        self.0 |= rhs.0;
    }
}

/// Safety limits of the device.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SafetyConfig {
    /// Lowest tension (N) passed to the motors while armed.
    pub t_min: f32,
    /// Highest tension (N) passed to the motors.
    pub t_max: f32,
    /// Largest force (N) on the end-effector that may be commanded.
    pub f_max: f32,
    /// Tension (N) of every string while disarmed or faulted, in `[0, t_max]`.
    pub pretension_n: f32,
    /// Longest time (ms) without a host heartbeat, in `1..=i32::MAX`.
    pub heartbeat_timeout_ms: u32,
    /// A string measured longer than its geometric length by more than this
    /// (mm) is slack.
    pub slack_threshold_mm: f32,
}

impl core::fmt::Display for SafetyConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::NonFinite => "safety configuration: a field is NaN or infinite",
            Self::TensionLimits => "safety configuration: not 0 <= t_min <= t_max",
            Self::ForceLimit => "safety configuration: f_max < 0",
            Self::Pretension => "safety configuration: pretension_n not in [0, t_max]",
            Self::HeartbeatTimeout => {
                "safety configuration: heartbeat_timeout_ms is 0 or above i32::MAX"
            }
            Self::SlackThreshold => "safety configuration: slack_threshold_mm < 0",
        })
    }
}

impl core::error::Error for SafetyConfigError {}

/// Why a [`SafetyConfig`] was rejected.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SafetyConfigError {
    /// A field is NaN or infinite.
    NonFinite,
    /// Not `0 <= t_min <= t_max`.
    TensionLimits,
    /// `f_max < 0`.
    ForceLimit,
    /// `pretension_n` not in `[0, t_max]`.
    Pretension,
    /// `heartbeat_timeout_ms` is 0 or above `i32::MAX`.
    HeartbeatTimeout,
    /// `slack_threshold_mm < 0`.
    SlackThreshold,
}

impl SafetyConfig {
    /// Checks the invariants documented on the fields.
    pub fn validate(&self) -> Result<(), SafetyConfigError> {
        let values = [
            self.t_min,
            self.t_max,
            self.f_max,
            self.pretension_n,
            self.slack_threshold_mm,
        ];
        if !values.iter().all(|v| v.is_finite()) {
            return Err(SafetyConfigError::NonFinite);
        }
        if self.t_min < 0.0 || self.t_min > self.t_max {
            return Err(SafetyConfigError::TensionLimits);
        }
        if self.f_max < 0.0 {
            return Err(SafetyConfigError::ForceLimit);
        }
        if self.pretension_n < 0.0 || self.pretension_n > self.t_max {
            return Err(SafetyConfigError::Pretension);
        }
        if self.heartbeat_timeout_ms == 0 || self.heartbeat_timeout_ms > i32::MAX as u32 {
            return Err(SafetyConfigError::HeartbeatTimeout);
        }
        if self.slack_threshold_mm < 0.0 {
            return Err(SafetyConfigError::SlackThreshold);
        }
        Ok(())
    }
}

/// The latched safety state of the device. Starts disarmed with no fault.
#[derive(Clone, Debug, PartialEq)]
pub struct SafetyMonitor {
    config: SafetyConfig,
    faults: SafetyFaults,
    warnings: SafetyFaults,
    slack_mask: u8,
    armed: bool,
    last_heartbeat_ms: Option<u32>,
    estop_active: bool,
    model_valid: bool,
    /// Channels that carry a string (bit `i` = channel `i`): the others are
    /// not checked and always get tension 0.
    active: u8,
    /// The string lengths come from a calibrated model (see
    /// [`SafetyMonitor::set_lengths_calibrated`]).
    lengths_calibrated: bool,
}

impl SafetyMonitor {
    /// A disarmed monitor with no fault, or the reason `config` is invalid.
    pub fn new(config: SafetyConfig) -> Result<Self, SafetyConfigError> {
        config.validate()?;
        Ok(Self {
            config,
            faults: SafetyFaults::NONE,
            warnings: SafetyFaults::NONE,
            slack_mask: 0,
            armed: false,
            last_heartbeat_ms: None,
            estop_active: false,
            model_valid: true,
            active: u8::MAX,
            lengths_calibrated: true,
        })
    }

    /// The limits in force.
    pub fn config(&self) -> &SafetyConfig {
        &self.config
    }

    /// Records a host heartbeat at `now_ms` (ms, any monotonic u32 clock that
    /// may wrap). Does not clear a latched `HEARTBEAT_LOST`.
    pub fn heartbeat(&mut self, now_ms: u32) {
        self.last_heartbeat_ms = Some(now_ms);
    }

    /// Sets the hardware emergency-stop input; active latches `ESTOP` at once.
    pub fn set_estop(&mut self, active: bool) {
        self.estop_active = active;
        if active {
            self.latch(SafetyFaults::ESTOP);
        }
    }

    /// Flags the calibration model valid or not; invalid latches `MODEL_INVALID` at once.
    pub fn set_model_valid(&mut self, valid: bool) {
        self.model_valid = valid;
        if !valid {
            self.latch(SafetyFaults::MODEL_INVALID);
        }
    }

    /// Which channels carry a string (the layout's `active` mask, bit `i` =
    /// channel `i`; all 8 by default). The others are left out of the
    /// length checks and get tension 0 from [`SafetyMonitor::apply`], armed
    /// or not.
    pub fn set_active(&mut self, active: u8) {
        self.active = active;
    }

    /// Whether the string lengths come from a calibrated model (default)
    /// or from a nominal one (`payout = r theta`, before any calibration).
    /// A nominal law is off by up to 40 % of the payout far from home (the
    /// winding radius grows with the wound string: the paper's 267 mm), so
    /// the strings disagree by tens of millimetres there by the model's own
    /// error; `FK_FAULT` and `SLACK`, which exist to catch a string that
    /// breaks, slips or jams on a calibrated device, cannot tell that from
    /// it and are not raised with uncalibrated lengths. The other faults
    /// are.
    pub fn set_lengths_calibrated(&mut self, calibrated: bool) {
        self.lengths_calibrated = calibrated;
    }

    /// The channels that carry a string (see [`SafetyMonitor::set_active`]).
    pub fn active(&self) -> u8 {
        self.active
    }

    /// One control-loop check at `now_ms` (ms). `measured_lengths_mm` are the
    /// string lengths from the encoders (mm), `geometric_lengths_mm` the
    /// distances from the estimated position to the anchors (mm), `fk_ok`
    /// whether forward kinematics found a consistent position. Latches:
    /// `HEARTBEAT_LOST` while armed, if the last heartbeat is older than
    /// the timeout or there never was one (as the wire's bit says: a
    /// disarmed device renders no force, and a host that went away after
    /// a command is not a fault); `NON_FINITE` for any NaN or
    /// infinite length; `FK_FAULT` if `!fk_ok`; `SLACK` with the strings'
    /// bits in the slack mask for `measured - geometric > slack_threshold_mm`
    /// (checked only when `fk_ok`: otherwise the geometric lengths are
    /// meaningless); `ESTOP`/`MODEL_INVALID` while their inputs are active.
    /// Lengths of inactive channels are not read. Returns the latched faults.
    pub fn check(
        &mut self,
        now_ms: u32,
        measured_lengths_mm: &[f32; STRINGS],
        geometric_lengths_mm: &[f32; STRINGS],
        fk_ok: bool,
    ) -> SafetyFaults {
        if self.armed {
            match self.last_heartbeat_ms {
                Some(last) => {
                    // Wrapping difference; a heartbeat stamped after `now_ms`
                    // (negative age) counts as fresh.
                    let age = now_ms.wrapping_sub(last) as i32;
                    if age > self.config.heartbeat_timeout_ms as i32 {
                        self.latch(SafetyFaults::HEARTBEAT_LOST);
                    }
                }
                None => self.latch(SafetyFaults::HEARTBEAT_LOST),
            }
        }
        if !fk_ok && self.lengths_calibrated {
            self.latch(SafetyFaults::FK_FAULT);
        }
        let mut slack = 0u8;
        let mut non_finite = false;
        for i in 0..STRINGS {
            let (m, g) = (measured_lengths_mm[i], geometric_lengths_mm[i]);
            if !(m.is_finite() && g.is_finite()) {
                non_finite |= self.active >> i & 1 != 0;
            } else if fk_ok && self.lengths_calibrated && m - g > self.config.slack_threshold_mm {
                slack |= 1 << i;
            }
        }
        // Inactive channels' lengths are not the strings': left out.
        slack &= self.active;
        if non_finite {
            self.latch(SafetyFaults::NON_FINITE);
        }
        if slack != 0 {
            self.slack_mask |= slack;
            self.latch(SafetyFaults::SLACK);
        }
        if self.estop_active {
            self.latch(SafetyFaults::ESTOP);
        }
        if !self.model_valid {
            self.latch(SafetyFaults::MODEL_INVALID);
        }
        self.faults
    }

    /// Clamps the magnitude of a commanded force (N) to `f_max`, preserving
    /// its direction, and sets or clears the `OVERFORCE` warning. A non-finite
    /// force becomes zero and latches `NON_FINITE`.
    pub fn limit_force(&mut self, force: [f32; 3]) -> [f32; 3] {
        if !force.iter().all(|f| f.is_finite()) {
            self.latch(SafetyFaults::NON_FINITE);
            return [0.0; 3];
        }
        // Scaled norm: no overflow for any finite force.
        let m = force
            .iter()
            .fold(0.0f32, |m, f| if f.abs() > m { f.abs() } else { m });
        if m <= 0.0 {
            self.warnings.remove(SafetyFaults::OVERFORCE);
            return force;
        }
        let w = [force[0] / m, force[1] / m, force[2] / m];
        let w_norm = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt_rounded();
        let norm = m * w_norm; // may be +inf for huge finite forces
        if norm > self.config.f_max {
            self.warnings.insert(SafetyFaults::OVERFORCE);
            let scale = self.config.f_max / w_norm;
            [w[0] * scale, w[1] * scale, w[2] * scale]
        } else {
            self.warnings.remove(SafetyFaults::OVERFORCE);
            force
        }
    }

    /// The tensions (N) to send to the motors: the pre-tension on every
    /// string while any fault is latched or the device is disarmed, otherwise
    /// each tension clamped to `[t_min, t_max]`. Any non-finite tension
    /// latches `NON_FINITE` (and so gives the pre-tension). Inactive channels
    /// (see [`SafetyMonitor::set_active`]) get 0 whatever they were given.
    pub fn apply(&mut self, tensions: [f32; STRINGS]) -> [f32; STRINGS] {
        let active = self.active;
        let finite = if active == u8::MAX {
            tensions.iter().all(|t| t.is_finite())
        } else {
            (0..STRINGS).all(|i| active >> i & 1 == 0 || tensions[i].is_finite())
        };
        if !finite {
            self.latch(SafetyFaults::NON_FINITE);
        }
        let mut out = if !self.faults.is_empty() || !self.armed {
            [self.config.pretension_n; STRINGS]
        } else {
            let (lo, hi) = (self.config.t_min, self.config.t_max);
            tensions.map(|t| {
                if t < lo {
                    lo
                } else if t > hi {
                    hi
                } else {
                    t
                }
            })
        };
        if active != u8::MAX {
            for (i, t) in out.iter_mut().enumerate() {
                if active >> i & 1 == 0 {
                    *t = 0.0;
                }
            }
        }
        out
    }

    /// Arms the device (tensions pass through `apply`). Refused, returning the
    /// blocking faults, while any fault is latched or before the first
    /// heartbeat (`HEARTBEAT_LOST`).
    pub fn arm(&mut self) -> Result<(), SafetyFaults> {
        if !self.faults.is_empty() {
            return Err(self.faults);
        }
        if self.last_heartbeat_ms.is_none() {
            return Err(SafetyFaults::HEARTBEAT_LOST);
        }
        self.armed = true;
        Ok(())
    }

    /// Disarms the device: pre-tension only.
    pub fn disarm(&mut self) {
        self.armed = false;
    }

    /// Whether the device is armed (faults latched or not).
    pub fn is_armed(&self) -> bool {
        self.armed
    }

    /// The latched faults.
    pub fn faults(&self) -> SafetyFaults {
        self.faults
    }

    /// Warnings of the last call (`OVERFORCE`), not latched.
    pub fn warnings(&self) -> SafetyFaults {
        self.warnings
    }

    /// Strings found slack since the last `clear()`, bit `i` = string `i`.
    pub fn slack_mask(&self) -> u8 {
        self.slack_mask
    }

    /// Clears the latched faults and the slack mask, except `ESTOP` and
    /// `MODEL_INVALID` while their inputs are still active. Does not arm.
    /// Returns the faults still latched.
    pub fn clear(&mut self) -> SafetyFaults {
        let mut keep = SafetyFaults::NONE;
        if self.estop_active {
            keep.insert(SafetyFaults::ESTOP);
        }
        if !self.model_valid {
            keep.insert(SafetyFaults::MODEL_INVALID);
        }
        self.faults = SafetyFaults::from_bits_truncate(self.faults.bits() & keep.bits());
        self.slack_mask = 0;
        self.faults
    }

    /// Latches `fault` and disarms.
    fn latch(&mut self, fault: SafetyFaults) {
        self.faults.insert(fault);
        self.armed = false;
    }
}

#[cfg(test)]
mod tests;
