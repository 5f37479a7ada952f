//! Instruction-count benchmarks: marker functions and the measuring loop.
//!
//! `scripts/qemu-bench` runs the `bench` binary under QEMU with the TCG plugin
//! `plugin/icount.c`, giving it the addresses of the three marker functions
//! below (read from the ELF symbol table). The plugin counts every executed
//! guest instruction; between the entry of [`spidar_bench_start`] and the
//! entry of [`spidar_bench_stop`] it accumulates one call's count, and on
//! [`spidar_bench_report`] it prints `ICOUNT calls min max sum` for the calls
//! since the previous report. The guest prints the matching `BENCH` line
//! (name, target, calls) just before, so the script pairs them in order.
//!
//! The count of one call includes a constant marker overhead (the marker's own
//! instructions and the call into it); [`measure_overhead`] measures it with
//! an empty body and the script subtracts it.

use core::hint::black_box;

/// Start of one measured call. Never inlined, distinct body (the markers must
/// keep distinct addresses: no function merging).
#[inline(never)]
#[no_mangle]
pub extern "C" fn spidar_bench_start() {
    // SAFETY: a no-op instruction; not `pure`, so the call is never removed.
    unsafe { core::arch::asm!("nop", options(nostack, preserves_flags)) }
}

/// End of one measured call.
#[inline(never)]
#[no_mangle]
pub extern "C" fn spidar_bench_stop() {
    // SAFETY: as above.
    unsafe { core::arch::asm!("nop", "nop", options(nostack, preserves_flags)) }
}

/// End of one benchmark: the plugin prints the statistics of its calls.
#[inline(never)]
#[no_mangle]
pub extern "C" fn spidar_bench_report() {
    // SAFETY: as above.
    unsafe { core::arch::asm!("nop", "nop", "nop", options(nostack, preserves_flags)) }
}

/// Measures `calls` calls of `f(i)`, `i = 0..calls`, each between the start
/// and stop markers. `target` is the most instructions per call the issue
/// allows (`None`: informative). The argument and the result pass through
/// [`black_box`] inside the markers, so the call can be neither hoisted out
/// of them nor removed. Never inlined: each benchmark's loop is its own
/// function with its own small frame, so the marker overhead is the same in
/// every one (inlined into `main`, whose frame grew past the reach of an
/// immediate offset, the empty body's loop addressed its `black_box` slots
/// with two more instructions each than the 100 `nop`s' and the self-check
/// counted 96).
#[inline(never)]
pub fn measure<O>(name: &str, target: Option<u32>, calls: u32, mut f: impl FnMut(u32) -> O) {
    crate::hprintln!("BENCH\t{}\t{}\t{}", name, target.unwrap_or(0), calls);
    for i in 0..calls {
        let i = black_box(i);
        spidar_bench_start();
        let out = f(black_box(i));
        black_box(out);
        spidar_bench_stop();
    }
    spidar_bench_report();
}

/// The marker overhead: an empty measured body. Must be the first benchmark.
/// Then a self-check the script verifies: a body of exactly 100 `nop`s must
/// count 100 instructions once the overhead is subtracted.
pub fn measure_overhead() {
    measure("(marker overhead)", None, 16, |_| ());
    measure("(self-check: 100 nops)", None, 4, |_| {
        // SAFETY: no-ops.
        unsafe { core::arch::asm!(".rept 100", "nop", ".endr", options(nomem, nostack, preserves_flags)) }
    });
}
