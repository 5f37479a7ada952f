//! The order of the loop's steps: each spool's own rate, the layer tables
//! and the effects ([`LoopState::rates_tables_and_effects`]); a term on
//! time of every string or the layer tables first; a term of the whole
//! device or one string's.
//!
//! **A term on time of every string, or the layer tables.**
//! The loop tries each spool's own rate and the layer tables before any
//! effect. On a lattice walked plane by plane each string's payout goes
//! with time, so a table of the payout fitted per string takes part of a
//! drift; what is left of the drift may then no longer show where the
//! session comes back to a place, or fit alike on the earlier and the
//! later half, and the drift is refused. When the model took rates or
//! tables and keeps no term on time, the loop is run once more from the
//! base model: the spool rates, then the terms on time of every string
//! alone (a shared drift or creep, the drifts of every string; one
//! string's term is a stand-in there more often than not), the rates
//! judged again after them, then the tables and the effects as before.
//! Of the two models, the one the blocked folds prefer by the loop's own
//! rule is kept ([`judge`], the order's gain held to the gain any change
//! must make), and the report says which order was taken and what the
//! other reached (decision record 0057).
//!
//! **A term that follows a string's motion, or the layer tables.**
//! On a stream the strings move back and forth; where a string's motion
//! goes with its payout along the session, a table of its payout takes
//! part of a backlash or a latency of that string, which is then refused.
//! When such a term was refused on a string that took a table, the loop is
//! run once more from the base model with the terms that follow the
//! motion first ([`LoopState::motion_terms_first`]), and the two models
//! are judged as the orders above (decision record 0070).
//!
//! **A term of the whole device, or one string's**
//! ([`LoopState::prefer_frame_wide`], decision record 0058); **a term
//! shared by every string, or each string its own**
//! ([`LoopState::prefer_each_string`], decision record 0063).

use super::describe::stage_name;
use super::trials::is_spool_rates;
use super::{drifts_with_time, same_term, Finding, LoopState, StringLayers, Variable};
use crate::model::identify::IdentifyError;
use crate::model::validate::judge;

use super::{adds_a_drift, adds_a_motion_term, Change, Proposals};

/// What an order other than the tables first tries before them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum FirstStep {
    /// A term on time of every string (decision record 0057).
    TimeTerms,
    /// A term that follows a string's motion, a backlash or a latency,
    /// refused on a string that took a table (decision record 0070).
    MotionTerms,
}

impl FirstStep {
    /// Whether `change` adds a term of this step.
    fn adds(self, change: Change) -> bool {
        match self {
            FirstStep::TimeTerms => adds_a_drift(change),
            FirstStep::MotionTerms => adds_a_motion_term(change),
        }
    }

    /// The findings of this step's kind in the order with the tables
    /// first.
    fn reads(self, variable: Variable) -> bool {
        match self {
            FirstStep::TimeTerms => variable == Variable::Time,
            FirstStep::MotionTerms => matches!(variable, Variable::Direction | Variable::Speed),
        }
    }

    /// Why the tables took part of it.
    fn why_the_tables_took_it(self) -> &'static str {
        match self {
            FirstStep::TimeTerms => "on a session whose payout goes with time they took part of it",
            FirstStep::MotionTerms => {
                "a table of the payout took part of it where the string's motion goes with \
                 its payout along the session"
            }
        }
    }
}

/// What [`LoopState::rates_tables_and_effects`] chose: each string's layer
/// spacing, and whether spool rates or tables were taken before the
/// effects.
pub(super) struct Sequence {
    pub(super) layers: Vec<StringLayers>,
    pub(super) took_before_effects: bool,
}

