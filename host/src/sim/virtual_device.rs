//! A SPIDAR controller on the host: the firmware's own device logic
//! ([`spidar_core::device::Device`], [`DeviceLink`]) behind a
//! pseudo-terminal, driven by a [`Plant`] (strings, end-effector on a
//! trajectory, motors, encoders) and a two-slot [`RamFlash`] that can lose
//! power at any write.
//!
//! [`spawn`] opens the pseudo-terminal pair, runs the device in a thread and
//! returns a [`VirtualDevice`] whose [`VirtualDevice::port_path`] any serial
//! client opens (`spidar flash --port PATH`, [`crate::device::link::Client::open`]):
//! host commands and tests go through the same serial path as with a real
//! device.
//!
//! # Time
//!
//! The device runs on its own clock (µs since boot), one [`Device::tick`]
//! every [`VirtualDeviceConfig::tick_us`] of device time. [`Pace`] maps it to
//! real time: `RealTime { speed }` keeps device time at `speed` x real time
//! (1.0: like the hardware); `Fast` runs ticks back to back while a state
//! stream is on (paced by the reader: a full pseudo-terminal holds the
//! device back) and holds the device's clock otherwise, so a stream always
//! starts where the last one stopped (at boot: time 0), whatever the host's
//! speed. Requests are handled at the
//! device time of the last tick, so heartbeat timeouts are in device time.
//! `Virtual` is virtual time for a simulated rig: the plant's end-effector
//! is in a simulated operator's clocked [`Hand`], and the device ticks as
//! far as the operator has committed the hand's path, back to back, and
//! waits there (still answering requests, at the device time it reached).
//! The simulated world then runs as fast as it is computed, and a host
//! starved of CPU slows all of it down instead of finding its heartbeat
//! late; a host that stops sending heartbeats while the world goes on
//! still trips the device, after 100 ms of simulated time. Whatever the
//! pace, a plant with a clocked hand never ticks past the committed path.
//!
//! # Home
//!
//! The device declares home (its encoders' zero, the calibration's home
//! point) at boot when a model is stored, else when its first geometry
//! arrives (a flashed model, `SetNominalGeometry`). The end-effector waits
//! at home until then and sets off on its trajectory at that instant
//! ([`VirtualStatus::path_start_us`]), as an operator holds it at home
//! until the device is initialized: flashed over the link at any time,
//! a model reads the positions it was made for
//! (`docs/decisions/0043-virtual-path-and-motors-on.md`).
//!
//! # Power
//!
//! [`VirtualDevice::cut_flash_after`] plans a power loss at the n-th next
//! flash operation ([`RamFlash::cut_after`]); when it happens the device goes
//! silent (it stops answering and ticking) until
//! [`VirtualDevice::power_cycle`], which boots a new `Device` on the same
//! flash (the plant back at home, device time 0), as the firmware would boot.

pub use crate::sim::plant::{Hand, Plant, SimClock, Trajectory, Waypoint};

