//! Fixed-point helpers shared by the device evaluators: Q-format conversions,
//! saturating narrowing, little-endian reads from unaligned flash bytes, and
//! the two transcendental functions of the position corrections:
//!
//! - [`tanh_q27`]: `tanh` of a Q4.27 argument, Q1.30 result, by odd symmetry
//!   from a table of 512 cubic Hermite segments over `[0, 16)` (segment width
//!   1/32, derivative `1 - tanh^2` at both ends), evaluated in three
//!   `smmla`-style steps. Absolute error about 1e-9 (see the tests).
//! - [`exp2_neg_q22`]: `2^-u` of a Q10.22 exponent (`u32`), Q1.30 result:
//!   per segment of 2^11 Q22 steps (the 11 bits above the low 11), a line
//!   (intercept and slope from two tables, one `smlawb` with the low half
//!   word of `u`), then a right shift by the integer part (saturated at 31,
//!   the cutoff). Relative error below 1e-7 (the argument's Q22 resolution).
//!
//! The tables are computed by `const fn`s at compile time. Const evaluation is
//! done by the compiler with software IEEE arithmetic, so the host build and the
//! `thumbv7em-none-eabihf` build embed the very same table bits, and the
//! evaluators are integer-only at run time: host and device results are
//! bit-identical by construction.
//!
//! Notation: `Qm.n` is a two's complement integer with `n` fractional bits
//! (value = integer / 2^n) and `m` integer bits including the sign.

/// `ln 2`.
const LN2: f64 = core::f64::consts::LN_2;

/// Fractional bits of the argument of [`tanh_q27`] (Q4.27, range ±16).
pub const TANH_IN_FRAC: u32 = 27;
/// Fractional bits of the result of [`tanh_q27`] (Q1.30).
pub const TANH_OUT_FRAC: u32 = 30;
/// Segments per unit of the tanh table (segment width 1/32).
const TANH_SEG_PER_UNIT_LOG2: u32 = 5;
/// Segments of the tanh table: `[0, 16)` in steps of 1/32.
pub const TANH_SEGMENTS: usize = 512;

/// Fractional bits of the exponent `u` of [`exp2_neg_q22`] (Q10.22, `u32`).
pub const EXP2_IN_FRAC: u32 = 22;
/// Fractional bits of the result of [`exp2_neg_q22`] (Q1.30).
pub const EXP2_OUT_FRAC: u32 = 30;
/// Bits of `u` below the segment index of the exp2 tables: `u = n 2^22 + a
/// 2^11 + b`.
const EXP2_SPLIT_BITS: u32 = 11;
/// Segments (entries of each of the two tables) of [`exp2_neg_q22`]: every
/// `a` of `u = n 2^22 + a 2^11 + b` (`2^11`).
pub const EXP2_FRACTION_ENTRIES: usize = 1 << EXP2_SPLIT_BITS;
/// Largest right shift of [`exp2_neg_q22`]: the integer part `n = u >> 22` is
/// saturated to it. The fraction value is below `2^30`, so a shift by 31
/// (indeed by 30) gives 0: the cutoff.
pub const EXP2_MAX_SHIFT: u32 = 31;
/// Smallest exponent `u` (Q10.22) for which [`exp2_neg_q22`] returns 0 through
/// the saturated shift (`2^-31` is below half the resolution of Q1.30; the
/// product already underflows from `u = 30`).
pub const EXP2_CUTOFF_Q22: u32 = EXP2_MAX_SHIFT << EXP2_IN_FRAC;

// ---------------------------------------------------------------------------
// Const-evaluated elementary functions (compile time only).

/// Nearest integer, ties away from zero (const).
const fn round_i64(x: f64) -> i64 {
    if x >= 0.0 {
        (x + 0.5) as i64
    } else {
        (x - 0.5) as i64
    }
}

