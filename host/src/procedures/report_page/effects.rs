//! Each effect the diagnosis loop tried, added or not: its size, the share
//! of the residual it explains, the held-out figures that decided it, and
//! the residual against its variable before and after.

use serde_json::Value;

use super::data::FigureData;
use super::evidence::{EffectEvidence, StringEvidence};
use super::html::{self, f, figure, list, mm, p, percent, s, Cell, Html, Table};
use super::svg::{Axis, Plot, Stroke, MUTED, PALETTE, PANEL_WIDTH};

pub(super) fn section(r: &Value, figures: Option<&FigureData>) -> Html {
    let effects = list(&r["effects"]);
    let added = effects
        .iter()
        .filter(|e| e["added"].as_bool() == Some(true))
        .count();
    if let Some(why) = r["identification"]["loop_not_run"].as_str() {
        return p(&format!(
            "None tried: the diagnosis loop did not run ({why})."
        ));
    }
    if effects.is_empty() {
        return p(&format!(
            "None significant: the identified model explains the residual of every string. A \
             constant error of one string above {} mm would have been seen.",
            mm(f(&r["device"]["smallest_detectable_offset_mm"]))
        ));
    }
    let mut h = p(&format!(
        "Diagnosis reported {}; the loop added {added}. An effect is added only when held-out \
         rows say it helps: the held-out mean must fall (2 %, 3.5 % for a term on one string) \
         without the p95 or the max rising beyond their noise, and its value fitted on each \
         half of the session must agree. Each figure shows the training rows' string residual \
         (the string's length from the tracker minus the model's) against the variable the \
         effect follows.",
        html::plural(effects.len(), "finding", "findings")
    ));
    let drawn: Vec<&EffectEvidence> = figures.map_or(Vec::new(), |d| d.effects.iter().collect());
    let mut shown = vec![false; effects.len()];
    // Every added effect first, then the strongest of the others.
    let mut order: Vec<usize> = (0..effects.len()).collect();
    order.sort_by_key(|&i| effects[i]["added"].as_bool() != Some(true));
    for i in order {
        let evidence = drawn.iter().find(|e| e.effect == i).copied();
        let is_added = effects[i]["added"].as_bool() == Some(true);
        if evidence.is_some() || (is_added && figures.is_none()) {
            h.push(card(&effects[i], evidence, figures.is_some()));
            shown[i] = true;
        }
    }
    let rest: Vec<&Value> = (0..effects.len())
        .filter(|&i| !shown[i])
        .map(|i| &effects[i])
        .collect();
    if !rest.is_empty() {
        h.push(html::tag("h3", "The other findings, not added"));
        h.push(rest_table(&rest));
    }
    h.push(layer_tables(&r["identification"]["layer_tables"]));
    h
}

/// "string 3", "strings 0, 1, 2", "every string".
fn strings_of(e: &Value) -> String {
    let strings: Vec<String> = list(&e["strings"])
        .iter()
        .filter_map(|v| v.as_u64().map(|v| v.to_string()))
        .collect();
    match strings.len() {
        0 => "every string".into(),
        1 => format!("string {}", strings[0]),
        _ => format!("strings {}", strings.join(", ")),
    }
}

fn words(key: &str) -> String {
    key.replace('_', " ")
}

/// The held-out mean before and after, with the change in percent.
fn held_out_change(v: &Value) -> String {
    let (b, a) = (
        f(&v["before"]["held"]["mean_mm"]),
        f(&v["after"]["held"]["mean_mm"]),
    );
    match (b, a) {
        (Some(b), Some(a)) if b > 0.0 => format!(
            "{} → {} mm ({:+.1} %)",
            mm(Some(b)),
            mm(Some(a)),
            100.0 * (a - b) / b
        ),
        _ => html::NONE.into(),
    }
}

/// One finding: what it is, the figures that decided it, its figure.
fn card(e: &Value, evidence: Option<&EffectEvidence>, have_data: bool) -> Html {
    let added = e["added"].as_bool() == Some(true);
    let v = &e["validation"];
    let heading = format!(
        "{}: {} on {}, against {}",
        if added { "Added" } else { "Not added" },
        words(s(&e["family"])),
        strings_of(e),
        words(s(&e["variable"]))
    );
    let mut facts = vec![
        (
            "size (largest contribution)",
            format!("{} mm", mm(f(&e["amplitude_mm"]))),
        ),
        (
            "share of the residual it explains",
            percent(f(&e["explained"])),
        ),
        ("test statistic (chi-square)", html::sig(f(&e["chi2"]))),
    ];
    if v.is_object() {
        facts.push(("held-out mean", held_out_change(v)));
        facts.push((
            "held-out p95",
            format!(
                "{} → {} mm",
                mm(f(&v["before"]["held"]["p95_mm"])),
                mm(f(&v["after"]["held"]["p95_mm"]))
            ),
        ));
        facts.push((
            "held-out max",
            format!(
                "{} → {} mm",
                mm(f(&v["before"]["held"]["max_mm"])),
                mm(f(&v["after"]["held"]["max_mm"]))
            ),
        ));
        facts.push(("held-out folds", words(s(&v["after"]["folds"]))));
        if let Some(chi2) = f(&v["stability_chi2"]) {
            facts.push(("halves agree (chi-square)", html::sig(Some(chi2))));
        }
    }
    let mut h = Html::raw(format!(
        "<article class=\"effect{}\"><h3>{}</h3>",
        if added { " added" } else { "" },
        html::escape(&heading)
    ));
    h.push(html::facts(&facts));
    let verdict = if v.is_object() {
        s(&v["reason"]).to_string()
    } else {
        "Not tested on held-out rows: structure no family of effects explains; what follows \
         position is left to the learned correction."
            .to_string()
    };
    h.push(Html::raw(format!(
        "<p class=\"verdict\">{}</p>",
        html::escape(&verdict)
    )));
    if !s(&e["description"]).is_empty() {
        h.push(p(s(&e["description"])));
    }
    h.push(match evidence {
        Some(ev) => residual_figure(ev),
        None if have_data => html::no_figure("No figure: no training row shows this residual."),
        None => super::without_figure_data(),
    });
    h.push(Html::raw("</article>"));
    h
}