use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{channel, Receiver, Sender, TryRecvError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::SerialPort;
use spidar_core::control::ControlConfig;
use spidar_core::device::{Device, DeviceConfig, DeviceLink, TickInput};
use spidar_core::model_store::{FlashError, ModelFlash, RamFlash, Slot, RECORD_LEN};
use spidar_core::STRINGS;
use spidar_protocol::{DecodeStats, Request};

/// Bytes per flash slot of the virtual device: a 128 KiB blob and its
/// commit record.
pub const SLOT_LEN: usize = 128 * 1024 + RECORD_LEN;

/// Largest blob the firmware takes (its RAM model buffers, see
/// `docs/hardware.md`); the virtual device takes up to
/// [`VirtualDeviceConfig::blob_capacity`].
pub const FIRMWARE_BLOB_CAPACITY: usize = spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY;

/// How long [`VirtualDevice::power_cycle`] waits for the new boot: a wait,
/// not a measure (a boot takes milliseconds; a machine with every core
/// busy several times over stalled one past 5 s in the load test).
pub const REBOOT_WAIT: Duration = Duration::from_secs(30);

/// Why the virtual device could not start.
#[derive(Debug, thiserror::Error)]
pub enum VirtualDeviceError {
    #[error("virtual device: cannot open a pseudo-terminal: {0}")]
    Pty(serialport::Error),
    #[error("virtual device: cannot make the pseudo-terminal non-blocking: {0}")]
    NonBlocking(nix::Error),
    #[error("virtual device: cannot start its thread: {0}")]
    Thread(std::io::Error),
    #[error("virtual device: {0}")]
    Config(#[from] crate::ConfigError),
    #[error("virtual device: the device thread has stopped")]
    Stopped,
    #[error("virtual device: no reboot within {0:?}")]
    RebootTimeout(Duration),
}

/// How device time relates to real time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Pace {
    /// Device time runs `speed` times as fast as real time.
    RealTime { speed: f64 },
    /// Back-to-back ticks while streaming; the device's clock holds
    /// otherwise (no tick, no timeout), so what a stream shows does not
    /// depend on how fast the host opened it.
    Fast,
    /// Virtual time: the device ticks as far as the simulated world has
    /// been computed (a clocked [`Hand`]'s committed path,
    /// [`Plant::ready_until_us`]) and no further, back to back, whatever
    /// the wall clock says; a starved host slows the whole simulated world
    /// down instead of letting the device's timeouts expire. With nothing
    /// to wait for (a trajectory, a free hand) it runs in real time.
    Virtual,
}

/// Settings of a virtual device.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VirtualDeviceConfig {
    /// What the device says about itself, and its loop settings.
    pub device: DeviceConfig,
    /// Bytes of each RAM model buffer (the largest blob; at most a slot's
    /// [`SLOT_LEN`] - [`RECORD_LEN`]). The firmware's is
    /// [`FIRMWARE_BLOB_CAPACITY`].
    pub blob_capacity: usize,
    /// Device time per control-loop iteration, µs.
    pub tick_us: u32,
    pub pace: Pace,
}

impl Default for VirtualDeviceConfig {
    fn default() -> Self {
        VirtualDeviceConfig {
            device: DeviceConfig {
                firmware_version: [0, 1, 0],
                device_id: *b"VIRTUAL-0001",
                loop_period_us: 1000,
                boot_id: 1,
                control: ControlConfig::default(),
            },
            blob_capacity: SLOT_LEN - RECORD_LEN,
            tick_us: 1000,
            pace: Pace::RealTime { speed: 1.0 },
        }
    }
}

/// What the device thread reports.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VirtualStatus {
    /// Boots so far (1 after `spawn`).
    pub boots: u32,
    /// Device time of the last tick, µs since the last boot.
    pub device_time_us: u64,
    /// Ticks since the last boot.
    pub ticks: u64,
    /// The flash lost power and the device is silent until a power cycle.
    pub power_lost: bool,
    /// The device link's decoder counters since the last boot.
    pub rx: DecodeStats,
    /// Frames sent since the last boot.
    pub tx_frames: u32,
    /// Frames not sent because the pseudo-terminal was full (nobody reading).
    pub tx_dropped: u32,
    /// Tension of each string at the plant, N.
    pub plant_tensions_n: [f64; STRINGS],
    /// Commanded tension of each string after the last tick, N.
    pub commanded_n: [f32; STRINGS],
    pub armed: bool,
    /// The plant's last error (a pulley ran empty, ...).
    pub plant_error: Option<String>,
    /// Flash operations (word writes and erases) since spawn.
    pub flash_operations: usize,
    /// Device time at which the end-effector set off on its trajectory
    /// this boot: when the device declared home (at boot with a stored
    /// model, else at its first geometry); `None`: it waits at home.
    pub path_start_us: Option<u64>,
}

enum Control {
    PowerCycle,
    Shutdown,
}

struct FlashShared {
    cut: Mutex<Option<usize>>,
    lost: AtomicBool,
    ops: AtomicUsize,
}