/// `e^x` for `x` in about `[-700, 700]` (const): `2^k e^r` with `|r| <= ln2/2`
/// and a 27-term Taylor series; relative error a few ulp.
const fn exp_const(x: f64) -> f64 {
    let kf = x / LN2;
    let k = round_i64(kf);
    let r = x - (k as f64) * LN2;
    let mut term = 1.0;
    let mut sum = 1.0;
    let mut i = 1;
    while i < 28 {
        term = term * r / (i as f64);
        sum += term;
        i += 1;
    }
    sum * f64::from_bits(((k + 1023) as u64) << 52)
}

/// `tanh x` for `x >= 0` (const).
const fn tanh_const(x: f64) -> f64 {
    let e = exp_const(-2.0 * x);
    (1.0 - e) / (1.0 + e)
}

/// The tanh table: per segment `[c0, c1, c2, c3]` of
/// `tanh(x0 + t/32) = c0 + t (c1 + t (c2 + t c3))`, `t in [0, 1)`, with
/// `c0` in Q1.30, `c1` in Q0.31, `c2` in Q32 and `c3` in Q33 (each Horner step
/// is one `(a * t_q31) >> 32`). Cubic Hermite: values and derivatives
/// `1 - tanh^2` match at both ends of the segment.
const fn tanh_table() -> [[i32; 4]; TANH_SEGMENTS] {
    let mut t = [[0i32; 4]; TANH_SEGMENTS];
    let h = 1.0 / (1u32 << TANH_SEG_PER_UNIT_LOG2) as f64;
    let mut i = 0;
    while i < TANH_SEGMENTS {
        let x0 = i as f64 * h;
        let y0 = tanh_const(x0);
        let y1 = tanh_const(x0 + h);
        let d0 = h * (1.0 - y0 * y0);
        let d1 = h * (1.0 - y1 * y1);
        let c0 = y0;
        let c1 = d0;
        let c2 = 3.0 * (y1 - y0) - 2.0 * d0 - d1;
        let c3 = 2.0 * (y0 - y1) + d0 + d1;
        t[i] = [
            round_i64(c0 * (1u64 << 30) as f64) as i32,
            round_i64(c1 * (1u64 << 31) as f64) as i32,
            round_i64(c2 * (1u64 << 32) as f64) as i32,
            round_i64(c3 * (1u64 << 33) as f64) as i32,
        ];
        i += 1;
    }
    t
}

/// The exp2 tables of [`exp2_neg_q22`], for `u = n 2^22 + a 2^11 + b` (Q10.22).
///
/// On segment `a` (`b` in `0..2048`), `f(b) = 2^30 2^-((a 2^11 + b + 1/2) /
/// 2^22)` (Q1.30; the exponent reaching the table is truncated to Q22, so
/// the value is taken at the centre of its bin: a zero-mean error instead
/// of a bias when hundreds of kernels add up) is replaced by its
/// least-squares line `alpha + beta b` (the segment spans a relative change
/// of 3.4e-4; the line's error is below 1e-8 relative, zero-mean). The
/// device evaluates the line as
///
/// `k = base[a] + ((slope[a] * s16(u)) >> 16)` (one `smlawb`)
///
/// where `s16(u)` is the low half word of `u` as an `i16`: `b + C_a` with
/// `C_a = 2^11 (a mod 32) - 2^16 [a mod 32 >= 16]`, a constant of the
/// segment, so no masking of `b` is needed: `slope = round(beta 2^16)` and
/// `base` absorbs `C_a` and the mean of the floor. The integer part `n` is a
/// right shift of `k` (no table). `k` is within `[2^29, 2^30)`.
pub struct Exp2Tables {
    pub base: [i32; EXP2_FRACTION_ENTRIES],
    pub slope: [i32; EXP2_FRACTION_ENTRIES],
}

