//! `spidar compile`: a calibration (`calibration.json`, serde JSON of
//! [`Calibration`]) into the device's model blob, checked bit for bit with the
//! device's own parser, and the fixed-point error measured against the f64
//! model on a test session.
//!
//! The device way ([`device_positions`]) is exactly what
//! `spidar_core::control::Controller::step` computes from the same string-law
//! inputs: the fixed-point string law of the blob, forward kinematics in f32
//! (warm-started, the last good position kept), the f32 room transform,
//! Q15.16 rounding and the fixed-point correction. The reference
//! ([`crate::model::predict`]) is the same pipeline in f64 with the f64 correction.
//! The inputs are the session's own (counts, direction, recorded commanded
//! tensions, time), so the difference is the arithmetic alone. The rows a
//! session records under the calibration's home capture (`home`,
//! [`LaterHome::under`]) are evaluated as the device evaluates them there:
//! with the training's slips on both sides, so that the budget covers the
//! blob's home section too.

use std::path::{Path, PathBuf};

use spidar_core::blob::{compile, position_q16, CompiledCalibration};
use spidar_core::control::ControlConfig;
use spidar_core::geometry::{distance, room_from_device};
use spidar_core::kinematics::{forward_kinematics_inclined, FkStatus};
use spidar_core::model::{Calibration, StringInputs};
use spidar_protocol::blob::{BlobError, CRC32};

use crate::data::dataset::{DatasetError, Geometry, LayoutMismatch, Session};
use crate::data::home::LaterHome;
use crate::data::observe::{observations, rows_under_the_training_home, Observation};
use crate::data::output::{refuse_output_over_input, write_atomically};
use crate::data::stats::ErrorStats;
use crate::model::predict::{corrected, predict, KinematicModel};

/// Mean fixed-point error allowed by the budget, mm.
pub const FIXED_POINT_BUDGET_MM: f64 = 0.02;

/// Why `spidar compile` failed; each names the file or field.
#[derive(Debug, thiserror::Error)]
pub enum CompileCmdError {
    #[error("{}: {action}: {source}", file.display())]
    Io {
        file: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
    #[error("{}:{line}:{column}: not a calibration: {message}", file.display())]
    Json {
        file: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
    #[error("{}: does not compile: {error}", file.display())]
    Compile {
        file: PathBuf,
        #[source]
        error: spidar_core::blob::BlobCompileError,
    },
    #[error(
        "{}: does not compile: {error}; calibrate again: `spidar calibrate` sizes its correction to \
         what the model leaves of the device's tick",
        file.display()
    )]
    TickBudget {
        file: PathBuf,
        #[source]
        error: spidar_core::blob::BlobCompileError,
    },
    #[error("compiled blob does not parse back: {0}")]
    ParseBack(#[source] BlobError),
    #[error("compiled blob is not reproducible: two compilations differ at byte {at}")]
    NotReproducible { at: usize },
    #[error("{0}")]
    Dataset(#[from] DatasetError),
    #[error("{}: `{field}` is {found} but the calibration has {expected}", file.display())]
    GeometryMismatch {
        file: PathBuf,
        field: &'static str,
        found: String,
        expected: String,
    },
    #[error("{}: no row of the session has a usable position to compare", file.display())]
    NoRows { file: PathBuf },
    #[error(
        "{}: {problem}, but the calibration {} is of a device of {strings} strings{}: the session \
         is another device's (compile with the calibration of the device that recorded it)",
        file.display(),
        calibration.display(),
        if *planar { ", planar" } else { "" }
    )]
    SessionMismatch {
        file: PathBuf,
        problem: String,
        calibration: PathBuf,
        strings: usize,
        planar: bool,
    },
    #[error("{why} ({})", if *written {
        format!("blob written to {} as asked", out.display())
    } else {
        format!("no blob written to {}; --write-over-budget writes it anyway", out.display())
    })]
    OverBudget {
        why: String,
        out: PathBuf,
        written: bool,
    },
    #[error("--budget-mm is {value}: the budget must be a positive number of mm")]
    Budget { value: f64 },
    #[error("{0}")]
    OutputOverInput(#[from] crate::data::output::OutputOverInput),
}

