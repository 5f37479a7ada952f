//! `spidar calibrate` and `spidar demo`.

use std::path::{Path, PathBuf};

use spidar::procedures::calibrate::{CalibrateConfig, CalibrateError, CalibrateRequest};
use spidar::procedures::demo::{DemoError, DemoRequest};

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
    /// Most training rows the identification loop decides on (which
    /// effects, tolerance and kinematics' rule): a longer session is read
    /// one row in every k, in time order, and the model is identified on
    /// those rows; every row enters the error figures. 0: every row (a
    /// 30,000-row session then takes ~10 times as long).
    #[arg(long, value_name = "ROWS", default_value_t = CalibrateConfig::full().max_loop_rows)]
    pub loop_rows: usize,
    /// The tracker's clock is about this far ahead of the device's (s;
    /// negative: behind): the alignment of streams searches 5 s around it
    /// instead of around 0. Only for a rig known to be further off; the
    /// offset is still found from the motion and reported.
    #[arg(long, value_name = "S", default_value_t = 0.0, allow_hyphen_values = true,
          value_parser = finite_seconds)]
    pub clock_offset_s: f64,
    /// The tracker's and the device's rows were paired by one clock when
    /// they were logged: streams are read as written, no clock offset is
    /// searched (a stream too short or too still to align from its motion,
    /// a tracker stamped by the device's logger). A latency every string
    /// shares is then the strings' own, in the model.
    #[arg(long, conflicts_with = "clock_offset_s")]
    pub clocks_paired: bool,
    /// Write the learners' data to DIR as `x,y,z,tx,ty,tz` CSVs (input and
    /// tracker, mm), for `scripts/reference/reference.py`:
    /// residual_{train,test}.csv and, when the sessions have dev_* columns
    /// (read, and checked, only with --blackbox or this option),
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
        c.max_loop_rows = self.loop_rows;
        c.clock_offset_s = self.clock_offset_s;
        c.clocks_paired = self.clocks_paired;
        c
    }

    /// What the library is asked to calibrate.
    pub fn request(&self) -> CalibrateRequest {
        CalibrateRequest {
            geometry: self.geometry.clone(),
            train: self.train.clone(),
            test: self.test.clone(),
            out: self.out.clone(),
            json: self.json.clone(),
            export_pairs: self.export_pairs.clone(),
            figures: !self.no_figures,
            config: self.config(),
        }
    }
}

/// Run `spidar calibrate`.
pub fn run_calibrate(args: &CalibrateArgs) -> Result<CalibrateOutput, CalibrateError> {
    let calibrated = spidar::procedures::calibrate::run_calibrate(&args.request())?;
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

impl DemoArgs {
    /// What the library is asked to run.
    pub fn request(&self) -> DemoRequest {
        DemoRequest {
            out: self.out.clone(),
            seed: self.seed,
            config: self.config.clone(),
            effects: self.effects.clone(),
            blackbox: self.blackbox,
            quick: self.quick,
            quiet: self.quiet,
            virtual_device: !self.no_device,
        }
    }
}

/// Run `spidar demo`; returns the text to print.
pub fn run_demo(args: &DemoArgs) -> Result<String, DemoError> {
    Ok(spidar::procedures::demo::run_demo(&args.request())?.to_string())
}

/// A finite number of seconds (`--clock-offset-s`).
fn finite_seconds(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(v) => Err(format!("{v} is not a finite number of seconds")),
        Err(e) => Err(format!("`{text}` is not a number of seconds ({e})")),
    }
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
