//! `spidar compile` refuses what cannot be a device and never spoils a file:
//! an output path over an input, impossible calibrations, budgets that are
//! not numbers, blobs over the budget (issue 37, findings 2 and 6).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use spidar_core::correction::CorrectionModel;
use spidar_core::model::{Calibration, Frame, StringLaw, StringLayout};
use spidar_core::STRINGS;

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("spidar-compile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn spidar(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(args)
        .env("SOURCE_DATE_EPOCH", "0")
        .output()
        .expect("run the spidar binary")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 2 m cube with the strings' exits at its corners, home at its centre,
/// 10 mm spools that shrink a little as they pay out.
fn cube() -> Calibration {
    let half = 1000.0;
    Calibration {
        frame: Frame {
            anchors: core::array::from_fn(|i| {
                [1, 2, 4].map(|bit| if i & bit == 0 { -half } else { half })
            }),
            layout: StringLayout::ALL,
            home: [0.0; 3],
            room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            room_translation: [0.0, 0.0, 1500.0],
            room_scale: 1.0,
        },
        strings: [StringLaw::polynomial(4096, [10.0, -0.002, 0.0, 0.0]); STRINGS],
        effects: Vec::new(),
        correction: CorrectionModel::None,
        length_scale_mm: [0.0; STRINGS],
        kinematics: Default::default(),
        home: None,
    }
}

fn write(dir: &Path, name: &str, c: &Calibration) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, serde_json::to_string(c).unwrap()).unwrap();
    path
}

/// `spidar compile` of `calibration`, written as `{name}.json` in `dir`,
/// to `{name}.blob`: its output and the blob's path.
fn compile_in(dir: &Path, name: &str, calibration: &Calibration) -> (Output, PathBuf) {
    let cal = write(dir, &format!("{name}.json"), calibration);
    let blob = dir.join(format!("{name}.blob"));
    let o = spidar(&["compile", "--calibration", s(&cal), "--out", s(&blob)]);
    (o, blob)
}

