//! Figures drawn for the page as inline SVG: axes with ticks and units,
//! lines, points, a dot chart of named rows and a colour scale, in a
//! `viewBox` that scales to the page's width (a phone's too).
//!
//! Every data mark carries `class="mark"`, which the browser check counts
//! to tell a drawn figure from an empty frame. Text is escaped; nothing
//! refers outside the page.

use std::fmt::Write as _;

use super::html::{escape, Html};

/// The drawing's width in SVG units: at a phone's width (about 370 CSS
/// pixels for the figure) its 12-unit text reads at about 11 pixels, at the
/// page's widest (544) at 16.
pub(super) const WIDTH: f64 = 400.0;
/// Height of an x-y plot.
pub(super) const HEIGHT: f64 = 300.0;
/// Width of one panel of several side by side (small multiples, a map's
/// views): as wide as it is shown on the page, so its text reads as the
/// others'.
pub(super) const PANEL_WIDTH: f64 = 280.0;
const LEFT: f64 = 62.0;
const RIGHT: f64 = 20.0;
const TOP: f64 = 12.0;
const BOTTOM: f64 = 46.0;

/// Colour-blind-safe colours (Okabe and Ito), in the order series take them.
pub(super) const PALETTE: [&str; 7] = [
    "#0072b2", "#d55e00", "#009e73", "#cc79a7", "#e69f00", "#56b4e9", "#444444",
];
/// Points drawn behind the others (a "before").
pub(super) const MUTED: &str = "#b8b8b8";

/// How an axis maps values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Scale {
    Linear,
    Log,
}

/// One axis: its label (with the unit), scale and range.
#[derive(Clone, Debug)]
pub(super) struct Axis {
    pub label: String,
    pub scale: Scale,
    pub lo: f64,
    pub hi: f64,
}

impl Axis {
    /// A linear axis over `values` widened to round ticks; `from_zero`
    /// starts it at 0 (errors, counts).
    pub fn linear(label: &str, values: impl IntoIterator<Item = f64>, from_zero: bool) -> Axis {
        let (mut lo, mut hi) = finite_range(values);
        if from_zero {
            lo = lo.min(0.0);
        }
        if !(lo.is_finite() && hi.is_finite()) {
            (lo, hi) = (0.0, 1.0);
        }
        if hi - lo <= 1e-12 * hi.abs().max(1.0) {
            let pad = (hi.abs() * 0.1).max(1e-3);
            (lo, hi) = (lo - pad, hi + pad);
        }
        // Ends on a finer step than the ticks': a range is not stretched
        // by up to a whole tick interval.
        let step = nice_step((hi - lo) / 8.0);
        Axis {
            label: label.to_string(),
            scale: Scale::Linear,
            lo: (lo / step).floor() * step,
            hi: (hi / step).ceil() * step,
        }
    }

    /// A logarithmic axis over the positive `values`, whole decades.
    pub fn log(label: &str, values: impl IntoIterator<Item = f64>) -> Axis {
        let (lo, hi) = finite_range(values.into_iter().filter(|v| *v > 0.0));
        let (lo, hi) = if lo.is_finite() && hi.is_finite() {
            (lo, hi)
        } else {
            (0.1, 1.0)
        };
        let mut lo = 10f64.powf(lo.log10().floor());
        let mut hi = 10f64.powf(hi.log10().ceil());
        if hi <= lo {
            hi = lo * 10.0;
        }
        if hi / lo > 1e8 {
            lo = hi / 1e8;
        }
        Axis {
            label: label.to_string(),
            scale: Scale::Log,
            lo,
            hi,
        }
    }

    /// Log when the positive values span `ratio` or more, else linear from 0.
    pub fn errors(label: &str, values: &[f64], ratio: f64) -> Axis {
        let (lo, hi) = finite_range(values.iter().copied().filter(|v| *v > 0.0));
        if lo.is_finite() && hi / lo >= ratio {
            Axis::log(label, values.iter().copied())
        } else {
            Axis::linear(label, values.iter().copied(), true)
        }
    }

    /// Where `v` falls, 0 at `lo` and 1 at `hi`; `None` off a log axis.
    fn fraction(&self, v: f64) -> Option<f64> {
        if !v.is_finite() {
            return None;
        }
        match self.scale {
            Scale::Linear => Some((v - self.lo) / (self.hi - self.lo)),
            Scale::Log if v > 0.0 => Some((v / self.lo).ln() / (self.hi / self.lo).ln()),
            Scale::Log => None,
        }
    }

