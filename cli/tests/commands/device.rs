//! `spidar device` against a virtual device, and where its options go.

use spidar::sim::virtual_device::{
    plant_of, spawn, PlantPath, PlantRequest, Trajectory, VirtualDevice, VirtualDeviceConfig,
};
use spidar_core::correction::CorrectionModel;
use spidar_tests::{blob, device_time_reaches, patient_virtual_device, sim_device};

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
    // Disarmed, motors off (a busy machine may have left LOOP_OVERRUN).
    assert!(
        info.contains("state: disarmed, motors off, faults "),
        "{info}"
    );
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

/// `spidar device stream` on a device that has no geometry says why every
/// position is 0, and says nothing of it once a model is flashed.
#[test]
fn device_stream_without_geometry_says_why_positions_are_zero() {
    let vd = patient_virtual_device(Trajectory::Hold);
    let stream = || {
        spidar(&[
            "device",
            "stream",
            "--frames",
            "3",
            "--port",
            vd.port_path(),
        ])
    };
    let (ok, csv, err) = stream();
    assert!(ok, "{err}");
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(rows.len(), 3, "{csv}");
    assert!(
        rows.iter().all(|r| r.split(',').nth(1) == Some("0")),
        "{csv}"
    );
    assert!(
        err.contains("the device has no geometry") && err.contains("spidar flash"),
        "{err}"
    );
    let (ok, _, err) = flash(
        &vd,
        "stream-geometry",
        &blob(&sim_device(), CorrectionModel::None, 12),
    );
    assert!(ok, "{err}");
    let (ok, csv, err) = stream();
    assert!(ok, "{err}");
    assert!(!err.contains("no geometry"), "{err}");
    assert!(
        csv.lines().skip(1).all(|r| r.ends_with("0x0000000c")),
        "{csv}"
    );
}

/// Runs `spidar` with a patient client: (success, stdout, stderr).
fn spidar(args: &[&str]) -> (bool, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(args)
        .args(PATIENT_CLIENT)
        .output()
        .expect("run spidar");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).to_string(),
        String::from_utf8_lossy(&out.stderr).to_string(),
    )
}

/// Writes `bytes` to a model file of this test process and flashes it with
/// `spidar flash` (a port this process held could be inherited by a
/// `spidar` another test starts, see `device_force_reports_the_rendered_force`).
fn flash(vd: &VirtualDevice, name: &str, bytes: &[u8]) -> (bool, String, String) {
    let model = std::env::temp_dir().join(format!("spidar-{name}-{}.blob", std::process::id()));
    std::fs::write(&model, bytes).unwrap();
    let r = spidar(&["flash", "--port", vd.port_path(), model.to_str().unwrap()]);
    let _ = std::fs::remove_file(&model);
    r
}

/// The plant `spidar virtual-device` runs by default (seed 1, the orbit),
/// behind a device whose heartbeat timeout is `heartbeat_ms`.
fn default_virtual_device(heartbeat_ms: u32) -> VirtualDevice {
    let plant = plant_of(&PlantRequest {
        seed: 1,
        config: None,
        effects: Vec::new(),
        path: PlantPath::Orbit,
        points: 50,
    })
    .unwrap();
    let mut config = VirtualDeviceConfig::default();
    config.device.control.safety.heartbeat_timeout_ms = heartbeat_ms;
    spawn(config, plant).unwrap()
}

/// The rendered force of `device force`'s report line.
fn rendered(line: &str) -> [f64; 3] {
    let inside = line
        .split("rendered [")
        .nth(1)
        .and_then(|r| r.split(']').next())
        .unwrap_or_else(|| panic!("no rendered force in {line}"));
    let v: Vec<f64> = inside.split(", ").map(|x| x.parse().unwrap()).collect();
    [v[0], v[1], v[2]]
}