/// The virtual device's flash: two [`RamFlash`] slots on the heap, with a
/// power cut that the test thread can plan while the device runs.
pub struct VirtualFlash {
    inner: Box<RamFlash<SLOT_LEN>>,
    shared: Arc<FlashShared>,
}

impl VirtualFlash {
    fn arm_cut(&mut self) {
        if let Ok(mut cut) = self.shared.cut.lock() {
            if let Some(n) = cut.take() {
                self.inner.cut_after(n);
            }
        }
    }

    fn note<T>(&self, r: Result<T, FlashError>) -> Result<T, FlashError> {
        if matches!(r, Err(FlashError::PowerLost)) {
            self.shared.lost.store(true, Ordering::SeqCst);
        }
        self.shared
            .ops
            .store(self.inner.operations(), Ordering::SeqCst);
        r
    }
}

impl ModelFlash for VirtualFlash {
    const SLOT_LEN: usize = SLOT_LEN;

    fn read(&mut self, slot: Slot, offset: usize, buf: &mut [u8]) -> Result<(), FlashError> {
        self.arm_cut();
        let r = self.inner.read(slot, offset, buf);
        self.note(r)
    }

    fn erase(&mut self, slot: Slot) -> Result<(), FlashError> {
        self.arm_cut();
        let r = self.inner.erase(slot);
        self.note(r)
    }

    fn write(&mut self, slot: Slot, offset: usize, data: &[u8]) -> Result<(), FlashError> {
        self.arm_cut();
        let r = self.inner.write(slot, offset, data);
        self.note(r)
    }
}

/// A running virtual device. Dropping it stops the device thread.
pub struct VirtualDevice {
    port_path: String,
    control: Sender<Control>,
    status: Arc<Mutex<VirtualStatus>>,
    flash: Arc<FlashShared>,
    plant: Plant,
    config: VirtualDeviceConfig,
    thread: Option<JoinHandle<()>>,
}

/// Starts a virtual device: opens a pseudo-terminal pair, boots the device
/// (erased flash, the plant at home) and runs it in a thread.
pub fn spawn(
    config: VirtualDeviceConfig,
    plant: Plant,
) -> Result<VirtualDevice, VirtualDeviceError> {
    if config.blob_capacity == 0 || config.blob_capacity > SLOT_LEN - RECORD_LEN {
        return Err(VirtualDeviceError::Config(crate::ConfigError::new(
            "blob_capacity",
            format!(
                "{} bytes; must be 1..={} (a slot)",
                config.blob_capacity,
                SLOT_LEN - RECORD_LEN
            ),
        )));
    }
    if config.tick_us == 0 {
        return Err(VirtualDeviceError::Config(crate::ConfigError::new(
            "tick_us",
            "must be positive",
        )));
    }
    if let Pace::RealTime { speed } = config.pace {
        if !(speed.is_finite() && speed > 0.0) {
            return Err(VirtualDeviceError::Config(crate::ConfigError::new(
                "pace.speed",
                format!("{speed} is not a positive speed"),
            )));
        }
    }
    let (mut master, slave) = serialport::TTYPort::pair().map_err(VirtualDeviceError::Pty)?;
    let port_path = slave.name().ok_or_else(|| {
        VirtualDeviceError::Pty(serialport::Error::new(
            serialport::ErrorKind::Unknown,
            "the pseudo-terminal has no name",
        ))
    })?;
    // The device must never block on a full pseudo-terminal.
    nix::fcntl::fcntl(
        master.as_raw_fd(),
        nix::fcntl::FcntlArg::F_SETFL(nix::fcntl::OFlag::O_NONBLOCK),
    )
    .map_err(VirtualDeviceError::NonBlocking)?;
    master
        .set_timeout(Duration::from_millis(1))
        .map_err(VirtualDeviceError::Pty)?;
    let flash_shared = Arc::new(FlashShared {
        cut: Mutex::new(None),
        lost: AtomicBool::new(false),
        ops: AtomicUsize::new(0),
    });
    let status = Arc::new(Mutex::new(VirtualStatus::default()));
    let (tx, rx) = channel();
    let thread_status = status.clone();
    let thread_flash = flash_shared.clone();
    let thread_plant = plant.clone();
    let thread = std::thread::Builder::new()
        .name(format!("virtual-device {port_path}"))
        .stack_size(8 << 20)
        .spawn(move || {
            // Keep the slave side open so the master never sees a hang-up
            // between two clients.
            let _slave = slave;
            run(
                master,
                config,
                thread_plant,
                rx,
                thread_status,
                thread_flash,
            );
        })
        .map_err(VirtualDeviceError::Thread)?;
    let vd = VirtualDevice {
        port_path,
        control: tx,
        status,
        flash: flash_shared,
        plant,
        config,
        thread: Some(thread),
    };
    vd.wait_boots(1, Duration::from_secs(5))?;
    Ok(vd)
}

