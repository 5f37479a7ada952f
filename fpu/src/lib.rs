//! A correctly rounded `f32` square root, in hardware where the target has
//! a floating-point unit that `core` cannot reach.
//!
//! `core` has no `f32::sqrt` (it is `std`'s, and `core`'s is unstable), so
//! no_std code calls `libm::sqrtf`: an integer digit-by-digit routine of
//! ~45 cycles on a Cortex-M7, called ~40 times per control-loop tick by
//! forward kinematics and the tension solve. The Cortex-M7's FPU computes
//! the same correctly rounded result with one `VSQRT.F32` (14 cycles,
//! pipelined behind other work). This crate is that one instruction, kept
//! apart so that `spidar-core` stays `forbid(unsafe_code)`.
//!
//! IEEE 754 requires `sqrt` to be correctly rounded: `VSQRT.F32`,
//! `libm::sqrtf` and x86's `SQRTSS` return the same bits for every input
//! (NaN payloads aside), so host and device keep computing bit-identical
//! positions and tensions (the QEMU bit-identity test checks it).

#![no_std]

/// `sqrt(x)` for `f32`, correctly rounded (round to nearest even); NaN for
/// negative `x`, `-0.0` for `-0.0`.
#[inline]
pub fn sqrtf(x: f32) -> f32 {
    #[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
    {
        vsqrt(x)
    }
    #[cfg(not(all(target_arch = "arm", target_abi = "eabihf")))]
    {
        libm::sqrtf(x)
    }
}

// `VSQRT.F32` as a leaf function of the hard-float calling convention
// (argument and result in `s0`). Not inline `asm!`: its `sreg` operands need
// the `vfp2` target feature, which is unstable to name
// (rust-lang/rust#150246) although every `eabihf` target has it, and the C
// ABI's clobber list names D16-D31, which a single-precision FPU lacks.
#[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
core::arch::global_asm!(
    ".section .text.spidar_fpu_vsqrt,\"ax\",%progbits",
    ".global spidar_fpu_vsqrt",
    ".type spidar_fpu_vsqrt,%function",
    // The module assembler does not see the target's FPU: name the one
    // every thumbv7em `eabihf` part has (Cortex-M4F; the M7's is a superset).
    ".fpu fpv4-sp-d16",
    ".thumb_func",
    "spidar_fpu_vsqrt:",
    "vsqrt.f32 s0, s0",
    "bx lr",
    ".size spidar_fpu_vsqrt, . - spidar_fpu_vsqrt",
);

#[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
extern "C" {
    fn spidar_fpu_vsqrt(x: f32) -> f32;
}

#[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
#[inline]
fn vsqrt(x: f32) -> f32 {
    // SAFETY: `spidar_fpu_vsqrt` above follows the AAPCS-VFP convention
    // `extern "C"` means on an `eabihf` target (f32 in and out through
    // `s0`, only caller-saved registers touched); it reads no memory and
    // every `eabihf` target has an FPU with VSQRT.F32 (VFPv2 and later; the
    // Cortex-M7's FPv5).
    unsafe { spidar_fpu_vsqrt(x) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn correctly_rounded_and_ieee_special_values() {
        for x in [
            0.0f32,
            1.0,
            2.0,
            0.5,
            1e-38,
            1e38,
            123456.78,
            f32::MAX,
            f32::MIN_POSITIVE,
        ] {
            assert_eq!(sqrtf(x).to_bits(), libm::sqrtf(x).to_bits(), "{x}");
            let r = sqrtf(x) as f64;
            assert!((r * r - x as f64).abs() <= (x as f64) * 2.0 * f32::EPSILON as f64);
        }
        assert_eq!(sqrtf(-0.0).to_bits(), (-0.0f32).to_bits());
        assert!(sqrtf(-1.0).is_nan());
        assert_eq!(sqrtf(f32::INFINITY), f32::INFINITY);
        assert!(sqrtf(f32::NAN).is_nan());
    }
}