    /// The tick values and their labels.
    fn ticks(&self) -> Vec<(f64, String)> {
        match self.scale {
            Scale::Linear => {
                let step = nice_step((self.hi - self.lo) / 5.0);
                let first = (self.lo / step).ceil() as i64;
                let last = (self.hi / step).floor() as i64;
                let decimals = (-step.log10().floor()).max(0.0) as usize;
                (first..=last)
                    .map(|k| {
                        let v = k as f64 * step;
                        (v, tick_label(v, decimals))
                    })
                    .collect()
            }
            Scale::Log => {
                let decades = (self.hi / self.lo).log10().round() as i32;
                let first = self.lo.log10().round() as i32;
                let steps: &[f64] = if decades <= 2 {
                    &[1.0, 2.0, 5.0]
                } else {
                    &[1.0]
                };
                let every = (decades / 6 + 1).max(1);
                let mut ticks = Vec::new();
                for d in (first..=first + decades).step_by(every as usize) {
                    for m in steps {
                        let v = m * 10f64.powi(d);
                        if v <= self.hi * (1.0 + 1e-9) {
                            ticks.push((v, log_label(v)));
                        }
                    }
                }
                ticks
            }
        }
    }
}

/// The range of the finite values (infinite when there are none).
fn finite_range(values: impl IntoIterator<Item = f64>) -> (f64, f64) {
    values
        .into_iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        })
}

/// 1, 2 or 5 times a power of ten, at least `raw`.
pub(super) fn nice_step(raw: f64) -> f64 {
    if !(raw.is_finite() && raw > 0.0) {
        return 1.0;
    }
    let magnitude = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * magnitude)
        .find(|s| *s >= raw * (1.0 - 1e-9))
        .unwrap_or(10.0 * magnitude)
}

fn tick_label(v: f64, decimals: usize) -> String {
    let v = if v.abs() < 1e-12 { 0.0 } else { v };
    if v.abs() >= 1e5 {
        format!("{v:.0e}")
    } else {
        format!("{v:.decimals$}")
    }
}

fn log_label(v: f64) -> String {
    if (1e-3..1e5).contains(&v) {
        let s = format!("{v:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{v:.0e}")
    }
}

/// One entry of a figure's legend.
struct Key {
    label: String,
    colour: String,
    line: bool,
    dashed: bool,
}

/// An x-y plot being drawn.
pub(super) struct Plot {
    x: Axis,
    y: Axis,
    width: f64,
    height: f64,
    body: String,
    keys: Vec<Key>,
    marks: usize,
}

/// How a line is stroked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Stroke {
    Solid,
    Dashed,
}

impl Plot {
    pub fn new(x: Axis, y: Axis) -> Plot {
        Plot {
            x,
            y,
            width: WIDTH,
            height: HEIGHT,
            body: String::new(),
            keys: Vec::new(),
            marks: 0,
        }
    }

    /// A plot of another size (a panel, a map).
    pub fn with_size(mut self, width: f64, height: f64) -> Plot {
        self.width = width;
        self.height = height;
        self
    }

    /// A panel whose axes keep one scale (a map): its height follows the
    /// ranges, within `lo..hi`.
    pub fn equal_aspect(self, width: f64, (lo, hi): (f64, f64)) -> Plot {
        let ratio = (self.y.hi - self.y.lo) / (self.x.hi - self.x.lo);
        let inner = (width - LEFT - RIGHT) * ratio;
        let height = (inner + TOP + BOTTOM).clamp(lo, hi);
        self.with_size(width, height)
    }

    fn px(&self, v: f64) -> Option<f64> {
        let f = self.x.fraction(v)?;
        (-1e-6..=1.0 + 1e-6)
            .contains(&f)
            .then_some(LEFT + f * (self.width - LEFT - RIGHT))
    }

    fn py(&self, v: f64) -> Option<f64> {
        let f = self.y.fraction(v)?;
        let h = self.height - TOP - BOTTOM;
        (-1e-6..=1.0 + 1e-6)
            .contains(&f)
            .then_some(TOP + (1.0 - f) * h)
    }