/// The fixed-point error of a blob against its f64 calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct FixedPointError {
    /// Rows compared (forward kinematics converged in both).
    pub rows: usize,
    /// Rows of the session.
    pub session_rows: usize,
    /// Rows where one side's forward kinematics failed and the other's did not.
    pub status_mismatches: usize,
    /// Device-frame position (string law + FK), blob vs f64.
    pub string_model: ErrorStats,
    /// Corrected room position (everything), blob vs f64.
    pub corrected: ErrorStats,
    /// Of `rows`, those under the calibration's home capture, compared with
    /// its training slips applied on both sides.
    pub home_rows: usize,
}

/// Positions the device computes from a session's inputs with `blob`:
/// (device-frame FK position, corrected room position Q15.16 -> mm, FK status).
/// The first `home_rows` observations are under the blob's home capture
/// (its training slips applied, [`BlobHead::string_lengths`]), the others
/// after a new one.
///
/// [`BlobHead::string_lengths`]: spidar_core::blob::BlobHead::string_lengths
pub fn device_positions(
    blob: &CompiledCalibration<'_>,
    observations: &[Observation],
    home_rows: usize,
) -> Vec<([f64; 3], [f64; 3], FkStatus)> {
    // The device's kinematics: the blob's string weights and thresholds
    // (`Control` runs `head.fk_config` once the lengths are calibrated).
    let fk_config = blob.head.fk_config(&ControlConfig::default().fk);
    let frame = &blob.head.frame;
    let inclined = blob.head.effects.iter().any(|e| e.reads_inclination());
    let training_home = blob.head.home.as_ref().map(|h| h.home_id);
    let mut position = frame.home;
    observations
        .iter()
        .enumerate()
        .map(|(k, o)| {
            let home_id = training_home.filter(|_| k < home_rows);
            let lengths = |inputs: &StringInputs| {
                blob.head
                    .string_lengths(inputs, home_id)
                    .map(|l| l as f32 / 65536.0)
            };
            let fk = forward_kinematics_inclined(
                frame, &o.inputs, position, &fk_config, inclined, lengths,
            );
            if matches!(fk.status, FkStatus::Ok | FkStatus::FaultyStringExcluded) {
                position = fk.position;
            }
            let room = position_q16(room_from_device(frame, position));
            let c = blob.correction.evaluate(room);
            (
                position.map(f64::from),
                c.map(|v| f64::from(v) / 65536.0),
                fk.status,
            )
        })
        .collect()
}

/// Compares the blob (the device way) with the f64 calibration on every row.
/// The rows before the first marked as after a new home capture
/// ([`LaterHome::mark`] from the calibration's home capture) are under
/// that capture when the calibration has one, and both sides apply the
/// training's slips there ([`Calibration::under_home`]). `None` if no row
/// converged on both sides.
pub fn fixed_point_error(
    calibration: &Calibration,
    blob: &CompiledCalibration<'_>,
    observations: &[Observation],
) -> Option<FixedPointError> {
    let training_home = calibration.home.as_ref().map(|h| h.home_id);
    let home_rows = if training_home.is_some() {
        rows_under_the_training_home(observations)
    } else {
        0
    };
    let (under, after) = observations.split_at(home_rows);
    let under_model = calibration.under_home(training_home);
    let mut reference = predict(KinematicModel::of(&under_model), under);
    reference.extend(predict(KinematicModel::of(calibration), after));
    let reference_corrected = corrected(&calibration.correction, &reference);
    let device = device_positions(blob, observations, home_rows);
    let ok = |s: FkStatus| matches!(s, FkStatus::Ok | FkStatus::FaultyStringExcluded);
    let mut model = Vec::new();
    let mut all = Vec::new();
    let mut mismatches = 0;
    let mut compared_under_home = 0;
    for (k, ((r, rc), (d, dc, ds))) in reference
        .iter()
        .zip(&reference_corrected)
        .zip(&device)
        .enumerate()
    {
        match (ok(r.status), ok(*ds)) {
            (true, true) => {
                model.push(distance(r.device, *d));
                all.push(distance(*rc, *dc));
                compared_under_home += usize::from(k < home_rows);
            }
            (false, false) => {}
            _ => mismatches += 1,
        }
    }
    (!all.is_empty()).then(|| FixedPointError {
        rows: all.len(),
        session_rows: observations.len(),
        status_mismatches: mismatches,
        string_model: ErrorStats::of(&model),
        corrected: ErrorStats::of(&all),
        home_rows: compared_under_home,
    })
}

