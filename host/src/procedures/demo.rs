//! `spidar demo`: simulate a device (the model simulator), its lattice and
//! a test session, calibrate it from them, and, as a last act, flash the
//! nominal and the calibrated model to a virtual device whose plant replays
//! the test trajectory, measuring what the device reports against the true
//! position.

use std::path::{Path, PathBuf};

use spidar_core::correction::CorrectionModel;
use spidar_core::model::Calibration;

use crate::data::dataset::{DatasetError, Geometry};
use crate::model::compile::CompileCmdError;
use crate::procedures::calibrate::{
    run_calibrate, CalibrateConfig, CalibrateError, CalibrateRequest,
};
use crate::sim::measure::{measure_on_virtual_device, VirtualDeviceRun, VirtualDeviceRunError};
use crate::sim::{
    run_simulate, simulate_session_with_truth, SessionKind, SessionPath, SimConfig, SimError,
    SimulateReport, SimulateRequest, SimulatedDevice,
};

/// Any failure of the demo; the calibration's own errors as they are.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    #[error("{0}")]
    Calibrate(#[from] CalibrateError),
    #[error("{0}")]
    Dataset(#[from] DatasetError),
    #[error("{0}")]
    Simulate(#[from] SimError),
    #[error("{0}")]
    Compile(#[from] CompileCmdError),
    #[error("model blob of {what}: {message}")]
    Blob { what: &'static str, message: String },
    #[error("{0}")]
    Device(#[from] VirtualDeviceRunError),
}

/// What the demo is asked for.
#[derive(Clone, Debug)]
pub struct DemoRequest {
    /// Output directory: geometry.toml, lattice.csv, test.csv, truth.toml and
    /// calibration/ (report, calibration, figures).
    pub out: PathBuf,
    /// Device seed (the simulated device's as-built errors).
    pub seed: u64,
    /// Simulator configuration TOML (default: the built-in device).
    pub config: Option<PathBuf>,
    /// Injected effects, `--effect` syntax ([`crate::sim::effects::parse_effect`]).
    pub effects: Vec<String>,
    /// Also run the paper's black-box procedure.
    pub blackbox: bool,
    /// Reduced NN sweep and SVR grid.
    pub quick: bool,
    /// No progress bars.
    pub quiet: bool,
    /// Run the last act (flash and measure on the virtual device).
    pub virtual_device: bool,
}

/// What the demo did; its [`Display`](std::fmt::Display) is the text
/// `spidar demo` prints.
#[derive(Clone, Debug)]
pub struct Demo {
    /// The device seed.
    pub seed: u64,
    /// The simulated lattice (training) session and its geometry and truth.
    pub lattice: SimulateReport,
    /// The simulated test session.
    pub test: SimulateReport,
    /// The calibration's summary.
    pub summary: String,
    /// The calibration's report as a page for people (`report.html`).
    pub page: PathBuf,
    /// The last act: the nominal and the calibrated model on the virtual
    /// device (`None` when not asked for).
    pub on_device: Option<OnDevice>,
}

/// The nominal and the calibrated model flashed to the virtual device.
#[derive(Clone, Copy, Debug)]
pub struct OnDevice {
    pub before: VirtualDeviceRun,
    pub after: VirtualDeviceRun,
}

/// Runs the demo: simulate, calibrate (outputs in `OUT/calibration`), and the
/// last act when asked for.
pub fn run_demo(request: &DemoRequest) -> Result<Demo, DemoError> {
    let simulate = |kind: SessionPath, name: &str| SimulateRequest {
        out: request.out.clone(),
        seed: request.seed,
        config: request.config.clone(),
        preset: None,
        kind,
        points: None,
        effects: request.effects.clone(),
        name: Some(name.to_string()),
        session_seed: None,
        physics: Default::default(),
    };
    let lattice = run_simulate(&simulate(SessionPath::Lattice, "lattice"))?;
    let test = run_simulate(&simulate(SessionPath::Random, "test"))?;
    let out = request.out.join("calibration");
    let out_dir = out.clone();
    let mut config = if request.quick {
        CalibrateConfig::quick()
    } else {
        CalibrateConfig::full()
    };
    config.seed = 1;
    config.blackbox = request.blackbox;
    config.quiet = request.quiet;
    config.loop_config.layer_tables = true;
    let calibrated = run_calibrate(&CalibrateRequest {
        geometry: lattice.geometry.clone(),
        train: lattice.session.clone(),
        test: test.session.clone(),
        json: Some(out.join("report.json")),
        out,
        export_pairs: None,
        figures: true,
        config,
    })?;
    let on_device = if request.virtual_device {
        Some(run_on_virtual_device(request, &lattice.geometry, &out_dir)?)
    } else {
        None
    };
    Ok(Demo {
        seed: request.seed,
        lattice,
        test,
        summary: calibrated.report.summary(),
        page: PathBuf::from(&calibrated.report.files.page),
        on_device,
    })
}

/// The demo's last act: compile the nominal and the calibrated model, flash
/// each to a virtual device whose plant follows the test trajectory, and
/// measure what the device reports against the true position.
fn run_on_virtual_device(
    request: &DemoRequest,
    geometry_path: &Path,
    calibration_dir: &Path,
) -> Result<OnDevice, DemoError> {
    let mut config = match &request.config {
        Some(path) => SimConfig::load(path)?,
        None => SimConfig::default(),
    };
    config.effects.extend(request.effects.iter().cloned());
    let device = SimulatedDevice::new(&config, request.seed)?;
    // The test session's trajectory (run_simulate's seed rule for random sessions).
    let (_, truths) = simulate_session_with_truth(
        &device,
        SessionKind::Random {
            points: config.random.points,
        },
        request.seed.wrapping_add(2),
    )?;
    let geometry = Geometry::load(geometry_path)?;
    let nominal = Calibration {
        frame: geometry.nominal_frame(),
        strings: geometry.nominal_string_laws(),
        effects: Vec::new(),
        correction: CorrectionModel::None,
        length_scale_mm: [0.0; spidar_core::STRINGS],
        kinematics: Default::default(),
        home: None,
    };
    let calibrated =
        crate::model::compile::load_calibration(&calibration_dir.join("calibration.json"))?;
    let blob = |what: &'static str, c: &Calibration| {
        spidar_core::blob::compile(c, crate::model::compile::model_id_of(c), 0).map_err(|e| {
            DemoError::Blob {
                what,
                message: e.to_string(),
            }
        })
    };
    let before =
        measure_on_virtual_device(&device, &truths, &blob("the nominal model", &nominal)?)?;
    let after =
        measure_on_virtual_device(&device, &truths, &blob("the calibration", &calibrated)?)?;
    Ok(OnDevice { before, after })
}

impl std::fmt::Display for Demo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (lattice, test) = (&self.lattice, &self.test);
        let mut text = format!(
            "simulated device (seed {}): {}, {} ({} rows), {} ({} rows), {} (the truth, not used)\n\n",
            self.seed,
            lattice.geometry.display(),
            lattice.session.display(),
            lattice.rows,
            test.session.display(),
            test.rows,
            lattice.truth.display(),
        );
        text.push_str(&self.summary);
        if let Some(on_device) = &self.on_device {
            text.push_str(&on_device.to_string());
        }
        text.push_str(&format!(
            "\nThe report, for people: {} (open it in a browser)\n",
            self.page.display()
        ));
        f.write_str(&text)
    }
}

impl std::fmt::Display for OnDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let row = |name: &str, r: &VirtualDeviceRun| {
            format!(
                "  {name:<22} {:>9.3} {:>8.3} {:>9.3} {:>8} {:>6} {:>8}\n",
                r.error.mean_mm, r.error.sd_mm, r.error.max_mm, r.frames, r.lost, r.blob_len
            )
        };
        f.write_str(&format!(
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
            row("before (nominal)", &self.before),
            row("after (calibrated)", &self.after),
        ))
    }
}
