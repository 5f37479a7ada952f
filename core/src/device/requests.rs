//! What the device does with each host request ([`Device::handle`]): the
//! protocol-version check and the heartbeat every request counts as, one
//! handler per request of the protocol, and how the model store's and the
//! safety limits' errors read on the wire.

use spidar_protocol::messages::name;
use spidar_protocol::{
    BadState, DeviceError, Event, Limits, ModelInfo, NominalGeometry, Request, Response,
    UploadState, PROTOCOL_VERSION,
};

use super::calibration::{nominal_calibration, parse_model, ActiveModel, ParsedModel};
use super::{ms, Device, Stream};
use crate::control::Target;
use crate::model_store::{CommitError, ModelFlash, StoreError};
use crate::safety::{SafetyConfigError, SafetyMonitor};
use crate::tension::{force_closure, TensionStatus};

/// `DeviceError::Storage` code of a commit record that did not read back.
pub const STORAGE_RECORD_VERIFY: u32 = 0x8000_0010;

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

impl<'m, F: ModelFlash> Device<'m, F> {
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
}
