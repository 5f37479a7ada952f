//! What goes to the device: the model blob `spidar compile` makes of
//! `calibration.json` (its size against the firmware's slot, its error in
//! fixed point), the forward kinematics' rule and the strings' weights.

use serde_json::Value;

use super::data::FigureData;
use super::html::{self, f, list, mm, p, s, sig, u, Cell, Html, Table};

pub(super) fn section(r: &Value, figures: Option<&FigureData>) -> Html {
    let mut h = match figures.map(|d| &d.device) {
        None => super::without_figure_data(),
        Some(d) => blob(d),
    };
    h.push(tick(&r["selection"]["device_tick"]));
    h.push(rule(&r["kinematics"]));
    h.push(weights(&r["device"]));
    h.push(p(
        "To make the blob and measure it on a session: spidar compile --calibration \
         calibration.json --test <session.csv> --out model.blob; spidar flash writes it to the \
         device.",
    ));
    h
}

fn blob(d: &super::data::DeviceData) -> Html {
    if let Some(why) = &d.refused {
        return Html::raw(format!(
            "<p class=\"alert\">The compiler refuses this calibration: {}</p>",
            html::escape(why)
        ));
    }
    let mut facts = vec![
        (
            "model blob",
            match d.bytes {
                Some(b) => format!(
                    "{b} bytes of the firmware's {} ({})",
                    d.capacity,
                    if b <= d.capacity { "fits" } else { "too large" }
                ),
                None => html::NONE.into(),
            },
        ),
        ("model id", format!("{:#010x}", d.model_id)),
        (
            "correction",
            d.correction.clone().unwrap_or_else(|| html::NONE.into()),
        ),
        (
            "effect terms",
            d.effects
                .map_or_else(|| html::NONE.into(), |e| e.to_string()),
        ),
    ];
    if d.hidden.is_some_and(|h| h > 0) {
        facts.push(("hidden neurons", d.hidden.unwrap_or(0).to_string()));
    }
    if d.support_vectors.is_some_and(|n| n > 0) {
        facts.push((
            "support vectors",
            d.support_vectors.unwrap_or(0).to_string(),
        ));
    }
    let mut h = html::facts(&facts);
    match &d.fixed_point {
        Some(e) => {
            h.push(p(&format!(
                "In fixed point, as the device computes it, against the f64 model on {} test \
                 rows: the string model's position is off by {} mm on average ({} mm at most), \
                 the corrected position by {} mm ({} mm at most); the budget is {} mm on \
                 average: {}.{}",
                e.rows,
                sig(Some(e.string_model_mean_mm)),
                sig(Some(e.string_model_max_mm)),
                sig(Some(e.corrected_mean_mm)),
                sig(Some(e.corrected_max_mm)),
                sig(Some(e.budget_mm)),
                if e.corrected_mean_mm <= e.budget_mm {
                    "within it"
                } else {
                    "OVER it"
                },
                if e.status_mismatches > 0 {
                    format!(
                        " On {} rows forward kinematics converged on one side only.",
                        e.status_mismatches
                    )
                } else {
                    String::new()
                }
            )));
        }
        None => h.push(p(
            "No test row converged in both the device's arithmetic and the f64 model's: no \
             fixed-point error to report.",
        )),
    }
    h
}

/// What the device's control loop takes a tick with the calibration, and
/// the room a correction had beside its model (`selection.device_tick`).
fn tick(t: &Value) -> Html {
    if t.is_null() {
        return Html::default();
    }
    let n = |k: &str| {
        t[k].as_u64()
            .map_or_else(|| html::NONE.to_string(), |v| v.to_string())
    };
    p(&format!(
        "The device's control loop runs every 100 µs: with this calibration a tick takes an \
         estimated {} of the {} instructions it has. Beside the model a correction may have {} \
         hidden neurons or {} support vectors; the learned ones were held to that.",
        n("final_instructions"),
        n("budget"),
        n("neurons"),
        n("support_vectors")
    ))
}

/// The forward kinematics' rule the blob carries, and the candidates.
fn rule(k: &Value) -> Html {
    let mut h = html::tag("h3", "Forward kinematics' rule");
    h.push(p(&format!(
        "A string is left out of a row from {} mm RMS disagreement; the strings are \
         inconsistent (force off) from {} mm; {}. {}.",
        mm(f(&k["rule"]["exclusion_threshold_mm"])),
        mm(f(&k["rule"]["fault_threshold_mm"])),
        if k["weighted"].as_bool() == Some(false) {
            "the strings weigh alike"
        } else {
            "each string weighs by its measured scale"
        },
        html::capitalized(s(&k["reason"]).trim_end_matches('.'))
    )));
    let candidates = list(&k["candidates"]);
    if !candidates.is_empty() {
        let mut t = Table::new(&[
            "candidate",
            "leave out from, mm",
            "inconsistent from, mm",
            "weighed",
            "held-out mean, mm",
            "p95, mm",
        ]);
        for c in candidates {
            t.row(vec![
                Cell::text(s(&c["name"])),
                Cell::num(mm(f(&c["rule"]["exclusion_threshold_mm"]))),
                Cell::num(mm(f(&c["rule"]["fault_threshold_mm"]))),
                Cell::text(if c["weighted"].as_bool() == Some(true) {
                    "yes"
                } else {
                    "no"
                }),
                Cell::num(mm(f(&c["held_out"]["mean_mm"]))),
                Cell::num(mm(f(&c["held_out"]["p95_mm"]))),
            ]);
        }
        h.push(t.html());
    }
    h
}

/// Each string's measured scale and its weight in forward kinematics.
fn weights(d: &Value) -> Html {
    let weights = list(&d["string_weights"]);
    if weights.is_empty() {
        return Html::default();
    }
    let mut h = html::tag("h3", "The strings' weights");
    // The report's typical scale is 0 when the strings' scatter was not
    // measured: the kinematics' rule weighs every string alike.
    let Some(typical) = f(&d["typical_scale_mm"]).filter(|s| *s > 0.0) else {
        h.push(p(
            "Every string pulls the position alike: the kinematics' rule does not weigh the \
             strings by how much their lengths scatter, so no string's scatter is measured \
             for the device.",
        ));
        return h;
    };
    h.push(p(&format!(
        "A string whose length scatters more than the typical string's ({} mm) pulls the \
         position less.",
        mm(Some(typical))
    )));
    let mut t = Table::new(&["string (channel)", "scale, mm", "weight"]);
    for w in weights {
        t.row(vec![
            Cell::num(html::count(u(&w["channel"]))),
            Cell::num(mm(f(&w["scale_mm"]))),
            Cell::num(html::fixed(f(&w["weight"]), 2)),
        ]);
    }
    h.push(t.html());
    h
}
