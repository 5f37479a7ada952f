//! The identified parameters with their uncertainty and whether the data
//! determined them, the fit's residual, and the anchors' tolerance.

use serde_json::Value;

use super::html::{self, f, list, mm, p, percent, s, sig, u, Cell, Html, Table};
use crate::model::identify::{radius_string, value_with_sd, xyz_stem};

/// Parameters listed one by one; beyond, the undetermined ones and a count.
const LISTED: usize = 120;

pub(super) fn section(r: &Value) -> Html {
    let id = &r["identification"];
    let parameters = list(&id["parameters"]);
    let undetermined: Vec<&Value> = parameters
        .iter()
        .filter(|v| v["determined"].as_bool() == Some(false))
        .collect();
    let mut h = p(&format!(
        "{} of the final identification (anchors, home, the tracker's frame, the winding laws \
         and every effect added), each with its posterior standard deviation; {}",
        html::plural(parameters.len(), "parameter", "parameters"),
        match undetermined.len() {
            0 => "the data determine every one.".to_string(),
            n => format!(
                "{n} the data do not determine (marked: {} uncertainty is about {} prior's, \
                 so the value is the prior's, not a measurement).",
                if n == 1 { "its" } else { "their" },
                if n == 1 { "its" } else { "their" }
            ),
        }
    ));
    h.push(html::facts(&[
        (
            "string residual, robust scale",
            format!("{} mm", mm(f(&id["residual_scale_mm"]))),
        ),
        (
            "before any effect",
            format!("{} mm", mm(f(&id["base_residual_scale_mm"]))),
        ),
        (
            "residuals the robust fit weighed out",
            percent(f(&id["rejected_fraction"])),
        ),
        ("model evaluations", html::count(u(&id["evaluations"]))),
    ]));
    let warnings: Vec<&str> = list(&id["warnings"]).iter().map(s).collect();
    if !warnings.is_empty() {
        h.push(Html::raw(format!(
            "<div class=\"warnings\">{}</div>",
            html::bullets(warnings).0
        )));
    }
    h.push(parameter_table(
        parameters,
        &r["device"]["channels"],
        &id["mechanical_advantage"],
    ));
    // The plain least-squares reference is what the device runs when the
    // selection held to it.
    let reference = list(&id["reference_parameters"]);
    if r["selection"]["choice"].as_str() == Some("reference") && !reference.is_empty() {
        h.push(p(
            "The final model is the plain least-squares reference: its parameters, each with \
             its standard deviation from the data alone (no prior holds it), are what the \
             device runs.",
        ));
        h.push(parameter_table(
            reference,
            &r["device"]["channels"],
            &id["mechanical_advantage"],
        ));
    }
    h.push(tolerance(&r["anchor_tolerance"]));
    h
}

/// The parameters in two tables: points and vectors (`name.x`, `.y`, `.z`
/// of one unit, one row each) and scalars; the undetermined first when
/// they are too many to list.
fn parameter_table(parameters: &[Value], channels: &Value, advantage: &Value) -> Html {
    // A string's `r_home` is its effective radius: the spool's over its
    // mechanical advantage (its position in `channels`).
    let advantage_of = |name: &str| -> Option<f64> {
        let string = radius_string(name)?;
        let k = list(channels)
            .iter()
            .position(|c| c.as_u64() == Some(string as u64))?;
        f(list(advantage).get(k)?).filter(|ma| *ma != 1.0)
    };
    let listed: Vec<&Value> = if parameters.len() <= LISTED {
        parameters.iter().collect()
    } else {
        // The undetermined first: they are what needs reading.
        let mut v: Vec<&Value> = parameters
            .iter()
            .filter(|p| p["determined"].as_bool() == Some(false))
            .collect();
        v.extend(
            parameters
                .iter()
                .filter(|p| p["determined"].as_bool() != Some(false)),
        );
        v.truncate(LISTED);
        v
    };
    let mut vectors = Table::new(&["parameter", "x", "y", "z", "unit", "prior sd", "determined"]);
    let mut scalars = Table::new(&["parameter", "value", "unit", "prior sd", "determined"]);
    let mut k = 0;
    while k < listed.len() {
        if let Some(group) = xyz_group(&listed[k..]) {
            let cells = vec![
                Cell::text(group.0),
                Cell::num(with_sd(group.1[0])),
                Cell::num(with_sd(group.1[1])),
                Cell::num(with_sd(group.1[2])),
                Cell::text(s(&group.1[0]["unit"])),
                Cell::num(shared(group.1.map(|v| sig(f(&v["prior_sd"]))))),
                Cell::text(&determined(&group.1)),
            ];
            push_row(&mut vectors, cells, &group.1);
            k += 3;
        } else {
            let v = listed[k];
            let name = match advantage_of(s(&v["name"])) {
                Some(ma) => format!(
                    "{} (effective radius: the spool's / mechanical advantage {ma})",
                    s(&v["name"])
                ),
                None => s(&v["name"]).to_string(),
            };
            let cells = vec![
                Cell::text(&name),
                Cell::num(with_sd(v)),
                Cell::text(s(&v["unit"])),
                Cell::num(sig(f(&v["prior_sd"]))),
                Cell::text(&determined(&[v])),
            ];
            push_row(&mut scalars, cells, &[v]);
            k += 1;
        }
    }
    let mut h = Html::default();
    if vectors.rows() > 0 {
        h.push(vectors.html());
    }
    if scalars.rows() > 0 {
        h.push(scalars.html());
    }
    if parameters.len() > listed.len() {
        h.push(p(&format!(
            "{} of {} parameters listed (the undetermined first); report.json has them all.",
            listed.len(),
            parameters.len()
        )));
    }
    h
}

