//! Which comes first: a term on time of every string, or the layer tables.
//!
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

use super::{Finding, LoopState, StringLayers, Variable};
use crate::model::identify::IdentifyError;
use crate::model::validate::judge;

use super::{adds_a_drift, Proposals};

impl LoopState<'_> {
    /// The loop from this (the base) model with the terms on time of every
    /// string tried before the tables: `None` when none is taken there,
    /// else the model after the tables and effects that follow it, and its
    /// layer choice.
    pub(super) fn time_terms_first(
        mut self,
    ) -> Result<Option<(Self, Vec<StringLayers>)>, IdentifyError> {
        let rates_free = self.structure.hold_kappa_each && self.nominal.layout.count() > 1;
        if rates_free {
            self.try_spool_rates()?;
        }
        let rates_added = rates_free && !self.structure.hold_kappa_each;
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

    /// The better of this model (tables first) and `first`'s (terms on
    /// time first, with `first_layers`): `first` is taken when its
    /// blocked folds gain on this one's as a change must; this state
    /// becomes the one taken, its report saying why. The layer choice of
    /// the one taken.
    pub(super) fn the_better_order(
        &mut self,
        (first, first_layers): (Self, Vec<StringLayers>),
        layers: Vec<StringLayers>,
    ) -> Vec<StringLayers> {
        let check = judge(
            &self.validation,
            &first.validation,
            None,
            self.config.min_relative_gain,
        );
        let time_terms: Vec<&Finding> = first
            .findings
            .iter()
            .filter(|f| f.added && f.change.is_some_and(adds_a_drift))
            .collect();
        let names: Vec<String> = time_terms.iter().map(|f| order_name(f)).collect();
        let names = names.join(", ");
        if !check.accepted {
            // The term on time stays in this order's report: refused here
            // where the rates and tables came first, and as the first step
            // it did not lead to a better model.
            let why = format!(
                "tried before the layer tables ({names}), it leads to a model the blocked \
                 folds do not prefer to this one ({})",
                check.reason
            );
            for f in self
                .findings
                .iter_mut()
                .filter(|f| !f.added && f.variable == Variable::Time && f.change.is_some())
            {
                f.description += &format!("; {why}");
            }
            return layers;
        }
        let mut first = first;
        let why = format!(
            "; taken before the layer tables: on a session whose payout goes with time they \
             took part of it, and it was not taken after them; the model with it first is \
             preferred on the blocked folds to the one with the tables first ({})",
            check.reason
        );
        if let Some(stage) = first
            .stages
            .iter_mut()
            .find(|s| s.finding.change.is_some_and(adds_a_drift))
        {
            stage.finding.description += &why;
        }
        if let Some(f) = first
            .findings
            .iter_mut()
            .find(|f| f.added && f.change.is_some_and(adds_a_drift))
        {
            f.description += &why;
        }
        *self = first;
        first_layers
    }
}

/// A time term's family and strings, for the report.
fn order_name(f: &Finding) -> String {
    format!("{} strings {:?}", super::family_name(f.family), f.strings)
}
