//! The wall robot: `calibrate`'s stage table, and a plain least-squares fit
//! beside it.

use super::runs::{run_calibration, Run};
use super::table::three;
use spidar::data::dataset::Session;
use spidar::data::observe::observations;
use spidar::data::observe::Observation;
use spidar::data::stats::{position_error, ErrorStats};
use spidar::procedures::calibrate::align::{repaired_at, tracked_interval_s, SessionTiming};
use spidar::procedures::calibrate::CalibrateConfig;
use spidar::sim::physics::{self, PhysicsConfig, PhysicsDevice};
use spidar::sim::{SessionKind, StreamArea};

/// The wall robot's parameters in a plain least-squares fit: per string
/// the anchor (x, y) and the effective radius, then home (x, y) and the
/// tracker's yaw and translation (x, y): `p_room = R(yaw) p + t` in the plane.
struct PlainModel {
    anchors: Vec<[f64; 2]>,
    radii: Vec<f64>,
    home: [f64; 2],
    yaw: f64,
    translation: [f64; 2],
}

impl PlainModel {
    fn of(x: &[f64], n: usize) -> PlainModel {
        PlainModel {
            anchors: (0..n).map(|i| [x[2 * i], x[2 * i + 1]]).collect(),
            radii: x[2 * n..3 * n].to_vec(),
            home: [x[3 * n], x[3 * n + 1]],
            yaw: x[3 * n + 2],
            translation: [x[3 * n + 3], x[3 * n + 4]],
        }
    }

    /// The device-plane position of a room position.
    fn device_of(&self, room: &[f64; 3]) -> [f64; 2] {
        let (s, c) = self.yaw.sin_cos();
        let (dx, dy) = (room[0] - self.translation[0], room[1] - self.translation[1]);
        [c * dx + s * dy, -s * dx + c * dy]
    }

    fn room_of(&self, p: &[f64; 2], plane_z: f64) -> [f64; 3] {
        let (s, c) = self.yaw.sin_cos();
        [
            c * p[0] - s * p[1] + self.translation[0],
            s * p[0] + c * p[1] + self.translation[1],
            plane_z,
        ]
    }

    /// String `i`'s length from its counts: home length + radius x angle.
    fn length(&self, i: usize, counts: i32, counts_per_rev: u32) -> f64 {
        let theta = std::f64::consts::TAU * f64::from(counts) / f64::from(counts_per_rev);
        distance2(&self.home, &self.anchors[i]) + self.radii[i] * theta
    }
}

