//! The calibration's page (`report.html`) as a reader's browser shows it:
//! the demo's, the Hangprinter's (measured data) and a planar device's
//! pages are loaded in headless Chromium, which must log no console message
//! (the page's Content-Security-Policy makes any request leaving the file
//! one), draw every figure, and show the stage table's figures as
//! `report.json` has them; a screenshot of each goes to `out/report-check/`.
//! `spidar report DIR` rebuilds the same page from the files beside it.
//!
//! Chromium comes from Debian (`chromium-headless-shell`, which
//! `scripts/install-deps` installs; `SPIDAR_BROWSER` names another). Without
//! one the browser part is skipped, saying so, except under CI (`CI` set),
//! where it fails.
//!
//! Hangprinter data: `../shared/data/hangprinter-hp4-2022/`, Hangprinter v4
//! prototype "force series 2" (April 2022) by Torbjørn Ludvigsen, from
//! github.com/tobbelobb/auto-calibration-simulation-for-hangprinter (commit
//! eff69f9e6522a526ed2dce2d83eed9bc3843a5cc), MIT licence (see that
//! folder's LICENSE and README).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use serde_json::Value;

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("spidar-report-page-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn spidar(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(args)
        .output()
        .expect("run the spidar binary");
    assert!(
        o.status.success(),
        "spidar {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Where the screenshots go: `out/report-check/` of the repository.
fn screenshot_dir() -> PathBuf {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../out/report-check");
    std::fs::create_dir_all(&d).unwrap();
    d.canonicalize().unwrap()
}

/// A headless Chromium: `SPIDAR_BROWSER`, else the first of Debian's names
/// on the PATH.
fn browser() -> Option<PathBuf> {
    if let Some(b) = std::env::var_os("SPIDAR_BROWSER").filter(|b| !b.is_empty()) {
        return Some(PathBuf::from(b));
    }
    let path = std::env::var_os("PATH")?;
    [
        "chromium-headless-shell",
        "chromium",
        "chromium-browser",
        "google-chrome",
    ]
    .iter()
    .flat_map(|name| std::env::split_paths(&path).map(move |d| d.join(name)))
    .find(|p| p.is_file())
}

/// The browser, or `None` (said on stderr) when there is none outside CI.
fn browser_or_skip(test: &str) -> Option<PathBuf> {
    let found = browser();
    if found.is_none() {
        assert!(
            std::env::var_os("CI").is_none_or(|v| v.is_empty()),
            "{test}: no headless Chromium on the PATH; scripts/install-deps installs \
             chromium-headless-shell (CI runs it)"
        );
        // Straight to the process's stderr, past the test harness's
        // capture: a skipped check is said even when the test passes.
        let _ = writeln!(
            std::io::stderr(),
            "{test}: SKIPPED the browser check: no headless Chromium (chromium-headless-shell, \
             chromium) on the PATH; scripts/install-deps installs it"
        );
    }
    found
}

/// What the browser made of a page: the DOM it built and the console
/// messages it logged.
struct Loaded {
    dom: String,
    console: Vec<String>,
}

/// Runs the browser on `page` with `extra` arguments (a minute at most);
/// returns its standard output and error.
fn run_browser(browser: &Path, page: &Path, extra: &[String]) -> (String, String) {
    static RUNS: AtomicUsize = AtomicUsize::new(0);
    let profile = temp_dir(&format!("browser-{}", RUNS.fetch_add(1, Ordering::Relaxed)));
    let url = format!("file://{}", page.canonicalize().unwrap().display());
    let mut child = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--hide-scrollbars",
            "--enable-logging=stderr",
            "--v=0",
            // Nothing leaves the machine even if the page asked.
            "--host-resolver-rules=MAP * ~NOTFOUND",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(extra)
        .arg(&url)
        // Into files, not pipes: a page's DOM fills a pipe long before the
        // browser ends, and nothing reads it while we wait.
        .stdout(std::fs::File::create(profile.join("stdout")).unwrap())
        .stderr(std::fs::File::create(profile.join("stderr")).unwrap())
        .spawn()
        .expect("start the browser");
    let deadline = Instant::now() + Duration::from_secs(60);
    while child.try_wait().expect("browser status").is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("{}: the browser did not finish in a minute", page.display());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let read = |name: &str| {
        String::from_utf8_lossy(&std::fs::read(profile.join(name)).unwrap_or_default()).into_owned()
    };
    let out = (read("stdout"), read("stderr"));
    let _ = std::fs::remove_dir_all(&profile);
    out
}

/// Loads `page` and dumps its DOM; writes a screenshot to `screenshot`
/// (`width` x `height` CSS pixels).
fn load(browser: &Path, page: &Path, screenshot: &Path, (width, height): (u32, u32)) -> Loaded {
    let (dom, log) = run_browser(browser, page, &["--dump-dom".to_string()]);
    let mut console: Vec<String> = log
        .lines()
        .filter(|l| l.contains(":CONSOLE"))
        .map(str::to_string)
        .collect();
    let _ = std::fs::remove_file(screenshot);
    let (_, log) = run_browser(
        browser,
        page,
        &[
            format!("--screenshot={}", screenshot.display()),
            format!("--window-size={width},{height}"),
        ],
    );
    console.extend(
        log.lines()
            .filter(|l| l.contains(":CONSOLE"))
            .map(str::to_string),
    );
    assert!(
        screenshot.metadata().is_ok_and(|m| m.len() > 1000),
        "{}: no screenshot written",
        screenshot.display()
    );
    Loaded { dom, console }
}

/// The text of the first element after `from` that starts with `open`, up
/// to `close`.
fn between<'a>(text: &'a str, open: &str, close: &str) -> Option<&'a str> {
    let start = text.find(open)?;
    let end = text[start..].find(close)? + start;
    Some(&text[start..end])
}

