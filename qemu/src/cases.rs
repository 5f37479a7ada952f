//! Test vectors of the bit-identity test, shared by `build.rs` (compiled for
//! the host, where it computes the expected outputs) and the `bit_identity`
//! binary (compiled for the Cortex-M7, where it recomputes and compares them).
//! Both sides include this very file and link the same `spidar-core`.
//!
//! A [`Case`] draws its inputs from a deterministic [`Rng`] seeded by (case,
//! vector) and writes every output word to an [`Out`]: floats as their IEEE
//! bits, integers as they are. To cover a new function, write one `fn` and add
//! one line to [`CASES`].
//!
//! Keep this file `no_std`-clean: only `core`, `spidar_core` and
//! `spidar_protocol`.

#![allow(dead_code)]

/// xorshift64* (Vigna): tiny, deterministic, same sequence on every target.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        // Never the all-zero state; mix the seed a little (splitmix64 step).
        let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        Rng(if z == 0 { 1 } else { z })
    }

    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    pub fn next_u32(&mut self) -> u32 {
        (self.next_u64() >> 32) as u32
    }

    /// Uniform in `[lo, hi]` (inclusive), integer arithmetic only.
    pub fn i32_in(&mut self, lo: i32, hi: i32) -> i32 {
        let span = (hi as i64 - lo as i64 + 1) as u64;
        (lo as i64 + (self.next_u64() % span) as i64) as i32
    }

    /// Uniform in `[lo, hi)`. Built from 24 random bits with exact f32
    /// operations (power-of-two scaling, then one `*` and one `+`), so host
    /// and device draw the same bits.
    pub fn f32_in(&mut self, lo: f32, hi: f32) -> f32 {
        let unit = (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0);
        lo + (hi - lo) * unit
    }

    /// Uniform in `[lo, hi)` in f64 (53 random bits).
    pub fn f64_in(&mut self, lo: f64, hi: f64) -> f64 {
        let unit = (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0);
        lo + (hi - lo) * unit
    }

    pub fn fill_bytes(&mut self, out: &mut [u8]) {
        for chunk in out.chunks_mut(8) {
            let w = self.next_u64().to_le_bytes();
            chunk.copy_from_slice(&w[..chunk.len()]);
        }
    }
}

/// Where a case writes its outputs. One word per scalar: floats as their
/// IEEE bits ([`f32::to_bits`], [`f64::to_bits`]), integers sign-extended.
pub trait Out {
    fn word(&mut self, w: u64);

    fn u32(&mut self, v: u32) {
        self.word(v as u64)
    }
    fn i32(&mut self, v: i32) {
        self.word(v as i64 as u64)
    }
    fn i64(&mut self, v: i64) {
        self.word(v as u64)
    }
    fn f32(&mut self, v: f32) {
        self.word(v.to_bits() as u64)
    }
    fn f64(&mut self, v: f64) {
        self.word(v.to_bits())
    }
    fn f32s(&mut self, v: &[f32]) {
        for &x in v {
            self.f32(x)
        }
    }
    fn i32s(&mut self, v: &[i32]) {
        for &x in v {
            self.i32(x)
        }
    }
    fn i64s(&mut self, v: &[i64]) {
        for &x in v {
            self.i64(x)
        }
    }
}

/// Data the cases need besides random inputs: compiled model blobs, made by
/// `build.rs` on the host and embedded in the device binary (empty until the
/// core can compile them).
#[derive(Clone, Copy, Debug)]
pub struct Fixtures<'a> {
    /// Compiled calibration blob with an NN 3-20-3 correction.
    pub nn_blob: &'a [u8],
    /// Compiled calibration blob with an SVR correction of 1,000 support vectors.
    pub svr_blob: &'a [u8],
}

/// One function under test.
pub struct Case {
    /// Printed on a mismatch; unique.
    pub name: &'static str,
    /// Number of vectors (each with its own seeded [`Rng`]).
    pub vectors: u32,
    /// Draws one vector's inputs from the rng, evaluates, writes the outputs.
    pub run: fn(&Fixtures, &mut Rng, &mut dyn Out),
}

/// The seed of vector `vector` of case `case`.
pub fn rng_for(case: &Case, vector: u32) -> Rng {
    // FNV-1a of the name, so adding or reordering cases keeps other vectors.
    let mut h: u64 = 0xCBF2_9CE4_8422_2325;
    for b in case.name.bytes() {
        h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01B3);
    }
    Rng::new(h ^ ((vector as u64) << 32))
}

/// Every case of the bit-identity test. One line per function under test.
pub const CASES: &[Case] = &[
    Case {
        name: "protocol::blob::CRC32",
        vectors: 16,
        run: blob_crc32,
    },
    Case {
        name: "rng::f32_in",
        vectors: 4,
        run: rng_f32,
    },
];

// ---------------------------------------------------------------------------
// The cases.

/// CRC-32 of blob bodies (checked by the device at load): random lengths
/// 0..=300, random bytes.
fn blob_crc32(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    let mut buf = [0u8; 300];
    let len = rng.i32_in(0, buf.len() as i32) as usize;
    rng.fill_bytes(&mut buf[..len]);
    out.u32(len as u32);
    out.u32(spidar_protocol::blob::CRC32.checksum(&buf[..len]));
}

/// The input generator itself (f32 path): guards the other cases' inputs.
fn rng_f32(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    for _ in 0..8 {
        out.f32(rng.f32_in(-1500.0, 1500.0));
    }
    out.f64(rng.f64_in(-1.0, 1.0));
}
