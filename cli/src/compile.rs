//! `spidar compile`.

use std::path::PathBuf;

use spidar::model::compile::{CompileRequest, FIXED_POINT_BUDGET_MM};

/// `spidar compile`.
#[derive(Clone, Debug, clap::Args)]
pub struct CompileArgs {
    /// Calibration written by `spidar calibrate` (calibration.json).
    #[arg(long)]
    pub calibration: PathBuf,
    /// Where to write the model blob.
    #[arg(long)]
    pub out: PathBuf,
    /// Test session CSV: measure the fixed-point error on its rows.
    #[arg(long)]
    pub test: Option<PathBuf>,
    /// Nominal geometry of the session (checks its counts per revolution
    /// against the calibration's).
    #[arg(long)]
    pub geometry: Option<PathBuf>,
    /// Model id (default: CRC-32 of the calibration).
    #[arg(long)]
    pub model_id: Option<u32>,
    /// Largest mean fixed-point error accepted, mm.
    #[arg(long, default_value_t = FIXED_POINT_BUDGET_MM)]
    pub budget_mm: f64,
    /// Write the blob even when its fixed-point error is over the budget or
    /// it is too large for the firmware (the command still fails).
    #[arg(long)]
    pub write_over_budget: bool,
}

/// Runs `spidar compile`; returns what to print.
pub fn run(args: &CompileArgs) -> anyhow::Result<String> {
    let request = CompileRequest {
        calibration: args.calibration.clone(),
        out: args.out.clone(),
        test: args.test.clone(),
        geometry: args.geometry.clone(),
        model_id: args.model_id,
        budget_mm: args.budget_mm,
        write_over_budget: args.write_over_budget,
    };
    Ok(spidar::model::compile::run_compile(&request)?.to_string())
}
