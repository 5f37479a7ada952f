//! The calibration report's readable summary ([`Report::summary`]): the
//! sessions and the device, the error table of every stage, the effects
//! diagnosis found, the corrections and the choice of the final model,
//! warnings, time and the files written, as printed on stdout.

use std::fmt::Write as _;

use serde::Serialize;

use super::{Choice, Report, Stage};
use crate::model::identify::{radius_string, value_with_sd, xyz_stem, ParameterEstimate};
use crate::procedures::calibrate::{align, MIN_SELECTION_POINTS};

fn stage_table(out: &mut String, stages: &[Stage]) {
    let width = stages
        .iter()
        .map(|s| s.name.chars().count())
        .max()
        .unwrap_or(5)
        .max(5);
    let (ntr, nte) = stages.first().map_or((0, 0), |s| (s.train.n, s.test.n));
    let _ = writeln!(
        out,
        "  {:width$}  {:>27}  {:>27}",
        "",
        format!("training session (n = {ntr})"),
        format!("test session (n = {nte})"),
    );
    let _ = writeln!(
        out,
        "  {:width$}  {:>8} {:>8} {:>9}  {:>8} {:>8} {:>9}",
        "stage", "mean", "sd", "max", "mean", "sd", "max"
    );
    for s in stages {
        let _ = writeln!(
            out,
            "  {:width$}  {:>8} {:>8} {:>9}  {:>8} {:>8} {:>9}",
            s.name,
            num(s.train.mean_mm),
            num(s.train.sd_mm),
            num(s.train.max_mm),
            num(s.test.mean_mm),
            num(s.test.sd_mm),
            num(s.test.max_mm),
        );
    }
}

/// Three decimals below 1000 mm, one above; "-" for a missing value.
fn num(v: f64) -> String {
    if !v.is_finite() {
        "-".into()
    } else if v.abs() < 1000.0 {
        format!("{v:.3}")
    } else {
        format!("{v:.1}")
    }
}

/// The JSON name of an enum value (e.g. `pulley_angle`).
fn label<T: Serialize>(value: &T) -> String {
    match serde_json::to_value(value) {
        Ok(serde_json::Value::String(s)) => s,
        _ => "?".into(),
    }
}

/// Parameter lines in the summary; the rest are counted.
const PARAMETER_LINES: usize = 24;

/// A parameter's value and its sd (the value alone when it has none).
fn estimate(p: &ParameterEstimate) -> String {
    value_with_sd(p.value, p.sd).unwrap_or_else(|| format!("{:.4}", p.value))
}

fn pct(v: f64) -> String {
    format!("{:.0} %", 100.0 * v)
}

impl Report {
    /// The readable summary: the paper's tables (raw, identified, effects,
    /// NN, SVR, final; mean, sd, max; training and test), the effects found,
    /// the choice, warnings, and where the files went.
    pub fn summary(&self) -> String {
        let mut o = String::new();
        self.write_inputs(&mut o);
        self.write_error_tables(&mut o);
        self.write_effects(&mut o);
        self.write_parameters(&mut o);
        self.write_corrections(&mut o);
        self.write_warnings(&mut o);
        self.write_time(&mut o);
        self.write_files(&mut o);
        o
    }

