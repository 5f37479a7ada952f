//! `spidar monitor`: runtime recalibration on a rig or a simulated one.

use std::path::{Path, PathBuf};
use std::time::Duration;

use spidar::data::dataset::Session;
use spidar::model::compile::load_calibration;
use spidar::procedures::monitor::{
    calibrate_simulated_with, event_line, monitor, summary, Check, MonitorConfig, MonitorError,
    MonitorEvent, MonitorInputs, RefitPolicy, SimRigConfig, SimulatedMonitorRig,
};

use crate::interrupt::{self, EndOnInterrupt, Interrupted};
use crate::rig::RigArgs;

/// `spidar monitor`.
#[derive(Clone, Debug, clap::Args)]
pub struct MonitorArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// The calibration the device runs (calibration.json of `spidar calibrate`).
    #[arg(long, required_unless_present = "simulate")]
    pub calibration: Option<PathBuf>,
    /// The training session of that calibration (CSV): used in a refit too.
    #[arg(long)]
    pub train: Option<PathBuf>,
    /// Where the tracked body's origin sits from the strings' meeting point
    /// (body frame, mm): the tracker is read at the meeting point, as the
    /// calibration read it. Default: `identification.marker_body_mm` of the
    /// report.json beside --calibration (none without one).
    #[arg(
        long,
        value_name = "X,Y,Z",
        value_delimiter = ',',
        allow_hyphen_values = true
    )]
    pub marker_body_mm: Option<Vec<f64>>,
    /// Pairs in the rolling window (and the baseline).
    #[arg(long, default_value_t = 600)]
    pub window: usize,
    /// Run the drift check every this many new pairs.
    #[arg(long, default_value_t = 200)]
    pub check_every: usize,
    /// Drift when the window error exceeds the baseline by this factor.
    #[arg(long, default_value_t = 1.5)]
    pub error_factor: f64,
    /// What to do on drift: ask (the operator, y/N on standard input), yes
    /// (refit and reflash automatically), no (report only).
    #[arg(long, value_enum, default_value_t = RefitArg::Ask)]
    pub refit: RefitArg,
    /// Model id the device runs, when the blob was compiled with `--model-id`.
    #[arg(long)]
    pub model_id: Option<u32>,
    /// Stop after this long, s (default: until interrupted: SIGINT or
    /// SIGTERM then ends the run normally, with the summary and exit 0; with
    /// --seconds they end it early, with the summary and exit 130 or 143).
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Injected effect of the simulated device at run time, e.g.
    /// `slip:2:at_s=20,mm=8` (device time since boot; repeatable).
    #[arg(long = "effect", value_name = "SPEC", requires = "simulate")]
    pub effects: Vec<String>,
}

/// `--refit`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
// Described in `--refit`'s help (see `AudioChoice` for why not here).
pub enum RefitArg {
    Ask,
    Yes,
    No,
}

/// Where the tracked body's origin sits from the strings' meeting point:
/// `--marker-body-mm`, or else what the calibration found, from the
/// `report.json` that `spidar calibrate` wrote beside the `--calibration`
/// file (`identification.marker_body_mm`; none when the report is absent
/// or says `null`). Said on standard error when it comes from the report.
fn marker_of(args: &MonitorArgs) -> anyhow::Result<Option<[f64; 3]>> {
    if let Some(v) = args.marker_body_mm.as_deref() {
        let marker = <[f64; 3]>::try_from(v).map_err(|_| {
            MonitorError::Config(spidar::ConfigError::new(
                "marker_body_mm",
                format!(
                    "{} values given: X,Y,Z (mm, the body's frame) expected",
                    v.len()
                ),
            ))
        })?;
        return Ok(Some(marker));
    }
    let Some(calibration) = &args.calibration else {
        return Ok(None);
    };
    let report = calibration.with_file_name("report.json");
    let marker = marker_in_report(&report)?;
    if let Some(m) = marker {
        eprintln!(
            "reading the tracker at the strings' meeting point: the body's origin is [{}, {}, {}] mm \
             from it (identification.marker_body_mm of {}; --marker-body-mm overrides)",
            m[0],
            m[1],
            m[2],
            report.display()
        );
    }
    Ok(marker)
}

