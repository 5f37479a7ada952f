//! The evidence of each effect the loop tried, for its figure: the training
//! rows' string residual (geometric length from the tracker minus the
//! model's, mm) against the variable the effect follows. "After" is the
//! final model's residual; "before" is the same model with the effect's
//! terms (or layer tables) taken out, everything else held: what the
//! effect takes out of the residual. A change that is no term of the string
//! law (an anchor released, the tracker's scale, the tracked body's offset)
//! has its "after" only.

use std::f64::consts::TAU;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use spidar_core::geometry::distance;
use spidar_core::model::{Effect, EffectTerm, LayerTable, StringLaw};
use spidar_core::string_law::{guide_elevation_q32, guide_elevation_rad, payout_f64, pulley_angle};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::model::diagnose::{Family, Finding, Variable};
use crate::model::identify::{
    device_position, string_residuals, Identification, GROSS_RESIDUAL_MM,
};

use super::data::{round_sig, thin_evenly};

/// Findings the loop did not add that get a figure, strongest first (the
/// others are rows of a table).
pub(super) const NOT_ADDED_WITH_FIGURE: usize = 6;
/// Strings drawn per finding.
const STRINGS_DRAWN: usize = 4;
/// Binned means per string (equal numbers of rows).
const BINS: usize = 20;
/// Residual points drawn per string.
const POINTS: usize = 240;

/// One finding's residuals against its variable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EffectEvidence {
    /// The finding's index in `report.json`'s `effects`.
    pub effect: usize,
    /// What the x axis is, with its unit.
    pub x_label: String,
    /// What "before" is (`null`: the figure has the final model's residual
    /// only).
    pub before: Option<String>,
    /// Strings of the finding that are not drawn.
    pub strings_not_drawn: usize,
    pub strings: Vec<StringEvidence>,
}

/// One string's residual against the variable: binned means and a thinned
/// set of the rows.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StringEvidence {
    pub string: usize,
    /// Rows with a residual (tracked, not a gross failure).
    pub rows: usize,
    /// Mean of the variable in each bin, and the mean residual before
    /// (empty without a "before") and after, mm.
    pub bin_x: Vec<f64>,
    pub bin_before_mm: Vec<f64>,
    pub bin_after_mm: Vec<f64>,
    /// Every k-th row: the variable, the residual before (empty without
    /// one) and after, mm.
    pub x: Vec<f64>,
    pub before_mm: Vec<f64>,
    pub after_mm: Vec<f64>,
}

/// The findings that get a figure: every one the loop added, then the
/// strongest others (not one the loop did not test, with neither a check
/// nor a statistic: a family without a candidate, such as a latency on a
/// static session, has no evidence).
pub(super) fn drawn_findings(findings: &[Finding]) -> Vec<usize> {
    let mut added: Vec<usize> = (0..findings.len()).filter(|&i| findings[i].added).collect();
    let tested = |f: &Finding| f.validation.is_some() || f.chi2 > 0.0;
    let mut others: Vec<usize> = (0..findings.len())
        .filter(|&i| !findings[i].added && tested(&findings[i]))
        .collect();
    others.sort_by(|&a, &b| findings[b].chi2.total_cmp(&findings[a].chi2));
    others.truncate(NOT_ADDED_WITH_FIGURE);
    added.extend(others);
    added
}

/// The evidence of the findings [`drawn_findings`] picks, on the training
/// rows under the final identification `fin`.
pub(super) fn effect_evidence(
    fin: &Identification,
    findings: &[Finding],
    rows: &[Observation],
) -> Vec<EffectEvidence> {
    let after = string_residuals(&fin.frame, &fin.laws, &fin.effects, rows);
    let variables = RowVariables::of(fin, rows);
    // Each finding on its own core: a long session's residuals without it
    // are a pass over every row.
    drawn_findings(findings)
        .into_par_iter()
        .map(|i| {
            let finding = &findings[i];
            let without = if finding.added {
                without_finding(fin, finding)
            } else {
                None
            };
            let before = without
                .as_ref()
                .map(|(laws, effects)| string_residuals(&fin.frame, laws, effects, rows));
            let mut strings: Vec<usize> = finding.strings.iter().map(|&s| usize::from(s)).collect();
            if strings.is_empty() {
                strings = fin.frame.layout.indices().collect();
            }
            let strings_not_drawn = strings.len().saturating_sub(STRINGS_DRAWN);
            strings.truncate(STRINGS_DRAWN);
            EffectEvidence {
                effect: i,
                x_label: x_label(finding.variable).to_string(),
                before: before.as_ref().map(|_| before_label(finding).to_string()),
                strings_not_drawn,
                strings: strings
                    .into_iter()
                    .filter(|&s| s < STRINGS)
                    .map(|s| {
                        string_evidence(s, &variables, finding.variable, before.as_deref(), &after)
                    })
                    .collect(),
            }
        })
        .collect()
}

