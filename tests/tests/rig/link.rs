//! The device link end to end, through the same serial path as a real
//! device: `link::Client` (serialport crate) on the slave side of the
//! virtual device's pseudo-terminal, the firmware's `Device`/`DeviceLink` on
//! the master side.

use spidar_tests::{blob, eventually, sim_device, virtual_device, virtual_device_in_device_time};
use std::time::Duration;

use spidar::device::link::{Client, ClientOptions, FlashPhase, LinkError, StreamOptions};
use spidar::sim::virtual_device::{spawn, Plant, Trajectory, VirtualDeviceConfig};
use spidar_core::correction::{CorrectionModel, NnModel, OutputMode, Standardization};
use spidar_protocol::blob::{split_blob, write_blob, CRC32};
use spidar_protocol::{
    encode_device_message, encode_request, BadState, BlobRejection, DeviceError, DeviceMessage,
    Event, Faults, FrameDecoder, HelloAck, Request, Response, State, MAX_FRAME,
};

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
        w2: [0, 1, 2].map(|a| (0..hidden).map(|h| w(h + a + 5) / 1000.0).collect()),
        b2: [0.0; 3],
        mode: OutputMode::Residual,
    })
}

fn quick() -> ClientOptions {
    ClientOptions {
        timeout: Duration::from_millis(40),
        retries: 0,
        ..ClientOptions::default()
    }
}

#[test]
fn flash_commits_reads_back_and_the_stream_reports_the_model() {
    let dev = sim_device();
    let vd = virtual_device(Trajectory::Hold);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    assert!(c.info().unwrap().is_none());
    let b = blob(&dev, nn(6), 0xA11C_E001);
    let mut phases = Vec::new();
    let report = c.flash(&b, |p| phases.push(p)).unwrap();
    assert_eq!(report.model_id, 0xA11C_E001);
    assert_eq!(report.blob_crc32, CRC32.checksum(&b));
    assert_eq!(report.resumed_at, 0);
    assert_eq!(report.chunks as usize, b.len().div_ceil(256));
    assert_eq!(phases.first().unwrap().phase, FlashPhase::Begin);
    assert_eq!(phases.last().unwrap().phase, FlashPhase::Verified);
    assert!(phases.windows(2).all(|w| w[0].sent <= w[1].sent));
    let info = c.info().unwrap().unwrap();
    assert_eq!(info.blob_crc32, CRC32.checksum(&b));
    let mut states = Vec::new();
    let r = c
        .stream(
            StreamOptions {
                decimation: 5,
                max_frames: Some(10),
                ..StreamOptions::default()
            },
            |s| {
                states.push(*s);
                true
            },
        )
        .unwrap();
    // Frames a busy host left unread may be dropped by the real-time
    // device; every one received runs the flashed model.
    assert_eq!(r.frames, 10);
    assert!(states.iter().all(|s| s.model_id == Some(0xA11C_E001)));
}

#[test]
fn upload_resumes_where_the_device_stands() {
    let dev = sim_device();
    let vd = virtual_device(Trajectory::Hold);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let b = blob(&dev, nn(40), 42);
    assert!(b.len() > 1024);
    let crc32 = CRC32.checksum(&b);
    let total_len = b.len() as u32;
    // Three chunks, then the host "crashes" and a new session resumes.
    let r = c
        .request(&Request::UploadBegin {
            total_len,
            crc32,
            model_id: 42,
        })
        .unwrap();
    assert_eq!(r, Response::ChunkAck { next_offset: 0 });
    for k in 0..3u32 {
        let at = (k * 256) as usize;
        c.request(&Request::UploadChunk {
            offset: k * 256,
            data: &b[at..at + 256],
        })
        .unwrap();
    }
    // A resent chunk (lost ack) is acknowledged again without effect.
    let again = c
        .request(&Request::UploadChunk {
            offset: 256,
            data: &b[256..512],
        })
        .unwrap();
    assert_eq!(again, Response::ChunkAck { next_offset: 768 });
    drop(c);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let report = c.flash(&b, |_| {}).unwrap();
    assert_eq!(report.resumed_at, 768);
    assert_eq!(c.info().unwrap().unwrap().header.model_id, 42);
}

