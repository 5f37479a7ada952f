//! The problem's Jacobian: each string residual's row on its own and the
//! shared columns (analytic), the prior rows, their sum into the normal
//! equations; and the data Jacobian diagnosis projects candidate effects on.

use nalgebra::{DMatrix, DVector};
use spidar_core::geometry::{cross, distance, mat_vec, sub};
use spidar_core::model::{Effect, EffectTerm, Frame, StringLaw, EVERY_STRING};
use spidar_core::string_law::{
    sag_home_slope, sag_slope, total_tension_n, EffectContext, StringHome,
};
use spidar_core::STRINGS;

use super::layout::{encode, Layout, State, HOME, ROTATION, TRANSLATION};
use super::problem::Problem;
use super::residuals::{device_position, inputs_for, GROSS_RESIDUAL_MM};
use super::result::Identification;
use super::structure::Structure;
use super::winding::WindingPhysics;
use crate::data::observe::Observation;
use crate::model::normal::{BlockSums, NormalEquations, SpareBuffers, BLOCK_OBSERVATIONS};

impl Problem<'_> {
    /// The effect columns of one observation, per column and string, into
    /// `effect_grad`: analytic gradients of the terms (each term touches
    /// only its own string) at each string's `contexts`.
    fn effect_gradients(
        &self,
        state: &State,
        contexts: &[Option<EffectContext>; STRINGS],
        effect_grad: &mut Vec<[f64; STRINGS]>,
    ) {
        effect_grad.clear();
        effect_grad.resize(self.layout.effect_columns.len(), [0.0; STRINGS]);
        for (c, &(e, pi)) in self.layout.effect_columns.iter().enumerate() {
            let term = &state.effects[e];
            for s in state.frame.layout.indices().filter(|&s| term.applies_to(s)) {
                if let Some(ctx) = &contexts[s] {
                    if let Some(g) = term.effect.gradient_f64(ctx).get(pi) {
                        effect_grad[c][s] = -g;
                    }
                }
            }
        }
    }

    /// Each string residual's row of the Jacobian (over the scaled LM
    /// variables) at `state`, in row order: `visit(row, string, own,
    /// shared)` with its values on the string's own columns and on the
    /// shared ones ([`Layout::arrow`]); it is zero elsewhere. Rows of
    /// weight 0 (zero) are not visited. False when a value is not finite.
    pub(super) fn string_rows(
        &self,
        state: &State,
        mut visit: impl FnMut(usize, usize, &[f64], &[f64]),
    ) -> bool {
        let mut pass = RowPass::new(self, state.clone());
        let mut finite = true;
        for (k, o) in self.observations.iter().enumerate() {
            finite &= pass.observation_rows(self, k, o, &mut visit);
        }
        finite
    }

    /// The prior rows of the Jacobian (over the scaled LM variables) at
    /// `state`, each on every column.
    pub(super) fn scaled_prior_rows(&self, state: &State) -> Vec<Vec<f64>> {
        let scale = &self.layout.scale;
        self.prior_rows(state)
            .into_iter()
            .map(|(_, grad)| {
                let mut values = vec![0.0; scale.len()];
                for (c, d) in grad {
                    values[c] += d;
                }
                for (v, s) in values.iter_mut().zip(scale) {
                    *v *= s;
                }
                values
            })
            .collect()
    }

    /// `J^T J` and `J^T residuals` of the Jacobian `J` at the current
    /// variables, summed without forming `J` ([`crate::model::normal`]):
    /// the same figures as the dense products. `None` when `J` is not
    /// finite.
    pub(super) fn normal_equations(
        &self,
        residuals: &DVector<f64>,
    ) -> Option<(DMatrix<f64>, DVector<f64>)> {
        let state = self.state();
        let mut normal = NormalEquations::new(&self.layout.arrow);
        let strings_finite = self.string_blocks(&state, residuals, &mut normal);
        let base = self.observations.len() * STRINGS;
        let mut priors_finite = true;
        for (j, values) in self.scaled_prior_rows(&state).into_iter().enumerate() {
            priors_finite &= values.iter().all(|v| v.is_finite());
            normal.add_row(base + j, &values, residuals[base + j]);
        }
        (strings_finite && priors_finite).then(|| normal.finish())
    }
}

