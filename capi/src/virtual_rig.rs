//! `spidar_open_virtual`: a virtual device (the firmware's device logic on
//! a simulated plant, behind a pseudo-terminal) in this process, with the
//! simulated device's true calibration flashed, so that an application can
//! run against it as against a calibrated device.

#![allow(non_camel_case_types)]

use host::device::link::{Client, ClientOptions};
use host::sim::virtual_device::{
    spawn, Pace, Plant, Trajectory, VirtualDevice, VirtualDeviceConfig,
};
use host::sim::{SimConfig, SimulatedDevice};
use spidar_core::blob::compile;
use spidar_core::correction::CorrectionModel;
use spidar_core::model::Calibration;

use crate::error::{Error, SPIDAR_E_VIRTUAL};

/// Settings of a virtual device (`spidar_open_virtual`). All zero is the
/// default: seed 0, the firmware's heartbeat timeout (20 ms), device time
/// at the pace of real time, the end-effector on a 150 mm orbit.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct spidar_virtual_options {
    /// Seed of the simulated device (as `spidar simulate --seed`).
    pub seed: u64,
    /// The device's heartbeat timeout, ms (0: the firmware's, 20 ms).
    pub heartbeat_timeout_ms: u32,
    /// 0: device time runs with real time (like the hardware). 1: device
    /// time runs only while the stream is on, back to back as fast as the
    /// library reads it (`Pace::Fast`): for tests in device time.
    pub fast: u8,
    /// 0: the end-effector orbits (150 mm circle every 8 s of device time);
    /// 1: it stays at home.
    pub hold: u8,
}

/// Model id of the true calibration `spidar_open_virtual` flashes.
pub const SPIDAR_VIRTUAL_MODEL_ID: u32 = 0x5B1D_A000;

/// Starts a virtual device as `options` say and flashes its true
/// calibration; the device, a client open on its port and the blob.
pub fn spawn_virtual(
    options: &spidar_virtual_options,
) -> Result<(VirtualDevice, Client, Vec<u8>), Error> {
    let fail = |what: &str, e: &dyn std::fmt::Display| {
        Error::new(SPIDAR_E_VIRTUAL, format!("virtual device: {what}: {e}"))
    };
    let mut sim = SimConfig::default();
    // A device whose true parameters are an exact calibration.
    sim.abnormal_motor.enabled = false;
    sim.effects.clear();
    let device =
        SimulatedDevice::new(&sim, options.seed).map_err(|e| fail("simulated device", &e))?;
    let calibration = Calibration {
        frame: device.frame,
        strings: device.laws,
        effects: device.effects.clone(),
        correction: CorrectionModel::None,
        length_scale_mm: [0.0; spidar_core::STRINGS],
        kinematics: Default::default(),
        home: None,
    };
    let blob = compile(&calibration, SPIDAR_VIRTUAL_MODEL_ID, 0)
        .map_err(|e| fail("compile its calibration", &e))?;
    let trajectory = if options.hold != 0 {
        Trajectory::Hold
    } else {
        Trajectory::Orbit {
            radius_mm: 150.0,
            period_s: 8.0,
        }
    };
    let mut config = VirtualDeviceConfig {
        pace: if options.fast != 0 {
            Pace::Fast
        } else {
            Pace::RealTime { speed: 1.0 }
        },
        ..VirtualDeviceConfig::default()
    };
    if options.heartbeat_timeout_ms > 0 {
        config.device.control.safety.heartbeat_timeout_ms = options.heartbeat_timeout_ms;
    }
    let vd = spawn(config, Plant::new(device, trajectory)).map_err(|e| fail("start", &e))?;
    let mut client = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device())?;
    client.flash(&blob, |_| {})?;
    Ok((vd, client, blob))
}
