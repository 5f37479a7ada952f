//! Devices with 3 to 8 strings and planar devices on the project's own
//! simulator (`nominal.strings`, `nominal.planar`), and a tracker whose clock
//! is seconds off the device's: calibration finds the offset from the motion.
//! (Measured data of a real 4-line robot: `real_data.rs`.)

use std::path::Path;

use spidar::data::dataset::Session;
use spidar::procedures::calibrate::align::SessionTiming;
use spidar::procedures::calibrate::{calibrate, CalibrateConfig, Calibrated, NamedSession};
use spidar::sim::{simulate_session, SessionKind, SimConfig, SimulatedDevice};

fn config(strings: usize, planar: bool) -> SimConfig {
    let mut c = SimConfig::default();
    c.nominal.strings = strings;
    c.nominal.planar = planar;
    c.abnormal_motor.enabled = false;
    c
}

fn run(c: &SimConfig, train: &Session, test: &Session) -> Calibrated {
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    crate::calibrate_in_memory(&c.nominal.geometry(), train, test, &cfg)
}

fn final_test_mean(c: &Calibrated) -> f64 {
    c.report.stages.last().unwrap().test.mean_mm
}

/// A device of `strings` (planar or not, device seed `seed`) and two 100 Hz
/// streams of it, `train` and `test` rows long (session seeds 11 and 12),
/// whose tracker clock is `offset_s` ahead and runs `drift_ppm` fast.
fn clock_streams(
    strings: usize,
    planar: bool,
    seed: u64,
    (offset_s, drift_ppm): (f64, f64),
    (train, test): (usize, usize),
) -> (SimConfig, Session, Session) {
    let mut c = config(strings, planar);
    c.random.capture_interval_s = 0.01;
    c.tracker.clock_offset_s = offset_s;
    c.tracker.clock_drift_ppm = drift_ppm;
    let device = SimulatedDevice::new(&c, seed).unwrap();
    let stream = |points: usize, session_seed: u64| {
        simulate_session(&device, SessionKind::Random { points }, session_seed).unwrap()
    };
    let (train, test) = (stream(train, 11), stream(test, 12));
    (c, train, test)
}

#[test]
fn four_strings_in_3d_and_three_in_the_plane_calibrate_to_the_tracker_noise() {
    for (strings, planar, floor_mm) in [(4, false, 0.32), (3, true, 0.25)] {
        let mut c = config(strings, planar);
        c.lattice.cells_per_axis = 7;
        let device = SimulatedDevice::new(&c, 3).unwrap();
        let train = simulate_session(&device, SessionKind::Lattice, 4).unwrap();
        let test = simulate_session(&device, SessionKind::Random { points: 300 }, 5).unwrap();
        assert_eq!((train.strings, test.strings), (strings, strings));
        assert!(train
            .samples
            .iter()
            .all(|s| s.counts[strings..].iter().all(|&c| c == 0)));
        let r = run(&c, &train, &test);
        let mean = final_test_mean(&r);
        // Tracker noise 0.2 mm per axis: ~0.32 mm mean in 3-D, ~0.25 in 2-D.
        assert!(
            mean < 1.3 * floor_mm,
            "{strings} strings, planar {planar}: {mean} mm"
        );
        assert_eq!(r.report.device.strings, strings);
        assert_eq!(r.report.device.planar, planar);
        assert_eq!(r.report.device.redundancy, 1);
        assert!(matches!(
            r.report.timing.train,
            SessionTiming::Static { .. }
        ));
        // The calibration's frame carries the layout to the device.
        assert_eq!(r.calibration.frame.layout.count(), strings);
        assert!(
            r.calibration.effects.is_empty(),
            "{:?}",
            r.calibration.effects
        );
    }
}