fn distance2(a: &[f64; 2], b: &[f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// The rows of `session` paired as the calibration paired them (its
/// report's offset and drift for that session), the tracker's z put in the
/// device's plane as the calibration does (the errors are in the plane).
fn paired_rows(session: &Session, timing: &SessionTiming, plane_z: f64) -> Vec<Observation> {
    let obs = observations(&session.samples);
    let mut rows = match timing {
        SessionTiming::Aligned(a) => {
            let gap = 4.0 * tracked_interval_s(&obs).unwrap_or(0.1);
            let at = |t: f64| t + a.offset_s + 1e-6 * a.drift_ppm * (t - a.reference_t_s);
            repaired_at(&obs, at, gap).0
        }
        SessionTiming::Static { .. } | SessionTiming::Paired { .. } => obs,
    };
    for o in rows.iter_mut() {
        if let Some(t) = o.tracker.as_mut() {
            t[2] = plane_z;
        }
    }
    rows
}

/// Every string's residual (tracker geometry minus counts' length) of every
/// tracked row.
fn plain_residuals(x: &[f64], rows: &[Observation], n: usize, cpr: &[u32]) -> Vec<f64> {
    let m = PlainModel::of(x, n);
    let mut r = Vec::with_capacity(rows.len() * n);
    for o in rows {
        let Some(t) = o.tracker else { continue };
        let p = m.device_of(&t);
        for (i, (anchor, &c)) in m.anchors.iter().zip(cpr).enumerate() {
            r.push(distance2(&p, anchor) - m.length(i, o.inputs.counts[i], c));
        }
    }
    r
}

/// Unweighted Levenberg-Marquardt on the string residuals, numeric
/// Jacobian; `held` parameters stay at their start (the plane's rigid
/// motions, which the tracker's transform undoes: anchor 0's x, y and
/// anchor 1's y).
fn plain_fit(
    start: Vec<f64>,
    held: &[usize],
    rows: &[Observation],
    n: usize,
    cpr: &[u32],
) -> Vec<f64> {
    use nalgebra::{DMatrix, DVector};
    let free: Vec<usize> = (0..start.len()).filter(|k| !held.contains(k)).collect();
    let cost = |x: &[f64]| {
        plain_residuals(x, rows, n, cpr)
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
    };
    let mut x = start;
    let mut c = cost(&x);
    let mut lambda = 1e-3;
    for _ in 0..200 {
        let r = DVector::from_vec(plain_residuals(&x, rows, n, cpr));
        let mut j = DMatrix::zeros(r.len(), free.len());
        for (col, &k) in free.iter().enumerate() {
            let h = 1e-6 * x[k].abs().max(1.0);
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[k] += h;
            xm[k] -= h;
            let d = DVector::from_vec(plain_residuals(&xp, rows, n, cpr))
                - DVector::from_vec(plain_residuals(&xm, rows, n, cpr));
            j.set_column(col, &(d / (2.0 * h)));
        }
        let jtj = j.transpose() * &j;
        let g = j.transpose() * &r;
        let mut improved = false;
        while lambda < 1e12 {
            let mut a = jtj.clone();
            for k in 0..free.len() {
                a[(k, k)] += lambda * jtj[(k, k)].max(1e-12);
            }
            let Some(step) = a.lu().solve(&(-&g)) else {
                lambda *= 10.0;
                continue;
            };
            let mut trial = x.clone();
            for (col, &k) in free.iter().enumerate() {
                trial[k] += step[col];
            }
            let ct = cost(&trial);
            if ct < c {
                let settled = (c - ct) <= 1e-12 * c;
                x = trial;
                c = ct;
                lambda = (lambda / 10.0).max(1e-9);
                improved = !settled;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    x
}

/// Forward kinematics of the plain model: every tracked row placed by all
/// strings equally weighted (Gauss-Newton in the plane from the previous
/// row's position); its error against the tracker, mm.
fn plain_errors(m: &PlainModel, rows: &[Observation], cpr: &[u32], plane_z: f64) -> Vec<f64> {
    let n = m.anchors.len();
    let mut p = m.home;
    let mut errors = Vec::new();
    for o in rows {
        let lengths: Vec<f64> = (0..n)
            .map(|i| m.length(i, o.inputs.counts[i], cpr[i]))
            .collect();
        for _ in 0..50 {
            let (mut a, mut b) = ([[0.0; 2]; 2], [0.0; 2]);
            for (anchor, length) in m.anchors.iter().zip(&lengths) {
                let d = [p[0] - anchor[0], p[1] - anchor[1]];
                let l = d[0].hypot(d[1]);
                let u = [d[0] / l, d[1] / l];
                let r = l - length;
                for (row, u_row) in a.iter_mut().zip(u) {
                    row[0] += u_row * u[0];
                    row[1] += u_row * u[1];
                }
                b[0] += u[0] * r;
                b[1] += u[1] * r;
            }
            let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
            let dx = -(a[1][1] * b[0] - a[0][1] * b[1]) / det;
            let dy = -(-a[1][0] * b[0] + a[0][0] * b[1]) / det;
            p = [p[0] + dx, p[1] + dy];
            if dx.hypot(dy) < 1e-9 {
                break;
            }
        }
        if let Some(t) = o.tracker {
            errors.push(position_error(m.room_of(&p, plane_z), t));
        }
    }
    errors
}

/// The wall robot: `calibrate`'s stage table, and the plain least-squares
/// fit's held-out error beside it.
pub(super) fn wall_robot(seeds: u64, config: &CalibrateConfig) {
    let preset = PhysicsConfig::preset("wall-robot").expect("the wall-robot preset");
    let rows = preset.stream.rows;
    println!();
    println!(
        "wall robot (preset `wall-robot`): train a {rows}-row stream over the central {:.0} % of \
         each side of the workspace (seed + 3), test a {rows}-row stream over the whole of it \
         (seed + 4); tracker clock {} s ahead; held-out mean / p95 / max, mm",
        100.0 * preset.stream.training_span,
        preset.tracker.clock_offset_s
    );
    for seed in 1..=seeds {
        let device = PhysicsDevice::new(&preset, seed).expect("wall robot");
        let stream = |area, session_seed| {
            physics::simulate_session(&device, SessionKind::Stream { rows, area }, session_seed)
                .expect("stream")
                .0
        };
        let run = Run {
            geometry: device.nominal.clone(),
            train: stream(StreamArea::Training, seed + 3),
            test: stream(StreamArea::Whole, seed + 4),
        };
        let c = run_calibration(&run, config);
        let offset = |t: &SessionTiming| match t {
            SessionTiming::Aligned(a) => {
                format!("{:+.4} s (sd {:.1} ms)", a.offset_s, 1e3 * a.offset_sd_s)
            }
            SessionTiming::Static { .. } => "static".to_string(),
            SessionTiming::Paired { .. } => "paired".to_string(),
        };
        println!();
        println!(
            "seed {seed}: clock offset found, train {}, test {}",
            offset(&c.report.timing.train),
            offset(&c.report.timing.test)
        );
        println!();
        println!("| stage | train mean / p95 / max | held-out mean / p95 / max |");
        println!("|---|---|---|");
        for s in &c.report.stages {
            println!("| {} | {} | {} |", s.name, three(&s.train), three(&s.test));
        }

        let n = device.string_count();
        let nominal = device.nominal.nominal_frame();
        let plane_z = nominal.room_translation[2] + nominal.anchors[0][2];
        let cpr = device.nominal.counts_per_rev[..n].to_vec();
        let train = paired_rows(&run.train, &c.report.timing.train, plane_z);
        let test = paired_rows(&run.test, &c.report.timing.test, plane_z);
        let g = &device.nominal;
        let mut start: Vec<f64> = (0..n)
            .flat_map(|i| [g.anchors_mm[i][0], g.anchors_mm[i][1]])
            .collect();
        start.extend((0..n).map(|i| g.pulley_radius_mm[i]));
        start.extend([g.home_mm[0], g.home_mm[1], 0.0]);
        start.extend([
            g.room_from_device_translation_mm[0],
            g.room_from_device_translation_mm[1],
        ]);
        let x = plain_fit(start, &[0, 1, 3], &train, n, &cpr);
        let m = PlainModel::of(&x, n);
        let fit = ErrorStats::of(&plain_errors(&m, &train, &cpr, plane_z));
        let held_out = ErrorStats::of(&plain_errors(&m, &test, &cpr, plane_z));
        println!(
            "| plain least squares (this bench) | {} | {} |",
            three(&fit),
            three(&held_out)
        );
        println!();
        println!(
            "plain fit: radii {} mm (nominal {} mm); rows train {} / test {} (paired by the \
             report's offsets)",
            m.radii
                .iter()
                .map(|r| format!("{r:.3}"))
                .collect::<Vec<_>>()
                .join(", "),
            g.pulley_radius_mm[0],
            fit.n,
            held_out.n
        );
        let last = c.report.stages.last().expect("final stage");
        println!(
            "{} / plain held-out mean: {:.2}x",
            last.name,
            last.test.mean_mm / held_out.mean_mm
        );
    }
}
