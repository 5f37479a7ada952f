//! The rig `init`, `collect` and `monitor` run on: the device's serial port,
//! its nominal geometry and the optical tracker, or a simulated rig.

use std::net::SocketAddr;
use std::path::PathBuf;

use spidar::data::dataset::Geometry;
use spidar::device::link::Client;
use spidar::device::tracker::{DtrackReceiver, ReceiverConfig};

/// Where the device and the tracker are; one group, flattened into each
/// procedure's options.
#[derive(Clone, Debug, clap::Args)]
pub struct RigArgs {
    /// Serial port of the device (not with --simulate).
    #[arg(long, required_unless_present = "simulate")]
    pub port: Option<String>,
    /// Nominal geometry TOML (sent to a device that has no calibration; its
    /// frame centre and eq. 6 translation are the procedure's defaults).
    #[arg(long, required_unless_present = "simulate")]
    pub geometry: Option<PathBuf>,
    /// Address to receive DTrack2 UDP datagrams on.
    #[arg(long, default_value = "0.0.0.0:5000")]
    pub tracker: SocketAddr,
    /// DTrack body id of the end-effector's marker.
    #[arg(long, default_value_t = 0)]
    pub body: u32,
    /// Run on the built-in simulated device with a simulated operator and
    /// tracker (device seed; --port, --geometry and --tracker are ignored).
    #[arg(long, value_name = "SEED")]
    pub simulate: Option<u64>,
    /// Simulator configuration of the --simulate device (TOML, as `spidar
    /// simulate --config`; e.g. `[nominal] strings = 4` for a 4-string rig)
    /// (default: the built-in 8-string Scalable-SPIDAR).
    #[arg(long, value_name = "TOML", requires = "simulate")]
    pub sim_config: Option<PathBuf>,
}

impl RigArgs {
    /// The nominal geometry of a real rig (`--geometry`).
    pub fn geometry(&self) -> Result<Geometry, spidar::data::dataset::DatasetError> {
        Geometry::load(self.geometry.clone().unwrap_or_default())
    }

    /// The device's port opened (`--port`).
    pub fn client(&self) -> Result<Client, spidar::device::link::LinkError> {
        Client::open(self.port.as_deref().unwrap_or_default())
    }

    /// The tracker's receiver bound to `--tracker`, for `--body`.
    pub fn receiver(&self) -> Result<DtrackReceiver, spidar::device::tracker::TrackerError> {
        let mut config = ReceiverConfig::new(self.tracker);
        config.body_id = self.body;
        DtrackReceiver::bind(config)
    }

    /// The simulated device of `--simulate SEED` and `--sim-config`.
    pub fn simulated_device(
        &self,
        seed: u64,
    ) -> Result<spidar::sim::SimulatedDevice, spidar::sim::operator::RigError> {
        let config = spidar::sim::SimConfig::load_or_default(self.sim_config.as_deref())?;
        Ok(spidar::sim::SimulatedDevice::new(&config, seed)?)
    }
}
