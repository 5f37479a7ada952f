//! What the page's figures are drawn from beyond `report.json`: the
//! per-row data a calibration holds only while it runs, reduced to what the
//! figures show, written beside the report as `report-figures.json`
//! (compact JSON, `docs/json-schema.md`) so that `spidar report DIR`
//! draws the same page again.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::model::compile::{
    compile_checked, fixed_point_error, model_id_of, over_the_budget, FIXED_POINT_BUDGET_MM,
};
use crate::procedures::calibrate::{Calibrated, PointErrors};

use super::evidence::{effect_evidence, EffectEvidence};

/// The figure data's layout version; as `report.json`'s, its number changes
/// when a key is removed or changes meaning.
pub const FIGURE_DATA_SCHEMA: &str = "spidar-report-figures/1";
/// The file's name, beside `report.json`.
pub const FIGURE_DATA_FILE: &str = "report-figures.json";

/// Points of the error map at most (evenly through the session).
const MAP_POINTS: usize = 1500;
/// Runs of rows the error along the session is summarised in, at most.
const ALONG_RUNS: usize = 300;

/// Everything the page draws that `report.json` does not hold.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FigureData {
    pub schema: String,
    /// Each stage's errors at 0, 1, ..., 100 % of the rows (nearest rank),
    /// per session, mm.
    pub quantiles: Vec<StageQuantiles>,
    /// The final model's error on the test session, where it was.
    pub map: Option<ErrorMap>,
    /// The error along the training session, identified and final model.
    pub along: Vec<AlongSession>,
    /// The residual against its variable of each finding with a figure.
    pub effects: Vec<EffectEvidence>,
    /// The blob the calibration compiles to.
    pub device: DeviceData,
}

/// One stage's error quantiles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StageQuantiles {
    pub name: String,
    pub train: Vec<f64>,
    pub test: Vec<f64>,
}

/// Tracker positions (room frame, mm) and the error there.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ErrorMap {
    pub stage: String,
    /// Tracked rows of the session (the points are at most 1500
    /// of them, evenly).
    pub rows: usize,
    /// `[x, y, z, error]` per point, mm.
    pub points: Vec<[f64; 4]>,
}

/// One stage's error along the training session, in runs of consecutive
/// tracked rows: each run's first file line, median and largest error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlongSession {
    pub stage: String,
    pub line: Vec<u64>,
    pub median_mm: Vec<f64>,
    pub max_mm: Vec<f64>,
}

/// The model blob `spidar compile` makes of `calibration.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeviceData {
    /// Why the compiler refused the calibration (`null` when it compiled).
    pub refused: Option<String>,
    pub bytes: Option<usize>,
    /// What the firmware's model slot holds, bytes.
    pub capacity: usize,
    pub model_id: u32,
    pub correction: Option<String>,
    pub effects: Option<u8>,
    pub hidden: Option<u16>,
    pub support_vectors: Option<u32>,
    /// The blob's positions against the f64 model's on the test rows.
    pub fixed_point: Option<FixedPoint>,
}

/// The fixed-point error ([`crate::model::compile::FixedPointError`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FixedPoint {
    pub rows: usize,
    pub status_mismatches: usize,
    pub string_model_mean_mm: f64,
    pub string_model_max_mm: f64,
    pub corrected_mean_mm: f64,
    pub corrected_max_mm: f64,
    pub budget_mm: f64,
}

