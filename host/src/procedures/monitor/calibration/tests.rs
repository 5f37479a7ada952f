//! Tests of the calibration as the monitor reads and writes it.

use super::*;

use spidar_core::correction::CorrectionModel;

const TRAINING_HOME: u64 = 0x5eed_0000_0001;

fn slip(string: u8, at_s: f64, mm: f64) -> EffectTerm {
    EffectTerm {
        string,
        effect: Effect::Slip { at_s, mm },
    }
}

/// A calibration of the simulated device whose training slipped string 2
/// under [`TRAINING_HOME`], its effects an offset on string 1.
fn calibration() -> Calibration {
    let device =
        crate::sim::SimulatedDevice::new(&crate::sim::SimConfig::default(), 1).expect("device");
    Calibration {
        frame: device.frame,
        strings: device.laws,
        effects: vec![EffectTerm {
            string: 1,
            effect: Effect::Offset { mm: 0.4 },
        }],
        correction: CorrectionModel::None,
        length_scale_mm: [0.0; STRINGS],
        kinematics: Default::default(),
        home: Some(HomeSlips {
            home_id: TRAINING_HOME,
            slips: vec![slip(2, 30.0, 6.0)],
        }),
    }
}

fn slips_in(effects: &[EffectTerm]) -> usize {
    effects
        .iter()
        .filter(|t| matches!(t.effect, Effect::Slip { .. }))
        .count()
}

/// A slip a refit finds at run time is an event of the home capture the
/// device is under, as a training slip is: it goes into the calibration's
/// home section under the states' `home_id`, not into `effects` (the model
/// for the next home capture), and the next `Home` ends it.
#[test]
fn a_run_time_slip_goes_under_the_current_home_capture() {
    let previous = calibration();
    // Under the training's capture: its slip (refitted) and a new one.
    let mut refitted = under_home(&previous, Some(TRAINING_HOME)).effects;
    refitted[1] = slip(2, 30.0, 6.2);
    refitted.push(slip(5, 12.5, -3.0));
    let (effects, home) = split_home_slips(&refitted, &previous, Some(TRAINING_HOME));
    assert_eq!(effects, previous.effects);
    assert_eq!(
        home,
        Some(HomeSlips {
            home_id: TRAINING_HOME,
            slips: vec![slip(2, 30.0, 6.2), slip(5, 12.5, -3.0)],
        })
    );
    let refit = Calibration {
        effects,
        home,
        ..previous.clone()
    };
    // The device after a new `Home`: neither slip applies any more.
    let next = TRAINING_HOME + 1;
    assert_eq!(slips_in(&under_home(&refit, Some(next)).effects), 0);
    assert_eq!(
        slips_in(&under_home(&refit, Some(TRAINING_HOME)).effects),
        2
    );

    // A slip found under the next capture goes under that one; the
    // training's capture, over, carries nothing into it.
    let mut refitted = under_home(&refit, Some(next)).effects;
    refitted.push(slip(3, 4.0, 2.5));
    let (effects, home) = split_home_slips(&refitted, &refit, Some(next));
    assert_eq!(effects, previous.effects);
    assert_eq!(
        home,
        Some(HomeSlips {
            home_id: next,
            slips: vec![slip(3, 4.0, 2.5)],
        })
    );

    // A calibration without training slips: the run-time slip still has
    // its capture.
    let plain = Calibration {
        home: None,
        ..previous.clone()
    };
    let mut refitted = plain.effects.clone();
    refitted.push(slip(3, 4.0, 2.5));
    let (effects, home) = split_home_slips(&refitted, &plain, Some(next));
    assert_eq!(
        (effects, home.map(|h| h.home_id)),
        (plain.effects, Some(next))
    );
}

/// What the monitor does not move: a slip the calibration's effects
/// already hold (written before run-time slips had a capture), a slip
/// shared by every string (a blob's home section takes slips of one
/// string), and anything while no state has named the capture.
#[test]
fn slips_without_a_capture_of_their_own_stay_in_the_effects() {
    let mut previous = calibration();
    previous.home = None;
    previous.effects.push(slip(4, 8.0, 1.0));
    let mut refitted = previous.effects.clone();
    refitted.push(slip(spidar_core::model::EVERY_STRING, 3.0, 1.0));
    let (effects, home) = split_home_slips(&refitted, &previous, Some(TRAINING_HOME));
    assert_eq!((effects, home), (refitted.clone(), None));
    refitted.push(slip(6, 3.0, 1.0));
    let (effects, home) = split_home_slips(&refitted, &previous, None);
    assert_eq!((effects, home), (refitted, None));
}

/// A calibration written as `spidar calibrate` writes it and read back as
/// `spidar compile` and the monitor read it is the same model to the bit:
/// the report's model id is the blob's (serde_json parses an f64 to the
/// nearest double only with its `float_roundtrip` feature; without it,
/// values of 17 significant digits came back a unit in the last place off
/// and the page named another model id than the flashed blob).
#[test]
fn a_calibration_read_back_is_the_model_written() {
    let mut c = calibration();
    // Values of every magnitude with 17 significant digits.
    for (k, anchor) in c.frame.anchors.iter_mut().enumerate() {
        for (j, v) in anchor.iter_mut().enumerate() {
            *v += core::f64::consts::PI * 10f64.powi(k as i32 - 4) / (j as f64 + 3.0);
        }
    }
    let path = std::env::temp_dir().join(format!(
        "spidar-calibration-roundtrip-{}.json",
        std::process::id()
    ));
    std::fs::write(&path, serde_json::to_string_pretty(&c).unwrap()).unwrap();
    let back = crate::model::compile::load_calibration(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    assert_eq!(
        crate::model::compile::model_id_of(&back),
        crate::model::compile::model_id_of(&c)
    );
    for (a, b) in back
        .frame
        .anchors
        .iter()
        .flatten()
        .zip(c.frame.anchors.iter().flatten())
    {
        assert_eq!(a.to_bits(), b.to_bits());
    }
}
