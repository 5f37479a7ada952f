use super::*;
use serde_json::json;

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("spidar-report-page-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A report of two stages whose texts try to break out of the page.
fn small_report() -> Value {
    let stats = |mean: f64| {
        json!({"n": 3, "mean_mm": mean, "sd_mm": 0.5, "max_mm": 2.0 * mean,
               "median_mm": mean, "p95_mm": null})
    };
    json!({
        "schema": crate::procedures::calibrate::SCHEMA,
        "tool": {"name": "spidar", "version": "0.1.0"},
        "inputs": {
            "geometry": "g.toml",
            "train": {"path": "<script>alert(1)</script>.csv", "rows": 4, "tracked": 3,
                      "set_aside": [{"line": 3, "column": "enc0", "value": -2147483648.0,
                                     "part": "row", "why": "a & b"}]},
            "test": {"path": "test.csv", "rows": 3, "tracked": 3}
        },
        "stages": [
            {"name": "raw", "kind": "raw", "train": stats(200.0), "test": stats(190.0)},
            {"name": "final (string model)", "kind": "final", "train": stats(0.3),
             "test": stats(0.4)}
        ],
        "effects": [{"family": "offset", "strings": [3], "variable": "length",
                     "amplitude_mm": 8.0, "explained": 0.5, "added": true, "chi2": 800.0,
                     "description": "<b>bold</b>"}],
        "warnings": ["look <here>"],
        "selection": {"stage": "final (string model)", "reason": "because",
                      "device_tick": {"model_instructions": 23530, "budget": 55000,
                                      "support_vectors": 1000, "neurons": 400,
                                      "final_instructions": 24296}}
    })
}

#[test]
fn a_report_renders_whole_with_its_text_escaped() {
    let page = render(&small_report(), None);
    assert!(page.starts_with("<!DOCTYPE html>") && page.ends_with("</html>\n"));
    assert!(page.contains(CONTENT_SECURITY_POLICY));
    for raw in ["<script>", "<b>bold", "<here>"] {
        assert!(!page.contains(raw), "{raw} unescaped");
    }
    assert!(page.contains("&lt;script&gt;alert(1)&lt;/script&gt;.csv"));
    // The stage table, keyed for the browser check; a missing p95 is a dash.
    assert!(page.contains("<tr class=\"final\" data-stage=\"1\">"));
    assert!(page.contains("<td class=\"num\" data-key=\"test.mean_mm\">0.400</td>"));
    assert!(page.contains("<td class=\"num\" data-key=\"train.p95_mm\">–</td>"));
    // Without the figure data the page says why the figures are missing.
    assert!(page.contains(FIGURE_DATA_FILE) && page.contains("class=\"missing\""));
    // Every section is there, in the order of the reader's questions.
    let at = |id: &str| page.find(&format!("<section id=\"{id}\">")).unwrap();
    let ids = [
        "inputs",
        "warnings",
        "stages",
        "effects",
        "parameters",
        "corrections",
        "device",
        "timings",
    ];
    assert!(ids.windows(2).all(|w| at(w[0]) < at(w[1])));
    // The device's tick with the calibration, and the room a correction had.
    assert!(page.contains("an estimated 24296 of the 55000 instructions"));
    assert!(page.contains("400 hidden neurons or 1000 support vectors"));
}

#[test]
fn any_json_renders_without_a_panic() {
    for v in [
        json!({}),
        json!(null),
        json!([1, 2]),
        json!({"stages": 3, "effects": [null]}),
    ] {
        let page = render(&v, None);
        assert!(page.contains("</html>"));
    }
}

#[test]
fn a_missing_or_malformed_report_is_an_error_naming_the_file() {
    let dir = temp_dir("bad");
    let report = dir.join(REPORT_FILE);
    let e = rebuild(&dir).unwrap_err().to_string();
    assert!(
        e.contains(&report.display().to_string()) && e.contains("cannot read"),
        "{e}"
    );
    std::fs::write(&report, "{\"schema\": ").unwrap();
    let e = rebuild(&dir).unwrap_err().to_string();
    assert!(e.starts_with(&format!("{}:1:", report.display())), "{e}");
    std::fs::write(&report, "{\"schema\": \"something-else/2\"}").unwrap();
    let e = rebuild(&dir).unwrap_err().to_string();
    assert!(
        e.contains("something-else/2") && e.contains(&report.display().to_string()),
        "{e}"
    );
    // A malformed figure file is an error naming it; no page is written.
    std::fs::write(&report, small_report().to_string()).unwrap();
    let figures = dir.join(FIGURE_DATA_FILE);
    std::fs::write(&figures, "[]").unwrap();
    let e = rebuild(&dir).unwrap_err().to_string();
    assert!(e.contains(&figures.display().to_string()), "{e}");
    assert!(!dir.join(PAGE_FILE).exists());
    // Without it the page is rebuilt, saying which figures it lacks.
    std::fs::remove_file(&figures).unwrap();
    let page = rebuild(&dir).unwrap();
    assert_eq!(page, dir.join(PAGE_FILE));
    assert!(std::fs::read_to_string(&page)
        .unwrap()
        .contains(FIGURE_DATA_FILE));
    let _ = std::fs::remove_dir_all(&dir);
}

/// What stops the device from running a calibration as reported goes to
/// the report's warnings, naming the reason and the command that refuses
/// it; a blob the device runs within the budget gives none.
#[test]
fn a_calibration_the_device_cannot_run_as_reported_is_a_warning() {
    let fine = DeviceData {
        refused: None,
        bytes: Some(1296),
        capacity: 98_304,
        model_id: 1,
        correction: Some("none".into()),
        effects: Some(10),
        hidden: Some(0),
        support_vectors: Some(0),
        fixed_point: Some(FixedPoint {
            rows: 500,
            status_mismatches: 0,
            string_model_mean_mm: 1e-4,
            string_model_max_mm: 3e-4,
            corrected_mean_mm: 1e-4,
            corrected_max_mm: 3e-4,
            budget_mm: 0.02,
        }),
    };
    assert!(fine.warnings().is_empty());
    let refused = DeviceData {
        refused: Some("string 1: home_tension_n = -0.5 is outside [0, 65.535]".into()),
        bytes: None,
        fixed_point: None,
        ..fine.clone()
    };
    let w = refused.warnings();
    assert!(
        w.len() == 1 && w[0].contains("does not compile") && w[0].contains("home_tension_n"),
        "{w:?}"
    );
    let large = DeviceData {
        bytes: Some(100_000),
        ..fine.clone()
    };
    let w = large.warnings();
    assert!(w.len() == 1 && w[0].contains("100000 bytes"), "{w:?}");
    let mut over = fine.clone();
    if let Some(f) = over.fixed_point.as_mut() {
        f.corrected_mean_mm = 0.143;
    }
    let w = over.warnings();
    assert!(
        w.len() == 1 && w[0].contains("0.1430 mm") && w[0].contains("--write-over-budget"),
        "{w:?}"
    );
}

/// A string's `r_home` is named the effective radius (the spool's over its
/// mechanical advantage) when that advantage is not 1: a Hangprinter user
/// reading 37.9 mm expects the spool's 75 mm (a survey's finding F5e).
#[test]
fn a_radius_under_a_mechanical_advantage_is_named_the_effective_one() {
    let mut r = small_report();
    let radius = |k: usize, v: f64| {
        json!({"name": format!("string{k}.r_home"), "unit": "mm", "value": v, "sd": 0.09,
               "prior_sd": null, "determined": true})
    };
    r["device"] = json!({"channels": [0, 1]});
    r["identification"] = json!({
        "parameters": [radius(0, 37.94), radius(1, 7.5)],
        "mechanical_advantage": [2.0, 1.0]
    });
    let page = render(&r, None);
    assert!(
        page.contains(
            "string0.r_home (effective radius: the spool&#39;s / mechanical advantage 2)"
        ),
        "string 0"
    );
    assert!(
        page.contains(">string1.r_home<"),
        "string 1 has no advantage"
    );
}
