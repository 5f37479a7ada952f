//! The UDP receiver over loopback: loss, duplicates, reordering, occlusion,
//! bad datagrams, midnight, restarts, and the simulated sender.

use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use super::fixtures::{frame_text, loopback, receive_all, receiver};
use proptest::prelude::*;
use spidar::device::tracker::dtrack::DtrackError;
use spidar::device::tracker::receiver::Reorder;
use spidar::device::tracker::{collect, TrackerError, TrackerFrame, TrackerSource};
use spidar::sim::tracker::{SimSender, SimSenderConfig};

fn circle(t: f64) -> Option<[f64; 3]> {
    let w = 2.0 * std::f64::consts::PI * 0.5;
    Some([300.0 * (w * t).cos(), 300.0 * (w * t).sin(), 1500.0])
}

#[test]
fn receiver_counts_loss_duplicates_and_reordering() {
    let mut rx = receiver(8, 500);
    let cfg = SimSenderConfig {
        frames: 400,
        first_frame: 1000,
        ts_start_s: 100.0,
        loss: 0.1,
        duplicate: 0.05,
        reorder: 0.1,
        extra_records: true,
        seed: 7,
        ..SimSenderConfig::new(rx.local_addr())
    };
    let sender = SimSender::spawn(cfg, circle).unwrap();
    let (frames, report) = receive_all(&mut rx, sender);
    let stats = rx.receiver_stats();
    // The seed gives some of each, or the test proves nothing.
    assert!(report.expected_lost() > 10, "{report:?}");
    assert!(report.expected_duplicates() > 3, "{report:?}");
    assert!(report.expected_out_of_order() > 10, "{report:?}");

    assert_eq!(stats.datagrams, report.sent.len() as u64);
    assert_eq!(stats.source.malformed, 0, "{:?}", stats.last_error);
    assert_eq!(stats.source.lost, report.expected_lost());
    assert_eq!(stats.source.duplicates, report.expected_duplicates());
    assert_eq!(stats.source.out_of_order, report.expected_out_of_order());
    assert_eq!(stats.source.late, 0);
    let mut distinct = report.sent.clone();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        distinct,
        "every frame sent, once, in order"
    );
    assert_eq!(stats.source.delivered, frames.len() as u64);
    for f in &frames {
        let t = f64::from(f.frame - 1000) / 100.0;
        assert!((f.ts_s - (100.0 + t)).abs() < 1e-9);
        let p = f.body.as_ref().expect("never occluded").position_mm;
        let q = circle(t).unwrap();
        assert!((0..3).all(|k| (p[k] - q[k]).abs() < 1e-9));
    }
}

fn occluded_between(t: f64) -> Option<[f64; 3]> {
    if (0.2..0.4).contains(&t) || (0.71..0.73).contains(&t) {
        None
    } else {
        circle(t)
    }
}

#[test]
fn occlusion_gives_body_none_both_ways() {
    for negative_quality in [false, true] {
        let mut rx = receiver(4, 30);
        let cfg = SimSenderConfig {
            frames: 100,
            occluded_as_negative_quality: negative_quality,
            ..SimSenderConfig::new(rx.local_addr())
        };
        let sender = SimSender::spawn(cfg, occluded_between).unwrap();
        let (frames, report) = receive_all(&mut rx, sender);
        assert_eq!(frames.len(), 100);
        assert_eq!(report.occluded.len(), 22, "20 + 2 frames");
        let none: Vec<u32> = frames
            .iter()
            .filter(|f| f.body.is_none())
            .map(|f| f.frame)
            .collect();
        assert_eq!(none, report.occluded);
        assert_eq!(rx.stats().occluded, 22);
        assert_eq!(rx.stats().lost, 0);
    }
}

#[test]
fn bad_datagrams_are_counted_and_skipped() {
    let mut rx = receiver(4, 30);
    let tx = UdpSocket::bind(loopback()).unwrap();
    let to = rx.local_addr();
    let good = |n: u32| {
        format!(
            "fr {n}\r\nts {}.5\r\n6d 1 [0 1.0][1 2 3 0 0 0][1 0 0 0 1 0 0 0 1]\r\n",
            n
        )
    };
    tx.send_to(good(1).as_bytes(), to).unwrap();
    tx.send_to(b"\x00\x01garbage\xff", to).unwrap();
    tx.send_to(b"fr 2\r\n6d 1 [0 1.0][1 2 3][1 0 0]\r\n", to)
        .unwrap();
    tx.send_to(b"fr 3\r\n6d 0\r\n", to).unwrap(); // no ts
    tx.send_to(good(2).as_bytes(), to).unwrap();
    tx.send_to(good(3).as_bytes(), to).unwrap();
    let frames = collect(&mut rx, 3, Duration::from_secs(5)).unwrap();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [1, 2, 3]
    );
    let stats = rx.receiver_stats();
    assert_eq!(stats.datagrams, 6);
    assert_eq!(stats.source.malformed, 3);
    assert_eq!(stats.last_error, Some(DtrackError::MissingTimestamp));
    assert_eq!(stats.source.lost, 0);
}

