use super::svr::SvrRecords;
use super::*;
use crate::fixed::{mm_to_q16, q16_to_mm};
use proptest::prelude::*;

/// splitmix64: deterministic test data without a dependency.
struct Rng(u64);
impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in [lo, hi).
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let u1 = self.uniform(1e-12, 1.0);
        let u2 = self.uniform(0.0, 1.0);
        libm::sqrt(-2.0 * libm::log(u1)) * libm::cos(2.0 * core::f64::consts::PI * u2)
    }
}

/// Half the side of the workspace cube (mm): a 1 m cube around the origin.
const HALF: f64 = 500.0;

fn input_std() -> Standardization {
    // A uniform distribution over ±500 mm has std 1000/sqrt(12) = 288.7 mm.
    Standardization {
        mean: [3.217, -7.93, 11.4041],
        std: [288.1, 291.7, 286.9],
    }
}

fn output_std() -> Standardization {
    Standardization {
        mean: [1.9, -4.3, 8.77],
        std: [301.3, 297.8, 305.2],
    }
}

/// A 3-H-3 network shaped like an LM-trained one: first-layer weights of a
/// few units, and pairs of neurons with close first-layer weights and
/// large opposite output weights, so that sum |W2| * std_out is about
/// 37,000 mm per axis while the output stays within a few hundred mm.
fn nn_model(hidden: usize, seed: u64, mode: OutputMode) -> NnModel {
    let mut rng = Rng(seed);
    let mut w1 = Vec::new();
    let mut b1 = Vec::new();
    let mut w2: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for h in 0..hidden {
        if h % 2 == 1 {
            let prev: [f64; 3] = w1[h - 1];
            w1.push([
                prev[0] * (1.0 + 0.08 * rng.normal()),
                prev[1] * (1.0 + 0.08 * rng.normal()),
                prev[2] * (1.0 + 0.08 * rng.normal()),
            ]);
            b1.push(b1[h - 1] + 0.1 * rng.normal());
            for (a, w) in w2.iter_mut().enumerate() {
                let prev = w[h - 1];
                let _ = a;
                w.push(-prev * (1.0 + 0.05 * rng.normal()));
            }
        } else {
            w1.push([1.5 * rng.normal(), 1.5 * rng.normal(), 1.5 * rng.normal()]);
            b1.push(rng.uniform(-1.5, 1.5));
            for w in w2.iter_mut() {
                w.push(rng.uniform(-12.0, 12.0));
            }
        }
    }
    // Scale the output weights so that sum |W2| * std_out = 37,000 mm.
    let out = output_std();
    for (a, w) in w2.iter_mut().enumerate() {
        let s: f64 = w.iter().map(|v| v.abs()).sum::<f64>() * out.std[a];
        w.iter_mut().for_each(|v| *v *= 37_000.0 / s);
    }
    NnModel {
        input: input_std(),
        output: out,
        w1,
        b1,
        w2,
        b2: [0.03, -0.02, 0.05],
        mode,
    }
}

/// An RBF SVR shaped like the notes' one: support vectors over the
/// standardized workspace, gamma = 1/3, sum |coef| = 845 per axis.
fn svr_model(n: usize, seed: u64, mode: OutputMode) -> SvrModel {
    let mut rng = Rng(seed);
    let lim = HALF / 288.7;
    let support = (0..n)
        .map(|_| {
            [
                rng.uniform(-lim, lim),
                rng.uniform(-lim, lim),
                rng.uniform(-lim, lim),
            ]
        })
        .collect();
    let mut coef: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for c in coef.iter_mut() {
        *c = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let s: f64 = c.iter().map(|v| v.abs()).sum();
        c.iter_mut().for_each(|v| *v *= 845.0 / s);
    }
    SvrModel {
        input: input_std(),
        output: output_std(),
        gamma: 1.0 / 3.0,
        support,
        coef,
        bias: [0.01, -0.04, 0.02],
        mode,
    }
}

/// Positions of the 1 m workspace cube: a 21^3 grid (10 steps of 100 mm per
/// axis... 50 mm) and 2,000 random points, as Q15.16.
fn workspace_points() -> Vec<[i32; 3]> {
    let mut pts = Vec::new();
    for i in 0..21 {
        for j in 0..21 {
            for k in 0..21 {
                let c = |n: i32| -HALF + 50.0 * n as f64;
                pts.push([mm_to_q16(c(i)), mm_to_q16(c(j)), mm_to_q16(c(k))]);
            }
        }
    }
    let mut rng = Rng(77);
    for _ in 0..2000 {
        pts.push([
            mm_to_q16(rng.uniform(-HALF, HALF)),
            mm_to_q16(rng.uniform(-HALF, HALF)),
            mm_to_q16(rng.uniform(-HALF, HALF)),
        ]);
    }
    pts
}

