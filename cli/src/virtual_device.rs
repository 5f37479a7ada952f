//! `spidar virtual-device`: a virtual device on a pseudo-terminal.

use std::io::Write as _;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use spidar::sim::virtual_device::{
    plant_of, spawn, Pace, PlantPath, PlantRequest, VirtualDeviceConfig, VirtualDeviceError,
    FIRMWARE_BLOB_CAPACITY,
};

/// `spidar virtual-device`: a virtual device on a pseudo-terminal.
#[derive(Clone, Debug, clap::Args)]
pub struct VirtualDeviceArgs {
    /// Device seed of the simulated device (as `spidar simulate --seed`).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Simulator configuration TOML (as `spidar simulate --config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Injected effect, e.g. `offset:3:mm=10` (repeatable).
    #[arg(long = "effect", value_name = "SPEC")]
    pub effects: Vec<String>,
    /// Path of the end-effector.
    #[arg(long, value_enum, default_value_t = TrajectoryArg::Orbit)]
    pub trajectory: TrajectoryArg,
    /// Points of a `random` trajectory (a random session's path).
    #[arg(long, default_value_t = 50)]
    pub points: usize,
    /// Device time per real time (1 = like the hardware).
    #[arg(long, default_value_t = 1.0, value_parser = crate::args::positive)]
    pub speed: f64,
    /// Largest model blob, KiB, at most 128 (the virtual flash slot). The
    /// default is the reference firmware's capacity, so that a blob the
    /// board would refuse is refused here too.
    #[arg(long, default_value_t = FIRMWARE_BLOB_CAPACITY / 1024)]
    pub capacity_kib: usize,
    /// Stop after this many seconds (default: run until killed).
    #[arg(long, value_parser = crate::args::positive)]
    pub seconds: Option<f64>,
}

/// `--trajectory`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TrajectoryArg {
    Hold,
    Orbit,
    Random,
}

impl VirtualDeviceArgs {
    /// The plant the library is asked to build.
    fn plant(&self) -> PlantRequest {
        PlantRequest {
            seed: self.seed,
            config: self.config.clone(),
            effects: self.effects.clone(),
            path: match self.trajectory {
                TrajectoryArg::Hold => PlantPath::Hold,
                TrajectoryArg::Orbit => PlantPath::Orbit,
                TrajectoryArg::Random => PlantPath::Random,
            },
            points: self.points,
        }
    }
}

/// Runs `spidar virtual-device`: prints the port path, then serves until
/// killed (or `--seconds`).
pub fn run(args: &VirtualDeviceArgs) -> anyhow::Result<String> {
    let plant = plant_of(&args.plant())?;
    let config = VirtualDeviceConfig {
        blob_capacity: args.capacity_kib.saturating_mul(1024),
        pace: Pace::RealTime { speed: args.speed },
        ..VirtualDeviceConfig::default()
    };
    let vd = spawn(config, plant)?;
    println!("{}", vd.port_path());
    println!(
        "virtual SPIDAR running (seed {}, trajectory {:?}, blob capacity {} KiB; the firmware takes {} KiB); Ctrl-C stops it",
        args.seed,
        args.trajectory,
        args.capacity_kib,
        FIRMWARE_BLOB_CAPACITY / 1024
    );
    let _ = std::io::stdout().flush();
    let t0 = Instant::now();
    loop {
        std::thread::sleep(Duration::from_millis(100));
        if args
            .seconds
            .is_some_and(|s| t0.elapsed().as_secs_f64() >= s)
        {
            break;
        }
        if !vd.is_running() {
            return Err(VirtualDeviceError::Stopped.into());
        }
    }
    let s = vd.status();
    Ok(format!(
        "virtual device stopped after {:.1} s of device time, {} frames sent, {} received ({} rejected)\n",
        s.device_time_us as f64 / 1e6,
        s.tx_frames,
        s.rx.ok,
        s.rx.rejected()
    ))
}
