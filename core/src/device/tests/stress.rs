//! The device under arbitrary input, and what a tick costs.

use super::bench::{calibration, nn, raw_at, Bench, Flash, SLOT};
use crate::blob::{compile, BlobHead};
use crate::control::LoopInput;
use crate::correction::CorrectionModel;
use crate::device::*;
use spidar_protocol::{Request, Response};
use std::vec::Vec;

/// Arbitrary bytes and arbitrary upload requests never panic the device.
#[test]
fn garbage_never_panics() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let mut x = 0x1234_5678_9abc_def0u64;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    let mut bytes = Vec::new();
    for _ in 0..20_000 {
        let v = next();
        bytes.push(if v % 7 == 0 { 0 } else { v as u8 });
    }
    for piece in bytes.chunks(61) {
        let dev = &mut b.dev;
        let mut rest = piece;
        while !rest.is_empty() {
            let (used, _) = b.link.push(rest, |req, _| dev.handle(req, 0));
            rest = &rest[used..];
        }
    }
    let data = [0xA5u8; MAX_CHUNK];
    for _ in 0..2000 {
        let v = next();
        let offset = (v >> 8) as u32 % 20_000;
        let len = 1 + (v >> 40) as usize % MAX_CHUNK;
        let req = match v % 5 {
            0 => Request::UploadBegin {
                total_len: (v >> 20) as u32 % 20_000,
                crc32: v as u32,
                model_id: 1,
            },
            1 | 2 => Request::UploadChunk {
                offset,
                data: &data[..len],
            },
            3 => Request::UploadCommit {
                crc32: (v >> 3) as u32,
            },
            _ => Request::UploadStatus,
        };
        b.dev.handle(&req, 0);
        b.tick_at(raw_at([0.0; 3]));
    }
}

/// What a tick costs with the borrow handled three ways (host timings;
/// `cargo test -p spidar-core --release --lib device::tests::stress::tick_cost
/// -- --ignored --nocapture`).
#[test]
#[ignore]
fn tick_cost() {
    use std::time::Instant;
    const N: u32 = 20_000;
    for hidden in [0usize, 16, 64] {
        let model = if hidden == 0 {
            CorrectionModel::None
        } else {
            nn(hidden)
        };
        let blob = compile(&calibration(model), 1, 0).unwrap();
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
        assert_eq!(b.upload(&blob, 1, 256), Response::Committed { model_id: 1 });
        let raw = raw_at([10.0, 20.0, 30.0]);
        let input = |k: u32| TickInput {
            raw_counts: raw,
            now_us: u64::from(k) * 100,
            estop: false,
        };
        let t = Instant::now();
        for k in 0..N {
            std::hint::black_box(b.dev.tick(&input(k)));
        }
        let device_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
        let cal = CompiledCalibration::from_blob(&blob).unwrap();
        let mut ctl = Controller::new(ControlConfig::default(), &cal, raw, 0).unwrap();
        let li = |k: u32| LoopInput {
            raw_counts: raw,
            now_ms: k / 10,
            now_us: k * 100,
            estop: false,
        };
        let t = Instant::now();
        for k in 0..N {
            std::hint::black_box(ctl.step(&cal, &li(k)));
        }
        let step_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
        let t = Instant::now();
        for k in 0..N {
            let c = CompiledCalibration::from_blob(std::hint::black_box(&blob)).unwrap();
            std::hint::black_box(ctl.step(&c, &li(k)));
        }
        let reparse_ns = t.elapsed().as_nanos() as f64 / f64::from(N);
        std::println!(
            "hidden {hidden:3}, blob {:5} B: step alone {step_ns:7.0} ns, Device::tick \
             {device_ns:7.0} ns (+{:5.0}), from_blob every tick {reparse_ns:7.0} ns (+{:5.0}); \
             BlobHead {} B",
            blob.len(),
            device_ns - step_ns,
            reparse_ns - step_ns,
            core::mem::size_of::<BlobHead>()
        );
    }
}