/// Cuts the power at every flash operation of an upload (erase, every word
/// of every chunk: chunk boundaries and mid-chunk, each torn half-way, and
/// the commit record): after the power cycle the previous model is active
/// and intact, and the upload finally goes through.
#[test]
fn upload_cut_at_every_flash_operation_keeps_the_previous_model() {
    let dev = sim_device();
    let vd = virtual_device(Trajectory::Hold);
    let old = blob(&dev, CorrectionModel::None, 1);
    let new = blob(&dev, nn(4), 2);
    // Opening and reading back wait as long as a busy machine needs; the
    // upload that the cut silences gives up after 4 x 40 ms (a device that
    // lost its power never answers; one reply late under load is resent).
    let opts = ClientOptions {
        max_chunk: 64,
        ..ClientOptions::for_simulated_device()
    };
    let cutting = ClientOptions {
        timeout: Duration::from_millis(40),
        ..opts
    };
    let mut c = Client::open_with(vd.port_path(), opts).unwrap();
    c.flash(&old, |_| {}).unwrap();
    let old_info = c.info().unwrap().unwrap();
    drop(c);
    let mut cut = 0usize;
    let mut cuts_survived = 0;
    loop {
        let mut c = Client::open_with(vd.port_path(), opts).unwrap();
        c.set_options(cutting);
        vd.cut_flash_after(cut);
        match c.flash(&new, |_| {}) {
            Ok(r) => {
                assert_eq!(r.model_id, 2);
                break;
            }
            Err(LinkError::Timeout { .. } | LinkError::CommitUnanswered { .. }) => {}
            Err(e) => panic!("cut {cut}: {e}"),
        }
        assert!(vd.status().power_lost, "cut {cut}: the power went");
        drop(c);
        vd.power_cycle().unwrap();
        let mut c = Client::open_with(vd.port_path(), opts).unwrap();
        let info = c.info().unwrap().expect("a model after the cut");
        assert_eq!(info, old_info, "cut after {cut} operations");
        cuts_survived += 1;
        cut += 1;
        assert!(cut < 200, "the upload never completes");
    }
    // erase + one op per 32-byte word + the record
    assert!(cuts_survived > new.len() / 32, "{cuts_survived} cuts");
    vd.power_cycle().unwrap();
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let info = c.info().unwrap().unwrap();
    assert_eq!(info.header.model_id, 2);
    assert_eq!(info.blob_crc32, CRC32.checksum(&new));
}

/// The link drops mid-chunk (half a frame on the wire) and the device
/// power-cycles: old model intact, the half frame is not a request.
#[test]
fn half_a_chunk_frame_then_a_power_cycle() {
    let dev = sim_device();
    let vd = virtual_device(Trajectory::Hold);
    let old = blob(&dev, CorrectionModel::None, 10);
    let new = blob(&dev, nn(4), 11);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    c.flash(&old, |_| {}).unwrap();
    let old_info = c.info().unwrap().unwrap();
    c.request(&Request::UploadBegin {
        total_len: new.len() as u32,
        crc32: CRC32.checksum(&new),
        model_id: 11,
    })
    .unwrap();
    let mut tx = [0u8; MAX_FRAME];
    let frame = encode_request(
        900,
        &Request::UploadChunk {
            offset: 0,
            data: &new[..256],
        },
        &mut tx,
    )
    .unwrap();
    c.write_raw(&frame[..frame.len() / 2]).unwrap();
    drop(c);
    vd.power_cycle().unwrap();
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    assert_eq!(c.info().unwrap().unwrap(), old_info);
    let r = c.flash(&new, |_| {}).unwrap();
    assert_eq!(r.resumed_at, 0);
    assert_eq!(c.info().unwrap().unwrap().header.model_id, 11);
}

