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
}

fn main() {
    let cli = Cli::parse();
    let result: Result<String, Box<dyn std::error::Error>> = match &cli.command {
        Command::Simulate(args) => spidar::sim::run_simulate(args)
            .map(|report| report.to_string())
            .map_err(Into::into),
    };
    match result {
        Ok(text) => print!("{text}"),
        Err(e) => {
            eprintln!("spidar: {e}");
            std::process::exit(1);
        }
    }
}
