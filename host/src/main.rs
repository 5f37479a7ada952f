//! The `spidar` command line.

use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "spidar",
    version,
    about = "Simulate, calibrate and diagnose string-based haptic devices (Scalable-SPIDAR)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// One variant per subcommand.
#[derive(Debug, Subcommand)]
enum Command {
    /// Simulate a device and write its nominal geometry, one session and the truth.
    Simulate(spidar::sim::SimulateArgs),
    /// Compile a calibration into the device's model blob and measure its fixed-point error.
    Compile(spidar::compile::CompileArgs),
    /// Upload a model blob to a device (chunks, retry, resume, CRC, atomic commit, read-back).
    Flash(spidar::link::cli::FlashArgs),
    /// Talk to a device: info, stream, arm, disarm, force.
    Device(spidar::link::cli::DeviceArgs),
    /// Run a virtual device (firmware logic + simulated plant) behind a pseudo-terminal.
    VirtualDevice(spidar::virtual_device::VirtualDeviceArgs),
}

fn main() {
    let cli = Cli::parse();
    let result: Result<String, Box<dyn std::error::Error>> = match &cli.command {
        Command::Simulate(args) => spidar::sim::run_simulate(args)
            .map(|report| report.to_string())
            .map_err(Into::into),
        Command::Compile(args) => spidar::compile::run_compile(args)
            .map(|report| report.to_string())
            .map_err(Into::into),
        Command::Flash(args) => spidar::link::cli::run_flash(args),
        Command::Device(args) => spidar::link::cli::run_device(args),
        Command::VirtualDevice(args) => {
            spidar::virtual_device::run_virtual_device(args).map_err(Into::into)
        }
    };
    match result {
        Ok(text) => print!("{text}"),
        Err(e) => {
            eprintln!("spidar: {e}");
            std::process::exit(1);
        }
    }
}