#[test]
fn a_blob_the_device_refuses_leaves_the_old_model() {
    let dev = sim_device();
    let vd = virtual_device(Trajectory::Hold);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let good = blob(&dev, CorrectionModel::None, 5);
    c.flash(&good, |_| {}).unwrap();
    // Header and CRCs fine, but 7 strings: the device's parser refuses it.
    let (mut h, body) = split_blob(&good).unwrap();
    h.strings = 7;
    h.model_id = 6;
    let mut bad = vec![0u8; good.len()];
    let n = write_blob(&h, body, &mut bad).unwrap();
    bad.truncate(n);
    let e = c.flash(&bad, |_| {}).unwrap_err();
    match e.device_error() {
        Some(DeviceError::BlobRejected(BlobRejection::Dimension { field, .. })) => {
            assert_eq!(field.as_str(), "strings")
        }
        _ => panic!("{e}"),
    }
    assert!(e.to_string().contains("strings"), "{e}");
    assert_eq!(c.info().unwrap().unwrap().header.model_id, 5);
    // A local check before anything is sent: not a blob at all.
    assert!(matches!(
        c.flash(b"not a blob", |_| {}),
        Err(LinkError::InvalidBlob(_))
    ));
}

#[test]
fn a_blob_larger_than_the_device_s_capacity_is_refused() {
    // Every blob within the correction's tick budget (decision record 0068)
    // fits the reference firmware's 96 KiB, so the refusal is shown on a
    // device that takes less: 8 KiB, and a 400-neuron network (11 KiB).
    let dev = sim_device();
    let capacity = 8 * 1024;
    let vd = spawn(
        VirtualDeviceConfig {
            blob_capacity: capacity,
            ..VirtualDeviceConfig::default()
        },
        Plant::new(dev.clone(), Trajectory::Hold),
    )
    .unwrap();
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let big = blob(
        &dev,
        nn(spidar_core::correction::MAX_HIDDEN_NEURONS as usize),
        3,
    );
    assert!(big.len() > capacity);
    let e = c.flash(&big, |_| {}).unwrap_err();
    assert!(
        matches!(e.device_error(), Some(DeviceError::TooLarge { capacity: c, .. }) if *c as usize == capacity),
        "{e}"
    );
}

#[test]
fn corrupted_frames_are_rejected_and_counted() {
    let vd = virtual_device(Trajectory::Hold);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let before = c.stats().unwrap().rx;
    let mut tx = [0u8; MAX_FRAME];
    let good = encode_request(77, &Request::GetInfo, &mut tx)
        .unwrap()
        .to_vec();
    // One flipped bit: CRC (or COBS) error.
    let mut flipped = good.clone();
    flipped[2] ^= 0x04;
    c.write_raw(&flipped).unwrap();
    // Garbage.
    c.write_raw(&[0x13, 0x37, 0x42, 0x99, 0x01, 0x00]).unwrap();
    // Longer than any frame.
    c.write_raw(&[0x55; 600]).unwrap();
    c.write_raw(&[0x00]).unwrap();
    // Still answering, nothing answered for the bad frames.
    let after = c.stats().unwrap().rx;
    assert_eq!(after.rejected() - before.rejected(), 3, "{after:?}");
    assert!(after.crc + after.cobs > before.crc + before.cobs);
    assert_eq!(after.overlong - before.overlong, 1);
    assert_eq!(vd.status().rx.rejected(), after.rejected());
}