    /// The sessions, the device, its forward-kinematics rejections and the
    /// clock alignment.
    fn write_inputs(&self, o: &mut String) {
        let i = &self.inputs;
        let _ = writeln!(
            o,
            "training session {} ({} rows, {} tracked); test session {} ({} rows, {} tracked)",
            i.train.path, i.train.rows, i.train.tracked, i.test.path, i.test.rows, i.test.tracked
        );
        if let Some(h) = &i.test.home {
            let _ = writeln!(o, "test session's home capture: {}", h.reason);
        }
        let _ = writeln!(
            o,
            "training slips on the device: {}",
            self.device_slips.reason
        );
        let d = &self.device;
        let _ = writeln!(
            o,
            "device: {} strings (channels {:?}), {}, {} spare string{}",
            d.strings,
            d.channels,
            if d.planar { "planar" } else { "3-D" },
            d.redundancy,
            if d.redundancy == 1 { "" } else { "s" }
        );
        for l in &d.limits {
            let _ = writeln!(o, "  limit: {l}");
        }
        if let Some(w) = d.describe_weights() {
            let _ = writeln!(o, "  {w}");
        }
        for (name, r) in [
            ("training", &d.rejections.train),
            ("test", &d.rejections.test),
        ] {
            if r.flagged() > 0 {
                let _ = writeln!(o, "  forward kinematics, {name} session: {}", r.describe());
            }
        }
        for (name, t) in [
            ("training", &self.timing.train),
            ("test", &self.timing.test),
        ] {
            if let align::SessionTiming::Paired {
                median_interval_s,
                rows,
            } = t
            {
                let _ = writeln!(
                    o,
                    "{name} session: a stream of {rows} rows {median_interval_s:.3} s apart, its \
                     tracker and device rows paired by one clock (--clocks-paired): read as \
                     written, no offset searched"
                );
            }
            if let align::SessionTiming::Aligned(a) = t {
                let drift = if a.drift_ppm != 0.0 {
                    format!(
                        " at {:.1} s, running {:+.1} ppm fast (sd {:.1} ppm)",
                        a.reference_t_s, a.drift_ppm, a.drift_sd_ppm
                    )
                } else {
                    String::new()
                };
                let again = a.first_offset_s.map_or(String::new(), |first| {
                    format!(
                        ", moved by the latency every string shares that the loop found (the \
                         alignment's quick model, without one string's latencies, found {:+.2} \
                         ms)",
                        first * 1e3
                    )
                });
                let _ = writeln!(
                    o,
                    "{name} session: tracker clock {:+.2} ms (sd {:.3} ms){drift} from the \
                     device's, found from the motion ({} pairs, speed correlation {:.3}){again}; \
                     rows re-paired",
                    a.offset_s * 1e3,
                    a.offset_sd_s * 1e3,
                    a.pairs,
                    a.correlation
                );
            }
        }
    }

    /// The error table of every stage, and the black-box one.
    fn write_error_tables(&self, o: &mut String) {
        let _ = writeln!(
            o,
            "\nAbsolute position error (eq. 7) against the tracker, room frame, mm:"
        );
        stage_table(o, &self.stages);

        if let Some(bb) = &self.blackbox {
            let _ = writeln!(
                o,
                "\nBlack-box, as the paper ({}; {} mode):",
                bb.input, bb.mode
            );
            stage_table(o, &bb.stages);
            let _ = writeln!(
                o,
                "  NN: {} hidden neurons; SVR: C = {}, epsilon = {}, gamma = {}, {} support vectors; \
                 outliers removed: {} of {} (fence {:.1} mm)",
                bb.nn.best_hidden,
                bb.svr.best.c,
                bb.svr.best.epsilon,
                bb.svr.best.gamma,
                bb.svr.support_vectors,
                bb.outliers.removed,
                bb.outliers.points,
                bb.outliers.upper_fence_mm
            );
        }
    }

    /// The effects diagnosis found (or the smallest it would have seen).
    fn write_effects(&self, o: &mut String) {
        let _ = writeln!(o, "\nEffects found by diagnosis:");
        if let Some(why) = &self.identification.loop_not_run {
            let _ = writeln!(o, "  none tried: the diagnosis loop did not run ({why})");
        } else if self.effects.is_empty() {
            let _ = writeln!(
                o,
                "  none significant: the identified model explains the residual (a constant \
                 error of one string above ~{:.2} mm would have been seen)",
                self.device.smallest_detectable_offset_mm
            );
        }
        for f in &self.effects {
            let strings = if f.strings.is_empty() {
                "all strings".to_string()
            } else {
                let s: Vec<String> = f.strings.iter().map(|s| s.to_string()).collect();
                format!("string {}", s.join(", "))
            };
            let _ = writeln!(
                o,
                "  {:9} {} ({strings}) against {}: amplitude {:.3} mm, explains {}{}",
                if f.added { "added" } else { "not added" },
                label(&f.family),
                label(&f.variable),
                f.amplitude_mm,
                pct(f.explained),
                if f.description.is_empty() {
                    String::new()
                } else {
                    format!(" - {}", f.description)
                }
            );
            if let Some(check) = &f.validation {
                let _ = writeln!(o, "            {}", check.reason);
            }
        }
    }

