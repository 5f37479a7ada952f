//! Trials before the effect families: each spool's own thinning rate, and
//! layer tables in the string law ([`crate::model::layers`]), each judged on
//! the held-out folds as the loop judges a change.

use spidar_core::model::{Frame, MAX_LAYER_STEP_LOG2};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::model::identify::{identify, Identification, IdentifyError, Start, Structure};
use crate::model::layers::{self, StringLayers, TableLevel};
use crate::model::validate::{
    folds, judge, validate_by, validate_fits, Check, FoldScope, Folds, Validation,
};

use super::vocabulary::{Family, Finding, LoopConfig, Variable};

/// What [`add_layer_tables`] tried.
pub(super) struct LayerTry {
    pub(super) choice: Vec<StringLayers>,
    /// `None` when no string's spacing helped (nothing to check).
    pub(super) finding: Option<Finding>,
    /// The refit with the tables and its validation, when accepted.
    pub(super) added: Option<(Identification, Validation)>,
}

/// Layer tables ([`crate::model::layers`]) on the strings whose held-out string
/// residual they lower, kept when [`judge`] accepts them on the blocked
/// folds with every fold refitting geometry and tables on its own rows.
pub(super) fn add_layer_tables(
    train: &[Observation],
    nominal: &Frame<f64>,
    id: &Identification,
    structure: &Structure,
    before: &Validation,
    config: &LoopConfig,
) -> Result<LayerTry, IdentifyError> {
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let (kind, all_folds) = folds(&tracked);
    let spacing_folds = match kind {
        Folds::Blocked => &all_folds[2..],
        Folds::Interleaved => &all_folds[..],
    };
    let mut choice = layers::choose_spacings(id, train, spacing_folds);
    let steps = layers::steps_of(&choice);
    if choice.iter().all(|c| c.step_counts.is_none()) {
        return Ok(LayerTry {
            choice,
            finding: None,
            added: None,
        });
    }
    let cold = layers::without_layers(id);
    let validate_steps = |steps: &[Option<u8>; STRINGS]| {
        validate_by(train, FoldScope::Judged, |rows| {
            let plain = identify(rows, nominal, &cold, structure)?;
            layers::identify_with_layers(
                rows,
                nominal,
                &plain,
                structure,
                steps,
                TableLevel::Dropped,
            )
        })
        .map(|(after, _)| after)
    };
    let judged = judge_layer_steps(validate_steps, steps, before, config, &mut choice)?;
    let refit = if judged.check.accepted {
        Some(layers::identify_with_layers(
            train,
            nominal,
            id,
            structure,
            &judged.steps,
            TableLevel::Kept,
        )?)
    } else {
        None
    };
    if let Some(refit) = &refit {
        for c in choice.iter_mut().filter(|c| c.step_counts.is_some()) {
            c.knots = refit.winding.layers[usize::from(c.string)]
                .knots_mm
                .as_slice()
                .len();
        }
    }
    let finding = layers_finding(&choice, id, judged.check, &judged.coarser_note);
    Ok(LayerTry {
        choice,
        finding: Some(finding),
        added: refit.map(|r| (r, judged.after)),
    })
}

/// The layer tables' check ([`judge_layer_steps`]).
struct LayerJudgement {
    /// Each string's knot spacing (log2 counts) the check judged.
    steps: [Option<u8>; STRINGS],
    after: Validation,
    check: Check,
    /// Said when the spacings chosen per string were refused and knots
    /// twice as far apart taken; empty otherwise.
    coarser_note: String,
}

/// Judges the tables at the spacings chosen per string (`steps`,
/// validated by `validate_steps`) against `before`; when refused, tries
/// once knots twice as far apart, and when those are accepted, `choice`
/// follows them.
fn judge_layer_steps(
    validate_steps: impl Fn(&[Option<u8>; STRINGS]) -> Result<Validation, IdentifyError>,
    steps: [Option<u8>; STRINGS],
    before: &Validation,
    config: &LoopConfig,
    choice: &mut [StringLayers],
) -> Result<LayerJudgement, IdentifyError> {
    let mut steps = steps;
    let mut after = validate_steps(&steps)?;
    let mut check = judge(before, &after, None, config.min_relative_gain);
    let mut coarser_note = String::new();
    if !check.accepted {
        // Refused (most often on the max of the shell fold, which the
        // finest spacing follows least smoothly beyond its counts): one try
        // with knots twice as far apart on every string.
        let coarser = steps.map(|s| s.map(|s| s.saturating_add(1).min(MAX_LAYER_STEP_LOG2)));
        let after2 = validate_steps(&coarser)?;
        let check2 = judge(before, &after2, None, config.min_relative_gain);
        if check2.accepted {
            coarser_note = format!(
                " (the spacing chosen per string was refused, {}; knots twice as far apart were \
                 taken)",
                check.reason
            );
            steps = coarser;
            after = after2;
            check = check2;
            for c in choice.iter_mut() {
                if let Some(step) = c.step_counts {
                    let step = step.saturating_mul(2);
                    c.step_counts = Some(step);
                    if let Some(&(_, rms)) = c.tried.iter().find(|t| t.0 == step) {
                        c.held_rms_with_mm = rms;
                    }
                }
            }
        }
    }
    Ok(LayerJudgement {
        steps,
        after,
        check,
        coarser_note,
    })
}

