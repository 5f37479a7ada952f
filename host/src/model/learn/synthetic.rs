//! A smooth synthetic distortion field over a cube, for tests and benchmarks
//! of the learners (no device or simulator needed).
//!
//! The device reports `p`; the tracker sees `p + field(p) + noise`. The field
//! reaches a few tens of mm inside a 1 m cube and mixes periodic and
//! polynomial terms so neither learner fits it exactly.

use super::Rng;

/// Pairs of (device position, tracker position), mm.
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    pub inputs: Vec<[f64; 3]>,
    pub targets: Vec<[f64; 3]>,
}

impl Dataset {
    /// Write `x,y,z,tx,ty,tz` rows with a header (the reference script's format).
    pub fn to_csv(&self) -> String {
        let mut s = String::from("x,y,z,tx,ty,tz\n");
        for (p, t) in self.inputs.iter().zip(&self.targets) {
            s.push_str(&format!(
                "{:.9},{:.9},{:.9},{:.9},{:.9},{:.9}\n",
                p[0], p[1], p[2], t[0], t[1], t[2]
            ));
        }
        s
    }
}

/// The distortion (tracker minus device) at device position `p`, mm, for a
/// cube of half-size `half` mm centred on the origin, scaled by `amplitude`.
pub fn field(p: &[f64; 3], half: f64, amplitude: f64) -> [f64; 3] {
    let u = [p[0] / half, p[1] / half, p[2] / half];
    let dx = 30.0 * (1.3 * u[1] + 0.5).sin() * (0.9 * u[2]).cos()
        + 15.0 * u[0] * u[0]
        + 10.0 * u[0] * u[1];
    let dy = 25.0 * (1.1 * u[0] - 0.3).cos() * (1.2 * u[2]).sin() + 12.0 * u[1] * u[2] - 8.0;
    let dz = 20.0 * (1.5 * u[0] + u[1]).sin() + 15.0 * u[2] * u[2] * u[2] + 10.0 * u[1] * u[1];
    [amplitude * dx, amplitude * dy, amplitude * dz]
}

fn observe(p: [f64; 3], half: f64, amplitude: f64, noise: f64, rng: &mut Rng) -> [f64; 3] {
    let d = field(&p, half, amplitude);
    [
        p[0] + d[0] + noise * rng.normal(),
        p[1] + d[1] + noise * rng.normal(),
        p[2] + d[2] + noise * rng.normal(),
    ]
}

/// `per_axis^3` lattice points over `[-half, half]^3` (the paper's protocol
/// uses 13^3 = 2197 cells over 1 m^3), Gaussian tracker noise `noise_mm` (sd
/// per axis).
pub fn lattice(per_axis: usize, half: f64, amplitude: f64, noise_mm: f64, seed: u64) -> Dataset {
    let mut rng = Rng::new(seed);
    let step = if per_axis > 1 {
        2.0 * half / (per_axis - 1) as f64
    } else {
        0.0
    };
    let mut inputs = Vec::with_capacity(per_axis.pow(3));
    let mut targets = Vec::with_capacity(per_axis.pow(3));
    for i in 0..per_axis {
        for j in 0..per_axis {
            for k in 0..per_axis {
                let p = [
                    -half + step * i as f64,
                    -half + step * j as f64,
                    -half + step * k as f64,
                ];
                targets.push(observe(p, half, amplitude, noise_mm, &mut rng));
                inputs.push(p);
            }
        }
    }
    Dataset { inputs, targets }
}

/// `n` uniform random points in the cube, same field and noise.
pub fn random(n: usize, half: f64, amplitude: f64, noise_mm: f64, seed: u64) -> Dataset {
    let mut rng = Rng::new(seed);
    let mut inputs = Vec::with_capacity(n);
    let mut targets = Vec::with_capacity(n);
    for _ in 0..n {
        let p = [
            rng.range(-half, half),
            rng.range(-half, half),
            rng.range(-half, half),
        ];
        targets.push(observe(p, half, amplitude, noise_mm, &mut rng));
        inputs.push(p);
    }
    Dataset { inputs, targets }
}
