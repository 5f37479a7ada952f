//! Figures of the calibration report, as PNG files (plotters, bitmap backend).
//!
//! The paper's figures: spatial error map (figs. 9, 14, 16), error against
//! distance to the origin before and after (figs. 15, 17), histogram (fig. 11),
//! error in collection order (fig. 10), mean error against hidden neurons
//! (fig. 13); and the diagnosis figure: a residual against the variable it
//! follows.
//!
//! Text is drawn with a font compiled into the binary (the Ubuntu Light face
//! that `epaint_default_fonts` ships), so figures need no system font stack.

use crate::data::output::PartialFile;
use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::coord::ranged1d::ValueFormatter;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

/// A figure that could not be written; names the file.
#[derive(Debug, thiserror::Error)]
#[error("cannot draw figure {path}: {message}")]
pub struct FigureError {
    pub path: PathBuf,
    pub message: String,
}

const SIZE: (u32, u32) = (900, 640);

/// What a figure shows, from the data it was drawn with: its axes' ranges
/// and, for the spatial map, its colour scale (the report lists it beside
/// each figure, and tests assert it).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Drawn {
    /// x axis range (the histogram's error range, mm).
    pub x: (f64, f64),
    /// y axis range (the histogram's count range).
    pub y: (f64, f64),
    /// The y axis is logarithmic.
    pub log_y: bool,
    /// The x axis is logarithmic (the before/after histogram).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub log_x: bool,
    /// Spatial map: the error the top colour stands for, mm, and how many
    /// points lie beyond it (drawn in that colour, larger).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub colour_max_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub beyond_colour_max: Option<usize>,
    /// An x value marked on the figure (the chosen hidden size).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub marked_x: Option<f64>,
}

/// How an x-y figure is drawn beyond its series.
#[derive(Clone, Copy, Debug, Default)]
pub struct XyOptions<'a> {
    /// A logarithmic y axis when the series' medians are this many times
    /// apart or more (one series of hundreds of mm, another of tenths).
    pub log_y_beyond_ratio: Option<f64>,
    /// Integer ticks on x (counts, neuron numbers).
    pub integer_x: bool,
    /// A vertical mark at this x, with its label.
    pub mark_x: Option<(f64, &'a str)>,
}

/// The colour scale of a spatial map: the 98th percentile of the errors,
/// or the maximum when it is no more than twice that (one far point must
/// not turn every other point the same blue).
pub fn robust_colour_max(errors_mm: &[f64]) -> f64 {
    let mut e: Vec<f64> = errors_mm
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    if e.is_empty() {
        return 1.0;
    }
    e.sort_by(f64::total_cmp);
    let max = e[e.len() - 1];
    let p98 = e[((0.98 * e.len() as f64).ceil() as usize).clamp(1, e.len()) - 1];
    let top = if max <= 2.0 * p98 { max } else { p98 };
    top.max(1e-9)
}

/// A histogram's x range from 0 to just past the largest finite value.
pub fn from_zero(values: &[f64]) -> (f64, f64) {
    let max = values
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max);
    (0.0, (1.05 * max).max(1e-9))
}

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font bytes are a valid TTF shipped by the crate; registration
        // can only fail on malformed data, which would show as missing text.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        );
    });
}