impl VirtualDevice {
    /// Path of the serial port to open (the pseudo-terminal's slave side).
    pub fn port_path(&self) -> &str {
        &self.port_path
    }

    /// The configuration it runs with.
    pub fn config(&self) -> &VirtualDeviceConfig {
        &self.config
    }

    /// Whether the device thread still runs (it stops on a fault of its
    /// pseudo-terminal, or when the device is dropped).
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// What the device thread last reported.
    pub fn status(&self) -> VirtualStatus {
        self.status.lock().map(|s| s.clone()).unwrap_or_default()
    }

    /// Flash operations (word writes and erases) so far.
    pub fn flash_operations(&self) -> usize {
        self.flash.ops.load(Ordering::SeqCst)
    }

    /// Lets `ops` more flash word writes / erases succeed; the next one is
    /// torn and the power goes (the device falls silent).
    pub fn cut_flash_after(&self, ops: usize) {
        if let Ok(mut cut) = self.flash.cut.lock() {
            *cut = Some(ops);
        }
    }

    /// Power off and on: a new `Device` boots on the same flash, the plant
    /// is back at home, device time restarts at 0. Returns when it booted;
    /// waits up to [`REBOOT_WAIT`] for it.
    pub fn power_cycle(&self) -> Result<(), VirtualDeviceError> {
        let boots = self.status().boots;
        self.control
            .send(Control::PowerCycle)
            .map_err(|_| VirtualDeviceError::Stopped)?;
        self.wait_boots(boots + 1, REBOOT_WAIT)
    }

