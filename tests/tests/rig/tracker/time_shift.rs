//! The time-shift estimate, through the simulated tracker.

use std::time::Duration;

use super::fixtures::{receive_all, receiver};
use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use spidar::device::tracker::{
    estimate_time_shift, ShiftConfig, SyncError, TimedPosition, TrackerSource,
};
use spidar::sim::tracker::{SimSender, SimSenderConfig};

/// A hand-like motion: varying speed in all three axes (room frame, mm).
fn wander(t: f64) -> [f64; 3] {
    let tau = 2.0 * std::f64::consts::PI;
    [
        250.0 * (tau * 0.31 * t).sin() + 60.0 * (tau * 1.3 * t).sin(),
        -450.0 + 180.0 * (tau * 0.53 * t + 1.0).sin(),
        1050.0 + 120.0 * (tau * 0.17 * t).sin() + 40.0 * (tau * 0.9 * t + 0.3).cos(),
    ]
}

fn wander_with_occlusion(t: f64) -> Option<[f64; 3]> {
    // 0.3 s occlusions every 4 s.
    (t % 4.0 >= 0.3).then(|| wander(t))
}

/// Device samples at `rate` Hz on the device clock, with a room-transform
/// error `bias` and `noise_mm` of Gaussian-ish noise.
fn device_samples(rate: f64, seconds: f64, bias: [f64; 3], noise_mm: f64) -> Vec<TimedPosition> {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let n = (rate * seconds) as usize;
    (0..n)
        .map(|i| {
            let t = i as f64 / rate;
            let p = wander(t);
            TimedPosition {
                t_s: t,
                position_mm: core::array::from_fn(|k| {
                    // Sum of three uniforms: close enough to Gaussian.
                    let u: f64 = (0..3).map(|_| rng.random_range(-1.0..1.0)).sum::<f64>();
                    p[k] - bias[k] + noise_mm * u
                }),
            }
        })
        .collect()
}

#[test]
fn time_shift_recovered_through_the_simulated_tracker() {
    const OFFSET: f64 = 0.0375;
    const DAY_TIME: f64 = 39_596.0;
    let mut rx = receiver(8, 200);
    let cfg = SimSenderConfig {
        frames: 2000, // 20 s at 100 Hz
        ts_start_s: DAY_TIME,
        clock_offset_s: OFFSET,
        loss: 0.05,
        reorder: 0.05,
        send_interval: Duration::from_micros(500),
        seed: 11,
        ..SimSenderConfig::new(rx.local_addr())
    };
    let sender = SimSender::spawn(cfg, wander_with_occlusion).unwrap();
    let (frames, report) = receive_all(&mut rx, sender);
    // (Exact loss accounting is tested above; here a starved receiver's
    // kernel buffer may drop a few more, which the estimate must survive.)
    assert!(rx.stats().lost >= report.expected_lost());
    assert!(frames.iter().any(|f| f.body.is_none()));
    let tracker = TimedPosition::from_frames(&frames);
    let device = device_samples(500.0, 20.0, [8.0, -5.0, 14.0], 1.0);
    let shift = estimate_time_shift(
        &device,
        &tracker,
        &ShiftConfig {
            prior_offset_s: DAY_TIME,
            max_shift_s: 0.25,
            ..ShiftConfig::default()
        },
    )
    .unwrap();
    let error = shift.offset_s - (DAY_TIME + OFFSET);
    assert!(error.abs() < 0.003, "{shift:?}");
    assert!(
        (shift.coarse_offset_s - (DAY_TIME + OFFSET)).abs() < 0.02,
        "{shift:?}"
    );
    assert!(
        shift.offset_std_s > 0.0 && shift.offset_std_s < 0.003,
        "{shift:?}"
    );
    assert!(error.abs() < 5.0 * shift.offset_std_s + 1e-4, "{shift:?}");
    assert!(shift.correlation > 0.9, "{shift:?}");
    for k in 0..3 {
        assert!(
            (shift.bias_mm[k] - [8.0, -5.0, 14.0][k]).abs() < 0.5,
            "{shift:?}"
        );
    }
    assert!(shift.rms_residual_mm < 3.0, "{shift:?}");
    // The map and its inverse.
    let t = 7.25;
    assert!((shift.device_time(shift.tracker_time(t)) - t).abs() < 1e-9);
}