/// Mean and max Euclidean distance (mm) between the fixed-point output and
/// the f64 output on the same (Q15.16-representable) inputs.
fn error_stats(
    f64_eval: impl Fn([f64; 3]) -> [f64; 3],
    fixed_eval: impl Fn([i32; 3]) -> [i32; 3],
) -> (f64, f64) {
    let pts = workspace_points();
    let mut sum = 0.0;
    let mut max = 0f64;
    for p in &pts {
        let pf = [q16_to_mm(p[0]), q16_to_mm(p[1]), q16_to_mm(p[2])];
        let want = f64_eval(pf);
        let got = fixed_eval(*p);
        let e = (0..3)
            .map(|a| (q16_to_mm(got[a]) - want[a]).powi(2))
            .sum::<f64>()
            .sqrt();
        sum += e;
        max = max.max(e);
    }
    (sum / pts.len() as f64, max)
}

fn nn_view<'a>(bytes: &'a [u8], model: &NnModel) -> NnView<'a> {
    NnView::parse(bytes, model.w1.len() as u16).expect("compiled NN parses")
}

#[test]
fn nn_model_is_realistic() {
    let m = nn_model(20, 1, OutputMode::Absolute);
    for a in 0..3 {
        let s: f64 = m.w2[a].iter().map(|v| v.abs()).sum::<f64>() * m.output.std[a];
        assert!((s - 37_000.0).abs() < 1.0);
    }
    // Outputs stay within a plausible range despite the large weights.
    let mut max = 0f64;
    for p in workspace_points().iter().step_by(37) {
        let y = m.evaluate([q16_to_mm(p[0]), q16_to_mm(p[1]), q16_to_mm(p[2])]);
        max = max.max(y.iter().fold(0f64, |m, v| m.max(v.abs())));
    }
    assert!(max < 20_000.0, "{max}");
}

#[test]
fn nn_error_budget() {
    for (seed, mode) in [
        (1, OutputMode::Absolute),
        (2, OutputMode::Residual),
        (3, OutputMode::Absolute),
    ] {
        let m = nn_model(20, seed, mode);
        let bytes = m.compile().expect("compiles");
        assert_eq!(bytes.len(), NN_HEADER_LEN + 20 * NN_NEURON_LEN);
        let v = nn_view(&bytes, &m);
        let (mean, max) = error_stats(|p| m.evaluate(p), |p| v.evaluate(p));
        eprintln!("NN 3-20-3 seed {seed} {mode:?}: mean {mean:.6} mm, max {max:.6} mm");
        assert!(mean < 0.001, "NN mean error {mean} mm");
        assert!(max < 0.002, "NN max error {max} mm");
    }
}

/// A steep neuron (an LM-trained step, first-layer weights of tens per
/// standard deviation) whose first-layer bias of -14 brings it back from
/// beyond the pre-activation's +-16: at a point where `w1 . x` is 30 the
/// neuron is at tanh(16), 1 to 13 digits. Saturating `w1 . x` to 16 before
/// adding the bias read it at tanh(2), 0.036 off: with an output weight of
/// 100 mm, 3.6 mm on the device where the host's figures have none.
#[test]
fn a_steep_neuron_adds_its_bias_before_it_saturates() {
    let m = NnModel {
        input: Standardization {
            mean: [0.0; 3],
            std: [100.0; 3],
        },
        output: Standardization {
            mean: [0.0; 3],
            std: [1.0; 3],
        },
        w1: vec![[30.0, 0.0, 0.0]],
        b1: vec![-14.0],
        w2: [vec![100.0], vec![0.0], vec![0.0]],
        b2: [0.0; 3],
        mode: OutputMode::Residual,
    };
    let bytes = m.compile().expect("compiles");
    let v = nn_view(&bytes, &m);
    // w1 . x from -60 to 60 along x: through the step (at x = 47 mm) and
    // far past it on both sides.
    for k in -20..=20 {
        let p = [10.0 * f64::from(k), 3.0, -2.0];
        let host = m.evaluate(p);
        let device = v.evaluate(p.map(mm_to_q16)).map(q16_to_mm);
        assert!(
            (host[0] - device[0]).abs() < 0.002,
            "x = {} mm: host {} mm, device {} mm",
            p[0],
            host[0],
            device[0]
        );
    }
}

