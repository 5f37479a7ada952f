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
    /// FNV-1a 64 of the `Debug` text: covers every field of a result struct
    /// or enum (f32 `Debug` prints the shortest round-trip decimal, so equal
    /// bits give equal text) without naming its fields here.
    fn debug(&mut self, v: &dyn core::fmt::Debug) {
        struct Fnv(u64);
        impl core::fmt::Write for Fnv {
            fn write_str(&mut self, s: &str) -> core::fmt::Result {
                for b in s.bytes() {
                    self.0 = (self.0 ^ b as u64).wrapping_mul(0x0000_0100_0000_01B3);
                }
                Ok(())
            }
        }
        let mut h = Fnv(0xCBF2_9CE4_8422_2325);
        let _ = core::fmt::write(&mut h, format_args!("{v:?}"));
        self.word(h.0)
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
    /// The same SVR blob at an address 1 mod 4: its records are read as
    /// bytes (the fallback path), `svr_blob`'s as aligned words.
    pub svr_blob_odd: &'a [u8],
    /// N = 4: a 4-line cable robot in space ([`FOUR_LINE_ANCHORS`] on
    /// channels 0..4), NN 3-20-3.
    pub four_blob: &'a [u8],
    /// N = 4, planar: [`PLANAR_ANCHORS`] on the channels of
    /// [`PLANAR_ACTIVE`], NN 3-20-3.
    pub planar_blob: &'a [u8],
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
    case("protocol::blob::CRC32", 16, blob_crc32),
    case("rng::f32_in", 4, rng_f32),
    case("tension::distribute (feasible)", 48, tension_feasible),
    case("tension::distribute (scaled)", 48, tension_scaled),
    case("tension::distribute_warm", 24, tension_warm),
    case("guidance", 48, guidance),
    case("safety::SafetyMonitor", 32, safety),
    case("blob::CompiledCalibration::from_blob", 1, blob_parse),
    case("blob::position_q16/position_mm", 32, positions),
    case("fixed::tanh_q27/exp2_neg_q22", 64, fixed_functions),
    case("encoder::EncoderExtender/DirectionTracker", 16, encoder),
    case("string_law::string_lengths", 48, string_lengths),
    case("kinematics::inverse_kinematics::<f32>", 32, inverse_kinematics),
    case("kinematics::forward_kinematics::<f32> (warm)", 48, fk_warm),
    case("kinematics::forward_kinematics::<f32> (cold, faulty string)", 24, fk_faulty),
    case("kinematics::forward_kinematics::<f32> (5 strings, one 40-120 mm off)", 32, fk_two_spares),
    case("correction::NnView::evaluate (3-20-3)", 48, nn_evaluate),
    case("correction::SvrView::evaluate (1000 SV)", 16, svr_evaluate),
    case("correction::SvrView::evaluate (1000 SV, words/bytes, near/far)", 24, svr_paths),
    case("control::Controller::step (NN, 8 steps)", 6, control_nn),
    case("control::Controller::step (SVR, 8 steps)", 4, control_svr),
    case("blob::BlobHead::string_lengths (training slips: their home, another, none)", 48, home_string_lengths),
    case("control::Controller::step (NN, training slips, a new Home after 4 steps)", 6, control_home),
    case("N=4: blob::CompiledCalibration::from_blob (4-line, planar)", 1, layout_blob_parse),
    case("N=4: string_law::string_lengths (4-line)", 24, string_lengths_four),
    case("N=4: string_law::string_lengths (planar)", 24, string_lengths_planar),
    case("N=4: kinematics::forward_kinematics::<f32> (4-line, warm)", 32, fk_four),
    case("N=4: kinematics::forward_kinematics::<f32> (planar, warm)", 32, fk_planar),
    case("N=4: tension::distribute (4-line)", 32, tension_four),
    case("N=4: tension::distribute (planar)", 32, tension_planar),
    case("N=4: control::Controller::step (4-line NN, 8 steps)", 6, control_four),
    case("N=4: control::Controller::step (planar NN, 8 steps)", 6, control_planar),
];