fn before_label(finding: &Finding) -> &'static str {
    if finding.family == Family::Layers {
        "the final model without its layer tables"
    } else {
        "the final model without this effect's terms"
    }
}

/// The x axis of a variable, with its unit.
fn x_label(v: Variable) -> &'static str {
    match v {
        Variable::Position => "x of the tracker, device frame, mm",
        Variable::Length => "string length from the tracker, mm",
        Variable::WoundLength => "string paid out since home, mm",
        Variable::PulleyAngle => "pulley angle within a turn, rad",
        Variable::Tension => "commanded tension, N",
        Variable::Direction => "direction of the last motion (-1 in, +1 out)",
        Variable::Speed => "string speed, mm/s",
        Variable::Time => "time since home, s",
        Variable::Order => "row of the training session",
        Variable::Orientation => "tracked body's rotation, degrees",
        Variable::Elevation => "string's elevation from its guide's swivel plane, degrees",
    }
}

/// The final model's laws and effects without what `finding` added; `None`
/// when the change is no term of the string law.
fn without_finding(
    fin: &Identification,
    finding: &Finding,
) -> Option<([StringLaw; STRINGS], Vec<EffectTerm>)> {
    let mut effects = fin.effects.clone();
    let mut laws = fin.laws;
    let change = finding.change?;
    let terms = change.effect_terms();
    if !terms.is_empty() {
        for term in &terms {
            remove_term(&mut effects, term)?;
        }
    } else if finding.family == Family::Layers {
        for &s in &finding.strings {
            laws.get_mut(usize::from(s))?.layers = LayerTable::NONE;
        }
    } else {
        return None;
    }
    Some((laws, effects))
}

/// Removes the final model's term that `term` (as proposed) became: the
/// same family on the same string, the nearest slip time for a slip.
fn remove_term(effects: &mut Vec<EffectTerm>, term: &EffectTerm) -> Option<()> {
    let slip_time = |e: &Effect| match e {
        Effect::Slip { at_s, .. } => *at_s,
        _ => 0.0,
    };
    let at = effects
        .iter()
        .enumerate()
        .filter(|(_, e)| {
            e.string == term.string
                && std::mem::discriminant(&e.effect) == std::mem::discriminant(&term.effect)
        })
        .min_by(|(_, a), (_, b)| {
            let d = |e: &EffectTerm| (slip_time(&e.effect) - slip_time(&term.effect)).abs();
            d(a).total_cmp(&d(b))
        })?
        .0;
    effects.remove(at);
    Some(())
}

/// What the variables read on each row and string.
struct RowVariables<'a> {
    fin: &'a Identification,
    rows: &'a [Observation],
    /// String paid out on each row, per string.
    payout: Vec<[f64; STRINGS]>,
}

impl<'a> RowVariables<'a> {
    fn of(fin: &'a Identification, rows: &'a [Observation]) -> RowVariables<'a> {
        let payout = rows
            .iter()
            .map(|o| {
                let mut p = [0.0; STRINGS];
                for i in fin.frame.layout.indices() {
                    p[i] = payout_f64(&fin.laws[i], o.inputs.counts[i]);
                }
                p
            })
            .collect();
        RowVariables { fin, rows, payout }
    }

    /// `variable` of string `s` on row `k` (not finite where it has no
    /// value).
    fn value(&self, variable: Variable, s: usize, k: usize) -> f64 {
        let o = &self.rows[k];
        let law = &self.fin.laws[s];
        match variable {
            Variable::Position => device_position(&self.fin.frame, o)[0],
            Variable::Length => distance(
                device_position(&self.fin.frame, o),
                self.fin.frame.anchors[s],
            ),
            Variable::WoundLength => self.payout[k][s],
            Variable::PulleyAngle => pulley_angle(law, o.inputs.counts[s]).rem_euclid(TAU),
            Variable::Tension => o.tension_n[s],
            Variable::Direction => f64::from(o.inputs.direction[s]),
            Variable::Speed => match k.checked_sub(1).map(|j| (j, o.t_s - self.rows[j].t_s)) {
                Some((j, dt)) if dt > 0.0 => (self.payout[k][s] - self.payout[j][s]) / dt,
                _ => f64::NAN,
            },
            Variable::Time => o.t_s,
            Variable::Order => o.row as f64,
            Variable::Orientation => o.tracker_rotation.map_or(f64::NAN, |r| {
                let trace = r[0][0] + r[1][1] + r[2][2];
                ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
            }),
            Variable::Elevation => {
                let frame = &self.fin.frame;
                let q =
                    guide_elevation_q32(&frame.anchors[s], &frame.home, &device_position(frame, o));
                guide_elevation_rad(q).to_degrees()
            }
        }
    }
}