#[test]
fn view_rebuilt_from_its_summary_evaluates_the_same() {
    for model in [
        CorrectionModel::Svr(svr_model(200, 5, OutputMode::Residual)),
        CorrectionModel::Svr(svr_model(70, 6, OutputMode::Absolute)),
        CorrectionModel::Nn(nn_model(20, 7, OutputMode::Residual)),
        CorrectionModel::Nn(nn_model(3, 8, OutputMode::Absolute)),
    ] {
        let c = model.compile().expect("compiles");
        let parsed =
            Correction::parse(c.kind, c.hidden, c.support_vectors, &c.bytes).expect("parses");
        let rebuilt = Correction::from_summary(&parsed.summary(), &c.bytes).expect("rebuilds");
        assert_eq!(rebuilt, parsed);
        // A summary does not fit bytes of another length.
        assert!(
            Correction::from_summary(&parsed.summary(), &c.bytes[..c.bytes.len() - 1]).is_err()
        );
    }
}

#[test]
fn svr_error_budget() {
    for (n, seed, mode) in [
        (350, 11, OutputMode::Absolute),
        (1000, 12, OutputMode::Residual),
    ] {
        let m = svr_model(n, seed, mode);
        let bytes = m.compile().expect("compiles");
        assert_eq!(bytes.len(), SVR_HEADER_LEN + n * SVR_RECORD_LEN);
        let v = SvrView::parse(&bytes, n as u32).expect("parses");
        let (mean, max) = error_stats(|p| m.evaluate(p), |p| v.evaluate(p));
        eprintln!("SVR {n} SV seed {seed} {mode:?}: mean {mean:.6} mm, max {max:.6} mm");
        assert!(mean < 0.001, "SVR mean error {mean} mm");
        assert!(max < 0.002, "SVR max error {max} mm");
    }
}

/// Records at a 4-aligned address are read as words, else as bytes; the
/// word path with the one-`usat` shift (inputs near the support vectors)
/// and with the general one (far inputs) and the byte path give the same
/// bits.
#[test]
fn svr_word_and_byte_paths_agree() {
    let m = svr_model(1000, 12, OutputMode::Residual);
    let bytes = m.compile().expect("compiles");
    let mut words = vec![0u32; bytes.len().div_ceil(4)];
    let aligned = &mut bytemuck::cast_slice_mut::<u32, u8>(&mut words)[..bytes.len()];
    aligned.copy_from_slice(&bytes);
    let mut store = vec![0u32; bytes.len() / 4 + 2];
    let shifted = &mut bytemuck::cast_slice_mut::<u32, u8>(&mut store)[1..=bytes.len()];
    shifted.copy_from_slice(&bytes);
    let w = SvrView::parse(aligned, 1000).expect("parses");
    let b = SvrView::parse(shifted, 1000).expect("parses");
    assert!(w.reads_words());
    assert!(!b.reads_words());
    assert_eq!(w.support_vectors(), b.support_vectors());
    let mut rng = Rng(77);
    let mut points = workspace_points();
    points.truncate(3000);
    let (mut narrow, mut wide) = (0, 0);
    for k in 0..3000 {
        let far = match k % 3 {
            0 => [
                rng.next_u64() as i32,
                rng.next_u64() as i32,
                rng.next_u64() as i32,
            ],
            1 => [i32::MIN, i32::MAX, (rng.next_u64() as i32) >> 8],
            _ => [(rng.next_u64() as i32) >> 4, 0, 0],
        };
        points.push(far);
    }
    for p in points {
        let q = w.scaled(p);
        if w.exponents_below_2p31(q) {
            narrow += 1;
        } else {
            wide += 1;
        }
        assert_eq!(w.evaluate(p), b.evaluate(p), "p {p:?}");
    }
    assert!(narrow > 1000 && wide > 1000, "narrow {narrow}, wide {wide}");
}