impl LoopState<'_> {
    /// The loop's steps from the current model: each spool's own rate, the
    /// layer tables, the effects, the tables and then the rates again when
    /// refused and a term came after them, and the rates and tables judged
    /// again when a term on time came after them.
    pub(super) fn rates_tables_and_effects(&mut self) -> Result<Sequence, IdentifyError> {
        let time_term_before = self.keeps_time_term();
        let mut layers = Vec::new();
        let mut rates_added = false;
        let rates_tried = self.spool_rates_held();
        if rates_tried {
            self.try_spool_rates()?;
            rates_added = !self.structure.hold_kappa_each;
        }
        let stages_after_rates = self.stages.len();
        // Layer tables first; refused ones are tried once more after the
        // effects (an effect the model lacked, a heavy string's sag, can hide
        // what the tables gain until it is in).
        let mut layers_refused = false;
        let mut layers_added = false;
        if self.config.layer_tables {
            let (added, choice) = self.try_layer_tables()?;
            layers = choice;
            layers_refused = added == Some(false);
            layers_added = added == Some(true);
        }
        let effects_before = self.stages.len();
        self.add_effects(Proposals::All)?;
        if layers_refused && self.stages.len() > effects_before {
            let (added, choice) = self.try_layer_tables()?;
            if added == Some(true) {
                layers = choice;
                // What the tables' staircase hid (a slip's jump among the
                // layers' jumps) is looked for again with them in.
                self.add_effects(Proposals::All)?;
            }
        }
        // Spool rates and tables taken before a term on time that the model
        // keeps: on a lattice walked plane by plane each string's payout goes
        // with time, and they took part of what the drift now takes. They are
        // judged again from the model without them, as if the drift had come
        // first (`rejudge`).
        let time_term_after = !time_term_before && self.keeps_time_term();
        if rates_added && time_term_after {
            self.rejudge_spool_rates()?;
        }
        if layers_added && time_term_after {
            if let Some(choice) = self.rejudge_layer_tables()? {
                layers = choice;
            }
        }
        // Spool rates refused at first are tried once more from the model
        // the steps since have built, when they took or dropped a term, as
        // the tables are after the effects (record 0065).
        if rates_tried
            && !rates_added
            && self.stages.len() > stages_after_rates
            && self.try_spool_rates_again()?
        {
            self.add_effects(Proposals::All)?;
        }
        Ok(Sequence {
            layers,
            took_before_effects: rates_added || layers_added,
        })
    }

    /// Each spool's own rate, refused when first tried, tried again from
    /// the model the terms taken since then built: whether it is taken.
    /// Before the layer tables and the effects, the residual a spool's own
    /// rate is fitted to holds the layers' staircase and what the effects
    /// take; a fold that sees a smaller part of the workspace (a stream's
    /// outer shell, fitted on its inner region) then extrapolates the rates
    /// by mm where the whole session does not, and the rates are refused
    /// for what the model lacked (decision record 0065). One finding stays,
    /// the second try's, saying why the first refused them.
    fn try_spool_rates_again(&mut self) -> Result<bool, IdentifyError> {
        let first = self
            .findings
            .iter()
            .rposition(|f| is_spool_rates(f, self.nominal) && !f.added && f.validation.is_some());
        // Not judged at first (a fold too small for the freed rates): the
        // folds are no larger now.
        let Some(first) = first.map(|k| self.findings.remove(k)) else {
            return Ok(false);
        };
        self.try_spool_rates()?;
        let taken = !self.structure.hold_kappa_each;
        if let Some(again) = self.findings.last_mut() {
            let why = first
                .validation
                .as_ref()
                .map_or_else(String::new, |c| c.reason.clone());
            again.description = format!(
                "{}; tried again once the terms taken after the first try were in (first try, \
                 before them: {why})",
                again.description
            );
        }
        Ok(taken)
    }

    /// Whether the model holds a term on time (a drift or a creep).
    pub(super) fn keeps_time_term(&self) -> bool {
        self.structure
            .effects
            .iter()
            .any(|t| drifts_with_time(&t.effect))
    }

    /// Whether each spool's own rate is held to the shared one on a device
    /// of several strings: whether it can be tried.
    fn spool_rates_held(&self) -> bool {
        self.structure.hold_kappa_each && self.nominal.layout.count() > 1
    }

    /// After a term of one string was taken (this state; `before`: the
    /// model without it), the terms of the whole frame or the tracked body
    /// the same diagnosis proposed and the round has not tried: the first
    /// taken from `before` whose blocked folds reach a lower mean than the
    /// one-string term's replaces it (the one-string term is proposed
    /// again, or not, by the next diagnosis). A term of one string stands
    /// in more often; one that takes what a term of the whole device
    /// explains better must not come first (decision record 0058).
    pub(super) fn prefer_frame_wide(
        &mut self,
        before: Self,
        frame_wide: &[Finding],
        tried: &[Finding],
    ) -> Result<(), IdentifyError> {
        for f in frame_wide
            .iter()
            .filter(|f| !tried.iter().any(|t| same_term(t, f)))
        {
            let mut alternative = before.clone();
            if alternative.try_rival(f.clone(), self.validation.held.mean_mm)?
                && alternative.validation.held.mean_mm < self.validation.held.mean_mm
            {
                *self = alternative;
                return Ok(());
            }
        }
        Ok(())
    }

    /// After a term shared by every string was taken (this state;
    /// `before`: the model without it), the terms of every string, each its
    /// own coefficients, on the same variable, that the same diagnosis
    /// proposed and the round has not tried: the first taken from `before`
    /// whose blocked folds gain on the shared term's as a change must
    /// ([`judge`], the loop's `min_relative_gain`) replaces it, and the
    /// shared term is reported with the comparison. The proposals are
    /// ranked by chi-square, and a group of every string ranks below a
    /// shared term of two columns that explains less beyond the model's
    /// span per column (a sag many times what the strings weigh standing
    /// in for strings of other stiffnesses, decision record 0063).
    pub(super) fn prefer_each_string(
        &mut self,
        before: Self,
        each_string: &[Finding],
        tried: &[Finding],
    ) -> Result<(), IdentifyError> {
        let Some(shared) = self.findings.last().filter(|f| f.added).cloned() else {
            return Ok(());
        };
        for f in each_string
            .iter()
            .filter(|f| f.variable == shared.variable && !tried.iter().any(|t| same_term(t, f)))
        {
            // The judge below takes a change only where the mean falls.
            let mut alternative = before.clone();
            if !alternative.try_rival(f.clone(), self.validation.held.mean_mm)? {
                continue;
            }
            let check = judge(
                &self.validation,
                &alternative.validation,
                None,
                self.config.min_relative_gain,
            );
            if check.accepted {
                let mut replaced = shared;
                replaced.added = false;
                if let Some(v) = replaced.validation.as_mut() {
                    v.accepted = false;
                    v.reason = format!(
                        "not added: replaced by {}, proposed by the same diagnosis and tried \
                         from the model without it: {}",
                        stage_name(f),
                        check.reason.trim_start_matches("added: ")
                    );
                }
                *self = alternative;
                self.report(replaced);
                return Ok(());
            }
        }
        Ok(())
    }

    /// The loop from this (the base) model with the terms on time of every
    /// string tried before the tables: `None` when none is taken there,
    /// else the model after the tables and effects that follow it, and its
    /// layer choice.
    pub(super) fn time_terms_first(
        mut self,
    ) -> Result<Option<(Self, Vec<StringLayers>)>, IdentifyError> {
        let rates_held = self.spool_rates_held();
        if rates_held {
            self.try_spool_rates()?;
        }
        let rates_added = rates_held && !self.structure.hold_kappa_each;
        self.add_effects(Proposals::TimeTerms)?;
        if !self.keeps_time_term() {
            return Ok(None);
        }
        if rates_added {
            self.rejudge_spool_rates()?;
        }
        let sequence = self.rates_tables_and_effects()?;
        Ok(Some((self, sequence.layers)))
    }

    /// Whether a term that follows a string's motion (a backlash, a
    /// latency) was proposed and refused on a string that took a layer
    /// table (`layers`, the tables this model took).
    pub(super) fn refused_a_motion_term_on_a_table(&self, layers: &[StringLayers]) -> bool {
        let tabled: Vec<u8> = layers
            .iter()
            .filter(|l| l.step_counts.is_some())
            .map(|l| l.string)
            .collect();
        self.findings.iter().any(|f| {
            !f.added
                && f.change.is_some_and(adds_a_motion_term)
                && f.strings.iter().any(|s| tabled.contains(s))
        })
    }

    /// The loop from this (the base) model with the terms that follow the
    /// strings' motion (a backlash, a latency) tried before the tables:
    /// `None` when none is taken there, else the model after the tables
    /// and effects that follow it, and its layer choice.
    pub(super) fn motion_terms_first(
        mut self,
    ) -> Result<Option<(Self, Vec<StringLayers>)>, IdentifyError> {
        let rates_held = self.spool_rates_held();
        if rates_held {
            self.try_spool_rates()?;
        }
        let before = self.stages.len();
        self.add_effects(Proposals::MotionTerms)?;
        if self.stages.len() == before {
            return Ok(None);
        }
        let sequence = self.rates_tables_and_effects()?;
        Ok(Some((self, sequence.layers)))
    }

    /// The better of this model (tables first) and `first`'s (`step`'s
    /// terms first, with `first_layers`): `first` is taken when its
    /// blocked folds gain on this one's as a change must; this state
    /// becomes the one taken, its report saying why. The layer choice of
    /// the one taken.
    pub(super) fn the_better_order(
        &mut self,
        (first, first_layers): (Self, Vec<StringLayers>),
        layers: Vec<StringLayers>,
        step: FirstStep,
    ) -> Vec<StringLayers> {
        let check = judge(
            &self.validation,
            &first.validation,
            None,
            self.config.min_relative_gain,
        );
        let names: Vec<String> = first
            .findings
            .iter()
            .filter(|f| f.added && f.change.is_some_and(|c| step.adds(c)))
            .map(stage_name)
            .collect();
        let names = names.join(", ");
        if !check.accepted {
            // The term stays in this order's report: refused here where the
            // rates and tables came first, and as the first step it did not
            // lead to a better model.
            let why = format!(
                "tried before the layer tables ({names}), it leads to a model the blocked \
                 folds do not prefer to this one ({})",
                check.reason
            );
            for f in self
                .findings
                .iter_mut()
                .filter(|f| !f.added && step.reads(f.variable) && f.change.is_some())
            {
                f.description += &format!("; {why}");
            }
            return layers;
        }
        let mut first = first;
        let why = format!(
            "; taken before the layer tables: {}, and it was not taken after them; the model \
             with it first is preferred on the blocked folds to the one with the tables first \
             ({})",
            step.why_the_tables_took_it(),
            check.reason
        );
        if let Some(stage) = first
            .stages
            .iter_mut()
            .find(|s| s.finding.change.is_some_and(|c| step.adds(c)))
        {
            stage.finding.description += &why;
        }
        if let Some(f) = first
            .findings
            .iter_mut()
            .find(|f| f.added && f.change.is_some_and(|c| step.adds(c)))
        {
            f.description += &why;
        }
        *self = first;
        first_layers
    }
}