/// Reads `calibration.json`.
pub fn load_calibration(path: &Path) -> Result<Calibration, CompileCmdError> {
    let text = std::fs::read_to_string(path).map_err(|source| CompileCmdError::Io {
        file: path.to_path_buf(),
        action: "cannot read the calibration",
        source,
    })?;
    serde_json::from_str(&text).map_err(|e| CompileCmdError::Json {
        file: path.to_path_buf(),
        line: e.line(),
        column: e.column(),
        message: e.to_string(),
    })
}

/// A model id from the calibration's content (CRC-32 of its JSON).
pub fn model_id_of(calibration: &Calibration) -> u32 {
    let json = serde_json::to_vec(calibration).unwrap_or_default();
    CRC32.checksum(&json)
}

/// What the device's tick leaves a position correction beside a model
/// (`spidar_core::tick_cost`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct TickRoom {
    /// The model's tick without a correction, with the most training slips
    /// a blob takes (the calibration's are found after the corrections),
    /// estimated instructions.
    pub model_instructions: u32,
    /// The device's budget (instructions a tick).
    pub budget: u32,
    /// The most support vectors an SVR may have beside it.
    pub support_vectors: u32,
    /// The most hidden neurons an NN may have beside it.
    pub neurons: u16,
}

impl TickRoom {
    /// The room beside `calibration`'s frame, laws and effect terms (its
    /// correction and slips are not read); `None` when they do not compile
    /// for another reason than the budget.
    pub fn beside(calibration: &Calibration) -> Option<TickRoom> {
        use spidar_core::tick_cost;
        let mut model = calibration.clone();
        model.correction = spidar_core::correction::CorrectionModel::None;
        model.home = None;
        let terms = tick_instructions(&model)?;
        let slips = tick_cost::PER_SLIP * spidar_core::model::MAX_HOME_SLIPS as u32;
        let model_instructions = terms.saturating_add(slips);
        Some(TickRoom {
            model_instructions,
            budget: tick_cost::TICK_BUDGET,
            support_vectors: tick_cost::support_vectors_left(model_instructions),
            neurons: tick_cost::neurons_left(model_instructions),
        })
    }
}

/// The instructions the device's tick is estimated to take with
/// `calibration` (`spidar_core::tick_cost`): also when over the budget;
/// `None` when it does not compile for another reason.
pub fn tick_instructions(calibration: &Calibration) -> Option<u32> {
    match compile(calibration, 0, 0) {
        Ok(blob) => Some(
            CompiledCalibration::from_blob(&blob)
                .ok()?
                .tick_instructions(),
        ),
        Err(spidar_core::blob::BlobCompileError::TickOverBudget { instructions, .. }) => {
            Some(instructions)
        }
        Err(_) => None,
    }
}

/// Why the device cannot hold `calibration` (a parameter beyond its fixed
/// point's range, say), or `None` when it compiles; a tick over the budget
/// is not such a reason here (the corrections are sized to what the model
/// leaves, and the report warns of a model over it).
pub fn device_cannot_hold(calibration: &Calibration) -> Option<String> {
    match compile(calibration, 0, 0) {
        Ok(_) | Err(spidar_core::blob::BlobCompileError::TickOverBudget { .. }) => None,
        Err(e) => Some(e.to_string()),
    }
}

