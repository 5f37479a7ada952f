//! `spidar collect --simulate` as a user runs it: a collection stopped and
//! run again (a new process, so a new simulated device) goes on to the end,
//! and a lattice the strings cannot reach is refused naming the option.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use spidar::data::dataset::Session;

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("spidar-collect-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn spidar(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(args)
        .output()
        .expect("run the spidar binary")
}

fn said(o: &Output) -> String {
    format!(
        "status {:?}\nstdout:\n{}\nstderr (last 2000 bytes):\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
            .chars()
            .rev()
            .take(2000)
            .collect::<String>()
            .chars()
            .rev()
            .collect::<String>()
    )
}

/// `spidar collect --simulate 3 --cells 3 --size-mm SIZE --out OUT`, then
/// `extra`.
fn collect_simulated(out: &Path, size_mm: &str, extra: &[&str]) -> Output {
    let mut args = vec![
        "collect",
        "--simulate",
        "3",
        "--cells",
        "3",
        "--size-mm",
        size_mm,
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    spidar(&args)
}

#[test]
fn a_simulated_collection_stopped_twice_resumes_to_the_end_and_reads_back() {
    let dir = temp_dir("resume");
    let out = dir.join("lat3b.csv");
    let run = |extra: &[&str]| collect_simulated(&out, "300", extra);
    let first = run(&["--max-cells", "10"]);
    assert!(first.status.success(), "{}", said(&first));
    // The survey's case: the same command again (it exited 1 on line 12,
    // "time since home goes backwards ... same home capture").
    let second = run(&["--max-cells", "10"]);
    assert!(second.status.success(), "{}", said(&second));
    let text = String::from_utf8_lossy(&second.stdout);
    assert!(text.contains("resumed from 10 of 27"), "{text}");
    // A write cut short before the third run: cut off, said, collected again.
    let whole = std::fs::read_to_string(&out).unwrap();
    let half_row = whole.lines().last().unwrap()[..40].to_string();
    std::fs::write(&out, format!("{whole}{half_row}")).unwrap();
    let third = run(&[]);
    assert!(third.status.success(), "{}", said(&third));
    let text = String::from_utf8_lossy(&third.stdout);
    assert!(text.contains("27/27 done: complete"), "{text}");
    assert!(text.contains("line 22: cut off"), "{text}");

    let session = Session::load(&out).expect("the dataset reader reads it");
    assert_eq!(session.samples.len(), 27);
    let homes: Vec<u64> = session.samples.iter().map(|s| s.home.unwrap()).collect();
    // Three runs, three boots of the simulated device: three home captures.
    assert_eq!(homes[0], homes[9]);
    assert_eq!(homes[10], homes[19]);
    assert_eq!(homes[20], homes[26]);
    assert!(homes[0] != homes[10] && homes[10] != homes[20] && homes[0] != homes[20]);
    for w in session.samples.windows(2) {
        assert!(w[1].t_s >= w[0].t_s, "t_s {} -> {}", w[0].t_s, w[1].t_s);
    }
}

#[test]
fn a_lattice_beyond_the_anchors_is_refused_naming_size_mm_and_the_largest_that_fits() {
    let dir = temp_dir("too-big");
    let out = dir.join("c5000.csv");
    let o = collect_simulated(&out, "5000", &[]);
    assert!(!o.status.success(), "{}", said(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--size-mm 5000 is too large"), "{err}");
    assert!(err.contains("convex hull"), "{err}");
    // The frame's anchors are 2200 mm apart; the lattice is centred 1.1 m
    // from each face.
    assert!(
        err.contains("the largest that fits around this centre is --size-mm 2200.0"),
        "{err}"
    );
    assert!(!out.exists(), "no file is started");
}
