//! What a calibration writes: `calibration.json`, `report.json` (and the
//! report wherever `--json` asks), the report as a page (`report.html` and
//! its figures' data), the figures, and the learners' pairs as CSV.

use crate::data::output::write_atomically;
use crate::procedures::report_page;
use std::path::{Path, PathBuf};
use std::time::Instant;

use super::{plots, report, spinner, CalibrateError, Calibrated};

/// (input, tracker) pairs in mm: the training pairs after Tukey's outlier
/// removal (what the learners train on), the test pairs all tracked rows.
#[derive(Clone, Debug, Default)]
pub struct PairSet {
    pub train_inputs: Vec<[f64; 3]>,
    pub train_targets: Vec<[f64; 3]>,
    pub test_inputs: Vec<[f64; 3]>,
    pub test_targets: Vec<[f64; 3]>,
}

impl PairSet {
    /// Write `DIR/{stem}_train.csv` and `DIR/{stem}_test.csv` in the layout
    /// `scripts/reference/reference.py` reads (`x,y,z,tx,ty,tz`).
    pub fn write(&self, dir: &Path, stem: &str) -> Result<[PathBuf; 2], CalibrateError> {
        std::fs::create_dir_all(dir).map_err(|source| CalibrateError::Io {
            file: dir.to_path_buf(),
            action: "cannot create the directory",
            source,
        })?;
        let write = |name: String, x: &[[f64; 3]], t: &[[f64; 3]]| {
            let path = dir.join(name);
            let mut text = String::from("x,y,z,tx,ty,tz\n");
            for (a, b) in x.iter().zip(t) {
                text.push_str(&format!(
                    "{},{},{},{},{},{}\n",
                    a[0], a[1], a[2], b[0], b[1], b[2]
                ));
            }
            write_atomically(&path, text.as_bytes()).map_err(|source| CalibrateError::Io {
                file: path.clone(),
                action: "cannot write",
                source,
            })?;
            Ok::<PathBuf, CalibrateError>(path)
        };
        Ok([
            write(
                format!("{stem}_train.csv"),
                &self.train_inputs,
                &self.train_targets,
            )?,
            write(
                format!("{stem}_test.csv"),
                &self.test_inputs,
                &self.test_targets,
            )?,
        ])
    }
}

/// Where [`write_outputs`] put things.
#[derive(Clone, Debug)]
pub struct Written {
    pub calibration: PathBuf,
    pub report: Vec<PathBuf>,
    /// The report as a page for people (`report.html`).
    pub page: PathBuf,
    pub figures: Vec<PathBuf>,
}

/// Write the figures (unless `figures` is false), `DIR/calibration.json`,
/// `DIR/report.json` and, when given, the JSON report at `json` too (`-` is
/// stdout, written by the caller), then the page `DIR/report.html`. Fills
/// the report's file paths.
pub fn write_outputs(
    calibrated: &mut Calibrated,
    out: &Path,
    json: Option<&Path>,
    figures: bool,
    quiet: bool,
) -> Result<Written, CalibrateError> {
    std::fs::create_dir_all(out).map_err(|source| CalibrateError::Io {
        file: out.to_path_buf(),
        action: "cannot create the output directory",
        source,
    })?;
    let t = Instant::now();
    if figures {
        let pb = spinner("figures", quiet);
        let drawn = plots::draw_all(calibrated, &out.join("figures"));
        pb.finish_and_clear();
        calibrated.report.figures = drawn?;
    }
    calibrated.report.timings_s.figures_s = Some(t.elapsed().as_secs_f64());
    // The device's view (compiled, its fixed point on the test rows) for
    // the page, and what stops the device from running the calibration
    // as reported for the warnings.
    let figure_data = report_page::FigureData::of(calibrated);
    calibrated
        .report
        .warnings
        .extend(figure_data.device.warnings());
    let calibration_path = out.join("calibration.json");
    write_json(&calibration_path, &calibrated.calibration)?;
    let report_path = out.join("report.json");
    let mut reports = vec![report_path.clone()];
    if let Some(j) = json {
        if j != Path::new("-") && j != report_path {
            reports.push(j.to_path_buf());
        }
    }
    calibrated.report.files = report::Files {
        calibration: calibration_path.display().to_string(),
        reports: reports.iter().map(|p| p.display().to_string()).collect(),
        out_dir: out.display().to_string(),
        page: out.join(report_page::PAGE_FILE).display().to_string(),
    };
    for r in &reports {
        if let Some(parent) = r.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|source| CalibrateError::Io {
                file: parent.to_path_buf(),
                action: "cannot create the directory",
                source,
            })?;
        }
        write_json(r, &calibrated.report)?;
    }
    let page = write_page(calibrated, &figure_data, out)?;
    Ok(Written {
        calibration: calibration_path,
        report: reports,
        page,
        figures: calibrated
            .report
            .figures
            .iter()
            .map(|f| PathBuf::from(&f.path))
            .collect(),
    })
}

/// `DIR/report.html` and the data of its figures, from the report as
/// `report.json` holds it: its JSON text read back, as `spidar report DIR`
/// reads it, so that both draw the same page.
fn write_page(
    calibrated: &Calibrated,
    figures: &report_page::FigureData,
    out: &Path,
) -> Result<PathBuf, CalibrateError> {
    let file = out.join(report_page::REPORT_FILE);
    let report = serde_json::to_string(&calibrated.report)
        .and_then(|text| serde_json::from_str(&text))
        .map_err(|source| CalibrateError::Json { file, source })?;
    Ok(report_page::write_page(out, &report, figures)?)
}

fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), CalibrateError> {
    let mut text = serde_json::to_string_pretty(value).map_err(|source| CalibrateError::Json {
        file: path.to_path_buf(),
        source,
    })?;
    text.push('\n');
    write_atomically(path, text.as_bytes()).map_err(|source| CalibrateError::Io {
        file: path.to_path_buf(),
        action: "cannot write",
        source,
    })
}
