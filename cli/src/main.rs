//! The `spidar` command line: a thin shell over the `spidar` library. It owns
//! the arguments (clap), the progress bars and terminal output, and the
//! error context; every computation is the library's.

mod args;
mod audio;
mod calibrate;
mod collect;
mod compile;
mod device;
mod init;
mod interrupt;
mod monitor;
mod progress;
mod report;
mod rig;
mod simulate;
mod view;
mod virtual_device;

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
    Flash(device::FlashArgs),
    /// Talk to a device: info, stream, arm, disarm, force.
    Device(device::DeviceArgs),
    /// Run a virtual device (firmware logic + simulated plant) behind a pseudo-terminal.
    VirtualDevice(virtual_device::VirtualDeviceArgs),
    /// Calibrate a device from a training and a test session: identification,
    /// diagnosis, NN and SVR corrections, error statistics, figures, JSON report.
    Calibrate(calibrate::CalibrateArgs),
    /// Simulate a device with a lattice and a test session, and calibrate it.
    Demo(calibrate::DemoArgs),
    /// Rebuild a calibration's report page (report.html) from the
    /// report.json and report-figures.json in its folder.
    Report(report::ReportArgs),
    /// Guided initialization: haptic and audio cues bring the marker to the
    /// frame centre, home is declared there, the room transform recorded.
    ///
    /// SIGINT (Ctrl-C) or SIGTERM before home is declared stops it with
    /// the force off and the device disarmed, writes nothing, and exits
    /// 130 (SIGINT) or 143 (SIGTERM).
    Init(init::InitArgs),
    /// Lattice data collection: the operator brings the marker into each
    /// cell in turn; tracker and device state are captured there, appended
    /// to the session CSV as they come; a stopped run resumes.
    ///
    /// SIGINT (Ctrl-C) or SIGTERM stops the run between two frames: the
    /// motors off, the summary printed, exit 130 (SIGINT) or 143 (SIGTERM),
    /// not 0 as a completed run or one stopped by --max-cells.
    Collect(collect::CollectArgs),
    /// Runtime recalibration: pair device states with tracker frames while
    /// the device is used, report drift (a slipped string, ...) and refit
    /// and reflash the calibration.
    ///
    /// It runs until interrupted, or for --seconds. SIGINT (Ctrl-C) or
    /// SIGTERM stops it (a refit under way finishes first), leaves the device
    /// disarmed and prints the summary; without --seconds that is its
    /// normal end (exit 0), with --seconds it ends the run short of what
    /// was asked (exit 130 for SIGINT, 143 for SIGTERM).
    Monitor(monitor::MonitorArgs),
}

/// Prints an error (the library's messages name the file, line or field) and
/// exits 1; a command a signal stopped after its cleanup
/// ([`interrupt::Interrupted`]) prints what a normal end would have on
/// standard output first, and exits 128 + the signal's number.
fn fail(e: anyhow::Error) -> ! {
    if let Some(i) = e.downcast_ref::<interrupt::Interrupted>() {
        // What was done before the interrupt; a closed pipe takes none.
        let mut out = std::io::stdout().lock();
        let _ = std::io::Write::write_all(&mut out, i.output.as_bytes());
        let _ = std::io::Write::flush(&mut out);
        drop(out);
        eprintln!("spidar: {i}");
        std::process::exit(i.exit_code());
    }
    eprintln!("spidar: {e}");
    std::process::exit(1);
}

/// Runs one command; returns what goes to standard output.
fn run(command: &Command) -> anyhow::Result<String> {
    Ok(match command {
        Command::Simulate(args) => simulate::run(args)?,
        Command::Calibrate(args) => {
            let out = calibrate::run_calibrate(args)?;
            match out.json_stdout {
                // The report on stdout: the summary goes to stderr.
                Some(json) => {
                    eprint!("{}", out.summary);
                    format!("{json}\n")
                }
                None => out.summary,
            }
        }
        Command::Demo(args) => calibrate::run_demo(args)?,
        Command::Report(args) => report::run(args)?,
        Command::Compile(args) => compile::run(args)?,
        Command::Flash(args) => device::run_flash(args)?,
        Command::Device(args) => device::run_device(args)?,
        Command::Init(args) => init::run(args)?,
        Command::Collect(args) => collect::run(args)?,
        Command::Monitor(args) => monitor::run(args)?,
        Command::VirtualDevice(args) => virtual_device::run(args)?,
    })
}

fn main() {
    return_large_blocks_to_the_system();
    let cli = Cli::parse();
    spidar::progress::set_reporter(Box::new(progress::TerminalBars));
    match run(&cli.command) {
        Ok(text) => write_out(&text),
        Err(e) => fail(e),
    }
}

/// Writes a command's output on stdout. A reader that closed the pipe
/// (`spidar device stream | head -5`) wants no more: the run ends quietly,
/// where `print!` panicked with a backtrace.
fn write_out(text: &str) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    if let Err(e) = out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        if e.kind() != std::io::ErrorKind::BrokenPipe {
            fail(anyhow::anyhow!("writing the output: {e}"));
        }
    }
}

/// Allocations from 128 KiB up each get their own mapping, returned to the
/// system when freed. glibc raises that threshold to the largest block
/// freed so far (up to 32 MiB), after which a calibration's per-row vectors
/// of a long session (megabytes each, made and freed at every step of every
/// fit, on two threads) are carved from the heap and leave it fragmented: a
/// 100,000-row session peaked at 196 MB resident for 150 MB of live data,
/// 141 MB with the threshold held. Elsewhere the system allocator's default
/// stays.
fn return_large_blocks_to_the_system() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const LARGE_BLOCK_BYTES: nix::libc::c_int = 128 * 1024;
        // SAFETY: `mallopt` only sets a parameter of glibc's allocator; it
        // is called before any thread is started.
        unsafe { nix::libc::mallopt(nix::libc::M_MMAP_THRESHOLD, LARGE_BLOCK_BYTES) };
    }
}