/// `identification.marker_body_mm` of a calibration report; `None` when the
/// file does not exist or the field is `null`.
fn marker_in_report(report: &Path) -> anyhow::Result<Option<[f64; 3]>> {
    let text = match std::fs::read_to_string(report) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => anyhow::bail!(
            "{}: cannot read the calibration report: {e}",
            report.display()
        ),
    };
    let json: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| anyhow::anyhow!("{}: not a calibration report: {e}", report.display()))?;
    let field = &json["identification"]["marker_body_mm"];
    if field.is_null() {
        return Ok(None);
    }
    let values: Option<Vec<f64>> = field
        .as_array()
        .map(|a| a.iter().filter_map(serde_json::Value::as_f64).collect());
    match values.as_deref() {
        Some(&[x, y, z]) if [x, y, z].iter().all(|c| c.is_finite()) => Ok(Some([x, y, z])),
        _ => anyhow::bail!(
            "{}: `identification.marker_body_mm` is {field}, not three numbers (mm)",
            report.display()
        ),
    }
}

/// Asks on standard error / standard input.
fn ask_on_terminal(check: &Check) -> bool {
    use std::io::Write;
    eprint!(
        "drift found ({} effect(s), window error {:.2} x baseline): refit and reflash the device? [y/N] ",
        check.findings.len(),
        check.error_ratio
    );
    let _ = std::io::stderr().flush();
    let mut line = String::new();
    match std::io::stdin().read_line(&mut line) {
        // Interrupted meanwhile: no refit, the monitor stops.
        Ok(_) if interrupt::raised() => false,
        Ok(_) => matches!(line.trim(), "y" | "Y" | "yes" | "Yes"),
        Err(_) => false,
    }
}

/// Runs `spidar monitor`; events are printed as they come, the summary is
/// returned. SIGINT or SIGTERM ends the run (the tracker is read as ended:
/// the library stops, disarms and reports): without `--seconds` that is the
/// normal end, with it the summary comes back as [`Interrupted`].
pub fn run(args: &MonitorArgs) -> anyhow::Result<String> {
    let mut config = MonitorConfig {
        body_id: args.rig.body,
        window: args.window,
        check_every: args.check_every,
        error_factor: args.error_factor,
        refit: match args.refit {
            RefitArg::Ask => RefitPolicy::Ask,
            RefitArg::Yes => RefitPolicy::Yes,
            RefitArg::No => RefitPolicy::No,
        },
        expected_model_id: args.model_id,
        marker_body_mm: marker_of(args)?,
        ..MonitorConfig::default()
    };
    if let Some(s) = args.seconds {
        if !(s.is_finite() && s > 0.0) {
            return Err(MonitorError::Config(spidar::ConfigError::new(
                "seconds",
                format!("{s} is not a positive duration"),
            ))
            .into());
        }
        config.duration = Some(Duration::from_secs_f64(s));
    }
    let mut print = |e: &MonitorEvent| println!("{}", event_line(e));
    let mut confirm = ask_on_terminal;
    let report = match args.rig.simulate {
        Some(seed) => {
            eprintln!(
                "calibrating the simulated device (seed {seed}) from its simulated lattice ..."
            );
            let sim_config =
                spidar::sim::SimConfig::load_or_default(args.rig.sim_config.as_deref())
                    .map_err(MonitorError::from)?;
            let calibrated = calibrate_simulated_with(seed, &sim_config)?;
            eprintln!("calibrated in {:.1} s", calibrated.seconds);
            let mut rig = SimulatedMonitorRig::start(
                &calibrated,
                &SimRigConfig {
                    effects: args.effects.clone(),
                    max_duration: config
                        .duration
                        .map_or(Duration::from_secs(3600), |d| d + Duration::from_secs(5)),
                    ..SimRigConfig::default()
                },
            )?;
            let mut client = rig.client()?;
            config.host_clock = rig.host_clock();
            let mut tracker = EndOnInterrupt(&mut rig.receiver);
            announce(&config);
            monitor(
                &mut client,
                &mut tracker,
                MonitorInputs {
                    geometry: &calibrated.geometry,
                    calibration: &calibrated.calibration,
                    calibration_file: Path::new("(simulated calibration)"),
                    training: Some(&calibrated.training),
                },
                &config,
                &mut print,
                &mut confirm,
            )?
        }
        None => {
            let geometry = args.rig.geometry().map_err(MonitorError::from)?;
            let calibration_path = args.calibration.clone().unwrap_or_default();
            let calibration = load_calibration(&calibration_path).map_err(MonitorError::from)?;
            let training = args
                .train
                .as_ref()
                .map(Session::load)
                .transpose()
                .map_err(MonitorError::from)?;
            let mut client = args.rig.client().map_err(MonitorError::from)?;
            let mut receiver = args.rig.receiver().map_err(MonitorError::from)?;
            let mut tracker = EndOnInterrupt(&mut receiver);
            announce(&config);
            monitor(
                &mut client,
                &mut tracker,
                MonitorInputs {
                    geometry: &geometry,
                    calibration: &calibration,
                    calibration_file: &calibration_path,
                    training: training.as_ref(),
                },
                &config,
                &mut print,
                &mut confirm,
            )?
        }
    };
    if let Some(signal) = interrupt::received() {
        if config.duration.is_some() {
            return Err(Interrupted {
                signal,
                output: summary(&report),
                message: format!(
                    "monitor: interrupted by {} before --seconds was up",
                    interrupt::signal_name(signal)
                ),
            }
            .into());
        }
        eprintln!("stopped by {}", interrupt::signal_name(signal));
    }
    Ok(summary(&report))
}

