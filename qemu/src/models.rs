//! Host only (`build.rs`): the deterministic calibrations whose compiled blobs
//! the device binaries embed. Both have the 2.2 m cube frame, a quadratic
//! winding law with a layer table per string and one effect term of every family (14: 10 of one
//! string, 4 shared); one carries an
//! NN 3-20-3 correction, the other an RBF SVR with 1,000 support vectors (the
//! issue's benchmark sizes). Weights are shaped like trained ones (see
//! `spidar_core::correction`'s tests): realistic magnitudes, random values.
//! Two more use 4 of the 8 channels (issue 11): a 4-line cable robot in
//! space and a planar device, both with the NN. Every one carries the most
//! training slips a blob takes (issue 33, point 1), one per string, under
//! [`TRAINING_HOME_ID`]: the benchmark device's first home capture, so that
//! `Device::tick` is measured applying them.

/// The home capture of the models' training slips: the benchmark device's
/// first (boot id 1, first capture).
pub const TRAINING_HOME_ID: u64 = 1 << 32 | 1;

use spidar_core::correction::{CorrectionModel, NnModel, OutputMode, Standardization, SvrModel};
use spidar_core::model::{
    Calibration, Effect, EffectTerm, Frame, HomeSlips, Knots, LayerTable, StringLaw, StringLayout, EVERY_STRING,
    LAYER_KNOTS, MAX_HOME_SLIPS,
};
use spidar_core::STRINGS;

use crate::cases::Rng;

/// Hidden neurons of the benchmark NN.
pub const NN_HIDDEN: usize = 20;
/// Support vectors of the benchmark SVR: the most a blob may carry, so that
/// the tick is measured with the largest correction the device takes.
pub const SVR_SUPPORT: usize = spidar_core::correction::MAX_SUPPORT_VECTORS as usize;

