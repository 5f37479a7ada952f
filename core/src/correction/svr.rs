//! The compiled RBF SVR, evaluated in place from its bytes, support vectors
//! in blocks.

use super::*;

/// The support-vector records of an [`SvrView`], as the evaluator reads them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum SvrRecords<'a> {
    /// The records start at a 4-byte aligned address (a version-2 blob in a
    /// 4-aligned buffer) on a little-endian target: viewed as words
    /// `[s0, s1, s2, coef0, coef1, coef2]`, read with word-pair loads.
    Words(&'a [[i32; 6]]),
    /// Any other placement: `support_vectors * SVR_RECORD_LEN` bytes, read
    /// with single (unaligned) word loads. Same results, bit for bit.
    Bytes(&'a [u8]),
}

impl<'a> SvrRecords<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        #[cfg(target_endian = "little")]
        if let Ok(words) = bytemuck::try_cast_slice::<u8, [i32; 6]>(bytes) {
            return SvrRecords::Words(words);
        }
        SvrRecords::Bytes(bytes)
    }

    fn len(&self) -> usize {
        match self {
            SvrRecords::Words(w) => w.len(),
            SvrRecords::Bytes(b) => b.len() / SVR_RECORD_LEN,
        }
    }
}

/// A compiled RBF SVR with three outputs sharing their support vectors, read
/// in place from its bytes (see [`SVR_HEADER_LEN`] for the layout). Positions
/// in and out are Q15.16 mm.
/// The checked, borrow-free part of an [`SvrView`] (see
/// [`SvrView::from_summary`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SvrSummary {
    mode: OutputMode,
    scale_frac: u8,
    coef_frac: [u8; 3],
    mean: [i32; 3],
    scale: [i32; 3],
    offset: [i32; 3],
    support_abs_max: [u32; 3],
    support_vectors: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SvrView<'a> {
    pub(super) mode: OutputMode,
    /// Fractional bits of the input scales (per mm).
    pub(super) scale_frac: u8,
    /// Fractional bits of the coefficients (mm), per axis.
    pub(super) coef_frac: [u8; 3],
    /// Input mean, Q15.16 mm.
    pub(super) mean: [i32; 3],
    /// `sqrt(gamma log2 e) / std_in`, Q(`scale_frac`) per mm.
    pub(super) scale: [i32; 3],
    /// `bias * std_out + mean_out`, Q15.16 mm.
    pub(super) offset: [i32; 3],
    /// Largest `|s_i|` over the support vectors, per axis (Q4.27, at most
    /// [`SUPPORT_MAX`]): bounds the kernel exponent of an input.
    pub(super) support_abs_max: [u32; 3],
    pub(super) records: SvrRecords<'a>,
}