fn failure(o: &Output) -> String {
    assert!(
        !o.status.success(),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn an_output_over_its_input_is_refused_and_the_input_kept() {
    let dir = temp_dir("over");
    let cal = write(&dir, "calibration.json", &cube());
    let before = std::fs::read(&cal).unwrap();
    let o = spidar(&["compile", "--calibration", s(&cal), "--out", s(&cal)]);
    let err = failure(&o);
    assert!(
        err.contains("`--out`") && err.contains("`--calibration`"),
        "{err}"
    );
    assert_eq!(
        std::fs::read(&cal).unwrap(),
        before,
        "the calibration was overwritten"
    );
    // The same file by another spelling.
    let other = dir.join(".").join("calibration.json");
    let err = failure(&spidar(&[
        "compile",
        "--calibration",
        s(&cal),
        "--out",
        s(&other),
    ]));
    assert!(err.contains("`--out`"), "{err}");
    assert_eq!(std::fs::read(&cal).unwrap(), before);
    // A plausible calibration to another path compiles.
    let blob = dir.join("model.blob");
    let o = spidar(&["compile", "--calibration", s(&cal), "--out", s(&blob)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(blob.exists());
    // Its correction in words, not a Rust debug print ("None correction").
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("bytes: no position correction, ") && !out.contains("None correction"),
        "{out}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn calibrations_that_cannot_be_a_device_do_not_compile() {
    let dir = temp_dir("impossible");
    let mut cases: Vec<(&str, Calibration, &str)> = Vec::new();
    let mut c = cube();
    c.frame.room_rotation[0][1] = 0.2;
    cases.push(("skewed", c, "frame.room_rotation"));
    let mut c = cube();
    c.frame.anchors[5] = c.frame.anchors[1];
    cases.push(("coincident", c, "frame.anchors[1] and frame.anchors[5]"));
    let mut c = cube();
    c.frame.anchors[2] = [1e12, 0.0, 0.0];
    cases.push(("far", c, "frame.anchors[2]"));
    let mut c = cube();
    c.strings[4].winding_mm[0] = -10.0;
    cases.push(("negative-winding", c, "strings[4].winding_mm"));
    for (name, scale) in [
        ("scale-1000", 1000.0),
        ("scale-tiny", 1e-30),
        ("scale-0", 0.0),
    ] {
        let mut c = cube();
        c.frame.room_scale = scale;
        cases.push((name, c, "frame.room_scale"));
    }
    for (name, calibration, field) in cases {
        let cal = write(&dir, &format!("{name}.json"), &calibration);
        let blob = dir.join(format!("{name}.blob"));
        let err = failure(&spidar(&[
            "compile",
            "--calibration",
            s(&cal),
            "--out",
            s(&blob),
        ]));
        assert!(
            err.contains(&format!("{name}.json"))
                && err.contains(field)
                && err.contains("not a device"),
            "{name}: {err}"
        );
        assert!(!blob.exists(), "{name}: a blob was written");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn budgets_that_are_not_numbers_are_refused_and_over_budget_blobs_not_written() {
    let dir = temp_dir("budget");
    let cal = write(&dir, "calibration.json", &cube());
    let blob = dir.join("model.blob");
    for budget in ["NaN", "-1", "0", "inf"] {
        let option = format!("--budget-mm={budget}");
        let err = failure(&spidar(&[
            "compile",
            "--calibration",
            s(&cal),
            "--out",
            s(&blob),
            &option,
        ]));
        assert!(err.contains("--budget-mm"), "{budget}: {err}");
        assert!(!blob.exists(), "{budget}: a blob was written");
    }
    // A test session measures the fixed-point error; no blob meets a
    // budget of 1e-300 mm.
    let o = spidar(&[
        "simulate",
        "--out",
        s(&dir),
        "--seed",
        "2",
        "--kind",
        "random",
        "--name",
        "test",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let test = dir.join("test.csv");
    let args = |extra: &[&'static str]| {
        let mut a = vec![
            "compile".to_string(),
            "--calibration".into(),
            s(&cal).into(),
            "--out".into(),
            s(&blob).into(),
            "--test".into(),
            s(&test).into(),
            "--budget-mm".into(),
            "1e-300".into(),
        ];
        a.extend(extra.iter().map(|e| e.to_string()));
        a
    };
    let run = |a: Vec<String>| spidar(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = failure(&run(args(&[])));
    assert!(
        err.contains("exceeds the budget") && err.contains("no blob written"),
        "{err}"
    );
    assert!(!blob.exists());
    // Asked for: written, and the command still fails saying so.
    let err = failure(&run(args(&["--write-over-budget"])));
    assert!(
        err.contains("written to") && err.contains("as asked"),
        "{err}"
    );
    assert!(blob.exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// An SVR correction with more support vectors than the device evaluates
/// within its control loop's tick (an older calibration's, say) does not
/// compile: the error names the file, the count and the most the device
/// takes, and says what to do; no blob is written. One fewer compiles.
#[test]
fn a_correction_the_device_cannot_evaluate_within_its_tick_does_not_compile() {
    use spidar_core::correction::{OutputMode, Standardization, SvrModel, MAX_SUPPORT_VECTORS};
    let dir = temp_dir("svr-budget");
    let svr = |n: usize| {
        let mut c = cube();
        c.correction = CorrectionModel::Svr(SvrModel {
            input: Standardization {
                mean: [0.0; 3],
                std: [500.0; 3],
            },
            output: Standardization {
                mean: [0.0; 3],
                std: [1.0; 3],
            },
            gamma: 1.0,
            support: (0..n)
                .map(|j| {
                    [
                        (j % 10) as f64 * 0.2 - 1.0,
                        (j / 10 % 10) as f64 * 0.2 - 1.0,
                        (j / 100) as f64 * 0.2 - 1.0,
                    ]
                })
                .collect(),
            coef: core::array::from_fn(|a| {
                (0..n).map(|j| 1e-3 * ((j + a) % 7) as f64 - 3e-3).collect()
            }),
            bias: [0.0; 3],
            mode: OutputMode::Residual,
        });
        c
    };
    let most = MAX_SUPPORT_VECTORS as usize;
    let (o, blob) = compile_in(&dir, "over", &svr(most + 1));
    let err = failure(&o);
    assert!(
        err.contains("over.json")
            && err.contains(&format!("`support` has {} entries", most + 1))
            && err.contains(&format!("at most {most}"))
            && err.contains("calibrate again"),
        "{err}"
    );
    assert!(!blob.exists(), "a blob was written");
    let (o, _) = compile_in(&dir, "most", &svr(most));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    std::fs::remove_dir_all(&dir).ok();
}

/// A model whose effect terms alone would overrun the device's tick (eight
/// guide pulleys every string shares) does not compile: the error names the
/// file and the estimated instructions against the budget; seven compile,
/// and `spidar compile` says what their tick takes.
#[test]
fn a_model_whose_tick_would_overrun_does_not_compile() {
    use spidar_core::model::{Effect, EffectTerm, EVERY_STRING};
    use spidar_core::tick_cost::TICK_BUDGET;
    let dir = temp_dir("tick-budget");
    let guides = |n: usize| {
        let mut c = cube();
        c.effects = vec![
            EffectTerm {
                string: EVERY_STRING,
                effect: Effect::Guide { radius_mm: 10.0 },
            };
            n
        ];
        c
    };
    let (o, blob) = compile_in(&dir, "eight", &guides(8));
    let err = failure(&o);
    assert!(
        err.contains("eight.json")
            && err.contains("instructions a tick")
            && err.contains(&format!("over the {TICK_BUDGET}")),
        "{err}"
    );
    assert!(!blob.exists(), "a blob was written");
    let (o, _) = compile_in(&dir, "seven", &guides(7));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains(&format!(
            "an estimated {} of the {TICK_BUDGET}",
            16_270 + 7 * 5_340
        )),
        "{out}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A geometry or a test session of another device than the calibration's
/// is refused, naming the file and what differs (a 3-string calibration
/// compiled beside a 4-anchor geometry, and measured on a 4-encoder
/// session's rows, without a word).
#[test]
fn a_geometry_or_session_of_another_device_is_refused() {
    let dir = temp_dir("other-device");
    let cal = write(&dir, "cube.json", &cube());
    let geometry = dir.join("four.toml");
    std::fs::write(
        &geometry,
        "anchors_mm = [[0, 0, 0], [1000, 0, 0], [0, 1000, 0], [0, 0, 1000]]\n\
         counts_per_rev = 4096\npulley_radius_mm = 10\nhome_mm = [250, 250, 250]\n\
         room_from_device_translation_mm = [0, 0, 0]\n",
    )
    .unwrap();
    let session = dir.join("four.csv");
    std::fs::write(
        &session,
        "t_s,enc0,enc1,enc2,enc3,ots_x,ots_y,ots_z\n0,0,0,0,0,250,250,250\n1,10,20,30,40,251,250,250\n",
    )
    .unwrap();
    let blob = dir.join("cube.blob");
    let o = spidar(&[
        "compile",
        "--calibration",
        s(&cal),
        "--geometry",
        s(&geometry),
        "--out",
        s(&blob),
    ]);
    let err = failure(&o);
    assert!(
        err.contains("four.toml")
            && err.contains("`anchors_mm` is 4 anchors but the calibration has 8 strings"),
        "{err}"
    );
    let o = spidar(&[
        "compile",
        "--calibration",
        s(&cal),
        "--test",
        s(&session),
        "--out",
        s(&blob),
    ]);
    let err = failure(&o);
    assert!(
        err.contains("four.csv")
            && err.contains("4 encoder columns (enc0..enc3)")
            && err.contains("a device of 8 strings"),
        "{err}"
    );
    assert!(!blob.exists());
    let _ = std::fs::remove_dir_all(&dir);
}