/// Compiles `calibration` and checks the blob with the device's parser and
/// a second compilation (bit for bit).
pub fn compile_checked(
    calibration: &Calibration,
    model_id: u32,
    created_unix_s: u32,
    file: &Path,
) -> Result<Vec<u8>, CompileCmdError> {
    use spidar_core::blob::BlobCompileError;
    let err = |error| match error {
        BlobCompileError::Correction(
            spidar_core::correction::CorrectionCompileError::OverBudget { .. },
        )
        | BlobCompileError::TickOverBudget { .. } => CompileCmdError::TickBudget {
            file: file.to_path_buf(),
            error,
        },
        _ => CompileCmdError::Compile {
            file: file.to_path_buf(),
            error,
        },
    };
    let blob = compile(calibration, model_id, created_unix_s).map_err(err)?;
    let again = compile(calibration, model_id, created_unix_s).map_err(err)?;
    if let Some(at) = blob
        .iter()
        .zip(&again)
        .position(|(a, b)| a != b)
        .or((blob.len() != again.len()).then(|| blob.len().min(again.len())))
    {
        return Err(CompileCmdError::NotReproducible { at });
    }
    CompiledCalibration::from_blob(&blob).map_err(CompileCmdError::ParseBack)?;
    Ok(blob)
}

/// What `spidar compile` is asked for.
#[derive(Clone, Debug)]
pub struct CompileRequest {
    /// Calibration written by `spidar calibrate` (calibration.json).
    pub calibration: PathBuf,
    /// Where to write the model blob.
    pub out: PathBuf,
    /// Test session CSV: measure the fixed-point error on its rows.
    pub test: Option<PathBuf>,
    /// Nominal geometry of the session (checks its counts per revolution
    /// against the calibration's).
    pub geometry: Option<PathBuf>,
    /// Model id (default: CRC-32 of the calibration).
    pub model_id: Option<u32>,
    /// Largest mean fixed-point error accepted, mm
    /// ([`FIXED_POINT_BUDGET_MM`] by default on the command line).
    pub budget_mm: f64,
    /// Write the blob even when it is over the budget or too large for the
    /// firmware (the command still fails, saying so).
    pub write_over_budget: bool,
}

/// What `spidar compile` did.
#[derive(Clone, Debug)]
pub struct CompileReport {
    pub out: PathBuf,
    pub bytes: usize,
    pub model_id: u32,
    pub header: spidar_protocol::blob::ModelHeader,
    pub error: Option<FixedPointError>,
    pub budget_mm: f64,
    /// [`describe_home_slips`] of the blob.
    pub home_slips: Option<String>,
    /// Which rows of the test session are under the blob's home capture,
    /// and why ([`LaterHome::under`]); `None` without a test session or
    /// without home slips.
    pub test_home: Option<LaterHome>,
    /// The device's tick with the blob, estimated instructions
    /// (`spidar_core::tick_cost`, within its budget or it would not compile).
    pub tick_instructions: u32,
}

impl std::fmt::Display for CompileReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let h = &self.header;
        writeln!(
            f,
            "wrote {} ({} bytes: {}, {} effects, hidden {}, support vectors {}; model id {:#010x})",
            self.out.display(),
            self.bytes,
            h.kind.describe(),
            h.effects,
            h.hidden,
            h.support_vectors,
            self.model_id
        )?;
        writeln!(
            f,
            "blob parses back with the device's parser and compiles bit-identically; firmware capacity {} KiB = {} bytes ({})",
            spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY / 1024,
            spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY,
            if self.bytes <= spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY {
                "fits"
            } else {
                "TOO LARGE for the firmware"
            }
        )?;
        writeln!(
            f,
            "device control loop: an estimated {} of the {} instructions it has a tick",
            self.tick_instructions,
            spidar_core::tick_cost::TICK_BUDGET
        )?;
        if let Some(h) = &self.home_slips {
            writeln!(f, "{h}")?;
        }
        if let Some(h) = &self.test_home {
            writeln!(f, "test session's home capture: {}", h.reason)?;
        }
        if let Some(e) = &self.error {
            writeln!(
                f,
                "fixed-point error vs f64 over {}{}: string model mean {:.5} mm max {:.5} mm; corrected mean {:.5} mm max {:.5} mm (budget {} mm mean){}",
                compared_rows(e),
                if self.test_home.is_some() {
                    format!(" ({} with the training's slips, under their home capture)", e.home_rows)
                } else {
                    String::new()
                },
                e.string_model.mean_mm,
                e.string_model.max_mm,
                e.corrected.mean_mm,
                e.corrected.max_mm,
                self.budget_mm,
                if e.status_mismatches > 0 {
                    format!("; {} rows converged on one side only", e.status_mismatches)
                } else {
                    String::new()
                }
            )?;
        }
        Ok(())
    }
}