impl FigureData {
    /// The figure data of a calibration.
    pub fn of(c: &Calibrated) -> FigureData {
        let final_stage = c.report.selection.stage.as_str();
        let quantiles = c
            .report
            .stages
            .iter()
            .filter_map(|s| c.points_of(&s.name))
            .map(|p| StageQuantiles {
                name: p.name.clone(),
                train: quantiles(&p.train.errors),
                test: quantiles(&p.test.errors),
            })
            .collect();
        let map = c.points_of(final_stage).map(|p| ErrorMap {
            stage: final_stage.to_string(),
            rows: p.test.errors.len(),
            points: thin_evenly(p.test.errors.len(), MAP_POINTS)
                .into_iter()
                .map(|k| {
                    let t = p.test.tracker[k];
                    [t[0], t[1], t[2], p.test.errors[k]].map(round_sig)
                })
                .collect(),
        });
        let along = ["identified", final_stage]
            .into_iter()
            .filter_map(|name| c.points_of(name))
            .map(|p| along(&p.name, &p.train))
            .collect();
        FigureData {
            schema: FIGURE_DATA_SCHEMA.to_string(),
            quantiles,
            map,
            along,
            effects: effect_evidence(
                &c.loop_result.identification,
                &c.loop_result.findings,
                &c.train_rows,
            ),
            device: DeviceData::of(c),
        }
    }

    /// Reads `path`; `Ok(None)` when there is no such file.
    pub fn load(path: &Path) -> Result<Option<FigureData>, super::PageError> {
        let text = match std::fs::read_to_string(path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => {
                return Err(super::PageError::Read {
                    file: path.to_path_buf(),
                    source,
                })
            }
        };
        let data: FigureData =
            serde_json::from_str(&text).map_err(|e| super::PageError::Malformed {
                file: path.to_path_buf(),
                line: e.line(),
                column: e.column(),
                message: e.to_string(),
            })?;
        if data.schema != FIGURE_DATA_SCHEMA {
            return Err(super::PageError::Schema {
                file: path.to_path_buf(),
                found: data.schema,
                expected: FIGURE_DATA_SCHEMA,
            });
        }
        Ok(Some(data))
    }
}

impl DeviceData {
    /// What stops the device from running the calibration as reported,
    /// for the report's warnings: the compiler refused it, its blob is
    /// larger than the firmware's model slot, or its fixed point is further
    /// from the f64 model on the test rows than the budget `spidar compile`
    /// holds it to. Empty when the device runs it as reported.
    pub fn warnings(&self) -> Vec<String> {
        let mut out = Vec::new();
        if let Some(why) = &self.refused {
            out.push(format!(
                "the calibration does not compile for the device ({why}): `spidar compile` \
                 refuses it"
            ));
        }
        if let Some(bytes) = self.bytes.filter(|&b| b > self.capacity) {
            out.push(format!(
                "the device's model blob is {bytes} bytes, more than the firmware's model slot \
                 holds ({} bytes): `spidar compile` refuses it",
                self.capacity
            ));
        }
        if let Some(f) = self
            .fixed_point
            .as_ref()
            .filter(|f| over_the_budget(f.corrected_mean_mm, f.budget_mm))
        {
            out.push(format!(
                "the device's fixed point is {:.4} mm (mean; max {:.4}) from the f64 model on \
                 the {} test rows, over the {} mm budget: `spidar compile` refuses the blob \
                 unless `--write-over-budget`",
                f.corrected_mean_mm, f.corrected_max_mm, f.rows, f.budget_mm
            ));
        }
        out
    }

    /// The device's view of a calibration: compiled and checked, its
    /// fixed point against the f64 model on the test rows.
    pub fn of(c: &Calibrated) -> DeviceData {
        let capacity = spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY;
        let model_id = model_id_of(&c.calibration);
        let mut d = DeviceData {
            refused: None,
            bytes: None,
            capacity,
            model_id,
            correction: None,
            effects: None,
            hidden: None,
            support_vectors: None,
            fixed_point: None,
        };
        let blob = match compile_checked(&c.calibration, model_id, 0, Path::new("calibration.json"))
        {
            Ok(blob) => blob,
            Err(e) => {
                d.refused = Some(e.to_string());
                return d;
            }
        };
        d.bytes = Some(blob.len());
        let Ok(parsed) = spidar_core::blob::CompiledCalibration::from_blob(&blob) else {
            // compile_checked parsed it already.
            return d;
        };
        let h = parsed.header;
        d.correction = Some(format!("{:?}", h.kind).to_lowercase());
        d.effects = Some(h.effects);
        d.hidden = Some(h.hidden);
        d.support_vectors = Some(h.support_vectors);
        // The test rows of the training's home capture (marked by the
        // calibration) are judged with its slips, and the device runs them
        // so there.
        d.fixed_point =
            fixed_point_error(&c.calibration, &parsed, &c.test_rows).map(|e| FixedPoint {
                rows: e.rows,
                status_mismatches: e.status_mismatches,
                string_model_mean_mm: e.string_model.mean_mm,
                string_model_max_mm: e.string_model.max_mm,
                corrected_mean_mm: e.corrected.mean_mm,
                corrected_max_mm: e.corrected.max_mm,
                budget_mm: FIXED_POINT_BUDGET_MM,
            });
        d
    }
}

