//! Instruction-count benchmarks of spidar-core on the Cortex-M7. Run with
//! `scripts/qemu-bench` (QEMU + the icount plugin); alone, it just runs.
//! One `measure(...)` line per measured function; the targets are the issue's.
#![no_std]
#![no_main]

use core::hint::black_box;
use spidar_qemu::bench::{measure, measure_overhead};
use spidar_qemu::{exit, hprintln};

spidar_qemu::fault_handlers!();

#[cortex_m_rt::entry]
fn main() -> ! {
    if !spidar_qemu::fpu_enabled() {
        hprintln!("FAIL: FPU not enabled (CPACR)");
        exit(false);
    }
    measure_overhead();

    let mut body = [0u8; 256];
    spidar_qemu::cases::Rng::new(1).fill_bytes(&mut body);
    measure("blob CRC-32 (256 B)", None, 8, |_| {
        spidar_protocol::blob::CRC32.checksum(black_box(&body))
    });

    hprintln!("BENCH_DONE");
    exit(true)
}