impl Problem<'_> {
    /// The string rows' sums into `normal`, a block of observations per
    /// task on every core, added in block order (the same sums as one row
    /// after the other: [`crate::model::normal`]). False when a value is
    /// not finite.
    fn string_blocks(
        &self,
        state: &State,
        residuals: &DVector<f64>,
        normal: &mut NormalEquations<'_>,
    ) -> bool {
        use rayon::prelude::*;
        // Blocks summed at once: enough to keep every core busy, few
        // enough that their sums (~50 kB each) stay small.
        const BATCH_BLOCKS: usize = 64;
        let columns = &self.layout.arrow;
        let blocks: Vec<(usize, &[&Observation])> = self
            .observations
            .chunks(BLOCK_OBSERVATIONS)
            .enumerate()
            .collect();
        let spare = self.spare;
        let mut finite = true;
        for batch in blocks.chunks(BATCH_BLOCKS) {
            let summed: Vec<(BlockSums, bool)> = batch
                .par_iter()
                .map_init(
                    || RowPass::new(self, state.clone()),
                    |pass, &(block, observations)| {
                        let buffers = [spare.take(), spare.take()];
                        let mut sums = BlockSums::with_buffers(columns, block, buffers);
                        let mut finite = true;
                        for (j, o) in observations.iter().enumerate() {
                            let k = block * BLOCK_OBSERVATIONS + j;
                            finite &=
                                pass.observation_rows(self, k, o, &mut |row, i, own, shared| {
                                    sums.add_string_row(i, own, shared, residuals[row]);
                                });
                        }
                        let mut sums = sums.sum_rows();
                        spare.give(sums.take_rows_buffer());
                        (sums, finite)
                    },
                )
                .collect();
            for (sums, block_finite) in summed {
                finite &= block_finite;
                spare.give(normal.add_block(sums));
            }
        }
        finite
    }
}

/// What every row of the Jacobian at one state shares, and one row's
/// values, reused.
pub(super) struct RowPass {
    state: State,
    laws: [StringLaw; STRINGS],
    /// The effect columns (counted from the first) of the every-string
    /// terms and of each string's own.
    shared_terms: Vec<usize>,
    own_terms: [Vec<usize>; STRINGS],
    /// The frame's home terms of each string's context (its length at home
    /// too).
    homes: [Option<StringHome>; STRINGS],
    own: Vec<f64>,
    shared: Vec<f64>,
    /// One observation's effect columns per string, reused.
    effect_grad: Vec<[f64; STRINGS]>,
    /// The terms (indices into the state's effects, in order) on each
    /// string, its own and the shared ones.
    string_terms: [Vec<usize>; STRINGS],
    /// Each string's latency (s), [`latency_s`].
    latency_s: [f64; STRINGS],
}

impl RowPass {
    pub(super) fn new(problem: &Problem<'_>, state: State) -> RowPass {
        let layout = problem.layout;
        let frame = &state.frame;
        RowPass {
            laws: state.winding.laws(),
            shared_terms: layout
                .term_columns(problem.structure, EVERY_STRING)
                .collect(),
            own_terms: core::array::from_fn(|i| {
                layout.term_columns(problem.structure, i as u8).collect()
            }),
            homes: StringHome::of_every_string(frame),
            own: Vec::with_capacity(layout.arrow.n),
            shared: Vec::with_capacity(layout.arrow.n),
            effect_grad: Vec::with_capacity(layout.effect_columns.len()),
            string_terms: core::array::from_fn(|i| {
                (0..state.effects.len())
                    .filter(|&e| state.effects[e].applies_to(i))
                    .collect()
            }),
            latency_s: core::array::from_fn(|i| latency_s(&state.effects, i)),
            state,
        }
    }