fn fail(path: &Path, e: impl std::fmt::Display) -> FigureError {
    FigureError {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Range of finite values with a margin; (0, 1) when there are none.
fn span(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-9);
    (lo - pad, hi + pad)
}

fn palette(i: usize) -> RGBColor {
    const COLORS: [RGBColor; 6] = [
        RGBColor(200, 40, 40),
        RGBColor(30, 90, 200),
        RGBColor(20, 150, 60),
        RGBColor(200, 120, 0),
        RGBColor(120, 40, 170),
        RGBColor(0, 150, 160),
    ];
    COLORS[i % COLORS.len()]
}

/// Error magnitude to colour: blue (low) to red (high), as the paper's maps.
fn heat(t: f64) -> RGBColor {
    let t = t.clamp(0.0, 1.0);
    let r = (255.0 * (1.5 * t).min(1.0)) as u8;
    let b = (255.0 * (1.5 * (1.0 - t)).min(1.0)) as u8;
    let g = (255.0 * (1.0 - (2.0 * t - 1.0).abs()) * 0.8) as u8;
    RGBColor(r, g, b)
}

/// Spatial error map (paper figs. 9, 14, 16): each reference position as a
/// point in 3D coloured by its error.
pub fn spatial_error_map(
    path: &Path,
    title: &str,
    positions: &[[f64; 3]],
    errors_mm: &[f64],
) -> Result<Drawn, FigureError> {
    register_font();
    let partial = PartialFile::beside(path).map_err(|e| fail(path, e))?;
    let target = partial.path().to_path_buf();
    let root = BitMapBackend::new(&target, SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(path, e))?;
    let (main, bar) = root.split_horizontally(SIZE.0 - 110);
    let x = span(positions.iter().map(|p| p[0]));
    let y = span(positions.iter().map(|p| p[1]));
    let z = span(positions.iter().map(|p| p[2]));
    let emax = robust_colour_max(errors_mm);
    let beyond = errors_mm.iter().filter(|e| **e > emax).count();
    let mut chart = ChartBuilder::on(&main)
        .caption(title, ("sans-serif", 22))
        .margin(10)
        .build_cartesian_3d(x.0..x.1, z.0..z.1, y.0..y.1)
        .map_err(|e| fail(path, e))?;
    chart.with_projection(|mut p| {
        p.pitch = 0.35;
        p.yaw = 0.6;
        p.scale = 0.85;
        p.into_matrix()
    });
    chart
        .configure_axes()
        .x_formatter(&|v| format!("x {v:.0} mm"))
        .y_formatter(&|v| format!("z {v:.0} mm"))
        .z_formatter(&|v| format!("y {v:.0} mm"))
        .draw()
        .map_err(|e| fail(path, e))?;
    chart
        .draw_series(positions.iter().zip(errors_mm).map(|(p, e)| {
            let size = if *e > emax { 4 } else { 2 };
            Circle::new((p[0], p[2], p[1]), size, heat(e / emax).filled())
        }))
        .map_err(|e| fail(path, e))?;
    // Colour bar.
    let steps = 50;
    let mut bar_chart = ChartBuilder::on(&bar)
        .margin_top(60)
        .margin_bottom(60)
        .y_label_area_size(60)
        .caption(
            if beyond > 0 {
                format!("error mm ({beyond} beyond)")
            } else {
                "error mm".to_string()
            },
            ("sans-serif", 14),
        )
        .build_cartesian_2d(0.0..1.0, 0.0..emax)
        .map_err(|e| fail(path, e))?;
    bar_chart
        .configure_mesh()
        .disable_x_mesh()
        .disable_x_axis()
        .y_labels(8)
        .y_label_style(("sans-serif", 14))
        .draw()
        .map_err(|e| fail(path, e))?;
    bar_chart
        .draw_series((0..steps).map(|i| {
            let lo = emax * i as f64 / steps as f64;
            let hi = emax * (i + 1) as f64 / steps as f64;
            Rectangle::new(
                [(0.0, lo), (1.0, hi)],
                heat(i as f64 / steps as f64).filled(),
            )
        }))
        .map_err(|e| fail(path, e))?;
    root.present().map_err(|e| fail(path, e))?;
    partial.commit(path).map_err(|e| fail(path, e))?;
    Ok(Drawn {
        x,
        y: (0.0, emax),
        log_y: false,
        log_x: false,
        colour_max_mm: Some(emax),
        beyond_colour_max: Some(beyond),
        marked_x: None,
    })
}

/// One named set of (x, y) points of a scatter or line figure.
pub struct Series<'a> {
    pub label: &'a str,
    pub x: &'a [f64],
    pub y: &'a [f64],
}

/// How an x-y chart draws its series.
#[derive(Clone, Copy, PartialEq)]
pub enum XyStyle {
    /// A scatter (e.g. error against distance to the origin before and
    /// after calibration, paper figs. 15 and 17).
    Points,
    /// Lines, with markers when a series has few points (e.g. error in
    /// collection order, paper fig. 10; mean error against hidden neurons,
    /// fig. 13).
    Lines,
}

