//! What came in: the geometry and the sessions, the device their strings
//! make, the tracker's clock against the device's, and the rows set aside.

use std::collections::BTreeMap;

use serde_json::Value;

use super::html::{self, count, f, list, mm, p, plural, s, some_lines, u, Cell, Html, Table};

/// Rows set aside listed one by one, per session; the others are counted.
const SET_ASIDE_LISTED: usize = 8;
/// Line numbers named in a summary before "and N more".
const LINES_NAMED: usize = 12;

pub(super) fn section(r: &Value) -> Html {
    let mut h = p(&format!("Geometry: {}.", s(&r["inputs"]["geometry"])));
    h.push(sessions(&r["inputs"]));
    h.push(html::tag("h3", "The device"));
    h.push(device(&r["device"]));
    h.push(html::tag("h3", "The tracker's clock"));
    h.push(clocks(&r["timing"]));
    h.push(html::tag("h3", "Rows set aside"));
    h.push(set_aside(r));
    h
}

fn sessions(inputs: &Value) -> Html {
    let mut t = Table::new(&[
        "session",
        "file",
        "rows",
        "tracked",
        "occluded",
        "set aside",
        "tensions",
        "columns not read",
    ]);
    for (name, v) in [("training", &inputs["train"]), ("test", &inputs["test"])] {
        let mut unread: Vec<&str> = list(&v["unread_columns"]).iter().map(s).collect();
        unread.extend(list(&v["ignored_columns"]).iter().map(s));
        t.row(vec![
            Cell::text(name),
            Cell::text(s(&v["path"])),
            Cell::num(count(u(&v["rows"]))),
            Cell::num(count(u(&v["tracked"]))),
            Cell::num(count(u(&v["occluded"]))),
            Cell::num(list(&v["set_aside"]).len().to_string()),
            Cell::text(yes_no(&v["has_tension"])),
            Cell::text(&unread.join(", ")),
        ]);
    }
    let mut h = t.html();
    h.push(p(
        "Tracked rows are those with a tracker position: every error on this page is over them.",
    ));
    if let Some(reason) = inputs["test"]["home"]["reason"].as_str() {
        h.push(p(&format!("The test session's home capture: {reason}.")));
    }
    h
}

fn yes_no(v: &Value) -> &'static str {
    match v.as_bool() {
        Some(true) => "yes",
        Some(false) => "no",
        None => html::NONE,
    }
}

fn device(d: &Value) -> Html {
    let channels: Vec<String> = list(&d["channels"])
        .iter()
        .filter_map(|c| c.as_u64().map(|c| c.to_string()))
        .collect();
    let mut h = html::facts(&[
        ("strings", count(u(&d["strings"]))),
        ("encoder channels", channels.join(", ")),
        (
            "motion",
            format!(
                "{}, {} degrees of freedom",
                if d["planar"].as_bool() == Some(true) {
                    "planar"
                } else {
                    "3-D"
                },
                count(u(&d["dof"]))
            ),
        ),
        ("spare strings", count(u(&d["redundancy"]))),
        (
            "a faulty string can be left out",
            yes_no(&d["fault_rejection"]).to_string(),
        ),
        (
            "smallest error of one string diagnosis sees",
            format!("{} mm", mm(f(&d["smallest_detectable_offset_mm"]))),
        ),
    ]);
    let limits: Vec<&str> = list(&d["limits"]).iter().map(s).collect();
    if !limits.is_empty() {
        h.push(p("What the number of strings and rows leaves unchecked:"));
        h.push(html::bullets(limits));
    }
    let mut lines = Vec::new();
    for (name, r) in [
        ("training", &d["rejections"]["train"]),
        ("test", &d["rejections"]["test"]),
    ] {
        lines.push(format!(
            "Forward kinematics of the final model, {name} session: {}.",
            rejections(r)
        ));
    }
    h.push(html::bullets(lines.iter().map(String::as_str)));
    h
}