/// Installs the SIGINT and SIGTERM handlers and says on standard error how
/// the run ends. Only now: before, a signal ends the command at once (the
/// simulated device's calibration has nothing to clean up).
fn announce(config: &MonitorConfig) {
    interrupt::install();
    match config.duration {
        None => eprintln!(
            "monitoring until interrupted (Ctrl-C or SIGTERM: the summary, the device disarmed)"
        ),
        Some(d) => eprintln!(
            "monitoring for {:.1} s (Ctrl-C or SIGTERM ends it early: the summary, the device disarmed, exit 130 or 143)",
            d.as_secs_f64()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--marker-body-mm X,Y,Z` reaches the monitor's settings; an offset
    /// that is not finite is refused by name.
    #[test]
    fn the_marker_offset_is_given_on_the_command_line_and_checked() {
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            args: MonitorArgs,
        }
        let cli = Cli::try_parse_from([
            "monitor",
            "--simulate",
            "1",
            "--marker-body-mm",
            "9.5,-1.25,-38",
        ])
        .unwrap();
        assert_eq!(marker_of(&cli.args).unwrap(), Some([9.5, -1.25, -38.0]));
        let two =
            Cli::try_parse_from(["monitor", "--simulate", "1", "--marker-body-mm", "1,2"]).unwrap();
        let e = marker_of(&two.args).unwrap_err().to_string();
        assert!(e.contains("`marker_body_mm`: 2 values given"), "{e}");
    }

    /// Without `--marker-body-mm`, the monitor reads the body's origin from
    /// the report beside the calibration; an absent report or a `null` means
    /// none, a malformed one is an error naming the file and the field.
    #[test]
    fn the_marker_offset_comes_from_the_report_beside_the_calibration() {
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            args: MonitorArgs,
        }
        let dir =
            std::env::temp_dir().join(format!("spidar-monitor-marker-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let calibration = dir.join("calibration.json");
        let cli = Cli::try_parse_from([
            "monitor",
            "--port",
            "/dev/null",
            "--geometry",
            "g.toml",
            "--calibration",
            calibration.to_str().unwrap(),
        ])
        .unwrap();
        let report = dir.join("report.json");
        let _ = std::fs::remove_file(&report);
        assert_eq!(marker_of(&cli.args).unwrap(), None);
        std::fs::write(&report, r#"{"identification": {"marker_body_mm": null}}"#).unwrap();
        assert_eq!(marker_of(&cli.args).unwrap(), None);
        std::fs::write(
            &report,
            r#"{"identification": {"marker_body_mm": [1.5, -2.0, 40.0]}}"#,
        )
        .unwrap();
        assert_eq!(marker_of(&cli.args).unwrap(), Some([1.5, -2.0, 40.0]));
        std::fs::write(&report, r#"{"identification": {"marker_body_mm": [1.5]}}"#).unwrap();
        let e = marker_of(&cli.args).unwrap_err().to_string();
        assert!(
            e.contains("report.json") && e.contains("marker_body_mm"),
            "{e}"
        );
        std::fs::write(&report, "{ not json").unwrap();
        let e = marker_of(&cli.args).unwrap_err().to_string();
        assert!(
            e.contains("report.json") && e.contains("not a calibration report"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