#[test]
fn time_shift_with_drift() {
    // Tracker clock 200 ppm fast, 12.3 ms ahead at the middle of 60 s.
    let (offset, drift) = (0.0123, 200e-6);
    let device = device_samples(200.0, 60.0, [0.0; 3], 0.5);
    let reference = 0.5 * (device[0].t_s + device[device.len() - 1].t_s);
    let tracker: Vec<TimedPosition> = (0..6000)
        .map(|i| {
            let t = i as f64 / 100.0; // true (device) time
            TimedPosition {
                t_s: t + offset + drift * (t - reference),
                position_mm: wander(t),
            }
        })
        .collect();
    let cfg = ShiftConfig {
        estimate_drift: true,
        ..ShiftConfig::default()
    };
    let shift = estimate_time_shift(&device, &tracker, &cfg).unwrap();
    assert!((shift.offset_s - offset).abs() < 0.001, "{shift:?}");
    assert!((shift.drift - drift).abs() < 30e-6, "{shift:?}");
    assert!(shift.drift_std > 0.0, "{shift:?}");
    assert_eq!(shift.reference_t_s, reference);
    // Without drift the offset is still found (the mid-stream value).
    let plain = estimate_time_shift(&device, &tracker, &ShiftConfig::default()).unwrap();
    assert!((plain.offset_s - offset).abs() < 0.002, "{plain:?}");
    assert_eq!(plain.drift, 0.0);
}

#[test]
fn time_shift_errors_name_the_problem() {
    let device = device_samples(100.0, 5.0, [0.0; 3], 0.0);
    let still: Vec<TimedPosition> = (0..500)
        .map(|i| TimedPosition {
            t_s: i as f64 / 100.0,
            position_mm: [1.0, 2.0, 3.0],
        })
        .collect();
    let cfg = ShiftConfig::default();
    assert_eq!(
        estimate_time_shift(&device, &still, &cfg),
        Err(SyncError::NoMotion { stream: "tracker" })
    );
    assert_eq!(
        estimate_time_shift(&device[..3], &device, &cfg),
        Err(SyncError::TooFewSamples {
            stream: "device",
            have: 3,
            need: 10
        })
    );
    let mut bad = device.clone();
    bad[4].position_mm[1] = f64::NAN;
    assert!(matches!(
        estimate_time_shift(&bad, &device, &cfg),
        Err(SyncError::NotFinite {
            stream: "device",
            index: 4,
            field: "position_mm[1]",
            ..
        })
    ));
    let mut back = device.clone();
    back[7].t_s = 0.0;
    assert!(matches!(
        estimate_time_shift(&device, &back, &cfg),
        Err(SyncError::TimeDecreasing {
            stream: "tracker",
            index: 7,
            ..
        })
    ));
    // Tracker an hour away from the prior: nothing overlaps.
    let far: Vec<TimedPosition> = device
        .iter()
        .map(|p| TimedPosition {
            t_s: p.t_s + 3600.0,
            ..*p
        })
        .collect();
    let r = estimate_time_shift(&device, &far, &cfg);
    assert!(matches!(r, Err(SyncError::NoOverlap { .. })), "{r:?}");
    assert!(matches!(
        estimate_time_shift(
            &device,
            &device,
            &ShiftConfig {
                max_gap_s: 0.0,
                ..cfg.clone()
            }
        ),
        Err(SyncError::Config(c)) if c.field == "max_gap_s"
    ));
}