#[test]
fn correction_enum_and_header_checks() {
    let nn = nn_model(4, 5, OutputMode::Absolute);
    let c = CorrectionModel::Nn(nn.clone()).compile().expect("compiles");
    assert_eq!(
        (c.kind, c.hidden, c.support_vectors),
        (CorrectionKind::Nn, 4, 0)
    );
    assert_eq!(check_header_formats(c.q_position, c.q_weight), Ok(()));
    let view = Correction::parse(c.kind, c.hidden, c.support_vectors, &c.bytes).expect("parses");
    let p = [mm_to_q16(10.0), mm_to_q16(-20.0), mm_to_q16(30.0)];
    assert_eq!(
        view.evaluate(p),
        NnView::parse(&c.bytes, 4).unwrap().evaluate(p)
    );
    assert_eq!(view.kind(), CorrectionKind::Nn);
    assert_eq!(
        Correction::parse(CorrectionKind::Nn, 4, 1, &c.bytes),
        Err(BlobError::Dimension {
            field: "support_vectors",
            found: 1,
            expected: 0
        })
    );
    assert_eq!(
        Correction::parse(CorrectionKind::Nn, 5, 0, &c.bytes),
        Err(BlobError::Dimension {
            field: "nn.body_len",
            found: c.bytes.len() as u32,
            expected: (NN_HEADER_LEN + 5 * NN_NEURON_LEN) as u32
        })
    );
    let none = Correction::parse(CorrectionKind::None, 0, 0, &[]).expect("parses");
    assert_eq!(none.evaluate(p), p);
    assert!(Correction::parse(CorrectionKind::None, 0, 0, &[0]).is_err());
    assert_eq!(
        check_header_formats(16, 24),
        Err(BlobError::Dimension {
            field: "q_weight",
            found: 24,
            expected: 30
        })
    );
    assert!(check_header_formats(15, 30).is_err());
    let svr = CorrectionModel::Svr(svr_model(3, 9, OutputMode::Residual))
        .compile()
        .expect("compiles");
    assert_eq!(
        (svr.kind, svr.hidden, svr.support_vectors),
        (CorrectionKind::Svr, 0, 3)
    );
    assert!(Correction::parse(svr.kind, 0, 3, &svr.bytes).is_ok());
    assert!(Correction::parse(svr.kind, 1, 3, &svr.bytes).is_err());
    // An SVR without support vectors is a constant (plus the input in residual mode).
    let mut empty = svr_model(0, 9, OutputMode::Absolute);
    empty.bias = [1.0, 2.0, 3.0];
    let b = empty.compile().expect("compiles");
    let v = SvrView::parse(&b, 0).expect("parses");
    let want = empty.evaluate([0.0; 3]);
    let got = v.evaluate([0; 3]);
    for a in 0..3 {
        assert!((q16_to_mm(got[a]) - want[a]).abs() < 1e-4);
    }
}

#[test]
fn every_truncation_and_bad_field_is_refused_by_name() {
    let nn = nn_model(3, 4, OutputMode::Residual).compile().unwrap();
    for cut in 0..nn.len() {
        assert!(NnView::parse(&nn[..cut], 3).is_err(), "cut {cut}");
    }
    let mut bad = nn.clone();
    bad[0] = 2;
    assert_eq!(
        NnView::parse(&bad, 3),
        Err(BlobError::Body { field: "nn.mode" })
    );
    let mut bad = nn.clone();
    bad[1] = 61;
    assert_eq!(
        NnView::parse(&bad, 3),
        Err(BlobError::Body {
            field: "nn.w1_frac"
        })
    );
    let mut bad = nn.clone();
    bad[3] = 49;
    assert_eq!(
        NnView::parse(&bad, 3),
        Err(BlobError::Body {
            field: "nn.w2_frac"
        })
    );
    let mut bad = nn.clone();
    bad[6] = 1;
    assert_eq!(
        NnView::parse(&bad, 3),
        Err(BlobError::Body {
            field: "nn.reserved"
        })
    );
    let mut bad = nn.clone();
    bad[NN_HEADER_LEN + 4..NN_HEADER_LEN + 8].copy_from_slice(&(W1_MAX + 1).to_le_bytes());
    assert_eq!(
        NnView::parse(&bad, 3),
        Err(BlobError::Body { field: "nn.w1" })
    );
    let mut bad = nn_model(5, 4, OutputMode::Residual).compile().unwrap();
    for h in 0..5 {
        let at = NN_HEADER_LEN + h * NN_NEURON_LEN + 20;
        bad[at..at + 4].copy_from_slice(&i32::MIN.to_le_bytes());
    }
    assert_eq!(
        NnView::parse(&bad, 5),
        Err(BlobError::Body { field: "nn.w2" })
    );
    assert_eq!(
        NnView::parse(&nn, 0),
        Err(BlobError::Dimension {
            field: "hidden",
            found: 0,
            expected: 1
        })
    );

    let svr = svr_model(5, 4, OutputMode::Absolute).compile().unwrap();
    for cut in 0..svr.len() {
        assert!(SvrView::parse(&svr[..cut], 5).is_err(), "cut {cut}");
    }
    let mut long = svr.clone();
    long.push(0);
    assert_eq!(
        SvrView::parse(&long, 5),
        Err(BlobError::Dimension {
            field: "svr.body_len",
            found: long.len() as u32,
            expected: svr.len() as u32
        })
    );
    assert!(SvrView::parse(&svr, u32::MAX).is_err());
    let mut bad = svr.clone();
    bad[SVR_HEADER_LEN..SVR_HEADER_LEN + 4].copy_from_slice(&(SUPPORT_MAX + 1).to_le_bytes());
    assert_eq!(
        SvrView::parse(&bad, 5),
        Err(BlobError::Body {
            field: "svr.support"
        })
    );
    let mut bad = svr.clone();
    bad[1] = 10;
    assert_eq!(
        SvrView::parse(&bad, 5),
        Err(BlobError::Body {
            field: "svr.scale_frac"
        })
    );
}

