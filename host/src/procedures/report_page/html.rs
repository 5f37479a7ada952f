//! The page's building blocks: escaped text ([`Html`]), numbers as the
//! report prints them, the report's JSON values read without panicking,
//! tables and short lists.

use std::fmt::Write as _;

use serde_json::Value;

/// Markup that is safe to put in the page: text enters only through
/// [`Html::text`] (escaped) or from this module's builders.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct Html(pub String);

impl Html {
    /// `text`, escaped.
    pub fn text(text: &str) -> Html {
        Html(escape(text))
    }

    /// Markup built by the page's own code (its text escaped already).
    pub fn raw(markup: impl Into<String>) -> Html {
        Html(markup.into())
    }

    pub fn push(&mut self, more: Html) {
        self.0.push_str(&more.0);
    }
}

impl From<&str> for Html {
    fn from(text: &str) -> Html {
        Html::text(text)
    }
}

impl From<String> for Html {
    fn from(text: String) -> Html {
        Html::text(&text)
    }
}

/// `text` with the characters HTML gives a meaning escaped (in element
/// content and in quoted attributes alike).
pub(super) fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// An element with escaped-text content.
pub(super) fn tag(name: &str, text: &str) -> Html {
    Html(format!("<{name}>{}</{name}>", escape(text)))
}

/// `text` with its first letter a capital (the report's reasons start in
/// lower case, as a clause).
pub(super) fn capitalized(text: &str) -> String {
    let mut chars = text.chars();
    match chars.next() {
        Some(first) => first.to_uppercase().chain(chars).collect(),
        None => String::new(),
    }
}

/// A paragraph of text.
pub(super) fn p(text: &str) -> Html {
    tag("p", text)
}

/// A value of the report as a number (`null`, absent or not a number:
/// `None`).
pub(super) fn f(v: &Value) -> Option<f64> {
    v.as_f64().filter(|x| x.is_finite())
}

/// A value of the report as a count.
pub(super) fn u(v: &Value) -> Option<u64> {
    v.as_u64()
}

/// A value of the report as text ("" when not a string).
pub(super) fn s(v: &Value) -> &str {
    v.as_str().unwrap_or("")
}

/// A value of the report as a list (empty when not one).
pub(super) fn list(v: &Value) -> &[Value] {
    v.as_array().map_or(&[], Vec::as_slice)
}

/// A dash for a value the report does not have.
pub(super) const NONE: &str = "–";

/// Millimetres as the terminal summary prints them: three decimals below
/// 1000 mm, one above; a dash when missing. The browser check reads the
/// stage table back at this precision.
pub(super) fn mm(v: Option<f64>) -> String {
    match v {
        Some(v) if v.abs() < 1000.0 => format!("{v:.3}"),
        Some(v) => format!("{v:.1}"),
        None => NONE.into(),
    }
}

/// A number with `decimals` decimals, or a dash.
pub(super) fn fixed(v: Option<f64>, decimals: usize) -> String {
    v.map_or_else(|| NONE.into(), |v| format!("{v:.decimals$}"))
}

/// A number in a few significant digits (parameters of any size).
pub(super) fn sig(v: Option<f64>) -> String {
    match v {
        None => NONE.into(),
        Some(0.0) => "0".into(),
        Some(v) if (1e-3..1e6).contains(&v.abs()) => {
            let decimals = (3 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
            format!("{v:.decimals$}")
        }
        Some(v) => format!("{v:.3e}"),
    }
}

/// A share as a percentage.
pub(super) fn percent(v: Option<f64>) -> String {
    v.map_or_else(|| NONE.into(), |v| format!("{:.0} %", 100.0 * v))
}

/// A count, or a dash.
pub(super) fn count(v: Option<u64>) -> String {
    v.map_or_else(|| NONE.into(), |n| n.to_string())
}

pub(super) use crate::procedures::plural;

/// A table cell: its content and whether it holds a number (right-aligned).
pub(super) struct Cell {
    html: Html,
    numeric: bool,
    attributes: String,
}

impl Cell {
    pub fn text(text: &str) -> Cell {
        Cell {
            html: Html::text(text),
            numeric: false,
            attributes: String::new(),
        }
    }

    pub fn num(text: String) -> Cell {
        Cell {
            html: Html::text(&text),
            numeric: true,
            attributes: String::new(),
        }
    }

    /// The cell with a `data-key` naming what it shows (the browser check
    /// reads the stage table by it).
    pub fn keyed(mut self, key: &str) -> Cell {
        let _ = write!(self.attributes, " data-key=\"{}\"", escape(key));
        self
    }
}

/// A table (scrolling sideways on a narrow screen); `row_class` gives each
/// row's class and attributes.
pub(super) struct Table {
    id: Option<String>,
    head: Vec<Vec<(String, usize)>>,
    rows: Vec<(String, Vec<Cell>)>,
}

impl Table {
    /// A table with one header row.
    pub fn new(headers: &[&str]) -> Table {
        Table {
            id: None,
            head: vec![headers.iter().map(|h| (h.to_string(), 1)).collect()],
            rows: Vec::new(),
        }
    }

    /// A table with a grouping header row above the column headers:
    /// `(title, columns spanned)`.
    pub fn grouped(groups: &[(&str, usize)], headers: &[&str]) -> Table {
        let mut t = Table::new(headers);
        t.head
            .insert(0, groups.iter().map(|(g, n)| (g.to_string(), *n)).collect());
        t
    }

    pub fn with_id(mut self, id: &str) -> Table {
        self.id = Some(id.to_string());
        self
    }

    pub fn row(&mut self, cells: Vec<Cell>) {
        self.rows.push((String::new(), cells));
    }

    /// A row with attributes (e.g. ` class="final" data-stage="3"`).
    pub fn row_with(&mut self, attributes: String, cells: Vec<Cell>) {
        self.rows.push((attributes, cells));
    }

    /// Rows so far.
    pub fn rows(&self) -> usize {
        self.rows.len()
    }

    pub fn html(&self) -> Html {
        let mut o = String::from("<div class=\"scroll\"><table");
        if let Some(id) = &self.id {
            let _ = write!(o, " id=\"{}\"", escape(id));
        }
        o.push_str("><thead>");
        for row in &self.head {
            o.push_str("<tr>");
            for (h, span) in row {
                if *span > 1 {
                    let _ = write!(o, "<th colspan=\"{span}\">{}</th>", escape(h));
                } else {
                    let _ = write!(o, "<th>{}</th>", escape(h));
                }
            }
            o.push_str("</tr>");
        }
        o.push_str("</thead><tbody>");
        for (attributes, cells) in &self.rows {
            let _ = write!(o, "<tr{attributes}>");
            for c in cells {
                let class = if c.numeric { " class=\"num\"" } else { "" };
                let _ = write!(o, "<td{class}{}>{}</td>", c.attributes, c.html.0);
            }
            o.push_str("</tr>");
        }
        o.push_str("</tbody></table></div>");
        Html(o)
    }
}

/// A bulleted list of texts.
pub(super) fn bullets<'a>(items: impl IntoIterator<Item = &'a str>) -> Html {
    let mut o = String::new();
    for i in items {
        let _ = write!(o, "<li>{}</li>", escape(i));
    }
    if o.is_empty() {
        Html::default()
    } else {
        Html(format!("<ul>{o}</ul>"))
    }
}