/// The y axis of an x-y figure: logarithmic when the series' medians are
/// [`XyOptions::log_y_beyond_ratio`] apart, and its range.
fn xy_y_axis(series: &[Series<'_>], options: &XyOptions<'_>) -> (bool, (f64, f64)) {
    let medians: Vec<f64> = series
        .iter()
        .map(|s| {
            let mut y: Vec<f64> = s.y.iter().copied().filter(|v| v.is_finite()).collect();
            crate::data::stats::median(&mut y)
        })
        .filter(|m| m.is_finite() && *m > 0.0)
        .collect();
    let log_y = options.log_y_beyond_ratio.is_some_and(|r| {
        let lo = medians.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = medians.iter().cloned().fold(0.0, f64::max);
        medians.len() >= 2 && hi >= r * lo
    });
    let y = if log_y {
        // Positive values only on a log axis; a decade of room below.
        let (lo, hi) = series
            .iter()
            .flat_map(|s| s.y.iter().copied())
            .filter(|v| v.is_finite() && *v > 0.0)
            .fold((f64::INFINITY, 0.0f64), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            });
        (lo.max(1e-6) / 1.5, hi * 1.5)
    } else {
        span(series.iter().flat_map(|s| s.y.iter().copied()))
    };
    (log_y, y)
}

/// What [`xy_chart`] draws on its chart, whichever the y axis' scale.
struct XyChart<'a> {
    path: &'a Path,
    x_label: &'a str,
    y_label: &'a str,
    series: &'a [Series<'a>],
    style: XyStyle,
    options: XyOptions<'a>,
    x: (f64, f64),
    y: (f64, f64),
    log_y: bool,
}

/// The mesh, the series, the x mark and the legend of an x-y figure on its
/// chart (a linear or a logarithmic y axis).
fn draw_xy<'a, 'b: 'a, Y>(
    mut chart: ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, Y>>,
    xy: &XyChart<'_>,
) -> Result<(), FigureError>
where
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let (path, style, log_y, x, y) = (xy.path, xy.style, xy.log_y, xy.x, xy.y);
    let integer_x = xy.options.integer_x;
    let x_ticks = if integer_x {
        ((x.1 - x.0).round() as usize).clamp(2, 25)
    } else {
        10
    };
    let x_format = move |v: &f64| {
        if integer_x {
            format!("{v:.0}")
        } else {
            format!("{v}")
        }
    };
    chart
        .configure_mesh()
        .x_desc(xy.x_label)
        .y_desc(xy.y_label)
        .x_labels(x_ticks)
        .x_label_formatter(&x_format)
        .draw()
        .map_err(|e| fail(path, e))?;
    for (i, s) in xy.series.iter().enumerate() {
        let color = palette(i);
        let points: Vec<(f64, f64)> =
            s.x.iter()
                .copied()
                .zip(s.y.iter().copied())
                .filter(|p| !log_y || p.1 > 0.0)
                .collect();
        let markers = style == XyStyle::Points || points.len() <= 60;
        let radius = if style == XyStyle::Points { 2 } else { 3 };
        if style == XyStyle::Lines {
            chart
                .draw_series(LineSeries::new(points.clone(), color.stroke_width(1)))
                .map_err(|e| fail(path, e))?
                .label(s.label)
                .legend(move |(a, b)| PathElement::new(vec![(a, b), (a + 16, b)], color));
        }
        if markers {
            let drawn = chart
                .draw_series(
                    points
                        .into_iter()
                        .map(move |p| Circle::new(p, radius, color.filled())),
                )
                .map_err(|e| fail(path, e))?;
            if style == XyStyle::Points {
                drawn
                    .label(s.label)
                    .legend(move |(a, b)| Circle::new((a + 8, b), 4, color.filled()));
            }
        }
    }
    if let Some((at, label)) = xy.options.mark_x {
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![(at, y.0), (at, y.1)],
                BLACK.stroke_width(2),
            )))
            .map_err(|e| fail(path, e))?
            .label(label)
            .legend(move |(a, b)| PathElement::new(vec![(a, b), (a + 16, b)], BLACK));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(path, e))?;
    Ok(())
}

