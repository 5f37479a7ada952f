//! The calibration report as one page for people: `report.html`, written
//! beside `report.json` by every calibration and rebuilt from it by
//! `spidar report DIR`.
//!
//! One self-contained file: the styles inline, the figures inline SVG drawn
//! for the page (`svg.rs`), no script, and a Content-Security-Policy that
//! lets the page load nothing from outside. Its sections follow the
//! questions of whoever reads it, in order: what came in (`inputs.rs`), the
//! warnings, the error of every stage (`stages.rs`), each effect the loop
//! tried and its evidence (`effects.rs`), the identified parameters
//! (`parameters.rs`), the corrections chosen and why (`corrections.rs`), what
//! goes to the device (`device.rs`), and where the time went (`timings.rs`).
//!
//! The page reads `report.json` as JSON values (a key it does not find is
//! shown as missing, never a panic) and the per-row data the report does
//! not hold from `report-figures.json` ([`FigureData`]).

mod corrections;
mod data;
mod device;
mod effects;
mod evidence;
mod html;
mod inputs;
mod parameters;
mod stages;
mod svg;
mod timings;

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::data::output::write_atomically;

pub use data::{
    AlongSession, DeviceData, ErrorMap, FigureData, FixedPoint, StageQuantiles, FIGURE_DATA_FILE,
    FIGURE_DATA_SCHEMA,
};
pub use evidence::{EffectEvidence, StringEvidence};

use html::{escape, Html};

/// The page's file name, beside `report.json`.
pub const PAGE_FILE: &str = "report.html";
/// The report's file name in a calibration's folder.
pub const REPORT_FILE: &str = "report.json";

/// Why a page could not be written; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum PageError {
    #[error("{}: cannot read: {source}", file.display())]
    Read {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{}:{line}:{column}: not the JSON this file should hold: {message}", file.display())]
    Malformed {
        file: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
    #[error("{}: schema `{found}` is not `{expected}`, which this spidar reads", file.display())]
    Schema {
        file: PathBuf,
        found: String,
        expected: &'static str,
    },
    #[error("{}: cannot encode JSON: {source}", file.display())]
    Encode {
        file: PathBuf,
        source: serde_json::Error,
    },
    #[error("{}: cannot write (the previous file, if any, is kept): {source}", file.display())]
    Write {
        file: PathBuf,
        source: std::io::Error,
    },
}

/// Writes `DIR/report-figures.json` and `DIR/report.html` for the report
/// `report` (the JSON of `DIR/report.json`); returns the page's path.
pub fn write_page(dir: &Path, report: &Value, figures: &FigureData) -> Result<PathBuf, PageError> {
    let data_path = dir.join(FIGURE_DATA_FILE);
    let mut text = serde_json::to_string(figures).map_err(|source| PageError::Encode {
        file: data_path.clone(),
        source,
    })?;
    text.push('\n');
    write_atomically(&data_path, text.as_bytes()).map_err(|source| PageError::Write {
        file: data_path.clone(),
        source,
    })?;
    write_html(dir, &render(report, Some(figures)))
}

/// Rebuilds `DIR/report.html` from `DIR/report.json` and, when there,
/// `DIR/report-figures.json` (without it the page says which figures it
/// cannot draw); returns the page's path.
pub fn rebuild(dir: &Path) -> Result<PathBuf, PageError> {
    let report_path = dir.join(REPORT_FILE);
    let text = std::fs::read_to_string(&report_path).map_err(|source| PageError::Read {
        file: report_path.clone(),
        source,
    })?;
    let report: Value = serde_json::from_str(&text).map_err(|e| PageError::Malformed {
        file: report_path.clone(),
        line: e.line(),
        column: e.column(),
        message: e.to_string(),
    })?;
    let schema = html::s(&report["schema"]);
    if schema != crate::procedures::calibrate::SCHEMA {
        return Err(PageError::Schema {
            file: report_path,
            found: schema.to_string(),
            expected: crate::procedures::calibrate::SCHEMA,
        });
    }
    let figures = FigureData::load(&dir.join(FIGURE_DATA_FILE))?;
    write_html(dir, &render(&report, figures.as_ref()))
}

fn write_html(dir: &Path, page: &str) -> Result<PathBuf, PageError> {
    let path = dir.join(PAGE_FILE);
    write_atomically(&path, page.as_bytes()).map_err(|source| PageError::Write {
        file: path.clone(),
        source,
    })?;
    Ok(path)
}

/// The styles, inline in the page.
const STYLE: &str = include_str!("style.css");

/// Nothing may load from outside the page: any attempt is refused and
/// shows as a console error (what the browser check looks for).
const CONTENT_SECURITY_POLICY: &str =
    "default-src 'none'; style-src 'unsafe-inline'; img-src data:";

/// The page of `report` (the JSON of `report.json`), with the figures of
/// `figures` when given.
pub fn render(report: &Value, figures: Option<&FigureData>) -> String {
    let sections: [(&str, &str, Html); 8] = [
        ("inputs", "What came in", inputs::section(report)),
        ("warnings", "Warnings", warnings(report)),
        (
            "stages",
            "Error at every stage",
            stages::section(report, figures),
        ),
        (
            "effects",
            "Effects the loop tried",
            effects::section(report, figures),
        ),
        (
            "parameters",
            "Identified parameters",
            parameters::section(report),
        ),
        (
            "corrections",
            "Corrections chosen, and why",
            corrections::section(report),
        ),
        (
            "device",
            "What goes to the device",
            device::section(report, figures),
        ),
        ("timings", "Time and files", timings::section(report)),
    ];
    let mut nav = String::new();
    let mut body = Html::default();
    for (id, heading, content) in sections {
        nav.push_str(&format!(
            "<li><a href=\"#{id}\">{}</a></li>",
            escape(heading)
        ));
        body.push(html::section(id, heading, content));
    }
    let title = format!(
        "Calibration report: {}",
        html::s(&report["inputs"]["train"]["path"])
    );
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <meta http-equiv=\"Content-Security-Policy\" content=\"{CONTENT_SECURITY_POLICY}\">\
         <title>{}</title><style>{STYLE}</style></head>\n<body><header>{}</header>\
         <nav><ol>{nav}</ol></nav><main>{}</main><footer>{}</footer></body></html>\n",
        escape(&title),
        headline(report).0,
        body.0,
        footer(report).0
    )
}