/// Shorthand of [`CASES`]: name, number of vectors, function.
const fn case(name: &'static str, vectors: u32, run: fn(&Fixtures, &mut Rng, &mut dyn Out)) -> Case {
    Case { name, vectors, run }
}

// ---------------------------------------------------------------------------
// Shared inputs (also used by the benchmarks).

/// Half the side of the cube whose corners are the anchors (mm): a 2.2 m frame.
pub const FRAME_HALF_MM: f32 = 1100.0;

/// The 8 anchors at the corners of the 2.2 m cube (device frame, mm).
pub fn cube_anchors() -> [[f32; 3]; spidar_core::STRINGS] {
    let h = FRAME_HALF_MM;
    let mut a = [[0.0; 3]; spidar_core::STRINGS];
    for (i, p) in a.iter_mut().enumerate() {
        *p = [if i & 1 == 0 { -h } else { h }, if i & 2 == 0 { -h } else { h }, if i & 4 == 0 { -h } else { h }];
    }
    a
}

/// A 4-line cable robot's anchors (three low, one high; device frame, mm),
/// channels 0..4 of the N = 4 model.
pub const FOUR_LINE_ANCHORS: [[f32; 3]; 4] =
    [[0.0, -1620.0, -150.0], [1272.8, 1272.8, -150.0], [-1403.0, 810.0, -150.0], [0.0, 0.0, 2350.0]];

/// A planar device's anchors: corners of a 1.6 m x 1.2 m frame in z = 25 mm.
pub const PLANAR_ANCHORS: [[f32; 3]; 4] =
    [[-800.0, -600.0, 25.0], [800.0, -600.0, 25.0], [800.0, 600.0, 25.0], [-800.0, 600.0, 25.0]];

/// The planar model's channels: 0, 2, 5, 7.
pub const PLANAR_ACTIVE: u8 = 0b1010_0101;

/// The compiled N = 4 calibration: 4-line (`planar == false`) or planar.
pub fn layout_calibration<'a>(fx: &Fixtures<'a>, planar: bool) -> Option<spidar_core::blob::CompiledCalibration<'a>> {
    spidar_core::blob::CompiledCalibration::from_blob(if planar { fx.planar_blob } else { fx.four_blob }).ok()
}

/// A position inside the active anchors' hull: a convex combination with
/// weights in [0.2, 1] (exact f32 operations in a fixed order); planar: in
/// the anchors' plane.
pub fn position_inside(frame: &spidar_core::model::Frame<f32>, rng: &mut Rng) -> [f32; 3] {
    let mut p = [0.0f32; 3];
    let mut total = 0.0f32;
    for i in frame.layout.indices() {
        let w = rng.f32_in(0.2, 1.0);
        total += w;
        for k in 0..3 {
            p[k] += w * frame.anchors[i][k];
        }
    }
    p.map(|v| v / total)
}

/// A position in the central 1 m cube (mm).
pub fn central_position(rng: &mut Rng) -> [f32; 3] {
    [rng.f32_in(-500.0, 500.0), rng.f32_in(-500.0, 500.0), rng.f32_in(-500.0, 500.0)]
}

/// A force with components in `[-max, max]` (N).
pub fn force(rng: &mut Rng, max: f32) -> [f32; 3] {
    [rng.f32_in(-max, max), rng.f32_in(-max, max), rng.f32_in(-max, max)]
}

/// Tension limits of the benchmarks and vectors: 0.5 to 20 N.
pub fn tension_limits() -> spidar_core::tension::TensionLimits<f32> {
    spidar_core::tension::TensionLimits { t_min: 0.5, t_max: 20.0 }
}

