//! The integer arithmetic the compiled law runs on: saturating shifts, the
//! rounded 64 x 32 bit products (no 128-bit multiply, a library call on
//! Cortex-M), the Q47.16 / Q31.32 conversions and the quarter-wave sine
//! table. The same bits on every target.

/// `v * 2^k`, saturated to i64.
#[inline]
pub(super) fn shl_sat(v: i64, k: u32) -> i64 {
    if k == 0 {
        return v;
    }
    let lim = i64::MAX >> k;
    if v > lim {
        i64::MAX
    } else if v < -lim - 1 {
        i64::MIN
    } else {
        v << k
    }
}

#[inline]
fn clamp_i128(v: i128) -> i64 {
    if v > i128::from(i64::MAX) {
        i64::MAX
    } else if v < i128::from(i64::MIN) {
        i64::MIN
    } else {
        v as i64
    }
}

/// `round_half_up(a * b / 2^s)` saturated to i64, for `1 <= s <= 32`
/// (`s` outside is clamped into it). Two 32x32->64 multiplies, no 128-bit
/// multiply (which is a library call on Cortex-M).
#[inline]
pub(crate) fn mul_i32_shr(a: i64, b: i32, s: u32) -> i64 {
    let s = s.clamp(1, 32);
    let lo = (a as u64 & 0xFFFF_FFFF) as i64; // 0 ..= 2^32 - 1
    let hi = a >> 32; // i32 range
    let b = i64::from(b);
    // |lo * b| <= (2^32 - 1) 2^31 < 2^63 - 2^31: room for the rounding half.
    let low = (lo * b + (1i64 << (s - 1))) >> s;
    let high = hi * b; // |.| <= 2^62
    clamp_i128((i128::from(high) << (32 - s)) + i128::from(low))
}

/// `round_half_up(a * b / 2^s)` saturated to i64, for `1 <= s <= 32`.
#[inline]
pub(crate) fn mul_u32_shr(a: i64, b: u32, s: u32) -> i64 {
    let s = s.clamp(1, 32);
    let lo = a as u64 & 0xFFFF_FFFF;
    let hi = a >> 32;
    // lo * b <= (2^32 - 1)^2 = 2^64 - 2^33 + 1: room for the rounding half.
    let low = (lo * u64::from(b) + (1u64 << (s - 1))) >> s;
    let high = hi * i64::from(b); // |.| < 2^63
    clamp_i128((i128::from(high) << (32 - s)) + i128::from(low))
}

/// Q47.16 -> Q31.32, saturating.
#[inline]
pub(super) fn q16_to_q32(v: i64) -> i64 {
    shl_sat(v, 16)
}

/// Q31.32 -> Q47.16, rounding half up (never overflows).
#[inline]
pub(super) fn q32_to_q16(v: i64) -> i64 {
    (v >> 16) + ((v >> 15) & 1)
}

/// Segments of the sine table per quarter turn (power of two).
const SIN_SEGMENTS_LOG2: u32 = 9;
const SIN_SEGMENTS: usize = 1 << SIN_SEGMENTS_LOG2;
/// round(pi/2 * 2^62).
const HALF_PI_Q62: i128 = 7_244_019_458_077_122_842;

/// `sin(k pi / (2 SIN_SEGMENTS))` in Q1.30 for `k = 0..=SIN_SEGMENTS + 1`
/// (one entry past the quarter so that interpolation never reads out of
/// bounds), computed at compile time with an integer Taylor series in Q62:
/// the same bits on every target.
static SIN_TABLE_Q30: [i32; SIN_SEGMENTS + 2] = build_sin_table();

const fn build_sin_table() -> [i32; SIN_SEGMENTS + 2] {
    let mut table = [0i32; SIN_SEGMENTS + 2];
    let mut k = 0;
    while k < SIN_SEGMENTS + 2 {
        let x = HALF_PI_Q62 * (k as i128) / (SIN_SEGMENTS as i128); // Q62, <= 1.58
        let x2 = (x * x) >> 62;
        let mut term = x;
        let mut sum = x;
        let mut n: i128 = 1;
        while n < 16 {
            term = -((term * x2) >> 62) / ((2 * n) * (2 * n + 1));
            sum += term;
            n += 1;
        }
        table[k] = ((sum + (1i128 << 31)) >> 32) as i32;
        k += 1;
    }
    table
}

/// `sin(2 pi phase / 2^32)` in Q1.30, `phase` in Q0.32 turns. Linear
/// interpolation in a quarter-wave table: max error 1.2e-6 (measured in tests).
#[inline]
pub(crate) fn sin_q30(phase: u32) -> i32 {
    let quadrant = phase >> 30;
    let f = phase & 0x3FFF_FFFF; // Q0.30 of a quarter turn
    let g = if quadrant & 1 == 1 {
        (1u32 << 30) - f
    } else {
        f
    }; // 0..=2^30
    const FRAC_BITS: u32 = 30 - SIN_SEGMENTS_LOG2;
    let idx = (g >> FRAC_BITS) as usize; // 0..=SIN_SEGMENTS
    let frac = i64::from(g & ((1 << FRAC_BITS) - 1));
    let (y0, y1) = match (SIN_TABLE_Q30.get(idx), SIN_TABLE_Q30.get(idx + 1)) {
        (Some(&a), Some(&b)) => (i64::from(a), i64::from(b)),
        _ => (1 << 30, 1 << 30),
    };
    let y = y0 + (((y1 - y0) * frac + (1 << (FRAC_BITS - 1))) >> FRAC_BITS);
    let y = if quadrant >= 2 { -y } else { y };
    y as i32
}
