//! One open device: the streaming link client, what the application did
//! with it (armed it or not), and the room frame of its model. Every
//! method is one C call's body, returning [`Error`]s that name the port.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError, RwLock};
use std::time::{Duration, Instant};

use host::device::link::{Client, ClientOptions, LinkError, StreamingClient};
use host::sim::virtual_device::VirtualDevice;
use spidar_core::blob::CompiledCalibration;
use spidar_protocol::{Event, Faults, HelloAck, LinkStats, ModelInfo, Request, Response};

use crate::convert::{
    device_from_room_force, fault_names, info_of, model_info_of, spidar_info, spidar_link_stats,
    spidar_model_info, spidar_state, state_of, Rotation, IDENTITY,
};
use crate::error::{
    Error, SPIDAR_E_ARGUMENT, SPIDAR_E_BLOB, SPIDAR_E_CLOSED, SPIDAR_E_DISARMED,
    SPIDAR_E_FRAME_UNKNOWN, SPIDAR_E_IO, SPIDAR_E_NO_STATE,
};

/// What the application did, as far as the library must remember it.
#[derive(Clone, Copy, Debug, Default)]
struct Intent {
    /// The application armed the device and has not disarmed it (nor been
    /// told that the device disarmed itself).
    armed: bool,
    /// Rotation of the active model's room frame, when known.
    rotation: Option<Rotation>,
}

/// An open device (`spidar_device *` in C).
pub struct Session {
    /// `None` once a failed flash could not restart the stream.
    link: RwLock<Option<StreamingClient>>,
    port: String,
    hello: Option<HelloAck>,
    intent: Mutex<Intent>,
    /// Index of the last state handed to the application.
    last_index: AtomicU64,
    /// The device's counters when the session started.
    stats0: LinkStats,
    /// The virtual device behind the port, if the library spawned it
    /// (dropped after the link: fields drop in order).
    _virtual_device: Option<VirtualDevice>,
}

/// A blob's room rotation (the blob checked whole).
fn rotation_of(blob: &[u8]) -> Result<Rotation, Error> {
    CompiledCalibration::from_blob(blob)
        .map(|c| c.head.frame.room_rotation)
        .map_err(|e| Error::new(SPIDAR_E_BLOB, format!("model blob: {e}")))
}

impl Session {
    /// Opens `port` and starts the session on it.
    pub fn open(port: &str, options: ClientOptions) -> Result<Session, Error> {
        Self::start(Client::open_with(port, options)?, None)
    }

    /// Reads the device's model and starts the stream (every control-loop
    /// iteration); `virtual_device` is kept alive with the session.
    pub fn start(
        mut client: Client,
        virtual_device: Option<VirtualDevice>,
    ) -> Result<Session, Error> {
        let info = client.info()?;
        let stats0 = client.stats()?;
        let session = Session {
            port: client.port_name().to_string(),
            hello: client.device().copied(),
            intent: Mutex::new(Intent {
                armed: false,
                // Without a model the nominal geometry is the room frame.
                rotation: if info.is_none() { Some(IDENTITY) } else { None },
            }),
            link: RwLock::new(Some(StreamingClient::start(client, 1)?)),
            last_index: AtomicU64::new(0),
            stats0,
            _virtual_device: virtual_device,
        };
        Ok(session)
    }

