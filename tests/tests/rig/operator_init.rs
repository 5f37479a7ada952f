//! Guided initialization end to end: a virtual device whose end-effector is
//! in a simulated operator's hand, the operator following the haptic cue the
//! device renders and the audio cue the host plays, a simulated DTrack2
//! tracker on loopback, and `spidar::procedures::init::initialize` between
//! them over the serial link.

use spidar_tests::eventually;
use std::net::SocketAddr;
use std::time::Duration;

use spidar::device::cues::{CueSink, Cues, SharedCues};
use spidar::device::link::Client;
use spidar::device::tracker::{DtrackReceiver, ReceiverConfig, TrackerSource};
use spidar::procedures::init::{initialize, InitConfig, InitError};
use spidar::sim::operator::{FreeMotion, SimOperator, SimOperatorConfig};
use spidar::sim::virtual_device::{spawn, Hand, Pace, Plant, Trajectory, VirtualDeviceConfig};
use spidar::sim::{SimConfig, SimulatedDevice};

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Records every cue and passes it on to the simulated operator.
struct Recorder {
    to_operator: SharedCues,
    shown: Vec<Cues>,
}

impl CueSink for Recorder {
    fn show(&mut self, cues: &Cues) {
        self.to_operator.show(cues);
        self.shown.push(cues.clone());
    }
}

struct World {
    device: SimulatedDevice,
    hand: Hand,
    vd: spidar::sim::virtual_device::VirtualDevice,
    receiver: DtrackReceiver,
    cues: SharedCues,
}

/// The simulated operator in step with the procedure, and a link client
/// with generous timeouts (a busy machine may not run the device's thread
/// for a while; that is not a lost device).
fn operator_and_client(w: &World, op_config: SimOperatorConfig) -> (SimOperator, Client) {
    let operator = SimOperator::spawn_in_step(
        op_config,
        w.device.clone(),
        w.hand.clone(),
        w.cues.clone(),
        Some(w.receiver.progress()),
    )
    .unwrap();
    let client = Client::open_with(
        w.vd.port_path(),
        spidar::device::link::ClientOptions::for_simulated_device(),
    )
    .unwrap();
    (operator, client)
}

/// A device as built (seed 3), its end-effector `offset` (device frame) off
/// where the built-in homing left it.
fn world(offset: [f64; 3]) -> World {
    let device = SimulatedDevice::new(&SimConfig::default(), 3).unwrap();
    let start: [f64; 3] = core::array::from_fn(|k| device.frame.home[k] + offset[k]);
    let hand = Hand::at(start);
    // On the simulated clock from the start, as `SimulatedRig` does.
    hand.attach();
    let plant = Plant::new(device.clone(), Trajectory::Held(hand.clone()));
    let vd = spawn(
        VirtualDeviceConfig {
            pace: Pace::Virtual,
            ..VirtualDeviceConfig::default()
        },
        plant,
    )
    .unwrap();
    let receiver =
        DtrackReceiver::bind(ReceiverConfig::new(SocketAddr::from(([127, 0, 0, 1], 0)))).unwrap();
    let cues = SharedCues::stamped_by(receiver.progress());
    World {
        device,
        hand,
        vd,
        receiver,
        cues,
    }
}