/// What forward kinematics did with a session's rows, in words.
fn rejections(r: &Value) -> String {
    let per_channel = |key: &str, what: &str| -> Vec<String> {
        list(&r[key])
            .iter()
            .enumerate()
            .filter_map(|(c, n)| n.as_u64().filter(|&n| n > 0).map(|n| (c, n)))
            .map(|(c, n)| format!("string {c} {what} in {}", plural(n as usize, "row", "rows")))
            .collect()
    };
    let mut parts = per_channel("excluded_by_channel", "left out as faulty");
    let inconsistent = u(&r["inconsistent"]).unwrap_or(0);
    if inconsistent > 0 {
        let mut text = format!(
            "{} whose strings disagree with no exclusion trusted (the device turns force off there)",
            plural(inconsistent as usize, "row", "rows")
        );
        let placed = per_channel("inconsistent_excluded_by_channel", "placed without");
        if !placed.is_empty() {
            text += &format!("; of them {}", placed.join(", "));
        }
        parts.push(text);
    }
    for (key, what) in [
        ("not_converged", "not converged"),
        ("invalid", "with invalid lengths"),
    ] {
        if let Some(n) = u(&r[key]).filter(|&n| n > 0) {
            parts.push(format!("{} {what}", plural(n as usize, "row", "rows")));
        }
    }
    match u(&r["rows"]) {
        None => "not reported".into(),
        Some(rows) if parts.is_empty() => format!("all {rows} rows solved with every string"),
        Some(rows) => format!("of {rows} rows, {}", parts.join("; ")),
    }
}

fn clocks(timing: &Value) -> Html {
    let mut lines = Vec::new();
    for (name, t) in [("Training", &timing["train"]), ("Test", &timing["test"])] {
        lines.push(match s(&t["kind"]) {
            "static" => format!(
                "{name} session: one pose per row ({} rows, {} s apart at the median): nothing to align.",
                count(u(&t["rows"])),
                html::sig(f(&t["median_interval_s"]))
            ),
            "paired" => format!(
                "{name} session: a stream ({} rows, {} s apart at the median) whose tracker and \
                 device rows were paired by one clock when logged (--clocks-paired): \
                 read as written, no offset searched.",
                count(u(&t["rows"])),
                html::sig(f(&t["median_interval_s"]))
            ),
            "aligned" => {
                let drift = match f(&t["drift_ppm"]) {
                    Some(d) if d != 0.0 => format!(
                        ", running {d:+.1} ppm fast (sd {} ppm) from {} s",
                        html::fixed(f(&t["drift_sd_ppm"]), 1),
                        html::fixed(f(&t["reference_t_s"]), 1)
                    ),
                    _ => String::new(),
                };
                let again = match f(&t["first_offset_s"]) {
                    Some(first) => format!(
                        " Moved by the latency every string shares that the loop found: the \
                         alignment's quick model, without one string's latencies, found {} ms.",
                        html::fixed(Some(first * 1e3), 2)
                    ),
                    None => String::new(),
                };
                format!(
                    "{name} session: the tracker's clock is {} ms off the device's (sd {} ms){drift}, \
                     found from the motion: {} pairs, speed correlation {}; {} rows left unpaired; \
                     every row re-paired.{again}",
                    html::fixed(f(&t["offset_s"]).map(|v| v * 1e3), 2),
                    html::fixed(f(&t["offset_sd_s"]).map(|v| v * 1e3), 3),
                    count(u(&t["pairs"])),
                    html::fixed(f(&t["correlation"]), 3),
                    count(u(&t["rows_unpaired"]))
                )
            }
            _ => format!("{name} session: not reported."),
        });
    }
    html::bullets(lines.iter().map(String::as_str))
}

