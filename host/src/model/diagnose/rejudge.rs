//! Terms judged again once a term on time came after them. On a lattice
//! walked plane by plane each string's payout goes with time, so layer
//! tables and each spool's own rate, which the loop tries before any
//! effect, can take a drift's error. When the model keeps a term on time,
//! they are judged again from the model without them, as they were judged
//! when first tried, and dropped (a stage saying so) when refused there.

use spidar_core::STRINGS;

use super::trials::{add_layer_tables, free_spool_rates};
use super::{Check, Family, Finding, LoopState, Validated, Variable};
use crate::model::identify::{identify, Identification, IdentifyError, Start, Structure};
use crate::model::layers::{self, StringLayers};
use crate::model::validate::{validate, FoldScope, Validation};

impl LoopState<'_> {
    /// Each spool's own rate judged again from the current model with the
    /// rates held to the shared one ([`free_spool_rates`] on that model's
    /// validation): kept when taken again, else dropped (the model with the
    /// shared rate, a stage saying so).
    pub(super) fn rejudge_spool_rates(&mut self) -> Result<(), IdentifyError> {
        let held = Structure {
            hold_kappa_each: true,
            ..self.structure.clone()
        };
        let (shared, without) =
            self.refit_and_validate(&Start::from_identification(&self.id), &held)?;
        let (finding, again) = free_spool_rates(
            &self.seen_train,
            self.nominal,
            &shared,
            &held,
            &without,
            self.config,
        )?;
        // Taken again, or not tried (a fold too small for the freed rates
        // beside the terms added since): the model stays as it is.
        if again.is_some() || finding.validation.is_none() {
            return Ok(());
        }
        let why = finding
            .validation
            .as_ref()
            .map_or_else(|| finding.description.clone(), |c| c.reason.clone());
        let finding = Finding {
            description: format!(
                "each spool's own thinning rate, added before a term on time, judged again from \
                 the model with the shared rate: {why}; dropped (the term on time takes what \
                 they took)"
            ),
            ..finding
        };
        let name = format!("without spool rates strings {:?}", finding.strings);
        let before = self.validation.clone();
        self.drop_term(name, finding, &before, shared, held, without);
        Ok(())
    }

    /// The layer tables judged again from the current model without them
    /// ([`add_layer_tables`] on that model's validation): kept as they are
    /// when the same strings and spacings are taken again, replaced when
    /// others are, dropped (the model without them, a stage saying so) when
    /// none are. The strings' new choice when it changed.
    pub(super) fn rejudge_layer_tables(
        &mut self,
    ) -> Result<Option<Vec<StringLayers>>, IdentifyError> {
        let before_steps = layers::steps_in(&self.id);
        let (plain, without) =
            self.refit_and_validate(&layers::without_layers(&self.id), &self.structure)?;
        let tried = add_layer_tables(
            &self.seen_train,
            self.nominal,
            &plain,
            &self.structure,
            &without,
            self.config,
        )?;
        let again = tried.added.is_some();
        if again && layers::steps_of(&tried.choice) == before_steps {
            return Ok(None);
        }
        let tabled: Vec<u8> = (0..STRINGS)
            .filter(|&i| before_steps[i].is_some())
            .map(|i| i as u8)
            .collect();
        let why = tried
            .finding
            .as_ref()
            .and_then(|f| f.validation.as_ref())
            .map_or_else(
                || "no string's table lowers its held-out residual".to_string(),
                |c| c.reason.clone(),
            );
        self.findings
            .retain(|f| f.family != Family::Layers || f.added);
        if again {
            // Other strings or spacings: the tables as tried again.
            let (added, choice) = self.take_layer_try(tried)?;
            debug_assert_eq!(added, Some(true));
            return Ok(Some(choice));
        }
        let finding = Finding {
            family: Family::Layers,
            strings: tabled.clone(),
            variable: Variable::WoundLength,
            amplitude_mm: 0.0,
            explained: 0.0,
            added: true,
            chi2: 0.0,
            description: format!(
                "the layer tables on strings {tabled:?}, added before a term on time, judged \
                 again from the model without them: {why}; dropped (the term on time takes \
                 what they took)"
            ),
            validation: None,
            change: None,
        };
        let name = format!("without layer tables strings {tabled:?}");
        let (before, structure) = (self.validation.clone(), self.structure.clone());
        self.drop_term(name, finding, &before, plain, structure, without);
        Ok(Some(tried.choice))
    }

    /// The model refitted from `start` with `structure`, and its
    /// validation on the folds every change is judged on.
    fn refit_and_validate(
        &self,
        start: &Start,
        structure: &Structure,
    ) -> Result<(Identification, Validation), IdentifyError> {
        let refit = identify(&self.seen_train, self.nominal, start, structure)?;
        let validation = validate(
            &self.seen_train,
            self.nominal,
            &refit,
            structure,
            FoldScope::Judged,
        )?;
        Ok((refit, validation))
    }

    /// Takes the model without a term judged again and refused (`reduced`,
    /// its `structure` and `validation`): a stage `name` whose finding says
    /// why and carries the held-out means from the model `before`.
    fn drop_term(
        &mut self,
        name: String,
        finding: Finding,
        before: &Validation,
        reduced: Identification,
        structure: Structure,
        validation: Validation,
    ) {
        let finding = Finding {
            validation: Some(Check {
                before: before.summary(),
                after: validation.summary(),
                stability_chi2: None,
                accepted: true,
                reason: format!(
                    "dropped: held-out mean {:.3} -> {:.3} mm without it",
                    before.held.mean_mm, validation.held.mean_mm
                ),
            }),
            added: true,
            change: None,
            ..finding
        };
        let validated = Validated {
            validation,
            from: reduced.clone(),
        };
        self.accept(name, finding, reduced, structure, validated, None);
    }
}