#[test]
fn compile_errors_name_the_parameter() {
    let mut m = nn_model(4, 6, OutputMode::Absolute);
    m.b1.pop();
    assert_eq!(
        m.compile(),
        Err(CorrectionCompileError::Dimension {
            field: "b1",
            found: 3,
            expected: 4
        })
    );
    let mut m = nn_model(4, 6, OutputMode::Absolute);
    m.w2[1][2] = f64::NAN;
    assert_eq!(
        m.compile(),
        Err(CorrectionCompileError::NotFinite {
            field: "w2[1]",
            index: 2
        })
    );
    let mut m = nn_model(4, 6, OutputMode::Absolute);
    m.input.std[2] = 0.0;
    assert!(matches!(
        m.compile(),
        Err(CorrectionCompileError::NotPositive {
            field: "input.std",
            index: 2,
            ..
        })
    ));
    let mut m = nn_model(4, 6, OutputMode::Absolute);
    m.b1[3] = 20.0;
    assert!(matches!(
        m.compile(),
        Err(CorrectionCompileError::OutOfRange {
            field: "b1",
            index: 3,
            ..
        })
    ));
    let mut m = nn_model(4, 6, OutputMode::Absolute);
    m.w1[1][0] = 1e9;
    assert!(matches!(
        m.compile(),
        Err(CorrectionCompileError::OutOfRange {
            field: "w1",
            index: 3,
            ..
        })
    ));
    let mut m = nn_model(4, 6, OutputMode::Absolute);
    m.input.mean[0] = 40_000.0;
    assert!(matches!(
        m.compile(),
        Err(CorrectionCompileError::OutOfRange {
            field: "input.mean",
            index: 0,
            ..
        })
    ));
    let mut m = svr_model(4, 6, OutputMode::Absolute);
    m.support[2][1] = 30.0;
    assert!(matches!(
        m.compile(),
        Err(CorrectionCompileError::OutOfRange {
            field: "support",
            index: 7,
            ..
        })
    ));
    let mut m = svr_model(4, 6, OutputMode::Absolute);
    m.gamma = -1.0;
    assert!(matches!(
        m.compile(),
        Err(CorrectionCompileError::NotPositive { field: "gamma", .. })
    ));
    let mut m = svr_model(4, 6, OutputMode::Absolute);
    m.coef[2][0] = 1e30;
    assert!(matches!(
        m.compile(),
        Err(CorrectionCompileError::OutOfRange {
            field: "coef[2]",
            index: 0,
            ..
        })
    ));
    let e = CorrectionCompileError::OutOfRange {
        field: "w1",
        index: 3,
        value: 1e9,
        format: "Q",
    };
    assert!(e.to_string().contains("`w1`[3]"));
}