/// The default virtual device renders force with its own calibration
/// flashed over the link while its end-effector would be on its orbit (2 s
/// after boot, a quarter turn): the model homes the device at home and the
/// orbit starts there (issue 37, finding 7: 0 N with KINEMATICS, exit 0).
/// Timed on the device's clock, not the test's.
#[test]
fn device_force_renders_on_the_default_virtual_device_with_its_own_calibration() {
    let vd = default_virtual_device(2000);
    let model = blob(&vd.plant().device, CorrectionModel::None, 0x37);
    assert!(device_time_reaches(&vd, 2_000_000));
    let (ok, _, err) = flash(&vd, "own-calibration", &model);
    assert!(ok, "{err}");
    // Two seconds of orbit after the flash: a device homed off its path
    // has latched KINEMATICS long before.
    let flashed_us = vd.status().device_time_us;
    assert!(device_time_reaches(&vd, flashed_us + 2_000_000));
    let port = vd.port_path();
    let (ok, out, err) = spidar(&[
        "device", "force", "--port", port, "--hold", "0.5", "1", "0", "0",
    ]);
    assert!(ok, "{out}{err}");
    let f = rendered(&out);
    assert!(
        (f[0] - 1.0).abs() < 0.05 && f[1].abs() < 0.05 && f[2].abs() < 0.05,
        "{out}"
    );
    // Off after the force; no fault of the strings (a busy machine may have
    // left LOOP_OVERRUN, or HEARTBEAT_LOST between the two commands).
    let (ok, info, err) = spidar(&["device", "info", "--port", port]);
    assert!(ok, "{err}");
    assert!(
        info.contains("state: disarmed, motors off, faults ") && !info.contains("KINEMATICS"),
        "{info}"
    );
}

/// `device force` fails, naming the fault and what to do, when the device
/// disarms itself instead of rendering: a model whose spools are a third
/// larger than the device's on four strings, on the moving default plant,
/// reads strings that disagree (`KINEMATICS`).
#[test]
fn device_force_fails_when_the_device_disarms_itself() {
    let vd = default_virtual_device(2000);
    let mut wrong = spidar_tests::calibration(&vd.plant().device, CorrectionModel::None);
    for law in wrong.strings.iter_mut().take(4) {
        law.winding_mm[0] *= 1.3;
    }
    let model = spidar_core::blob::compile(&wrong, 0x38, 0).unwrap();
    let (ok, _, err) = flash(&vd, "wrong-spools", &model);
    assert!(ok, "{err}");
    let flashed_us = vd.status().device_time_us;
    assert!(device_time_reaches(&vd, flashed_us + 1_000_000));
    let port = vd.port_path();
    let (ok, out, err) = spidar(&[
        "device", "force", "--port", port, "--hold", "0.3", "1", "0", "0",
    ]);
    assert!(!ok, "{out}{err}");
    // After the line saying what it holds.
    assert!(
        err.lines().any(|l| l.starts_with(&format!(
            "spidar: {port}: requested [1, 0, 0] N; rendered [0.000, 0.000, 0.000] N"
        ))) && err
            .contains("the device disarmed itself (KINEMATICS: the string lengths do not agree")
            && err.contains("`spidar init`")
            && err.contains("the force is off and the device disarmed"),
        "{err}"
    );
}

