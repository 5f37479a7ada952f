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