/// The acceptance: a planar 4-string device whose tracker clock is
/// 2 s ahead: the offset within 5 ms, the held-out error within 1.5x the same
/// device recorded with one clock.
#[test]
fn a_two_second_tracker_clock_offset_is_found_and_removed() {
    let mut errors = Vec::new();
    for offset_s in [0.0, 2.0] {
        let (c, train, test) = clock_streams(4, true, 5, (offset_s, 0.0), (3000, 1000));
        let r = run(&c, &train, &test);
        for t in [&r.report.timing.train, &r.report.timing.test] {
            let SessionTiming::Aligned(a) = t else {
                panic!("a 100 Hz stream is dynamic: {t:?}");
            };
            assert!(
                (a.offset_s - offset_s).abs() < 0.005,
                "offset {} s for {offset_s} s",
                a.offset_s
            );
            assert!(a.offset_sd_s < 0.005, "{a:?}");
        }
        errors.push(final_test_mean(&r));
    }
    assert!(errors[1] <= 1.5 * errors[0], "{errors:?}");
}

/// The paper-sized 8-string device (its nominal geometry 200 mm off), a
/// 100 Hz stream with the clocks agreeing and with the tracker half a
/// second behind: the first pass's fine fit with the nominal model is not
/// determined and must not move the speed profiles' peak. (It did: 60 ms
/// off, then 15 ms after the second pass, and a held-out error of 7.6 mm
/// for a stream with no offset at all; positive offsets were found.)
#[test]
fn a_stream_with_no_or_a_negative_clock_offset_is_aligned_to_the_millisecond() {
    for offset_s in [0.0, -0.5] {
        let (c, train, test) = clock_streams(8, false, 7, (offset_s, 0.0), (3000, 1000));
        let r = run(&c, &train, &test);
        for t in [&r.report.timing.train, &r.report.timing.test] {
            let SessionTiming::Aligned(a) = t else {
                panic!("a 100 Hz stream is dynamic: {t:?}");
            };
            assert!(
                (a.offset_s - offset_s).abs() < 0.001,
                "offset {} s for {offset_s} s",
                a.offset_s
            );
        }
        let mean = final_test_mean(&r);
        assert!(mean < 0.4, "offset {offset_s} s: held out {mean} mm");
    }
}

/// A short test stream (10 s) whose clock is 4.5 s off: its search is
/// centred on the training stream's offset, and lags that pair a sliver of
/// the streams do not compete (centred on 0 it found -5.0 s, then +9.2 s
/// on 76 pairs; 58.8 mm held out). A stream 12 s off, beyond the search,
/// is refused naming the file, where it was calibrated to 536 mm; told the
/// rig's clock is about 10 s off, the search finds it.
#[test]
fn a_short_stream_far_off_is_aligned_and_one_beyond_the_search_is_refused() {
    let (c, train, test) = clock_streams(4, true, 5, (4.5, 0.0), (3000, 1000));
    let r = run(&c, &train, &test);
    let SessionTiming::Aligned(a) = &r.report.timing.test else {
        panic!("{:?}", r.report.timing.test);
    };
    assert!((a.offset_s - 4.5).abs() < 0.001, "{a:?}");
    assert!(final_test_mean(&r) < 0.35, "{}", final_test_mean(&r));

    // 30 s streams, the first 12 s of each without a tracker position.
    let (c, train, test) = clock_streams(8, false, 7, (12.0, 0.0), (3000, 3000));
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    let err = calibrate(
        &c.nominal.geometry(),
        Path::new("geometry.toml"),
        NamedSession {
            path: Path::new("stream-12s.csv"),
            session: &train,
        },
        NamedSession {
            path: Path::new("test.csv"),
            session: &test,
        },
        &cfg,
    )
    .map(|_| ())
    .expect_err("12 s off is beyond the search");
    let e = err.to_string();
    assert!(
        e.starts_with("stream-12s.csv: the tracker's clock could not be aligned"),
        "{e}"
    );
    assert!(e.contains("--clock-offset-s"), "{e}");
    // Told the rig's clock is about 10 s off, the search reaches it.
    cfg.clock_offset_s = 10.0;
    let r = crate::calibrate_in_memory(&c.nominal.geometry(), &train, &test, &cfg);
    let SessionTiming::Aligned(a) = &r.report.timing.train else {
        panic!("{:?}", r.report.timing.train);
    };
    assert!((a.offset_s - 12.0).abs() < 0.001, "{a:?}");
    assert!(final_test_mean(&r) < 0.4, "{}", final_test_mean(&r));
}