/// A heartbeat lost while holding fails `device arm --hold` and `device
/// force`, saying so; `info` then says the motors still hold pre-tension,
/// which is why `flash` is refused, until `disarm` (issue 37, findings 7
/// and 8). The device's heartbeat timeout is 1 ms: shorter than the time
/// between two of the command's heartbeats, so every hold loses it.
#[test]
fn device_commands_fail_when_the_heartbeat_is_lost_and_info_says_the_motors_are_on() {
    let dev = sim_device();
    let mut config = VirtualDeviceConfig::default();
    config.device.control.safety.heartbeat_timeout_ms = 1;
    let vd = spawn(
        config,
        spidar::sim::virtual_device::Plant::new(dev.clone(), Trajectory::Hold),
    )
    .unwrap();
    let model = blob(&dev, CorrectionModel::None, 0x39);
    let (ok, _, err) = flash(&vd, "heartbeat", &model);
    assert!(ok, "{err}");
    let port = vd.port_path();
    let (ok, out, err) = spidar(&["device", "arm", "--port", port, "--hold", "0.3"]);
    assert!(!ok, "{out}{err}");
    // After the line saying what it holds.
    assert!(
        err.lines().any(|l| l.starts_with(&format!(
            "spidar: {port}: armed, then the device lost the heartbeat"
        ))) && err.contains("HEARTBEAT_LOST: no request came within the heartbeat timeout")
            && err.contains("`spidar device disarm`"),
        "{err}"
    );
    let (ok, info, err) = spidar(&["device", "info", "--port", port]);
    assert!(ok, "{err}");
    assert!(
        info.contains("state: disarmed by a fault, motors on")
            && info.contains("faults HEARTBEAT_LOST"),
        "{info}"
    );
    let (ok, _, err) = flash(&vd, "heartbeat-again", &model);
    assert!(!ok && err.contains("the motors are on"), "{err}");
    let (ok, out, err) = spidar(&[
        "device", "force", "--port", port, "--hold", "0.3", "0", "0", "1",
    ]);
    assert!(!ok, "{out}{err}");
    assert!(
        err.contains("the device lost the heartbeat during the hold")
            && err.contains("the force is off and the device disarmed"),
        "{err}"
    );
    let (ok, info, err) = spidar(&["device", "info", "--port", port]);
    assert!(ok, "{err}");
    assert!(info.contains("state: disarmed, motors off"), "{info}");
    let (ok, _, err) = flash(&vd, "heartbeat-after", &model);
    assert!(ok, "{err}");
}

/// A blob of another string count than the model the device runs is
/// refused before the upload, naming both counts and the option (the
/// survey's 4-string blob on an 8-string device flashed "verified", and
/// the first sign was a KINEMATICS fault on arming); with
/// `--string-count-change` it goes, and `device info` says the count.
#[test]
fn a_model_of_another_string_count_is_refused_unless_the_rig_was_rebuilt() {
    let vd = default_virtual_device(2000);
    let eight = blob(&vd.plant().device, CorrectionModel::None, 0x81);
    let (ok, _, err) = flash(&vd, "eight-strings", &eight);
    assert!(ok, "{err}");
    let mut four = spidar::sim::SimConfig::default();
    four.nominal.strings = 4;
    four.abnormal_motor.enabled = false;
    let four = spidar::sim::SimulatedDevice::new(&four, 3).unwrap();
    let four_blob = blob(&four, CorrectionModel::None, 0x82);
    let (ok, _, err) = flash(&vd, "four-strings", &four_blob);
    assert!(!ok, "a 4-string model flashed over an 8-string one");
    assert!(
        err.contains("a model of 4 strings, and the device runs one of 8 (model id 0x00000081)")
            && err.contains("--string-count-change"),
        "{err}"
    );
    let (ok, info, err) = spidar(&["device", "info", "--port", vd.port_path()]);
    assert!(ok, "{err}");
    assert!(info.contains("model id 0x00000081 in slot"), "{info}");
    assert!(info.contains(": 8 strings, "), "{info}");

    let model = std::env::temp_dir().join(format!("spidar-rebuilt-{}.blob", std::process::id()));
    std::fs::write(&model, &four_blob).unwrap();
    let (ok, _, err) = spidar(&[
        "flash",
        "--port",
        vd.port_path(),
        model.to_str().unwrap(),
        "--string-count-change",
    ]);
    let _ = std::fs::remove_file(&model);
    assert!(ok, "{err}");
    let (ok, info, err) = spidar(&["device", "info", "--port", vd.port_path()]);
    assert!(ok, "{err}");
    assert!(info.contains(": 4 strings, "), "{info}");
}
