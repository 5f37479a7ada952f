//! How far the anchors may be from the drawing: the identification's prior
//! on each anchor, chosen on held-out rows when the geometry does not say.
//!
//! A frame built to its drawing has its string exits within millimetres of
//! it; a rig measured by hand (a cable robot whose exits are pulleys tens
//! of mm off the frame's corners) has them 30 to 130 mm off. A tight prior
//! keeps the anchors where the data would move them and costs most outside
//! the training area; a loose one lets a few rows move them where noise
//! says. Which holds is a fact of the rig, so the data choose: the base
//! model is fitted with each candidate tolerance on the fitting rows of
//! held-out folds and judged on the rows they hold out (the loop's judge,
//! every string alike). The tightest candidate stays unless a looser one
//! lowers the held-out mean by the loop's [`LoopConfig::min_relative_gain`].
//! A geometry that declares `anchor_sd_mm` is taken at its word. On the
//! same folds, the rows' robust reweighing is kept or dropped for plain
//! least-squares weights ([`choose`]).

use rayon::prelude::*;
use serde::Serialize;
use spidar_core::model::Frame;
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::data::stats::ErrorStats;
use crate::model::diagnose::LoopConfig;
use crate::model::identify::{identify, rows_needed_for, Identification, Priors, Start};
use crate::model::validate::{choice_folds, held_out_error_list, preferred, Preferred};

/// The tolerances tried (mm, one sd per coordinate): the drawing's
/// ([`Priors::default`]), four and ten times it (a hand-measured rig).
pub fn candidates_mm() -> [f64; 3] {
    let drawing = Priors::default().anchor_sd_mm;
    [drawing, 4.0 * drawing, 10.0 * drawing]
}

/// The share of its sd below which the drawing's tolerance pulls every
/// anchor coordinate of every fold's model toward the drawing for the
/// looser tolerances not to be tried: none could then move an anchor by
/// more than this. Measured (record 0052): where the largest pull was
/// 0.006-0.13 sd (the 30,000-row sessions, the 6,000-row wall robot) the
/// candidates' held-out means agreed within 0.15 %; at 0.86 sd (500 rows of
/// the model simulator) the looser ones held out 8 % worse. The difference
/// grows as the pull squared: about 0.4 % at 0.2 sd, a fifth of the loop's
/// 2 % margin.
const DETERMINED_PULL_SHARE: f64 = 0.2;

/// One tolerance and its held-out error.
#[derive(Clone, Debug, Serialize)]
pub struct ToleranceScore {
    pub anchor_sd_mm: f64,
    pub held_out: ErrorStats,
}

/// What the folds said of the anchors' tolerance, and the choice.
#[derive(Clone, Debug, Serialize)]
pub struct ToleranceChoice {
    /// The tolerance the calibration used, mm (per anchor).
    pub anchor_sd_mm: [f64; STRINGS],
    /// The candidates (empty when the geometry declared it or the session
    /// has too few rows to hold any out).
    pub scores: Vec<ToleranceScore>,
    /// How the rows were held out.
    pub folds: String,
    pub reason: String,
    /// The rows are reweighed robustly (Huber, Tukey) after the
    /// least-squares round; false: plain least-squares weights.
    pub robust: bool,
    /// The held-out error with plain least-squares weights at the chosen
    /// tolerance (`null` when not tried).
    pub unweighted: Option<ErrorStats>,
}