    fn key(&mut self, label: Option<&str>, colour: &str, line: bool, dashed: bool) {
        if let Some(label) = label {
            self.keys.push(Key {
                label: label.to_string(),
                colour: colour.to_string(),
                line,
                dashed,
            });
        }
    }

    /// A line through the points in order, broken where a value is missing
    /// or off the axes.
    pub fn line(
        &mut self,
        xs: &[f64],
        ys: &[f64],
        colour: &str,
        stroke: Stroke,
        label: Option<&str>,
    ) {
        let mut d = String::new();
        let mut pen_down = false;
        for (&x, &y) in xs.iter().zip(ys) {
            match (self.px(x), self.py(y)) {
                (Some(px), Some(py)) => {
                    let _ = write!(d, "{}{px:.1},{py:.1}", if pen_down { "L" } else { "M" });
                    pen_down = true;
                }
                _ => pen_down = false,
            }
        }
        if d.is_empty() {
            return;
        }
        let dash = if stroke == Stroke::Dashed {
            " stroke-dasharray=\"5 3\""
        } else {
            ""
        };
        let _ = write!(
            self.body,
            "<path class=\"mark\" d=\"{d}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.8\"{dash}/>"
        );
        self.marks += 1;
        self.key(label, colour, true, stroke == Stroke::Dashed);
    }

    /// Points of one colour.
    pub fn points(
        &mut self,
        xs: &[f64],
        ys: &[f64],
        colour: &str,
        radius: f64,
        label: Option<&str>,
    ) {
        let mut g = String::new();
        for (&x, &y) in xs.iter().zip(ys) {
            if let (Some(px), Some(py)) = (self.px(x), self.py(y)) {
                let _ = write!(g, "<circle cx=\"{px:.1}\" cy=\"{py:.1}\" r=\"{radius}\"/>");
            }
        }
        if g.is_empty() {
            return;
        }
        let _ = write!(
            self.body,
            "<g class=\"mark\" fill=\"{colour}\" fill-opacity=\"0.75\">{g}</g>"
        );
        self.marks += 1;
        self.key(label, colour, false, false);
    }

    /// Points coloured by `values` on [`colour_of`]'s scale up to `top`
    /// (beyond it: the top colour, drawn larger).
    pub fn coloured_points(&mut self, xs: &[f64], ys: &[f64], values: &[f64], top: f64) {
        let mut g = String::new();
        let mut order: Vec<usize> = (0..values.len().min(xs.len()).min(ys.len())).collect();
        // The largest errors are drawn last, on top.
        order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
        for i in order {
            if let (Some(px), Some(py)) = (self.px(xs[i]), self.py(ys[i])) {
                let t = values[i] / top;
                let r = if t > 1.0 { 3.6 } else { 2.4 };
                let _ = write!(
                    g,
                    "<circle cx=\"{px:.1}\" cy=\"{py:.1}\" r=\"{r}\" fill=\"{}\"/>",
                    colour_of(t)
                );
            }
        }
        if g.is_empty() {
            return;
        }
        let _ = write!(self.body, "<g class=\"mark\">{g}</g>");
        self.marks += 1;
    }

    /// A vertical mark at `x` with its label.
    pub fn vline(&mut self, x: f64, label: &str) {
        let Some(px) = self.px(x) else { return };
        let bottom = self.height - BOTTOM;
        let _ = write!(
            self.body,
            "<line x1=\"{px:.1}\" y1=\"{TOP}\" x2=\"{px:.1}\" y2=\"{bottom}\" stroke=\"#222\" stroke-dasharray=\"2 3\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" class=\"note\">{}</text>",
            px + 4.0,
            TOP + 12.0,
            escape(label)
        );
    }

    /// A horizontal reference line at `y` with its label.
    pub fn hline(&mut self, y: f64, label: &str) {
        let Some(py) = self.py(y) else { return };
        let _ = write!(
            self.body,
            "<line x1=\"{LEFT}\" y1=\"{py:.1}\" x2=\"{:.1}\" y2=\"{py:.1}\" stroke=\"#222\" stroke-dasharray=\"2 3\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" class=\"note\" text-anchor=\"end\">{}</text>",
            self.width - RIGHT,
            self.width - RIGHT - 2.0,
            py - 4.0,
            escape(label)
        );
    }

