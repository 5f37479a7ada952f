//! The data cache, and the one region it must not cover.
//!
//! With the L1 data cache on, the control loop reads the model buffers (AXI
//! SRAM) and the lookup tables (`.rodata` in flash) without wait states once
//! they are cached: what the cycle estimates of docs/benchmarks.md ("Device
//! (Cortex-M7 under QEMU)") assume.
//! It is coherent because no DMA touches memory (USB runs in FIFO mode,
//! flash is programmed by the CPU); the only memory that changes behind the
//! cache's back is the flash of the model slots, erased and programmed by
//! the flash controller. An MPU region makes those two sectors normal,
//! non-cacheable memory, so every read of a slot (boot scan, commit
//! read-back) sees the flash as it is, and no write-through store ever goes
//! to cacheable memory (Arm erratum 1259864). Everything else keeps the
//! default memory map (PRIVDEFENA). DTCM and ITCM are never cached.

use cortex_m::peripheral::MPU;

/// Model slots A and B: sectors 6 and 7, 256 KiB from 0x080C_0000 (aligned
/// to its size, as an ARMv7-M MPU region must be). See memory.x.
const SLOTS_BASE: u32 = 0x080C_0000;
const SLOTS_SIZE_LOG2: u32 = 18;

/// RASR of a region of `2^size_log2` bytes: enabled, normal memory
/// non-cacheable (TEX 001, C 0, B 0), not shareable, read-write for all,
/// execute never.
const fn rasr_uncached(size_log2: u32) -> u32 {
    const XN: u32 = 1 << 28;
    const AP_RW: u32 = 0b011 << 24;
    const TEX_NORMAL_NONCACHEABLE: u32 = 0b001 << 19;
    XN | AP_RW | TEX_NORMAL_NONCACHEABLE | ((size_log2 - 1) << 1) | 1
}

const _: () = assert!(SLOTS_BASE % (1 << SLOTS_SIZE_LOG2) == 0);
const _: () = assert!(rasr_uncached(SLOTS_SIZE_LOG2) == 0x1308_0023);

/// MPU_CTRL: MPU on, the default memory map for everything outside the
/// regions (PRIVDEFENA), regions off in HardFault/NMI handlers.
const CTRL_ENABLE_PRIVDEFENA: u32 = 0b101;

/// Makes the model slots uncached (MPU region 0) and enables the MPU.
/// Call before the data cache is enabled.
pub fn model_slots_uncached(mpu: &mut MPU) {
    cortex_m::asm::dsb();
    // SAFETY: writes the MPU while no region is in use (the MPU is off
    // until CTRL); region 0 covers only the model slots, which nothing has
    // read yet, and the default map stays for all other memory.
    unsafe {
        mpu.ctrl.write(0);
        mpu.rnr.write(0);
        mpu.rbar.write(SLOTS_BASE);
        mpu.rasr.write(rasr_uncached(SLOTS_SIZE_LOG2));
        mpu.ctrl.write(CTRL_ENABLE_PRIVDEFENA);
    }
    cortex_m::asm::dsb();
    cortex_m::asm::isb();
}