/// Reads the stage table back from the DOM and compares every figure with
/// `report.json`'s at the precision shown. Returns the rows read.
fn check_stage_table(dom: &str, report: &Value) -> usize {
    let table = between(dom, "<table id=\"stage-table\">", "</table>").expect("the stage table");
    let stages = report["stages"].as_array().expect("stages");
    let rows: Vec<&str> = table
        .split("<tr")
        .filter(|r| r.contains("data-stage="))
        .collect();
    assert_eq!(rows.len(), stages.len(), "one row per stage");
    for (i, row) in rows.iter().enumerate() {
        assert!(
            row.contains(&format!("data-stage=\"{i}\"")),
            "row {i} out of order"
        );
        let name = stages[i]["name"].as_str().unwrap();
        let escaped = name
            .replace('&', "&amp;")
            .replace('<', "&lt;")
            .replace('>', "&gt;");
        assert!(
            row.contains(&format!(">{escaped}</td>")),
            "row {i}: no name {name}"
        );
        for session in ["train", "test"] {
            for key in ["mean_mm", "sd_mm", "median_mm", "p95_mm", "max_mm"] {
                let open = format!("data-key=\"{session}.{key}\">");
                let shown = between(row, &open, "</td>")
                    .map(|c| &c[open.len()..])
                    .unwrap_or_else(|| panic!("{name}: no {session}.{key}"));
                let want = &stages[i][session][key];
                match want.as_f64() {
                    None => assert_eq!(shown, "–", "{name} {session}.{key}: null shown as {shown}"),
                    Some(v) => {
                        let got: f64 = shown
                            .parse()
                            .unwrap_or_else(|_| panic!("{name} {session}.{key}: {shown}"));
                        let decimals = shown.split('.').nth(1).map_or(0, str::len);
                        let half = 0.5 * 10f64.powi(-(decimals as i32));
                        assert!(
                            (got - v).abs() <= half * (1.0 + 1e-9),
                            "{name} {session}.{key}: page {shown}, report.json {v}"
                        );
                    }
                }
            }
        }
    }
    rows.len()
}

/// Every figure holds a drawing with data marks; returns how many there are.
fn check_figures(dom: &str, page: &Path) -> usize {
    let figures: Vec<&str> = dom.split("<figure class=\"plot\">").skip(1).collect();
    for (k, f) in figures.iter().enumerate() {
        let f = &f[..f.find("</figure>").expect("a closed figure")];
        let caption = between(f, "<figcaption>", "</figcaption>").unwrap_or("");
        assert!(
            f.contains("<svg") && f.contains("class=\"mark\""),
            "{}: figure {k} has nothing drawn ({caption})",
            page.display()
        );
    }
    assert!(
        !dom.contains("class=\"missing\""),
        "{}: a figure is missing: {}",
        page.display(),
        between(dom, "class=\"missing\"", "</p>").unwrap_or("")
    );
    figures.len()
}

