//! The error of every stage, training and test session, with the plain
//! least-squares reference every calibration is held to; and the figures
//! of how the errors spread, where they are and when they happened.

use serde_json::Value;

use super::data::FigureData;
use super::html::{self, f, figure, list, mm, p, s, u, Cell, Html, Table};
use super::svg::{self, Axis, DotSeries, Plot, Stroke, PALETTE, PANEL_WIDTH};

/// The statistics of a stage's columns, in order: JSON key and heading.
pub(super) const COLUMNS: [(&str, &str); 5] = [
    ("mean_mm", "mean"),
    ("sd_mm", "sd"),
    ("median_mm", "median"),
    ("p95_mm", "p95"),
    ("max_mm", "max"),
];

/// Positive values this many times apart go on a log axis.
const LOG_RATIO: f64 = 20.0;

pub(super) fn section(r: &Value, figures: Option<&FigureData>) -> Html {
    let stages = list(&r["stages"]);
    let mut h = p(
        "The absolute position error (eq. 7) of every stage against the tracker, room frame, \
         in mm: raw is the nominal geometry; the plain least-squares reference is the floor \
         every calibration is held to; each stage after the identified one adds what its name \
         says; the last is the final model.",
    );
    h.push(stage_table(stages, "stage-table"));
    h.push(p(&format!(
        "Why the final model is {}: {}.",
        s(&r["selection"]["stage"]),
        s(&r["selection"]["reason"]).trim_end_matches('.')
    )));
    h.push(stage_chart(stages));
    match figures {
        Some(data) => {
            h.push(spread(data, r));
            h.push(error_map(
                data,
                r["device"]["planar"].as_bool() == Some(true),
            ));
            h.push(along(data));
        }
        None => h.push(super::without_figure_data()),
    }
    let bb = &r["blackbox"];
    if bb.is_object() {
        h.push(html::tag(
            "h3",
            "The paper's black-box procedure, for comparison",
        ));
        h.push(p(&format!(
            "Input: {}; {} mode. Over the rows with both a legacy and a tracker position.",
            s(&bb["input"]),
            s(&bb["mode"])
        )));
        h.push(stage_table(
            list(&r["blackbox"]["stages"]),
            "blackbox-table",
        ));
    }
    h
}

/// A table of stages: name, kind, then the statistics on each session.
/// Each statistic's cell carries `data-key="<session>.<key>"` and each row
/// `data-stage="<index>"`: the browser check reads them back.
pub(super) fn stage_table(stages: &[Value], id: &str) -> Html {
    let n = |session: &str| {
        stages.first().map_or(html::NONE.to_string(), |st| {
            html::count(u(&st[session]["n"]))
        })
    };
    let train = format!("training session (n = {})", n("train"));
    let test = format!("test session (n = {})", n("test"));
    let mut headers = vec!["stage", "kind"];
    for _ in 0..2 {
        headers.extend(COLUMNS.iter().map(|c| c.1));
    }
    let mut t = Table::grouped(&[("", 2), (&train, 5), (&test, 5)], &headers).with_id(id);
    for (i, st) in stages.iter().enumerate() {
        let kind = s(&st["kind"]);
        let mut cells = vec![Cell::text(s(&st["name"])), Cell::text(kind)];
        for session in ["train", "test"] {
            for (key, _) in COLUMNS {
                cells.push(Cell::num(mm(f(&st[session][key]))).keyed(&format!("{session}.{key}")));
            }
        }
        let class = match kind {
            "reference" | "final" => format!(" class=\"{kind}\""),
            _ => String::new(),
        };
        t.row_with(format!("{class} data-stage=\"{i}\""), cells);
    }
    t.html()
}

/// The mean error of every stage on both sessions.
fn stage_chart(stages: &[Value]) -> Html {
    let names: Vec<String> = stages.iter().map(|st| s(&st["name"]).to_string()).collect();
    let mean = |session: &str| -> Vec<Option<f64>> {
        stages.iter().map(|st| f(&st[session]["mean_mm"])).collect()
    };
    let (test, train) = (mean("test"), mean("train"));
    let values: Vec<f64> = test.iter().chain(&train).flatten().copied().collect();
    if values.is_empty() {
        return html::no_figure("No stage has an error to draw.");
    }
    let axis = Axis::errors("mean absolute position error, mm", &values, LOG_RATIO);
    let series = [
        DotSeries {
            label: "test session",
            colour: PALETTE[0],
            values: test,
        },
        DotSeries {
            label: "training session",
            colour: PALETTE[1],
            values: train,
        },
    ];
    let (drawing, _) = svg::dot_chart(&names, &series, &axis, true, "mean error of every stage");
    let legend = svg::legend(series.iter().map(|s| (s.label, s.colour, false, false)));
    figure(
        drawing,
        legend,
        "Mean error of every stage, in pipeline order (a log axis when raw and calibrated \
         errors are far apart).",
    )
}

