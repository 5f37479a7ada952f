//! Structure left in the residual that no family explains, binned by each
//! variable: what the report names and the learned correction takes next.

use spidar_core::model::Frame;

use crate::data::observe::Observation;
use crate::model::identify::{Identification, Structure};

use super::candidates::chi2_threshold;
use super::describe::variable_name;
use super::evidence::{pulley_turn_angle, Evidence, Row};
use super::vocabulary::{Family, Finding, LoopConfig, Variable};

/// A variable of the residual and how to read it off a row.
type VariableOf = (Variable, fn(&Row) -> f64);

/// Structure left in the residual that no family explains: per string, the
/// residual binned by each variable; a variable whose bin means differ beyond
/// chance is reported, naming it. Position-dependent structure is what the
/// learned correction (NN/SVR) takes next.
pub fn unexplained(
    id: &Identification,
    observations: &[Observation],
    nominal: &Frame<f64>,
    structure: &Structure,
    config: &LoopConfig,
) -> Vec<Finding> {
    const BINS: usize = 8;
    let Some(ev) = Evidence::gather(id, observations, nominal, structure) else {
        return Vec::new();
    };
    let variables: [VariableOf; 10] = [
        (Variable::Length, |r| r.length),
        (Variable::WoundLength, |r| r.ctx.payout_mm),
        (Variable::PulleyAngle, |r| pulley_turn_angle(r.ctx.theta)),
        (Variable::Tension, |r| r.ctx.tension_n),
        (Variable::Direction, |r| f64::from(r.ctx.direction)),
        (Variable::Speed, |r| r.speed),
        (Variable::Time, |r| r.ctx.time_s),
        (Variable::Order, |r| r.obs as f64),
        (Variable::Position, |r| r.position[0]),
        (Variable::Position, |r| r.position[2]),
    ];
    let sigma2 = ev.sigma2;
    let threshold = chi2_threshold(config, BINS, 15.0);
    let mut by_variable: Vec<(Variable, Vec<u8>, f64, f64, f64)> = Vec::new();
    for i in ev.layout.indices() {
        // The string's rows the fit keeps: each variable's value, the
        // projected residual and the square root of the weight.
        let mut rows: Vec<([f64; 10], f64, f64)> = Vec::new();
        ev.for_each_row(Some(i), |k, r| {
            if r.weight > 0.1 {
                let values = variables.map(|(_, value)| value(r));
                rows.push((values, ev.residual[k], r.weight.sqrt()));
            }
        });
        if rows.len() < 4 * BINS {
            continue;
        }
        let mut best: Option<(Variable, f64, f64, f64)> = None;
        for (j, (variable, _)) in variables.iter().enumerate() {
            let mut v: Vec<(f64, f64, f64)> = rows
                .iter()
                .map(|(values, residual, sw)| (values[j], *residual, *sw))
                .collect();
            v.sort_by(|a, b| a.0.total_cmp(&b.0));
            let mut between = 0.0;
            let mut peak: f64 = 0.0;
            let per = v.len() / BINS;
            for b in 0..BINS {
                let part = &v[b * per..if b + 1 == BINS {
                    v.len()
                } else {
                    (b + 1) * per
                }];
                let sum: f64 = part.iter().map(|x| x.1).sum();
                let n = part.len() as f64;
                between += sum * sum / n;
                let w: f64 = part.iter().map(|x| x.2).sum::<f64>() / n;
                peak = peak.max((sum / n / w.max(1e-9)).abs());
            }
            let total: f64 = v.iter().map(|x| x.1).sum();
            between -= total * total / v.len() as f64;
            let chi2 = between / sigma2;
            if chi2 > threshold && best.is_none_or(|b| chi2 > b.1) {
                best = Some((*variable, chi2, peak, between));
            }
        }
        if let Some((variable, chi2, peak, between)) = best {
            match by_variable.iter_mut().find(|e| e.0 == variable) {
                Some(e) => {
                    e.1.push(i as u8);
                    e.2 = e.2.max(chi2);
                    e.3 = e.3.max(peak);
                    e.4 += between;
                }
                None => by_variable.push((variable, vec![i as u8], chi2, peak, between)),
            }
        }
    }
    by_variable
        .into_iter()
        .map(|(variable, strings, chi2, peak, between)| Finding {
            family: Family::Unexplained,
            description: format!(
                "strings {strings:?}: residual follows {} but fits no known effect{}",
                variable_name(variable),
                if variable == Variable::Position {
                    "; the learned position correction takes it"
                } else {
                    ""
                }
            ),
            strings,
            variable,
            amplitude_mm: peak,
            explained: between / ev.rss.max(1e-12),
            added: false,
            chi2,
            validation: None,
            change: None,
        })
        .collect()
}