/// Chooses the anchors' tolerance for `train` (see the module doc), or
/// takes the geometry's (`config.anchor_sd_mm`); then whether the rows are
/// reweighed robustly, on the same folds: the plain least-squares weights
/// are taken when they lower the held-out mean by the loop's margin (a rig
/// whose model error is smooth and shared extrapolates better balanced
/// than with its largest residuals down-weighted; a misbehaving motor's
/// rows want the robust weights). Every fold fits from the session's
/// start: a fold started from the whole session's fit chose other
/// tolerances on a 12-row session, and worse ones.
pub fn choose(
    train: &[Observation],
    nominal: &Frame<f64>,
    start: &Start,
    config: &LoopConfig,
) -> ToleranceChoice {
    let drawing = candidates_mm()[0];
    let tracked: Vec<&Observation> = train.iter().filter(|o| o.tracker.is_some()).collect();
    let structure = config.base_structure();
    let needed = rows_needed_for(&structure, nominal.layout);
    let (folds_name, folds) = choice_folds(&tracked, needed);
    let pick = |rows: &[usize]| -> Vec<&Observation> { rows.iter().map(|&k| tracked[k]).collect() };
    // Each fold's model at a tolerance, with its errors on the rows the
    // fold holds out.
    let fold_fits = |sd: [f64; STRINGS], robust: bool| -> Option<Vec<(Identification, Vec<f64>)>> {
        let mut s = structure.clone();
        s.priors.anchor_sd_each_mm = Some(sd);
        s.robust = robust;
        // Each fold's fit on its own core, as the loop's folds are.
        folds
            .par_iter()
            .map(|(fit, held)| {
                let id = identify(&pick(fit), nominal, start, &s).ok()?;
                let errors = held_out_error_list(&id, &pick(held));
                Some((id, errors))
            })
            .collect()
    };
    let pooled = |fits: &Option<Vec<(Identification, Vec<f64>)>>| -> ErrorStats {
        let errors: Vec<f64> = fits
            .iter()
            .flatten()
            .flat_map(|f| f.1.iter().copied())
            .collect();
        ErrorStats::of(&errors)
    };
    let held_out = |sd: [f64; STRINGS], robust: bool| pooled(&fold_fits(sd, robust));
    let mut choice = match config.anchor_sd_mm {
        Some(given) => ToleranceChoice {
            anchor_sd_mm: given,
            scores: Vec::new(),
            folds: folds_name.clone(),
            reason: "the geometry's `anchor_sd_mm`".into(),
            robust: true,
            unweighted: None,
        },
        None => {
            let at_drawing = fold_fits([drawing; STRINGS], true);
            let mut scores = vec![ToleranceScore {
                anchor_sd_mm: drawing,
                held_out: pooled(&at_drawing),
            }];
            // The drawing's prior pulls no anchor of any fold's model by
            // DETERMINED_PULL_SHARE of its sd: a looser one would move none
            // by more, and the models would hold out alike.
            let pull = at_drawing
                .as_ref()
                .filter(|f| !f.is_empty())
                .and_then(|fits| {
                    fits.iter()
                        .map(|(id, _)| largest_prior_pull(id, nominal))
                        .try_fold(0.0_f64, |a, p| p.map(|p| a.max(p)))
                });
            match pull.filter(|&p| p < DETERMINED_PULL_SHARE) {
                Some(pull) => ToleranceChoice {
                    anchor_sd_mm: [drawing; STRINGS],
                    scores,
                    folds: folds_name.clone(),
                    reason: format!(
                        "the drawing's {drawing} mm: the folds' data determine every anchor, and \
                         its prior moves none by {:.0} % of its sd (at most {:.1} %), so no \
                         looser tolerance was tried ({folds_name})",
                        100.0 * DETERMINED_PULL_SHARE,
                        100.0 * pull
                    ),
                    robust: true,
                    unweighted: None,
                },
                None => {
                    let looser: Vec<ToleranceScore> = candidates_mm()[1..]
                        .par_iter()
                        .map(|&sd| ToleranceScore {
                            anchor_sd_mm: sd,
                            held_out: held_out([sd; STRINGS], true),
                        })
                        .collect();
                    scores.extend(looser);
                    decide(
                        scores,
                        drawing,
                        folds_name.clone(),
                        config.min_relative_gain,
                    )
                }
            }
        }
    };
    if folds.is_empty() || !structure.robust {
        return choice;
    }
    let robust = choice
        .scores
        .iter()
        .find(|s| s.anchor_sd_mm == choice.anchor_sd_mm[0])
        .map(|s| s.held_out)
        .unwrap_or_else(|| held_out(choice.anchor_sd_mm, true));
    let plain = held_out(choice.anchor_sd_mm, false);
    if plain.mean_mm < robust.mean_mm * (1.0 - config.min_relative_gain) {
        choice.robust = false;
        choice.reason += &format!(
            "; plain least-squares weights: they lower the held-out mean {:.3} -> {:.3} mm \
             against the robust ones",
            robust.mean_mm, plain.mean_mm
        );
    } else {
        choice.reason += &format!(
            "; robust weights: plain ones do not lower the held-out mean {:.3} mm by {:.0} % \
             ({:.3} mm)",
            robust.mean_mm,
            100.0 * config.min_relative_gain,
            plain.mean_mm
        );
    }
    choice.unweighted = Some(plain);
    choice
}