    /// The identified parameters with their sds, and the plain
    /// least-squares reference's when it is the final model (what the
    /// device runs then).
    fn write_parameters(&self, o: &mut String) {
        self.write_parameter_table(
            o,
            "Identified parameters (value ± sd)",
            &self.identification.parameters,
        );
        if self.selection.choice == Choice::Reference {
            self.write_parameter_table(
                o,
                "The final model's parameters: the plain least-squares reference's (value ± sd \
                 from the data alone)",
                &self.identification.reference_parameters,
            );
        }
    }

    /// `params` with their sds under `title`, one line per point (an
    /// anchor, the home, the tracker's frame) or scalar, as the page groups
    /// them; the first [`PARAMETER_LINES`], the rest counted.
    fn write_parameter_table(&self, o: &mut String, title: &str, params: &[ParameterEstimate]) {
        if params.is_empty() {
            return;
        }
        let _ = writeln!(o, "\n{title}:");
        let mut lines: Vec<(String, String)> = Vec::new();
        let mut k = 0;
        while k < params.len() {
            let group = params.get(k..k + 3).and_then(|g| {
                xyz_stem(
                    [0, 1, 2].map(|i| g[i].name.as_str()),
                    [0, 1, 2].map(|i| g[i].unit.as_str()),
                )
                .map(|stem| (stem, g))
            });
            let (name, members) = match group {
                Some((stem, g)) => (stem.to_string(), g),
                None => (params[k].name.clone(), &params[k..k + 1]),
            };
            k += members.len();
            let values: Vec<String> = members.iter().map(estimate).collect();
            let mut line = format!("{} {}", values.join(", "), members[0].unit);
            let undetermined: Vec<&str> = members
                .iter()
                .filter(|p| !p.determined)
                .map(|p| p.name.rsplit('.').next().unwrap_or(""))
                .collect();
            if !undetermined.is_empty() {
                let which = if members.len() == 1 {
                    String::new()
                } else {
                    format!(" ({})", undetermined.join(", "))
                };
                line.push_str(&format!("; not determined{which}: about the prior"));
            }
            if let Some(ma) = radius_string(&name)
                .and_then(|s| self.identification.advantage_of(&self.device.channels, s))
            {
                line.push_str(&format!(
                    "; the effective radius: the spool's radius / mechanical advantage {ma}"
                ));
            }
            lines.push((name, line));
        }
        let width = lines.iter().map(|l| l.0.chars().count()).max().unwrap_or(0);
        for (name, line) in lines.iter().take(PARAMETER_LINES) {
            let _ = writeln!(o, "  {name:width$}  {line}");
        }
        if lines.len() > PARAMETER_LINES {
            let _ = writeln!(
                o,
                "  and {} more (report.json and report.html have them all)",
                lines.len() - PARAMETER_LINES
            );
        }
    }

    /// The rules the identification chose: the kinematics', the loop's
    /// rows, the anchors' tolerance.
    fn write_identification_rules(&self, o: &mut String) {
        let k = &self.kinematics;
        let _ = writeln!(
            o,
            "\nKinematics: leave a string out from {:.2} mm RMS, inconsistent from {:.2} mm, \
             strings {} - {}",
            k.rule.exclusion_threshold_mm,
            k.rule.fault_threshold_mm,
            if k.weighted {
                "weighed by their scales"
            } else {
                "weighing alike"
            },
            k.reason
        );
        for c in &k.candidates {
            let _ = writeln!(
                o,
                "  {:36} held out {} mm mean, {} p95",
                c.candidate.name,
                num(c.held_out.mean_mm),
                num(c.held_out.p95_mm)
            );
        }
        let r = &self.identification.loop_rows;
        if r.stride > 1 {
            let _ = writeln!(
                o,
                "Identification loop: decided on {} of the {} training rows (one in every {}, in time order); the model identified on those rows, every row in the figures",
                r.rows, r.of, r.stride
            );
        }
        let t = &self.anchor_tolerance;
        let _ = writeln!(
            o,
            "Anchors' tolerance: {} mm - {}",
            num(t.anchor_sd_mm[0]),
            t.reason
        );
    }