fn normal(rng: &mut Rng) -> f64 {
    // Box-Muller; host only, the blob (not this) is what both sides share.
    let u1 = rng.f64_in(1e-12, 1.0);
    let u2 = rng.f64_in(0.0, 1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn input_std() -> Standardization {
    Standardization { mean: [3.2, -7.9, 11.4], std: [288.1, 291.7, 286.9] }
}

fn output_std() -> Standardization {
    Standardization { mean: [1.9, -4.3, 8.8], std: [301.3, 297.8, 305.2] }
}

fn calibration(correction: CorrectionModel) -> Calibration {
    let h = 1100.0;
    let mut anchors = [[0.0; 3]; STRINGS];
    for (i, a) in anchors.iter_mut().enumerate() {
        *a = [if i & 1 == 0 { -h } else { h }, if i & 2 == 0 { -h } else { h }, if i & 4 == 0 { -h } else { h }];
    }
    let effects = vec![
        EffectTerm { string: 0, effect: Effect::Offset { mm: 4.5 } },
        EffectTerm { string: 1, effect: Effect::Scale { relative: 0.003 } },
        EffectTerm { string: 2, effect: Effect::Winding { power: 3, mm_per_rad_pow: 1.5e-6 } },
        EffectTerm { string: 3, effect: Effect::Eccentricity { sin_mm: 0.12, cos_mm: -0.05 } },
        EffectTerm { string: 4, effect: Effect::Elasticity { per_newton: 2e-4 } },
        EffectTerm { string: 5, effect: Effect::Backlash { half_width_mm: 0.7 } },
        EffectTerm { string: 6, effect: Effect::Drift { mm_per_s: 1e-4 } },
        EffectTerm { string: 7, effect: Effect::Slip { at_s: 600.0, mm: 1.2 } },
        // A heavy string's sag (issue 10, heavy-string).
        EffectTerm { string: 4, effect: Effect::Sag { mm_at_1m_1n: 1.6, home_mm_at_1m: 1.32 } },
        // One drift shared by every string (issue 10, point 4).
        EffectTerm { string: EVERY_STRING, effect: Effect::Drift { mm_per_s: 3e-5 } },
        // Strings of one kind stretching from their spools (issue 10).
        EffectTerm {
            string: EVERY_STRING,
            effect: Effect::Stretch { per_newton: 6e-5, mm_per_newton: 0.02, home_tension_n: 1.1 },
        },
        // A frame that flexes under the strings' total pull (issue 10).
        EffectTerm { string: EVERY_STRING, effect: Effect::FrameFlex { mm_per_newton: 0.012, home_mm: 0.1 } },
        // An encoder read 6 ms late, and the loop's shared delay (issue 33).
        EffectTerm { string: 2, effect: Effect::Latency { latency_s: 0.006 } },
        EffectTerm { string: EVERY_STRING, effect: Effect::Latency { latency_s: 0.0015 } },
        // A 12 mm guide pulley on one string, and guides of one radius on
        // every string (issue 33).
        EffectTerm { string: 1, effect: Effect::Guide { radius_mm: 12.0 } },
        EffectTerm { string: EVERY_STRING, effect: Effect::Guide { radius_mm: 8.5 } },
        // Creep: one string's natural length growing 1,000 ppm an hour, and
        // every string's 300 ppm an hour (issue 33).
        EffectTerm { string: 3, effect: Effect::Creep { per_s: 2.8e-7 } },
        EffectTerm { string: EVERY_STRING, effect: Effect::Creep { per_s: 8.3e-8 } },
    ];
    Calibration {
        frame: Frame {
            layout: StringLayout::ALL,
            anchors,
            home: [1.0, -2.0, 3.0],
            room_rotation: [[0.9998, -0.0175, 0.0], [0.0175, 0.9998, 0.0], [0.0, 0.0, 1.0]],
            room_translation: [12.0, -40.0, 1500.0],
            room_scale: 1.001,
        },
        strings: core::array::from_fn(layered_law),
        effects,
        correction,
        // Uneven measured scales: the forward kinematics weighs strings 3 and
        // 5 less (weights 1/3 and 2/3 of the others').
        length_scale_mm: [0.2, 0.2, 0.2, 0.6, 0.2, 0.3, 0.2, 0.2],
        kinematics: Default::default(),
        home: Some(home_slips(|k| k as u8)),
    }
}

/// [`spidar_core::model::MAX_HOME_SLIPS`] training slips under
/// [`TRAINING_HOME_ID`], slip `k` on string `string(k)`: half of them from
/// the home capture on, the others 2 ms to 1 s after it (the cases' times
/// reach an hour), of -3 to +3.5 mm.
fn home_slips(string: impl Fn(usize) -> u8) -> HomeSlips {
    HomeSlips {
        home_id: TRAINING_HOME_ID,
        slips: (0..MAX_HOME_SLIPS)
            .map(|k| EffectTerm {
                string: string(k),
                effect: Effect::Slip {
                    at_s: if k % 2 == 0 { 0.0 } else { [0.002, 0.4, 1.0, 0.25][k / 2 % 4] },
                    mm: -3.0 + 0.93 * k as f64,
                },
            })
            .collect(),
    }
}

/// String `i`'s law: the quadratic plus a layer table (issue 10) of 32 knots
/// 4096 or 8192 counts apart that starts inside the cases' +-30 turns, so
/// that the cases read its interpolation, its start and its held end.
fn layered_law(i: usize) -> StringLaw {
    let mut law = StringLaw::polynomial(4096, [12.0, -0.004, 0.0, 0.0]);
    let knots: Vec<f64> = (0..LAYER_KNOTS).map(|k| 0.8 * (0.9 * k as f64 + i as f64).sin()).collect();
    law.layers = LayerTable {
        start_counts: -30 * 4096 + 2000 * i as i32,
        step_log2: 12 + (i % 2) as u8,
        knots_mm: Knots::from_slice(&knots).expect("LAYER_KNOTS knots"),
    };
    law
}

/// A 4-line cable robot (three low anchors, one high; channels 0..4) with
/// two effect terms per string and the NN correction: the N = 4 model.
fn four_line(correction: CorrectionModel) -> Calibration {
    let mut c = calibration(correction);
    c.frame.layout = StringLayout::first(4, false);
    c.frame.anchors = [[0.0; 3]; STRINGS];
    for (i, a) in crate::cases::FOUR_LINE_ANCHORS.iter().enumerate() {
        c.frame.anchors[i] = a.map(f64::from);
    }
    c.frame.home = [10.0, -20.0, 300.0];
    for (k, t) in c.effects.iter_mut().enumerate().filter(|(_, t)| t.string != EVERY_STRING) {
        t.string = (k % 4) as u8;
    }
    c.home = Some(home_slips(|k| (k % 4) as u8));
    c
}

/// A planar SPIDAR: 4 strings at the corners of a 1.6 m x 1.2 m frame in
/// the plane z = 25 mm, on channels 0, 2, 5, 7 (the others unused), one or
/// two effect terms per string and the NN correction.
fn planar(correction: CorrectionModel) -> Calibration {
    let mut c = calibration(correction);
    c.frame.layout = StringLayout { active: crate::cases::PLANAR_ACTIVE, planar: true };
    c.frame.anchors = [[0.0; 3]; STRINGS];
    let channels = [0usize, 2, 5, 7];
    for (k, a) in crate::cases::PLANAR_ANCHORS.iter().enumerate() {
        c.frame.anchors[channels[k]] = a.map(f64::from);
    }
    c.frame.home = [10.0, -20.0, 25.0];
    for (k, t) in c.effects.iter_mut().enumerate() {
        t.string = channels[k % 4] as u8;
    }
    c.home = Some(home_slips(|k| channels[k % 4] as u8));
    c
}

fn nn_model() -> NnModel {
    let mut rng = Rng::new(0x4E4E);
    let (mut w1, mut b1) = (Vec::new(), Vec::new());
    let mut w2: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for h in 0..NN_HIDDEN {
        if h % 2 == 1 {
            // Pairs of close neurons with opposite output weights, as LM training makes.
            let prev: [f64; 3] = w1[h - 1];
            w1.push(prev.map(|v| v * (1.0 + 0.08 * normal(&mut rng))));
            b1.push(b1[h - 1] + 0.1 * normal(&mut rng));
            for w in w2.iter_mut() {
                let prev = w[h - 1];
                w.push(-prev * (1.0 + 0.05 * normal(&mut rng)));
            }
        } else {
            w1.push([1.5 * normal(&mut rng), 1.5 * normal(&mut rng), 1.5 * normal(&mut rng)]);
            b1.push(rng.f64_in(-1.5, 1.5));
            for w in w2.iter_mut() {
                w.push(rng.f64_in(-12.0, 12.0));
            }
        }
    }
    let out = output_std();
    for (a, w) in w2.iter_mut().enumerate() {
        let s: f64 = w.iter().map(|v| v.abs()).sum::<f64>() * out.std[a];
        w.iter_mut().for_each(|v| *v *= 37_000.0 / s);
    }
    NnModel { input: input_std(), output: out, w1, b1, w2, b2: [0.03, -0.02, 0.05], mode: OutputMode::Residual }
}

fn svr_model() -> SvrModel {
    let mut rng = Rng::new(0x5356);
    let lim = 500.0 / 288.7;
    let support = (0..SVR_SUPPORT).map(|_| [0; 3].map(|_: i32| rng.f64_in(-lim, lim))).collect();
    let mut coef: [Vec<f64>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for c in coef.iter_mut() {
        *c = (0..SVR_SUPPORT).map(|_| rng.f64_in(-1.0, 1.0)).collect();
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
        mode: OutputMode::Residual,
    }
}

fn compile(c: &Calibration, id: u32) -> Vec<u8> {
    spidar_core::blob::compile(c, id, 0)
        .unwrap_or_else(|e| panic!("benchmark calibration {id} does not compile: {e:?}"))
}

/// The compiled blob with the NN 3-20-3 correction.
pub fn nn_blob() -> Vec<u8> {
    compile(&calibration(CorrectionModel::Nn(nn_model())), 1)
}

/// The compiled blob with the 1,000-SV SVR correction.
pub fn svr_blob() -> Vec<u8> {
    compile(&calibration(CorrectionModel::Svr(svr_model())), 2)
}

/// The compiled N = 4 blob (4-line cable robot, NN 3-20-3).
pub fn four_line_blob() -> Vec<u8> {
    compile(&four_line(CorrectionModel::Nn(nn_model())), 3)
}

/// The compiled planar N = 4 blob (NN 3-20-3).
pub fn planar_blob() -> Vec<u8> {
    compile(&planar(CorrectionModel::Nn(nn_model())), 4)
}

/// The tick's cost model (`spidar_core::tick_cost`): what a tick costs with
/// the benchmark's frame and layered laws and nothing else (`bare`: no
/// effect term, no slip, no correction), and what each family of effect
/// terms and the training slips add to it. One model per line: the bare
/// one; the bare one with the benchmark model's term of a family on each of
/// the 8 strings, or as one term every string shares (the families that
/// take it); with the most training slips a blob takes. Names and blobs.
pub fn cost_models() -> Vec<(String, Vec<u8>)> {
    let mut bare = calibration(CorrectionModel::None);
    let terms = std::mem::take(&mut bare.effects);
    bare.home = None;
    let named = |what: &str| format!("tick cost, Controller::step: {what}");
    let mut out = vec![(named("bare model"), compile(&bare, 100))];
    let mut seen: Vec<String> = Vec::new();
    for term in &terms {
        let debug = format!("{:?}", term.effect);
        let family = debug.split([' ', '{']).next().unwrap_or("?").to_string();
        if seen.contains(&family) {
            continue;
        }
        seen.push(family.clone());
        // A family that does not take a shared term (or one per string)
        // does not compile so: that line is left out.
        let on = |strings: Vec<u8>, id: usize| {
            let mut c = bare.clone();
            c.effects = strings.into_iter().map(|string| EffectTerm { string, effect: term.effect }).collect();
            spidar_core::blob::compile(&c, 100 + id as u32, 0).ok()
        };
        if let Some(blob) = on((0..STRINGS as u8).collect(), out.len()) {
            out.push((named(&format!("{family} on each of 8 strings")), blob));
        }
        if let Some(blob) = on(vec![EVERY_STRING], out.len()) {
            out.push((named(&format!("{family} shared")), blob));
        }
    }
    let mut slips = bare.clone();
    slips.home = Some(home_slips(|k| k as u8));
    out.push((named(&format!("{MAX_HOME_SLIPS} training slips")), compile(&slips, 99)));
    out
}
