//! `spidar report`.

use std::path::PathBuf;

/// `spidar report DIR`: rebuild a calibration's page from its report.
#[derive(Clone, Debug, clap::Args)]
pub struct ReportArgs {
    /// The calibration's output folder (`--out` of `spidar calibrate`):
    /// report.json and, beside it, report-figures.json.
    pub dir: PathBuf,
}

/// Runs `spidar report`; returns what to print.
pub fn run(args: &ReportArgs) -> anyhow::Result<String> {
    let page = spidar::procedures::report_page::rebuild(&args.dir)?;
    Ok(format!("wrote {}\n", page.display()))
}