/// What a blob says of the training session's slips it carries
/// (`spidar compile`, `spidar flash`): under which home capture the device
/// applies them; `None` for a blob without.
pub fn describe_home_slips(blob: &CompiledCalibration<'_>) -> Option<String> {
    let home = blob.head.home.as_ref()?;
    let strings: Vec<String> = home.slips.iter().map(|s| s.string.to_string()).collect();
    Some(format!(
        "the model applies the training session's {} slip{} (string{} {}) while the device stays \
         under home capture {} ({:#018x}); from its next `Home` or a reboot it runs without them",
        home.slips.len(),
        if home.slips.len() == 1 { "" } else { "s" },
        if home.slips.len() == 1 { "" } else { "s" },
        strings.join(", "),
        home.home_id,
        home.home_id
    ))
}

/// The blob's creation time (Unix seconds): `SOURCE_DATE_EPOCH` when set to
/// a whole number (the reproducible-builds convention, so that compiling the
/// same calibration twice gives the same bytes), else the clock.
pub fn created_now() -> u32 {
    let from_env = std::env::var("SOURCE_DATE_EPOCH")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok());
    let seconds = from_env.unwrap_or_else(|| {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs())
    });
    u32::try_from(seconds).unwrap_or(u32::MAX)
}

/// Runs `spidar compile`: refuses an output over an input and a budget that
/// is not a positive number before any work; writes the blob (atomically)
/// only when it fits the firmware and the fixed-point budget, unless
/// `write_over_budget`.
pub fn run_compile(args: &CompileRequest) -> Result<CompileReport, CompileCmdError> {
    if !(args.budget_mm.is_finite() && args.budget_mm > 0.0) {
        return Err(CompileCmdError::Budget {
            value: args.budget_mm,
        });
    }
    let mut inputs = vec![("--calibration", args.calibration.as_path())];
    inputs.extend(args.test.as_deref().map(|p| ("--test", p)));
    inputs.extend(args.geometry.as_deref().map(|p| ("--geometry", p)));
    refuse_output_over_input(&[("--out", &args.out)], &inputs)?;
    let calibration = load_calibration(&args.calibration)?;
    let model_id = args.model_id.unwrap_or_else(|| model_id_of(&calibration));
    let blob = compile_checked(&calibration, model_id, created_now(), &args.calibration)?;
    let parsed = CompiledCalibration::from_blob(&blob).map_err(CompileCmdError::ParseBack)?;
    if let Some(g) = &args.geometry {
        check_geometry(&calibration, g)?;
    }
    let mut test_home = None;
    let error = match &args.test {
        Some(test) => {
            let session = Session::load(test)?;
            check_session(&calibration, &args.calibration, test, &session)?;
            let mut obs = observations(&session.samples);
            let home = calibration
                .home
                .as_ref()
                .map(|h| LaterHome::under(h.home_id, &session));
            if let Some(h) = &home {
                h.mark(&mut obs);
            }
            test_home = home;
            Some(
                fixed_point_error(&calibration, &parsed, &obs)
                    .ok_or_else(|| CompileCmdError::NoRows { file: test.clone() })?,
            )
        }
        None => None,
    };
    let report = CompileReport {
        out: args.out.clone(),
        bytes: blob.len(),
        model_id,
        header: parsed.header,
        error,
        budget_mm: args.budget_mm,
        home_slips: describe_home_slips(&parsed),
        test_home,
        tick_instructions: parsed.tick_instructions(),
    };
    let refusal = over_budget(&report);
    if refusal.is_none() || args.write_over_budget {
        write_blob(&args.out, &blob)?;
    }
    match refusal {
        Some(why) => Err(CompileCmdError::OverBudget {
            why,
            out: args.out.clone(),
            written: args.write_over_budget,
        }),
        None => Ok(report),
    }
}

