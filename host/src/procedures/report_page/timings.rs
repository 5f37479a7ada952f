//! Where the calibration's time went, and the files it wrote.

use serde_json::Value;

use super::html::{self, f, figure, list, p, s, Html};
use super::svg::{self, Axis, DotSeries, PALETTE};

/// The steps of `timings_s`, in the order they run: key and name.
const STEPS: [(&str, &str); 10] = [
    ("alignment_s", "tracker clock alignment"),
    ("raw_s", "raw stage"),
    ("identification_s", "identification and the loop"),
    ("reference_s", "plain least-squares reference"),
    ("rule_s", "kinematics rule"),
    ("nn_s", "NN sweep and training"),
    ("svr_s", "SVR search and refit"),
    ("selection_s", "choice and refit"),
    ("blackbox_s", "black-box procedure"),
    ("figures_s", "figures"),
];

pub(super) fn section(r: &Value) -> Html {
    let t = &r["timings_s"];
    let mut h = p(&format!(
        "The calibration took {} s of wall-clock time, figures {} s.",
        html::fixed(f(&t["calibration_s"]), 1),
        html::fixed(f(&t["figures_s"]), 1)
    ));
    let steps: Vec<(&str, f64)> = STEPS
        .iter()
        .filter_map(|(key, name)| f(&t[*key]).map(|v| (*name, v)))
        .collect();
    if !steps.is_empty() {
        let names: Vec<String> = steps.iter().map(|s| s.0.to_string()).collect();
        let axis = Axis::linear("wall-clock seconds", steps.iter().map(|s| s.1), true);
        let series = [DotSeries {
            label: "seconds",
            colour: PALETTE[2],
            values: steps.iter().map(|s| Some(s.1)).collect(),
        }];
        let (drawing, _) = svg::dot_chart(&names, &series, &axis, true, "seconds per step");
        h.push(figure(
            drawing,
            Html::default(),
            "Seconds per step of the calibration.",
        ));
    }
    h.push(html::tag("h3", "Files"));
    let files = &r["files"];
    let mut lines = vec![format!(
        "{} (the calibration, which later commands read)",
        s(&files["calibration"])
    )];
    lines.extend(
        list(&files["reports"])
            .iter()
            .map(|v| format!("{} (the JSON report)", s(v))),
    );
    lines.push(format!(
        "{}/{} (the data of this page's figures)",
        s(&files["out_dir"]),
        super::FIGURE_DATA_FILE
    ));
    let pngs = list(&r["figures"]);
    if let Some(first) = pngs.first() {
        let dir = std::path::Path::new(s(&first["path"]))
            .parent()
            .map(|d| d.display().to_string())
            .unwrap_or_default();
        lines.push(format!(
            "{dir}/ ({} figures as PNG, the paper's)",
            pngs.len()
        ));
    }
    h.push(html::bullets(lines.iter().map(String::as_str)));
    h
}