/// The whole check of one calibration's page: rebuilt the same by
/// `spidar report`, loaded without a console message, every figure drawn,
/// the stage table as `report.json` says. Returns the figures counted.
fn check_page(dir: &Path, name: &str) -> usize {
    let page = dir.join("report.html");
    let written = std::fs::read(&page).expect("calibrate wrote report.html");
    let out = spidar(&["report", s(dir)]);
    assert_eq!(out, format!("wrote {}\n", page.display()));
    assert!(
        std::fs::read(&page).unwrap() == written,
        "spidar report rebuilt another page"
    );
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    let Some(browser) = browser_or_skip(name) else {
        return 0;
    };
    let shots = screenshot_dir();
    let t = Instant::now();
    let loaded = load(
        &browser,
        &page,
        &shots.join(format!("{name}.png")),
        (1000, 2400),
    );
    let phone = load(
        &browser,
        &page,
        &shots.join(format!("{name}-phone.png")),
        (390, 1600),
    );
    assert!(
        loaded.console.is_empty() && phone.console.is_empty(),
        "{name}: the page logged {:?}",
        [loaded.console, phone.console].concat()
    );
    assert!(loaded.dom.contains("</html>"), "{name}: no page loaded");
    assert!(
        loaded.dom.contains("The test session's home capture: "),
        "{name}: the page does not say which home capture the test session follows"
    );
    let rows = check_stage_table(&loaded.dom, &report);
    let figures = check_figures(&loaded.dom, &page);
    eprintln!(
        "{name}: {rows} stages read back, {figures} figures drawn, no console message; \
         screenshots in {} ({:.1} s in the browser)",
        shots.display(),
        t.elapsed().as_secs_f64()
    );
    figures
}

#[test]
fn the_demo_report_renders_in_a_browser() {
    let dir = temp_dir("demo");
    let printed = spidar(&[
        "demo",
        "--quick",
        "--quiet",
        "--no-device",
        "--out",
        s(&dir),
        "--effect",
        "offset:3:mm=8",
        "--effect",
        "eccentricity:1:sin_mm=0.8,cos_mm=0.5",
    ]);
    let page = dir.join("calibration/report.html");
    assert!(
        printed.contains(&format!("The report, for people: {}", page.display())),
        "the demo does not print the page's path:\n{printed}"
    );
    let figures = check_page(&dir.join("calibration"), "demo");
    // Stages, spread, map, along the session; the two effects the loop
    // adds; the candidates, the NN sweep, the timings.
    assert!(figures == 0 || figures >= 10, "{figures} figures");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A quick calibration, without figures, of `data`'s `geometry.toml`,
/// `train.csv` and `test.csv`, written to `out`.
fn quick_calibration(data: &Path, out: &Path) {
    spidar(&[
        "calibrate",
        "--quick",
        "--quiet",
        "--no-figures",
        "--geometry",
        s(&data.join("geometry.toml")),
        "--train",
        s(&data.join("train.csv")),
        "--test",
        s(&data.join("test.csv")),
        "--out",
        s(out),
    ]);
}

#[test]
fn the_hangprinter_report_renders_in_a_browser() {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/hangprinter-hp4-2022");
    let dir = temp_dir("hangprinter");
    quick_calibration(&data, &dir);
    check_page(&dir, "hangprinter");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_planar_report_renders_in_a_browser() {
    let dir = temp_dir("wall-robot");
    for (kind, name) in [("stream", "train"), ("wide-stream", "test")] {
        spidar(&[
            "simulate",
            "--physics",
            "independent",
            "--preset",
            "wall-robot",
            "--out",
            s(&dir),
            "--kind",
            kind,
            "--name",
            name,
        ]);
    }
    let out = dir.join("calibration");
    quick_calibration(&dir, &out);
    check_page(&out, "wall-robot");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The check itself catches a page that reaches outside: the policy
/// refuses the request and the browser logs it.
#[test]
fn a_request_leaving_the_page_is_caught() {
    let Some(browser) = browser_or_skip("a_request_leaving_the_page_is_caught") else {
        return;
    };
    let dir = temp_dir("leak");
    let page = dir.join("leak.html");
    let report: Value = serde_json::json!({"schema": "spidar-calibrate-report/1"});
    let html = spidar::procedures::report_page::render(&report, None).replace(
        "</main>",
        "<img src=\"https://example.com/x.png\" alt=\"\"></main>",
    );
    std::fs::write(&page, html).unwrap();
    let loaded = load(&browser, &page, &dir.join("leak.png"), (600, 400));
    assert!(
        loaded.console.iter().any(|l| l.contains("example.com")),
        "{:?}",
        loaded.console
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn spidar_report_refuses_a_folder_without_a_report() {
    let dir = temp_dir("empty");
    let o = Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(["report", s(&dir)])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.starts_with(&format!(
            "spidar: {}: cannot read",
            dir.join("report.json").display()
        )),
        "{err}"
    );
    std::fs::write(dir.join("report.json"), "{\"stages\": [").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(["report", s(&dir)])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains(&format!("{}:1:", dir.join("report.json").display())),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
