//! A model measured on the (virtual) device: flash the blob, move the
//! end-effector along a session's trajectory, stream the device's state and
//! compare the corrected position it reports with the true room position.
//!
//! This is what the demo's before/after table is made of: the numbers come
//! from the device's own fixed-point pipeline over the serial link, not from
//! the host's f64 model.

use std::time::Duration;

use spidar_protocol::messages::q16_to_mm;

use crate::data::stats::{position_error, ErrorStats};
use crate::device::link::{Client, ClientOptions, LinkError, StreamOptions};
use crate::sim::virtual_device::{
    spawn, Pace, Plant, Trajectory, VirtualDeviceConfig, VirtualDeviceError,
};
use crate::sim::{SampleTruth, SimulatedDevice};

/// Why a device run failed.
#[derive(Debug, thiserror::Error)]
pub enum VirtualDeviceRunError {
    #[error("virtual device: {0}")]
    VirtualDevice(#[from] VirtualDeviceError),
    #[error("device link: {0}")]
    Link(#[from] LinkError),
    #[error("the trajectory is empty")]
    EmptyTrajectory,
    #[error("the device streamed no state while the end-effector moved")]
    NoStates,
}

/// What the device reported along the trajectory.
#[derive(Clone, Copy, Debug)]
pub struct VirtualDeviceRun {
    /// Corrected position (device output) against the true room position, mm.
    pub error: ErrorStats,
    pub frames: u64,
    pub lost: u64,
    pub blob_len: usize,
}

/// Flashes `blob` to a fresh virtual device of `device` (the simulated
/// plant), which homes it at the trajectory's start, streams the whole
/// trajectory and measures the reported positions.
pub fn measure_on_virtual_device(
    device: &SimulatedDevice,
    trajectory: &[SampleTruth],
    blob: &[u8],
) -> Result<VirtualDeviceRun, VirtualDeviceRunError> {
    let trajectory = Trajectory::from_truth(trajectory);
    let end_us = trajectory
        .end_us()
        .ok_or(VirtualDeviceRunError::EmptyTrajectory)?;
    let config = VirtualDeviceConfig {
        pace: Pace::Fast,
        tick_us: 2000,
        ..VirtualDeviceConfig::default()
    };
    let vd = spawn(config, Plant::new(device.clone(), trajectory))?;
    let mut client = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device())?;
    // The model homes the device at the trajectory's start, where the
    // end-effector waits until then.
    client.flash(blob, |_| {})?;
    let mut errors = Vec::new();
    let report = client.stream(
        StreamOptions {
            decimation: 10,
            heartbeat: None,
            idle_timeout: Duration::from_secs(5),
            ..StreamOptions::default()
        },
        |state| {
            let reported = state.corrected_mm.map(q16_to_mm);
            errors.push(position_error(reported, vd.truth_room_mm(state.time_us)));
            state.time_us < end_us
        },
    )?;
    if errors.is_empty() {
        return Err(VirtualDeviceRunError::NoStates);
    }
    Ok(VirtualDeviceRun {
        error: ErrorStats::of(&errors),
        frames: report.frames,
        lost: u64::from(report.lost),
        blob_len: blob.len(),
    })
}