#[test]
fn reordering_rules_on_a_fixed_sequence() {
    let mut rx = receiver(8, 10_000);
    let now = Instant::now();
    for n in [1, 2, 4, 3, 3, 7, 6, 2] {
        rx.accept(frame_text(n, f64::from(n)).as_bytes(), now);
    }
    let frames = rx.drain();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [1, 2, 3, 4, 6, 7]
    );
    let s = rx.stats();
    assert_eq!(
        (s.delivered, s.lost, s.out_of_order, s.duplicates, s.late),
        (6, 1, 2, 2, 0)
    );
    // 5 was given up: late; 1 was delivered: duplicate.
    rx.accept(frame_text(5, 5.0).as_bytes(), now);
    rx.accept(frame_text(1, 1.0).as_bytes(), now);
    let s = rx.stats();
    assert_eq!((s.late, s.duplicates), (1, 3));
    assert!(rx.drain().is_empty());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Whatever the arrival order: frames come out once each, in order;
    /// every arrival is delivered, a duplicate or late; every number in the
    /// delivered range is delivered or lost.
    #[test]
    fn reorder_accounts_for_every_arrival(
        arrivals in prop::collection::vec(0u32..60, 1..200),
        window in 0u32..10,
    ) {
        let mut r = Reorder::new(window, Duration::from_secs(3600));
        let now = Instant::now();
        let mut out = std::collections::VecDeque::new();
        for &n in &arrivals {
            let frame = TrackerFrame { frame: n, ts_s: f64::from(n), received_at: now, body: None };
            r.push(frame, &mut out);
            r.release(now, &mut out);
        }
        r.flush(&mut out);
        let got: Vec<u32> = out.iter().map(|f| f.frame).collect();
        prop_assert!(got.windows(2).all(|w| w[0] < w[1]), "{got:?}");
        let s = r.stats().clone();
        prop_assert_eq!(s.delivered as usize, got.len());
        prop_assert_eq!(s.delivered + s.duplicates + s.late, arrivals.len() as u64);
        let span = u64::from(got[got.len() - 1] - got[0]) + 1;
        prop_assert_eq!(s.delivered + s.lost, span);
        prop_assert_eq!(s.occluded, s.delivered);
        prop_assert_eq!(s.restarts, 0);
    }
}

#[test]
fn gaps_are_given_up_after_the_window_or_the_delay() {
    // Window: frame 2 never comes; 3..=6 arrive; with a window of 4 the
    // receiver gives 2 up and hands the rest out without waiting.
    let mut rx = receiver(4, 60_000);
    let tx = UdpSocket::bind(loopback()).unwrap();
    for n in [1, 3, 4, 5, 6] {
        tx.send_to(frame_text(n, f64::from(n)).as_bytes(), rx.local_addr())
            .unwrap();
    }
    let frames = collect(&mut rx, 5, Duration::from_secs(5)).unwrap();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [1, 3, 4, 5, 6]
    );
    assert_eq!(rx.stats().lost, 1);
    // Delay: 8 after 6 with a large window; 7 is given up after max_delay.
    let mut rx = receiver(1000, 20);
    for n in [6, 8] {
        tx.send_to(frame_text(n, f64::from(n)).as_bytes(), rx.local_addr())
            .unwrap();
    }
    let start = Instant::now();
    let frames = collect(&mut rx, 2, Duration::from_secs(5)).unwrap();
    assert_eq!(frames.iter().map(|f| f.frame).collect::<Vec<_>>(), [6, 8]);
    assert!(start.elapsed() >= Duration::from_millis(20));
    assert_eq!(rx.stats().lost, 1);
}

#[test]
fn timestamp_unwraps_at_midnight_and_counter_restarts() {
    let mut rx = receiver(2, 10_000);
    let now = Instant::now();
    rx.accept(frame_text(5000, 86_399.99).as_bytes(), now);
    rx.accept(frame_text(5001, 0.01).as_bytes(), now);
    // DTrack restarted: the counter starts again.
    rx.accept(frame_text(1, 0.02).as_bytes(), now);
    rx.accept(frame_text(2, 0.03).as_bytes(), now);
    let frames = rx.drain();
    let ts: Vec<f64> = frames.iter().map(|f| f.ts_s).collect();
    assert_eq!(
        frames.iter().map(|f| f.frame).collect::<Vec<_>>(),
        [5000, 5001, 1, 2]
    );
    assert!((ts[1] - 86_400.01).abs() < 1e-6, "{ts:?}");
    assert!((ts[3] - 86_400.03).abs() < 1e-6, "{ts:?}");
    let s = rx.stats();
    assert_eq!((s.restarts, s.lost, s.duplicates), (1, 0, 0));
}

#[test]
fn simulated_sender_refuses_other_than_loopback() {
    let target: SocketAddr = "192.0.2.1:5000".parse().unwrap();
    let err = SimSender::spawn(SimSenderConfig::new(target), circle).unwrap_err();
    assert!(matches!(err, TrackerError::NotLoopback(a) if a == target));
    let err = SimSender::spawn(
        SimSenderConfig {
            loss: 1.5,
            ..SimSenderConfig::new(loopback())
        },
        circle,
    )
    .unwrap_err();
    assert!(
        matches!(&err, TrackerError::Config(c) if c.field == "loss"),
        "{err}"
    );
}

#[test]
fn simulated_sender_stops_by_itself() {
    let mut rx = receiver(4, 30);
    let cfg = SimSenderConfig {
        frames: 1_000_000,
        send_interval: Duration::from_millis(2),
        max_duration: Duration::from_millis(100),
        ..SimSenderConfig::new(rx.local_addr())
    };
    let sender = SimSender::spawn(cfg, circle).unwrap();
    let (frames, report) = receive_all(&mut rx, sender);
    assert!(report.stopped_early);
    assert!(report.frames < 1000, "{}", report.frames);
    assert_eq!(frames.len() as u32, report.frames);
}
