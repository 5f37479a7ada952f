//! The virtual device's plant, the fuzzed decoders (host and device side,
//! and the device behind its pseudo-terminal), and `spidar compile`'s
//! fixed-point error.

use std::time::Duration;

use proptest::prelude::*;
use spidar::data::observe::observations;
use spidar::device::link::{Client, ClientOptions};
use spidar::model::compile::{
    fixed_point_error, run_compile, CompileRequest, FIXED_POINT_BUDGET_MM,
};
use spidar::sim::virtual_device::{spawn, Plant, Trajectory, VirtualDeviceConfig, Waypoint};
use spidar::sim::{self, SessionKind, SimConfig};
use spidar_core::blob::{compile, CompiledCalibration};
use spidar_core::correction::{CorrectionModel, NnModel, OutputMode, Standardization};
use spidar_core::device::DeviceLink;
use spidar_protocol::{
    encode_device_message, encode_request, DeviceMessage, FrameDecoder, Request, Response,
    MAX_FRAME,
};

fn sim_device(seed: u64) -> sim::SimulatedDevice {
    let mut config = SimConfig::default();
    config.abnormal_motor.enabled = false;
    config.effects = vec![
        "offset:2:mm=3".into(),
        "backlash:5:half_width_mm=0.4".into(),
    ];
    sim::SimulatedDevice::new(&config, seed).expect("simulated device")
}

fn nn(hidden: usize) -> CorrectionModel {
    let s = Standardization {
        mean: [0.0, 0.0, 1000.0],
        std: [500.0; 3],
    };
    let w = |k: usize| ((k * 37 % 17) as f64 - 8.0) / 20.0;
    CorrectionModel::Nn(NnModel {
        input: s,
        output: s,
        w1: (0..hidden).map(|h| [w(h), w(h + 1), w(h + 2)]).collect(),
        b1: (0..hidden).map(|h| w(h + 3) / 4.0).collect(),
        w2: [0, 1, 2].map(|a| (0..hidden).map(|h| w(h + a + 5) / 100.0).collect()),
        b2: [0.0; 3],
        mode: OutputMode::Residual,
    })
}

#[test]
fn trajectory_interpolates_and_starts_at_home() {
    let home = [1.0, 2.0, 3.0];
    let t = Trajectory::Waypoints(vec![
        Waypoint {
            t_us: 1_000_000,
            device_mm: [11.0, 2.0, 3.0],
        },
        Waypoint {
            t_us: 3_000_000,
            device_mm: [11.0, 22.0, 3.0],
        },
    ]);
    assert_eq!(t.position_at(home, 0), home);
    assert_eq!(t.position_at(home, 500_000), [6.0, 2.0, 3.0]);
    assert_eq!(t.position_at(home, 2_000_000), [11.0, 12.0, 3.0]);
    assert_eq!(t.position_at(home, 9_000_000), [11.0, 22.0, 3.0]);
    assert_eq!(t.end_us(), Some(3_000_000));
    let orbit = Trajectory::Orbit {
        radius_mm: 50.0,
        period_s: 4.0,
    };
    assert_eq!(orbit.position_at(home, 0), home);
}