/// The compiled calibration of a fixture blob (`nn` or `svr`).
pub fn calibration<'a>(fx: &Fixtures<'a>, svr: bool) -> Option<spidar_core::blob::CompiledCalibration<'a>> {
    spidar_core::blob::CompiledCalibration::from_blob(if svr { fx.svr_blob } else { fx.nn_blob }).ok()
}

/// Run-time string inputs over the whole workspace: up to +-30 pulley turns
/// (4096 counts per turn), any direction, 0 to 20 N, up to an hour, any
/// inclination.
pub fn string_inputs(rng: &mut Rng) -> spidar_core::model::StringInputs {
    let mut s = spidar_core::model::StringInputs::default();
    for i in 0..spidar_core::STRINGS {
        s.counts[i] = rng.i32_in(-30 * 4096, 30 * 4096);
        s.direction[i] = rng.i32_in(-1, 1) as i8;
        s.tension_mn[i] = rng.i32_in(0, 20_000) as u16;
        s.cos2_inclination_q16[i] = rng.i32_in(0, 65535) as u16;
        // Up to about 2 m/s of string (0.0184 mm per count).
        s.count_rate_cps[i] = rng.i32_in(-110_000, 110_000);
        // Any elevation from the swivel plane (Q0.32 turns, +-1/4 turn).
        s.guide_elevation_q32[i] = rng.i32_in(-(1 << 30), 1 << 30);
    }
    // Up to 10 h since home: a creep's strain over a long session (and
    // the model's slip at 600 s on either side).
    s.time_ms = rng.next_u32() % 36_000_000;
    s
}

/// Exact string lengths from a position, with +-`noise` mm on each (f32).
pub fn lengths_at(p: [f32; 3], rng: &mut Rng, noise: f32) -> [f32; spidar_core::STRINGS] {
    let mut l = spidar_core::kinematics::inverse_kinematics(&cube_anchors(), p);
    for x in l.iter_mut() {
        *x += rng.f32_in(-noise, noise);
    }
    l
}

fn tension_solution(out: &mut dyn Out, s: &spidar_core::tension::TensionSolution<f32>) {
    out.f32s(&s.tensions);
    out.f32(s.rendered_fraction);
    out.f32(s.residual_n);
    out.f32s(&s.multiplier);
    out.u32(s.iterations as u32);
    out.debug(s);
}

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

fn tension_case(rng: &mut Rng, out: &mut dyn Out, max_force: f32) {
    use spidar_core::tension::{distribute, TensionConfig};
    let p = central_position(rng);
    let f = force(rng, max_force);
    let s = distribute(
        &cube_anchors(),
        spidar_core::model::StringLayout::ALL,
        p,
        f,
        tension_limits(),
        &TensionConfig::default(),
    );
    tension_solution(out, &s);
}

/// Feasible forces (|F_i| <= 3 N) at central positions.
fn tension_feasible(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    tension_case(rng, out, 3.0)
}

/// Mostly infeasible forces (|F_i| <= 300 N): scaled back, more iterations.
fn tension_scaled(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    tension_case(rng, out, 300.0)
}

/// Warm start from the previous solution's multiplier, along a short path.
fn tension_warm(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::tension::{distribute_warm, TensionConfig};
    let mut p = central_position(rng);
    let f = force(rng, 30.0);
    let mut lambda = [0.0f32; 3];
    for _ in 0..4 {
        let s = distribute_warm(
            &cube_anchors(),
            spidar_core::model::StringLayout::ALL,
            p,
            f,
            tension_limits(),
            &TensionConfig::default(),
            lambda,
        );
        tension_solution(out, &s);
        lambda = s.multiplier;
        for x in p.iter_mut() {
            *x += rng.f32_in(-0.5, 0.5);
        }
    }
}

