//! What the identified model misses on the clean independent devices: its
//! string residuals against the physics' variables, its error beyond the
//! training volume.

use super::cases::CleanPhysics;
use super::runs::{model_run, run_calibration, Run, TEST_POINTS};
use super::table::three;
use spidar::data::dataset::Session;
use spidar::data::observe::observations;
use spidar::data::stats::{position_error, ErrorStats};
use spidar::model::identify::inputs_at;
use spidar::procedures::calibrate::{CalibrateConfig, Calibrated};
use spidar::sim::physics::{self, PhysicsDevice, PhysicsTruth};
use spidar::sim::{simulate_session, SessionKind, SimConfig, SimulatedDevice};
use spidar_core::geometry::device_from_room;
use spidar_core::string_law::string_lengths_f64;
use spidar_core::STRINGS;

/// Spread (max - min) of the bin means of `r` in 8 quantile bins of `x`.
fn bin_spread(x: &[f64], r: &[f64]) -> f64 {
    let mut idx: Vec<usize> = (0..x.len()).collect();
    idx.sort_by(|&a, &b| x[a].total_cmp(&x[b]));
    let bins = 8;
    let means: Vec<f64> = (0..bins)
        .map(|b| {
            let part = &idx[b * idx.len() / bins..(b + 1) * idx.len() / bins];
            part.iter().map(|&i| r[i]).sum::<f64>() / part.len().max(1) as f64
        })
        .collect();
    means.iter().cloned().fold(f64::MIN, f64::max) - means.iter().cloned().fold(f64::MAX, f64::min)
}

/// String residuals of the final identified model (no correction) on the
/// training lattice, against the physics' own variables.
pub(super) fn residual_analysis(
    device: &PhysicsDevice,
    run: &Run,
    truths: &[PhysicsTruth],
    c: &Calibrated,
) {
    let cal = &c.calibration;
    let obs = observations(&run.train.samples);
    println!(
        "| string | rms | vs payout | vs layer phase | vs tension | vs free length | vs exit travel | vs time | arc + sag range |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for i in 0..STRINGS {
        let (mut r, mut payout, mut phase, mut tension, mut free, mut exit, mut time, mut sag) = (
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
            vec![],
        );
        let spool = device.spool(i);
        let changes = spool.layer_changes_rad();
        let home_exit = truths[0].exit_mm[i];
        for (o, t) in obs.iter().zip(truths) {
            let Some(tracker) = o.tracker else { continue };
            if t.abnormal {
                continue;
            }
            let p = device_from_room(&cal.frame, tracker);
            let inputs = inputs_at(&cal.frame, o, &p);
            let lengths = string_lengths_f64(&cal.frame, &cal.strings, &cal.effects, &inputs);
            let a = cal.frame.anchors[i];
            let geometric = position_error(p, a);
            let res = geometric - lengths[i];
            if res.abs() > 25.0 {
                continue; // gross (the abnormal motor)
            }
            r.push(res);
            payout.push(f64::from(o.inputs.counts[i]));
            // Where in its layer the spool is: 0 at a layer change, 1 at the next.
            let phi = t.spool_rad[i];
            let k = changes.partition_point(|c| *c <= phi);
            let lo = if k == 0 { 0.0 } else { changes[k - 1] };
            let hi = changes.get(k).copied().unwrap_or(spool.max_angle_rad());
            phase.push((phi - lo) / (hi - lo));
            tension.push(o.tension_n[i]);
            free.push(t.free_mm[i]);
            exit.push(position_error(t.exit_mm[i], home_exit));
            time.push(o.t_s);
            let chord = t.free_mm[i];
            sag.push(t.geometric_mm[i] - chord);
        }
        let rms = (r.iter().map(|x| x * x).sum::<f64>() / r.len() as f64).sqrt();
        let sag_range = sag.iter().cloned().fold(f64::MIN, f64::max)
            - sag.iter().cloned().fold(f64::MAX, f64::min);
        println!(
            "| {i} | {rms:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.1} |",
            bin_spread(&payout, &r),
            bin_spread(&phase, &r),
            bin_spread(&tension, &r),
            bin_spread(&free, &r),
            bin_spread(&exit, &r),
            bin_spread(&time, &r),
            sag_range
        );
    }
}

/// Error of the final model on random points of a 1.2 m cube around the
/// 1 m training lattice: inside the training cube and outside it.
fn extrapolation(
    c: &Calibrated,
    test: &Session,
    centre: [f64; 3],
    half: f64,
) -> (ErrorStats, ErrorStats) {
    let cal = &c.calibration;
    let obs = observations(&test.samples);
    let model = spidar::model::predict::KinematicModel::of(cal);
    let predicted = spidar::model::predict::predict(model, &obs);
    let (mut inside, mut outside) = (vec![], vec![]);
    for (o, p) in obs.iter().zip(&predicted) {
        let Some(t) = o.tracker else { continue };
        let room = cal.correction.evaluate(p.room);
        let e = position_error(room, t);
        if (0..3).all(|k| (t[k] - centre[k]).abs() <= half) {
            inside.push(e);
        } else {
            outside.push(e);
        }
    }
    (ErrorStats::of(&inside), ErrorStats::of(&outside))
}

/// Trained on the 1 m lattice, tested on a 1.2 m cube: the error inside and
/// outside the training volume, on both simulators.
pub(super) fn print_extrapolation(
    seeds: u64,
    config: &CalibrateConfig,
    clean_physics: &[CleanPhysics],
) {
    println!();
    println!("extrapolation: trained on the 1 m lattice, tested on 500 random points of a 1.2 m cube (final model)");
    println!();
    println!("| simulator | seed | inside the training cube: mean / p95 / max (n) | outside: mean / p95 / max (n) |");
    println!("|---|---:|---|---|");
    for seed in 1..=seeds {
        // Model simulator.
        let run = model_run(seed, &[], false);
        let c = run_calibration(&run, config);
        let mut wide = SimConfig::default();
        wide.lattice.size_mm = 1200.0;
        let device = SimulatedDevice::new(&wide, seed).expect("model device");
        let test = simulate_session(
            &device,
            SessionKind::Random {
                points: TEST_POINTS,
            },
            seed + 2,
        )
        .expect("wide test");
        let centre = device.volume_centre_room();
        let (i, o) = extrapolation(&c, &test, centre, 500.0);
        println!(
            "| model | {seed} | {} ({}) | {} ({}) |",
            three(&i),
            i.n,
            three(&o),
            o.n
        );
    }
    for (device, _, _, c) in clean_physics {
        let mut wide = device.clone();
        wide.config.lattice.size_mm = 1200.0;
        let (test, _) = physics::simulate_session(
            &wide,
            SessionKind::Random {
                points: TEST_POINTS,
            },
            device.seed + 2,
        )
        .expect("wide test");
        let centre = device.volume_centre_room();
        let (i, o) = extrapolation(c, &test, centre, 500.0);
        println!(
            "| independent | {} | {} ({}) | {} ({}) |",
            device.seed,
            three(&i),
            i.n,
            three(&o),
            o.n
        );
    }
}