    /// The drawing: frame, grid, ticks, axis labels, the marks.
    pub fn svg(&self, description: &str) -> Html {
        let (w, h) = (self.width, self.height);
        let mut s = format!(
            "<svg viewBox=\"0 0 {w} {h:.0}\" role=\"img\" aria-label=\"{}\" xmlns=\"http://www.w3.org/2000/svg\">",
            escape(description)
        );
        let (x0, x1, y0, y1) = (LEFT, w - RIGHT, TOP, h - BOTTOM);
        for (v, label) in self.x.ticks() {
            if let Some(px) = self.px(v) {
                let _ = write!(
                    s,
                    "<line class=\"grid\" x1=\"{px:.1}\" y1=\"{y0}\" x2=\"{px:.1}\" y2=\"{y1}\"/>\
                     <text x=\"{px:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
                    y1 + 15.0,
                    escape(&label)
                );
            }
        }
        for (v, label) in self.y.ticks() {
            if let Some(py) = self.py(v) {
                let _ = write!(
                    s,
                    "<line class=\"grid\" x1=\"{x0}\" y1=\"{py:.1}\" x2=\"{x1}\" y2=\"{py:.1}\"/>\
                     <text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">{}</text>",
                    x0 - 5.0,
                    py + 4.0,
                    escape(&label)
                );
            }
        }
        let _ = write!(
            s,
            "<rect class=\"frame\" x=\"{x0}\" y=\"{y0}\" width=\"{:.1}\" height=\"{:.1}\"/>",
            x1 - x0,
            y1 - y0
        );
        s.push_str(&self.body);
        let _ = write!(
            s,
            "<text class=\"axis\" x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>\
             <text class=\"axis\" transform=\"translate(14 {:.1}) rotate(-90)\" text-anchor=\"middle\">{}</text></svg>",
            (x0 + x1) / 2.0,
            h - 8.0,
            escape(&self.x.label),
            (y0 + y1) / 2.0,
            escape(&self.y.label)
        );
        Html::raw(s)
    }

    /// The legend, as HTML under the drawing (it wraps on a narrow screen).
    pub fn legend(&self) -> Html {
        legend(
            self.keys
                .iter()
                .map(|k| (k.label.as_str(), k.colour.as_str(), k.line, k.dashed)),
        )
    }
}

/// A legend of `(label, colour, line, dashed)` entries.
pub(super) fn legend<'a>(keys: impl Iterator<Item = (&'a str, &'a str, bool, bool)>) -> Html {
    let mut s = String::new();
    for (label, colour, line, dashed) in keys {
        let class = match (line, dashed) {
            (true, true) => "key dashed",
            (true, false) => "key line",
            _ => "key dot",
        };
        let _ = write!(
            s,
            "<li><svg class=\"{class}\" viewBox=\"0 0 20 10\" aria-hidden=\"true\">{}</svg>{}</li>",
            if line {
                format!(
                    "<line x1=\"1\" y1=\"5\" x2=\"19\" y2=\"5\" stroke=\"{colour}\" stroke-width=\"2.5\"{}/>",
                    if dashed { " stroke-dasharray=\"4 2\"" } else { "" }
                )
            } else {
                format!("<circle cx=\"10\" cy=\"5\" r=\"4\" fill=\"{colour}\"/>")
            },
            escape(label)
        );
    }
    if s.is_empty() {
        Html::default()
    } else {
        Html::raw(format!("<ul class=\"legend\">{s}</ul>"))
    }
}

/// A colour of the error scale (dark blue, green, yellow) at `t` (0..1,
/// clamped): distinct in grey too, for a printed page.
pub(super) fn colour_of(t: f64) -> String {
    const STOPS: [(f64, [f64; 3]); 5] = [
        (0.0, [68.0, 1.0, 84.0]),
        (0.25, [59.0, 82.0, 139.0]),
        (0.5, [33.0, 145.0, 140.0]),
        (0.75, [94.0, 201.0, 98.0]),
        (1.0, [253.0, 231.0, 37.0]),
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        1.0
    };
    let k = STOPS
        .windows(2)
        .position(|w| t <= w[1].0)
        .unwrap_or(STOPS.len() - 2);
    let ((t0, a), (t1, b)) = (STOPS[k], STOPS[k + 1]);
    let f = (t - t0) / (t1 - t0);
    let c = |i: usize| (a[i] + f * (b[i] - a[i])).round() as u8;
    format!("#{:02x}{:02x}{:02x}", c(0), c(1), c(2))
}

