//! The float types of the device math and their square root.
//!
//! Kinematics and the tension solve are generic over [`Real`]: `f32` on the
//! device, `f64` on the host. Their square root is [`Real::sqrt_rounded`],
//! not `num_traits::Float::sqrt`, because in no_std the latter is
//! `libm::sqrtf` for `f32`, a software routine of ~45 cycles, where the
//! Cortex-M7 has a correctly rounded `VSQRT.F32` (`spidar_fpu::sqrtf`).
//! Both are correctly rounded, so the bits do not change (host and device
//! stay bit-identical: `scripts/qemu-test`).

use num_traits::Float;

/// A float the device math runs on.
pub trait Real: Float {
    /// `sqrt(self)`, correctly rounded.
    fn sqrt_rounded(self) -> Self;
}

impl Real for f32 {
    #[inline]
    fn sqrt_rounded(self) -> f32 {
        spidar_fpu::sqrtf(self)
    }
}

impl Real for f64 {
    #[inline]
    fn sqrt_rounded(self) -> f64 {
        libm::sqrt(self)
    }
}
