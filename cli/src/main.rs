//! The `spidar` command line: a thin shell over the `spidar` library. It owns
//! the arguments (clap), the progress bars and terminal output, and the
//! error context; every computation is the library's.

mod calibrate;
mod compile;
mod progress;
mod simulate;

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
    Simulate(simulate::SimulateArgs),
    /// Compile a calibration into the device's model blob and measure its fixed-point error.
    Compile(compile::CompileArgs),
    /// Upload a model blob to a device (chunks, retry, resume, CRC, atomic commit, read-back).
    Flash(spidar::device::link::cli::FlashArgs),
    /// Talk to a device: info, stream, arm, disarm, force.
    Device(spidar::device::link::cli::DeviceArgs),
    /// Run a virtual device (firmware logic + simulated plant) behind a pseudo-terminal.
    VirtualDevice(spidar::device::virtual_device::VirtualDeviceArgs),
    /// Calibrate a device from a training and a test session: identification,
    /// diagnosis, NN and SVR corrections, error statistics, figures, JSON report.
    Calibrate(calibrate::CalibrateArgs),
    /// Simulate a device with a lattice and a test session, and calibrate it.
    Demo(calibrate::DemoArgs),
    /// Guided initialization: haptic and audio cues bring the marker to the
    /// frame centre, home is declared there, the room transform recorded.
    Init(spidar::procedures::init::InitArgs),
    /// Lattice data collection: the operator brings the marker into each
    /// cell in turn; tracker and device state are captured there, appended
    /// to the session CSV as they come; a stopped run resumes.
    Collect(spidar::procedures::collect::CollectArgs),
    /// Runtime recalibration: pair device states with tracker frames while
    /// the device is used, report drift (a slipped string, ...) and refit
    /// and reflash the calibration.
    Monitor(spidar::procedures::recalibrate::MonitorArgs),
}

fn fail(e: &dyn std::error::Error) -> ! {
    eprintln!("spidar: {e}");
    std::process::exit(1);
}

/// Prints an error (the library's messages name the file, line or field) and exits 1.
fn fail_with(e: anyhow::Error) -> ! {
    eprintln!("spidar: {e}");
    std::process::exit(1);
}

fn main() {
    let cli = Cli::parse();
    spidar::progress::set_reporter(Box::new(progress::TerminalBars));
    match &cli.command {
        Command::Simulate(args) => match simulate::run(args) {
            Ok(report) => print!("{report}"),
            Err(e) => fail_with(e),
        },
        Command::Calibrate(args) => match calibrate::run_calibrate(args) {
            Ok(out) => match out.json_stdout {
                Some(json) => {
                    eprint!("{}", out.summary);
                    println!("{json}");
                }
                None => print!("{}", out.summary),
            },
            Err(e) => fail(&e),
        },
        Command::Demo(args) => match calibrate::run_demo(args) {
            Ok(text) => print!("{text}"),
            Err(e) => fail(&e),
        },
        Command::Compile(args) => match compile::run(args) {
            Ok(report) => print!("{report}"),
            Err(e) => fail_with(e),
        },
        Command::Flash(args) => match spidar::device::link::cli::run_flash(args) {
            Ok(text) => print!("{text}"),
            Err(e) => fail(e.as_ref()),
        },
        Command::Device(args) => match spidar::device::link::cli::run_device(args) {
            Ok(text) => print!("{text}"),
            Err(e) => fail(e.as_ref()),
        },
        Command::Init(args) => match spidar::procedures::init::run_init(args) {
            Ok(text) => print!("{text}"),
            Err(e) => fail(&e),
        },
        Command::Collect(args) => match spidar::procedures::collect::run_collect(args) {
            Ok(text) => print!("{text}"),
            Err(e) => fail(&e),
        },
        Command::Monitor(args) => match spidar::procedures::recalibrate::run_monitor(args) {
            Ok(text) => print!("{text}"),
            Err(e) => fail(&e),
        },
        Command::VirtualDevice(args) => {
            match spidar::device::virtual_device::run_virtual_device(args) {
                Ok(text) => print!("{text}"),
                Err(e) => fail(&e),
            }
        }
    }
}
