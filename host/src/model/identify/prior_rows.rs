//! The prior rows of the problem: each parameter around its nominal value
//! or its start, and the gauge that pins the anchors' centroid and mean
//! orientation.

use spidar_core::geometry::{cross, mat_mul, sub, transpose, vector_from_rotation};
use spidar_core::model::StringLayout;
use spidar_core::STRINGS;

use super::layout::{State, ANCHORS, HOME, ROTATION, TRANSLATION};
use super::problem::{PriorRow, Problem};
use super::structure::{anchor_prior_sd, effect_prior, HELD_SD};

impl Problem<'_> {
    fn anchor_sd(&self, i: usize) -> f64 {
        anchor_prior_sd(self.structure, self.nominal.layout, i)
    }

    /// Prior rows: (row value, gradient over physical parameters as (column, d)).
    pub(super) fn prior_rows(&self, state: &State) -> Vec<PriorRow> {
        let mut rows = Vec::new();
        self.frame_prior_rows(state, &mut rows);
        self.winding_prior_rows(state, &mut rows);
        self.effect_prior_rows(state, &mut rows);
        self.gauge_rows(state, &mut rows);
        rows
    }

    /// The frame's priors: each anchor, the home position, the tracker's
    /// translation and rotation around nominal.
    fn frame_prior_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let p = &self.structure.priors;
        let nominal = self.nominal;
        let layout = nominal.layout;
        let held = |active: bool, sd: f64| if active { sd } else { HELD_SD };
        for i in 0..STRINGS {
            for c in 0..3 {
                let sd = if layout.planar && c == 2 {
                    HELD_SD
                } else {
                    self.anchor_sd(i)
                };
                rows.push((
                    (state.frame.anchors[i][c] - nominal.anchors[i][c]) / sd,
                    vec![(ANCHORS + 3 * i + c, 1.0 / sd)],
                ));
            }
        }
        for c in 0..3 {
            let in_plane = !(layout.planar && c == 2);
            let sd = held(in_plane, p.home_sd_mm);
            rows.push((
                (state.frame.home[c] - nominal.home[c]) / sd,
                vec![(HOME + c, 1.0 / sd)],
            ));
            let sd = held(in_plane, p.translation_sd_mm);
            rows.push((
                (state.frame.room_translation[c] - nominal.room_translation[c]) / sd,
                vec![(TRANSLATION + c, 1.0 / sd)],
            ));
        }
        let total_rotation = vector_from_rotation(&mat_mul(
            &transpose(&nominal.room_rotation),
            &state.frame.room_rotation,
        ));
        for c in 0..3 {
            // A planar device's tracker frame turns about z only.
            let sd = held(!(layout.planar && c < 2), p.rotation_sd_rad);
            rows.push((total_rotation[c] / sd, vec![(ROTATION + c, 1.0 / sd)]));
        }
    }

    /// The winding's priors: the radius of a channel without a string, each
    /// spool's own thinning rate and their mean.
    fn winding_prior_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let p = &self.structure.priors;
        let layout = self.nominal.layout;
        // Channels without a string: their winding radius stays nominal.
        for i in (0..STRINGS).filter(|&i| !layout.is_active(i)) {
            let col = self.layout.r_home() + i;
            let s = self.layout.scale[col];
            rows.push((
                (state.winding.r_home_mm[i] - self.winding_fixed.r_home_mm[i]) / s,
                vec![(col, 1.0 / s)],
            ));
        }
        // Each spool's own thinning rate: a prior around the shared one on
        // active channels, held at 0 on the others, and their mean held at
        // 0 (the shared rate carries it); or all held at the start's.
        let hold = self.structure.hold_kappa_each;
        for i in 0..STRINGS {
            let col = self.layout.kappa_each() + i;
            let (centre, sd) = if hold {
                (
                    self.winding_fixed.kappa_each_mm[i],
                    1e-3 * self.layout.scale[col],
                )
            } else if layout.is_active(i) {
                (0.0, p.kappa_each_sd_mm)
            } else {
                (0.0, self.layout.scale[col])
            };
            rows.push((
                (state.winding.kappa_each_mm[i] - centre) / sd,
                vec![(col, 1.0 / sd)],
            ));
        }
        if !hold {
            const KAPPA_GAUGE_SD: f64 = 1e-6;
            let n = layout.count().max(1) as f64;
            let mean = layout
                .indices()
                .map(|i| state.winding.kappa_each_mm[i])
                .sum::<f64>()
                / n;
            rows.push((
                mean / KAPPA_GAUGE_SD,
                layout
                    .indices()
                    .map(|i| (self.layout.kappa_each() + i, 1.0 / (n * KAPPA_GAUGE_SD)))
                    .collect(),
            ));
        }
    }

    /// Effect parameters with a prior.
    fn effect_prior_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let p = &self.structure.priors;
        for (c, &(e, pi)) in self.layout.effect_columns.iter().enumerate() {
            let effect = &state.effects[e].effect;
            if let (Some((centre, sd)), Some(&value)) =
                (effect_prior(effect, pi, p), effect.parameters().get(pi))
            {
                rows.push((
                    (value - centre) / sd,
                    vec![(self.layout.first_effect() + c, 1.0 / sd)],
                ));
            }
        }
    }

    /// Gauge: the active anchors' centroid and mean orientation stay
    /// nominal (in the plane: the orientation about z only).
    fn gauge_rows(&self, state: &State, rows: &mut Vec<PriorRow>) {
        let nominal = self.nominal;
        let layout = nominal.layout;
        const GAUGE_SD_MM: f64 = 0.01;
        let n_active = layout.count() as f64;
        let centroid_nominal = centroid(&nominal.anchors, layout);
        let centroid_now = centroid(&state.frame.anchors, layout);
        for c in 0..3 {
            let grad = layout
                .indices()
                .map(|i| (ANCHORS + 3 * i + c, 1.0 / (n_active * GAUGE_SD_MM)))
                .collect();
            rows.push(((centroid_now[c] - centroid_nominal[c]) / GAUGE_SD_MM, grad));
        }
        let spread: f64 = layout
            .indices()
            .map(|i| {
                let d = sub(nominal.anchors[i], centroid_nominal);
                d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            })
            .sum();
        // Small-rotation gauge: sum_i (a0_i - c0) x (a_i - a0_i) / spread = 0.
        let mut value = [0.0; 3];
        let mut grads: [Vec<(usize, f64)>; 3] = Default::default();
        for i in layout.indices() {
            let r = sub(nominal.anchors[i], centroid_nominal);
            let d = sub(state.frame.anchors[i], nominal.anchors[i]);
            let x = cross(r, d);
            for c in 0..3 {
                value[c] += x[c] / spread;
            }
            // d(r x d)/dd = [r]x
            let rx = [[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]];
            for c in 0..3 {
                for k in 0..3 {
                    if rx[c][k] != 0.0 {
                        grads[c].push((ANCHORS + 3 * i + k, rx[c][k] / spread));
                    }
                }
            }
        }
        // Angle tolerance equivalent to GAUGE_SD_MM at the frame's size.
        let angle_sd = GAUGE_SD_MM / (spread / n_active).sqrt();
        // In the plane, rotations about x and y are held by the anchors' z
        // already; only the one about z is a gauge freedom.
        let gauge_axes = if layout.planar { 2..3 } else { 0..3 };
        for c in gauge_axes {
            let g = grads[c].iter().map(|&(j, d)| (j, d / angle_sd)).collect();
            rows.push((value[c] / angle_sd, g));
        }
    }
}

fn centroid(points: &[[f64; 3]; STRINGS], layout: StringLayout) -> [f64; 3] {
    let n = layout.count().max(1) as f64;
    let mut c = [0.0; 3];
    for i in layout.indices() {
        for k in 0..3 {
            c[k] += points[i][k] / n;
        }
    }
    c
}
