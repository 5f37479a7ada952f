//! Which figures a calibration report draws, from which stage and session
//! (the drawing itself is [`super::figures`]).

use std::path::Path;

use super::figures::{self, Drawn, Series, XyOptions};
use super::report::{Figure, NnReport};
use super::{CalibrateError, Calibrated, PointErrors};

struct Out<'a> {
    dir: &'a Path,
    figures: Vec<Figure>,
}

impl Out<'_> {
    fn file(&mut self, name: &str, paper: Option<&'static str>, title: &str) -> std::path::PathBuf {
        let path = self.dir.join(format!("{name}.png"));
        self.figures.push(Figure {
            name: name.to_string(),
            paper_figure: paper,
            path: path.display().to_string(),
            title: title.to_string(),
            drawn: None,
        });
        path
    }

    /// Records what the last figure shows.
    fn drawn(&mut self, drawn: Drawn) {
        if let Some(f) = self.figures.last_mut() {
            f.drawn = Some(drawn);
        }
    }
}

/// Error figures with a raw (hundreds of mm) and a calibrated (tenths)
/// series: a log y axis, so that both can be read.
const LOG_Y_BEYOND: XyOptions<'static> = XyOptions {
    log_y_beyond_ratio: Some(20.0),
    integer_x: false,
    mark_x: None,
};

fn order(p: &PointErrors) -> Vec<f64> {
    (1..=p.errors.len()).map(|i| i as f64).collect()
}

fn sweep_figure(
    out: &mut Out<'_>,
    name: &str,
    title: &str,
    nn: &NnReport,
) -> Result<(), CalibrateError> {
    let h: Vec<f64> = nn.sweep.iter().map(|p| p.hidden as f64).collect();
    let v: Vec<f64> = nn.sweep.iter().map(|p| p.validation_mean_mm).collect();
    let t: Vec<f64> = nn.sweep.iter().map(|p| p.train_mean_mm).collect();
    let path = out.file(name, Some("13"), title);
    let chosen = format!("chosen: {} neurons", nn.best_hidden);
    let drawn = figures::lines(
        &path,
        title,
        "neurons in the hidden layer",
        "mean absolute position error, mm",
        &[
            Series {
                label: "validation split",
                x: &h,
                y: &v,
            },
            Series {
                label: "training split",
                x: &h,
                y: &t,
            },
        ],
        XyOptions {
            integer_x: true,
            mark_x: Some((nn.best_hidden as f64, &chosen)),
            ..XyOptions::default()
        },
    )?;
    out.drawn(drawn);
    Ok(())
}

