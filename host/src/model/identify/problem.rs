//! One robust round's least-squares problem: the residuals (weighted string
//! rows, then prior rows) at the current LM variables, and its Jacobian for
//! the `levenberg-marquardt` crate's problem trait.

use nalgebra::{DMatrix, DVector, Dyn, Owned};
use spidar_core::geometry::{mat_mul, rotation_from_vector};
use spidar_core::model::{Frame, StringLaw};
use spidar_core::string_law::StringHome;
use spidar_core::STRINGS;

use super::layout::{Layout, State, ANCHORS, HOME, ROTATION, SCALE, TRANSLATION};
use super::residuals::residuals_at_homes;
use super::structure::{effect_prior, Structure};
use super::winding::WindingPhysics;
use crate::data::observe::Observation;
use crate::model::normal::SpareBuffers;

/// A prior row: its value and its gradient over the physical parameters as
/// (column, d).
pub(super) type PriorRow = (f64, Vec<(usize, f64)>);

/// The LM problem for one robust round: rotation is linearized around
/// `base_rotation` (the columns 27..30 are a small rotation vector on top).
pub(super) struct Problem<'a> {
    pub(super) observations: &'a [&'a Observation],
    pub(super) weights: &'a [[f64; STRINGS]],
    pub(super) residual_sd: f64,
    pub(super) structure: &'a Structure,
    pub(super) nominal: &'a Frame<f64>,
    pub(super) layout: &'a Layout,
    pub(super) base_rotation: [[f64; 3]; 3],
    /// Counts per revolution and mechanical advantage (not fitted).
    pub(super) winding_fixed: WindingPhysics,
    /// Current LM variables (scaled).
    pub(super) x: DVector<f64>,
    /// Buffers of the Jacobian passes' blocks, from one pass to the next.
    pub(super) spare: &'a SpareBuffers,
}

impl Problem<'_> {
    pub(super) fn state(&self) -> State {
        let v: Vec<f64> = self
            .x
            .iter()
            .zip(&self.layout.scale)
            .map(|(x, s)| x * s)
            .collect();
        let mut frame = *self.nominal;
        for i in 0..STRINGS {
            for c in 0..3 {
                frame.anchors[i][c] = v[ANCHORS + 3 * i + c];
            }
        }
        frame.home = [v[HOME], v[HOME + 1], v[HOME + 2]];
        frame.room_rotation = mat_mul(
            &self.base_rotation,
            &rotation_from_vector([v[ROTATION], v[ROTATION + 1], v[ROTATION + 2]]),
        );
        frame.room_translation = [v[TRANSLATION], v[TRANSLATION + 1], v[TRANSLATION + 2]];
        frame.room_scale = if self.layout.fit_scale {
            1.0 + v[SCALE]
        } else {
            self.nominal.room_scale
        };
        let mut r_home_mm = [0.0; STRINGS];
        r_home_mm.copy_from_slice(&v[self.layout.r_home()..self.layout.r_home() + STRINGS]);
        let winding = WindingPhysics {
            r_home_mm,
            kappa_mm: v[self.layout.kappa()],
            kappa_each_mm: core::array::from_fn(|i| v[self.layout.kappa_each() + i]),
            ..self.winding_fixed
        };
        let mut effects = self.structure.effects.clone();
        let first = self.layout.first_effect();
        let mut col = first;
        for term in effects.iter_mut() {
            let n = term.effect.parameters().len();
            if let Some(e) = term.effect.with_parameters(&v[col..col + n]) {
                term.effect = e;
            }
            col += n;
        }
        State {
            frame,
            winding,
            effects,
        }
    }

    pub(super) fn n_rows(&self) -> usize {
        let layout = self.nominal.layout;
        let gauge = if layout.planar { 4 } else { 6 };
        // Anchors, home/rotation/translation, inactive radii, each spool's
        // thinning rate and its mean, the gauge.
        self.observations.len() * STRINGS
            + 24
            + 9
            + (STRINGS - layout.count())
            + STRINGS
            + usize::from(!self.structure.hold_kappa_each)
            + self
                .layout
                .effect_columns
                .iter()
                .filter(|&&(e, pi)| {
                    effect_prior(
                        &self.structure.effects[e].effect,
                        pi,
                        &self.structure.priors,
                    )
                    .is_some()
                })
                .count()
            + gauge
    }

    /// String-space residuals of one observation (geometric minus model; 0
    /// on channels without a string).
    /// `homes`: the state's frame's ([`StringHome::of_every_string`]).
    pub(super) fn string_residuals(
        state: &State,
        homes: &[Option<StringHome>; STRINGS],
        laws: &[StringLaw; STRINGS],
        o: &Observation,
    ) -> [f64; 8] {
        residuals_at_homes(&state.frame, homes, laws, &state.effects, o)
    }
}

impl levenberg_marquardt::LeastSquaresProblem<f64, Dyn, Dyn> for Problem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.x.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.x.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let state = self.state();
        let laws = state.winding.laws();
        let homes = StringHome::of_every_string(&state.frame);
        let mut r = DVector::zeros(self.n_rows());
        // Each row on its own, on every core: the same figures in any order.
        let string_residuals: Vec<[f64; STRINGS]> = {
            use rayon::prelude::*;
            self.observations
                .par_iter()
                .map(|o| Problem::string_residuals(&state, &homes, &laws, o))
                .collect()
        };
        for (k, res) in string_residuals.iter().enumerate() {
            for i in 0..STRINGS {
                r[k * STRINGS + i] = self.weights[k][i].sqrt() * res[i] / self.residual_sd;
            }
        }
        let base = self.observations.len() * STRINGS;
        for (j, (value, _)) in self.prior_rows(&state).into_iter().enumerate() {
            r[base + j] = value;
        }
        r.iter().all(|v| v.is_finite()).then_some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let state = self.state();
        let columns = &self.layout.arrow;
        let mut jac = DMatrix::zeros(self.n_rows(), columns.n);
        let strings_finite = self.string_rows(&state, |row, i, own, shared| {
            for (&c, &v) in columns.own[i].iter().zip(own) {
                jac[(row, c)] = v;
            }
            for (&c, &v) in columns.shared.iter().zip(shared) {
                jac[(row, c)] = v;
            }
        });
        let base = self.observations.len() * STRINGS;
        for (j, values) in self.scaled_prior_rows(&state).into_iter().enumerate() {
            jac.row_mut(base + j).copy_from_slice(&values);
        }
        (strings_finite && jac.iter().all(|v| v.is_finite())).then_some(jac)
    }
}
