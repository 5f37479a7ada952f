//! One diagnosis of a fitted model: the candidate effects that explain its
//! residual significantly off the model's span, strongest first
//! ([`diagnose`]).

use spidar_core::model::{Effect, EffectTerm, Frame};

use super::candidates::{
    anchors_beyond_tolerance, beyond_rivals, candidates, chi2_threshold, Candidate,
};
use super::evidence::{Columns, Evidence};
use super::revisits;
use super::slips::{slip_times, steps_where_it_slipped};
use super::vocabulary::{Change, Family, Finding, LoopConfig, Variable};
use crate::data::observe::Observation;
use crate::model::identify::{Identification, Structure};

/// Significant candidate effects of the current fit, strongest first; one
/// without a change is reported, not proposed (an anchor beyond its
/// tolerance is proposed released; a term on time that the session's
/// revisits of a place do not show is not).
pub fn diagnose(
    id: &Identification,
    observations: &[Observation],
    nominal: &Frame<f64>,
    structure: &Structure,
    config: &LoopConfig,
) -> Vec<Finding> {
    let Some(ev) = Evidence::gather(id, observations, nominal, structure) else {
        return Vec::new();
    };
    let splits = slip_times(&ev);
    let candidates = candidates(&ev, structure, &splits, config);
    let mut findings = significant(&ev, &candidates, config);
    findings.extend(anchors_beyond_tolerance(id, nominal, structure));
    findings.sort_by(|a, b| b.chi2.total_cmp(&a.chi2));
    findings
}

/// The candidates that explain the residual significantly off the model's
/// span (and beyond their rival's columns), in order, as findings; a slip
/// only where the residual jumps; a term on time that the session's
/// revisits of a place do not show ([`revisits`]) without a change, saying
/// why. Each test's passes over the rows serve every candidate at once.
fn significant(ev: &Evidence, candidates: &[Candidate], config: &LoopConfig) -> Vec<Finding> {
    let own: Vec<Columns> = candidates.iter().map(Candidate::own).collect();
    let fits: Vec<Option<(Vec<f64>, f64)>> = ev
        .off_span(&own)
        .iter()
        .map(|off| off.outside().then(|| off.fit()).flatten())
        .collect();
    // Terms of several strings, each its own coefficients (the drifts or
    // the stretches of every string), must explain beyond the strongest
    // one string's term of their family (its columns are among theirs: a
    // nested test at the extra dof), so that one drifting or stretching
    // string takes its own parameters, not every string's.
    let mut strongest: Vec<(Family, f64, usize)> = Vec::new();
    for (c, f) in candidates.iter().zip(&fits) {
        let (Some(f), Some(_)) = (f, c.on_string) else {
            continue;
        };
        match strongest.iter_mut().find(|s| s.0 == c.family) {
            Some(s) if f.1 > s.1 => *s = (c.family, f.1, c.columns.len()),
            Some(_) => {}
            None => strongest.push((c.family, f.1, c.columns.len())),
        }
    }
    let strongest_one = |family: Family| {
        strongest
            .iter()
            .find(|s| s.0 == family)
            .map_or((0.0, 0), |s| (s.1, s.2))
    };
    let fitted: Vec<(&Candidate, Vec<f64>, f64)> = fits
        .into_iter()
        .zip(candidates)
        .filter_map(|(fit, c)| {
            let (beta, explained) = fit?;
            let chi2 = explained / ev.sigma2;
            let beyond_one = !terms_of_several_strings(c) || {
                let (one, one_columns) = strongest_one(c.family);
                (explained - one) / ev.sigma2
                    >= chi2_threshold(
                        config,
                        c.columns.len().saturating_sub(one_columns).max(1),
                        0.0,
                    )
            };
            (beyond_one && chi2 >= chi2_threshold(config, c.columns.len(), c.search_penalty))
                .then_some((c, beta, explained))
        })
        .collect();
    let with_rival: Vec<&Candidate> = fitted
        .iter()
        .map(|f| f.0)
        .filter(|c| !c.rival.is_empty())
        .collect();
    let mut beyond = beyond_rivals(ev, &with_rival, config).into_iter();
    let kept: Vec<(&Candidate, Vec<f64>, f64)> = fitted
        .into_iter()
        .filter(|(c, _, _)| c.rival.is_empty() || beyond.next().unwrap_or(false))
        .collect();
    let sets: Vec<(Columns, &[f64])> = kept
        .iter()
        .map(|(c, beta, _)| (c.own(), &beta[..]))
        .collect();
    let amplitudes = ev.amplitudes(&sets);
    kept.into_iter()
        .zip(amplitudes)
        .filter_map(|((c, beta, explained), amplitude_mm)| {
            let change = (c.build)(&beta);
            if let Change::Effect(EffectTerm {
                string,
                effect: Effect::Slip { at_s, mm },
            }) = change
            {
                if !steps_where_it_slipped(ev, usize::from(string), at_s, mm) {
                    return None;
                }
            }
            // A term on time must show where the session comes back to a
            // place (a slip has its own local test, the jump above).
            let revisited = (c.variable == Variable::Time && c.family != Family::Slip)
                .then(|| revisits::where_revisited(ev, c, &beta, config))
                .flatten();
            let shown = !matches!(revisited, Some(revisits::Revisited::NotShown(_)));
            Some(Finding {
                family: c.family,
                strings: c.strings.clone(),
                variable: c.variable,
                amplitude_mm,
                explained: explained / ev.rss.max(1e-12),
                added: false,
                chi2: explained / ev.sigma2,
                description: match &revisited {
                    Some(
                        revisits::Revisited::NotShown(why) | revisits::Revisited::Confirmed(why),
                    ) => format!("{}; {why}", c.describe),
                    None => c.describe.clone(),
                },
                validation: None,
                change: shown.then_some(change),
            })
        })
        .collect()
}

/// Whether `c` adds drifts of several strings, each its own rate
/// ([`Change::Drifts`]).
pub(super) fn drifts_of_several_strings(c: &Candidate) -> bool {
    c.family == Family::Drift && terms_of_several_strings(c)
}

/// Whether `c` adds a term on each of several strings, each its own
/// coefficients ([`Change::Drifts`], [`Change::Stretches`]).
fn terms_of_several_strings(c: &Candidate) -> bool {
    c.on_string.is_none() && c.strings.len() > 1
}