/// `name.x`, `name.y`, `name.z` of one unit at the head of `rest`.
fn xyz_group<'a>(rest: &[&'a Value]) -> Option<(&'a str, [&'a Value; 3])> {
    let [x, y, z]: [&'a Value; 3] = rest.get(..3)?.try_into().ok()?;
    let stem = xyz_stem(
        [x, y, z].map(|v| s(&v["name"])),
        [x, y, z].map(|v| s(&v["unit"])),
    )?;
    Some((stem, [x, y, z]))
}

fn push_row(table: &mut Table, cells: Vec<Cell>, values: &[&Value]) {
    if values
        .iter()
        .any(|v| v["determined"].as_bool() == Some(false))
    {
        table.row_with(" class=\"undetermined\"".into(), cells);
    } else {
        table.row(cells);
    }
}

/// "yes", or which of the values the data do not determine.
fn determined(values: &[&Value]) -> String {
    let not: Vec<&str> = values
        .iter()
        .filter(|v| v["determined"].as_bool() == Some(false))
        .map(|v| s(&v["name"]).rsplit('.').next().unwrap_or(""))
        .collect();
    match (not.len(), values.len()) {
        (0, _) => "yes".into(),
        (_, 1) => "no: about its prior".into(),
        _ => format!("no ({}): about the prior", not.join(", ")),
    }
}

/// One text when the three agree, else all three.
fn shared(texts: [String; 3]) -> String {
    if texts[0] == texts[1] && texts[1] == texts[2] {
        texts[0].clone()
    } else {
        texts.join(", ")
    }
}

/// A parameter's value and its sd, to the decimals the sd warrants (two
/// significant digits of the sd).
fn with_sd(v: &Value) -> String {
    match (f(&v["value"]), f(&v["sd"])) {
        (Some(value), sd) => {
            value_with_sd(value, sd.unwrap_or(f64::NAN)).unwrap_or_else(|| sig(Some(value)))
        }
        (None, _) => html::NONE.into(),
    }
}

/// How far the anchors may be from the geometry, and how that was chosen.
fn tolerance(t: &Value) -> Html {
    let mut h = html::tag("h3", "The anchors' tolerance");
    let sds: Vec<f64> = list(&t["anchor_sd_mm"]).iter().filter_map(f).collect();
    let sd = match (sds.first(), sds.iter().all(|v| Some(v) == sds.first())) {
        (Some(v), true) => format!("{} mm on every anchor", sig(Some(*v))),
        (Some(_), false) => {
            let each: Vec<String> = sds.iter().map(|v| sig(Some(*v))).collect();
            format!("{} mm per channel", each.join(", "))
        }
        (None, _) => html::NONE.into(),
    };
    h.push(p(&format!(
        "The identification's prior on the anchors: {sd}. {}",
        html::capitalized(s(&t["reason"]))
    )));
    let scores = list(&t["scores"]);
    if !scores.is_empty() {
        let mut table = Table::new(&["anchor sd, mm", "held-out mean, mm", "p95, mm", "max, mm"]);
        for sc in scores {
            let held = &sc["held_out"];
            table.row(vec![
                Cell::num(sig(f(&sc["anchor_sd_mm"]))),
                Cell::num(mm(f(&held["mean_mm"]))),
                Cell::num(mm(f(&held["p95_mm"]))),
                Cell::num(mm(f(&held["max_mm"]))),
            ]);
        }
        h.push(table.html());
        h.push(p(&format!(
            "On {}; {}.",
            s(&t["folds"]),
            if t["robust"].as_bool() == Some(false) {
                "plain least-squares weights gained on the same folds and are used"
            } else {
                "the rows are reweighed robustly after the least-squares round"
            }
        )));
    }
    h
}
