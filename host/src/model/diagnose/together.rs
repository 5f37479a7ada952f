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
/// ([`Change::Slips`], [`group`]); `None` for fewer than two strings.
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
    let description = format!(
        "several strings slipped ({}; steps in their lengths), tried together: none of the \
         steps helped alone while the others were missing",
        times.join(", ")
    );
    let change = Change::Slips(steps);
    Some(group(
        slips,
        (Family::Slip, strings),
        Variable::Time,
        description,
        change,
    ))
}

/// The significant latencies of several strings as one finding and change
/// ([`Change::Latencies`], [`group`]); `None` for fewer than two strings. Two strings read 6
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
    let description = format!(
        "several strings are read late ({}; their lengths lag their speed), tried together: \
         none of the latencies helped alone while the others were missing",
        each.join(", ")
    );
    let change = Change::Latencies(lags);
    Some(group(
        latencies,
        (Family::Latency, strings),
        Variable::Speed,
        description,
        change,
    ))
}

/// The finding of `members`' terms (one family's, on `strings`) tried as
/// one `change`: its largest amplitude, and its chi-square and share
/// explained the sums of the members' own (their terms lie on different
/// strings, nearly orthogonal).
fn group(
    members: &[&Finding],
    (family, mut strings): (Family, Vec<u8>),
    variable: Variable,
    description: String,
    change: Change,
) -> (Finding, Change) {
    strings.sort_unstable();
    let finding = Finding {
        family,
        strings,
        variable,
        amplitude_mm: members.iter().map(|f| f.amplitude_mm).fold(0.0, f64::max),
        explained: members.iter().map(|f| f.explained).sum(),
        added: false,
        chi2: members.iter().map(|f| f.chi2).sum(),
        description,
        validation: None,
        change: Some(change),
    };
    (finding, change)
}
