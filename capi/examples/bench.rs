//! Benchmark of the C API on a virtual device (not a test: it prints
//! figures). State age: host time since the library received the newest
//! state, read in a loop. Set-force call: `spidar_set_force` from call to
//! return (the device's `Ack`). Force round trip: from calling
//! `spidar_set_force` with a new force to the first state whose rendered
//! force shows it. Median and p99 of each.
//!
//! ```sh
//! cargo run --release -p spidar-capi --example bench -- [SECONDS]
//! ```
//!
//! The virtual device runs in real time (1 kHz loop, a state every
//! iteration) with a 2 s heartbeat timeout, so that a loaded machine does
//! not disarm it mid-run; the end-effector stays at home.

use std::ffi::CStr;
use std::ptr::null_mut;
use std::time::{Duration, Instant};

use spidar_capi::*;

fn check(rc: i32, what: &str) {
    if rc != SPIDAR_OK {
        let msg = unsafe { CStr::from_ptr(spidar_last_error()) };
        panic!("{what}: {}", msg.to_string_lossy());
    }
}

fn quantiles(mut v: Vec<f64>) -> (f64, f64, usize) {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return (f64::NAN, f64::NAN, 0);
    }
    (v[n / 2], v[(n * 99 / 100).min(n - 1)], n)
}

fn main() {
    let seconds: f64 = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(5.0);
    let options = spidar_virtual_options {
        seed: 1,
        heartbeat_timeout_ms: 2000,
        fast: 0,
        hold: 1,
    };
    let mut dev = null_mut();
    check(spidar_open_virtual(&options, &mut dev), "open_virtual");
    // SAFETY: plain data.
    let mut s: spidar_state = unsafe { std::mem::zeroed() };
    check(spidar_wait_state(dev, 5000, &mut s), "wait_state");
    check(spidar_arm(dev), "arm");

    // State age, read in a tight loop (with a heartbeat every ms).
    let mut ages = Vec::new();
    let t0 = Instant::now();
    let mut beat = Instant::now();
    while t0.elapsed() < Duration::from_secs_f64(seconds / 2.0) {
        check(spidar_get_state(dev, &mut s), "get_state");
        ages.push(s.age_us as f64);
        if beat.elapsed() >= Duration::from_millis(1) {
            check(spidar_heartbeat(dev), "heartbeat");
            beat = Instant::now();
        }
    }

    // Force round trips: alternate 1 N and 2 N up (room frame).
    let mut calls = Vec::new();
    let mut trips = Vec::new();
    let t1 = Instant::now();
    let mut k = 0u32;
    while t1.elapsed() < Duration::from_secs_f64(seconds / 2.0) {
        let fz = if k % 2 == 0 { 1.0 } else { 2.0 };
        k += 1;
        let start = Instant::now();
        check(spidar_set_force(dev, 0.0, 0.0, fz), "set_force");
        calls.push(start.elapsed().as_secs_f64() * 1e6);
        loop {
            check(spidar_wait_state(dev, 2000, &mut s), "wait_state");
            if (s.rendered_force_n[2] - fz).abs() < 0.05 * fz {
                trips.push(start.elapsed().as_secs_f64() * 1e6);
                break;
            }
            if start.elapsed() > Duration::from_millis(500) {
                panic!("the device did not render {fz} N: {s:?}");
            }
        }
    }
    check(spidar_set_force(dev, 0.0, 0.0, 0.0), "set_force");
    check(spidar_disarm(dev), "disarm");
    check(spidar_get_state(dev, &mut s), "get_state");
    let lost = s.lost;
    check(spidar_close(dev), "close");

    let print = |name: &str, v: Vec<f64>| {
        let (median, p99, n) = quantiles(v);
        println!("{name:<22} median {median:>8.0} µs   p99 {p99:>8.0} µs   ({n} samples)");
    };
    print("state age", ages);
    print("set_force call", calls);
    print("force round trip", trips);
    println!("state frames lost: {lost}");
}