fn arb_std() -> impl Strategy<Value = Standardization> {
    (
        prop::array::uniform3(-2000.0..2000.0f64),
        prop::array::uniform3(1.0..2000.0f64),
    )
        .prop_map(|(mean, std)| Standardization { mean, std })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Arbitrary bytes never make parsing or evaluation panic.
    #[test]
    fn arbitrary_bytes_never_panic(
        bytes in prop::collection::vec(any::<u8>(), 0..400),
        hidden in 0u16..12,
        svs in 0u32..14,
        p in prop::array::uniform3(any::<i32>()),
    ) {
        for kind in [CorrectionKind::None, CorrectionKind::Nn, CorrectionKind::Svr] {
            if let Ok(c) = Correction::parse(kind, hidden, svs, &bytes) {
                let _ = c.evaluate(p);
            }
        }
        // Well-sized bodies with arbitrary contents, headers made valid.
        let mut nn = bytes.clone();
        nn.resize(NN_HEADER_LEN + NN_NEURON_LEN * hidden.max(1) as usize, 0x5a);
        nn[0] &= 1;
        nn[1] = 11 + nn[1] % 50;
        for b in &mut nn[2..5] { *b %= 49; }
        nn[5..8].fill(0);
        if let Ok(v) = NnView::parse(&nn, hidden.max(1)) {
            let _ = v.evaluate(p);
        }
        let mut svr = bytes;
        svr.resize(SVR_HEADER_LEN + SVR_RECORD_LEN * svs as usize, 0xa5);
        svr[0] &= 1;
        svr[1] = 11 + svr[1] % 50;
        for b in &mut svr[2..5] { *b %= 49; }
        svr[5..8].fill(0);
        if let Ok(v) = SvrView::parse(&svr, svs) {
            // The same records at an odd address (byte path): same bits.
            let mut store = vec![0u32; svr.len() / 4 + 2];
            let shifted = &mut bytemuck::cast_slice_mut::<u32, u8>(&mut store)[1..=svr.len()];
            shifted.copy_from_slice(&svr);
            let shifted: &[u8] = shifted;
            let u = SvrView::parse(shifted, svs);
            prop_assert_eq!(u, Ok(SvrView { records: SvrRecords::Bytes(&shifted[SVR_HEADER_LEN..]), ..v }));
            if let Ok(u) = u {
                prop_assert_eq!(v.evaluate(p), u.evaluate(p));
            }
        }
    }

    /// Arbitrary weights (any f64 bits, NaN and infinities included) either
    /// compile or give an error; compiled models evaluate any position.
    #[test]
    fn arbitrary_weights_compile_or_fail_cleanly(
        w in prop::collection::vec(any::<f64>(), 30),
        input in arb_std(),
        output in arb_std(),
        p in prop::array::uniform3(any::<i32>()),
    ) {
        let nn = NnModel {
            input, output,
            w1: vec![[w[0], w[1], w[2]], [w[3], w[4], w[5]]],
            b1: vec![w[6], w[7]],
            w2: [vec![w[8], w[9]], vec![w[10], w[11]], vec![w[12], w[13]]],
            b2: [w[14], w[15], w[16]],
            mode: OutputMode::Residual,
        };
        if let Ok(b) = nn.compile() {
            let v = NnView::parse(&b, 2);
            prop_assert!(v.is_ok());
            if let Ok(v) = v { let _ = v.evaluate(p); }
        }
        let svr = SvrModel {
            input, output, gamma: w[17],
            support: vec![[w[18], w[19], w[20]], [w[21], w[22], w[23]]],
            coef: [vec![w[24], w[25]], vec![w[26], w[27]], vec![w[28], w[29]]],
            bias: [w[0], w[1], w[2]],
            mode: OutputMode::Absolute,
        };
        if let Ok(b) = svr.compile() {
            let v = SvrView::parse(&b, 2);
            prop_assert!(v.is_ok());
            if let Ok(v) = v { let _ = v.evaluate(p); }
        }
    }

    /// Plausible but random models with extreme weights still compile and
    /// evaluate any input bits without panicking; the f64 model agrees
    /// near the workspace.
    #[test]
    fn random_models_evaluate_any_position(
        w in prop::collection::vec(-50.0..50.0f64, 30),
        gamma in 0.01..5.0f64,
        input in arb_std(),
        output in arb_std(),
        p in prop::array::uniform3(any::<i32>()),
    ) {
        let nn = NnModel {
            input, output,
            w1: vec![[w[0], w[1], w[2]], [w[3], w[4], w[5]]],
            b1: vec![w[6] / 5.0, w[7] / 5.0],
            w2: [vec![w[8], w[9]], vec![w[10], w[11]], vec![w[12], w[13]]],
            b2: [w[14] / 10.0, w[15] / 10.0, w[16] / 10.0],
            mode: OutputMode::Absolute,
        };
        let b = nn.compile();
        prop_assert!(b.is_ok(), "{:?}", b);
        if let Ok(b) = b {
            if let Ok(v) = NnView::parse(&b, 2) {
                let _ = v.evaluate(p);
                let pm = input.mean;
                let q = [mm_to_q16(pm[0]), mm_to_q16(pm[1]), mm_to_q16(pm[2])];
                let got = v.evaluate(q);
                let want = nn.evaluate([q16_to_mm(q[0]), q16_to_mm(q[1]), q16_to_mm(q[2])]);
                for a in 0..3 {
                    // Beyond ±32.7 m the Q15.16 output saturates by design.
                    if want[a].abs() < 30_000.0 {
                        prop_assert!((q16_to_mm(got[a]) - want[a]).abs() < 0.01);
                    }
                }
            }
        }
        let svr = SvrModel {
            input, output, gamma,
            support: vec![[w[18] / 25.0, w[19] / 25.0, w[20] / 25.0], [w[21] / 25.0, w[22] / 25.0, w[23] / 25.0]],
            coef: [vec![w[24], w[25]], vec![w[26], w[27]], vec![w[28], w[29]]],
            bias: [w[0] / 10.0, w[1] / 10.0, w[2] / 10.0],
            mode: OutputMode::Residual,
        };
        if let Ok(b) = svr.compile() {
            if let Ok(v) = SvrView::parse(&b, 2) {
                let _ = v.evaluate(p);
                let pm = input.mean;
                let q = [mm_to_q16(pm[0]), mm_to_q16(pm[1]), mm_to_q16(pm[2])];
                let got = v.evaluate(q);
                let want = svr.evaluate([q16_to_mm(q[0]), q16_to_mm(q[1]), q16_to_mm(q[2])]);
                for a in 0..3 {
                    // Beyond ±32.7 m the Q15.16 output saturates by design.
                    if want[a].abs() < 30_000.0 {
                        prop_assert!((q16_to_mm(got[a]) - want[a]).abs() < 0.01);
                    }
                }
            }
        }
    }
}