    fn wait_boots(&self, boots: u32, timeout: Duration) -> Result<(), VirtualDeviceError> {
        let t0 = Instant::now();
        while self.status().boots < boots {
            if self.thread.as_ref().is_none_or(|t| t.is_finished()) {
                return Err(VirtualDeviceError::Stopped);
            }
            if t0.elapsed() > timeout {
                return Err(VirtualDeviceError::RebootTimeout(timeout));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        Ok(())
    }

    /// The plant as configured (its trajectory and true geometry).
    pub fn plant(&self) -> &Plant {
        &self.plant
    }

    /// True end-effector position at device time `t_us` of this boot,
    /// device frame, mm (on its trajectory from when the device declared
    /// home, [`VirtualStatus::path_start_us`]).
    pub fn truth_device_mm(&self, t_us: u64) -> [f64; 3] {
        self.plant
            .device_mm_on_path(t_us, self.status().path_start_us)
    }

    /// True end-effector position at device time `t_us` of this boot, room
    /// frame, mm (what a perfect tracker sees).
    pub fn truth_room_mm(&self, t_us: u64) -> [f64; 3] {
        self.plant
            .device
            .room_from_device(&self.truth_device_mm(t_us))
    }

    /// Stops the device thread.
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        let _ = self.control.send(Control::Shutdown);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for VirtualDevice {
    fn drop(&mut self) {
        self.stop();
    }
}

enum Exit {
    PowerCycle,
    Shutdown,
}

fn run(
    mut master: serialport::TTYPort,
    config: VirtualDeviceConfig,
    mut plant: Plant,
    control: Receiver<Control>,
    status: Arc<Mutex<VirtualStatus>>,
    flash_shared: Arc<FlashShared>,
) {
    let mut flash = VirtualFlash {
        inner: Box::new(RamFlash::new()),
        shared: flash_shared,
    };
    let mut ram = vec![0u8; config.blob_capacity];
    let mut spare = vec![0u8; config.blob_capacity];
    let mut boots = 0u32;
    loop {
        boots += 1;
        flash.inner.power_cycle();
        flash.shared.lost.store(false, Ordering::SeqCst);
        plant.reset();
        let (f, exit) = run_boot(
            &mut master,
            &config,
            &mut plant,
            flash,
            &mut ram,
            &mut spare,
            &control,
            &status,
            boots,
        );
        flash = f;
        if let Exit::Shutdown = exit {
            return;
        }
    }
}

/// Writes one frame to the master side; waits at most `wait` for room.
/// Returns false if (part of) the frame was dropped.
fn write_frame(
    master: &mut serialport::TTYPort,
    frame: &[u8],
    wait: Duration,
    resync: &mut bool,
) -> bool {
    let deadline = Instant::now() + wait;
    if *resync {
        // The peer may hold half a frame: a lone 0x00 ends it.
        match master.write(&[0]) {
            Ok(1) => *resync = false,
            _ => return false,
        }
    }
    let mut rest = frame;
    let mut started = false;
    while !rest.is_empty() {
        match master.write(rest) {
            Ok(n) if n > 0 => {
                started = true;
                rest = &rest[n..];
            }
            Ok(_) => {}
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock
                        | std::io::ErrorKind::TimedOut
                        | std::io::ErrorKind::Interrupted
                ) => {}
            Err(_) => {}
        }
        if !rest.is_empty() && Instant::now() >= deadline {
            if started {
                *resync = true;
            }
            return false;
        }
    }
    true
}

#[allow(clippy::too_many_arguments)]
fn run_boot(
    master: &mut serialport::TTYPort,
    config: &VirtualDeviceConfig,
    plant: &mut Plant,
    flash: VirtualFlash,
    ram: &mut [u8],
    spare: &mut [u8],
    control: &Receiver<Control>,
    status: &Mutex<VirtualStatus>,
    boots: u32,
) -> (VirtualFlash, Exit) {
    let shared = flash.shared.clone();
    // Each boot has its own id, as the firmware's random one: the configured
    // id plus the boots before it.
    let device_config = DeviceConfig {
        boot_id: config.device.boot_id.wrapping_add(boots.saturating_sub(1)),
        ..config.device
    };
    let dev = match Device::new(device_config, flash, ram, spare, plant.raw_home, 0) {
        Ok(d) => d,
        // Invalid safety limits in the configuration: the device cannot
        // boot.
        Err(_) => return stay_unbooted(control, shared),
    };
    if dev.home_declared_us().is_none() {
        // No model to home with at boot: the end-effector waits at home
        // until the device declares home there (its first geometry).
        plant.rest_until_started();
    }
    let mut boot = Boot {
        master,
        config,
        plant,
        status,
        shared,
        boots,
        dev,
        link: DeviceLink::new(),
        now_us: 0,
        ticks: 0,
        anchor: (Instant::now(), 0),
        speed: match config.pace {
            Pace::RealTime { speed } => speed,
            Pace::Fast | Pace::Virtual => 1.0,
        },
        streaming: false,
        resync: false,
        tx_dropped: 0,
    };
    let mut buf = [0u8; 4096];
    boot.publish();
    loop {
        match control.try_recv() {
            Ok(Control::PowerCycle) => return (boot.dev.into_flash(), Exit::PowerCycle),
            Ok(Control::Shutdown) | Err(TryRecvError::Disconnected) => {
                return (boot.dev.into_flash(), Exit::Shutdown)
            }
            Err(TryRecvError::Empty) => {}
        }
        boot.serve(&mut buf);
    }
}

/// A device that cannot boot stays silent until told otherwise (a power
/// cycle boots it again on the same configuration: silent again).
fn stay_unbooted(control: &Receiver<Control>, shared: Arc<FlashShared>) -> (VirtualFlash, Exit) {
    loop {
        match control.recv() {
            Ok(Control::PowerCycle) => {}
            _ => {
                return (
                    VirtualFlash {
                        inner: Box::new(RamFlash::new()),
                        shared,
                    },
                    Exit::Shutdown,
                )
            }
        }
    }
}

/// One boot of the virtual device: the device and its link, its clock
/// against real time, and what it tells the [`VirtualDevice`].
struct Boot<'a> {
    master: &'a mut serialport::TTYPort,
    config: &'a VirtualDeviceConfig,
    plant: &'a mut Plant,
    status: &'a Mutex<VirtualStatus>,
    shared: Arc<FlashShared>,
    boots: u32,
    dev: Device<'a, VirtualFlash>,
    link: DeviceLink,
    /// Device time of the last tick, µs since boot.
    now_us: u64,
    ticks: u64,
    /// (real time, device time) that keep the pace: device time `t` is due
    /// at `anchor.0 + (t - anchor.1) / speed`.
    anchor: (Instant, u64),
    speed: f64,
    /// A state stream is on.
    streaming: bool,
    /// The peer may hold half a frame (see [`write_frame`]).
    resync: bool,
    tx_dropped: u32,
}

/// How one pass runs its ticks.
struct Pass {
    /// The simulated world's limit (a clocked hand's committed path).
    gate: Option<u64>,
    /// Ticks back to back in virtual time.
    run_virtual: bool,
    /// Ticks back to back (`Fast` while streaming, or virtual time).
    run_fast: bool,
    /// No tick at all (`Fast` while not streaming).
    hold: bool,
}

impl Pass {
    /// Device time `t` lies past the simulated world's limit.
    fn gated(&self, t: u64) -> bool {
        self.gate.is_some_and(|g| t > g)
    }
}

impl Boot<'_> {
    /// When device time `t_us` is due in real time.
    fn real_at(&self, t_us: u64) -> Instant {
        let anchor = self.anchor;
        anchor.0 + Duration::from_secs_f64(t_us.saturating_sub(anchor.1) as f64 / 1e6 / self.speed)
    }