/// The largest pull of the anchors' prior of `id` on one of their
/// coordinates, in that coordinate's sd: how far the prior moves the
/// estimate from where the data alone put it (`|estimate - drawing| *
/// sd_data^2 / sd_prior^2` for a Gaussian prior), over its sd. `None` when
/// a coordinate is not determined or the prior dominates it.
fn largest_prior_pull(id: &Identification, nominal: &Frame<f64>) -> Option<f64> {
    let mut largest: f64 = 0.0;
    for p in &id.parameters {
        let Some(coordinate) = p.name.strip_prefix("anchor") else {
            continue;
        };
        let (i, c) = coordinate.split_once('.')?;
        let i: usize = i.parse().ok()?;
        let c = ["x", "y", "z"].iter().position(|&n| n == c)?;
        let prior = p.prior_sd?;
        if !p.determined || !p.sd.is_finite() || p.sd <= 0.0 || p.sd >= prior {
            return None;
        }
        let data_variance = 1.0 / (1.0 / (p.sd * p.sd) - 1.0 / (prior * prior));
        let drawing = nominal.anchors.get(i)?[c];
        let pull = (p.value - drawing).abs() * data_variance / (prior * prior);
        largest = largest.max(pull / p.sd);
    }
    Some(largest)
}

/// The tightest tolerance unless a looser one lowers the held-out mean by
/// `min_gain`; then the one with the lowest mean.
fn decide(
    scores: Vec<ToleranceScore>,
    drawing: f64,
    folds: String,
    min_gain: f64,
) -> ToleranceChoice {
    let means: Vec<f64> = scores.iter().map(|s| s.held_out.mean_mm).collect();
    let first = means.first().copied().unwrap_or(f64::NAN);
    let Preferred { best, chosen } = preferred(&means, min_gain);
    let (sd, reason) = match best.map(|_| &scores[chosen]) {
        Some(b) if b.anchor_sd_mm != drawing => (
            b.anchor_sd_mm,
            format!(
                "{} mm lowers the held-out mean {:.3} -> {:.3} mm against the drawing's {drawing} mm ({folds})",
                b.anchor_sd_mm, first, b.held_out.mean_mm
            ),
        ),
        Some(_) => (
            drawing,
            format!(
                "the drawing's {drawing} mm: no looser tolerance lowers the held-out mean {first:.3} mm by {:.0} % ({folds})",
                100.0 * min_gain
            ),
        ),
        None => (
            drawing,
            format!("the drawing's {drawing} mm: the session has too few rows to hold any out"),
        ),
    };
    ToleranceChoice {
        anchor_sd_mm: [sd; STRINGS],
        scores,
        folds,
        reason,
        robust: true,
        unweighted: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn score(sd: f64, mean: f64) -> ToleranceScore {
        let mut held_out = ErrorStats::of(&[mean]);
        held_out.mean_mm = mean;
        ToleranceScore {
            anchor_sd_mm: sd,
            held_out,
        }
    }

    #[test]
    fn the_drawing_stays_unless_a_looser_tolerance_gains_the_loops_margin() {
        let kept = decide(
            vec![score(15.0, 1.0), score(60.0, 0.99)],
            15.0,
            "f".into(),
            0.02,
        );
        assert_eq!(kept.anchor_sd_mm[0], 15.0, "{}", kept.reason);
        let loose = decide(
            vec![score(15.0, 1.0), score(60.0, 0.9), score(150.0, 0.95)],
            15.0,
            "f".into(),
            0.02,
        );
        assert_eq!(loose.anchor_sd_mm[0], 60.0, "{}", loose.reason);
    }
}
