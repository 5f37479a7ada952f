//! Runtime glue shared by the Cortex-M7 binaries that run under
//! `qemu-system-arm -machine mps2-an500` with semihosting:
//!
//! - `bit_identity`: recomputes the test vectors of [`cases`] with
//!   `spidar-core` on the Cortex-M7 and compares them bit for bit with the
//!   outputs `build.rs` computed on the host with the same crate;
//! - `bench`: runs each measured function between the marker functions of
//!   [`bench`], whose executed instructions a small QEMU TCG plugin
//!   (`plugin/icount.c`, driven by `scripts/qemu-bench`) counts.
//!
//! The exit code of QEMU is the binary's verdict (semihosting `SYS_EXIT`):
//! 0 pass, 1 fail. A panic or a fault exits with failure, never hangs.
#![no_std]

pub mod bench;
pub mod cases;
pub mod fixtures;

pub use cortex_m_semihosting::{hprint, hprintln};

use core::panic::PanicInfo;
use cortex_m_semihosting::debug;

/// Ends the QEMU run: exit code 0 if `pass`, 1 otherwise.
pub fn exit(pass: bool) -> ! {
    debug::exit(if pass { debug::EXIT_SUCCESS } else { debug::EXIT_FAILURE });
    // Only reached without semihosting (e.g. on real hardware).
    loop {
        cortex_m::asm::bkpt();
    }
}

/// Checks that the FPU is on (cortex-m-rt enables it in `Reset` for the
/// `eabihf` targets): CPACR CP10/CP11 full access. A core that ran f32 code
/// with the FPU off would fault, not compute wrong bits; this makes the cause
/// explicit.
pub fn fpu_enabled() -> bool {
    // SAFETY: CPACR (0xE000_ED88) is an always-readable SCB register.
    let cpacr = unsafe { core::ptr::read_volatile(0xE000_ED88 as *const u32) };
    (cpacr >> 20) & 0xF == 0xF
}

#[panic_handler]
fn panic(info: &PanicInfo) -> ! {
    hprintln!("PANIC: {}", info);
    exit(false)
}

/// Defines the fault handlers of a binary: a HardFault prints the stacked
/// PC and exits with failure instead of hanging QEMU.
#[macro_export]
macro_rules! fault_handlers {
    () => {
        #[cortex_m_rt::exception]
        unsafe fn HardFault(frame: &cortex_m_rt::ExceptionFrame) -> ! {
            $crate::hprintln!("HARDFAULT at pc={:#010x}: {:?}", frame.pc(), frame);
            $crate::exit(false)
        }
    };
}