    /// The residual corrections and the choice of the final stage.
    fn write_corrections(&self, o: &mut String) {
        self.write_identification_rules(o);
        let s = &self.selection;
        let Some(c) = &self.corrections else {
            let _ = writeln!(
                o,
                "\nFinal stage `{}` (no learned corrections): {} (selection split of {} points: \
                 identified {}, plain least squares {} mm)",
                s.stage,
                s.reason,
                s.selection_points,
                num(s.validation_mean_mm.identified),
                num(s.validation_mean_mm.reference)
            );
            self.write_device_tick(o);
            return;
        };
        let _ = writeln!(
            o,
            "\nCorrections ({} mode, on top of the identified model):",
            c.mode
        );
        let _ = writeln!(
            o,
            "  outliers (Tukey box plot): {} of {} training points removed (fences {:.3} .. {:.3} mm)",
            c.outliers.removed, c.outliers.points, c.outliers.lower_fence_mm, c.outliers.upper_fence_mm
        );
        if let Some(cell) = c.learning_points.cell_mm {
            let _ = writeln!(
                o,
                "  learned from {} of the {} kept training points, one per {:.1} mm cell (a larger session is thinned evenly through its volume)",
                c.learning_points.used, c.learning_points.kept, cell
            );
        }
        let _ = writeln!(
            o,
            "  nn: sweep of {} hidden sizes, best {} neurons; svr: C = {}, epsilon = {}, gamma = {}, {} support vectors",
            c.nn.sweep.len(),
            c.nn.best_hidden,
            c.svr.best.c,
            c.svr.best.epsilon,
            c.svr.best.gamma,
            c.svr.support_vectors
        );
        if let Some(cell) = c.svr_learning_points.cell_mm {
            let room = s
                .device_tick
                .map_or(spidar_core::correction::MAX_SUPPORT_VECTORS, |t| {
                    t.room.support_vectors
                });
            let _ = writeln!(
                o,
                "  svr: learned from {} of the {} fit points, one per {:.1} mm cell: the device's control loop has room for {} support vectors a tick beside this model",
                c.svr_learning_points.used,
                c.svr_learning_points.kept,
                cell,
                room
            );
        }
        let why = match s.choice {
            Choice::Identified if s.selection_points < MIN_SELECTION_POINTS => format!(
                "the identified model alone: corrections are not chosen on fewer than {} points, \
                 and there are",
                MIN_SELECTION_POINTS
            ),
            Choice::Identified => format!(
                "the identified model alone: no correction lowered its mean error by {} without \
                 raising its p95 or max beyond noise, on",
                pct(s.min_correction_gain)
            ),
            Choice::Nn => {
                "the NN correction, refitted on all the points it learns from; lowest error on"
                    .into()
            }
            Choice::Svr => {
                "the SVR correction, refitted on all the points it learns from; lowest error on"
                    .into()
            }
            Choice::Reference => {
                "the plain least-squares reference: the chosen model was not better on".into()
            }
        };
        let _ = writeln!(
            o,
            "  final stage `{}`: {why} a {}-point selection split of the training session \
             (identified {}, nn {}, svr {}, plain least squares {} mm)",
            s.stage,
            s.selection_points,
            num(s.validation_mean_mm.identified),
            num(s.validation_mean_mm.nn),
            num(s.validation_mean_mm.svr),
            num(s.validation_mean_mm.reference)
        );
        let _ = writeln!(o, "    why: {}", s.reason);
        self.write_device_tick(o);
    }

