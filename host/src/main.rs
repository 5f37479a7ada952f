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
    /// Calibrate a device from a training and a test session: identification,
    /// diagnosis, NN and SVR corrections, error statistics, figures, JSON report.
    Calibrate(spidar::calibrate::CalibrateArgs),
    /// Simulate a device with a lattice and a test session, and calibrate it.
    Demo(spidar::calibrate::DemoArgs),
}

fn fail(e: &dyn std::error::Error) -> ! {
    eprintln!("spidar: {e}");
    std::process::exit(1);
}

fn main() {
    let cli = Cli::parse();
    match &cli.command {
        Command::Simulate(args) => match spidar::sim::run_simulate(args) {
            Ok(report) => print!("{report}"),
            Err(e) => fail(&e),
        },
        Command::Calibrate(args) => match spidar::calibrate::run_calibrate(args) {
            Ok(out) => match out.json_stdout {
                Some(json) => {
                    eprint!("{}", out.summary);
                    println!("{json}");
                }
                None => print!("{}", out.summary),
            },
            Err(e) => fail(&e),
        },
        Command::Demo(args) => match spidar::calibrate::run_demo(args) {
            Ok(text) => print!("{text}"),
            Err(e) => fail(&e),
        },
    }
}
