//! Helpers of the cross-crate tests (`tests/rig`): the host's link, procedures
//! and tracker input against the device's own logic (`spidar-core`) over the
//! protocol, each in a thread of its own.

use std::time::{Duration, Instant};

use spidar::sim::virtual_device::{spawn, Plant, Trajectory, VirtualDevice, VirtualDeviceConfig};
use spidar::sim::{self, SimConfig};
use spidar_core::blob::compile;
use spidar_core::correction::CorrectionModel;
use spidar_core::model::Calibration;

/// Whether `condition` comes to hold within 5 s (polled every 5 ms): what a
/// device thread does after a call returns is not timed by the test, which
/// must pass on a busy machine (a fixed 50 ms sleep did not, with every
/// core loaded).
pub fn eventually(condition: impl Fn() -> bool) -> bool {
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        if condition() {
            return true;
        }
        if Instant::now() > deadline {
            return false;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Whether the virtual device's clock comes to `t_us` (µs since boot):
/// waits on device time, not on a length of wall-clock time. The 60 s
/// limit only detects a device that stopped ticking.
pub fn device_time_reaches(vd: &VirtualDevice, t_us: u64) -> bool {
    let deadline = Instant::now() + Duration::from_secs(60);
    while vd.status().device_time_us < t_us {
        if Instant::now() > deadline || !vd.is_running() {
            return false;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    true
}

/// The simulated device as built (no injected effects, no abnormal motor, so
/// its true parameters are an exact calibration).
pub fn sim_device() -> sim::SimulatedDevice {
    let mut config = SimConfig::default();
    config.abnormal_motor.enabled = false;
    config.effects.clear();
    sim::SimulatedDevice::new(&config, 7).expect("simulated device")
}

/// The device's true calibration with an optional correction.
pub fn calibration(device: &sim::SimulatedDevice, correction: CorrectionModel) -> Calibration {
    Calibration {
        frame: device.frame,
        strings: device.laws,
        effects: device.effects.clone(),
        correction,
        // The true model: no string noisier than another.
        length_scale_mm: [0.0; spidar_core::STRINGS],
        kinematics: Default::default(),
        home: None,
    }
}

/// The device's true calibration compiled into a model blob.
pub fn blob(device: &sim::SimulatedDevice, correction: CorrectionModel, model_id: u32) -> Vec<u8> {
    compile(&calibration(device, correction), model_id, 0).expect("compiles")
}

/// A virtual device (real time, default configuration) on [`sim_device`].
pub fn virtual_device(trajectory: Trajectory) -> VirtualDevice {
    spawn(
        VirtualDeviceConfig::default(),
        Plant::new(sim_device(), trajectory),
    )
    .expect("virtual device starts")
}

/// A virtual device in device time (`Pace::Fast`: its clock holds between
/// requests and ticks run back to back while it streams) holding still on
/// [`sim_device`], with the default heartbeat timeout or `heartbeat_timeout_ms`:
/// for tests of timeouts that must not depend on how fast the host runs.
pub fn virtual_device_in_device_time(heartbeat_timeout_ms: Option<u32>) -> VirtualDevice {
    let mut config = VirtualDeviceConfig {
        pace: spidar::sim::virtual_device::Pace::Fast,
        ..VirtualDeviceConfig::default()
    };
    if let Some(ms) = heartbeat_timeout_ms {
        config.device.control.safety.heartbeat_timeout_ms = ms;
    }
    spawn(config, Plant::new(sim_device(), Trajectory::Hold)).expect("virtual device starts")
}

/// A virtual device in real time whose heartbeat timeout is 2 s instead of
/// 20 ms: for tests of what an armed device renders, which must not depend
/// on how fast a busy machine schedules the host (a host process held off
/// the CPU for 20 ms would trip the device's heartbeat check; that check
/// has its own test, in device time).
pub fn patient_virtual_device(trajectory: Trajectory) -> VirtualDevice {
    let mut config = VirtualDeviceConfig::default();
    config.device.control.safety.heartbeat_timeout_ms = 2000;
    spawn(config, Plant::new(sim_device(), trajectory)).expect("virtual device starts")
}
