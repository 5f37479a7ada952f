//! Several strings' terms of one family tried as one change, when none of
//! the strongest proposals helped alone: the slips of several strings
//! ([`slips_together`]) and the latencies of several strings
//! ([`latencies_together`]). Each string's term alone leaves the others'
//! error to the rest of the model, which bends to it (anchors, home, the
//! shared terms), and a fold the bent model extrapolates to is worse for
//! the one term; together they take it all.

use spidar_core::model::{Effect, EffectTerm};
use spidar_core::STRINGS;

use super::vocabulary::{Change, Family, Finding, Variable};

/// The significant slips of several strings as one finding and change
/// ([`Change::Slips`]): its chi-square and share explained the sums of the
/// strings' own (their steps lie on different strings, nearly orthogonal);
/// `None` for fewer than two strings.
pub(super) fn slips_together(slips: &[&Finding]) -> Option<(Finding, Change)> {
    if slips.len() < 2 {
        return None;
    }
    let mut steps = [None; STRINGS];
    let mut strings = Vec::new();
    let mut times = Vec::new();
    for f in slips {
        if let Some(Change::Effect(EffectTerm {
            string,
            effect: Effect::Slip { at_s, mm },
        })) = f.change
        {
            steps[usize::from(string)] = Some((at_s, mm));
            strings.push(string);
            times.push(format!("string {string} at {at_s:.1} s"));
        }
    }
    if strings.len() < 2 {
        return None;
    }
    strings.sort_unstable();
    let change = Change::Slips(steps);
    let finding = Finding {
        family: Family::Slip,
        strings,
        variable: Variable::Time,
        amplitude_mm: slips.iter().map(|f| f.amplitude_mm).fold(0.0, f64::max),
        explained: slips.iter().map(|f| f.explained).sum(),
        added: false,
        chi2: slips.iter().map(|f| f.chi2).sum(),
        description: format!(
            "several strings slipped ({}; steps in their lengths), tried together: none of the \
             steps helped alone while the others were missing",
            times.join(", ")
        ),
        validation: None,
        change: Some(change),
    };
    Some((finding, change))
}

/// The significant latencies of several strings as one finding and change
/// ([`Change::Latencies`]), its chi-square and share explained the sums of
/// the strings' own; `None` for fewer than two strings. Two strings read 6
/// ms late on the model simulator's stream of seed 4: each latency alone,
/// fitted at 6 ms on every fold, is refused (the earlier half's fold
/// 1.05 -> 1.14 mm with the other string's lag in the model's geometry),
/// and a latency every string shares stands in (decision record 0067).
pub(super) fn latencies_together(latencies: &[&Finding]) -> Option<(Finding, Change)> {
    let mut lags = [None; STRINGS];
    let mut strings = Vec::new();
    let mut each = Vec::new();
    for f in latencies {
        if let Some(Change::Effect(EffectTerm {
            string,
            effect: Effect::Latency { latency_s },
        })) = f.change
        {
            if usize::from(string) < STRINGS && lags[usize::from(string)].is_none() {
                lags[usize::from(string)] = Some(latency_s);
                strings.push(string);
                each.push(format!("string {string} {:.1} ms", 1e3 * latency_s));
            }
        }
    }
    if strings.len() < 2 {
        return None;
    }
    strings.sort_unstable();
    let change = Change::Latencies(lags);
    let finding = Finding {
        family: Family::Latency,
        strings,
        variable: Variable::Speed,
        amplitude_mm: latencies.iter().map(|f| f.amplitude_mm).fold(0.0, f64::max),
        explained: latencies.iter().map(|f| f.explained).sum(),
        added: false,
        chi2: latencies.iter().map(|f| f.chi2).sum(),
        description: format!(
            "several strings are read late ({}; their lengths lag their speed), tried together: \
             none of the latencies helped alone while the others were missing",
            each.join(", ")
        ),
        validation: None,
        change: Some(change),
    };
    Some((finding, change))
}
