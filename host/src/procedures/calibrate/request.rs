//! A calibration from files to files, as `spidar calibrate` and the demo
//! run it: the geometry and both sessions read, [`calibrate`] run, the
//! learners' pairs exported when asked, and the outputs written
//! ([`write_outputs`]).

use std::path::{Path, PathBuf};

use crate::data::dataset::{Geometry, ReadOptions, Session};
use crate::data::output::refuse_output_over_input;

use super::{calibrate, write_outputs, CalibrateConfig, CalibrateError, Calibrated, NamedSession};

/// What a calibration from files is asked for.
#[derive(Clone, Debug)]
pub struct CalibrateRequest {
    /// Nominal geometry (TOML).
    pub geometry: PathBuf,
    /// Training session (CSV).
    pub train: PathBuf,
    /// Test session (CSV).
    pub test: PathBuf,
    /// Output directory: calibration.json, report.json, figures/.
    pub out: PathBuf,
    /// Also write the JSON report here (`-`: the caller writes it to stdout).
    pub json: Option<PathBuf>,
    /// Write the learners' data to this directory as `x,y,z,tx,ty,tz` CSVs
    /// ([`super::PairSet::write`]).
    pub export_pairs: Option<PathBuf>,
    /// Draw the figures.
    pub figures: bool,
    pub config: CalibrateConfig,
}

/// Runs a calibration from files and writes its outputs; returns what it
/// computed, the report's file paths filled in.
pub fn run_calibrate(request: &CalibrateRequest) -> Result<Calibrated, CalibrateError> {
    refuse_outputs_over_inputs(request)?;
    let geometry = Geometry::load(&request.geometry)?;
    let config = &request.config;
    // The legacy controller's columns are read (and checked) only by what
    // uses them: the black-box comparison and the exported pairs.
    let read = ReadOptions {
        legacy: config.blackbox || request.export_pairs.is_some(),
    };
    let train = Session::load_with(&request.train, read)?;
    let test = Session::load_with(&request.test, read)?;
    let mut calibrated = calibrate(
        &geometry,
        &request.geometry,
        NamedSession {
            path: &request.train,
            session: &train,
        },
        NamedSession {
            path: &request.test,
            session: &test,
        },
        config,
    )?;
    let has_legacy = |s: &Session| s.has_legacy() || !s.unread_columns.is_empty();
    if !config.blackbox && has_legacy(&train) && has_legacy(&test) {
        calibrated.report.notes.push(
            "the sessions have dev_* columns: --blackbox adds the paper's black-box NN and SVR \
             for comparison"
                .into(),
        );
    }
    if let Some(dir) = &request.export_pairs {
        calibrated.pairs.residual.write(dir, "residual")?;
        if let Some(bb) = &calibrated.pairs.blackbox {
            bb.write(dir, "blackbox")?;
        }
    }
    write_outputs(
        &mut calibrated,
        &request.out,
        request.json.as_deref(),
        request.figures,
        config.quiet,
    )?;
    Ok(calibrated)
}

/// Refuses, before any work, a run whose outputs (the calibration and the
/// report in `--out`, `--json`) would overwrite one of its inputs.
fn refuse_outputs_over_inputs(request: &CalibrateRequest) -> Result<(), CalibrateError> {
    let calibration = request.out.join("calibration.json");
    let report = request.out.join("report.json");
    let mut outputs: Vec<(&'static str, &Path)> = vec![
        ("--out (calibration.json)", &calibration),
        ("--out (report.json)", &report),
    ];
    if let Some(json) = request.json.as_deref().filter(|j| *j != Path::new("-")) {
        outputs.push(("--json", json));
    }
    let inputs = [
        ("--geometry", request.geometry.as_path()),
        ("--train", request.train.as_path()),
        ("--test", request.test.as_path()),
    ];
    Ok(refuse_output_over_input(&outputs, &inputs)?)
}
