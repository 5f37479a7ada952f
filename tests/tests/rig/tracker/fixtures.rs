//! What the tests share: the DTrack2 manual's datagram, a frame's text, a
//! malformed datagram's error, and a receiver on loopback receiving all a
//! sender sends.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use spidar::device::tracker::dtrack::{
    format_datagram, parse_datagram, BodyPose, DtrackError, DtrackFrame, FieldProblem,
};
use spidar::device::tracker::{DtrackReceiver, Next, ReceiverConfig, TrackerFrame, TrackerSource};
use spidar::sim::tracker::{SimReport, SimSender};

const LOOPBACK_ANY_PORT: &str = "127.0.0.1:0";

/// The example of the DTrack2 manual (B.2.1-B.2.3) as one datagram.
pub(super) const MANUAL: &str = "fr 21753\r\nts 39596.024470\r\n6dcal 2\r\n6d 1 [0 1.000][326.848 -187.216 109.503 -160.4704 -3.6963 -7.0913][-0.940508 -0.339238 0.019025 0.333599 -0.932599 -0.137735 0.064467 -0.123194 0.990286]\r\n";

pub(super) fn loopback() -> SocketAddr {
    LOOPBACK_ANY_PORT.parse().unwrap()
}

/// The error of a malformed datagram names the line and the field.
pub(super) fn field_error(d: &str) -> (usize, String, FieldProblem) {
    match parse_datagram(d.as_bytes()) {
        Err(DtrackError::Field {
            line,
            field,
            problem,
        }) => {
            let e = DtrackError::Field {
                line,
                field: field.clone(),
                problem: problem.clone(),
            };
            assert!(e.to_string().contains(&field), "{e}");
            (line, field, problem)
        }
        other => panic!("{d:?}: expected a field error, got {other:?}"),
    }
}

pub(super) fn receiver(window: u32, max_delay_ms: u64) -> DtrackReceiver {
    DtrackReceiver::bind(ReceiverConfig {
        reorder_window: window,
        max_delay: Duration::from_millis(max_delay_ms),
        ..ReceiverConfig::new(loopback())
    })
    .unwrap()
}

/// Receive until the sender is done and the line is quiet, then drain.
pub(super) fn receive_all(
    rx: &mut DtrackReceiver,
    sender: SimSender,
) -> (Vec<TrackerFrame>, SimReport) {
    let start = Instant::now();
    let mut frames = Vec::new();
    while start.elapsed() < Duration::from_secs(30) {
        match rx.next_frame(Duration::from_millis(100)).unwrap() {
            Next::Frame(f) => frames.push(f),
            Next::Timeout if sender.is_finished() => break,
            Next::Timeout => {}
            Next::End => break,
        }
    }
    frames.extend(rx.drain());
    (frames, sender.join().unwrap())
}

pub(super) fn frame_text(n: u32, ts: f64) -> String {
    format_datagram(&DtrackFrame {
        frame: n,
        ts_s: Some(ts),
        calibrated_bodies: None,
        bodies: vec![BodyPose::at(0, [1.0, 2.0, 3.0])],
        has_6d: true,
    })
}
