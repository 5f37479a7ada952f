//! The Hangprinter-like robot (the `hangprinter` preset): small static
//! sessions, as real cable robots are calibrated, beside the plain
//! least-squares reference stage.

use super::runs::{run_calibration, Run};
use super::table::stage_of;
use spidar::procedures::calibrate::report::StageKind;
use spidar::procedures::calibrate::CalibrateConfig;
use spidar::sim::physics::{self, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;

/// The training sessions' sizes (poses): the real robot's sessions of 12,
/// 16, 19, 25 and 31 tracked training rows (`docs/benchmarks.md`, "Real
/// data").
const TRAINING_POSES: [usize; 5] = [12, 16, 19, 25, 31];

/// The test session's poses: enough that its mean is worth comparing
/// under the camera's scatter.
const TEST_POSES: usize = 300;

/// Each seed's device, one training session of every size and one test
/// session (session seeds `seed * 1000 + poses` and `seed * 1000 + 999`):
/// the held-out means of the reference, identified and final stages, and
/// over the seeds how often the final model holds out worse than the
/// reference.
pub(super) fn hangprinter(seeds: u64, config: &CalibrateConfig) {
    let preset = PhysicsConfig::preset("hangprinter").expect("the hangprinter preset");
    let t = &preset.tracker;
    // The mean 3-D length of the camera's error: a normal's per axis, and
    // the tail's share with the sds added in quadrature.
    let mean_of = |sd: f64| 2.0 * sd * (2.0 / std::f64::consts::PI).sqrt();
    let floor = (1.0 - t.tail_share) * mean_of(t.noise_sigma_mm)
        + t.tail_share * mean_of(t.noise_sigma_mm.hypot(t.tail_sigma_mm));
    println!();
    println!(
        "Hangprinter-like robot (preset `hangprinter`): static poses spread through a {} mm cube, \
         a camera of {} mm per axis, {} of the poses {} mm more (held-out floor ~{floor:.2} mm \
         mean); test {TEST_POSES} poses; held-out mean, mm: reference / identified / final (stage)",
        preset.lattice.size_mm, t.noise_sigma_mm, t.tail_share, t.tail_sigma_mm
    );
    println!();
    println!(
        "| seed | raw | {} |",
        TRAINING_POSES.map(|n| format!("{n} poses")).join(" | ")
    );
    println!("|---:|---:|{}", "---|".repeat(TRAINING_POSES.len()));
    let mut ratios: Vec<Vec<f64>> = vec![Vec::new(); TRAINING_POSES.len()];
    // Each size's (reference, identified, final) test means, summed.
    let mut sums = vec![[0.0f64; 3]; TRAINING_POSES.len()];
    for seed in 1..=seeds {
        let device = PhysicsDevice::new(&preset, seed).expect("hangprinter");
        let poses = |points, session_seed| {
            physics::simulate_session(&device, SessionKind::Random { points }, session_seed)
                .expect("poses")
                .0
        };
        let test = poses(TEST_POSES, seed * 1000 + 999);
        let mut cells = Vec::new();
        let mut raw = f64::NAN;
        for (k, &n) in TRAINING_POSES.iter().enumerate() {
            let run = Run {
                geometry: device.nominal.clone(),
                train: poses(n, seed * 1000 + n as u64),
                test: test.clone(),
            };
            let c = run_calibration(&run, config);
            let mean = |kind| stage_of(&c, kind).test.mean_mm;
            let (reference, fin) = (mean(StageKind::Reference), mean(StageKind::Final));
            raw = mean(StageKind::Raw);
            ratios[k].push(fin / reference);
            let identified = mean(StageKind::Identified);
            for (sum, x) in sums[k].iter_mut().zip([reference, identified, fin]) {
                *sum += x;
            }
            let chosen = &stage_of(&c, StageKind::Final).name;
            cells.push(format!(
                "{reference:.3} / {identified:.3} / **{fin:.3}** ({})",
                chosen.trim_start_matches("final ").trim_matches(['(', ')'])
            ));
        }
        println!("| {seed} | {raw:.2} | {} |", cells.join(" | "));
    }
    let over: Vec<String> = ratios
        .iter()
        .map(|r| {
            let worse = r.iter().filter(|&&x| x > 1.0).count();
            let mean = r.iter().sum::<f64>() / r.len() as f64;
            let worst = r.iter().copied().fold(f64::NAN, f64::max);
            format!("{mean:.3}, worst {worst:.3}, {worse} of {} worse", r.len())
        })
        .collect();
    let means: Vec<String> = sums
        .iter()
        .map(|[r, i, f]| {
            let n = seeds as f64;
            format!("{:.3} / {:.3} / **{:.3}**", r / n, i / n, f / n)
        })
        .collect();
    println!("| mean | | {} |", means.join(" | "));
    println!("| final / reference | | {} |", over.join(" | "));
}
