//! The corrections chosen and why: the candidates on the selection split,
//! the outliers left out, the NN sweep and the SVR search.

use serde_json::Value;

use super::html::{self, f, figure, list, mm, p, s, sig, u, Cell, Html, Table};
use super::svg::{self, Axis, DotSeries, Plot, Stroke, PALETTE};

/// SVR candidates listed, best first; the others are counted.
const SVR_LISTED: usize = 12;

/// The candidates of the final model: their key in `validation_*_mm` and
/// their name.
const CANDIDATES: [(&str, &str); 4] = [
    ("identified", "string model alone"),
    ("nn", "nn correction"),
    ("svr", "svr correction"),
    ("reference", "plain least squares"),
];

pub(super) fn section(r: &Value) -> Html {
    let sel = &r["selection"];
    let mut h = p(&format!(
        "The final model is {}; calibration.json carries {}. {}.",
        s(&sel["stage"]),
        match s(&sel["correction"]) {
            "none" | "" => "no learned correction".to_string(),
            c => format!("the {c} correction"),
        },
        html::capitalized(s(&sel["reason"]).trim_end_matches('.'))
    ));
    let c = &r["corrections"];
    h.push(candidates(sel, c.is_object()));
    if !c.is_object() {
        h.push(p(
            "No learned correction was trained: the training session is too small for them \
             (see the warnings).",
        ));
        return h;
    }
    h.push(html::tag("h3", "What the corrections learn from"));
    let o = &c["outliers"];
    let lp = &c["learning_points"];
    h.push(html::facts(&[
        ("mode", s(&c["mode"]).to_string()),
        ("input", s(&c["input"]).to_string()),
        (
            "outliers left out (Tukey's box plot)",
            format!(
                "{} of {} (fences {} to {} mm)",
                html::count(u(&o["removed"])),
                html::count(u(&o["points"])),
                mm(f(&o["lower_fence_mm"])),
                mm(f(&o["upper_fence_mm"]))
            ),
        ),
        (
            "points learned from",
            match f(&lp["cell_mm"]) {
                Some(cell) => format!(
                    "{} of {} kept, one per {} mm cell",
                    html::count(u(&lp["used"])),
                    html::count(u(&lp["kept"])),
                    html::fixed(Some(cell), 1)
                ),
                None => format!("all {} kept", html::count(u(&lp["kept"]))),
            },
        ),
        (
            "fit split / selection split",
            format!(
                "{} / {} points",
                html::count(u(&sel["fit_points"])),
                html::count(u(&sel["selection_points"]))
            ),
        ),
    ]));
    h.push(nn(&c["nn"]));
    h.push(svr(&c["svr"]));
    h
}

/// The candidates' errors on the selection split (never the test session);
/// the thresholds a correction is held to when one was `learned`.
fn candidates(sel: &Value, learned: bool) -> Html {
    let chosen = s(&sel["choice"]);
    let names: Vec<String> = CANDIDATES
        .iter()
        .map(|(key, name)| {
            if *key == chosen {
                format!("{name} (chosen)")
            } else {
                (*name).to_string()
            }
        })
        .collect();
    let stat = |which: &str| -> Vec<Option<f64>> {
        CANDIDATES
            .iter()
            .map(|(key, _)| f(&sel[which][*key]))
            .collect()
    };
    let (mean, p95, max) = (
        stat("validation_mean_mm"),
        stat("validation_p95_mm"),
        stat("validation_max_mm"),
    );
    let mut t = Table::new(&["candidate", "mean, mm", "p95, mm", "max, mm"]);
    for (k, name) in names.iter().enumerate() {
        t.row(vec![
            Cell::text(name),
            Cell::num(mm(mean[k])),
            Cell::num(mm(p95[k])),
            Cell::num(mm(max[k])),
        ]);
    }
    let mut h = html::tag("h3", "The candidates on the selection split");
    let scored = format!(
        "Scored on the {} training points held out from fitting (the test session is never \
         used to choose).",
        html::count(u(&sel["selection_points"]))
    );
    h.push(p(&if learned {
        format!(
            "{scored} A correction must lower the string model's mean by {} without raising \
             its p95 by more than {} mm or its max by more than {} mm (their noise).",
            html::percent(f(&sel["min_correction_gain"])),
            mm(f(&sel["noise_p95_mm"])),
            mm(f(&sel["noise_max_mm"]))
        )
    } else {
        format!(
            "{scored} No correction was learned, so none is held to the string model's p95 \
             and max; the string model is held to the plain least-squares reference's mean."
        )
    }));
    h.push(t.html());
    let values: Vec<f64> = mean.iter().chain(&p95).flatten().copied().collect();
    if !values.is_empty() {
        let axis = Axis::linear(
            "error on the selection split, mm",
            values.iter().copied(),
            true,
        );
        let series = [
            DotSeries {
                label: "mean",
                colour: PALETTE[0],
                values: mean,
            },
            DotSeries {
                label: "p95",
                colour: PALETTE[1],
                values: p95,
            },
        ];
        let (drawing, _) = svg::dot_chart(&names, &series, &axis, true, "the candidates' errors");
        h.push(figure(
            drawing,
            svg::legend(series.iter().map(|s| (s.label, s.colour, false, false))),
            "The final model's candidates on the selection split (a dash: not trained).",
        ));
    }
    h
}