/// A device that stops hearing from its host drops the tensions to
/// pre-tension within 30 ms of device time. In device time (`Pace::Fast`:
/// the clock holds between requests and ticks run back to back while
/// streaming), so the last request is `StreamOn` whatever the host's speed:
/// in real time a host stalled between two requests lost the heartbeat
/// before the test began to watch. Frames are judged by their timestamps,
/// so a frame the host was too slow to take changes nothing.
#[test]
fn heartbeat_loss_drops_tensions_to_pretension_within_30_ms() {
    let dev = sim_device();
    let vd = virtual_device_in_device_time(None);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    c.flash(&blob(&dev, CorrectionModel::None, 9), |_| {})
        .unwrap();
    c.arm().unwrap();
    c.set_force([0.0, 0.0, 3.0]).unwrap();
    // Not streaming, the clock holds: `StreamOn` is handled at this time,
    // and it is the last request (no heartbeat after it).
    let t_last_request = vd.status().device_time_us;
    let pre = spidar_core::control::ControlConfig::default()
        .safety
        .pretension_n;
    let since = |s: &State| s.time_us.saturating_sub(t_last_request);
    let mut silent: Vec<State> = Vec::new();
    c.stream(
        StreamOptions {
            heartbeat: None,
            ..StreamOptions::default()
        },
        |s| {
            silent.push(*s);
            since(s) < 300_000
        },
    )
    .unwrap();
    let rendering = |s: &State| s.tensions_n.iter().any(|&t| t > pre + 0.1);
    let dropped = |s: &State| {
        s.faults.contains(Faults::HEARTBEAT_LOST) && s.tensions_n.iter().all(|&t| t == pre)
    };
    // Heard within the timeout (20 ms): the force is rendered.
    let heard: Vec<&State> = silent.iter().filter(|s| since(s) <= 10_000).collect();
    assert!(!heard.is_empty(), "no frame in the first 10 ms: {silent:?}");
    assert!(heard.iter().all(|s| rendering(s) && s.armed), "{heard:?}");
    // From 30 ms on, every frame says the heartbeat was lost, at pre-tension.
    let late: Vec<&State> = silent.iter().filter(|s| since(s) >= 30_000).collect();
    assert!(!late.is_empty());
    assert!(late.iter().all(|s| dropped(s)), "{late:?}");
    assert!(c.take_events().contains(&Event::HeartbeatLost));
    // The plant's tensions follow within a few motor time constants (of
    // the plant's own clock: the stream ran 300 ms of it).
    assert!(eventually(|| vd
        .status()
        .plant_tensions_n
        .iter()
        .all(|&t| (t - f64::from(pre)).abs() < 0.05)));
    c.disarm().unwrap();
}

/// What the device streams and what it enforces agree: after a heartbeat
/// loss the loop is disarmed but the motors hold pre-tension, and the state
/// says so (`motors_on`) while every model change is refused as `Armed`;
/// after `Disarm` both say off. In device time (`Pace::Fast`: no tick
/// between streams), so the heartbeat lapses inside one stream whatever
/// the host's speed.
#[test]
fn the_state_says_the_motors_are_on_while_model_changes_are_refused() {
    let dev = sim_device();
    let vd = virtual_device_in_device_time(None);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    c.flash(&blob(&dev, CorrectionModel::None, 21), |_| {})
        .unwrap();
    c.arm().unwrap();
    let mut states: Vec<State> = Vec::new();
    c.stream(
        StreamOptions {
            heartbeat: None,
            ..StreamOptions::default()
        },
        |s| {
            states.push(*s);
            !s.faults.contains(Faults::HEARTBEAT_LOST)
        },
    )
    .unwrap();
    assert!(states[0].armed && states[0].motors_on, "{:?}", states[0]);
    let lost = states.last().unwrap();
    assert!(
        lost.faults.contains(Faults::HEARTBEAT_LOST) && !lost.armed && lost.motors_on,
        "{lost:?}"
    );
    assert!(states.iter().all(|s| s.motors_on), "{states:?}");
    let refused = |c: &mut Client| {
        let e = c
            .flash(&blob(&dev, CorrectionModel::None, 22), |_| {})
            .unwrap_err();
        matches!(
            e.device_error(),
            Some(DeviceError::BadState(BadState::Armed))
        )
    };
    assert!(refused(&mut c));
    let some_states = |c: &mut Client| {
        let mut got = Vec::new();
        c.stream(
            StreamOptions {
                max_frames: Some(3),
                ..StreamOptions::default()
            },
            |s| {
                got.push(*s);
                true
            },
        )
        .unwrap();
        got
    };
    let holding = some_states(&mut c);
    assert!(
        holding.iter().all(|s| !s.armed && s.motors_on),
        "{holding:?}"
    );
    c.disarm().unwrap();
    let off = some_states(&mut c);
    assert!(off.iter().all(|s| !s.armed && !s.motors_on), "{off:?}");
    let flashed = c
        .flash(&blob(&dev, CorrectionModel::None, 22), |_| {})
        .unwrap();
    assert_eq!(flashed.model_id, 22);
}