/// How the test errors spread: the share of rows within each error, for the
/// raw, reference, identified and final stages.
fn spread(data: &FigureData, r: &Value) -> Html {
    let final_name = s(&r["selection"]["stage"]);
    let wanted = [
        "raw",
        crate::model::reference::STAGE_NAME,
        "identified",
        final_name,
    ];
    let chosen: Vec<&super::data::StageQuantiles> = wanted
        .iter()
        .filter_map(|w| {
            data.quantiles
                .iter()
                .find(|q| q.name == *w && !q.test.is_empty())
        })
        .collect();
    if chosen.is_empty() {
        return html::no_figure("No test errors to draw.");
    }
    let all: Vec<f64> = chosen.iter().flat_map(|q| q.test.iter().copied()).collect();
    let x = Axis::errors("absolute position error, mm", &all, LOG_RATIO);
    let y = Axis::linear("test rows within it, %", [0.0, 100.0], true);
    let mut plot = Plot::new(x, y);
    let percents: Vec<f64> = (0..=100).map(f64::from).collect();
    for (k, q) in chosen.iter().enumerate() {
        let stroke = if q.name == "raw" {
            Stroke::Dashed
        } else {
            Stroke::Solid
        };
        plot.line(
            &q.test,
            &percents,
            PALETTE[k % PALETTE.len()],
            stroke,
            Some(&q.name),
        );
    }
    figure(
        plot.svg("share of the test rows within each error"),
        plot.legend(),
        "How the errors spread on the test session: the share of its rows within each error \
         (read across at 50 % for the median, at 95 % for the p95).",
    )
}

/// Where the final model's errors are on the test session: a top view and,
/// for a 3-D device, a front view.
fn error_map(data: &FigureData, planar: bool) -> Html {
    let Some(map) = &data.map else {
        return html::no_figure("No test errors to map.");
    };
    if map.points.is_empty() {
        return html::no_figure("No tracked test row to map.");
    }
    let errors: Vec<f64> = map.points.iter().map(|p| p[3]).collect();
    let top = crate::procedures::calibrate::robust_colour_max(&errors);
    let views: &[(usize, usize, &str)] = if planar {
        &[(0, 1, "top view")]
    } else {
        &[(0, 1, "top view"), (0, 2, "front view")]
    };
    let mut panels = String::new();
    for &(a, b, view) in views {
        let xs: Vec<f64> = map.points.iter().map(|p| p[a]).collect();
        let ys: Vec<f64> = map.points.iter().map(|p| p[b]).collect();
        let axis = |k: usize, v: &[f64]| {
            Axis::linear(
                &format!("{} (room), mm", ["x", "y", "z"][k]),
                v.iter().copied(),
                false,
            )
        };
        let mut plot =
            Plot::new(axis(a, &xs), axis(b, &ys)).equal_aspect(PANEL_WIDTH, (200.0, 420.0));
        plot.coloured_points(&xs, &ys, &errors, top);
        panels.push_str(&plot.svg(&format!("{view} of the test errors")).0);
    }
    let beyond = errors.iter().filter(|e| **e > top).count();
    figure(
        Html::raw(format!(
            "<div class=\"panels\">{panels}</div>{}",
            svg::colour_bar(top, "absolute position error, mm").0
        )),
        Html::default(),
        &format!(
            "Where the final model ({}) errs on the test session: each tracked row at its tracker \
             position, coloured by its error{}{}.",
            map.stage,
            if beyond > 0 {
                format!("; {beyond} beyond the top colour, drawn larger")
            } else {
                String::new()
            },
            if map.points.len() < map.rows {
                format!("; {} of its {} rows, evenly", map.points.len(), map.rows)
            } else {
                String::new()
            }
        ),
    )
}

/// The error along the training session: median and largest of each run of
/// rows, identified and final model.
fn along(data: &FigureData) -> Html {
    if data.along.iter().all(|a| a.line.is_empty()) {
        return html::no_figure("No training errors to draw along the session.");
    }
    let values: Vec<f64> = data
        .along
        .iter()
        .flat_map(|a| a.median_mm.iter().chain(&a.max_mm).copied())
        .collect();
    let x = Axis::linear(
        "line of the training file",
        data.along
            .iter()
            .flat_map(|a| a.line.iter().map(|&l| l as f64)),
        false,
    );
    let y = Axis::errors("absolute position error, mm", &values, LOG_RATIO);
    let mut plot = Plot::new(x, y);
    for (k, a) in data.along.iter().enumerate() {
        let lines: Vec<f64> = a.line.iter().map(|&l| l as f64).collect();
        let colour = PALETTE[k % PALETTE.len()];
        plot.line(
            &lines,
            &a.max_mm,
            colour,
            Stroke::Dashed,
            Some(&format!("{}: largest", a.stage)),
        );
        plot.line(
            &lines,
            &a.median_mm,
            colour,
            Stroke::Solid,
            Some(&format!("{}: median", a.stage)),
        );
    }
    figure(
        plot.svg("error along the training session"),
        plot.legend(),
        "The error along the training session, in the order it was recorded: the median and \
         the largest of each run of rows. A step or a slope here is what a slip or a drift \
         leaves; a lone spike, one bad row.",
    )
}