/// An x-y chart of several series, drawn as `style` says.
pub fn xy_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
    style: XyStyle,
    options: XyOptions<'_>,
) -> Result<Drawn, FigureError> {
    register_font();
    let partial = PartialFile::beside(path).map_err(|e| fail(path, e))?;
    let target = partial.path().to_path_buf();
    let root = BitMapBackend::new(&target, SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(path, e))?;
    let x = span(series.iter().flat_map(|s| s.x.iter().copied()));
    let (log_y, y) = xy_y_axis(series, &options);
    let mut builder = ChartBuilder::on(&root);
    builder
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(65);
    let xy = XyChart {
        path,
        x_label,
        y_label,
        series,
        style,
        options,
        x,
        y,
        log_y,
    };
    if log_y {
        draw_xy(
            builder
                .build_cartesian_2d(x.0..x.1, (y.0..y.1).log_scale())
                .map_err(|e| fail(path, e))?,
            &xy,
        )?;
    } else {
        draw_xy(
            builder
                .build_cartesian_2d(x.0..x.1, y.0..y.1)
                .map_err(|e| fail(path, e))?,
            &xy,
        )?;
    }
    root.present().map_err(|e| fail(path, e))?;
    partial.commit(path).map_err(|e| fail(path, e))?;
    Ok(Drawn {
        x,
        y,
        log_y,
        log_x: false,
        colour_max_mm: None,
        beyond_colour_max: None,
        marked_x: options.mark_x.map(|m| m.0),
    })
}