#[test]
fn streamed_positions_follow_the_plant() {
    let dev = sim_device();
    let vd = virtual_device(Trajectory::Orbit {
        radius_mm: 100.0,
        period_s: 2.0,
    });
    // Flashed a fifth of an orbit (device time) after boot: the end-effector
    // waits at home until the model homes the device there, then sets off;
    // a device homed anywhere else reads every position off by as much.
    assert!(eventually(|| vd.status().device_time_us >= 400_000));
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    c.flash(&blob(&dev, CorrectionModel::None, 4), |_| {})
        .unwrap();
    let started = vd.status().path_start_us.expect("homed by the model");
    assert!(started >= 400_000, "{started}");
    let mut worst: f64 = 0.0;
    let r = c
        .stream(
            StreamOptions {
                decimation: 2,
                max_frames: Some(100),
                ..StreamOptions::default()
            },
            |s| {
                let truth = vd.truth_room_mm(s.time_us);
                let e = (0..3)
                    .map(|k| {
                        (spidar_protocol::messages::q16_to_mm(s.corrected_mm[k]) - truth[k]).powi(2)
                    })
                    .sum::<f64>()
                    .sqrt();
                worst = worst.max(e);
                true
            },
        )
        .unwrap();
    // Judged frame by frame at each frame's own device time: frames the
    // device dropped while a busy host did not read (a real-time device
    // does not queue them) change nothing here.
    assert_eq!(r.frames, 100, "{r:?}");
    // One count is 2 pi r / 4096, about 0.02 mm of string.
    assert!(worst < 0.1, "worst {worst} mm");
}