/// The `layers` finding of the strings that chose a spacing: each string's
/// spacing in turns, its table's peak to peak and its held-out string rms
/// without and with the table; `check` the tables' check.
fn layers_finding(
    choice: &[StringLayers],
    id: &Identification,
    check: Check,
    coarser_note: &str,
) -> Finding {
    let chosen: Vec<&StringLayers> = choice.iter().filter(|c| c.step_counts.is_some()).collect();
    let ss = |rms: f64| rms * rms;
    let without: f64 = chosen.iter().map(|c| ss(c.held_rms_without_mm)).sum();
    let with: f64 = chosen.iter().map(|c| ss(c.held_rms_with_mm)).sum();
    let amplitude_mm = chosen
        .iter()
        .map(|c| c.peak_to_peak_mm / 2.0)
        .fold(0.0, f64::max);
    let per_string: Vec<String> = chosen
        .iter()
        .map(|c| {
            let turns = c.step_counts.map_or(0.0, |s| {
                f64::from(s) / f64::from(id.laws[usize::from(c.string)].counts_per_rev)
            });
            format!(
                "string {} every {turns:.2} turns, {:.1} mm peak to peak, held-out string rms \
                 {:.3} -> {:.3} mm",
                c.string, c.peak_to_peak_mm, c.held_rms_without_mm, c.held_rms_with_mm
            )
        })
        .collect();
    Finding {
        family: Family::Layers,
        strings: chosen.iter().map(|c| c.string).collect(),
        variable: Variable::WoundLength,
        amplitude_mm,
        explained: if without > 0.0 {
            1.0 - with / without
        } else {
            0.0
        },
        added: false,
        chi2: 0.0,
        description: format!(
            "the spool departs from the smooth winding law (layers): {}{coarser_note}",
            per_string.join("; ")
        ),
        validation: Some(check.summarized()),
        change: None,
    }
}

/// Whether `f` is [`free_spool_rates`]' finding on `nominal`'s strings (a
/// `winding` of every active string without a change of its own).
pub(super) fn is_spool_rates(f: &Finding, nominal: &Frame<f64>) -> bool {
    f.family == Family::Winding
        && f.change.is_none()
        && f.strings
            .iter()
            .copied()
            .eq(nominal.layout.indices().map(|i| i as u8))
}

/// Each spool's own thinning rate ([`Structure::hold_kappa_each`] off),
/// kept when [`judge`] accepts it on the validation folds: the finding (a
/// `winding` on every active string, `added` as judged) and, when
/// accepted, the refit with its structure and validation.
#[allow(clippy::type_complexity)]
pub(super) fn free_spool_rates(
    train: &[Observation],
    nominal: &Frame<f64>,
    id: &Identification,
    structure: &Structure,
    before: &Validation,
    config: &LoopConfig,
) -> Result<(Finding, Option<(Identification, Structure, Validation)>), IdentifyError> {
    let free = Structure {
        hold_kappa_each: false,
        ..structure.clone()
    };
    let finding = |description: String, explained: f64, validation: Option<Check>| Finding {
        family: Family::Winding,
        strings: nominal.layout.indices().map(|i| i as u8).collect(),
        variable: Variable::WoundLength,
        amplitude_mm: 0.0,
        explained,
        added: validation.as_ref().is_some_and(|c| c.accepted),
        chi2: 0.0,
        description,
        validation,
        change: None,
    };
    let (after, _) = match validate_fits(train, nominal, id, &free, FoldScope::Judged) {
        Ok(v) => v,
        // A session just large enough for the base model's folds: the
        // shared rate stays, and the finding says why.
        Err(IdentifyError::TooFewRows { needed, got }) => {
            let why = format!(
                "each spool's own thinning rate not tried: a validation fold has {got} tracked \
                 rows, freeing the rates needs {needed}"
            );
            return Ok((finding(why, 0.0, None), None));
        }
        Err(e) => return Err(e),
    };
    let check = judge(before, &after, None, config.min_relative_gain);
    let explained = 1.0 - after.held.mean_mm / before.held.mean_mm.max(1e-12);
    let added = if check.accepted {
        let refit = identify(train, nominal, &Start::from_identification(id), &free)?;
        Some((refit, free, after))
    } else {
        None
    };
    let rates = added.as_ref().map_or_else(String::new, |(refit, _, _)| {
        let each: Vec<String> = refit
            .frame
            .layout
            .indices()
            .map(|i| format!("{i}: {:+.5}", refit.winding.kappa_each_mm[i]))
            .collect();
        format!(
            " (shared {:.5} mm/rad^2; each string's departure {})",
            refit.winding.kappa_mm,
            each.join(", ")
        )
    });
    let description = format!(
        "each spool thins at its own rate as string is paid out (spools of other widths, packing \
         or pitch){rates}"
    );
    Ok((
        finding(description, explained, Some(check.summarized())),
        added,
    ))
}