/// A 120 s training stream whose tracker clock runs 100 ppm fast (12 ms
/// over the stream): the drift is found and the rows re-paired with it
/// (one offset left them 6 ms off at either end: 0.761 mm held out). The
/// 30 s streams above keep the offset alone.
#[test]
fn a_long_stream_s_clock_drift_is_found_and_removed() {
    let (c, train, test) = clock_streams(8, false, 7, (1.0, 100.0), (12000, 3000));
    let r = run(&c, &train, &test);
    let SessionTiming::Aligned(a) = &r.report.timing.train else {
        panic!("{:?}", r.report.timing.train);
    };
    // Measured 89.8 +- 0.4 ppm, 1006.10 ms at 60 s (1006 true).
    assert!((a.drift_ppm - 100.0).abs() < 15.0, "{a:?}");
    let true_offset_s = 1.0 + 100e-6 * a.reference_t_s;
    assert!((a.offset_s - true_offset_s).abs() < 0.001, "{a:?}");
    let SessionTiming::Aligned(t) = &r.report.timing.test else {
        panic!("{:?}", r.report.timing.test);
    };
    // A 30 s test stream cannot tell a rate from the model's errors: it
    // takes the training stream's, the same two clocks' (with the offset
    // alone it was paired 1.5 ms off at its ends).
    assert_eq!(t.drift_ppm, a.drift_ppm, "{t:?}");
    let true_test_offset_s = 1.0 + 100e-6 * t.reference_t_s;
    assert!((t.offset_s - true_test_offset_s).abs() < 0.001, "{t:?}");
    let mean = final_test_mean(&r);
    assert!(mean < 0.4, "held out {mean} mm");
    assert!(r.report.summary().contains("ppm fast"));
}

/// A tracker restarted between the training and the test recordings: the
/// two streams' clocks 5.5 s apart (-3 s and +2.5 s), each within the
/// search alone. The test stream's search, centred on the training
/// stream's offset, cannot reach +2.5 s; it is searched again around 0
/// (the pair was refused, "the tracker's clock could not be aligned").
#[test]
fn a_test_stream_after_the_tracker_restarted_is_aligned_on_its_own() {
    let (c, train, _) = clock_streams(4, true, 5, (-3.0, 0.0), (3000, 10));
    let (_, _, test) = clock_streams(4, true, 5, (2.5, 0.0), (10, 1000));
    let r = run(&c, &train, &test);
    for (t, offset_s) in [(&r.report.timing.train, -3.0), (&r.report.timing.test, 2.5)] {
        let SessionTiming::Aligned(a) = t else {
            panic!("a 100 Hz stream is dynamic: {t:?}");
        };
        assert!((a.offset_s - offset_s).abs() < 0.001, "{a:?}");
    }
    let mean = final_test_mean(&r);
    assert!(mean < 0.35, "held out {mean} mm");
}

/// Rows at 10 Hz are a stream, as the session format says: their times,
/// written in decimal, step by a hair more than 0.1 s (0.3 written
/// 0.30000000000000004, less 0.2), which read them as poses, never
/// re-paired (a tracker 0.3 s ahead: 190 mm held out, a room scale of 1e8).
#[test]
fn a_ten_hertz_stream_is_aligned() {
    let mut c = config(4, true);
    c.random.capture_interval_s = 0.1;
    c.tracker.clock_offset_s = 0.3;
    let device = SimulatedDevice::new(&c, 5).unwrap();
    let stream = |points: usize, session_seed: u64| {
        let mut s =
            simulate_session(&device, SessionKind::Random { points }, session_seed).unwrap();
        // As a CSV writer gives them: k / 10 in decimal.
        for (k, sample) in s.samples.iter_mut().enumerate() {
            sample.t_s = format!("{}", k as f64 * 0.1).parse().unwrap();
        }
        s
    };
    let (train, test) = (stream(600, 11), stream(300, 12));
    let r = run(&c, &train, &test);
    for t in [&r.report.timing.train, &r.report.timing.test] {
        let SessionTiming::Aligned(a) = t else {
            panic!("a 10 Hz stream is dynamic: {t:?}");
        };
        assert!((a.offset_s - 0.3).abs() < 0.002, "{a:?}");
    }
    let mean = final_test_mean(&r);
    assert!(mean < 0.4, "held out {mean} mm");
}