    /// The rows of observation `k` (`o`) of `problem`, as
    /// [`Problem::string_rows`] visits them. False when a value is not
    /// finite.
    pub(super) fn observation_rows(
        &mut self,
        problem: &Problem<'_>,
        k: usize,
        o: &Observation,
        visit: &mut impl FnMut(usize, usize, &[f64], &[f64]),
    ) -> bool {
        let layout = problem.layout;
        let columns = &layout.arrow;
        let state = &self.state;
        let frame = &state.frame;
        let w = &state.winding;
        let two_pi = 2.0 * std::f64::consts::PI;
        let planar = frame.layout.planar;
        let (own, shared) = (&mut self.own, &mut self.shared);
        let mut finite = true;
        let p = device_position(frame, o);
        let inputs = inputs_for(frame, &state.effects, o, &p);
        // Each string's context once per row, not once per column.
        let total_tension_n = total_tension_n(frame.layout.active, &inputs.tension_mn);
        let contexts: [Option<EffectContext>; STRINGS] = core::array::from_fn(|s| {
            self.homes[s].as_ref().and_then(|home| {
                EffectContext::at_home(home, &self.laws, &inputs, s, total_tension_n)
            })
        });
        let effect_grad = &mut self.effect_grad;
        problem.effect_gradients(state, &contexts, effect_grad);
        for i in 0..STRINGS {
            let row = k * STRINGS + i;
            let f = problem.weights[k][i].sqrt() / problem.residual_sd;
            if f == 0.0 {
                continue;
            }
            let a = frame.anchors[i];
            let geo = distance(p, a);
            let up = {
                let d = sub(p, a);
                [d[0] / geo, d[1] / geo, d[2] / geo]
            };
            // Every string below STRINGS has its home terms; NaN (a row not
            // finite) otherwise.
            let lh = self.homes[i].as_ref().map_or(f64::NAN, |h| h.length_mm);
            let uh = {
                let d = sub(frame.home, a);
                [d[0] / lh, d[1] / lh, d[2] / lh]
            };
            let theta = two_pi * o.inputs.counts[i] as f64 / w.counts_per_rev[i] as f64;
            let terms = self.string_terms[i].iter().map(|&e| &state.effects[e]);
            let (d_payout, d_home) = length_derivatives(terms, i, o, contexts[i].as_ref());
            own.clear();
            shared.clear();
            // Anchor, then home.
            own.extend((0..3).map(|c| f * (-up[c] + d_home * uh[c])));
            shared.extend((0..3).map(|c| f * (-d_home * uh[c])));
            // The tracker frame: rotation, translation.
            let rup = mat_vec(&frame.room_rotation, up);
            let wgrad = cross(up, p);
            shared.extend((0..3).map(|c| f * wgrad[c]));
            shared.extend((0..3).map(|c| f * (-rup[c] / frame.room_scale)));
            if planar {
                // The position is held in the plane: the tracker's
                // tilts and z translation do not move it.
                shared[ROTATION - HOME] = 0.0;
                shared[ROTATION + 1 - HOME] = 0.0;
                shared[TRANSLATION + 2 - HOME] = 0.0;
            }
            if layout.fit_scale {
                let dot = up[0] * p[0] + up[1] * p[1] + up[2] * p[2];
                shared.push(f * (-dot / frame.room_scale));
            }
            // The winding law: radius, shared and own thinning rates. A
            // latency reads the law's slope, `r_home - 2 kappa theta / m`,
            // times the angle the pulley turns in it.
            let lag_rad = self.latency_s[i]
                * (two_pi / w.counts_per_rev[i] as f64)
                * f64::from(o.inputs.count_rate_cps[i]);
            own.push(f * (-(theta * d_payout + lag_rad)));
            let d_kappa = f
                * ((theta * theta * d_payout + 2.0 * theta * lag_rad) / w.mechanical_advantage[i]);
            shared.push(d_kappa);
            own.push(if problem.structure.hold_kappa_each {
                0.0
            } else {
                d_kappa
            });
            own.extend(self.own_terms[i].iter().map(|&c| f * effect_grad[c][i]));
            shared.extend(self.shared_terms.iter().map(|&c| f * effect_grad[c][i]));
            // To the scaled LM variables.
            for (v, &c) in own.iter_mut().zip(&columns.own[i]) {
                *v *= layout.scale[c];
            }
            for (v, &c) in shared.iter_mut().zip(&columns.shared) {
                *v *= layout.scale[c];
            }
            // Every value read, with no branch a value to stop early on.
            finite &= own
                .iter()
                .chain(shared.iter())
                .fold(true, |all, v| all & v.is_finite());
            visit(row, i, own, shared);
        }
        finite
    }
}

