//! Which figures a calibration report draws, from which stage and session
//! (the drawing itself is [`super::figures`]).

use std::path::Path;

use super::figures::{self, Drawn, Series, XyOptions, XyStyle};
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
    let drawn = figures::xy_chart(
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
        XyStyle::Lines,
        XyOptions {
            integer_x: true,
            mark_x: Some((nn.best_hidden as f64, &chosen)),
            ..XyOptions::default()
        },
    )?;
    out.drawn(drawn);
    Ok(())
}

/// A series of errors against distance to the device origin.
fn by_distance<'a>(label: &'a str, p: &'a PointErrors) -> Series<'a> {
    Series {
        label,
        x: &p.distance_mm,
        y: &p.errors,
    }
}

impl Out<'_> {
    /// Spatial error map (figs. 9, 14, 16) of a stage on the training session.
    fn spatial_map(
        &mut self,
        stage: &str,
        file: &str,
        paper: Option<&'static str>,
        train: &PointErrors,
    ) -> Result<(), CalibrateError> {
        let title = format!("{stage}: absolute position error, training session");
        let path = self.file(file, paper, &title);
        let drawn = figures::spatial_error_map(&path, &title, &train.tracker, &train.errors)?;
        self.drawn(drawn);
        Ok(())
    }

    /// Error against distance to the origin (figs. 15, 17), one series per
    /// stage.
    fn error_vs_distance(
        &mut self,
        file: &str,
        paper: Option<&'static str>,
        title: &str,
        series: &[Series<'_>],
    ) -> Result<(), CalibrateError> {
        let path = self.file(file, paper, title);
        let drawn = figures::xy_chart(
            &path,
            title,
            "distance to the device origin, mm",
            "absolute position error, mm",
            series,
            XyStyle::Points,
            LOG_Y_BEYOND,
        )?;
        self.drawn(drawn);
        Ok(())
    }

    /// Histogram of errors (fig. 11), the x axis from 0 mm.
    fn histogram(
        &mut self,
        file: &str,
        paper: Option<&'static str>,
        title: &str,
        errors: &[f64],
    ) -> Result<(), CalibrateError> {
        let path = self.file(file, paper, title);
        let drawn = figures::histogram(
            &path,
            title,
            "absolute position error, mm",
            errors,
            40,
            Some(figures::from_zero(errors)),
        )?;
        self.drawn(drawn);
        Ok(())
    }

    /// Error in collection order (fig. 10) on the training session.
    fn error_order(
        &mut self,
        file: &str,
        paper: Option<&'static str>,
        title: &str,
        label: &str,
        train: &PointErrors,
    ) -> Result<(), CalibrateError> {
        let x = order(train);
        let path = self.file(file, paper, title);
        let drawn = figures::xy_chart(
            &path,
            title,
            "capture (training session order)",
            "absolute position error, mm",
            &[Series {
                label,
                x: &x,
                y: &train.errors,
            }],
            XyStyle::Lines,
            XyOptions {
                integer_x: true,
                ..XyOptions::default()
            },
        )?;
        self.drawn(drawn);
        Ok(())
    }
}

/// The figures of the residual stages: spatial maps, error against distance,
/// histograms, error in collection order.
fn residual_figures(out: &mut Out<'_>, c: &Calibrated) -> Result<(), CalibrateError> {
    let final_name = c.report.selection.stage.as_str();
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
            out.spatial_map(stage, file, paper, &p.train)?;
        }
    }

    // Error against distance to the origin, before and after (figs. 15, 17).
    if let (Some(raw), Some(fin)) = (get("raw"), get(final_name)) {
        out.error_vs_distance(
            "error_vs_distance",
            Some("15, 17"),
            "absolute position error against distance to the origin, training session",
            &[
                by_distance("raw (before)", &raw.train),
                by_distance(final_name, &fin.train),
            ],
        )?;
    }
    if let (Some(id), Some(fin)) = (get("identified"), get(final_name)) {
        out.error_vs_distance(
            "error_vs_distance_after",
            None,
            "after calibration: error against distance to the origin, test session",
            &[
                by_distance("identified", &id.test),
                by_distance(final_name, &fin.test),
            ],
        )?;
    }

    // Histograms (fig. 11).
    if let Some(raw) = get("raw") {
        // The test session, as the final histogram: before and after on
        // the same points, both axes from 0 mm.
        out.histogram(
            "histogram_raw",
            Some("11"),
            "raw absolute position error, test session",
            &raw.test.errors,
        )?;
    }
    if let Some(fin) = get(final_name) {
        let title = format!("{final_name}: absolute position error, test session");
        out.histogram("histogram_final", None, &title, &fin.test.errors)?;
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
            out.error_order(file, paper, &title, stage, &p.train)?;
        }
    }
    Ok(())
}

/// The figures of the paper's black-box procedure.
fn blackbox_figures(
    out: &mut Out<'_>,
    c: &Calibrated,
    nn: &NnReport,
) -> Result<(), CalibrateError> {
    let get = |name: &str| c.points_of(name);
    for (stage, file, paper) in [
        ("legacy", "blackbox_error_map_legacy", Some("9")),
        ("blackbox nn", "blackbox_error_map_nn", Some("14")),
        ("blackbox svr", "blackbox_error_map_svr", Some("16")),
    ] {
        if let Some(p) = get(stage) {
            out.spatial_map(stage, file, paper, &p.train)?;
        }
    }
    if let (Some(l), Some(n), Some(s)) = (get("legacy"), get("blackbox nn"), get("blackbox svr")) {
        out.error_vs_distance(
            "blackbox_error_vs_distance",
            Some("15, 17"),
            "black-box: error against distance to the origin, training session",
            &[
                by_distance("legacy (before)", &l.train),
                by_distance("blackbox nn", &n.train),
                by_distance("blackbox svr", &s.train),
            ],
        )?;
        out.histogram(
            "blackbox_histogram_legacy",
            Some("11"),
            "legacy controller: absolute position error, training session",
            &l.train.errors,
        )?;
        out.error_order(
            "blackbox_error_order_legacy",
            Some("10"),
            "legacy controller: absolute position error in collection order",
            "legacy",
            &l.train,
        )?;
    }
    sweep_figure(
        out,
        "blackbox_nn_sweep",
        "black-box NN: mean error against hidden neurons",
        nn,
    )
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
    residual_figures(&mut out, c)?;

    // Mean error against hidden neurons (fig. 13).
    if let Some(corrections) = &r.corrections {
        sweep_figure(
            &mut out,
            "nn_sweep",
            "residual NN: mean error against hidden neurons",
            &corrections.nn,
        )?;
    }

    // The paper's black-box procedure.
    if let Some(bb) = &r.blackbox {
        blackbox_figures(&mut out, c, &bb.nn)?;
    }
    Ok(out.figures)
}