/// Draw every figure into `dir` (created if missing); returns them in order.
pub(super) fn draw_all(c: &Calibrated, dir: &Path) -> Result<Vec<Figure>, CalibrateError> {
    std::fs::create_dir_all(dir).map_err(|source| CalibrateError::Io {
        file: dir.to_path_buf(),
        action: "cannot create the figure directory",
        source,
    })?;
    let mut out = Out {
        dir,
        figures: Vec::new(),
    };
    let r = &c.report;
    let final_name = r.selection.stage.as_str();
    let get = |name: &str| c.points_of(name);

    // Spatial maps (figs. 9, 14, 16) on the training session.
    for (stage, file, paper) in [
        ("raw", "error_map_raw", Some("9")),
        ("identified", "error_map_identified", None),
        ("nn", "error_map_nn", Some("14")),
        ("svr", "error_map_svr", Some("16")),
        (final_name, "error_map_final", None),
    ] {
        if let Some(p) = get(stage) {
            let title = format!("{stage}: absolute position error, training session");
            let path = out.file(file, paper, &title);
            let drawn =
                figures::spatial_error_map(&path, &title, &p.train.tracker, &p.train.errors)?;
            out.drawn(drawn);
        }
    }

    // Error against distance to the origin, before and after (figs. 15, 17).
    if let (Some(raw), Some(fin)) = (get("raw"), get(final_name)) {
        let title = "absolute position error against distance to the origin, training session";
        let path = out.file("error_vs_distance", Some("15, 17"), title);
        let drawn = figures::scatter(
            &path,
            title,
            "distance to the device origin, mm",
            "absolute position error, mm",
            &[
                Series {
                    label: "raw (before)",
                    x: &raw.train.distance_mm,
                    y: &raw.train.errors,
                },
                Series {
                    label: final_name,
                    x: &fin.train.distance_mm,
                    y: &fin.train.errors,
                },
            ],
            LOG_Y_BEYOND,
        )?;
        out.drawn(drawn);
    }
    if let (Some(id), Some(fin)) = (get("identified"), get(final_name)) {
        let title = "after calibration: error against distance to the origin, test session";
        let path = out.file("error_vs_distance_after", None, title);
        let drawn = figures::scatter(
            &path,
            title,
            "distance to the device origin, mm",
            "absolute position error, mm",
            &[
                Series {
                    label: "identified",
                    x: &id.test.distance_mm,
                    y: &id.test.errors,
                },
                Series {
                    label: final_name,
                    x: &fin.test.distance_mm,
                    y: &fin.test.errors,
                },
            ],
            LOG_Y_BEYOND,
        )?;
        out.drawn(drawn);
    }

    // Histograms (fig. 11).
    if let Some(raw) = get("raw") {
        // The test session, as the final histogram: before and after on
        // the same points, both axes from 0 mm.
        let title = "raw absolute position error, test session";
        let path = out.file("histogram_raw", Some("11"), title);
        let drawn = figures::histogram(
            &path,
            title,
            "absolute position error, mm",
            &raw.test.errors,
            40,
            Some(figures::from_zero(&raw.test.errors)),
        )?;
        out.drawn(drawn);
    }
    if let Some(fin) = get(final_name) {
        let title = format!("{final_name}: absolute position error, test session");
        let path = out.file("histogram_final", None, &title);
        let drawn = figures::histogram(
            &path,
            &title,
            "absolute position error, mm",
            &fin.test.errors,
            40,
            Some(figures::from_zero(&fin.test.errors)),
        )?;
        out.drawn(drawn);
    }

    // Before and after on one (logarithmic) axis, the same test session.
    if let (Some(raw), Some(fin)) = (get("raw"), get(final_name)) {
        let title = "absolute position error before and after calibration, test session";
        let path = out.file("histogram_before_after", Some("11"), title);
        let drawn = figures::histogram_pair(
            &path,
            title,
            "absolute position error, mm (log scale)",
            [
                ("raw (before)", &raw.test.errors),
                (final_name, &fin.test.errors),
            ],
            60,
        )?;
        out.drawn(drawn);
    }

    // Error in collection order (fig. 10).
    for (stage, file, paper) in [
        ("raw", "error_order_raw", Some("10")),
        (final_name, "error_order_final", None),
    ] {
        if let Some(p) = get(stage) {
            let title = format!("{stage}: absolute position error in collection order");
            let x = order(&p.train);
            let path = out.file(file, paper, &title);
            let drawn = figures::lines(
                &path,
                &title,
                "capture (training session order)",
                "absolute position error, mm",
                &[Series {
                    label: stage,
                    x: &x,
                    y: &p.train.errors,
                }],
                XyOptions {
                    integer_x: true,
                    ..XyOptions::default()
                },
            )?;
            out.drawn(drawn);
        }
    }

    // Mean error against hidden neurons (fig. 13).
    sweep_figure(
        &mut out,
        "nn_sweep",
        "residual NN: mean error against hidden neurons",
        &r.corrections.nn,
    )?;

    // The paper's black-box procedure.
    if let Some(bb) = &r.blackbox {
        for (stage, file, paper) in [
            ("legacy", "blackbox_error_map_legacy", Some("9")),
            ("blackbox nn", "blackbox_error_map_nn", Some("14")),
            ("blackbox svr", "blackbox_error_map_svr", Some("16")),
        ] {
            if let Some(p) = get(stage) {
                let title = format!("{stage}: absolute position error, training session");
                let path = out.file(file, paper, &title);
                let drawn =
                    figures::spatial_error_map(&path, &title, &p.train.tracker, &p.train.errors)?;
                out.drawn(drawn);
            }
        }
        if let (Some(l), Some(n), Some(s)) =
            (get("legacy"), get("blackbox nn"), get("blackbox svr"))
        {
            let title = "black-box: error against distance to the origin, training session";
            let path = out.file("blackbox_error_vs_distance", Some("15, 17"), title);
            let drawn = figures::scatter(
                &path,
                title,
                "distance to the device origin, mm",
                "absolute position error, mm",
                &[
                    Series {
                        label: "legacy (before)",
                        x: &l.train.distance_mm,
                        y: &l.train.errors,
                    },
                    Series {
                        label: "blackbox nn",
                        x: &n.train.distance_mm,
                        y: &n.train.errors,
                    },
                    Series {
                        label: "blackbox svr",
                        x: &s.train.distance_mm,
                        y: &s.train.errors,
                    },
                ],
                LOG_Y_BEYOND,
            )?;
            out.drawn(drawn);
            let title = "legacy controller: absolute position error, training session";
            let path = out.file("blackbox_histogram_legacy", Some("11"), title);
            let drawn = figures::histogram(
                &path,
                title,
                "absolute position error, mm",
                &l.train.errors,
                40,
                Some(figures::from_zero(&l.train.errors)),
            )?;
            out.drawn(drawn);
            let title = "legacy controller: absolute position error in collection order";
            let x = order(&l.train);
            let path = out.file("blackbox_error_order_legacy", Some("10"), title);
            let drawn = figures::lines(
                &path,
                title,
                "capture (training session order)",
                "absolute position error, mm",
                &[Series {
                    label: "legacy",
                    x: &x,
                    y: &l.train.errors,
                }],
                XyOptions {
                    integer_x: true,
                    ..XyOptions::default()
                },
            )?;
            out.drawn(drawn);
        }
        sweep_figure(
            &mut out,
            "blackbox_nn_sweep",
            "black-box NN: mean error against hidden neurons",
            &bb.nn,
        )?;
    }
    Ok(out.figures)
}
