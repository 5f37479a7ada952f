//! The table rows: one per calibration, and the summary of every case.

use spidar::data::stats::ErrorStats;
use spidar::procedures::calibrate::report::{Stage, StageKind};
use spidar::procedures::calibrate::Calibrated;

pub(super) fn three(s: &ErrorStats) -> String {
    format!("{:.3} / {:.3} / {:.2}", s.mean_mm, s.p95_mm, s.max_mm)
}

/// The first stage of `kind` (every calibration has a reference, an
/// identified and a final stage).
pub(super) fn stage_of(c: &Calibrated, kind: StageKind) -> &Stage {
    c.report
        .stages
        .iter()
        .find(|s| s.kind == kind)
        .expect("a stage of every calibration")
}

/// One table row: the stages of one calibration, held-out.
pub(super) fn print_row(
    simulator: &str,
    effect: &str,
    seed: u64,
    c: &Calibrated,
) -> (f64, f64, f64, f64) {
    let stages = &c.report.stages;
    let raw = &stages[0].test;
    let identified = &stage_of(c, StageKind::Identified).test;
    let reference = &stage_of(c, StageKind::Reference).test;
    let added: Vec<String> = stages
        .iter()
        .filter(|s| s.kind == StageKind::Effect)
        .map(|s| format!("{} ({:.3})", s.name, s.test.mean_mm))
        .collect();
    let last = stages.last().expect("final stage");
    println!(
        "| {simulator} | {effect} | {seed} | {:.1} | {} | {} | {} | {} | {} |",
        raw.mean_mm,
        three(reference),
        three(identified),
        if added.is_empty() {
            "none".to_string()
        } else {
            added.join(", ")
        },
        last.name,
        three(&last.test)
    );
    (
        identified.mean_mm,
        last.test.mean_mm,
        last.test.p95_mm,
        last.test.max_mm,
    )
}

/// The final-test figures of one case's seeds, for the summary table.
pub(super) type CaseRows = (&'static str, &'static str, Vec<(f64, f64, f64, f64)>);

/// The averages of every case, and the notes.
pub(super) fn print_summary(summary: &[CaseRows], notes: &[String]) {
    println!();
    println!("| simulator | effect | identified mean (avg) | final mean (avg) | final p95 (worst) | final max (worst) |");
    println!("|---|---|---:|---:|---:|---:|");
    for (sim, effect, rows) in summary {
        let n = rows.len() as f64;
        println!(
            "| {sim} | {effect} | {:.3} | {:.3} | {:.3} | {:.2} |",
            rows.iter().map(|r| r.0).sum::<f64>() / n,
            rows.iter().map(|r| r.1).sum::<f64>() / n,
            rows.iter().map(|r| r.2).fold(0.0, f64::max),
            rows.iter().map(|r| r.3).fold(0.0, f64::max),
        );
    }
    println!();
    println!("significant but not added, and unexplained (independent simulator):");
    for n in notes {
        println!("- {n}");
    }
}