/// Term and description pairs (`<dl>`), laid out in columns.
pub(super) fn facts(pairs: &[(&str, String)]) -> Html {
    let mut o = String::from("<dl class=\"facts\">");
    for (term, value) in pairs {
        let _ = write!(
            o,
            "<div><dt>{}</dt><dd>{}</dd></div>",
            escape(term),
            escape(value)
        );
    }
    o.push_str("</dl>");
    Html(o)
}

/// Line numbers in short: the first `shown`, then how many more.
pub(super) fn some_lines(lines: &[u64], shown: usize) -> String {
    let mut text: Vec<String> = lines.iter().take(shown).map(u64::to_string).collect();
    if lines.len() > shown {
        text.push(format!("and {} more", lines.len() - shown));
    }
    text.join(", ")
}

/// A section of the page: its anchor, heading and content.
pub(super) fn section(id: &str, heading: &str, content: Html) -> Html {
    Html(format!(
        "<section id=\"{}\"><h2>{}</h2>{}</section>",
        escape(id),
        escape(heading),
        content.0
    ))
}

/// A figure: the drawing, its legend and caption (`class="plot"`: the
/// browser check finds every figure by it).
pub(super) fn figure(drawing: Html, legend: Html, caption: &str) -> Html {
    Html(format!(
        "<figure class=\"plot\">{}{}<figcaption>{}</figcaption></figure>",
        drawing.0,
        legend.0,
        escape(caption)
    ))
}

/// Why a figure is not drawn, where it would be.
pub(super) fn no_figure(why: &str) -> Html {
    Html(format!("<p class=\"missing\">{}</p>", escape(why)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn text_is_escaped_everywhere() {
        assert_eq!(
            escape("<script>alert('x') & \"y\"</script>"),
            "&lt;script&gt;alert(&#39;x&#39;) &amp; &quot;y&quot;&lt;/script&gt;"
        );
        let mut t = Table::new(&["<b>"]).with_id("a\"b");
        t.row(vec![Cell::text("<i>"), Cell::num("1".into()).keyed("x\"y")]);
        let html = t.html().0;
        assert!(!html.contains("<b>") && !html.contains("<i>"), "{html}");
        assert!(html.contains("id=\"a&quot;b\"") && html.contains("data-key=\"x&quot;y\""));
        assert_eq!(bullets(["a<b"]).0, "<ul><li>a&lt;b</li></ul>");
        assert!(facts(&[("<", ">".into())])
            .0
            .contains("<dt>&lt;</dt><dd>&gt;</dd>"));
    }

    #[test]
    fn missing_values_read_as_none() {
        let v = json!({"a": null, "b": 1.5, "c": "x", "d": [1]});
        assert_eq!(f(&v["a"]), None);
        assert_eq!(f(&v["b"]), Some(1.5));
        assert_eq!(f(&v["nope"]["deeper"]), None);
        assert_eq!(s(&v["c"]), "x");
        assert_eq!(s(&v["b"]), "");
        assert_eq!(list(&v["d"]).len(), 1);
        assert!(list(&v["c"]).is_empty());
        assert_eq!(mm(None), NONE);
        assert_eq!(mm(Some(0.12345)), "0.123");
        assert_eq!(mm(Some(1234.56)), "1234.6");
        assert_eq!(sig(Some(0.000_012_3)), "1.230e-5");
        assert_eq!(sig(Some(37.512_34)), "37.51");
        assert_eq!(some_lines(&[3, 5, 9], 2), "3, 5, and 1 more");
    }
}