#[test]
fn missing_busy_silent_and_mismatched_ports_are_named() {
    match Client::open("/dev/spidar-does-not-exist") {
        Err(LinkError::PortMissing { port }) => assert_eq!(port, "/dev/spidar-does-not-exist"),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("opened a missing port"),
    }
    let vd = virtual_device(Trajectory::Hold);
    let _first = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    match Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()) {
        Err(LinkError::PortBusy { port }) => assert_eq!(port, vd.port_path()),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("opened a busy port"),
    }

    // A port with nothing behind it.
    let (_master, slave) = serialport::TTYPort::pair().unwrap();
    let path = serialport::SerialPort::name(&slave).unwrap();
    match Client::open_with(&path, quick()) {
        Err(LinkError::Timeout {
            request, attempts, ..
        }) => {
            assert_eq!(request, "Hello");
            assert_eq!(attempts, 1);
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("a silent port answered"),
    }

    // A device of protocol version 99.
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    let path = serialport::SerialPort::name(&slave).unwrap();
    let responder = std::thread::spawn(move || {
        use std::io::{Read, Write};
        let mut rx: FrameDecoder = FrameDecoder::new();
        let mut buf = [0u8; 512];
        for _ in 0..200 {
            let n = master.read(&mut buf).unwrap_or(0);
            let mut seqs = Vec::new();
            rx.feed_requests(&buf[..n], |r| {
                if let Ok(p) = r {
                    seqs.push(p.seq)
                }
            });
            if let Some(&seq) = seqs.first() {
                let ack = DeviceMessage::Reply(Response::HelloAck(HelloAck {
                    protocol_version: 99,
                    firmware_version: [9, 9, 9],
                    device_id: [0; 12],
                    capabilities: Default::default(),
                    max_chunk: 256,
                    max_blob_len: 1024,
                    loop_period_us: 1000,
                }));
                let mut tx = [0u8; MAX_FRAME];
                let f = encode_device_message(seq, &ack, &mut tx).unwrap();
                master.write_all(f).unwrap();
                // Keep the master open until the client has read the reply.
                return Some(master);
            }
        }
        None
    });
    // The responder answers when it is scheduled: no deadline a busy
    // machine could miss (the silent port above is the timeout's case).
    let patient = ClientOptions {
        timeout: Duration::from_secs(10),
        retries: 0,
        ..ClientOptions::default()
    };
    match Client::open_with(&path, patient) {
        Err(LinkError::VersionMismatch { device, host, .. }) => {
            assert_eq!(device, 99);
            assert_eq!(host, spidar_protocol::PROTOCOL_VERSION);
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("accepted protocol 99"),
    }
    drop(responder.join().unwrap());
    drop(slave);
}

/// Benchmarks of docs/benchmarks.md ("Link, virtual device and simulated rig"):
/// `cargo test -p spidar-tests --test rig -- --ignored --nocapture link_benchmarks`
#[test]
#[ignore]
fn link_benchmarks() {
    let dev = sim_device();
    // A ~32 KB blob: NN with enough hidden neurons.
    let mut hidden = 1000;
    let mut big = blob(&dev, nn(hidden), 32);
    while big.len() < 32 * 1024 {
        hidden += 20;
        big = blob(&dev, nn(hidden), 32);
    }
    let vd = virtual_device_in_device_time(None);
    let mut c = Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let mut runs = Vec::new();
    for _ in 0..5 {
        c.clear_model().unwrap();
        runs.push(c.flash(&big, |_| {}).unwrap());
    }
    let med = |f: &dyn Fn(&spidar::device::link::FlashReport) -> f64| {
        let mut v: Vec<f64> = runs.iter().map(f).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!(
        "blob {} bytes (NN hidden {hidden}), {} chunks: upload {:.1} ms, commit {:.2} ms, read-back {:.2} ms (median of {})",
        big.len(),
        runs[0].chunks,
        med(&|r| r.upload.as_secs_f64() * 1e3),
        med(&|r| r.commit.as_secs_f64() * 1e3),
        med(&|r| r.verify.as_secs_f64() * 1e3),
        runs.len()
    );
    // Protocol overhead of a state frame: frame bytes minus postcard(State).
    let mut sizes = Vec::new();
    let r = c
        .stream(
            StreamOptions {
                decimation: 1,
                duration: Some(Duration::from_secs(1)),
                ..StreamOptions::default()
            },
            |s| {
                let msg = postcard::to_allocvec(&DeviceMessage::State(*s)).unwrap();
                sizes.push(msg.len() - 1);
                true
            },
        )
        .unwrap();
    let state = sizes.iter().sum::<usize>() as f64 / sizes.len() as f64;
    let per_frame = r.bytes as f64 / r.frames as f64;
    println!(
        "state stream (Pace::Fast, decimation 1): {} frames in {:.2} s = {:.0} frames/s, {} lost, {} rejected; {:.1} bytes/frame on the wire, State {:.1} bytes, overhead {:.1} bytes/frame",
        r.frames,
        r.elapsed.as_secs_f64(),
        r.frames as f64 / r.elapsed.as_secs_f64(),
        r.lost,
        r.rejected,
        per_frame,
        state,
        per_frame - state
    );
}