/// A correction the device cannot evaluate within its tick neither compiles
/// nor loads: the largest that does is taken, one more is refused, naming
/// the count and the most the device takes.
#[test]
fn corrections_beyond_the_tick_budget_are_refused_at_compile_and_at_load() {
    let most = MAX_SUPPORT_VECTORS as usize;
    let largest = svr_model(most, 7, OutputMode::Residual);
    let bytes = largest
        .compile()
        .expect("the largest SVR the device takes compiles");
    SvrView::parse(&bytes, most as u32).expect("and loads");
    let over = svr_model(most + 1, 7, OutputMode::Residual);
    let e = over.compile().unwrap_err();
    assert_eq!(
        e,
        CorrectionCompileError::OverBudget {
            field: "support",
            found: most + 1,
            most
        }
    );
    assert!(e.to_string().contains("1001 entries"), "{e}");
    assert!(e.to_string().contains("at most 1000"), "{e}");
    // A blob that says it carries more (whatever its body) is refused by
    // its count, before its length is read.
    assert_eq!(
        SvrView::parse(&bytes, most as u32 + 1),
        Err(BlobError::OverBudget {
            field: "svr.support_vectors",
            found: most as u32 + 1,
            most: most as u32
        })
    );

    let most = MAX_HIDDEN_NEURONS as usize;
    let largest = nn_model(most, 8, OutputMode::Residual);
    let bytes = largest
        .compile()
        .expect("the largest NN the device takes compiles");
    NnView::parse(&bytes, most as u16).expect("and loads");
    assert_eq!(
        nn_model(most + 1, 8, OutputMode::Residual).compile(),
        Err(CorrectionCompileError::OverBudget {
            field: "w1",
            found: most + 1,
            most
        })
    );
    let e = NnView::parse(&bytes, most as u16 + 1).unwrap_err();
    assert_eq!(
        e,
        BlobError::OverBudget {
            field: "nn.hidden",
            found: most as u32 + 1,
            most: most as u32
        }
    );
    assert!(e.to_string().contains("`nn.hidden` is 401"), "{e}");
}