/// Guidance cue (eqs. 2-5): `libm::expf`, a division, a square root.
fn guidance(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::guidance::*;
    let d_min = rng.f32_in(1.0, 200.0);
    let d = rng.f32_in(-10.0, 250.0);
    out.f32(closeness(d, d_min));
    out.f32(beep_frequency_hz(d, d_min));
    out.f32(guidance_profile(d, d_min));
    let v = [rng.f32_in(-300.0, 300.0), rng.f32_in(-300.0, 300.0), rng.f32_in(-300.0, 300.0)];
    out.f32s(&guidance_force(v, d_min, rng.f32_in(0.0, 10.0)));
}

/// Safety monitor: force and tension clamps, slack and fault latching.
fn safety(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::safety::{SafetyConfig, SafetyMonitor};
    let config = SafetyConfig {
        t_min: 0.5,
        t_max: 20.0,
        f_max: 10.0,
        pretension_n: 1.0,
        heartbeat_timeout_ms: 100,
        slack_threshold_mm: 5.0,
    };
    let Ok(mut m) = SafetyMonitor::new(config) else {
        out.u32(u32::MAX);
        return;
    };
    m.heartbeat(0);
    out.debug(&m.arm());
    let mut measured = [0.0f32; spidar_core::STRINGS];
    let mut geometric = [0.0f32; spidar_core::STRINGS];
    for i in 0..spidar_core::STRINGS {
        geometric[i] = rng.f32_in(300.0, 2500.0);
        measured[i] = geometric[i] + rng.f32_in(-6.0, 6.0);
    }
    let faults = m.check(rng.i32_in(0, 150) as u32, &measured, &geometric, rng.i32_in(0, 7) != 0);
    out.u32(faults.bits() as u32);
    out.f32s(&m.limit_force(force(rng, 15.0)));
    let mut t = [0.0f32; spidar_core::STRINGS];
    for x in t.iter_mut() {
        *x = rng.f32_in(-5.0, 25.0);
    }
    out.f32s(&m.apply(t));
    out.u32(m.warnings().bits() as u32);
    out.u32(m.slack_mask() as u32);
}

/// The device's parse of both fixture blobs (header, f32 frame, compiled
/// laws and effects, correction kind).
fn blob_parse(fx: &Fixtures, _: &mut Rng, out: &mut dyn Out) {
    for svr in [false, true] {
        match calibration(fx, svr) {
            Some(c) => {
                out.debug(&c.header);
                out.debug(&c.head);
                out.debug(&c.correction.kind());
            }
            None => out.u32(u32::MAX),
        }
    }
}

fn positions(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    let p = [rng.f32_in(-2000.0, 2000.0), rng.f32_in(-1.0, 1.0), rng.f32_in(-40000.0, 40000.0)];
    let q = spidar_core::blob::position_q16(p);
    out.i32s(&q);
    out.f32s(&spidar_core::blob::position_mm(q));
}

fn fixed_functions(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::fixed::*;
    for _ in 0..8 {
        out.i32(tanh_q27(rng.next_u32() as i32 >> rng.i32_in(0, 6)));
        out.i32(exp2_neg_q22(rng.next_u32() >> rng.i32_in(0, 8)));
    }
}

/// 16-bit counter wrap-around and direction hysteresis along a random walk.
fn encoder(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::encoder::{DirectionTracker, EncoderExtender};
    let mut raw = rng.next_u32() as u16;
    let mut ext = EncoderExtender::new(raw);
    let mut dir = DirectionTracker::new(rng.i32_in(0, 8) as u32);
    for _ in 0..32 {
        raw = raw.wrapping_add(rng.i32_in(-3000, 3000) as u16);
        let c = ext.update(raw);
        out.i32(c);
        out.i32(dir.update(c) as i32);
    }
}

fn string_lengths(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    let Some(c) = calibration(fx, false) else { return out.u32(u32::MAX) };
    let inputs = string_inputs(rng);
    out.i64s(&spidar_core::string_law::string_lengths(c.head.frame.layout, &c.head.laws, &c.head.effects, &inputs));
}

fn inverse_kinematics(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    let p = central_position(rng);
    out.f32s(&spidar_core::kinematics::inverse_kinematics(&cube_anchors(), p));
}