/// The values no device of the geometry could produce, per session, and
/// the tracker's glitches.
fn set_aside(r: &Value) -> Html {
    let mut h = Html::default();
    for (name, v) in [
        ("training", &r["inputs"]["train"]),
        ("test", &r["inputs"]["test"]),
    ] {
        let values = list(&v["set_aside"]);
        if values.is_empty() {
            h.push(p(&format!(
                "{} session: none; every value is one a device of this geometry can produce.",
                html::capitalized(name)
            )));
            continue;
        }
        h.push(p(&format!(
            "{} session: {} that no device of this geometry could produce (a whole row when \
             its counts cannot be; only the position when the tracker's or the legacy \
             controller's cannot):",
            html::capitalized(name),
            plural(values.len(), "value", "values")
        )));
        h.push(set_aside_summary(values));
        let mut t = Table::new(&["line", "column", "value", "part", "why"]);
        for v in values.iter().take(SET_ASIDE_LISTED) {
            t.row(vec![
                Cell::num(count(u(&v["line"]))),
                Cell::text(s(&v["column"])),
                Cell::num(html::sig(f(&v["value"]))),
                Cell::text(s(&v["part"])),
                Cell::text(s(&v["why"])),
            ]);
        }
        h.push(t.html());
        if values.len() > SET_ASIDE_LISTED {
            h.push(p(&format!(
                "The first {SET_ASIDE_LISTED} are listed; report.json lists all {}.",
                values.len()
            )));
        }
    }
    h.push(glitches(&r["identification"]["tracker_outliers"]));
    if let Some(d) = r["identification"]["marker_body_mm"].as_array() {
        let d: Vec<String> = d.iter().map(|v| html::fixed(f(v), 2)).collect();
        h.push(p(&format!(
            "The tracked body's origin is {} mm (body frame) from the strings' meeting point: \
             every stage after the identified one reads the tracker at the meeting point.",
            d.join(", ")
        )));
    }
    h
}

/// Values set aside counted by part and column, with their lines.
fn set_aside_summary(values: &[Value]) -> Html {
    let mut groups: BTreeMap<(&str, &str), Vec<u64>> = BTreeMap::new();
    for v in values {
        groups
            .entry((s(&v["part"]), s(&v["column"])))
            .or_default()
            .extend(u(&v["line"]));
    }
    let mut t = Table::new(&["part set aside", "column", "values", "lines"]);
    for ((part, column), lines) in &groups {
        t.row(vec![
            Cell::text(part),
            Cell::text(column),
            Cell::num(lines.len().to_string()),
            Cell::text(&some_lines(lines, LINES_NAMED)),
        ]);
    }
    t.html()
}

fn glitches(o: &Value) -> Html {
    let lines: Vec<u64> = list(&o["lines"]).iter().filter_map(Value::as_u64).collect();
    let too_many = u(&o["kept_too_many"]).unwrap_or(0);
    if too_many > 0 {
        return p(&format!(
            "Tracker: {too_many} training rows disagree with most of their strings by more than \
             {} mm, too many to be glitches: none is set aside (the model does not fit the session).",
            mm(f(&o["threshold_mm"]))
        ));
    }
    if lines.is_empty() {
        return p(&format!(
            "Tracker: no training row disagrees with most of its strings by more than {} mm \
             (20 times their median, {} mm, and at least 10 mm): no glitch set aside.",
            mm(f(&o["threshold_mm"])),
            mm(f(&o["median_mm"]))
        ));
    }
    let largest = list(&o["errors_mm"])
        .iter()
        .filter_map(f)
        .fold(0.0f64, f64::max);
    p(&format!(
        "Tracker: {} read as occluded, a glitch (a reflection, a swapped or lost marker): their \
         tracker disagrees with most of their strings by more than {} mm, up to {} mm. Lines \
         of the training file: {}.",
        plural(lines.len(), "training row", "training rows"),
        mm(f(&o["threshold_mm"])),
        mm(Some(largest)),
        some_lines(&lines, LINES_NAMED)
    ))
}
