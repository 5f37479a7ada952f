//! Encoder latency: simulated on a string, and named on its strings
//! through `calibrate`.

use super::fixtures::{calibrate_quick, quiet_config};
use spidar::sim::physics::{simulate_session, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;

/// The independent simulator's encoder latency: a string read `tau` late
/// holds its counts of `tau` earlier, the hand back along its velocity
/// (`latency:string=2,ms=6`): on a stream its counts fall behind by `tau`
/// times their rate, and every other string's counts are the clean
/// device's to the count.
#[test]
fn an_encoder_read_late_holds_its_string_as_it_was_then() {
    let kind = SessionKind::Stream {
        rows: 400,
        area: spidar::sim::StreamArea::Training,
    };
    let clean = PhysicsDevice::new(&quiet_config(), 5).unwrap();
    let late = PhysicsDevice::new(
        &PhysicsConfig {
            effects: vec!["latency:string=2,ms=6".into()],
            ..quiet_config()
        },
        5,
    )
    .unwrap();
    let (a, _) = simulate_session(&clean, kind, 8).unwrap();
    let (b, _) = simulate_session(&late, kind, 8).unwrap();
    let (mut moving, mut off) = (0, Vec::new());
    for r in 1..a.samples.len() - 1 {
        let (x, y) = (&a.samples[r], &b.samples[r]);
        for i in (0..8).filter(|&i| i != 2) {
            assert_eq!(x.counts[i], y.counts[i], "row {r}, string {i}");
        }
        let dt = a.samples[r + 1].t_s - a.samples[r - 1].t_s;
        let rate = f64::from(a.samples[r + 1].counts[2] - a.samples[r - 1].counts[2]) / dt;
        if rate.abs() > 2000.0 {
            moving += 1;
            let expected = f64::from(x.counts[2]) - 0.006 * rate;
            off.push((f64::from(y.counts[2]) - expected).abs());
        }
    }
    assert!(moving > 100, "{moving} moving rows");
    off.sort_by(f64::total_cmp);
    let median = off[off.len() / 2];
    // A central difference over 20 ms of a minimum-jerk stroke against
    // the velocity at the capture: a few counts (a count is ~0.02 mm).
    assert!(median < 5.0, "median {median} counts off tau * rate");
}

/// Issue 33 point 3 on the independent simulator: 6 ms of encoder latency
/// on strings 2 and 5 of a 100 Hz stream, through `calibrate` (the
/// tracker's clock found by the alignment): a latency on each of the two
/// strings of about 6 ms and on no other string. The alignment's quick
/// model has no latency of one string and finds the clock 0.2-0.5 ms off;
/// the loop takes that as a latency every string shares, which the device
/// would apply in use. It goes into the clocks' offsets, found within
/// 0.05 ms, and the model holds no such term (decision record 0064).
#[test]
fn encoder_latency_on_an_independent_stream_is_named_on_its_strings() {
    let device = lagging_device(1);
    let c = calibrated_streams(&device, (3000, 1000), (4, 5));
    let latencies: Vec<(Vec<u8>, f64, String)> = c
        .report
        .effects
        .iter()
        .filter(|f| f.added && f.family == spidar::model::diagnose::Family::Latency)
        .map(|f| (f.strings.clone(), f.amplitude_mm, f.description.clone()))
        .collect();
    let terms = latency_terms(&c);
    println!("{latencies:?}\n{terms:?}");
    for s in [2u8, 5] {
        let own = terms.iter().find(|t| t.0 == s).map(|t| t.1);
        assert!(
            own.is_some_and(|tau| (0.005..0.007).contains(&tau)),
            "string {s}: {terms:?}"
        );
    }
    assert!(
        terms.iter().all(|t| [2, 5].contains(&t.0)),
        "a latency on another string, or every string's: {terms:?}"
    );
    for (name, timing) in [
        ("train", &c.report.timing.train),
        ("test", &c.report.timing.test),
    ] {
        assert_clock_found(&device, name, timing);
    }
    for (strings, _, description) in &latencies {
        if strings.is_empty() {
            assert!(description.contains("tracker's clock"), "{description}");
        }
    }
}

/// The 30,000-row stream of `scripts/bench-large-session --kind stream
/// --seed 2` with 6 ms of latency on strings 2 and 5: the alignment's quick
/// model, without them, puts the tracker's clock 0.23 ms off, so every
/// string on time reads 0.23 ms early. The loop tried the latency every
/// string shares beside stronger terms, and later took strings 0, 3, 6
/// and 7 together at -0.22 ms each: four strings named that lag nothing.
/// The latency every string shares, proposed in the same round, is tried
/// in a group's place and takes it with a lower held-out mean; it goes into
/// the clocks' offsets, found at the truth (decision record 0080).
#[test]
fn strings_on_time_read_early_alike_are_the_clock_not_a_group() {
    // The session seeds `spidar simulate` gives streams of device 2.
    let device = lagging_device(2);
    let c = calibrated_streams(&device, (30_000, 3000), (5, 6));
    let terms = latency_terms(&c);
    println!("{terms:?}");
    assert_eq!(
        terms.iter().map(|t| t.0).collect::<Vec<_>>(),
        [2, 5],
        "{terms:?}"
    );
    assert!(
        terms.iter().all(|t| (0.0055..0.0065).contains(&t.1)),
        "{terms:?}"
    );
    assert_clock_found(&device, "train", &c.report.timing.train);
}

/// The independent device of `seed` with 6 ms of encoder latency on
/// strings 2 and 5.
fn lagging_device(seed: u64) -> PhysicsDevice {
    PhysicsDevice::new(
        &PhysicsConfig {
            effects: vec![
                "latency:string=2,ms=6".into(),
                "latency:string=5,ms=6".into(),
            ],
            ..PhysicsConfig::default()
        },
        seed,
    )
    .unwrap()
}

/// `device` calibrated (quick) on a 100 Hz training stream over the
/// training area and a test stream over the whole workspace, of `rows` rows
/// and session `seeds`.
fn calibrated_streams(
    device: &PhysicsDevice,
    rows: (usize, usize),
    seeds: (u64, u64),
) -> spidar::procedures::calibrate::Calibrated {
    let stream = |rows, area, seed| {
        simulate_session(device, SessionKind::Stream { rows, area }, seed)
            .unwrap()
            .0
    };
    let train = stream(rows.0, spidar::sim::StreamArea::Training, seeds.0);
    let test = stream(rows.1, spidar::sim::StreamArea::Whole, seeds.1);
    calibrate_quick(device, &train, &test)
}

/// The calibration's latency terms: (string, seconds).
fn latency_terms(c: &spidar::procedures::calibrate::Calibrated) -> Vec<(u8, f64)> {
    c.calibration
        .effects
        .iter()
        .filter_map(|t| match t.effect {
            spidar_core::model::Effect::Latency { latency_s } => Some((t.string, latency_s)),
            _ => None,
        })
        .collect()
}

/// Session `name`'s tracker clock was found from its motion within 0.05 ms
/// of `device`'s.
fn assert_clock_found(
    device: &PhysicsDevice,
    name: &str,
    timing: &spidar::procedures::calibrate::align::SessionTiming,
) {
    let spidar::procedures::calibrate::align::SessionTiming::Aligned(a) = timing else {
        panic!("{name}: {timing:?}");
    };
    println!("{name}: {a:?}");
    assert!(
        (a.offset_s - device.config.tracker.clock_offset_s).abs() < 5e-5,
        "{name}: {a:?}"
    );
}