fn fk_solution(out: &mut dyn Out, s: &spidar_core::kinematics::FkSolution<f32>) {
    out.f32s(&s.position);
    out.f32(s.rms_residual_mm);
    out.u32(s.iterations);
    out.debug(s);
}

/// Warm start 0.05-2 mm from the answer (the previous iteration's position),
/// 0.3 mm length noise.
fn fk_warm(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::kinematics::{forward_kinematics, FkConfig};
    let p = central_position(rng);
    let lengths = lengths_at(p, rng, 0.3);
    let start = [p[0] + rng.f32_in(-2.0, 2.0), p[1] + rng.f32_in(-2.0, 2.0), p[2] + rng.f32_in(-2.0, 2.0)];
    fk_solution(
        out,
        &forward_kinematics(
            &cube_anchors(),
            spidar_core::model::StringLayout::ALL,
            &lengths,
            start,
            &FkConfig::default(),
        ),
    );
}

/// Cold start (frame centre) with one string 5-40 mm off: the exclusion path.
fn fk_faulty(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::kinematics::{forward_kinematics, FkConfig};
    let p = central_position(rng);
    let mut lengths = lengths_at(p, rng, 0.2);
    let bad = rng.i32_in(0, spidar_core::STRINGS as i32 - 1) as usize;
    lengths[bad] += rng.f32_in(5.0, 40.0);
    fk_solution(
        out,
        &forward_kinematics(
            &cube_anchors(),
            spidar_core::model::StringLayout::ALL,
            &lengths,
            [0.0; 3],
            &FkConfig::default(),
        ),
    );
}

/// Five strings (2 spares), one 40-120 mm off, 0.1 mm noise, cold start;
/// every string weighed alike or a good one weighed low: the 2-spare
/// inconsistent path (the exclusion that fits clearly best, or the
/// all-string compromise).
fn fk_two_spares(_: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::kinematics::{forward_kinematics, FkConfig};
    let five = spidar_core::model::StringLayout { active: 0b0001_1111, planar: false };
    let p = central_position(rng);
    let mut lengths = lengths_at(p, rng, 0.1);
    let bad = rng.i32_in(0, 4) as usize;
    let size = rng.f32_in(40.0, 120.0);
    lengths[bad] += if rng.i32_in(0, 1) == 0 { size } else { -size };
    let mut config = FkConfig::default();
    if rng.i32_in(0, 1) == 0 {
        config.residual_weight[(bad + 1) % 5] = rng.f32_in(0.2, 0.9);
    }
    fk_solution(out, &forward_kinematics(&cube_anchors(), five, &lengths, [0.0; 3], &config));
}

fn correction_case(fx: &Fixtures, svr: bool, rng: &mut Rng, out: &mut dyn Out) {
    let Some(c) = calibration(fx, svr) else { return out.u32(u32::MAX) };
    let p = spidar_core::blob::position_q16(central_position(rng));
    out.i32s(&c.correction.evaluate(p));
}

fn nn_evaluate(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    correction_case(fx, false, rng, out)
}

fn svr_evaluate(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    correction_case(fx, true, rng, out)
}

/// The SVR read as aligned words and as bytes (blob at an odd address), at a
/// position of the central cube (one-`usat` kernel shift) or anywhere in the
/// `i32` range (mostly the general shift): both results, and which path each
/// view took.
fn svr_paths(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::correction::Correction;
    let (Some(words), Ok(bytes)) =
        (calibration(fx, true), spidar_core::blob::CompiledCalibration::from_blob(fx.svr_blob_odd))
    else {
        return out.u32(u32::MAX);
    };
    let p = if rng.next_u32() & 1 == 0 {
        spidar_core::blob::position_q16(central_position(rng))
    } else {
        [rng.next_u32() as i32, rng.next_u32() as i32, rng.next_u32() as i32]
    };
    for c in [&words.correction, &bytes.correction] {
        out.u32(matches!(c, Correction::Svr(v) if v.reads_words()) as u32);
        out.i32s(&c.evaluate(p));
    }
}