    fn intent(&self) -> std::sync::MutexGuard<'_, Intent> {
        self.intent.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Runs `f` on the link (shared: other threads' calls go on).
    fn with_link<T>(
        &self,
        f: impl FnOnce(&StreamingClient) -> Result<T, Error>,
    ) -> Result<T, Error> {
        let guard = self.link.read().unwrap_or_else(PoisonError::into_inner);
        match guard.as_ref() {
            Some(link) => f(link),
            None => Err(self.closed()),
        }
    }

    fn closed(&self) -> Error {
        Error::new(
            SPIDAR_E_CLOSED,
            format!(
                "serial port {}: the link is gone (a flash could not restart the stream); close the handle and open the port again",
                self.port
            ),
        )
    }

    /// What the device said about itself when it was opened.
    pub fn info(&self) -> Result<spidar_info, Error> {
        self.hello.as_ref().map(info_of).ok_or_else(|| {
            Error::new(
                SPIDAR_E_IO,
                format!("serial port {}: no Hello answer", self.port),
            )
        })
    }

    /// Whether the device disarmed itself since the application armed it
    /// (read from the events the stream brought, which come before the
    /// reply to any later request): the error that says so.
    fn check_still_armed(&self, link: &StreamingClient) -> Result<(), Error> {
        let events = link.take_events();
        let mut intent = self.intent();
        if !intent.armed {
            return Ok(());
        }
        let mut faults = Faults::default();
        let mut disarmed = false;
        for e in &events {
            match e {
                Event::HeartbeatLost => {
                    disarmed = true;
                    faults = faults.union(Faults::HEARTBEAT_LOST);
                }
                Event::Disarmed { faults: f } => {
                    disarmed = true;
                    faults = faults.union(*f);
                }
                Event::Fault { .. } | Event::Homed => {}
            }
        }
        if !disarmed {
            return Ok(());
        }
        intent.armed = false;
        let why = if faults.contains(Faults::HEARTBEAT_LOST) {
            " (no call reached it within its heartbeat timeout: a force command or spidar_heartbeat keeps it armed)"
        } else {
            ""
        };
        Err(Error::new(
            SPIDAR_E_DISARMED,
            format!(
                "serial port {}: the device disarmed itself, faults {}{why}; its motors hold pre-tension, spidar_arm arms it again",
                self.port,
                fault_names(faults)
            ),
        ))
    }

    /// `Arm` (the device clears the faults whose cause has gone).
    pub fn arm(&self) -> Result<(), Error> {
        self.with_link(|link| {
            link.take_events();
            link.expect_ack(&Request::Arm)?;
            self.intent().armed = true;
            Ok(())
        })
    }

    /// `Disarm`: the motors off.
    pub fn disarm(&self) -> Result<(), Error> {
        self.with_link(|link| {
            self.intent().armed = false;
            link.expect_ack(&Request::Disarm)?;
            link.take_events();
            Ok(())
        })
    }

    /// `Heartbeat`; fails with `SPIDAR_E_DISARMED` once if the device
    /// disarmed itself since it was armed.
    pub fn heartbeat(&self) -> Result<(), Error> {
        self.with_link(|link| {
            link.expect_ack(&Request::Heartbeat)?;
            self.check_still_armed(link)
        })
    }

    /// `SetForceTarget` of a room-frame force, N (also the heartbeat).
    pub fn set_force(&self, force_n: [f64; 3]) -> Result<(), Error> {
        if !force_n.iter().all(|f| f.is_finite()) {
            return Err(Error::new(
                SPIDAR_E_ARGUMENT,
                format!(
                    "serial port {}: spidar_set_force: the force {force_n:?} N is not finite",
                    self.port
                ),
            ));
        }
        let Some(rotation) = self.intent().rotation else {
            return Err(Error::new(
                SPIDAR_E_FRAME_UNKNOWN,
                format!(
                    "serial port {}: the device runs a model flashed before this session, whose room frame the library does not know: give its blob to spidar_use_model",
                    self.port
                ),
            ));
        };
        let device = device_from_room_force(&rotation, force_n.map(|f| f as f32));
        self.with_link(|link| {
            link.expect_ack(&Request::SetForceTarget { force_n: device })?;
            self.check_still_armed(link)
        })
    }

    fn lost(link: &StreamingClient) -> u64 {
        u64::from(link.stream_seq().lost)
    }

    /// The newest state, without waiting.
    pub fn state(&self) -> Result<spidar_state, Error> {
        let rotation = self.intent().rotation;
        self.with_link(|link| {
            let Some(r) = link.latest() else {
                return Err(Error::new(
                    SPIDAR_E_NO_STATE,
                    format!("serial port {}: no state frame has arrived yet", self.port),
                ));
            };
            self.last_index.fetch_max(r.index, Ordering::SeqCst);
            Ok(state_of(
                &r,
                rotation.as_ref(),
                Self::lost(link),
                Instant::now(),
            ))
        })
    }

    /// The newest state once one newer than the last one handed out has
    /// come, waiting at most `timeout`.
    pub fn wait_state(&self, timeout: Duration) -> Result<spidar_state, Error> {
        let rotation = self.intent().rotation;
        self.with_link(|link| {
            let after = self.last_index.load(Ordering::SeqCst);
            let r = link.wait_newer(after, timeout)?;
            self.last_index.fetch_max(r.index, Ordering::SeqCst);
            Ok(state_of(
                &r,
                rotation.as_ref(),
                Self::lost(link),
                Instant::now(),
            ))
        })
    }

    fn get_info(&self, link: &StreamingClient) -> Result<Option<ModelInfo>, Error> {
        match link.request(&Request::GetInfo)? {
            Response::Info(i) => Ok(i),
            got => Err(LinkError::Unexpected {
                port: self.port.clone(),
                request: "GetInfo",
                got: format!("{got:?}"),
            }
            .into()),
        }
    }

    /// The stream's counters since the session started (`GetStats` for
    /// the device's). The host's `lost` is read before the device's
    /// counters: the stream goes on while the request is answered, and a
    /// gap the host sees later may be a frame the device drops after it
    /// answered. So every frame `lost` counts that the device dropped is
    /// among `device_dropped`, however busy the host.
    pub fn link_stats(&self) -> Result<spidar_link_stats, Error> {
        self.with_link(|link| {
            let lost = Self::lost(link);
            let device = match link.request(&Request::GetStats)? {
                Response::Stats(s) => s,
                got => {
                    return Err(LinkError::Unexpected {
                        port: self.port.clone(),
                        request: "GetStats",
                        got: format!("{got:?}"),
                    }
                    .into())
                }
            };
            let since = |now: u32, then: u32| now.wrapping_sub(then);
            Ok(spidar_link_stats {
                states: link.latest().map_or(0, |r| r.index),
                lost,
                rejected: u64::from(link.rejected()),
                device_dropped: u64::from(since(device.tx_dropped, self.stats0.tx_dropped)),
                heartbeat_losses: since(device.heartbeat_losses, self.stats0.heartbeat_losses),
                loop_overruns: since(device.loop_overruns, self.stats0.loop_overruns),
            })
        })
    }

    /// The device's active model.
    pub fn model_info(&self) -> Result<spidar_model_info, Error> {
        self.with_link(|link| Ok(model_info_of(self.get_info(link)?.as_ref())))
    }

    /// Says that the device's active model is `blob` (checked against the
    /// device's model header and blob CRC): its room frame is used from now
    /// on.
    pub fn use_model(&self, blob: &[u8]) -> Result<(), Error> {
        let rotation = rotation_of(blob)?;
        let (header, _) = spidar_protocol::blob::split_blob(blob)
            .map_err(|e| Error::new(SPIDAR_E_BLOB, format!("model blob: {e}")))?;
        // The CRC alone does not tell two blobs apart whose headers (which
        // end with their own CRC) differ and bodies agree: the header too.
        let crc = spidar_protocol::blob::CRC32.checksum(blob);
        self.with_link(|link| match self.get_info(link)? {
            Some(info) if info.blob_crc32 == crc && info.header == header => {
                self.intent().rotation = Some(rotation);
                Ok(())
            }
            other => Err(Error::new(
                SPIDAR_E_BLOB,
                format!(
                    "serial port {}: the device's model is not this blob (model {:#010x}, blob CRC {crc:#010x}; the device has {})",
                    self.port,
                    header.model_id,
                    other.map_or("no model".into(), |i| format!(
                        "model {:#010x}, blob CRC {:#010x}",
                        i.header.model_id, i.blob_crc32
                    ))
                ),
            )),
        })
    }

    /// Uploads `blob` (the stream pauses meanwhile) and makes it the
    /// device's model; its info read back.
    pub fn flash(&self, blob: &[u8]) -> Result<spidar_model_info, Error> {
        let rotation = rotation_of(blob)?;
        let mut guard = self.link.write().unwrap_or_else(PoisonError::into_inner);
        let Some(link) = guard.take() else {
            return Err(self.closed());
        };
        if let Err(e) = link.expect_ack(&Request::StreamOff) {
            *guard = Some(link);
            return Err(e.into());
        }
        let mut client = link.into_client();
        let flashed = client.flash(blob, |_| {});
        let info = flashed.and_then(|_| client.info());
        *guard = Some(StreamingClient::start(client, 1)?);
        let info = info?;
        self.intent().rotation = Some(rotation);
        Ok(model_info_of(info.as_ref()))
    }

    /// No force, `Disarm`, `StreamOff`: what closing does before the port
    /// closes (every step tried; the first failure returned).
    pub fn shut(&self) -> Result<(), Error> {
        self.with_link(|link| {
            let a = link.expect_ack(&Request::SetForceTarget { force_n: [0.0; 3] });
            let b = link.expect_ack(&Request::Disarm);
            let c = link.expect_ack(&Request::StreamOff);
            a.and(b).and(c).map_err(Error::from)
        })
    }
}