/// The colour scale of a map, 0 to `top` mm, as a bar with ticks.
pub(super) fn colour_bar(top: f64, label: &str) -> Html {
    let w = WIDTH - LEFT - RIGHT;
    let mut s = format!(
        "<svg class=\"colourbar\" viewBox=\"0 0 {WIDTH} 42\" role=\"img\" aria-label=\"{}\" xmlns=\"http://www.w3.org/2000/svg\">",
        escape(label)
    );
    let cells = 40;
    for i in 0..cells {
        let t = (i as f64 + 0.5) / cells as f64;
        let _ = write!(
            s,
            "<rect x=\"{:.1}\" y=\"2\" width=\"{:.2}\" height=\"10\" fill=\"{}\"/>",
            LEFT + w * i as f64 / cells as f64,
            w / cells as f64 + 0.3,
            colour_of(t)
        );
    }
    let axis = Axis::linear(label, [0.0, top], true);
    for (v, text) in axis.ticks() {
        if v <= top * (1.0 + 1e-9) {
            let x = LEFT + w * v / top;
            let _ = write!(
                s,
                "<text x=\"{x:.1}\" y=\"26\" text-anchor=\"middle\">{}</text>",
                escape(&text)
            );
        }
    }
    let _ = write!(
        s,
        "<text x=\"{:.1}\" y=\"40\" text-anchor=\"middle\" class=\"axis\">{}</text></svg>",
        LEFT + w / 2.0,
        escape(label)
    );
    Html::raw(s)
}

/// One series of a [`dot_chart`]: a label, a colour and a value per row.
pub(super) struct DotSeries<'a> {
    pub label: &'a str,
    pub colour: &'a str,
    pub values: Vec<Option<f64>>,
}