    /// The end-effector sets off on its trajectory when the device
    /// declares home with it there: a device homed anywhere else reads
    /// every string off by where it was (on the default orbit, strings
    /// that disagree by more than the faulty-string threshold).
    fn start_path_at_home(&mut self) {
        if self.plant.path_start_us().is_none() {
            if let Some(home_us) = self.dev.home_declared_us() {
                self.plant.start_path(home_us);
            }
        }
    }

    /// Writes the device's status for the [`VirtualDevice`].
    fn publish(&mut self) {
        if let Ok(mut s) = self.status.lock() {
            s.boots = self.boots;
            s.device_time_us = self.now_us;
            s.ticks = self.ticks;
            s.power_lost = self.shared.lost.load(Ordering::SeqCst);
            let c = self.link.counters();
            s.rx = c.rx;
            s.tx_frames = c.tx_frames;
            s.tx_dropped = self.tx_dropped;
            s.plant_tensions_n = self.plant.tensions_n();
            s.commanded_n = self.dev.last_output().tensions_n;
            // As requests left it (a `Disarm` answered between two ticks
            // counts, even while the simulated world waits).
            s.armed = self.dev.armed();
            s.plant_error = self.plant.error().map(str::to_string);
            s.flash_operations = self.shared.ops.load(Ordering::SeqCst);
            s.path_start_us = self.plant.path_start_us();
        }
    }

