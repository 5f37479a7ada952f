//! Each free parameter's estimate and posterior sd at the solution, and
//! the warnings: what the data do not determine, strings that count down.

use nalgebra::DMatrix;
use spidar_core::model::{StringLaw, StringLayout};
use spidar_core::STRINGS;

use super::fit::Fit;
use super::layout::{column_is_free, column_value, parameter_names, State};
use super::result::ParameterEstimate;

impl Fit<'_> {
    /// Each free parameter's value at `state` and its posterior sd from
    /// the information matrix `info` (`J^T J` at the solution); a warning
    /// for each the data do not determine (or, failing any, for a singular
    /// information matrix).
    pub(super) fn estimates(
        &self,
        state: &State,
        info: DMatrix<f64>,
    ) -> (Vec<ParameterEstimate>, Vec<String>) {
        let (layout, structure, strings) = (self.layout, self.structure, self.nominal.layout);
        // Marginal posterior variances from the eigen-decomposition of the
        // information matrix: a direction with (numerically) no information
        // makes exactly the parameters that load on it undetermined (infinite
        // sd), instead of failing the whole inverse.
        let eig = info.symmetric_eigen();
        let largest = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
        let variance = |c: usize| -> f64 {
            let mut v = 0.0;
            for k in 0..eig.eigenvalues.len() {
                let load = eig.eigenvectors[(c, k)] * eig.eigenvectors[(c, k)];
                if eig.eigenvalues[k] > 1e-12 * largest {
                    v += load / eig.eigenvalues[k];
                } else if load > 1e-6 {
                    return f64::INFINITY;
                }
            }
            v
        };
        let singular = eig.eigenvalues.iter().any(|&l| l <= 1e-12 * largest);
        let mut parameters = Vec::new();
        let mut warnings = Vec::new();
        let names = parameter_names(layout, structure, strings);
        for (c, (name, unit, prior_sd)) in names.into_iter().enumerate() {
            if !column_is_free(layout, structure, strings, c) {
                continue;
            }
            let s = layout.scale[c];
            let value = column_value(layout, state, c);
            let sd = variance(c).sqrt() * s;
            let determined = match prior_sd {
                Some(p) => sd < 0.7 * p,
                None => sd.is_finite() && sd < 10.0 * s.max(value.abs()),
            };
            if !determined {
                warnings.push(match prior_sd {
                    Some(p) => format!(
                        "{name}: the data do not determine it (posterior sd {sd:.3} {unit} vs prior sd {p:.3} {unit}); its value comes from the nominal design"
                    ),
                    None => format!("{name}: the data do not determine it (sd {sd:.3e} {unit})"),
                });
            }
            parameters.push(ParameterEstimate {
                name,
                unit: unit.to_string(),
                value,
                sd,
                prior_sd,
                determined,
            });
        }
        if singular && warnings.is_empty() {
            warnings.push(
                "the information matrix is singular: some parameters are not determined by the data"
                    .into(),
            );
        }
        (parameters, warnings)
    }
}

/// A string whose identified winding radius at home is negative: its
/// encoder counts down as the string pays out (wired or mounted the other
/// way from the geometry's convention). The identification follows it (the
/// radius is free to change sign) and so does the calibration the device
/// reads; the nominal geometry (the raw stage) does not, which is why that
/// stage's error is large. Such a session calibrates as well as one with
/// the sign right, so without this warning nothing would tell.
pub(super) fn counting_down_warnings(
    laws: &[StringLaw; STRINGS],
    strings: StringLayout,
) -> Vec<String> {
    strings
        .indices()
        .filter(|&i| laws[i].winding_mm[0] < 0.0)
        .map(|i| {
            format!(
                "string {i}: its counts fall as its string pays out (identified winding radius at \
                 home {:.3} mm): its encoder counts the other way from the geometry's convention; \
                 the calibration carries the sign, the nominal geometry (the raw stage) does not",
                laws[i].winding_mm[0]
            )
        })
        .collect()
}