/// Eight control-loop iterations from home with random encoder motion (so
/// FK also meets inconsistent lengths), a random target kind; every output
/// field of every step.
fn control_case(fx: &Fixtures, svr: bool, rng: &mut Rng, out: &mut dyn Out) {
    let Some(cal) = calibration(fx, svr) else { return out.u32(u32::MAX) };
    control_steps(&cal, rng, out, None)
}

/// Eight steps as [`control_case`]'s; with `homes`, the controller starts
/// under home capture `homes[0]` and is homed again (a `Home`) under
/// `homes[1]` before step 4.
fn control_steps(
    cal: &spidar_core::blob::CompiledCalibration,
    rng: &mut Rng,
    out: &mut dyn Out,
    homes: Option<[u64; 2]>,
) {
    use spidar_core::control::{ControlConfig, Controller, LoopInput, Target};
    let mut raw: [u16; spidar_core::STRINGS] = core::array::from_fn(|_| rng.next_u32() as u16);
    let Ok(mut ctl) = Controller::new(ControlConfig::default(), cal, raw, 5) else { return out.u32(u32::MAX - 1) };
    ctl.set_home_id(homes.map(|h| h[0]));
    ctl.set_target(match rng.i32_in(0, 2) {
        0 => Target::Idle,
        1 => Target::Force(force(rng, 20.0)),
        _ => Target::Guidance { target_mm: central_position(rng), d_min_mm: rng.f32_in(10.0, 300.0), f_max_n: 5.0 },
    });
    ctl.safety().heartbeat(5);
    out.debug(&ctl.safety().arm());
    for step in 0..8u32 {
        for r in raw.iter_mut() {
            *r = r.wrapping_add(rng.i32_in(-400, 400) as u16);
        }
        let now = 5 + step;
        if let (4, Some(h)) = (step, homes) {
            ctl.home(cal, raw, now);
            ctl.set_home_id(Some(h[1]));
        }
        if rng.i32_in(0, 3) != 0 {
            ctl.safety().heartbeat(now);
        }
        let o = ctl
            .step(cal, &LoopInput { raw_counts: raw, now_ms: now, now_us: now * 1000, estop: rng.i32_in(0, 15) == 0 });
        out.f32s(&o.string_lengths_mm);
        out.f32s(&o.position_mm);
        out.i32s(&o.corrected_q16);
        out.f32s(&o.force_n);
        out.f32s(&o.tensions_n);
        out.debug(&o);
    }
}

fn control_nn(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    control_case(fx, false, rng, out)
}

fn control_svr(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    control_case(fx, true, rng, out)
}

/// The id of the home capture of a blob's training slips (0 without).
fn training_home(cal: &spidar_core::blob::CompiledCalibration) -> u64 {
    cal.head.home.as_ref().map_or(0, |h| h.home_id)
}

/// The string lengths of the three models with training slips under their
/// home capture, another one and none, at times near the slips' (up to
/// 1.2 s) or anywhere in an hour.
fn home_string_lengths(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    for cal in [calibration(fx, false), layout_calibration(fx, false), layout_calibration(fx, true)] {
        let Some(cal) = cal else { return out.u32(u32::MAX) };
        let mut inputs = string_inputs(rng);
        if rng.i32_in(0, 1) == 0 {
            inputs.time_ms %= 1200;
        }
        let home = training_home(&cal);
        for id in [Some(home), Some(home ^ rng.i32_in(1, 3) as u64), None] {
            out.i64s(&cal.head.string_lengths(&inputs, id));
        }
    }
}

/// [`control_case`]'s eight steps under the NN blob's training home
/// capture, then a new one from step 4 (its slips no longer apply).
fn control_home(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    let Some(cal) = calibration(fx, false) else { return out.u32(u32::MAX) };
    let home = training_home(&cal);
    control_steps(&cal, rng, out, Some([home, home + 1]))
}

