//! `spidar calibrate` and `spidar demo`.

use std::path::{Path, PathBuf};

use spidar::data::dataset::{Geometry, Session};
use spidar::procedures::calibrate::{
    calibrate, write_outputs, CalibrateConfig, CalibrateError, NamedSession,
};
use spidar::sim::{run_simulate, SessionPath, SimulateRequest};

/// `spidar calibrate`: identify the model, diagnose it, train the NN and SVR
/// corrections, and report every stage on the training and test sessions.
#[derive(Clone, Debug, clap::Args)]
pub struct CalibrateArgs {
    /// Nominal geometry (TOML).
    #[arg(long)]
    pub geometry: PathBuf,
    /// Training session (CSV), e.g. the lattice.
    #[arg(long)]
    pub train: PathBuf,
    /// Separate test session (CSV): the generalization figures.
    #[arg(long)]
    pub test: PathBuf,
    /// Output directory: calibration.json, report.json, figures/.
    #[arg(long, default_value = "calibration")]
    pub out: PathBuf,
    /// Also write the JSON report here (`-`: to stdout, the summary then goes
    /// to stderr).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Seed of the selection split, NN initializations and SVR folds.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Also run the paper's black-box procedure (legacy dev_* position in,
    /// tracker out) when both sessions have dev_* columns. Slow: its SVR
    /// alone takes tens of seconds.
    #[arg(long)]
    pub blackbox: bool,
    /// Reduced NN sweep and SVR grid (for tests and smoke runs), instead of
    /// the paper's full procedure.
    #[arg(long)]
    pub quick: bool,
    /// Do not draw the figures.
    #[arg(long)]
    pub no_figures: bool,
    /// Keep the smooth winding law: do not try layer tables (the spool's
    /// departure from it, fitted per string and kept only when held-out
    /// data say it helps; see docs/design.md, "Layer tables").
    #[arg(long)]
    pub no_layer_tables: bool,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// Write the learners' data to DIR as `x,y,z,tx,ty,tz` CSVs (input and
    /// tracker, mm), for `scripts/reference/reference.py`:
    /// residual_{train,test}.csv and, when the sessions have dev_* columns,
    /// blackbox_{train,test}.csv. Training files hold the pairs left after
    /// outlier removal, test files every tracked row.
    #[arg(long, value_name = "DIR")]
    pub export_pairs: Option<PathBuf>,
}

/// What `spidar calibrate` prints.
#[derive(Clone, Debug)]
pub struct CalibrateOutput {
    /// The readable summary.
    pub summary: String,
    /// The JSON report when `--json -` asked for it on stdout.
    pub json_stdout: Option<String>,
}

impl CalibrateArgs {
    fn config(&self) -> CalibrateConfig {
        let mut c = if self.quick {
            CalibrateConfig::quick()
        } else {
            CalibrateConfig::full()
        };
        c.seed = self.seed;
        c.blackbox = self.blackbox;
        c.quiet = self.quiet;
        c.loop_config.layer_tables = !self.no_layer_tables;
        c
    }
}

/// Run `spidar calibrate`.
pub fn run_calibrate(args: &CalibrateArgs) -> Result<CalibrateOutput, CalibrateError> {
    let geometry = Geometry::load(&args.geometry)?;
    let train = Session::load(&args.train)?;
    let test = Session::load(&args.test)?;
    let config = args.config();
    let mut calibrated = calibrate(
        &geometry,
        &args.geometry,
        NamedSession {
            path: &args.train,
            session: &train,
        },
        NamedSession {
            path: &args.test,
            session: &test,
        },
        &config,
    )?;
    if !config.blackbox && train.has_legacy() && test.has_legacy() {
        calibrated.report.notes.push(
            "the sessions have dev_* columns: --blackbox adds the paper's black-box NN and SVR \
             for comparison"
                .into(),
        );
    }
    if let Some(dir) = &args.export_pairs {
        calibrated.pairs.residual.write(dir, "residual")?;
        if let Some(bb) = &calibrated.pairs.blackbox {
            bb.write(dir, "blackbox")?;
        }
    }
    write_outputs(
        &mut calibrated,
        &args.out,
        args.json.as_deref(),
        !args.no_figures,
        args.quiet,
    )?;
    let json_stdout = match args.json.as_deref() {
        Some(p) if p == Path::new("-") => Some(
            serde_json::to_string_pretty(&calibrated.report).map_err(|source| {
                CalibrateError::Json {
                    file: PathBuf::from("-"),
                    source,
                }
            })?,
        ),
        _ => None,
    };
    Ok(CalibrateOutput {
        summary: calibrated.report.summary(),
        json_stdout,
    })
}

/// `spidar demo`: simulate a device, its lattice and a test session, and
/// calibrate it.
#[derive(Clone, Debug, clap::Args)]
pub struct DemoArgs {
    /// Output directory: geometry.toml, lattice.csv, test.csv, truth.toml and
    /// calibration/ (report, calibration, figures).
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// Device seed (the simulated device's as-built errors).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Simulator configuration TOML (default: the built-in device).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Injected effect, e.g. `offset:3:mm=10` (repeatable; see `spidar simulate`).
    #[arg(long = "effect", value_name = "SPEC")]
    pub effects: Vec<String>,
    /// Also run the paper's black-box procedure (slow, see `calibrate --blackbox`).
    #[arg(long)]
    pub blackbox: bool,
    /// Reduced NN sweep and SVR grid.
    #[arg(long)]
    pub quick: bool,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// Skip the last act (flash and measure on the virtual device).
    #[arg(long)]
    pub no_device: bool,
}