impl<'a> SvrView<'a> {
    /// Checks and wraps a compiled SVR of `support_vectors` support vectors
    /// (the blob header's count): no more than [`MAX_SUPPORT_VECTORS`],
    /// exact length, mode, Q formats in range,
    /// support vectors within [`SUPPORT_MAX`], every axis' coefficients
    /// within [`SVR_BLOCK_ABS_SUM_MAX`] per block of [`SVR_BLOCK`].
    /// O(support_vectors), done once at load. The records are read as words
    /// when they start at a 4-byte aligned address (see `docs/fixed-point.md`),
    /// else as bytes; the results are the same.
    pub fn parse(bytes: &'a [u8], support_vectors: u32) -> Result<SvrView<'a>, BlobError> {
        if support_vectors > MAX_SUPPORT_VECTORS {
            return Err(BlobError::OverBudget {
                field: "svr.support_vectors",
                found: support_vectors,
                most: MAX_SUPPORT_VECTORS,
            });
        }
        let expected = (SVR_HEADER_LEN as u64)
            .saturating_add((SVR_RECORD_LEN as u64).saturating_mul(support_vectors as u64));
        if bytes.len() as u64 != expected {
            return Err(BlobError::Dimension {
                field: "svr.body_len",
                found: len_u32(bytes.len()),
                expected: u32::try_from(expected).unwrap_or(u32::MAX),
            });
        }
        let mode = mode_from_byte(bytes[0], "svr.mode")?;
        let scale_frac = bytes[1];
        if !INPUT_FRAC_RANGE.contains(&scale_frac) {
            return Err(BlobError::Body {
                field: "svr.scale_frac",
            });
        }
        let coef_frac = [bytes[2], bytes[3], bytes[4]];
        if coef_frac.iter().any(|f| !OUTPUT_FRAC_RANGE.contains(f)) {
            return Err(BlobError::Body {
                field: "svr.coef_frac",
            });
        }
        if bytes[5..8] != [0, 0, 0] {
            return Err(BlobError::Body {
                field: "svr.reserved",
            });
        }
        let mean = read3(bytes, 8, "svr.mean")?;
        let scale = read3(bytes, 20, "svr.scale")?;
        let offset = read3(bytes, 32, "svr.offset")?;
        let records = SvrRecords::new(&bytes[SVR_HEADER_LEN..]);
        let support_abs_max = match records {
            SvrRecords::Words(words) => check_svr_records(words.chunks(SVR_BLOCK), |r| *r),
            SvrRecords::Bytes(b) => check_svr_records(
                b.chunks(SVR_RECORD_LEN * SVR_BLOCK)
                    .map(|block| block.chunks_exact(SVR_RECORD_LEN)),
                |r| core::array::from_fn(|i| read_i32(r, 4 * i).unwrap_or(i32::MIN)),
            ),
        }?;
        Ok(SvrView {
            mode,
            scale_frac,
            coef_frac,
            mean,
            scale,
            offset,
            support_abs_max,
            records,
        })
    }

    /// Number of support vectors.
    pub fn support_vectors(&self) -> usize {
        self.records.len()
    }

    /// What [`parse`](Self::parse) established, without the borrow.
    pub fn summary(&self) -> SvrSummary {
        SvrSummary {
            mode: self.mode,
            scale_frac: self.scale_frac,
            coef_frac: self.coef_frac,
            mean: self.mean,
            scale: self.scale,
            offset: self.offset,
            support_abs_max: self.support_abs_max,
            support_vectors: self.records.len() as u32,
        }
    }

    /// The view again over the same bytes, in O(1): for a caller that parsed
    /// these bytes once and has not changed them since (the device keeps the
    /// active blob in RAM and rebuilds the view every control-loop tick;
    /// re-running [`parse`](Self::parse) would scan every support vector).
    /// Only the length is checked; different bytes give different (still
    /// saturated, never panicking) results, not an error.
    pub fn from_summary(summary: &SvrSummary, bytes: &'a [u8]) -> Result<SvrView<'a>, BlobError> {
        let expected = (SVR_HEADER_LEN as u64)
            .saturating_add((SVR_RECORD_LEN as u64).saturating_mul(summary.support_vectors as u64));
        if bytes.len() as u64 != expected {
            return Err(BlobError::Dimension {
                field: "svr.body_len",
                found: len_u32(bytes.len()),
                expected: u32::try_from(expected).unwrap_or(u32::MAX),
            });
        }
        Ok(SvrView {
            mode: summary.mode,
            scale_frac: summary.scale_frac,
            coef_frac: summary.coef_frac,
            mean: summary.mean,
            scale: summary.scale,
            offset: summary.offset,
            support_abs_max: summary.support_abs_max,
            records: SvrRecords::new(&bytes[SVR_HEADER_LEN..]),
        })
    }

    /// Output mode of the regressor.
    pub fn mode(&self) -> OutputMode {
        self.mode
    }

    /// Whether the records are read as aligned words (else as bytes; the
    /// results are the same, only the speed differs).
    pub fn reads_words(&self) -> bool {
        matches!(self.records, SvrRecords::Words(_))
    }

    /// Maps a Q15.16 mm position into the scaled space (Q4.27, saturated).
    #[inline(always)]
    pub(super) fn scaled(&self, p: [i32; 3]) -> [i32; 3] {
        // Q(16 + scale_frac) -> Q27.
        let sh = (self.scale_frac as u32).wrapping_sub(SVR_SPACE_FRAC - POSITION_FRAC as u32);
        let mut q = [0i32; 3];
        for i in 0..3 {
            let d = p[i] as i64 - self.mean[i] as i64; // |d| < 2^32
            q[i] = sat_i32(shr_i64(d * self.scale[i] as i64, sh)); // |d * scale| < 2^63
        }
        q
    }

    /// Whether every kernel exponent of the scaled input `q` is below `2^31`
    /// in Q10.22 (i.e. `|q - s|^2 < 512`): then [`exp2_neg_q22_below_2p31_with`]
    /// is exact. `|sat(q_i - s_i)| <= |q_i| + max_j |s_ji|`, and the sum of
    /// the three squares of these bounds is below `2^63` in Q54.
    #[inline(always)]
    pub(super) fn exponents_below_2p31(&self, q: [i32; 3]) -> bool {
        // |q_i| <= 2^31 and max |s_i| <= 2^30: the bound fits a u32.
        let d = |i: usize| (q[i].unsigned_abs() + self.support_abs_max[i]) as u64;
        (d(0) * d(0))
            .checked_add(d(1) * d(1))
            .and_then(|s| s.checked_add(d(2) * d(2)))
            .is_some_and(|s| s < 1 << 63)
    }

    /// Corrected position (Q15.16 mm) of a position `p` (Q15.16 mm). Integer
    /// only, saturating, never panics.
    pub fn evaluate(&self, p: [i32; 3]) -> [i32; 3] {
        let pass = SvrPass {
            q: self.scaled(p),
            base: core::hint::black_box(&EXP2_BASE),
            slope: core::hint::black_box(&EXP2_SLOPE),
        };
        let mut acc = [0i64; 3];
        match self.records {
            SvrRecords::Words(records) => {
                // Whole blocks, then the rest (a constant length per call).
                let blocks = records.chunks_exact(SVR_BLOCK);
                let rest = blocks.remainder();
                if self.exponents_below_2p31(pass.q) {
                    for block in blocks.chain(core::iter::once(rest)) {
                        svr_block_words::<true>(block, &pass.q, pass.base, pass.slope, &mut acc);
                    }
                } else {
                    for block in blocks.chain(core::iter::once(rest)) {
                        svr_block_words::<false>(block, &pass.q, pass.base, pass.slope, &mut acc);
                    }
                }
            }
            SvrRecords::Bytes(records) => {
                for block in records.chunks(SVR_RECORD_LEN * SVR_BLOCK) {
                    svr_block_bytes(block, &pass.q, pass.base, pass.slope, &mut acc);
                }
            }
        }
        [
            svr_finish(acc[0], self.coef_frac[0], self.offset[0], self.mode, p[0]),
            svr_finish(acc[1], self.coef_frac[1], self.offset[1], self.mode, p[1]),
            svr_finish(acc[2], self.coef_frac[2], self.offset[2], self.mode, p[2]),
        ]
    }
}

/// What every support vector of one SVR evaluation needs besides its record:
/// the scaled input and the exp2 tables (always [`EXP2_BASE`], [`EXP2_SLOPE`],
/// passed in so that LLVM keeps their addresses in registers or reloads them,
/// instead of rebuilding each from a `movw`/`movt` pair per use). One
/// pointer argument: the block functions take all their arguments in
/// registers.
struct SvrPass<'t> {
    q: [i32; 3],
    base: &'t [i32; EXP2_FRACTION_ENTRIES],
    slope: &'t [i32; EXP2_FRACTION_ENTRIES],
}

/// Adds a block's `i32` sums to the `i64` totals.
#[inline(always)]
fn add_block(total: &mut [i64; 3], block: [i32; 3]) {
    for a in 0..3 {
        total[a] = total[a].wrapping_add(block[a] as i64);
    }
}

/// The record checks of [`SvrView::parse`] over blocks of [`SVR_BLOCK`]
/// records (`record` reads one as `[s0, s1, s2, coef0, coef1, coef2]`):
/// `|s| <= SUPPORT_MAX`, per axis and block `sum |coef| <=
/// SVR_BLOCK_ABS_SUM_MAX`. Returns the largest `|s|` per axis.
fn check_svr_records<R, B, I>(
    blocks: B,
    record: impl Fn(R) -> [i32; 6],
) -> Result<[u32; 3], BlobError>
where
    B: Iterator<Item = I>,
    I: IntoIterator<Item = R>,
{
    let mut support_abs_max = [0u32; 3];
    for block in blocks {
        let mut sums = [0u64; 3];
        for rec in block {
            let rec = record(rec);
            for i in 0..3 {
                let s = rec[i].unsigned_abs();
                if s > SUPPORT_MAX as u32 {
                    return Err(BlobError::Body {
                        field: "svr.support",
                    });
                }
                support_abs_max[i] = support_abs_max[i].max(s);
                sums[i] += rec[3 + i].unsigned_abs() as u64;
            }
            if sums.iter().any(|&sum| sum > SVR_BLOCK_ABS_SUM_MAX) {
                return Err(BlobError::Body { field: "svr.coef" });
            }
        }
    }
    Ok(support_abs_max)
}

/// `acc + round(a b / 2^32)` (wrapping), one `smmlar` on the Cortex-M7.
#[inline(always)]
fn mul_hi_round_acc(acc: i32, a: i32, b: i32) -> i32 {
    ((((acc as i64) << 32)
        .wrapping_add(a as i64 * b as i64)
        .wrapping_add(1 << 31))
        >> 32) as i32
}

/// One block of at most [`SVR_BLOCK`] support vectors read as aligned words:
/// adds to `total[a]` the block's `sum_j round(coef_a K_j / 2^32)`, `K_j =
/// 2^-|q - s_j|^2` (Q1.30), in Q(`coef_frac_a` - 2) mm, summed in an `i32`.
/// One pass: q (3), three `i32` accumulators, the record pointer and count
/// and the two table addresses (one reloaded per support vector: 14
/// registers for 13). `NARROW`: the caller checked that every exponent is
/// below `2^31` (`SvrView::exponents_below_2p31`), so the saturated shift of
/// the kernel is one `usat`; the results are the same as without. Not
/// inlined, so that the register allocation of this loop does not depend on
/// the caller.
#[inline(never)]
fn svr_block_words<const NARROW: bool>(
    block: &[[i32; 6]],
    q: &[i32; 3],
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
    total: &mut [i64; 3],
) {
    let q = *q;
    let mut acc = [0i32; 3];
    // An index loop: LLVM counts down and steps the pointer in the first
    // load (2 instructions of loop control; an iterator compares pointers, 3).
    #[allow(clippy::needless_range_loop)]
    for i in 0..block.len() {
        // An empty barrier (no instruction: an empty `asm` with a memory
        // clobber): LLVM does not unroll a loop containing it. Unrolled (and
        // interleaved), this loop no longer fits the registers and spills.
        core::hint::black_box(());
        let [s0, s1, s2, c0, c1, c2] = block[i];
        acc = svr_term::<NARROW>([s0, s1, s2], [c0, c1, c2], q, acc, base, slope);
    }
    add_block(total, acc);
}

/// [`svr_block_words`] for records at any address (`block` holds whole
/// [`SVR_RECORD_LEN`]-byte records; a trailing partial record adds nothing),
/// read with single little-endian word loads. Always the general saturated
/// shift: the same results as the word path, bit for bit.
#[inline(never)]
fn svr_block_bytes(
    block: &[u8],
    q: &[i32; 3],
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
    total: &mut [i64; 3],
) {
    let q = *q;
    let mut acc = [0i32; 3];
    for rec in block.chunks_exact(SVR_RECORD_LEN) {
        core::hint::black_box(());
        let Ok(rec) = <&[u8; SVR_RECORD_LEN]>::try_from(rec) else {
            continue;
        };
        let s = [
            le_i32::<SVR_RECORD_LEN, 0>(rec),
            le_i32::<SVR_RECORD_LEN, 4>(rec),
            le_i32::<SVR_RECORD_LEN, 8>(rec),
        ];
        let c = [
            le_i32::<SVR_RECORD_LEN, 12>(rec),
            le_i32::<SVR_RECORD_LEN, 16>(rec),
            le_i32::<SVR_RECORD_LEN, 20>(rec),
        ];
        acc = svr_term::<false>(s, c, q, acc, base, slope);
    }
    add_block(total, acc);
}

/// Adds one support vector's terms (support vector `s`, coefficients `c`)
/// to the block accumulators. `NARROW`: see [`svr_block_words`].
#[inline(always)]
fn svr_term<const NARROW: bool>(
    s: [i32; 3],
    c: [i32; 3],
    q: [i32; 3],
    acc: [i32; 3],
    base: &[i32; EXP2_FRACTION_ENTRIES],
    slope: &[i32; EXP2_FRACTION_ENTRIES],
) -> [i32; 3] {
    let d0 = q[0].saturating_sub(s[0]) as i64;
    let d1 = q[1].saturating_sub(s[1]) as i64;
    let d2 = q[2].saturating_sub(s[2]) as i64;
    // Each square <= 2^62; the sum < 2^64 as an unsigned bit pattern. Its
    // high word is u in Q10.22 (truncated).
    let u = ((d0 * d0) as u64)
        .wrapping_add((d1 * d1) as u64)
        .wrapping_add((d2 * d2) as u64);
    let u = (u >> 32) as u32;
    // K = 0 from u >= 30 on (the saturated shift).
    let k = if NARROW {
        exp2_neg_q22_below_2p31_with(u, base, slope)
    } else {
        exp2_neg_q22_with(u, base, slope)
    };
    [
        mul_hi_round_acc(acc[0], c[0], k),
        mul_hi_round_acc(acc[1], c[1], k),
        mul_hi_round_acc(acc[2], c[2], k),
    ]
}

/// SVR output step: accumulator in Q(`frac` - 2) mm to Q15.16 (a rounding
/// right shift, or a saturating left shift for `frac < 18`), plus offset,
/// plus the input in residual mode, saturated.
#[inline(always)]
fn svr_finish(acc: i64, frac: u8, offset: i32, mode: OutputMode, p: i32) -> i32 {
    const ACC_FRAC_BELOW_COEF: u32 = 32 - ACTIVATION_FRAC as u32; // 2
    let acc_frac = frac as i32 - ACC_FRAC_BELOW_COEF as i32;
    let sh = acc_frac - POSITION_FRAC as i32; // -18..=30
    let y = if sh >= 0 {
        shr_round_i64(acc, sh as u32)
    } else {
        let l = sh.unsigned_abs();
        // |acc| < 2^47 (at most 2^26 blocks of 2^31): no overflow below 2^16.
        if acc.unsigned_abs() >> (62 - l) != 0 {
            if acc < 0 {
                i64::MIN
            } else {
                i64::MAX
            }
        } else {
            acc << l
        }
    };
    let base = match mode {
        OutputMode::Absolute => 0,
        OutputMode::Residual => p as i64,
    };
    sat_i32(y.saturating_add(offset as i64).saturating_add(base))
}