// ---------------------------------------------------------------------------
// N = 4 (issue 11): a 4-line cable robot in space and a planar device, each
// on 4 of the 8 channels.

fn layout_blob_parse(fx: &Fixtures, _: &mut Rng, out: &mut dyn Out) {
    for planar in [false, true] {
        match layout_calibration(fx, planar) {
            Some(c) => {
                out.debug(&c.header);
                out.debug(&c.head);
            }
            None => out.u32(u32::MAX),
        }
    }
}

fn string_lengths_layout(fx: &Fixtures, planar: bool, rng: &mut Rng, out: &mut dyn Out) {
    let Some(c) = layout_calibration(fx, planar) else { return out.u32(u32::MAX) };
    let inputs = string_inputs(rng);
    out.i64s(&spidar_core::string_law::string_lengths(c.head.frame.layout, &c.head.laws, &c.head.effects, &inputs));
}

fn string_lengths_four(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    string_lengths_layout(fx, false, rng, out)
}

fn string_lengths_planar(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    string_lengths_layout(fx, true, rng, out)
}

/// Warm start 0.05-2 mm from a point inside the anchors' hull, 0.3 mm
/// length noise on the active strings (inactive lengths NaN: never read).
fn fk_layout(fx: &Fixtures, planar: bool, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::kinematics::{forward_kinematics, inverse_kinematics, FkConfig};
    let Some(c) = layout_calibration(fx, planar) else { return out.u32(u32::MAX) };
    let frame = &c.head.frame;
    let p = position_inside(frame, rng);
    let mut lengths = inverse_kinematics(&frame.anchors, p);
    for (i, l) in lengths.iter_mut().enumerate() {
        *l = if frame.layout.is_active(i) { *l + rng.f32_in(-0.3, 0.3) } else { f32::NAN };
    }
    let mut start = [p[0] + rng.f32_in(-2.0, 2.0), p[1] + rng.f32_in(-2.0, 2.0), p[2] + rng.f32_in(-2.0, 2.0)];
    if planar {
        start[2] = p[2];
    }
    fk_solution(out, &forward_kinematics(&frame.anchors, frame.layout, &lengths, start, &FkConfig::default()));
}

fn fk_four(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    fk_layout(fx, false, rng, out)
}

fn fk_planar(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    fk_layout(fx, true, rng, out)
}

/// Inside the hull (mostly), forces up to 30 N (feasible and scaled); one
/// vector in four at a central-cube position (outside the hull for some).
fn tension_layout(fx: &Fixtures, planar: bool, rng: &mut Rng, out: &mut dyn Out) {
    use spidar_core::tension::{distribute, force_closure, TensionConfig};
    let Some(c) = layout_calibration(fx, planar) else { return out.u32(u32::MAX) };
    let frame = &c.head.frame;
    let p = if rng.i32_in(0, 3) == 0 { central_position(rng) } else { position_inside(frame, rng) };
    let f = force(rng, 30.0);
    let cfg = TensionConfig::default();
    let s = distribute(&frame.anchors, frame.layout, p, f, tension_limits(), &cfg);
    tension_solution(out, &s);
    out.debug(&force_closure(&frame.anchors, frame.layout, p, tension_limits(), &cfg));
}

fn tension_four(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    tension_layout(fx, false, rng, out)
}

fn tension_planar(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    tension_layout(fx, true, rng, out)
}

fn control_four(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    let Some(c) = layout_calibration(fx, false) else { return out.u32(u32::MAX) };
    control_steps(&c, rng, out, None)
}

fn control_planar(fx: &Fixtures, rng: &mut Rng, out: &mut dyn Out) {
    let Some(c) = layout_calibration(fx, true) else { return out.u32(u32::MAX) };
    control_steps(&c, rng, out, None)
}