    /// What the device's control loop takes a tick with the calibration.
    fn write_device_tick(&self, o: &mut String) {
        if let Some(t) = self.selection.device_tick {
            let _ = writeln!(
                o,
                "  device: an estimated {} of the {} instructions its control loop has a tick; beside this model a correction may have {} hidden neurons or {} support vectors",
                t.final_instructions
                    .map_or("?".to_string(), |n| n.to_string()),
                t.room.budget,
                t.room.neurons,
                t.room.support_vectors
            );
        }
    }

    /// Warnings and notes.
    fn write_warnings(&self, o: &mut String) {
        if !self.warnings.is_empty() {
            let _ = writeln!(o, "\nWarnings:");
            for w in &self.warnings {
                let _ = writeln!(o, "  - {w}");
            }
        }
        if !self.notes.is_empty() {
            let _ = writeln!(o, "\nNotes:");
            for n in &self.notes {
                let _ = writeln!(o, "  - {n}");
            }
        }
    }

    /// Where the time went.
    fn write_time(&self, o: &mut String) {
        let _ = writeln!(o, "\n{}", time_line(&self.timings_s));
    }

    /// Where the files went.
    fn write_files(&self, o: &mut String) {
        if !self.files.calibration.is_empty() {
            let _ = writeln!(o, "\nWrote:");
            let _ = writeln!(o, "  {} (the calibration)", self.files.calibration);
            for r in &self.files.reports {
                let _ = writeln!(o, "  {r} (JSON report)");
            }
            if !self.files.page.is_empty() {
                let _ = writeln!(
                    o,
                    "  {} (the report as a page: open it in a browser)",
                    self.files.page
                );
            }
            if let Some(first) = self.figures.first() {
                let dir = std::path::Path::new(&first.path)
                    .parent()
                    .map(|p| p.display().to_string())
                    .unwrap_or_default();
                let _ = writeln!(o, "  {dir}/ ({} figures, PNG)", self.figures.len());
            }
        }
    }
}

/// The summary's line of where the time went: every part timed, and what
/// is left of the whole (reading, the stages' errors, the checks), so the
/// parts add up to it.
fn time_line(t: &super::Timings) -> String {
    let mut parts: Vec<(&str, f64)> = vec![
        ("clock alignment", t.alignment_s),
        ("identification and diagnosis", t.identification_s),
        ("plain least-squares reference", t.reference_s),
        ("kinematics' rule", t.rule_s),
        ("NN", t.nn_s),
        ("SVR", t.svr_s),
        ("choice and refit", t.selection_s),
    ];
    parts.extend(t.blackbox_s.map(|b| ("black-box", b)));
    let timed: f64 = parts.iter().map(|(_, s)| s).sum::<f64>() + t.raw_s;
    parts.push(("the rest", (t.calibration_s - timed).max(0.0)));
    let listed: Vec<String> = parts
        .iter()
        .filter(|(name, s)| *s >= 0.05 || matches!(*name, "NN" | "SVR"))
        .map(|(name, s)| format!("{name} {s:.1}"))
        .collect();
    format!(
        "Time: calibration {:.1} s ({}){}",
        t.calibration_s,
        listed.join(", "),
        t.figures_s
            .map_or(String::new(), |f| format!("; figures {f:.1} s")),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1 kHz stream's alignment took 9 of its 18.6 s, and the line named
    /// parts adding up to 5.
    #[test]
    fn the_time_line_names_the_alignment_and_adds_up() {
        let t = super::super::Timings {
            alignment_s: 9.0,
            identification_s: 3.2,
            nn_s: 1.4,
            svr_s: 0.3,
            selection_s: 0.1,
            calibration_s: 18.6,
            ..Default::default()
        };
        let line = time_line(&t);
        assert_eq!(
            line,
            "Time: calibration 18.6 s (clock alignment 9.0, identification and diagnosis 3.2, \
             NN 1.4, SVR 0.3, choice and refit 0.1, the rest 4.6)"
        );
    }
}