const fn exp2_tables() -> Exp2Tables {
    let mut t = Exp2Tables {
        base: [0; EXP2_FRACTION_ENTRIES],
        slope: [0; EXP2_FRACTION_ENTRIES],
    };
    // Per Q22 step of b: f(x) = F e^(-c x), x = b + 1/2 over 0.5..N-0.5.
    let c = LN2 / (1u64 << EXP2_IN_FRAC) as f64;
    let n = EXP2_FRACTION_ENTRIES as f64;
    let m = n / 2.0; // mean of x
    let var = (n * n - 1.0) / 12.0; // variance of x
    let mut a = 0;
    while a < EXP2_FRACTION_ENTRIES {
        let f = exp_const(-((a << EXP2_SPLIT_BITS) as f64 / (1u64 << EXP2_IN_FRAC) as f64) * LN2)
            * (1u64 << EXP2_OUT_FRAC) as f64;
        // e^(-c x) = 1 - c x + c^2 x^2 / 2 - ... (c x < 3.4e-4; the cubic term
        // is below 1e-11). The least-squares line of x^2 over the x values is
        // 2 m x - m^2 + var, so that of f is F (1 + c^2 (var - m^2) / 2) +
        // F (c^2 m - c) x.
        let beta = f * (c * c * m - c);
        let alpha = f * (1.0 + c * c * (var - m * m) / 2.0) + beta * 0.5; // at b = 0
        let slope = round_i64(beta * 65536.0);
        let lo = (a & 31) as i64;
        let c_a = 2048 * lo - if lo >= 16 { 65536 } else { 0 };
        // floor(slope (b + C_a) / 2^16) is slope (b + C_a) / 2^16 - 1/2 on average.
        t.base[a] = round_i64(alpha - (slope * c_a) as f64 / 65536.0 + 0.5) as i32;
        t.slope[a] = slope as i32;
        a += 1;
    }
    t
}

/// Cubic Hermite segments of `tanh` over `[0, 16)`; see [`tanh_q27`].
pub static TANH_TABLE: [[i32; 4]; TANH_SEGMENTS] = tanh_table();

const EXP2_TABLES: Exp2Tables = exp2_tables();
/// Segment intercepts of `2^-u` ([`Exp2Tables`], [`exp2_neg_q22`]), 8 KiB.
/// Two separate statics, so that each is a base address of its own.
pub static EXP2_BASE: [i32; EXP2_FRACTION_ENTRIES] = EXP2_TABLES.base;
/// Segment slopes of `2^-u` (Q16 per Q22 step, negative), 8 KiB.
pub static EXP2_SLOPE: [i32; EXP2_FRACTION_ENTRIES] = EXP2_TABLES.slope;

// ---------------------------------------------------------------------------
// Run-time helpers (integer only).

/// High word of the signed 64-bit product: `(a * b) >> 32` (floor), one
/// `smmul` on Cortex-M7.
#[inline(always)]
pub fn mul_hi(a: i32, b: i32) -> i32 {
    ((a as i64 * b as i64) >> 32) as i32
}

/// Saturates an `i64` to the `i32` range.
#[inline(always)]
pub fn sat_i32(v: i64) -> i32 {
    if v > i32::MAX as i64 {
        i32::MAX
    } else if v < i32::MIN as i64 {
        i32::MIN
    } else {
        v as i32
    }
}

/// Arithmetic right shift of an `i64` by `sh` (taken modulo 64), flooring.
#[inline(always)]
pub fn shr_i64(v: i64, sh: u32) -> i64 {
    v >> (sh & 63)
}

/// Arithmetic right shift of an `i64` by `sh` (modulo 64), rounding half up.
#[inline(always)]
pub fn shr_round_i64(v: i64, sh: u32) -> i64 {
    let sh = sh & 63;
    if sh == 0 {
        v
    } else {
        (v >> (sh - 1)).wrapping_add(1) >> 1
    }
}

/// `v >> sh` saturated to `i32`, for `sh` in `1..=31` (taken modulo 32; 0 is
/// not meaningful). A handful of 32-bit instructions instead of a generic
/// 64-bit variable shift: `(lo >> sh) | (hi << (32 - sh))`, then a sign check.
#[inline(always)]
pub fn shr_sat_i64_to_i32(v: i64, sh: u32) -> i32 {
    let sh = sh & 31;
    let lo = v as u32;
    let hi = (v >> 32) as i32;
    let x_lo = (lo >> sh) | ((hi as u32) << (32u32.wrapping_sub(sh) & 31));
    let x_hi = hi >> sh;
    if x_hi == (x_lo as i32) >> 31 {
        x_lo as i32
    } else if hi < 0 {
        i32::MIN
    } else {
        i32::MAX
    }
}