/// The NN's hidden-size sweep (the paper's fig. 13).
fn nn(n: &Value) -> Html {
    let mut h = html::tag("h3", "The NN: hidden-size sweep");
    let sweep = list(&n["sweep"]);
    let hidden: Vec<f64> = sweep
        .iter()
        .map(|v| f(&v["hidden"]).unwrap_or(f64::NAN))
        .collect();
    let validation: Vec<f64> = sweep
        .iter()
        .map(|v| f(&v["validation_mean_mm"]).unwrap_or(f64::NAN))
        .collect();
    let train: Vec<f64> = sweep
        .iter()
        .map(|v| f(&v["train_mean_mm"]).unwrap_or(f64::NAN))
        .collect();
    h.push(p(&format!(
        "Chosen: {} hidden neurons ({} epochs, stopped on {}, {} restarts; sweep {} s, final \
         training {} s).",
        html::count(u(&n["best_hidden"])),
        html::count(u(&n["epochs"])),
        stop_reason(&n["stop"]),
        html::count(u(&n["restarts"])),
        html::fixed(f(&n["sweep_seconds"]), 1),
        html::fixed(f(&n["final_seconds"]), 1)
    )));
    if sweep.is_empty() {
        return h;
    }
    let x = Axis::linear("neurons in the hidden layer", hidden.iter().copied(), false);
    let y = Axis::linear(
        "mean absolute position error, mm",
        validation.iter().chain(&train).copied(),
        true,
    );
    let mut plot = Plot::new(x, y);
    plot.line(
        &hidden,
        &validation,
        PALETTE[0],
        Stroke::Solid,
        Some("validation split"),
    );
    plot.points(&hidden, &validation, PALETTE[0], 2.6, None);
    plot.line(
        &hidden,
        &train,
        PALETTE[1],
        Stroke::Dashed,
        Some("training split"),
    );
    if let Some(best) = f(&n["best_hidden"]) {
        plot.vline(best, &format!("chosen: {best}"));
    }
    h.push(figure(
        plot.svg("NN mean error against hidden neurons"),
        plot.legend(),
        "Mean error against the number of hidden neurons (the paper's fig. 13).",
    ));
    h
}

/// Why the NN's training stopped, in words (the report's value as it is
/// when it is no plain name).
fn stop_reason(v: &Value) -> String {
    match v.as_str() {
        Some(name) => name.replace('_', " "),
        None => v.to_string(),
    }
}

/// The SVR's search: the chosen parameters and the candidates, best first.
fn svr(v: &Value) -> Html {
    let mut h = html::tag("h3", "The SVR: parameter search");
    let best = &v["best"];
    let converged: Vec<&str> = list(&v["converged"])
        .iter()
        .map(|c| {
            if c.as_bool() == Some(true) {
                "yes"
            } else {
                "no"
            }
        })
        .collect();
    h.push(p(&format!(
        "Chosen: C = {}, epsilon = {} (standardized output), gamma = {} (standardized inputs); \
         {} support vectors; converged per axis: {}; search {} s, refit {} s.",
        sig(f(&best["c"])),
        sig(f(&best["epsilon"])),
        sig(f(&best["gamma"])),
        html::count(u(&v["support_vectors"])),
        converged.join(", "),
        html::fixed(f(&v["search_seconds"]), 1),
        html::fixed(f(&v["refit_seconds"]), 1)
    )));
    let mut candidates: Vec<&Value> = list(&v["candidates"]).iter().collect();
    candidates.sort_by(|a, b| {
        let m = |c: &Value| f(&c["validation_mean_mm"]).unwrap_or(f64::INFINITY);
        m(a).total_cmp(&m(b))
    });
    if candidates.is_empty() {
        return h;
    }
    let mut t = Table::new(&[
        "C",
        "epsilon",
        "gamma",
        "validation mean, mm",
        "support vectors",
        "seconds",
    ]);
    for c in candidates.iter().take(SVR_LISTED) {
        t.row(vec![
            Cell::num(sig(f(&c["params"]["c"]))),
            Cell::num(sig(f(&c["params"]["epsilon"]))),
            Cell::num(sig(f(&c["params"]["gamma"]))),
            Cell::num(mm(f(&c["validation_mean_mm"]))),
            Cell::num(html::count(u(&c["support_vectors"]))),
            Cell::num(html::fixed(f(&c["seconds"]), 2)),
        ]);
    }
    h.push(t.html());
    if candidates.len() > SVR_LISTED {
        h.push(p(&format!(
            "The best {SVR_LISTED} of {} candidates; report.json has them all.",
            candidates.len()
        )));
    }
    h
}