/// String `s`'s residuals against `variable`.
fn string_evidence(
    s: usize,
    variables: &RowVariables<'_>,
    variable: Variable,
    before: Option<&[Option<[f64; STRINGS]>]>,
    after: &[Option<[f64; STRINGS]>],
) -> StringEvidence {
    // (x, before, after) of every row with a residual that is no gross failure.
    let mut rows: Vec<(f64, f64, f64)> = Vec::new();
    for (k, a) in after.iter().enumerate() {
        let Some(a) = a else { continue };
        let b = before
            .and_then(|b| b.get(k).copied().flatten())
            .map_or(f64::NAN, |b| b[s]);
        let x = variables.value(variable, s, k);
        let gross = a[s].abs() > GROSS_RESIDUAL_MM || b.abs() > GROSS_RESIDUAL_MM;
        if x.is_finite() && a[s].is_finite() && !gross {
            rows.push((x, b, a[s]));
        }
    }
    let has_before = before.is_some();
    let mut e = StringEvidence {
        string: s,
        rows: rows.len(),
        ..StringEvidence::default()
    };
    for &k in &thin_evenly(rows.len(), POINTS) {
        let (x, b, a) = rows[k];
        e.x.push(round_sig(x));
        if has_before {
            e.before_mm.push(round_sig(b));
        }
        e.after_mm.push(round_sig(a));
    }
    rows.sort_by(|p, q| p.0.total_cmp(&q.0));
    for bin in equal_count_bins(&rows, BINS) {
        let n = bin.len() as f64;
        e.bin_x
            .push(round_sig(bin.iter().map(|r| r.0).sum::<f64>() / n));
        if has_before {
            e.bin_before_mm
                .push(round_sig(bin.iter().map(|r| r.1).sum::<f64>() / n));
        }
        e.bin_after_mm
            .push(round_sig(bin.iter().map(|r| r.2).sum::<f64>() / n));
    }
    e
}

/// Consecutive runs of the rows (sorted by x) of about `len / bins` rows,
/// never splitting rows of one x between two runs; a variable of at most
/// `bins` values (the direction) gets a run per value.
fn equal_count_bins<T: Copy>(rows: &[(f64, T, T)], bins: usize) -> Vec<&[(f64, T, T)]> {
    let values = 1 + rows.windows(2).filter(|w| w[1].0 != w[0].0).count();
    let size = if values <= bins {
        1
    } else {
        rows.len().div_ceil(bins.max(1)).max(1)
    };
    let mut out = Vec::new();
    let mut start = 0;
    while start < rows.len() {
        let mut end = (start + size).min(rows.len());
        while end < rows.len() && rows[end].0 == rows[end - 1].0 {
            end += 1;
        }
        out.push(&rows[start..end]);
        start = end;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bins_never_split_one_value() {
        let rows: Vec<(f64, f64, f64)> = [-1.0, -1.0, -1.0, 0.0, 1.0, 1.0, 1.0, 1.0]
            .iter()
            .map(|&x| (x, 0.0, 0.0))
            .collect();
        let sizes = |rows: &[(f64, f64, f64)], bins| -> Vec<usize> {
            equal_count_bins(rows, bins)
                .iter()
                .map(|b| b.len())
                .collect()
        };
        assert_eq!(sizes(&rows, 4), [3, 1, 4]);
        // More values than bins: runs of about len / bins rows, the ties
        // kept together.
        assert_eq!(sizes(&rows, 2), [4, 4]);
        let many: Vec<(f64, f64, f64)> = (0..10).map(|k| (f64::from(k), 0.0, 0.0)).collect();
        assert_eq!(sizes(&many, 4), [3, 3, 3, 1]);
        assert!(equal_count_bins::<f64>(&[], 4).is_empty());
    }

    #[test]
    fn a_proposed_term_removes_its_refitted_self() {
        let slip = |string, at_s, mm| EffectTerm {
            string,
            effect: Effect::Slip { at_s, mm },
        };
        let offset = EffectTerm {
            string: 3,
            effect: Effect::Offset { mm: 7.9 },
        };
        let mut effects = vec![slip(2, 10.0, 1.0), offset, slip(2, 30.0, 2.0)];
        remove_term(&mut effects, &slip(2, 29.0, 1.5)).unwrap();
        assert_eq!(effects, [slip(2, 10.0, 1.0), offset]);
        let proposed = EffectTerm {
            string: 3,
            effect: Effect::Offset { mm: 8.0 },
        };
        remove_term(&mut effects, &proposed).unwrap();
        assert_eq!(effects, [slip(2, 10.0, 1.0)]);
        assert!(remove_term(&mut effects, &proposed).is_none());
    }
}