/// Small multiples, one per string: the residual rows before (grey) and
/// after (colour), and their binned means.
fn residual_figure(ev: &EffectEvidence) -> Html {
    let strings: Vec<&StringEvidence> = ev.strings.iter().filter(|s| s.rows > 0).collect();
    if strings.is_empty() {
        return html::no_figure("No figure: no tracked training row of these strings.");
    }
    let x_values = strings
        .iter()
        .flat_map(|s| s.x.iter().chain(&s.bin_x).copied());
    let x_axis = Axis::linear(&ev.x_label, x_values, false);
    let y_values: Vec<f64> = strings
        .iter()
        .flat_map(|s| s.before_mm.iter().chain(&s.after_mm).copied())
        .collect();
    let y_axis = Axis::linear("residual, mm", y_values.iter().copied(), false);
    let mut panels = String::new();
    let mut legend = Html::default();
    for (k, st) in strings.iter().enumerate() {
        let mut plot = Plot::new(
            x_axis.clone(),
            Axis {
                label: format!("string {}: residual, mm", st.string),
                ..y_axis.clone()
            },
        )
        .with_size(PANEL_WIDTH, 240.0);
        let colour = PALETTE[k % PALETTE.len()];
        let before = ev.before.as_deref();
        if before.is_some() {
            plot.points(&st.x, &st.before_mm, MUTED, 1.6, Some("before: each row"));
        }
        plot.points(&st.x, &st.after_mm, colour, 1.6, Some("after: each row"));
        if before.is_some() {
            plot.line(
                &st.bin_x,
                &st.bin_before_mm,
                "#555555",
                Stroke::Dashed,
                Some("before: binned mean"),
            );
        }
        plot.line(
            &st.bin_x,
            &st.bin_after_mm,
            colour,
            Stroke::Solid,
            Some("after: binned mean"),
        );
        plot.hline(0.0, "");
        panels.push_str(
            &plot
                .svg(&format!(
                    "string {} residual against {}",
                    st.string, ev.x_label
                ))
                .0,
        );
        if k == 0 {
            legend = plot.legend();
        }
    }
    let caption = format!(
        "The training rows' residual on {}, against {}: after is the final model{}{}.",
        if strings.len() == 1 {
            "its string"
        } else {
            "each string"
        },
        ev.x_label,
        match &ev.before {
            Some(b) => format!("; before is {b}"),
            None => " (this change is no term of the string law: no before)".into(),
        },
        if ev.strings_not_drawn > 0 {
            format!("; {} more strings not drawn", ev.strings_not_drawn)
        } else {
            String::new()
        }
    );
    figure(
        Html::raw(format!("<div class=\"panels\">{panels}</div>")),
        legend,
        &caption,
    )
}

fn rest_table(rest: &[&Value]) -> Html {
    let mut t = Table::new(&[
        "family",
        "strings",
        "against",
        "size, mm",
        "explains",
        "chi-square",
        "held-out mean",
        "why not added",
    ]);
    for e in rest {
        let v = &e["validation"];
        t.row(vec![
            Cell::text(&words(s(&e["family"]))),
            Cell::text(&strings_of(e)),
            Cell::text(&words(s(&e["variable"]))),
            Cell::num(mm(f(&e["amplitude_mm"]))),
            Cell::num(percent(f(&e["explained"]))),
            Cell::num(html::sig(f(&e["chi2"]))),
            Cell::num(if v.is_object() {
                held_out_change(v)
            } else {
                html::NONE.into()
            }),
            Cell::text(if v.is_object() {
                s(&v["reason"])
            } else {
                "untested: no family explains it"
            }),
        ]);
    }
    t.html()
}

/// The layer-table spacing chosen per string on the blocked folds.
fn layer_tables(tables: &Value) -> Html {
    let tried = list(tables);
    if tried.is_empty() {
        return Html::default();
    }
    let mut h = html::tag("h3", "Layer tables");
    let tables: Vec<&Value> = tried
        .iter()
        .filter(|l| html::u(&l["knots"]).is_some_and(|k| k > 0))
        .collect();
    if tables.is_empty() {
        h.push(p(&format!(
            "Tried on {}: no spacing lowered a string's held-out residual enough to keep a \
             table; every string keeps its smooth winding law.",
            html::plural(tried.len(), "string", "strings")
        )));
        return h;
    }
    h.push(p(
        "Each string's spool departs from the smooth winding law in steps of its layers. The \
         spacing of each string's table, chosen on held-out folds; whether the tables were kept \
         is the layers finding's verdict above.",
    ));
    let mut t = Table::new(&[
        "string",
        "knots every (counts)",
        "knots",
        "peak to peak, mm",
        "held-out rms without, mm",
        "with, mm",
    ]);
    for l in tables {
        t.row(vec![
            Cell::num(html::count(html::u(&l["string"]))),
            Cell::num(html::count(html::u(&l["step_counts"]))),
            Cell::num(html::count(html::u(&l["knots"]))),
            Cell::num(mm(f(&l["peak_to_peak_mm"]))),
            Cell::num(mm(f(&l["held_rms_without_mm"]))),
            Cell::num(mm(f(&l["held_rms_with_mm"]))),
        ]);
    }
    h.push(t.html());
    h
}