/// Run `spidar demo`; returns the text to print.
pub fn run_demo(args: &DemoArgs) -> Result<String, CalibrateError> {
    let simulate = |kind: SessionPath, name: &str| SimulateRequest {
        out: args.out.clone(),
        seed: args.seed,
        config: args.config.clone(),
        preset: None,
        kind,
        points: None,
        effects: args.effects.clone(),
        name: Some(name.to_string()),
        session_seed: None,
        physics: Default::default(),
    };
    let lattice = run_simulate(&simulate(SessionPath::Lattice, "lattice"))?;
    let test = run_simulate(&simulate(SessionPath::Random, "test"))?;
    let mut text = format!(
        "simulated device (seed {}): {}, {} ({} rows), {} ({} rows), {} (the truth, not used)\n\n",
        args.seed,
        lattice.geometry.display(),
        lattice.session.display(),
        lattice.rows,
        test.session.display(),
        test.rows,
        lattice.truth.display(),
    );
    let out = args.out.join("calibration");
    let out_dir = out.clone();
    let output = run_calibrate(&CalibrateArgs {
        geometry: lattice.geometry.clone(),
        train: lattice.session.clone(),
        test: test.session.clone(),
        json: Some(out.join("report.json")),
        out,
        seed: 1,
        blackbox: args.blackbox,
        quick: args.quick,
        no_figures: false,
        no_layer_tables: false,
        quiet: args.quiet,
        export_pairs: None,
    })?;
    text.push_str(&output.summary);
    if !args.no_device {
        text.push_str(&run_on_virtual_device(args, &lattice.geometry, &out_dir)?);
    }
    Ok(text)
}

/// The demo's last act: compile the nominal and the calibrated model, flash
/// each to a virtual device whose plant follows the test trajectory, and
/// measure what the device reports against the true position.
fn run_on_virtual_device(
    args: &DemoArgs,
    geometry_path: &Path,
    calibration_dir: &Path,
) -> Result<String, CalibrateError> {
    use spidar::sim::measure::measure_on_virtual_device;
    use spidar::sim::{simulate_session_with_truth, SessionKind, SimConfig, SimDevice};
    use spidar_core::correction::CorrectionModel;
    use spidar_core::model::Calibration;

    let mut config = match &args.config {
        Some(path) => SimConfig::load(path)?,
        None => SimConfig::default(),
    };
    config.effects.extend(args.effects.iter().cloned());
    let device = SimDevice::new(&config, args.seed)?;
    // The test session's trajectory (run_simulate's seed rule for random sessions).
    let (_, truths) = simulate_session_with_truth(
        &device,
        SessionKind::Random {
            points: config.random.points,
        },
        args.seed.wrapping_add(2),
    )?;
    let geometry = Geometry::load(geometry_path)?;
    let nominal = Calibration {
        frame: geometry.nominal_frame(),
        strings: geometry.nominal_string_laws(),
        effects: Vec::new(),
        correction: CorrectionModel::None,
        length_scale_mm: [0.0; spidar_core::STRINGS],
        kinematics: Default::default(),
    };
    let calibrated =
        spidar::model::compile::load_calibration(&calibration_dir.join("calibration.json"))?;
    let blob = |what: &'static str, c: &Calibration| {
        spidar_core::blob::compile(c, spidar::model::compile::model_id_of(c), 0).map_err(|e| {
            CalibrateError::Blob {
                what,
                message: e.to_string(),
            }
        })
    };
    let before =
        measure_on_virtual_device(&device, &truths, &blob("the nominal model", &nominal)?)?;
    let after =
        measure_on_virtual_device(&device, &truths, &blob("the calibration", &calibrated)?)?;
    let row = |name: &str, r: &spidar::sim::measure::DeviceRun| {
        format!(
            "  {name:<22} {:>9.3} {:>8.3} {:>9.3} {:>8} {:>6} {:>8}\n",
            r.error.mean_mm, r.error.sd_mm, r.error.max_mm, r.frames, r.lost, r.blob_len
        )
    };
    Ok(format!(
        "\nOn the virtual device (flashed over its serial link, test trajectory replayed by the plant;\n\
         error of the position the device reports against the true position, room frame, mm):\n\
         \x20 {:<22} {:>9} {:>8} {:>9} {:>8} {:>6} {:>8}\n{}{}",
        "model",
        "mean",
        "sd",
        "max",
        "frames",
        "lost",
        "blob B",
        row("before (nominal)", &before),
        row("after (calibrated)", &after),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Wrap {
        #[command(flatten)]
        args: CalibrateArgs,
    }

    /// `--no-layer-tables` turns the loop's layer tables off; they are on by
    /// default.
    #[test]
    fn layer_tables_are_on_unless_turned_off() {
        let parse = |extra: &[&str]| {
            let mut argv = vec![
                "calibrate",
                "--geometry",
                "g.toml",
                "--train",
                "a.csv",
                "--test",
                "b.csv",
            ];
            argv.extend_from_slice(extra);
            Wrap::try_parse_from(argv).expect("parses").args.config()
        };
        assert!(parse(&[]).loop_config.layer_tables);
        assert!(!parse(&["--no-layer-tables"]).loop_config.layer_tables);
    }
}