/// The errors at 0, 1, ..., 100 % (nearest rank; 0 % the smallest); empty
/// without errors.
pub(super) fn quantiles(errors: &[f64]) -> Vec<f64> {
    let mut e: Vec<f64> = errors.iter().copied().filter(|v| v.is_finite()).collect();
    if e.is_empty() {
        return Vec::new();
    }
    e.sort_by(f64::total_cmp);
    let n = e.len();
    (0..=100)
        .map(|k| {
            let rank = ((k as f64 / 100.0) * n as f64).ceil() as usize;
            round_sig(e[rank.clamp(1, n) - 1])
        })
        .collect()
}

/// One stage's errors along the training session in at most
/// [`ALONG_RUNS`] runs.
fn along(stage: &str, p: &PointErrors) -> AlongSession {
    let n = p.errors.len();
    let size = n.div_ceil(ALONG_RUNS).max(1);
    let mut a = AlongSession {
        stage: stage.to_string(),
        line: Vec::new(),
        median_mm: Vec::new(),
        max_mm: Vec::new(),
    };
    for (k, run) in p.errors.chunks(size).enumerate() {
        let mut run: Vec<f64> = run.iter().copied().filter(|v| v.is_finite()).collect();
        if run.is_empty() {
            continue;
        }
        run.sort_by(f64::total_cmp);
        // CSV line of the run's first row (the header is line 1).
        a.line
            .push(p.rows.get(k * size).map_or(0, |&r| r as u64 + 2));
        a.median_mm.push(round_sig(run[(run.len() - 1) / 2]));
        a.max_mm.push(round_sig(run[run.len() - 1]));
    }
    a
}

/// At most `most` indices of `0..n`, evenly spread, the first and the last
/// among them.
pub(super) fn thin_evenly(n: usize, most: usize) -> Vec<usize> {
    if n <= most {
        return (0..n).collect();
    }
    let most = most.max(2);
    (0..most)
        .map(|k| ((k as f64) * (n - 1) as f64 / (most - 1) as f64).round() as usize)
        .collect()
}

/// `v` to 5 significant digits (the file stays small; a figure cannot show
/// more).
pub(super) fn round_sig(v: f64) -> f64 {
    if !v.is_finite() || v == 0.0 {
        return v;
    }
    let scale = 10f64.powi(4 - v.abs().log10().floor() as i32);
    (v * scale).round() / scale
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_are_nearest_ranks() {
        let q = quantiles(&[3.0, 1.0, f64::NAN, 2.0, 4.0]);
        assert_eq!(q.len(), 101);
        assert_eq!(
            (q[0], q[25], q[26], q[50], q[100]),
            (1.0, 1.0, 2.0, 2.0, 4.0)
        );
        assert!(quantiles(&[]).is_empty());
    }

    #[test]
    fn thinning_keeps_the_ends_and_rounding_five_digits() {
        assert_eq!(thin_evenly(3, 5), [0, 1, 2]);
        assert_eq!(thin_evenly(101, 3), [0, 50, 100]);
        assert_eq!(round_sig(0.123_456_7), 0.123_46);
        assert_eq!(round_sig(-12_345.67), -12_346.0);
        assert_eq!(round_sig(0.0), 0.0);
        assert!(round_sig(f64::NAN).is_nan());
    }
}
