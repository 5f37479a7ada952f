//! `StreamingClient`: the stream read by a thread of its own while the
//! caller's requests are answered; the reader sends nothing, so a caller
//! that stops calling is disarmed by the device's watchdog. In device time
//! (`Pace::Fast`: the device ticks only while the stream is on, back to
//! back as the reader takes it), judged by the frames' timestamps.

use spidar_tests::{blob, sim_device, virtual_device_in_device_time};
use std::time::Duration;

use spidar::device::link::{Client, ClientOptions, StreamingClient};
use spidar_core::correction::CorrectionModel;
use spidar_protocol::{Event, Faults, Request, Response};

fn fast_device_with_model(
    heartbeat_timeout_ms: u32,
) -> (spidar::sim::virtual_device::VirtualDevice, Client) {
    let dev = sim_device();
    let vd = virtual_device_in_device_time(Some(heartbeat_timeout_ms));
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    c.flash(&blob(&dev, CorrectionModel::None, 0x57EA_0001), |_| {})
        .unwrap();
    (vd, c)
}

#[test]
fn requests_are_answered_while_the_reader_takes_every_frame() {
    let (_vd, c) = fast_device_with_model(60_000);
    let s = StreamingClient::start(c, 1).unwrap();
    let first = s.wait_newer(0, Duration::from_secs(10)).unwrap();
    s.expect_ack(&Request::Arm).unwrap();
    let mut last = first.index;
    for k in 0..50 {
        let f = [0.0, 0.0, 0.02 * k as f32];
        s.expect_ack(&Request::SetForceTarget { force_n: f })
            .unwrap();
        let r = s.wait_newer(last, Duration::from_secs(10)).unwrap();
        assert!(r.index > last && r.state.time_us > 0);
        last = r.index;
    }
    // A request whose reply carries data is matched by its sequence number
    // among the state frames.
    match s.request(&Request::GetInfo).unwrap() {
        Response::Info(Some(i)) => assert_eq!(i.header.model_id, 0x57EA_0001),
        other => panic!("{other:?}"),
    }
    // The newest frame renders the last force, armed.
    let newest = s.wait_newer(last, Duration::from_secs(10)).unwrap();
    assert!(newest.state.armed, "{:?}", newest.state);
    assert!(newest.state.rendered_force_n[2] > 0.5, "{:?}", newest.state);
    s.expect_ack(&Request::Disarm).unwrap();
    let seq = s.stream_seq();
    assert_eq!(seq.lost, 0, "{seq:?}");
    assert!(u64::from(seq.received) >= newest.index);
    assert_eq!(s.rejected(), 0);
    // Joined back, the client goes on as before: the stream off, requests
    // answered, the counters carried over.
    let mut c = s.stop().unwrap();
    assert_eq!(c.info().unwrap().unwrap().header.model_id, 0x57EA_0001);
    assert!(c.stream_seq().received >= seq.received);
}

#[test]
fn a_caller_that_stops_calling_is_disarmed_by_the_device_watchdog() {
    let (vd, mut c) = fast_device_with_model(20);
    c.arm().unwrap();
    c.set_force([0.0, 0.0, 2.0]).unwrap();
    // Not streaming, the device's clock holds: `StreamOn` is handled at
    // this device time, and it is the last request (the reader only
    // reads).
    let t_last = vd.status().device_time_us;
    let s = StreamingClient::start(c, 1).unwrap();
    let mut after = 0;
    let lost = loop {
        let r = s.wait_newer(after, Duration::from_secs(10)).unwrap();
        after = r.index;
        if r.state.faults.contains(Faults::HEARTBEAT_LOST) {
            break r;
        }
        assert!(
            r.state.time_us <= t_last + 20_000 + 1_000,
            "still armed at {} µs, 20 ms timeout from {t_last}: {:?}",
            r.state.time_us,
            r.state
        );
    };
    assert!(!lost.state.armed);
    assert!(lost.state.time_us >= t_last + 20_000, "{:?}", lost.state);
    assert!(s.take_events().contains(&Event::HeartbeatLost));
    s.expect_ack(&Request::Disarm).unwrap();
}