/// Reads a little-endian `i32` at byte offset `AT` of a fixed-size record.
/// The record may sit at any address (flash blobs are not aligned); on the
/// Cortex-M7 this is one unaligned `ldr`.
#[inline(always)]
pub fn le_i32<const N: usize, const AT: usize>(rec: &[u8; N]) -> i32 {
    i32::from_le_bytes([rec[AT], rec[AT + 1], rec[AT + 2], rec[AT + 3]])
}

/// Reads a little-endian `i32` at `at` of a slice, `None` past its end.
#[inline]
pub fn read_i32(bytes: &[u8], at: usize) -> Option<i32> {
    let end = at.checked_add(4)?;
    let b = bytes.get(at..end)?;
    Some(i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// Converts a value to a Q format with `frac` fractional bits, rounding to
/// nearest; `None` if it is not finite or does not fit an `i32`.
pub fn to_q_i32(v: f64, frac: u32) -> Option<i32> {
    if !v.is_finite() || frac > 62 {
        return None;
    }
    let s = v * (1u64 << frac) as f64;
    let r = libm::round(s);
    if (-2_147_483_648.0..2_147_483_648.0).contains(&r) {
        Some(r as i32)
    } else {
        None
    }
}

/// Converts a Q15.16 position (mm) to f64 mm.
#[inline]
pub fn q16_to_mm(v: i32) -> f64 {
    v as f64 / 65536.0
}

/// Converts f64 mm to a Q15.16 position, rounding and saturating (NaN gives 0).
pub fn mm_to_q16(mm: f64) -> i32 {
    if mm.is_nan() {
        return 0;
    }
    let r = libm::round(mm * 65536.0);
    if r >= i32::MAX as f64 {
        i32::MAX
    } else if r <= i32::MIN as f64 {
        i32::MIN
    } else {
        r as i32
    }
}

/// `tanh` in fixed point: Q4.27 argument (range ±16), Q1.30 result.
///
/// Odd symmetry; `|x|` selects one of 512 cubic Hermite segments of width
/// 1/32 over `[0, 16)`; the 22 bits below the index are the position `t` in
/// the segment, used as Q0.31. Beyond 16 (only `i32::MIN`) the result is the
/// last segment's end, `tanh(16)`, which is 1 in Q1.30. Integer only, never
/// panics, `|result| <= 2^30`.
#[inline(always)]
pub fn tanh_q27(x: i32) -> i32 {
    let ax = x.unsigned_abs().min(i32::MAX as u32);
    let idx = (ax >> (TANH_IN_FRAC - TANH_SEG_PER_UNIT_LOG2)) as usize;
    let frac_bits = TANH_IN_FRAC - TANH_SEG_PER_UNIT_LOG2; // 22
    let t = ((ax & ((1 << frac_bits) - 1)) << (31 - frac_bits)) as i32; // Q0.31
    let c = &TANH_TABLE[idx & (TANH_SEGMENTS - 1)];
    let a = c[2].wrapping_add(mul_hi(c[3], t)); // Q32
    let a = c[1].wrapping_add(mul_hi(a, t)); // Q31
    let y = c[0].wrapping_add(mul_hi(a, t)); // Q30
    if x < 0 {
        y.wrapping_neg()
    } else {
        y
    }
}

/// `2^-u` in fixed point: `u` in Q10.22 (`u32`, `u >= 0`), result Q1.30
/// (`< 2^30`). Returns 0 for `u >= 30` (and so at and beyond
/// [`EXP2_CUTOFF_Q22`]).
///
/// `u = n 2^22 + a 2^11 + b`:
/// `2^-u = (base[a] + ((slope[a] s16(u)) >> 16)) >> min(n, 31)`
/// (see [`Exp2Tables`]): one 32x16 multiply-accumulate
/// (`smlawb`), then the integer part as a right shift, saturated at
/// [`EXP2_MAX_SHIFT`] (a shift by 30 or 31 gives 0). Never panics. Relative
/// error below 1e-7 within the first octave (the Q22 truncation of the
/// argument, centred), absolute error below 2^-30 beyond.
#[inline(always)]
pub fn exp2_neg_q22(u: u32) -> i32 {
    exp2_neg_q22_with(u, &EXP2_BASE, &EXP2_SLOPE)
}

/// [`exp2_neg_q22`] with the tables passed in (always [`EXP2_BASE`],
/// [`EXP2_SLOPE`]): in a loop the caller holds their addresses in registers
/// (or reloads them) instead of rebuilding each with two instructions per
/// use.
#[inline(always)]
pub fn exp2_neg_q22_with(
    u: u32,
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
) -> i32 {
    exp2_fraction(u, base, slope) >> (u >> EXP2_IN_FRAC).min(EXP2_MAX_SHIFT)
}

/// [`exp2_neg_q22_with`] for an exponent below `2^31` (`u as i32 >= 0`, i.e.
/// `u < 512`): the saturated shift is then one `usat` (`(u as i32 >> 22)`
/// clamped to `0..=31`). For `u >= 2^31` the result is wrong (the signed
/// view is negative, the shift 0): the caller must guarantee the bound; for
/// `u < 2^31` the result equals [`exp2_neg_q22_with`] bit for bit.
#[inline(always)]
pub fn exp2_neg_q22_below_2p31_with(
    u: u32,
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
) -> i32 {
    let sh = ((u as i32) >> EXP2_IN_FRAC).clamp(0, EXP2_MAX_SHIFT as i32) as u32;
    exp2_fraction(u, base, slope) >> sh
}

/// The segment line of the fraction bits of `u`: `2^-(u mod 2^22)` in Q1.30,
/// within `[2^29, 2^30)`.
#[inline(always)]
fn exp2_fraction(
    u: u32,
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
) -> i32 {
    let a = (u >> EXP2_SPLIT_BITS) as usize & (EXP2_FRACTION_ENTRIES - 1);
    // |slope| < 2^24 and |s16| <= 2^15: the product fits 40 bits, the
    // shifted term 24 (one `smlawb`).
    let s16 = u as u16 as i16 as i64;
    base[a].wrapping_add(((slope[a] as i64 * s16) >> 16) as i32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn const_exp_matches_libm() {
        for i in 0..2000 {
            let x = -40.0 + i as f64 * 0.0213;
            let a = exp_const(x);
            let b = libm::exp(x);
            assert!(((a - b) / b).abs() < 1e-14, "x {x}: {a} vs {b}");
        }
    }

    #[test]
    fn tanh_q27_accuracy() {
        let mut max_err = 0f64;
        // Dense sweep of the argument range, both signs.
        let mut x: i64 = -(1i64 << 31) + 1;
        while x < (1i64 << 31) {
            let xi = x as i32;
            let got = tanh_q27(xi) as f64 / (1u64 << 30) as f64;
            let want = libm::tanh(xi as f64 / (1u64 << 27) as f64);
            max_err = max_err.max((got - want).abs());
            x += 9_973; // prime step: covers every segment at many positions
        }
        eprintln!("tanh: max abs error {max_err:e}");
        assert!(max_err < 1.5e-8, "tanh max error {max_err}");
        assert_eq!(tanh_q27(0), 0);
        assert_eq!(tanh_q27(i32::MAX), 1 << 30);
        assert_eq!(tanh_q27(i32::MIN), -(1 << 30));
        for x in [1, 12345, 1 << 27, 5 << 26, i32::MAX] {
            assert_eq!(tanh_q27(-x), -tanh_q27(x));
        }
    }

    #[test]
    fn exp2_accuracy() {
        let mut max_rel = 0f64;
        let mut max_abs = 0f64;
        let mut sum_rel = 0f64;
        let mut count = 0;
        let mut u: u64 = 0;
        while u < (31u64 << 22) {
            let got = exp2_neg_q22(u as u32) as f64 / (1u64 << 30) as f64;
            // The input stands for the Q22 bin [u, u+1): compare at its centre.
            let want = libm::exp2(-((u as f64 + 0.5) / (1u64 << 22) as f64));
            let abs = (got - want).abs();
            max_abs = max_abs.max(abs);
            // Relative error of the first octave (the table itself); below it
            // the right shift adds an absolute error under 2^-30.
            if want > 0.5 {
                let rel = (got - want) / want;
                max_rel = max_rel.max(rel.abs());
                sum_rel += rel;
                count += 1;
            }
            u += 1_237;
        }
        eprintln!("exp2: max rel {max_rel:e}, max abs {max_abs:e}");
        assert!(max_rel < 1.3e-7, "exp2 max relative error {max_rel}");
        assert!(max_abs < 1.3e-7, "exp2 max absolute error {max_abs}");
        assert!(
            (sum_rel / count as f64).abs() < 5e-9,
            "exp2 bias {}",
            sum_rel / count as f64
        );
        assert_eq!(exp2_neg_q22(30 << 22), 0);
        assert_eq!(exp2_neg_q22(EXP2_CUTOFF_Q22), 0);
        assert_eq!(exp2_neg_q22(u32::MAX), 0);
        assert!(exp2_neg_q22(0) <= 1 << 30);
    }

    #[test]
    fn exp2_segments_and_narrow_shift() {
        // Every segment line stays within [2^29, 2^30) over its 2^11 steps
        // (the bound the SVR's block sums rely on), for every low half word.
        for a in 0..EXP2_FRACTION_ENTRIES as u32 {
            for b in [0u32, 1, 1023, 1024, 2046, 2047] {
                let k = exp2_neg_q22((a << 11) | b);
                assert!((1 << 29..1 << 30).contains(&k), "a {a} b {b}: {k}");
            }
        }
        // The `usat` form equals the general one below 2^31; the general one
        // is 0 from 30 on, whatever the fraction bits.
        let mut u: u64 = 0;
        while u < 1 << 31 {
            let v = u as u32;
            assert_eq!(
                exp2_neg_q22_below_2p31_with(v, &EXP2_BASE, &EXP2_SLOPE),
                exp2_neg_q22(v),
                "u {v:#x}"
            );
            u += 65_521;
        }
        for n in 30..1024u32 {
            assert_eq!(exp2_neg_q22((n << 22) | 0x3f_ffff), 0);
            assert_eq!(exp2_neg_q22(n << 22), 0);
        }
        // Monotone non-increasing over the first octave (sampled).
        let mut prev = i32::MAX;
        for u in (0..1u32 << 22).step_by(97) {
            let k = exp2_neg_q22(u);
            assert!(k <= prev, "u {u}");
            prev = k;
        }
    }

    #[test]
    fn q_helpers() {
        assert_eq!(sat_i32(1 << 40), i32::MAX);
        assert_eq!(sat_i32(-(1 << 40)), i32::MIN);
        assert_eq!(shr_round_i64(5, 1), 3);
        for v in [
            0i64,
            1,
            -1,
            12345678901,
            -98765432109,
            i64::MAX,
            i64::MIN,
            1 << 40,
        ] {
            for sh in 1..32 {
                assert_eq!(shr_sat_i64_to_i32(v, sh), sat_i32(v >> sh), "{v} >> {sh}");
            }
        }
        assert_eq!(shr_round_i64(-5, 1), -2);
        assert_eq!(to_q_i32(1.5, 16), Some(98_304));
        assert_eq!(to_q_i32(40_000.0, 16), None);
        assert_eq!(to_q_i32(f64::NAN, 16), None);
        assert_eq!(mm_to_q16(1e12), i32::MAX);
        assert_eq!(read_i32(&[1, 0, 0, 0, 9], 0), Some(1));
        assert_eq!(read_i32(&[1, 0, 0, 0, 9], 2), None);
        assert_eq!(read_i32(&[1, 0, 0, 0], usize::MAX), None);
    }
}