/// Named rows (stages, candidates, steps) against one value axis: a dot per
/// series on each row, and a bar to the first series' dot when `bars`.
/// Returns the drawing and how many marks it holds.
pub(super) fn dot_chart(
    rows: &[String],
    series: &[DotSeries<'_>],
    axis: &Axis,
    bars: bool,
    description: &str,
) -> (Html, usize) {
    const ROW: f64 = 22.0;
    const NAMES: f64 = 166.0;
    let height = TOP + ROW * rows.len() as f64 + BOTTOM;
    let (x0, x1) = (NAMES, WIDTH - RIGHT);
    let px = |v: f64| axis.fraction(v).map(|f| x0 + f.clamp(0.0, 1.0) * (x1 - x0));
    let mut s = format!(
        "<svg viewBox=\"0 0 {WIDTH} {height}\" role=\"img\" aria-label=\"{}\" xmlns=\"http://www.w3.org/2000/svg\">",
        escape(description)
    );
    let y1 = height - BOTTOM;
    for (v, label) in axis.ticks() {
        if let Some(x) = px(v) {
            let _ = write!(
                s,
                "<line class=\"grid\" x1=\"{x:.1}\" y1=\"{TOP}\" x2=\"{x:.1}\" y2=\"{y1}\"/>\
                 <text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
                y1 + 15.0,
                escape(&label)
            );
        }
    }
    let mut marks = 0;
    for (r, name) in rows.iter().enumerate() {
        let y = TOP + ROW * (r as f64 + 0.5);
        let _ = write!(
            s,
            "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\"><title>{}</title>{}</text>",
            x0 - 6.0,
            y + 4.0,
            escape(name),
            escape(&shortened(name, 25))
        );
        let n = series.len().max(1) as f64;
        for (k, ser) in series.iter().enumerate() {
            let Some(x) = ser.values.get(r).copied().flatten().and_then(px) else {
                continue;
            };
            let dy = (k as f64 - (n - 1.0) / 2.0) * 5.0;
            if bars && k == 0 {
                let _ = write!(
                    s,
                    "<rect class=\"mark\" x=\"{x0}\" y=\"{:.1}\" width=\"{:.1}\" height=\"9\" fill=\"{}\" fill-opacity=\"0.35\"/>",
                    y - 4.5,
                    (x - x0).max(0.5),
                    ser.colour
                );
            }
            let _ = write!(
                s,
                "<circle class=\"mark\" cx=\"{x:.1}\" cy=\"{:.1}\" r=\"4\" fill=\"{}\"/>",
                y + dy,
                ser.colour
            );
            marks += 1;
        }
    }
    let _ = write!(
        s,
        "<rect class=\"frame\" x=\"{x0}\" y=\"{TOP}\" width=\"{:.1}\" height=\"{:.1}\"/>\
         <text class=\"axis\" x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text></svg>",
        x1 - x0,
        y1 - TOP,
        (x0 + x1) / 2.0,
        height - 8.0,
        escape(&axis.label)
    );
    (Html::raw(s), marks)
}

/// `text` cut to `max` characters with an ellipsis.
pub(super) fn shortened(text: &str, max: usize) -> String {
    if text.chars().count() <= max {
        text.to_string()
    } else {
        let mut s: String = text.chars().take(max.saturating_sub(1)).collect();
        s.push('…');
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_are_one_two_or_five_times_a_power_of_ten() {
        assert_eq!(nice_step(0.7), 1.0);
        assert_eq!(nice_step(1.3), 2.0);
        assert_eq!(nice_step(3.0), 5.0);
        assert_eq!(nice_step(0.031), 0.05);
        assert_eq!(nice_step(700.0), 1000.0);
        assert_eq!(nice_step(f64::NAN), 1.0);
    }

    #[test]
    fn a_linear_axis_ends_near_its_values_on_round_numbers() {
        let a = Axis::linear("mm", [0.13, 4.2], true);
        assert_eq!((a.lo, a.hi), (0.0, 5.0));
        let labels: Vec<String> = a.ticks().into_iter().map(|t| t.1).collect();
        assert_eq!(labels, ["0", "1", "2", "3", "4", "5"]);
        // Not stretched by a whole tick interval: ends on a finer step.
        let b = Axis::linear("mm", [-750.0, 740.0], false);
        assert_eq!((b.lo, b.hi), (-800.0, 800.0));
        let labels: Vec<String> = b.ticks().into_iter().map(|t| t.1).collect();
        assert_eq!(labels, ["-500", "0", "500"]);
        // One value: a range around it, never an empty one.
        let one = Axis::linear("mm", [2.0], false);
        assert!(one.lo < 2.0 && one.hi > 2.0);
    }

    #[test]
    fn a_log_axis_spans_whole_decades() {
        let a = Axis::log("mm", [0.12, 0.0, -1.0, 230.0]);
        assert_eq!((a.lo, a.hi), (0.1, 1000.0));
        let labels: Vec<String> = a.ticks().into_iter().map(|t| t.1).collect();
        assert_eq!(labels, ["0.1", "1", "10", "100", "1000"]);
        let narrow = Axis::log("mm", [0.2, 3.0]);
        let labels: Vec<String> = narrow.ticks().into_iter().map(|t| t.1).collect();
        assert_eq!(labels, ["0.1", "0.2", "0.5", "1", "2", "5", "10"]);
    }

    #[test]
    fn marks_are_counted_and_text_escaped() {
        let mut p = Plot::new(
            Axis::linear("x <mm>", [0.0, 1.0], false),
            Axis::linear("y", [0.0, 1.0], false),
        );
        p.line(
            &[0.0, 0.5, 1.0],
            &[0.0, f64::NAN, 1.0],
            PALETTE[0],
            Stroke::Solid,
            Some("a & b"),
        );
        p.points(&[2.0], &[2.0], PALETTE[1], 2.0, Some("off the axes"));
        assert_eq!(p.marks, 1);
        let svg = p.svg("x \"quoted\"").0;
        assert!(svg.contains("x &lt;mm&gt;") && svg.contains("&quot;quoted&quot;"));
        // The missing value breaks the line into two pieces of one point.
        assert!(svg.contains("d=\"M62.0,254.0M380.0,12.0\""), "{svg}");
        assert!(p.legend().0.contains("a &amp; b"));
        assert!(!p.legend().0.contains("off the axes"));
    }

    #[test]
    fn the_colour_scale_runs_from_dark_to_light() {
        assert_eq!(colour_of(0.0), "#440154");
        assert_eq!(colour_of(1.0), "#fde725");
        assert_eq!(colour_of(7.0), "#fde725");
        assert_eq!(colour_of(f64::NAN), "#fde725");
    }
}
