//! What `spidar --help` tells a user.

/// The help says what a user needs without the source (issue 13, point 4):
/// every effect kind of `simulate --effect` for both physics, the virtual
/// device's blob capacity as the firmware's, one option layout (no
/// per-value paragraphs) in the operator procedures.
#[test]
fn help_texts_list_effects_units_and_the_firmware_capacity() {
    let help = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_spidar"))
            .args(args)
            .output()
            .expect("run spidar");
        assert!(out.status.success());
        String::from_utf8_lossy(&out.stdout).to_string()
    };
    let simulate = help(&["simulate", "--help"]);
    for kind in [
        "offset",
        "scale",
        "winding",
        "eccentricity",
        "elasticity",
        "backlash",
        "drift",
        "slip",
        "speed",
        "anchor",
        "tracker_scale",
        "drift-all",
        "frame-flex",
        "marker-offset",
        "heavy-string",
        "latency:string=2,ms=6",
    ] {
        assert!(simulate.contains(kind), "simulate --help lacks {kind}");
    }
    let kib = spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY / 1024;
    let vd = help(&["virtual-device", "--help"]);
    assert!(vd.contains(&format!("[default: {kib}]")), "{vd}");
    for command in ["collect", "init", "monitor"] {
        let h = help(&[command, "--help"]);
        assert!(!h.contains("Possible values:"), "{command}: {h}");
        assert!(h.contains("[default: "), "{command}: {h}");
    }
}

/// Output to a reader that closed its pipe (`spidar ... | head -5`) ends
/// the run quietly: exit 0, no panic and no backtrace (`print!` panicked
/// on the broken pipe). The pipe's read end is closed before the command
/// writes (a simulation takes longer than that); had it written first, the
/// pipe would have taken it and the run passes the same.
#[test]
fn output_to_a_closed_pipe_ends_quietly() {
    let dir = std::env::temp_dir().join(format!("spidar-closed-pipe-{}", std::process::id()));
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(["simulate", "--out", dir.to_str().unwrap(), "--seed", "1"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run spidar");
    drop(child.stdout.take());
    let out = child.wait_with_output().expect("wait for spidar");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && !err.contains("panicked"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
