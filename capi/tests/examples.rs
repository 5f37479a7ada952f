//! The examples as an application runs them, against a virtual device:
//! `examples/spring.c` compiled with the system `cc` against
//! `include/spidar.h` and the built `libspidar_capi`, and
//! `python/examples/spring.py` through the Python package. Each must arm
//! the device, render a spring (the rendered force points to the target),
//! disarm it, and lose no frame. Judged by what the device reported (its
//! states' contents), not by how fast this machine ran the loop; the
//! virtual device's heartbeat timeout is 2 s so that a loop held off the
//! CPU for a while is not disarmed (the watchdog has its own test,
//! `tests/calls.rs`, in device time).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The directory of the libspidar_capi this test was built with: cargo builds
/// the crate's cdylib into `deps/` beside the test binary (the copy one
/// level up is `cargo build`'s, and may be older).
fn library_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let dir = exe.parent().unwrap().to_path_buf();
    assert!(
        dir.join("libspidar_capi.so").is_file(),
        "no libspidar_capi.so in {} (cargo builds it with the crate's tests)",
        dir.display()
    );
    dir
}

/// Runs `cmd`, failing after `limit` (a hung example, not a slow one).
/// Its output is read while it runs (a full pipe would stop it).
fn run(cmd: &mut Command, limit: Duration) -> Output {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    let drain = |mut pipe: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut bytes = Vec::new();
            let _ = pipe.read_to_end(&mut bytes);
            bytes
        })
    };
    let stdout = drain(Box::new(child.stdout.take().unwrap()));
    let stderr = drain(Box::new(child.stderr.take().unwrap()));
    let t0 = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            panic!("{cmd:?} still running after {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    Output {
        status,
        stdout: stdout.join().unwrap(),
        stderr: stderr.join().unwrap(),
    }
}

fn numbers(line: &str, key: &str) -> Option<Vec<f64>> {
    let rest = line.strip_prefix(key)?.strip_prefix(' ')?;
    rest.split_whitespace().map(|w| w.parse().ok()).collect()
}

/// What a spring example printed, checked: armed, a spring rendered
/// towards the target, disarmed, no frame lost on the link.
fn check_spring(out: &Output) {
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{}\n{stdout}\n{stderr}", out.status);
    let lines: Vec<&str> = stdout.lines().collect();
    let target = lines
        .iter()
        .find_map(|l| numbers(l, "target"))
        .expect("a target line");
    assert!(lines.contains(&"armed 1"), "{stdout}");
    assert!(lines.contains(&"disarmed 1"), "{stdout}");
    // No frame lost on the way: every gap in the sequence numbers is a
    // frame the device itself dropped because the host had not read the
    // link in time (it does not wait for a slow reader, as on USB), which
    // a loaded machine may cause; none rejected. The device's count is
    // read after the host's and may hold drops since (`link_stats`), so
    // the gaps are at most the drops: equal only on an idle machine.
    let link = lines
        .iter()
        .find_map(|l| l.strip_prefix("link "))
        .expect("a link line");
    let field = |name: &str| -> u64 {
        let words: Vec<&str> = link.split_whitespace().collect();
        let i = words.iter().position(|w| *w == name).unwrap();
        words[i + 1].parse().unwrap()
    };
    assert!(field("states") > 100, "{stdout}");
    assert!(
        field("lost") <= field("device_dropped"),
        "frames lost on the link: {stdout}"
    );
    assert_eq!(field("rejected"), 0, "{stdout}");
    // Every sampled state while armed, where the spring pulls (farther
    // than 30 mm from the target) and renders a force: the force points to
    // the target (the state is a few ms older than the force it shows,
    // and the end-effector moves at ~120 mm/s).
    let mut checked = 0;
    for v in lines.iter().filter_map(|l| numbers(l, "state")) {
        let (armed, p, f) = (v[1], &v[2..5], &v[5..8]);
        let to_target: Vec<f64> = (0..3).map(|k| target[k] - p[k]).collect();
        let d = to_target.iter().map(|x| x * x).sum::<f64>().sqrt();
        let fnorm = f.iter().map(|x| x * x).sum::<f64>().sqrt();
        if armed != 1.0 || d < 30.0 || fnorm < 0.2 {
            continue;
        }
        let cos = (0..3).map(|k| f[k] * to_target[k]).sum::<f64>() / (d * fnorm);
        assert!(
            cos > 0.9,
            "force {f:?} at {p:?} does not pull to {target:?}: {stdout}"
        );
        checked += 1;
    }
    assert!(
        checked >= 10,
        "only {checked} states rendered the spring: {stdout}"
    );
    let hz = lines.iter().find_map(|l| numbers(l, "loop_hz")).unwrap();
    assert!(hz[0] > 0.0);
    eprintln!("{stdout}");
}

#[test]
fn the_c_spring_example_renders_a_spring_on_a_virtual_device() {
    let lib = library_dir();
    let tmp = std::env::temp_dir().join(format!("spidar-capi-spring-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let exe = tmp.join("spring");
    let repo = repo();
    let cc = run(
        Command::new("cc")
            .arg("-O2")
            .arg("-Wall")
            .arg("-Werror")
            .arg("-I")
            .arg(repo.join("capi/include"))
            .arg(repo.join("capi/examples/spring.c"))
            .arg("-L")
            .arg(&lib)
            .arg("-lspidar_capi")
            .arg(format!("-Wl,-rpath,{}", lib.display()))
            .arg("-lm")
            .arg("-o")
            .arg(&exe),
        Duration::from_secs(120),
    );
    assert!(
        cc.status.success(),
        "cc: {}",
        String::from_utf8_lossy(&cc.stderr)
    );
    // The rpath names the fresh library; cargo's LD_LIBRARY_PATH, which
    // would come first, also names `cargo build`'s copy.
    let out = run(
        Command::new(&exe)
            .args(["--virtual", "--seconds", "2", "--heartbeat-ms", "2000"])
            .env_remove("LD_LIBRARY_PATH"),
        Duration::from_secs(120),
    );
    check_spring(&out);
    let _ = std::fs::remove_dir_all(&tmp);
}

#[test]
fn the_python_spring_example_renders_a_spring_on_a_virtual_device() {
    if Command::new("python3").arg("--version").output().is_err() {
        eprintln!("SKIPPED: python3 is not installed, the Python example did not run");
        return;
    }
    let lib = library_dir();
    let repo = repo();
    let out = run(
        Command::new("python3")
            .arg(repo.join("python/examples/spring.py"))
            .args(["--virtual", "--seconds", "2", "--heartbeat-ms", "2000"])
            .env("PYTHONPATH", repo.join("python"))
            .env("SPIDAR_LIBRARY", lib.join("libspidar_capi.so")),
        Duration::from_secs(120),
    );
    check_spring(&out);
}

#[test]
fn the_python_package_names_a_missing_library_and_how_to_build_it() {
    if Command::new("python3").arg("--version").output().is_err() {
        eprintln!("SKIPPED: python3 is not installed, the Python package was not loaded");
        return;
    }
    let out = run(
        Command::new("python3")
            .args(["-c", "import spidar; spidar.library()"])
            .env("PYTHONPATH", repo().join("python"))
            .env("SPIDAR_LIBRARY", "/nonexistent/libspidar_capi.so"),
        Duration::from_secs(60),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("SPIDAR_LIBRARY=/nonexistent/libspidar_capi.so: no such file")
            && stderr.contains("cargo build --release -p spidar-capi"),
        "{stderr}"
    );
}