#[test]
fn the_operator_follows_the_cues_to_the_centre_and_home_is_declared_there() {
    let mut w = world([45.0, -30.0, 25.0]);
    let mut op_config = SimOperatorConfig::new(w.receiver.local_addr());
    op_config.occlusion = 0.05;
    op_config.loss = 0.02;
    op_config.seed = 7;
    let (operator, mut client) = operator_and_client(&w, op_config.clone());
    let geometry = w.device.nominal.clone();
    let mut config = InitConfig::for_geometry(&geometry);
    config.timeout = Duration::from_secs(40);
    let mut recorder = Recorder {
        to_operator: w.cues.clone(),
        shown: Vec::new(),
    };
    let record = initialize(
        &mut client,
        &mut w.receiver,
        &geometry,
        &config,
        &mut recorder,
    );
    if std::env::var_os("TRACE").is_some() {
        for (i, c) in recorder.shown.iter().enumerate().step_by(25) {
            eprintln!(
                "{i} d {:?} beep {:.0} F {:?} {}",
                c.distance_mm, c.beep_hz, c.force_n, c.message
            );
        }
    }
    let record = record.expect("init");
    let history = operator.history();
    let report = operator.stop().unwrap();
    eprintln!(
        "init: {} frames ({} occluded), hand path {:.0} mm, {} cues; {record:?}",
        report.frames,
        report.occluded,
        report.path_mm,
        recorder.shown.len()
    );

    // The operator started several centimetres out, and got there by the
    // cues: the beep rose from silence to near 1 kHz, the force pulled.
    let first = recorder
        .shown
        .iter()
        .find_map(|c| c.distance_mm)
        .expect("a distance was shown");
    assert!(first > 30.0, "started {first} mm out");
    let beeps: Vec<f32> = recorder.shown.iter().map(|c| c.beep_hz).collect();
    assert!(beeps.iter().any(|&b| b > 0.0 && b < 800.0));
    let loudest = beeps.iter().fold(0.0f32, |m, &b| m.max(b));
    let near = 1000.0 * (1.0 - config.tolerance_mm as f32 / config.d_min_mm);
    assert!(loudest >= near, "highest pitch {loudest} Hz");
    assert!(recorder
        .shown
        .iter()
        .any(|c| c.force_n.iter().map(|f| f * f).sum::<f32>().sqrt() > 1.0));

    // Home is where the marker held, within tolerance of the centre.
    assert!(record.home_error_mm <= config.tolerance_mm, "{record:?}");
    assert!(record.hold_frames >= 30, "{record:?}");
    // The recorded home is the true marker position during the hold (the
    // tracker's noise averages out): compare with the operator's own truth.
    let held: Vec<_> = history
        .iter()
        .filter(|h| distance(&h.room_mm, &config.target_room_mm) <= config.tolerance_mm + 0.5)
        .collect();
    assert!(!held.is_empty());
    // The hold's frames: from `hold` (plus one frame period) before the
    // frame that declared home, to it; the hand wanders a few tenths of a
    // millimetre meanwhile, so the record is the mean, not any one frame.
    let hold_s = record.hold_s + 1.0 / op_config.frame_rate_hz;
    let during: Vec<[f64; 3]> = history
        .iter()
        .filter(|h| {
            let ts = op_config.tracker_ts_s(h.t_us);
            ts <= record.declared_at_ts_s + 1e-9 && ts >= record.declared_at_ts_s - hold_s
        })
        .map(|h| h.room_mm)
        .collect();
    assert!(
        during.len() >= record.hold_frames,
        "{} frames",
        during.len()
    );
    let true_mean: [f64; 3] =
        core::array::from_fn(|k| during.iter().map(|p| p[k]).sum::<f64>() / during.len() as f64);
    assert!(
        distance(&true_mean, &record.home_room_mm) < 0.2,
        "true marker over the hold {true_mean:?} vs recorded home {:?}",
        record.home_room_mm
    );
    // Eq. 6 translation: measured home minus the nominal device home.
    for k in 0..3 {
        assert!(
            (record.room_from_device_translation_mm[k]
                - (record.home_room_mm[k] - geometry.home_mm[k]))
                .abs()
                < 1e-9
        );
    }
    // The pretension it held at home goes into the geometry it writes (the
    // strings' stretch is counted from it).
    assert_eq!(record.home_tension_n, 1.0);
    assert_eq!(record.apply_to(&geometry).home_tension_n, Some(1.0));
    // The device homed there: its forward kinematics reads the nominal home.
    assert!(
        distance(&record.device_position_after_home_mm, &geometry.home_mm) < 0.5,
        "{:?}",
        record.device_position_after_home_mm
    );
    // The motors are off afterwards.
    assert!(eventually(|| !w.vd.status().armed));
    assert!(w.receiver.stats().delivered > 50);
}

#[test]
fn a_silent_tracker_is_an_error_and_the_device_is_left_disarmed() {
    let mut w = world([10.0, 0.0, 0.0]);
    let mut client = Client::open_with(
        w.vd.port_path(),
        spidar::device::link::ClientOptions::for_simulated_device(),
    )
    .unwrap();
    let geometry = w.device.nominal.clone();
    let mut config = InitConfig::for_geometry(&geometry);
    config.tracker_timeout = Duration::from_millis(300);
    let err = initialize(
        &mut client,
        &mut w.receiver,
        &geometry,
        &config,
        &mut w.cues.clone(),
    )
    .unwrap_err();
    assert!(matches!(err, InitError::TrackerSilent { .. }), "{err}");
    assert!(err.to_string().contains("tracker sent nothing"), "{err}");
    assert!(eventually(|| !w.vd.status().armed));
}

#[test]
fn an_operator_who_never_gets_there_times_out_with_the_closest_approach() {
    let mut w = world([80.0, 0.0, 0.0]);
    let mut op_config = SimOperatorConfig::new(w.receiver.local_addr());
    op_config.free_motion = FreeMotion::Still;
    let (operator, mut client) = operator_and_client(&w, op_config);
    let geometry = w.device.nominal.clone();
    let mut config = InitConfig::for_geometry(&geometry);
    config.timeout = Duration::from_millis(800);
    let err = initialize(
        &mut client,
        &mut w.receiver,
        &geometry,
        &config,
        &mut w.cues.clone(),
    )
    .unwrap_err();
    operator.stop().unwrap();
    match err {
        InitError::Timeout { closest_mm, .. } => assert!(closest_mm > 50.0, "{closest_mm}"),
        other => panic!("{other}"),
    }
    assert!(!w.vd.status().armed);
}