#[test]
fn plant_counters_wrap_and_motors_lag() {
    let dev = sim_device(3);
    // 600 mm away from home: tens of thousands of counts on some strings.
    let far = [
        dev.frame.home[0] + 600.0,
        dev.frame.home[1],
        dev.frame.home[2],
    ];
    let mut plant = Plant::new(
        dev,
        Trajectory::Waypoints(vec![Waypoint {
            t_us: 1_000_000,
            device_mm: far,
        }]),
    );
    // Counters near the top of their range: paying out wraps them.
    plant.raw_home = [60_000; 8];
    let commanded = [5.0f32; 8];
    let mut raw = [0u16; 8];
    let mut counts = [0i64; 8];
    let mut prev = plant.raw_home;
    for k in 1..=1000u64 {
        raw = plant.step(k * 1000, &commanded, true);
        for i in 0..8 {
            counts[i] += i64::from(raw[i].wrapping_sub(prev[i]) as i16);
        }
        prev = raw;
        if k == 2 {
            let t = plant.tensions_n();
            assert!(t.iter().all(|&x| x > 0.5 && x < 5.0), "{t:?}");
        }
    }
    assert!(plant.tensions_n().iter().all(|&t| (t - 5.0).abs() < 1e-6));
    let biggest = counts.iter().map(|c| c.abs()).max().unwrap();
    assert!(biggest > 15_000, "{counts:?}");
    assert!(plant.error().is_none());
    // The raw counters wrapped somewhere, the extended counts did not.
    assert!((0..8).any(|i| i64::from(raw[i]) != i64::from(plant.raw_home[i]) + counts[i]));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, .. ProptestConfig::default() })]

    /// Any bytes into either side's decoder: no panic, and a valid frame
    /// after a 0x00 always decodes.
    #[test]
    fn decoders_never_panic_and_resynchronize(
        chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..400), 0..6)
    ) {
        let mut host: FrameDecoder = FrameDecoder::new();
        let mut link = DeviceLink::new();
        for c in &chunks {
            host.feed_device_messages(c, |_| {});
            let mut rest = &c[..];
            while !rest.is_empty() {
                let (used, _) = link.push(rest, |_, _| Response::Ack);
                prop_assert!(used >= 1);
                rest = &rest[used..];
            }
        }
        let mut tx = [0u8; MAX_FRAME];
        let f = encode_device_message(3, &DeviceMessage::Reply(Response::Ack), &mut tx).unwrap();
        let mut got = Vec::new();
        host.feed_device_messages(&[0], |_| {});
        host.feed_device_messages(f, |r| got.push(r));
        prop_assert_eq!(got.len(), 1);
        prop_assert!(got[0].is_ok());
        let mut rx = [0u8; MAX_FRAME];
        let f = encode_request(4, &Request::GetInfo, &mut rx).unwrap().to_vec();
        let mut seen = 0;
        let mut rest = &[&[0u8][..], &f[..]].concat()[..];
        let mut owned;
        while !rest.is_empty() {
            let (used, reply) = link.push(rest, |r, _| {
                seen += usize::from(*r == Request::GetInfo);
                Response::Ack
            });
            owned = rest[used..].to_vec();
            rest = &owned[..];
            let _ = reply;
        }
        prop_assert_eq!(seen, 1);
    }
}

/// Random bytes through the pseudo-terminal: the device rejects and counts
/// them and still answers.
#[test]
fn the_virtual_device_survives_garbage_on_its_port() {
    let vd = spawn(
        VirtualDeviceConfig::default(),
        Plant::new(sim_device(1), Trajectory::Hold),
    )
    .unwrap();
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let mut x = 0x1234_5678u32;
    let mut garbage = Vec::new();
    for _ in 0..20_000 {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        garbage.push((x >> 24) as u8);
    }
    c.write_raw(&garbage).unwrap();
    c.write_raw(&[0]).unwrap();
    std::thread::sleep(Duration::from_millis(20));
    let stats = c.stats().unwrap();
    assert!(stats.rx.rejected() > 10, "{stats:?}");
    c.hello().unwrap();
}

#[test]
fn fixed_point_error_is_within_budget_on_a_test_session() {
    let dev = sim_device(5);
    let session = sim::simulate_session(&dev, SessionKind::Random { points: 60 }, 11).unwrap();
    let obs = observations(&session.samples);
    for correction in [CorrectionModel::None, nn(16)] {
        let cal = spidar_tests::calibration(&dev, correction);
        let blob = compile(&cal, 1, 0).unwrap();
        let parsed = CompiledCalibration::from_blob(&blob).unwrap();
        let e = fixed_point_error(&cal, &parsed, &obs).unwrap();
        assert!(e.rows > obs.len() / 2, "{e:?}");
        assert!(
            e.corrected.mean_mm <= FIXED_POINT_BUDGET_MM,
            "{:?}: {e:?}",
            cal.correction
        );
    }
}

#[test]
fn compile_command_writes_a_checked_blob_and_names_bad_files() {
    let dir = std::env::temp_dir().join(format!("spidar-compile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let dev = sim_device(5);
    let session = sim::simulate_session(&dev, SessionKind::Random { points: 40 }, 12).unwrap();
    let test = dir.join("test.csv");
    session.write(&test).unwrap();
    let cal_path = dir.join("calibration.json");
    let cal = spidar_tests::calibration(&dev, nn(8));
    std::fs::write(&cal_path, serde_json::to_string(&cal).unwrap()).unwrap();
    let geometry = dir.join("geometry.toml");
    dev.nominal.write(&geometry).unwrap();
    let out = dir.join("model.blob");
    let args = CompileRequest {
        calibration: cal_path.clone(),
        out: out.clone(),
        test: Some(test),
        geometry: Some(geometry),
        model_id: Some(77),
        budget_mm: FIXED_POINT_BUDGET_MM,
        write_over_budget: false,
    };
    let report = run_compile(&args).unwrap();
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(report.bytes, bytes.len());
    assert_eq!(
        CompiledCalibration::from_blob(&bytes)
            .unwrap()
            .header
            .model_id,
        77
    );
    let text = report.to_string();
    assert!(text.contains("fixed-point error"), "{text}");

    std::fs::write(&cal_path, "{\"frame\": 3}").unwrap();
    let e = run_compile(&args).unwrap_err().to_string();
    assert!(e.contains("calibration.json:1:"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}