    /// One pass: the requests that came, answered, then the ticks due.
    fn serve(&mut self, buf: &mut [u8]) {
        let tick_us = u64::from(self.config.tick_us);
        let dead = self.shared.lost.load(Ordering::SeqCst);
        // The simulated world's limit (a clocked hand's committed path):
        // never tick past it, whatever the pace.
        let gate = self.plant.ready_until_us();
        let run_virtual = matches!(self.config.pace, Pace::Virtual) && gate.is_some() && !dead;
        let pass = Pass {
            gate,
            run_virtual,
            run_fast: (matches!(self.config.pace, Pace::Fast) && self.streaming && !dead)
                || run_virtual,
            hold: matches!(self.config.pace, Pace::Fast) && !self.streaming,
        };
        let n = self.read_requests(buf, &pass);
        self.answer(&buf[..n]);
        if self.shared.lost.load(Ordering::SeqCst) {
            // Silent until the power cycle; keep the clock anchored.
            self.anchor = (Instant::now(), self.now_us);
            self.publish();
            return;
        }
        if !pass.hold {
            self.run_ticks(&pass);
        }
        if pass.run_fast
            || pass.hold
            || pass.gated(self.now_us + tick_us)
            || self.real_at(self.now_us + 100 * tick_us) < Instant::now()
        {
            // Fast, or far behind (a loaded host): device time goes on from
            // here instead of bursting to catch up.
            self.anchor = (Instant::now(), self.now_us);
        }
        self.publish();
    }

    /// Reads what the host sent into `buf`, waiting at most until the next
    /// tick is due (not at all when ticks run back to back); its length.
    fn read_requests(&mut self, buf: &mut [u8], pass: &Pass) -> usize {
        let next_us = self.now_us + u64::from(self.config.tick_us);
        let due = self.real_at(next_us);
        let wait = if pass.gated(next_us) {
            Duration::from_millis(1)
        } else if pass.run_fast {
            Duration::ZERO
        } else {
            due.saturating_duration_since(Instant::now())
                .min(Duration::from_millis(5))
        };
        let _ = self.master.set_timeout(wait.max(Duration::from_micros(1)));
        if wait.is_zero() {
            // Do not wait: only what is already there.
            let _ = self.master.set_timeout(Duration::ZERO);
            self.master.read(buf).unwrap_or(0)
        } else {
            self.master.read(buf).unwrap_or(0)
        }
    }

    /// Handles the requests in `bytes` at the device time of the last tick
    /// and sends the replies (none once the power went).
    fn answer(&mut self, bytes: &[u8]) {
        let mut rest = bytes;
        while !rest.is_empty() && !self.shared.lost.load(Ordering::SeqCst) {
            let now = self.now_us;
            let d = &mut self.dev;
            let st = &mut self.streaming;
            let (used, reply) = self.link.push(rest, |req, counters| {
                d.set_link_counters(counters);
                match req {
                    Request::StreamOn { decimation } if *decimation > 0 => *st = true,
                    Request::StreamOff => *st = false,
                    _ => {}
                }
                d.handle(req, now)
            });
            rest = rest.get(used..).unwrap_or(&[]);
            // The status is published before the reply goes out, so whoever
            // has seen a reply reads a status that already counts its request
            // (and the frames rejected before it).
            let reply = reply.map(<[u8]>::to_vec);
            self.start_path_at_home();
            self.publish();
            // A reply to a request during which the power went is never sent.
            if let Some(frame) = reply {
                if !self.shared.lost.load(Ordering::SeqCst)
                    && !write_frame(
                        self.master,
                        &frame,
                        Duration::from_millis(50),
                        &mut self.resync,
                    )
                {
                    self.tx_dropped = self.tx_dropped.wrapping_add(1);
                }
            }
        }
    }