/// The latency (s) of string `i`'s terms, its own and the shared ones.
fn latency_s(effects: &[EffectTerm], i: usize) -> f64 {
    effects
        .iter()
        .filter(|t| t.applies_to(i))
        .map(|t| match t.effect {
            Effect::Latency { latency_s } => latency_s,
            _ => 0.0,
        })
        .sum()
}

/// The derivatives of string `i`'s model length over its payout and over
/// its home length at `o` (1 each without effects): effects that scale with
/// the payout or the home length (scale, elasticity, stretch, creep, sag) carry
/// those derivatives along. `terms`: the terms on the string, in the
/// model's order; `context`: the string's, for the sag.
fn length_derivatives<'t>(
    terms: impl Iterator<Item = &'t EffectTerm>,
    i: usize,
    o: &Observation,
    context: Option<&EffectContext>,
) -> (f64, f64) {
    let (mut d_payout, mut d_home) = (1.0, 1.0);
    for term in terms {
        match term.effect {
            Effect::Scale { relative } => d_payout += relative,
            Effect::Elasticity { per_newton } => {
                let t = f64::from(o.inputs.tension_mn[i]) / 1000.0;
                d_payout += per_newton * t;
                d_home += per_newton * t;
            }
            Effect::Creep { per_s } => {
                let strain = per_s * f64::from(o.inputs.time_ms) / 1000.0;
                d_payout += strain;
                d_home += strain;
            }
            Effect::Stretch {
                per_newton,
                home_tension_n,
                ..
            } => {
                let t = f64::from(o.inputs.tension_mn[i]) / 1000.0;
                d_payout += per_newton * t;
                d_home += per_newton * (t - home_tension_n);
            }
            Effect::Sag {
                mm_at_1m_1n,
                home_mm_at_1m,
            } => {
                if let Some(ctx) = context {
                    let slope = sag_slope(mm_at_1m_1n, ctx);
                    d_payout += slope;
                    d_home += slope + sag_home_slope(home_mm_at_1m, ctx);
                }
            }
            _ => {}
        }
    }
    (d_payout, d_home)
}

/// The weighted Jacobian of the string-space residuals at an identified
/// solution (rows `u * STRINGS + i` for the u-th observation with a tracker
/// position and string i; weight 1, or 0 for residuals beyond
/// [`GROSS_RESIDUAL_MM`]; prior rows left out), the matching weighted
/// residuals, and the weights. Diagnosis projects candidate effects on the
/// complement of its columns: what the current model can already absorb is
/// not evidence of an effect.
///
/// The rows are made when asked for ([`DataJacobian::pass`]), not held: a
/// 100,000-row session has 800,000 of them, 0.35 GB over the base model's
/// 55 columns.
pub struct DataJacobian<'a> {
    used: Vec<&'a Observation>,
    weights: Vec<[f64; STRINGS]>,
    residuals: Vec<f64>,
    layout: Layout,
    structure: &'a Structure,
    nominal: &'a Frame<f64>,
    base_rotation: [[f64; 3]; 3],
    winding_fixed: WindingPhysics,
    /// The identified solution in the LM variables.
    x: DVector<f64>,
    spare: SpareBuffers,
}