/// The page's head: what was calibrated and the result in one line.
fn headline(report: &Value) -> Html {
    let d = &report["device"];
    let mut h = Html::raw("<h1>Calibration report</h1>");
    let shape = if d["planar"].as_bool() == Some(true) {
        "planar"
    } else {
        "3-D"
    };
    h.push(html::p(&format!(
        "A {shape} device of {} strings, geometry {}; trained on {}, tested on {}.",
        html::count(html::u(&d["strings"])),
        html::s(&report["inputs"]["geometry"]),
        html::s(&report["inputs"]["train"]["path"]),
        html::s(&report["inputs"]["test"]["path"]),
    )));
    let stages = html::list(&report["stages"]);
    if let (Some(first), Some(last)) = (stages.first(), stages.last()) {
        let mean = |s: &Value| html::mm(html::f(&s["test"]["mean_mm"]));
        let max = |s: &Value| html::mm(html::f(&s["test"]["max_mm"]));
        h.push(Html::raw(format!(
            "<p class=\"result\">Test session, mean error against the tracker: <b>{} mm</b> as built \
             (max {} mm) &rarr; <b>{} mm</b> with the final model <q>{}</q> (max {} mm).</p>",
            escape(&mean(first)),
            escape(&max(first)),
            escape(&mean(last)),
            escape(html::s(&last["name"])),
            escape(&max(last)),
        )));
    }
    let warnings = html::list(&report["warnings"]).len();
    if warnings > 0 {
        h.push(Html::raw(format!(
            "<p class=\"alert\"><a href=\"#warnings\">{}</a>: read them before using this calibration.</p>",
            escape(&html::plural(warnings, "warning", "warnings"))
        )));
    }
    h
}

/// The warnings, and the notes after them.
fn warnings(report: &Value) -> Html {
    let warnings: Vec<&str> = html::list(&report["warnings"])
        .iter()
        .map(html::s)
        .collect();
    let notes: Vec<&str> = html::list(&report["notes"]).iter().map(html::s).collect();
    let mut h = if warnings.is_empty() {
        html::p("None: nothing in this calibration needs a second look.")
    } else {
        Html::raw(format!(
            "<div class=\"warnings\">{}</div>",
            html::bullets(warnings).0
        ))
    };
    if !notes.is_empty() {
        h.push(html::tag("h3", "Notes"));
        h.push(html::p(
            "What else the run could do; not a problem with the result.",
        ));
        h.push(html::bullets(notes));
    }
    h
}

fn footer(report: &Value) -> Html {
    Html::text(&format!(
        "Written by {} {} from {} (schema {}). Every error is eq. 7 of the paper: the distance \
         between a position and the tracker's, in the room frame, in mm.",
        html::s(&report["tool"]["name"]),
        html::s(&report["tool"]["version"]),
        REPORT_FILE,
        html::s(&report["schema"]),
    ))
}

/// Why a figure drawn from `report-figures.json` is not on the page.
fn without_figure_data() -> Html {
    html::no_figure(&format!(
        "This figure is drawn from {FIGURE_DATA_FILE}, which is not beside {REPORT_FILE}; \
         a calibration run writes both."
    ))
}

#[cfg(test)]
mod tests;