/// A log of device states at 1 kHz with the 100 Hz tracker's position on
/// every tenth row (nine rows of counts between two frames, no tracker):
/// aligned as the 100 Hz stream it holds. (The gaps the alignment bridges
/// were bounded by the 1 ms row interval: "the streams overlap in 0
/// samples".)
#[test]
fn a_kilohertz_device_log_with_a_slower_tracker_is_aligned() {
    let (c, train, test) = clock_streams(4, true, 5, (0.5, 0.0), (3000, 1000));
    let mut log = train.clone();
    log.samples.clear();
    for pair in train.samples.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        log.samples.push(a.clone());
        for k in 1..10 {
            let f = k as f64 / 10.0;
            let mut between = a.clone();
            between.t_s = a.t_s + f * (b.t_s - a.t_s);
            between.counts = core::array::from_fn(|i| {
                (f64::from(a.counts[i]) + f * f64::from(b.counts[i] - a.counts[i])).round() as i32
            });
            between.tracker = None;
            between.orientation = None;
            log.samples.push(between);
        }
    }
    let r = run(&c, &log, &test);
    let SessionTiming::Aligned(a) = &r.report.timing.train else {
        panic!("{:?}", r.report.timing.train);
    };
    assert!((a.offset_s - 0.5).abs() < 0.001, "{a:?}");
    let mean = final_test_mean(&r);
    assert!(mean < 0.3, "held out {mean} mm");
}

/// Warnings where a result is not what it seems (issue 13): a test session
/// that is the training session, test points beyond the training volume.
#[test]
fn shared_rows_and_points_beyond_the_training_volume_are_warned_about() {
    let mut c = config(8, false);
    c.lattice.cells_per_axis = 5;
    c.lattice.size_mm = 400.0;
    let device = SimulatedDevice::new(&c, 2).unwrap();
    let train = simulate_session(&device, SessionKind::Lattice, 3).unwrap();
    // The test session is the training session.
    let r = run(&c, &train, &train);
    assert!(
        r.report
            .warnings
            .iter()
            .any(|w| w.contains("holds only rows of the training session")),
        "{:?}",
        r.report.warnings
    );
    // Random points over a 1 m cube against a 0.4 m training lattice.
    c.lattice.size_mm = 1000.0;
    let wide = SimulatedDevice::new(&c, 2).unwrap();
    let test = simulate_session(&wide, SessionKind::Random { points: 200 }, 4).unwrap();
    let r = run(&c, &train, &test);
    let w = r
        .report
        .warnings
        .iter()
        .find(|w| w.contains("outside the volume the training session covers"))
        .unwrap_or_else(|| panic!("{:?}", r.report.warnings));
    assert!(w.contains("test points") && w.contains("outside"), "{w}");
    assert!(!r.report.warnings.iter().any(|w| w.contains("also appear")));
}

/// A planar 4-string device (2 spares) whose string 1 drifts 0.001 mm/s
/// (4.8 mm over the 80 min lattice). On the lattice the fit on every row
/// absorbs the drift into position terms (time goes with position), so its
/// in-sample gain is small (0.260 -> 0.247 mm) and its position rival's
/// columns in z repeat the others (the tracked z is one value): the drift
/// was refused or never proposed, and the test session from home was off
/// by what the lattice's position terms had taken (1.19 mm). The blocked
/// folds see it (-61 %): it is added, and the test falls to the clean
/// planar device's level.
#[test]
fn a_drifting_string_of_a_planar_device_is_found() {
    use spidar::model::diagnose::Family;
    let mut c = config(4, true);
    c.effects = vec!["drift:1:mm_per_s=0.001".into()];
    let device = SimulatedDevice::new(&c, 3).unwrap();
    let train = simulate_session(&device, SessionKind::Lattice, 4).unwrap();
    let test = simulate_session(&device, SessionKind::Random { points: 500 }, 5).unwrap();
    let r = run(&c, &train, &test);
    let drift = r
        .report
        .effects
        .iter()
        .find(|f| f.family == Family::Drift && f.strings == [1] && f.added);
    assert!(drift.is_some(), "{:#?}", r.report.effects);
    let mean = final_test_mean(&r);
    assert!(mean < 0.3, "{mean} mm");
}