impl<'a> DataJacobian<'a> {
    /// The data Jacobian of `id` on `observations`; `None` when a residual
    /// or a prior row is not finite.
    pub fn new(
        id: &Identification,
        observations: &'a [Observation],
        nominal: &'a Frame<f64>,
        structure: &'a Structure,
    ) -> Option<DataJacobian<'a>> {
        use levenberg_marquardt::LeastSquaresProblem;
        let used: Vec<&Observation> = observations
            .iter()
            .filter(|o| o.tracker.is_some())
            .collect();
        let layout = Layout::new(structure);
        let state = State {
            frame: id.frame,
            winding: id.winding,
            effects: id.effects.clone(),
        };
        let laws = state.winding.laws();
        let homes = StringHome::of_every_string(&state.frame);
        let weights: Vec<[f64; STRINGS]> = used
            .iter()
            .map(|o| {
                let r = Problem::string_residuals(&state, &homes, &laws, o);
                core::array::from_fn(|i| {
                    if nominal.layout.is_active(i) && r[i].abs() <= GROSS_RESIDUAL_MM {
                        1.0
                    } else {
                        0.0
                    }
                })
            })
            .collect();
        let x = encode(&state, &layout);
        let mut jacobian = DataJacobian {
            used,
            weights,
            residuals: Vec::new(),
            layout,
            structure,
            nominal,
            base_rotation: state.frame.room_rotation,
            winding_fixed: state.winding,
            x,
            spare: SpareBuffers::default(),
        };
        let problem = jacobian.problem();
        let residuals = problem.residuals()?;
        let priors_finite = problem
            .scaled_prior_rows(&problem.state())
            .iter()
            .flatten()
            .all(|v| v.is_finite());
        let rows = jacobian.rows();
        let mut residuals = Vec::from(residuals.data);
        residuals.truncate(rows);
        jacobian.residuals = residuals;
        priors_finite.then_some(jacobian)
    }

    /// The identification's problem at the solution, every row weighed as
    /// [`Self::weights`] says.
    fn problem(&self) -> Problem<'_> {
        Problem {
            observations: &self.used,
            weights: &self.weights,
            residual_sd: 1.0,
            structure: self.structure,
            nominal: self.nominal,
            layout: &self.layout,
            base_rotation: self.base_rotation,
            winding_fixed: self.winding_fixed,
            x: self.x.clone(),
            spare: &self.spare,
        }
    }

    /// Number of rows: [`STRINGS`] per observation with a tracker position.
    pub fn rows(&self) -> usize {
        self.used.len() * STRINGS
    }

    /// Number of columns (the scaled parameters).
    pub fn columns(&self) -> usize {
        self.layout.len()
    }

    /// Per observation with a tracker position, per string: 1 or 0 (gross).
    pub fn weights(&self) -> &[[f64; STRINGS]] {
        &self.weights
    }

    /// Weighted string residuals, mm, row by row.
    pub fn residuals(&self) -> &[f64] {
        &self.residuals
    }

    /// The columns string `i`'s rows touch, in the order a pass gives
    /// their values ([`DataJacobianPass::rows_of`]: its own, then the
    /// shared ones); zero elsewhere.
    pub fn row_columns(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        let arrow = &self.layout.arrow;
        arrow.own[i].iter().chain(&arrow.shared).copied()
    }

    /// `J^T J`, summed as the dense product `J^T * J` sums it
    /// (`model::normal`); `None` when a value of `J` is not finite.
    pub fn gram(&self) -> Option<DMatrix<f64>> {
        let problem = self.problem();
        let state = problem.state();
        let mut normal = NormalEquations::new(&self.layout.arrow);
        let finite = problem.string_rows(&state, |row, i, own, shared| {
            normal.add_string_row(row, i, own, shared, 0.0);
        });
        finite.then(|| normal.finish().0)
    }

    /// A pass over the rows, in any order.
    pub fn pass(&self) -> DataJacobianPass<'_> {
        let problem = self.problem();
        let rows = RowPass::new(&problem, problem.state());
        DataJacobianPass { problem, rows }
    }
}

/// The rows of a [`DataJacobian`], observation by observation.
pub struct DataJacobianPass<'p> {
    problem: Problem<'p>,
    rows: RowPass,
}

impl DataJacobianPass<'_> {
    /// The rows of the `u`-th observation with a tracker position:
    /// `visit(string, own, shared)` with the row's values on the
    /// [`DataJacobian::row_columns`] of its string, its own then the shared
    /// ones. Rows of weight 0 (zero) are not visited.
    pub fn rows_of(&mut self, u: usize, mut visit: impl FnMut(usize, &[f64], &[f64])) {
        let problem = &self.problem;
        if let Some(o) = problem.observations.get(u) {
            self.rows
                .observation_rows(problem, u, o, &mut |_, i, own, shared| {
                    visit(i, own, shared)
                });
        }
    }
}
