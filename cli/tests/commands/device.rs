//! `spidar device` against a virtual device, and where its options go.

use spidar::sim::virtual_device::Trajectory;
use spidar_core::correction::CorrectionModel;
use spidar_tests::{blob, patient_virtual_device, sim_device};

/// `spidar device`'s port options go before or after the subcommand; a
/// missing port and a bad duration are argument errors that say so.
#[test]
fn device_command_line_takes_the_port_anywhere() {
    let spidar = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_spidar"))
            .args(args)
            .output()
            .expect("run spidar");
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).to_string(),
        )
    };
    for args in [
        &["device", "info", "--port", "/nonexistent/tty"][..],
        &["device", "--port", "/nonexistent/tty", "info"][..],
        &[
            "device",
            "info",
            "--timeout-ms",
            "20",
            "--port",
            "/nonexistent/tty",
        ][..],
    ] {
        let (ok, err) = spidar(args);
        assert!(
            !ok && err.contains("/nonexistent/tty") && err.contains("no such port"),
            "{args:?}: {err}"
        );
    }
    // Negative coordinates are values, not options.
    for args in [
        &[
            "collect",
            "--port",
            "/nonexistent/tty",
            "--geometry",
            "/nonexistent/g.toml",
            "--centre",
            "-100,0,1500",
            "--out",
            "/nonexistent/s.csv",
        ][..],
        &[
            "init",
            "--port",
            "/nonexistent/tty",
            "--geometry",
            "/nonexistent/g.toml",
            "--target",
            "-100,-5,1500",
            "--out",
            "/nonexistent/i.toml",
        ][..],
    ] {
        let (ok, err) = spidar(args);
        assert!(
            !ok && err.contains("/nonexistent/g.toml"),
            "{args:?}: {err}"
        );
    }
    let (ok, err) = spidar(&["device", "info"]);
    assert!(!ok && err.contains("--port"), "{err}");
    let (ok, err) = spidar(&["device", "arm", "--hold=-1", "--port", "/nonexistent/tty"]);
    assert!(
        !ok && err.contains("--hold") && !err.contains("serial port"),
        "{err}"
    );
    // Durations and counts that cannot be: refused before any port opens
    // (`--frames 0` printed a frame, `--seconds NaN` ran for ever).
    for args in [
        &[
            "device",
            "stream",
            "--frames",
            "0",
            "--port",
            "/nonexistent/tty",
        ][..],
        &[
            "device",
            "stream",
            "--seconds",
            "NaN",
            "--port",
            "/nonexistent/tty",
        ][..],
        &[
            "device", "force", "1", "0", "0", "--hold", "NaN", "--port", "/x",
        ][..],
        &["virtual-device", "--seconds", "NaN"][..],
        &["virtual-device", "--seconds", "0"][..],
        &["virtual-device", "--speed=-2"][..],
    ] {
        let (ok, err) = spidar(args);
        let option = args.iter().find(|a| a.starts_with("--") && **a != "--port");
        let option = option.unwrap().split('=').next().unwrap();
        assert!(
            !ok && err.contains(option) && !err.contains("serial port"),
            "{args:?}: {err}"
        );
    }
}

/// A reply timeout for the client that a busy machine cannot exceed: this
/// binary's calibration tests load every core while the virtual device's
/// thread must answer in real time.
const PATIENT_CLIENT: [&str; 2] = ["--timeout-ms", "5000"];

/// `spidar device force` reports what the device rendered, from its state
/// frames, and why it differs from the request (issue 13, point 3).
#[test]
fn device_force_reports_the_rendered_force() {
    let dev = sim_device();
    let vd = patient_virtual_device(Trajectory::Hold);
    // Flashed by `spidar flash`, not by a client of this process: a port this
    // process held could be inherited, locked, by a `spidar` that another test
    // of this binary starts at that moment, and be busy for the next command.
    let model =
        std::env::temp_dir().join(format!("spidar-device-force-{}.blob", std::process::id()));
    std::fs::write(&model, blob(&dev, CorrectionModel::None, 11)).unwrap();
    let flashed = std::process::Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(["flash", "--port", vd.port_path()])
        .args(PATIENT_CLIENT)
        .arg(&model)
        .output()
        .expect("run spidar");
    assert!(
        flashed.status.success(),
        "{}",
        String::from_utf8_lossy(&flashed.stderr)
    );
    let force = |f: [&str; 3]| {
        let port = vd.port_path().to_string();
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_spidar"))
            .args(["device", "force", "--hold", "0.3", "--port", &port])
            .args(PATIENT_CLIENT)
            .arg("--")
            .args(f)
            .output()
            .expect("run spidar");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).to_string()
    };
    // `device info` says the device's state with its fault bits by name.
    let port = vd.port_path().to_string();
    let info = std::process::Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(["device", "info", "--port", &port])
        .args(PATIENT_CLIENT)
        .output()
        .expect("run spidar");
    assert!(
        info.status.success(),
        "{}",
        String::from_utf8_lossy(&info.stderr)
    );
    let info = String::from_utf8_lossy(&info.stdout).to_string();
    assert!(info.contains("state: disarmed, faults none"), "{info}");
    assert!(info.contains("model id 0x0000000b"), "{info}");
    let small = force(["0", "0", "2"]);
    assert!(
        small.starts_with("requested [0, 0, 2] N; rendered [") && !small.contains("limited"),
        "{small}"
    );
    let z: f64 = small
        .split("rendered [")
        .nth(1)
        .and_then(|r| r.split(']').next())
        .and_then(|r| r.split(", ").nth(2))
        .and_then(|v| v.parse().ok())
        .expect("rendered z");
    assert!((z - 2.0).abs() < 0.1, "{small}");
    let huge = force(["1e9", "0", "0"]);
    assert!(
        huge.starts_with("requested [1000000000, 0, 0] N; rendered [")
            && huge.contains("the device limited it to"),
        "{huge}"
    );
    assert!(huge.contains("disarmed"), "{huge}");
}