/// The geometry's strings and counts per revolution against the
/// calibration's (a 3-string calibration compiled beside a 4-anchor
/// geometry was written without a word).
fn check_geometry(calibration: &Calibration, g: &Path) -> Result<(), CompileCmdError> {
    let geometry = Geometry::load(g)?;
    let layout = calibration.frame.layout;
    if geometry.strings() != layout.count() {
        return Err(CompileCmdError::GeometryMismatch {
            file: g.to_path_buf(),
            field: "anchors_mm",
            found: format!("{} anchors", geometry.strings()),
            expected: format!("{} strings", layout.count()),
        });
    }
    if geometry.layout.planar != layout.planar {
        let kind = |planar: bool| if planar { "planar" } else { "3-D" };
        return Err(CompileCmdError::GeometryMismatch {
            file: g.to_path_buf(),
            field: "planar",
            found: kind(geometry.layout.planar).into(),
            expected: kind(layout.planar).into(),
        });
    }
    for i in geometry.layout.indices() {
        let law = &calibration.strings[i];
        if law.counts_per_rev != geometry.counts_per_rev[i] {
            return Err(CompileCmdError::GeometryMismatch {
                file: g.to_path_buf(),
                field: "counts_per_rev",
                found: geometry.counts_per_rev[i].to_string(),
                expected: law.counts_per_rev.to_string(),
            });
        }
    }
    Ok(())
}

/// The test session's encoder columns and tracker z against the
/// calibration's device (a 4-encoder session was measured on a 3-string
/// calibration over the 500 rows the wrong strings gave; a planar session
/// on a 3-D calibration kept 108 of its rows, and neither said why).
fn check_session(
    calibration: &Calibration,
    calibration_file: &Path,
    file: &Path,
    session: &Session,
) -> Result<(), CompileCmdError> {
    let layout = calibration.frame.layout;
    let problem = match session.layout_mismatch(layout) {
        None => return Ok(()),
        Some(LayoutMismatch::Strings(strings)) => format!(
            "{strings} encoder columns (enc0..enc{})",
            strings.saturating_sub(1)
        ),
        Some(LayoutMismatch::NoTrackerZ) => "no tracker z (`ots_z`)".to_string(),
    };
    Err(CompileCmdError::SessionMismatch {
        file: file.to_path_buf(),
        problem,
        calibration: calibration_file.to_path_buf(),
        strings: layout.count(),
        planar: layout.planar,
    })
}

/// "N rows" compared, and of how many when the kinematics placed the
/// end-effector on fewer than the session's (most of them missing: a
/// planar session on a 3-D calibration kept 108 of 500 rows, unexplained).
fn compared_rows(e: &FixedPointError) -> String {
    if e.session_rows <= e.rows {
        return format!("{} rows", e.rows);
    }
    let hint = if 2 * e.rows < e.session_rows {
        "; is the session this device's?"
    } else {
        ""
    };
    format!(
        "{} of the session's {} rows (the kinematics placed the end-effector on no other, in \
         f64 as on the device{hint})",
        e.rows, e.session_rows
    )
}

/// Whether a mean fixed-point error of `mean_mm` is over `budget_mm` (one
/// not measured, NaN, is): the rule `spidar compile` refuses a blob by and
/// `calibrate` warns by.
pub fn over_the_budget(mean_mm: f64, budget_mm: f64) -> bool {
    mean_mm.is_nan() || mean_mm > budget_mm
}

/// Why a compiled blob must not be written: too large for the firmware, or
/// its fixed-point error over the budget.
fn over_budget(report: &CompileReport) -> Option<String> {
    let capacity = spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY;
    if report.bytes > capacity {
        return Some(format!(
            "the blob of {} bytes is too large for the firmware's {capacity} bytes",
            report.bytes
        ));
    }
    let e = report.error.as_ref()?;
    if over_the_budget(e.corrected.mean_mm, report.budget_mm) {
        return Some(format!(
            "fixed-point error {:.5} mm mean exceeds the budget of {} mm",
            e.corrected.mean_mm, report.budget_mm
        ));
    }
    None
}

/// Writes the blob atomically, creating its folder.
fn write_blob(out: &Path, blob: &[u8]) -> Result<(), CompileCmdError> {
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| CompileCmdError::Io {
            file: parent.to_path_buf(),
            action: "cannot create the output directory",
            source,
        })?;
    }
    write_atomically(out, blob).map_err(|source| CompileCmdError::Io {
        file: out.to_path_buf(),
        action: "cannot write the model blob (the previous file, if any, is kept)",
        source,
    })
}
