//! Instruction-count benchmarks of spidar-core on the Cortex-M7. Run with
//! `scripts/qemu-bench` (QEMU + the icount plugin); alone, it just runs.
//! One `measure(...)` line per measured function; the targets are the issue's.
//! Inputs are drawn before measuring (same generators as the bit-identity
//! vectors, `spidar_qemu::cases`).
#![no_std]
#![no_main]

use core::hint::black_box;
use spidar_core::tension::{distribute, distribute_warm, TensionConfig};
use spidar_core::STRINGS;
use spidar_qemu::bench::{measure, measure_overhead};
use spidar_qemu::cases::{central_position, cube_anchors, force, tension_limits, Rng};
use spidar_qemu::{exit, hprintln};

spidar_qemu::fault_handlers!();

/// Calls per benchmark (each with its own input).
const N: usize = 32;

#[cortex_m_rt::entry]
fn main() -> ! {
    if !spidar_qemu::fpu_enabled() {
        hprintln!("FAIL: FPU not enabled (CPACR)");
        exit(false);
    }
    measure_overhead();
    let mut rng = Rng::new(0x5EED);
    let anchors = cube_anchors();
    let positions: [[f32; 3]; N] = core::array::from_fn(|_| central_position(&mut rng));
    let small_forces: [[f32; 3]; N] = core::array::from_fn(|_| force(&mut rng, 3.0));
    let large_forces: [[f32; 3]; N] = core::array::from_fn(|_| force(&mut rng, 300.0));
    let cfg = TensionConfig::default();
    let lim = tension_limits();
    let at = |i: u32| i as usize % N;

    let mut body = [0u8; 256];
    rng.fill_bytes(&mut body);
    measure("blob CRC-32 (256 B, model upload check)", None, 4, |_| {
        spidar_protocol::blob::CRC32.checksum(black_box(&body))
    });

    measure("tension::distribute f32 (feasible, |F_i| <= 3 N)", None, N as u32, |i| {
        distribute(&anchors, positions[at(i)], small_forces[at(i)], lim, &cfg).tensions
    });
    measure("tension::distribute f32 (scaled, |F_i| <= 300 N)", None, N as u32, |i| {
        distribute(&anchors, positions[at(i)], large_forces[at(i)], lim, &cfg).tensions
    });
    // Control-loop use: warm start from the previous multiplier, 0.1 mm steps.
    let mut lambda = [0.0f32; 3];
    let mut p = positions[0];
    measure("tension::distribute_warm f32 (path, 30 N)", None, N as u32, |i| {
        p[(i % 3) as usize] += 0.1;
        let s = distribute_warm(&anchors, p, [10.0, -20.0, 30.0], lim, &cfg, lambda);
        lambda = s.multiplier;
        s.tensions
    });

    measure("guidance::guidance_force", None, N as u32, |i| {
        spidar_core::guidance::guidance_force(large_forces[at(i)], 150.0, 5.0)
    });

    let geometric: [f32; STRINGS] = core::array::from_fn(|_| rng.f32_in(300.0, 2500.0));
    let measured: [f32; STRINGS] = core::array::from_fn(|k| geometric[k] + rng.f32_in(-1.0, 1.0));
    let tensions: [f32; STRINGS] = core::array::from_fn(|_| rng.f32_in(-5.0, 25.0));
    let config = spidar_core::safety::SafetyConfig {
        t_min: 0.5,
        t_max: 20.0,
        f_max: 10.0,
        pretension_n: 1.0,
        heartbeat_timeout_ms: 100,
        slack_threshold_mm: 5.0,
    };
    let Ok(mut monitor) = spidar_core::safety::SafetyMonitor::new(config) else {
        hprintln!("FAIL: safety config rejected");
        exit(false)
    };
    monitor.heartbeat(0);
    measure("safety: check + limit_force + apply", None, N as u32, |i| {
        monitor.check(i, &measured, &geometric, true);
        let f = monitor.limit_force(small_forces[at(i)]);
        (f, monitor.apply(tensions))
    });

    hprintln!("BENCH_DONE");
    exit(true)
}