    /// Runs the ticks due (a bounded burst), sending each tick's events and
    /// state frame.
    fn run_ticks(&mut self, pass: &Pass) {
        let tick_us = u64::from(self.config.tick_us);
        let now_real = Instant::now();
        let mut budget = if pass.run_virtual {
            20
        } else if pass.run_fast {
            1
        } else {
            20
        };
        while budget > 0
            && !pass.gated(self.now_us + tick_us)
            && (pass.run_fast || self.real_at(self.now_us + tick_us) <= now_real)
        {
            budget -= 1;
            let t = self.now_us + tick_us;
            let commanded = self.dev.last_output().tensions_n;
            let raw = self.plant.step(t, &commanded, self.dev.motors_enabled());
            // The simulated clock is at `t` before anything stamped `t`
            // leaves the device: no sample arrives before its time.
            self.plant.publish_tick();
            let t0 = Instant::now();
            self.dev.tick(&TickInput {
                raw_counts: raw,
                now_us: t,
                estop: false,
            });
            let took = t0.elapsed().as_micros().min(u128::from(u16::MAX)) as u16;
            self.dev.record_loop_time(took);
            self.now_us = t;
            self.ticks += 1;
            self.send_tick_output(pass.run_fast);
        }
    }

    /// Sends the events and the state frame of the last tick; a state frame
    /// waits up to 200 ms for room when ticks run back to back (the reader
    /// paces the device), not at all otherwise.
    fn send_tick_output(&mut self, run_fast: bool) {
        let frame_wait = if run_fast {
            Duration::from_millis(200)
        } else {
            Duration::ZERO
        };
        while let Some(e) = self.dev.take_event() {
            if let Some(frame) = self.link.encode_event(&e) {
                if !write_frame(
                    self.master,
                    frame,
                    Duration::from_millis(5),
                    &mut self.resync,
                ) {
                    // Counted on the device too, as a state frame's and as
                    // the firmware counts an event it cannot queue: its
                    // sequence number is spent, and the host's count of
                    // lost frames is held to the device's.
                    self.tx_dropped = self.tx_dropped.wrapping_add(1);
                    self.dev.count_stream_dropped();
                }
            }
        }
        if let Some(s) = self.dev.state_frame() {
            self.plant.note_state_sent();
            let sent = match self.link.encode_state(&s) {
                Some(frame) => write_frame(self.master, frame, frame_wait, &mut self.resync),
                None => false,
            };
            if !sent {
                self.tx_dropped = self.tx_dropped.wrapping_add(1);
                self.dev.count_stream_dropped();
            }
        }
    }
}

/// The simulated device and the path of its end-effector that a virtual
/// device's plant follows (`spidar virtual-device`'s options).
#[derive(Clone, Debug)]
pub struct PlantRequest {
    /// Device seed of the simulated device (as `spidar simulate --seed`).
    pub seed: u64,
    /// Simulator configuration TOML (as `spidar simulate --config`).
    pub config: Option<PathBuf>,
    /// Injected effects, e.g. `offset:3:mm=10`.
    pub effects: Vec<String>,
    /// Path of the end-effector.
    pub path: PlantPath,
    /// Points of a [`PlantPath::Random`] path (a random session's path).
    pub points: usize,
}

/// The end-effector's path on a virtual device.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlantPath {
    /// Still at home.
    Hold,
    /// A 150 mm circle every 8 s.
    Orbit,
    /// The path of a random test session of the device.
    Random,
}

/// Builds the simulated device and plant of `request`.
pub fn plant_of(request: &PlantRequest) -> Result<Plant, crate::sim::SimError> {
    let mut sim_config = match &request.config {
        Some(path) => crate::sim::SimConfig::load(path)?,
        None => crate::sim::SimConfig::default(),
    };
    sim_config.effects.extend(request.effects.iter().cloned());
    let device = crate::sim::SimulatedDevice::new(&sim_config, request.seed)?;
    let trajectory = match request.path {
        PlantPath::Hold => Trajectory::Hold,
        PlantPath::Orbit => Trajectory::Orbit {
            radius_mm: 150.0,
            period_s: 8.0,
        },
        PlantPath::Random => {
            let (_, truths) = crate::sim::simulate_session_with_truth(
                &device,
                crate::sim::SessionKind::Random {
                    points: request.points,
                },
                request.seed.wrapping_add(2),
            )?;
            Trajectory::from_truth(&truths)
        }
    };
    Ok(Plant::new(device, trajectory))
}