/// Frequency histogram of errors (paper fig. 11).
pub fn histogram(
    path: &Path,
    title: &str,
    x_label: &str,
    values: &[f64],
    bins: usize,
    x_range: Option<(f64, f64)>,
) -> Result<Drawn, FigureError> {
    register_font();
    let bins = bins.max(1);
    let (lo, hi) = x_range.unwrap_or_else(|| span(values.iter().copied()));
    let width = (hi - lo) / bins as f64;
    let mut counts = vec![0usize; bins];
    for v in values.iter().filter(|v| v.is_finite()) {
        let b = (((v - lo) / width).max(0.0) as usize).min(bins - 1);
        counts[b] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(1).max(1) as f64 * 1.05;
    let partial = PartialFile::beside(path).map_err(|e| fail(path, e))?;
    let target = partial.path().to_path_buf();
    let root = BitMapBackend::new(&target, SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(path, e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(65)
        .build_cartesian_2d(lo..hi, 0.0..top)
        .map_err(|e| fail(path, e))?;
    // Whole counts on the y axis.
    let top_count = counts.iter().copied().max().unwrap_or(1).max(1);
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc("count")
        .y_labels((top_count + 1).min(10))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .draw()
        .map_err(|e| fail(path, e))?;
    chart
        .draw_series(counts.iter().enumerate().map(|(i, &c)| {
            let a = lo + width * i as f64;
            Rectangle::new([(a, 0.0), (a + width, c as f64)], palette(1).filled())
        }))
        .map_err(|e| fail(path, e))?;
    root.present().map_err(|e| fail(path, e))?;
    partial.commit(path).map_err(|e| fail(path, e))?;
    Ok(Drawn {
        x: (lo, hi),
        y: (0.0, top),
        ..Drawn::default()
    })
}

/// Two error distributions on one logarithmic error axis (bins equal in
/// log scale), overlaid: the errors before calibration (hundreds of mm) and
/// after (tenths) of the same session, each readable.
pub fn histogram_pair(
    path: &Path,
    title: &str,
    x_label: &str,
    series: [(&str, &[f64]); 2],
    bins: usize,
) -> Result<Drawn, FigureError> {
    register_font();
    let bins = bins.max(2);
    let positive = || {
        series
            .iter()
            .flat_map(|(_, v)| v.iter().copied())
            .filter(|v| v.is_finite() && *v > 0.0)
    };
    let lo = positive().fold(f64::INFINITY, f64::min);
    let hi = positive().fold(0.0f64, f64::max);
    let (lo, hi) = if lo.is_finite() && hi > lo {
        (lo / 1.2, hi * 1.2)
    } else {
        (1e-3, 1.0)
    };
    let (llo, lhi) = (lo.log10(), hi.log10());
    let step = (lhi - llo) / bins as f64;
    let counts: Vec<Vec<usize>> = series
        .iter()
        .map(|(_, values)| {
            let mut c = vec![0usize; bins];
            for v in values.iter().filter(|v| v.is_finite() && **v > 0.0) {
                let b = (((v.log10() - llo) / step).max(0.0) as usize).min(bins - 1);
                c[b] += 1;
            }
            c
        })
        .collect();
    let top_count = counts.iter().flatten().copied().max().unwrap_or(1).max(1);
    let top = top_count as f64 * 1.05;
    let partial = PartialFile::beside(path).map_err(|e| fail(path, e))?;
    let target = partial.path().to_path_buf();
    let root = BitMapBackend::new(&target, SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(path, e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(65)
        .build_cartesian_2d((lo..hi).log_scale(), 0.0..top)
        .map_err(|e| fail(path, e))?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc("count")
        .y_labels((top_count + 1).min(10))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .draw()
        .map_err(|e| fail(path, e))?;
    for (i, ((label, _), c)) in series.iter().zip(&counts).enumerate() {
        let color = palette(i);
        chart
            .draw_series(c.iter().enumerate().map(|(b, &n)| {
                let a = 10f64.powf(llo + step * b as f64);
                let z = 10f64.powf(llo + step * (b + 1) as f64);
                Rectangle::new([(a, 0.0), (z, n as f64)], color.mix(0.6).filled())
            }))
            .map_err(|e| fail(path, e))?
            .label(*label)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], color.filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperMiddle)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(path, e))?;
    root.present().map_err(|e| fail(path, e))?;
    partial.commit(path).map_err(|e| fail(path, e))?;
    Ok(Drawn {
        x: (lo, hi),
        y: (0.0, top),
        log_x: true,
        ..Drawn::default()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_figure_is_written() {
        let dir = std::env::temp_dir().join(format!("spidar-fig-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let pos: Vec<[f64; 3]> = (0..100)
            .map(|i| [i as f64, (i * 7 % 13) as f64, (i * 3 % 11) as f64])
            .collect();
        let err: Vec<f64> = (0..100).map(|i| (i % 17) as f64).collect();
        let idx: Vec<f64> = (0..100).map(|i| i as f64).collect();
        spatial_error_map(&dir.join("map.png"), "map", &pos, &err).unwrap();
        let s = [Series {
            label: "raw",
            x: &idx,
            y: &err,
        }];
        xy_chart(
            &dir.join("s.png"),
            "scatter",
            "x",
            "y",
            &s,
            XyStyle::Points,
            XyOptions::default(),
        )
        .unwrap();
        xy_chart(
            &dir.join("l.png"),
            "lines",
            "x",
            "y",
            &s,
            XyStyle::Lines,
            XyOptions::default(),
        )
        .unwrap();
        histogram(&dir.join("h.png"), "hist", "mm", &err, 20, None).unwrap();
        let big: Vec<f64> = err.iter().map(|e| 100.0 * (e + 1.0)).collect();
        let small: Vec<f64> = err.iter().map(|e| 0.01 * (e + 1.0)).collect();
        let d = histogram_pair(
            &dir.join("hp.png"),
            "pair",
            "mm",
            [("before", &big), ("after", &small)],
            30,
        )
        .unwrap();
        assert!(d.log_x && d.x.0 < 0.01 && d.x.1 > 1700.0, "{d:?}");
        for f in ["map.png", "s.png", "l.png", "h.png", "hp.png"] {
            let len = std::fs::metadata(dir.join(f)).unwrap().len();
            assert!(len > 1000, "{f} is {len} bytes");
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn unwritable_path_is_an_error_naming_it() {
        let e = histogram(
            Path::new("/nonexistent-dir/x.png"),
            "t",
            "mm",
            &[1.0, 2.0],
            4,
            None,
        )
        .unwrap_err();
        assert!(e.to_string().contains("/nonexistent-dir/x.png"));
    }
}
