//! What kind of term a change to the model adds: on every string or one,
//! on time, following the strings' motion, a step in time; and which of
//! a diagnosis's proposals a step of the loop tries ([`Proposals`]).

use super::{Change, Finding, Variable};
use spidar_core::model::{Effect, EffectTerm, EVERY_STRING};

/// Whether `change`'s terms are on every string: one shared term, or one
/// term of each string ([`Change::Drifts`]).
pub(super) fn on_every_string(change: Change) -> bool {
    matches!(change, Change::Drifts(_))
        || change
            .effect_terms()
            .iter()
            .all(|t| t.string == EVERY_STRING)
}

/// Which proposals [`LoopState::add_effects`](super::LoopState::add_effects) tries.
#[derive(Clone, Copy, PartialEq)]
pub(super) enum Proposals {
    All,
    /// Terms on time of every string only (a shared drift or creep, the
    /// drifts of every string at their own rates; findings without a
    /// change, such a term the revisits do not show, are reported).
    TimeTerms,
    /// Terms that follow the string's motion (a backlash, a latency).
    MotionTerms,
}

impl Proposals {
    pub(super) fn takes(self, finding: &Finding) -> bool {
        match self {
            Proposals::All => true,
            Proposals::TimeTerms => finding.change.map_or(
                finding.variable == Variable::Time && finding.strings.len() != 1,
                |change| adds_a_drift(change) && on_every_string(change),
            ),
            Proposals::MotionTerms => finding.change.is_some_and(adds_a_motion_term),
        }
    }
}

/// The times of the steps in time (slips) `change` adds; `None` for a
/// change that adds none.
pub(super) fn steps_of(change: Change) -> Option<Vec<f64>> {
    match change {
        Change::Effect(EffectTerm {
            effect: Effect::Slip { at_s, .. },
            ..
        }) => Some(vec![at_s]),
        Change::Slips(slips) => Some(slips.iter().flatten().map(|s| s.0).collect()),
        _ => None,
    }
}

/// Whether two findings are of one family on the same strings.
pub(super) fn same_term(a: &Finding, b: &Finding) -> bool {
    a.family == b.family && a.strings == b.strings
}

/// Whether `change` adds a term that follows the string's motion: a
/// backlash (its direction) or a latency (its speed).
pub(super) fn adds_a_motion_term(change: Change) -> bool {
    change
        .effect_terms()
        .iter()
        .any(|t| matches!(t.effect, Effect::Backlash { .. } | Effect::Latency { .. }))
}

/// Whether `change` adds a drift or a creep (of one string or of every
/// string): a time term, judged forward and on its own rows as a drift.
pub(super) fn adds_a_drift(change: Change) -> bool {
    change
        .effect_terms()
        .iter()
        .any(|t| drifts_with_time(&t.effect))
}

/// Whether `effect` is a drift or a creep: a length that changes steadily
/// with the time since home (a slip is a step).
pub(super) fn drifts_with_time(effect: &Effect) -> bool {
    matches!(effect, Effect::Drift { .. } | Effect::Creep { .. })
}

/// Whether `change` adds a term on one string (not a slip, not a shared
/// term).
pub(super) fn one_string_term(change: Change) -> bool {
    matches!(
        change,
        Change::Effect(EffectTerm { string, effect })
            if string != EVERY_STRING && !matches!(effect, Effect::Slip { .. })
    )
}

/// Whether `change` must gain what a term of one string must
/// ([`LoopConfig::min_relative_gain_one_string`](super::LoopConfig::min_relative_gain_one_string)): a term of one string, or
/// several such terms tried together (the latencies of several strings,
/// decision record 0067).
pub(super) fn held_to_one_string_gain(change: Change) -> bool {
    one_string_term(change) || matches!(change, Change::Latencies(_))
}
