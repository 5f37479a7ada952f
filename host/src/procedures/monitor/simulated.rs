//! Simulation: a calibrated virtual device in a simulated operator's hand,
//! the rig `spidar monitor --simulate` and the tests run the monitor on.

use std::path::Path;
use std::time::{Duration, Instant};

use spidar_core::model::Calibration;

use crate::data::dataset::{Geometry, Session};
use crate::device::link::{Client, ClientOptions};
use crate::model::compile::{compile_checked, model_id_of};

use super::MonitorError;

/// A simulated device calibrated from its simulated lattice session.
#[derive(Clone, Debug)]
pub struct SimCalibration {
    /// The device seed.
    pub seed: u64,
    /// The simulator configuration of the device (effects aside).
    pub sim_config: crate::sim::SimConfig,
    pub geometry: Geometry,
    /// The lattice (training) session.
    pub training: Session,
    pub calibration: Calibration,
    /// The calibrate pipeline's summary.
    pub summary: String,
    pub seconds: f64,
}

/// Simulates the lattice and a test session of the built-in device of
/// `seed` (no injected effect: the device as calibrated) and runs the
/// calibrate pipeline on them in process (reduced NN/SVR search).
pub fn calibrate_simulated(seed: u64) -> Result<SimCalibration, MonitorError> {
    calibrate_simulated_with(seed, &crate::sim::SimConfig::default())
}

/// [`calibrate_simulated`] for the device of another simulator
/// configuration (`spidar monitor --simulate --sim-config`: e.g. a
/// 4-string rig); its injected effects are left out.
pub fn calibrate_simulated_with(
    seed: u64,
    sim_config: &crate::sim::SimConfig,
) -> Result<SimCalibration, MonitorError> {
    use crate::procedures::calibrate::{calibrate, CalibrateConfig, NamedSession};
    use crate::sim::{simulate_session, SessionKind, SimConfig, SimulatedDevice};
    let t0 = Instant::now();
    let config = SimConfig {
        effects: Vec::new(),
        ..sim_config.clone()
    };
    let device = SimulatedDevice::new(&config, seed)?;
    let training = simulate_session(&device, SessionKind::Lattice, seed.wrapping_add(100))?;
    let test = simulate_session(
        &device,
        SessionKind::Random { points: 300 },
        seed.wrapping_add(200),
    )?;
    let mut cc = CalibrateConfig::quick();
    cc.quiet = true;
    cc.seed = seed;
    let calibrated = calibrate(
        &device.nominal,
        Path::new("(simulated geometry)"),
        NamedSession {
            path: Path::new("(simulated lattice)"),
            session: &training,
        },
        NamedSession {
            path: Path::new("(simulated test session)"),
            session: &test,
        },
        &cc,
    )
    .map_err(|e| MonitorError::SimulatedCalibration(Box::new(e)))?;
    Ok(SimCalibration {
        seed,
        sim_config: config.clone(),
        geometry: device.nominal.clone(),
        training,
        calibration: calibrated.calibration,
        summary: calibrated.report.summary(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Settings of a [`SimulatedMonitorRig`].
#[derive(Clone, Debug, PartialEq)]
pub struct SimRigConfig {
    /// Injected effects of the device at run time (`--effect` syntax, e.g.
    /// `slip:2:at_s=8,mm=6`: `at_s` is device time since boot, and the
    /// device boots, and homes, when monitoring starts).
    pub effects: Vec<String>,
    /// The operator wanders in a cube of this half size around home, mm.
    pub wander_half_size_mm: f64,
    pub wander_speed_mm_s: f64,
    /// Probability that a tracker frame has the marker occluded.
    pub occlusion: f64,
    /// Probability that a tracker frame's position is a glitch, thrown 50
    /// to 300 mm ([`crate::sim::operator::SimOperatorConfig::glitch`]).
    pub glitch: f64,
    pub operator_seed: u64,
    /// The tracker's frame rate, Hz (the device streams at 100 Hz: another
    /// rate puts frames between its states).
    pub frame_rate_hz: f64,
    /// The operator (and the tracker) stop after this long.
    pub max_duration: Duration,
}

impl Default for SimRigConfig {
    fn default() -> Self {
        SimRigConfig {
            effects: Vec::new(),
            wander_half_size_mm: 120.0,
            wander_speed_mm_s: 60.0,
            occlusion: 0.02,
            glitch: 0.0,
            operator_seed: 1,
            frame_rate_hz: 100.0,
            max_duration: Duration::from_secs(600),
        }
    }
}

/// A calibrated virtual device (real time) whose end-effector is in the
/// hand of a simulated operator who wanders about, and the DTrack2 receiver
/// on loopback the operator's tracker sends to: a [`SimulatedRig`] with the
/// calibration flashed before the operator starts.
///
/// [`SimulatedRig`]: crate::sim::operator::SimulatedRig
pub struct SimulatedMonitorRig {
    pub rig: crate::sim::operator::SimulatedRig,
    /// The model flashed before the start.
    pub model_id: u32,
}

impl std::ops::Deref for SimulatedMonitorRig {
    type Target = crate::sim::operator::SimulatedRig;
    fn deref(&self) -> &Self::Target {
        &self.rig
    }
}

impl std::ops::DerefMut for SimulatedMonitorRig {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.rig
    }
}

impl SimulatedMonitorRig {
    /// Builds the run-time device (same seed, plus `config.effects`),
    /// spawns it with the end-effector at its true home, flashes the
    /// calibration, power-cycles it (it homes at boot, where the hand is:
    /// device time since home = since boot), then starts the operator.
    pub fn start(
        calibrated: &SimCalibration,
        config: &SimRigConfig,
    ) -> Result<SimulatedMonitorRig, MonitorError> {
        use crate::sim::operator::{FreeMotion, SimulatedRig};
        use crate::sim::{SimConfig, SimulatedDevice};
        let sim_config = SimConfig {
            effects: config.effects.clone(),
            ..calibrated.sim_config.clone()
        };
        let device = SimulatedDevice::new(&sim_config, calibrated.seed)?;
        let model_id = model_id_of(&calibrated.calibration);
        let blob = compile_checked(
            &calibrated.calibration,
            model_id,
            0,
            Path::new("(simulated calibration)"),
        )?;
        let home = device.frame.home;
        let rig = SimulatedRig::start_prepared(
            device,
            [0.0; 3],
            |virtual_device| -> Result<(), MonitorError> {
                {
                    let mut client = Client::open_with(
                        virtual_device.port_path(),
                        ClientOptions::for_simulated_device(),
                    )?;
                    client.flash(&blob, |_| {})?;
                }
                Ok(virtual_device.power_cycle()?)
            },
            |op| {
                op.free_motion = FreeMotion::Wander {
                    centre_mm: home,
                    half_size_mm: config.wander_half_size_mm,
                    speed_mm_s: config.wander_speed_mm_s,
                };
                op.occlusion = config.occlusion;
                op.glitch = config.glitch;
                op.seed = config.operator_seed;
                op.frame_rate_hz = config.frame_rate_hz;
                op.max_duration = config.max_duration;
            },
        )?;
        Ok(SimulatedMonitorRig { rig, model_id })
    }
}
