//! One identification's rounds: the start's state, the robust rounds that
//! reweigh the rows and refit, each a problem minimized.

use spidar_core::model::{Frame, StringLaw};
use spidar_core::string_law::StringHome;
use spidar_core::STRINGS;

use super::layout::{encode, Layout, State};
use super::problem::Problem;
use super::result::IdentifyError;
use super::robust::{robust_scale, weight, Round};
use super::solver::{minimize, DAMPING_FAR, DAMPING_NEAR};
use super::start::same_term;
use super::start::Start;
use super::structure::Structure;
use crate::data::observe::Observation;
use crate::model::normal::SpareBuffers;

/// What the steps of [`identify`](super::identify) share: the observations with a tracker
/// position, the structure and its parameter layout, the design geometry
/// and the start.
pub(super) struct Fit<'a> {
    pub(super) used: &'a [&'a Observation],
    pub(super) structure: &'a Structure,
    pub(super) nominal: &'a Frame<f64>,
    pub(super) layout: &'a Layout,
    pub(super) start: &'a Start,
    /// Buffers of its problems' Jacobian passes ([`SpareBuffers`]).
    pub(super) spare: SpareBuffers,
}

impl Fit<'_> {
    /// The start's state, with the structure's terms; the start's values of
    /// its leading terms that are the structure's (a refit carries them).
    /// Whether the structure gained terms beyond those.
    pub(super) fn start_state(&self) -> (State, bool) {
        let mut effects = self.structure.effects.clone();
        let mut carried = 0;
        for (term, known) in effects.iter_mut().zip(&self.start.effects) {
            if !same_term(term, known) {
                break;
            }
            *term = *known;
            carried += 1;
        }
        let grown = carried < effects.len();
        let state = State {
            frame: self.start.frame,
            winding: self.start.winding,
            effects,
        };
        (state, grown)
    }

    /// `w` on the channels with a string, 0 on the others.
    fn active_weights(&self, w: [f64; STRINGS]) -> [f64; STRINGS] {
        let strings = self.nominal.layout;
        core::array::from_fn(|i| if strings.is_active(i) { w[i] } else { 0.0 })
    }

    /// String-space residuals of every used observation.
    pub(super) fn string_residuals(
        &self,
        state: &State,
        laws: &[StringLaw; STRINGS],
    ) -> Vec<[f64; STRINGS]> {
        let homes = StringHome::of_every_string(&state.frame);
        self.used
            .iter()
            .map(|o| Problem::string_residuals(state, &homes, laws, o))
            .collect()
    }

    /// The LM problem at `state` with the rows' `weights` and the residual
    /// scale `residual_sd`.
    pub(super) fn problem<'b>(
        &'b self,
        state: &State,
        weights: &'b [[f64; STRINGS]],
        residual_sd: f64,
    ) -> Problem<'b> {
        let base_rotation = state.frame.room_rotation;
        let x = encode(state, self.layout);
        Problem {
            observations: self.used,
            weights,
            residual_sd,
            structure: self.structure,
            nominal: self.nominal,
            layout: self.layout,
            base_rotation,
            winding_fixed: self.start.winding,
            x,
            spare: &self.spare,
        }
    }

    /// The robust rounds from the start: each reweights the rows from the
    /// current state's residuals and refits, until the weights settle. The
    /// state, the last round's weights and the evaluations used.
    pub(super) fn robust_rounds(
        &self,
    ) -> Result<(State, Vec<[f64; STRINGS]>, usize), IdentifyError> {
        let (mut state, grown) = self.start_state();
        let strings = self.nominal.layout;
        let mut weights = vec![self.active_weights([1.0; STRINGS]); self.used.len()];
        let mut evaluations = 0;
        let cold = [
            Round::LeastSquares,
            Round::Huber,
            Round::Tukey,
            Round::Tukey,
            Round::Tukey,
        ];
        let warm = [Round::Tukey, Round::Tukey, Round::Tukey];
        // A warm start whose structure gained a term begins with a Huber round:
        // Tukey weights from the start's residuals would give the rows the new
        // term explains (the minority side of a slip) no weight before it could
        // explain them.
        let warm_grown = [Round::Huber, Round::Tukey, Round::Tukey];
        let (rounds, settled_after): (&[Round], usize) =
            match (self.structure.robust, self.start.warm, grown) {
                (false, _, _) => (&[Round::LeastSquares], 1),
                (true, true, false) => (&warm, 1),
                (true, true, true) => (&warm_grown, 1),
                (true, false, _) => (&cold, 3),
            };
        for (n, &round) in rounds.iter().enumerate() {
            // Weights from the current state's residuals (dropped before
            // the fit: a long session's are megabytes).
            let (scale, new_weights) = {
                let laws = state.winding.laws();
                let residuals = self.string_residuals(&state, &laws);
                let scale = robust_scale(&residuals, strings).max(1e-3);
                let new_weights: Vec<[f64; STRINGS]> = residuals
                    .iter()
                    .map(|r| self.active_weights(r.map(|v| weight(round, v, scale))))
                    .collect();
                (scale, new_weights)
            };
            let changed = new_weights
                .iter()
                .flatten()
                .zip(weights.iter().flatten())
                .any(|(a, b)| (a - b).abs() > 1e-3);
            if n >= settled_after && !changed {
                break;
            }
            weights = new_weights;
            let problem = self.problem(&state, &weights, scale);
            // The first round of a cold start begins at the design
            // geometry; every other begins at a fitted state.
            let damping = if n == 0 && !self.start.warm {
                DAMPING_FAR
            } else {
                DAMPING_NEAR
            };
            let (problem, used_evaluations) = minimize(problem, damping)
                .map_err(|why| IdentifyError::Diverged(format!("robust round {n}: {why}")))?;
            evaluations += used_evaluations;
            state = problem.state();
        }
        Ok((state, weights, evaluations))
    }
}
