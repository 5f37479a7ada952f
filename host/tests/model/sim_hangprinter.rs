//! The independent simulator's Hangprinter-like robot (the `hangprinter`
//! preset): lines through pulley blocks, spools whose radius changes with
//! the line on them, few static poses under a camera's scatter; the model
//! simulator refuses pulley blocks it does not simulate.

use spidar::procedures::calibrate::report::StageKind;
use spidar::procedures::calibrate::CalibrateConfig;
use spidar::sim::physics::{simulate_session, PhysicsConfig, PhysicsDevice};
use spidar::sim::{SessionKind, SimConfig};

fn hangprinter(seed: u64) -> PhysicsDevice {
    PhysicsDevice::new(&PhysicsConfig::preset("hangprinter").unwrap(), seed).unwrap()
}

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "spidar-hangprinter-test-{}-{name}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Between two poses, each line's length beyond the spool changes by its
/// mechanical advantage times its path's (the runs between the pulley
/// blocks), and the geometry the simulator writes says so.
#[test]
fn lines_through_pulley_blocks_pay_out_their_runs() {
    let device = hangprinter(1);
    assert_eq!(
        device.nominal.mechanical_advantage[..4],
        [2.0, 2.0, 2.0, 4.0]
    );
    let truths = simulate_session(&device, SessionKind::Random { points: 40 }, 3)
        .unwrap()
        .1;
    let mut checked = [0usize; 4];
    for pair in truths.windows(2) {
        for (i, runs) in [2.0, 2.0, 2.0, 4.0].into_iter().enumerate() {
            let path = pair[1].free_mm[i] - pair[0].free_mm[i];
            if path.abs() < 100.0 {
                continue;
            }
            // The guide's arc and the stretch change a little too.
            let line = pair[1].natural_mm[i] - pair[0].natural_mm[i];
            let ratio = line / path;
            assert!(
                (ratio - runs).abs() < 0.05 * runs,
                "string {i}: {ratio} for {runs}"
            );
            checked[i] += 1;
        }
    }
    assert!(checked.iter().all(|&c| c >= 5), "{checked:?}");
    let dir = tmp("geometry");
    device.nominal.write(dir.join("geometry.toml")).unwrap();
    let text = std::fs::read_to_string(dir.join("geometry.toml")).unwrap();
    assert!(
        text.contains("mechanical_advantage = [2.0, 2.0, 2.0, 4.0]"),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pulley blocks are the independent simulator's: the model simulator
/// refuses them, and a count that does not fit the strings, or a ratio
/// below 1, is named.
#[test]
fn pulley_blocks_the_simulators_cannot_run_are_named() {
    let dir = tmp("config");
    let path = dir.join("sim.toml");
    std::fs::write(
        &path,
        "[nominal]\nmechanical_advantage = [2, 2, 2, 2, 2, 2, 2, 2]\n",
    )
    .unwrap();
    let msg = SimConfig::load(&path).unwrap_err().to_string();
    assert!(
        msg.contains("nominal.mechanical_advantage") && msg.contains("--physics independent"),
        "{msg}"
    );
    // Every ratio 1: lines straight to the end-effector, as without the key.
    std::fs::write(
        &path,
        "[nominal]\nmechanical_advantage = [1, 1, 1, 1, 1, 1, 1, 1]\n",
    )
    .unwrap();
    assert!(SimConfig::load(&path).is_ok());
    let physics = |text: &str| {
        std::fs::write(&path, text).unwrap();
        PhysicsConfig::load(&path).map(|_| ())
    };
    let msg = physics("[nominal]\nstrings = 4\nmechanical_advantage = [2, 2, 4]\n")
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("nominal.mechanical_advantage") && msg.contains("3 values for 4 strings"),
        "{msg}"
    );
    let msg = physics("[nominal]\nstrings = 4\nmechanical_advantage = [2, 0.5, 2, 2]\n")
        .unwrap_err()
        .to_string();
    assert!(msg.contains("nominal.mechanical_advantage[1]"), "{msg}");
    assert!(physics(
        "[nominal]\nstrings = 4\nmechanical_advantage = [2, 2, 2, 4]\n\
         [abnormal_motor]\nenabled = false\n"
    )
    .is_ok());
    let _ = std::fs::remove_dir_all(&dir);
}

/// 25 poses calibrate the robot: the effective radii come out near each
/// spool's over its mechanical advantage, and the final model holds out
/// within 1.1 times the plain least-squares reference on 300 other poses
/// (the figures of every seed and size: `physics_bench`'s `hangprinter`
/// case, docs/benchmarks.md).
#[test]
fn a_hangprinter_like_robot_calibrates_from_25_poses_beside_the_plain_fit() {
    let device = hangprinter(2);
    let poses = |points, seed| {
        simulate_session(&device, SessionKind::Random { points }, seed)
            .unwrap()
            .0
    };
    let (train, test) = (poses(25, 2025), poses(300, 2999));
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    let c = crate::calibrate_in_memory(&device.nominal, &train, &test, &cfg);
    let mean = |kind| {
        c.report
            .stages
            .iter()
            .find(|s| s.kind == kind)
            .unwrap()
            .test
            .mean_mm
    };
    let (raw, reference, fin) = (
        mean(StageKind::Raw),
        mean(StageKind::Reference),
        mean(StageKind::Final),
    );
    assert!(raw > 5.0, "raw {raw}");
    assert!(fin <= 1.1 * reference, "final {fin}, reference {reference}");
    let id = &c.loop_result.identification;
    for (i, runs) in [2.0, 2.0, 2.0, 4.0].into_iter().enumerate() {
        let r = id
            .parameters
            .iter()
            .find(|p| p.name == format!("string{i}.r_home"))
            .unwrap()
            .value;
        assert!(
            (r * runs / 75.0 - 1.0).abs() < 0.1,
            "string {i}: r_home {r}"
        );
    }
}
