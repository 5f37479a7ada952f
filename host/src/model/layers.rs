//! Layer tables: the part of a spool's winding law no polynomial follows.
//!
//! A string wound in level layers has a constant radius within a layer and
//! steps by about one diameter at each layer change, so its payout is a
//! chain of straight pieces around the smooth law `r_home theta - kappa
//! theta^2`; the departure is a few mm peak to peak with a period of one layer
//! (tens of turns), uneven when the layers hold different numbers of turns
//! (decision record 0006, `docs/decisions/0006-independent-simulator.md`).
//! No effect family follows it (`winding` bends the whole range,
//! `eccentricity` has the period of one turn), so it gets a flexible term:
//! a [`LayerTable`] per string, piecewise linear in the encoder counts, held
//! constant beyond the counts it was fitted on (it cannot grow there).
//!
//! How it is fitted, per string, on the identified model's string residuals
//! (geometric length from the tracker minus model length):
//! - the knots cover the string's counts on the training session, `2^s`
//!   counts apart; the table is fitted by least squares together with a
//!   constant, a linear and a quadratic term in the pulley angle that are
//!   fitted and dropped (what the geometry and the winding polynomial can
//!   absorb stays theirs; a weak prior on each knot, [`KNOT_PRIOR_SD_MM`],
//!   settles the overlap), residuals of the abnormal motor's gross failures
//!   left out (beyond 5 robust standard deviations);
//! - the spacing (its complexity) is chosen by validation on the loop's
//!   blocked folds (later half from the earlier, earlier from the later,
//!   outer shell from the inner: the table is held beyond the fold's counts,
//!   so extrapolation is what the shell fold measures): the spacing with the
//!   least held-out string residual, if it lowers it by [`MIN_STRING_GAIN`];
//!   otherwise that string gets no table;
//! - the geometry is then refitted with the tables held and the tables
//!   refitted on its residuals ([`REFINE_ROUNDS`] times).
//!
//! Whether the tables are kept is decided as every change of the loop is
//! ([`crate::model::validate::judge`]): held-out position error on the blocked
//! folds, every fold refitting geometry *and tables* on its own rows.
//!
//! Tables the loop kept are then refitted with their level ([`TableLevel`]),
//! and a string's slips are fitted together with its table
//! ([`fit_table_with_slips`]): a table is a function of the counts, and
//! fitted on residuals with a step in time it takes the step's level and
//! bends to follow the rows on one side of it.

use std::borrow::Borrow;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use spidar_core::model::{
    Effect, EffectTerm, Frame, Knots, LayerTable, StringLaw, LAYER_KNOTS, MAX_LAYER_STEP_LOG2,
};
use spidar_core::string_law::{compile_string_law, pulley_angle};
use spidar_core::STRINGS;

use crate::data::observe::Observation;
use crate::data::stats::robust_centre_and_sd;
use crate::model::identify::{
    identify, string_residuals, Identification, IdentifyError, Start, Structure, GROSS_RESIDUAL_MM,
};

/// Prior standard deviation of each knot, mm: a layer departure is a few mm;
/// the prior only decides what a knot takes when the nuisance terms could
/// take it too.
pub const KNOT_PRIOR_SD_MM: f64 = 3.0;

/// Held-out string residual sum of squares a table must remove (relative)
/// for its string to get one.
pub const MIN_STRING_GAIN: f64 = 0.03;

/// Fewest residuals per knot a spacing needs on the rows it is fitted on.
pub const MIN_ROWS_PER_KNOT: usize = 8;

/// Fewest rows on each side of a slip for its step to be refitted with the
/// tables ([`crate::model::validate::MIN_STEP_SIDE_ROWS`], as a step is
/// judged).
const MIN_STEP_SIDE_ROWS: usize = crate::model::validate::MIN_STEP_SIDE_ROWS;

/// Coarser spacings tried after the finest that fits [`LAYER_KNOTS`] knots.
pub const COARSER_SPACINGS: u8 = 4;

/// Geometry refits with the tables held, each followed by a table refit.
/// Two: of one, two and three rounds, the best final held-out mean and
/// worst max on independent devices (a third round changes the effects
/// the loop adds after the tables, not the tables themselves).
pub const REFINE_ROUNDS: usize = 2;

/// Who takes a string's level (its mean departure) when a layer table is
/// fitted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TableLevel {
    /// A constant fitted with the table and dropped (with the `theta` and
    /// `theta^2` terms): the table's level is what its knots' prior leaves.
    /// How the tables are chosen and judged: a table with a free level
    /// stands in for a drift or a step in time (a lattice collected plane
    /// by plane ties the counts to time), and is accepted on a drifting
    /// string whose spool has no layers.
    Dropped,
    /// The level is the table's: nothing else in the model takes a
    /// string's level (its payout law is 0 at home), so with the constant
    /// dropped an `offset` stands in for it (decision record 0030,
    /// `docs/decisions/0030-faulty-string-from-1mm.md`). How
    /// tables the loop accepted are refitted, and refitted with a slip.
    Kept,
}

/// One string's residuals: (counts since home, residual without the
/// string's current table, mm), gross failures left out.
type StringPoints = Vec<(i32, f64)>;

/// What the choice found for one string.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StringLayers {
    pub string: u8,
    /// Chosen knot spacing, counts (`None`: no spacing helped held out).
    pub step_counts: Option<u32>,
    /// Knots of the table fitted on the whole training session.
    pub knots: usize,
    /// Peak-to-peak of that table, mm.
    pub peak_to_peak_mm: f64,
    /// Held-out string residual rms (blocked folds pooled) without a table
    /// and with the chosen spacing, mm.
    pub held_rms_without_mm: f64,
    pub held_rms_with_mm: f64,
    /// Every spacing tried: (counts, held-out rms in mm).
    pub tried: Vec<(u32, f64)>,
}

impl StringLayers {
    /// `step_log2` of the chosen spacing.
    pub fn step_log2(&self) -> Option<u8> {
        self.step_counts.map(|s| s.trailing_zeros() as u8)
    }
}

/// The residual points of every string over the tracked rows of `rows`
/// (indexed as the folds index them: tracked rows only, in order), with
/// each string's current table added back.
fn points_by_string<O: Borrow<Observation> + Sync>(
    id: &Identification,
    rows: &[O],
) -> Vec<Vec<Option<(i32, f64)>>> {
    let tracked: Vec<(&Observation, [f64; STRINGS])> = rows
        .iter()
        .map(Borrow::borrow)
        .zip(string_residuals(&id.frame, &id.laws, &id.effects, rows))
        .filter_map(|(o, r)| Some((o, r?)))
        .collect();
    let layout = id.frame.layout;
    (0..STRINGS)
        .map(|i| {
            if !layout.is_active(i) {
                return vec![None; tracked.len()];
            }
            let raw: Vec<Option<(i32, f64)>> = tracked
                .iter()
                .map(|(o, r)| {
                    let r = r[i];
                    let c = o.inputs.counts[i];
                    (r.is_finite() && r.abs() <= GROSS_RESIDUAL_MM)
                        .then(|| (c, r + id.laws[i].layers.departure_mm(c)))
                })
                .collect();
            // Beyond 5 robust sd of this string: the abnormal motor's bad
            // captures, not its winding.
            let v: Vec<f64> = raw.iter().flatten().map(|p| p.1).collect();
            if v.len() < 4 {
                return raw;
            }
            let (med, sd) = robust_centre_and_sd(&v);
            raw.into_iter()
                .map(|p| p.filter(|p| (p.1 - med).abs() <= 5.0 * sd.max(1e-6)))
                .collect()
        })
        .collect()
}

/// Knots `2^step_log2` counts apart from `lo` that cover `lo..=hi`; `None`
/// when that takes fewer than 3 knots (a line: the winding law's own) or
/// more than [`LAYER_KNOTS`].
fn knot_count(lo: i32, hi: i32, step_log2: u8) -> Option<usize> {
    let span = i64::from(hi) - i64::from(lo);
    let step = 1i64 << step_log2;
    let n = (span + step - 1) / step + 1;
    (3..=LAYER_KNOTS as i64).contains(&n).then_some(n as usize)
}

/// Finest spacing (`step_log2`) with at most [`LAYER_KNOTS`] knots over `lo..=hi`.
fn finest_step(lo: i32, hi: i32) -> u8 {
    let span = (i64::from(hi) - i64::from(lo)).max(1);
    (0..=MAX_LAYER_STEP_LOG2)
        .find(|&s| (span + (1i64 << s) - 1) >> s < LAYER_KNOTS as i64)
        .unwrap_or(MAX_LAYER_STEP_LOG2)
}

/// Least-squares table of one string's points with knots `2^step_log2`
/// counts apart over the points' counts (nuisance constant, linear and
/// quadratic terms in the angle fitted and dropped); `None` when the spacing
/// gives fewer than 3 or more than [`LAYER_KNOTS`] knots, or fewer than
/// [`MIN_ROWS_PER_KNOT`] points per knot.
pub fn fit_table(points: &[(i32, f64)], counts_per_rev: u32, step_log2: u8) -> Option<LayerTable> {
    fit_table_with_slips(
        points,
        &[],
        &[],
        counts_per_rev,
        step_log2,
        TableLevel::Dropped,
    )
    .map(|(table, _)| table)
}

/// [`fit_table`] together with the string's slips: `times_s[k]` is when
/// `points[k]` was captured, `slips_at_s` when the string slipped (the
/// points without the slips' steps); each slip's step (mm) is fitted with
/// the table. A table fitted on residuals with a step in them bends to
/// follow the rows on one side of it (the rows before an early slip sit in
/// one corner of the lattice), and a step fitted with that table held is
/// undersized: the two are one least-squares problem, which only the counts
/// visited both before and after the slip can separate.
pub fn fit_table_with_slips(
    points: &[(i32, f64)],
    times_s: &[f64],
    slips_at_s: &[f64],
    counts_per_rev: u32,
    step_log2: u8,
    level: TableLevel,
) -> Option<(LayerTable, Vec<f64>)> {
    let lo = points.iter().map(|p| p.0).min()?;
    let hi = points.iter().map(|p| p.0).max()?;
    let n = knot_count(lo, hi, step_log2)?;
    if points.len() < MIN_ROWS_PER_KNOT * n {
        return None;
    }
    let mut table = LayerTable {
        start_counts: lo,
        step_log2,
        knots_mm: Knots::from_slice(&vec![0.0; n])?,
    };
    let law = StringLaw::polynomial(counts_per_rev, [1.0, 0.0, 0.0, 0.0]);
    let theta_scale = pulley_angle(&law, lo)
        .abs()
        .max(pulley_angle(&law, hi).abs())
        .max(1e-9);
    let dropped = level == TableLevel::Dropped;
    let m = n + 2 + slips_at_s.len() + usize::from(dropped);
    let mut normal = DMatrix::<f64>::zeros(m, m);
    let mut rhs = DVector::<f64>::zeros(m);
    let mut row = vec![0.0; m];
    let values: Vec<f64> = points.iter().map(|p| p.1).collect();
    let noise = robust_centre_and_sd(&values).1.max(1e-3);
    for (k_point, &(c, r)) in points.iter().enumerate() {
        row.iter_mut().for_each(|v| *v = 0.0);
        let (k, along) = table.locate(c)?;
        let f = f64::from(along) / f64::from(1u32 << step_log2);
        row[k] = 1.0 - f;
        if f > 0.0 {
            row[k + 1] = f;
        }
        let u = pulley_angle(&law, c) / theta_scale;
        row[n] = u;
        row[n + 1] = u * u;
        for (j, &at_s) in slips_at_s.iter().enumerate() {
            row[n + 2 + j] = if times_s[k_point] >= at_s { 1.0 } else { 0.0 };
        }
        if dropped {
            row[m - 1] = 1.0;
        }
        for a in 0..m {
            if row[a] == 0.0 {
                continue;
            }
            rhs[a] += row[a] * r;
            for b in 0..m {
                normal[(a, b)] += row[a] * row[b];
            }
        }
    }
    let ridge = (noise / KNOT_PRIOR_SD_MM).powi(2);
    for k in 0..n {
        normal[(k, k)] += ridge;
    }
    let solution = normal.cholesky()?.solve(&rhs);
    let knots: Vec<f64> = (0..n).map(|k| solution[k]).collect();
    let steps_mm: Vec<f64> = (n + 2..n + 2 + slips_at_s.len())
        .map(|k| solution[k])
        .collect();
    if !knots.iter().chain(&steps_mm).all(|v| v.is_finite()) {
        return None;
    }
    table.knots_mm = Knots::from_slice(&knots)?;
    Some((table, steps_mm))
}

/// Held-out string residual sum of squares of one string for one spacing
/// (`None` for no table) over `folds` (indices into the tracked rows), and
/// the number of residuals.
fn held_ss(
    points: &[Option<(i32, f64)>],
    counts_per_rev: u32,
    step_log2: Option<u8>,
    folds: &[(Vec<usize>, Vec<usize>)],
) -> Option<(f64, usize)> {
    let mut ss = 0.0;
    let mut n = 0;
    for (fit, held) in folds {
        let table = match step_log2 {
            None => LayerTable::NONE,
            Some(s) => {
                let fit_points: StringPoints = fit.iter().filter_map(|&k| points[k]).collect();
                fit_table(&fit_points, counts_per_rev, s)?
            }
        };
        for p in held.iter().filter_map(|&k| points[k]) {
            ss += (p.1 - table.departure_mm(p.0)).powi(2);
            n += 1;
        }
    }
    Some((ss, n))
}

/// Chooses each active string's spacing on `folds` (indices into the
/// tracked rows of `train`) from the residuals of `id`.
pub fn choose_spacings(
    id: &Identification,
    train: &[Observation],
    folds: &[(Vec<usize>, Vec<usize>)],
) -> Vec<StringLayers> {
    use rayon::prelude::*;
    let points = points_by_string(id, train);
    id.frame
        .layout
        .indices()
        .collect::<Vec<usize>>()
        .par_iter()
        .map(|&i| {
            let cpr = id.laws[i].counts_per_rev;
            let all: StringPoints = points[i].iter().flatten().copied().collect();
            let (lo, hi) = (
                all.iter().map(|p| p.0).min().unwrap_or(0),
                all.iter().map(|p| p.0).max().unwrap_or(0),
            );
            let (ss0, n0) = held_ss(&points[i], cpr, None, folds).unwrap_or((0.0, 0));
            let rms = |ss: f64, n: usize| (ss / n.max(1) as f64).sqrt();
            let finest = finest_step(lo, hi);
            let mut tried = Vec::new();
            let mut best: Option<(u8, f64)> = None;
            for s in finest..=(finest + COARSER_SPACINGS).min(MAX_LAYER_STEP_LOG2) {
                let Some((ss, n)) = held_ss(&points[i], cpr, Some(s), folds) else {
                    continue;
                };
                tried.push((1u32 << s, rms(ss, n)));
                if best.is_none_or(|b| ss < b.1) {
                    best = Some((s, ss));
                }
            }
            let chosen = best.filter(|b| b.1 < (1.0 - MIN_STRING_GAIN) * ss0);
            let table = chosen.and_then(|(s, _)| fit_table(&all, cpr, s));
            let peak_to_peak_mm = table.map_or(0.0, |t| {
                let v = t.knots_mm.as_slice();
                v.iter().cloned().fold(f64::MIN, f64::max)
                    - v.iter().cloned().fold(f64::MAX, f64::min)
            });
            StringLayers {
                string: i as u8,
                step_counts: chosen.map(|b| 1u32 << b.0),
                knots: table.map_or(0, |t| t.knots_mm.len()),
                peak_to_peak_mm,
                held_rms_without_mm: rms(ss0, n0),
                held_rms_with_mm: chosen.map_or(rms(ss0, n0), |b| rms(b.1, n0)),
                tried,
            }
        })
        .collect()
}

/// Tables of every string with a spacing in `steps`, fitted on the
/// residuals of `id` over the tracked rows of `rows`; a table the device would
/// refuse (it makes the payout fall) is dropped.
fn fit_all<O: Borrow<Observation> + Sync>(
    id: &Identification,
    rows: &[O],
    steps: &[Option<u8>; STRINGS],
    level: TableLevel,
) -> ([LayerTable; STRINGS], Vec<(usize, f64)>) {
    let points = points_by_string(id, rows);
    let times_s: Vec<f64> = rows
        .iter()
        .map(Borrow::borrow)
        .filter(|o| o.tracker.is_some())
        .map(|o| f64::from(o.inputs.time_ms) / 1000.0)
        .collect();
    let mut slip_steps = Vec::new();
    let tables = core::array::from_fn(|i| {
        let Some(s) = steps[i] else {
            return LayerTable::NONE;
        };
        // The string's slips that these rows see from both sides: (index
        // among the effects, time, fitted step). A step with too few rows
        // on a side is not refitted (a fold that ends before it, or begins
        // after it): it keeps its value, since the table's level would take
        // it.
        let rows_of = |t: &f64| {
            points[i]
                .iter()
                .zip(&times_s)
                .filter(|(p, _)| p.is_some())
                .filter(move |(_, s)| *s >= t)
                .count()
        };
        let visible = points[i].iter().filter(|p| p.is_some()).count();
        let slips: Vec<(usize, f64, f64)> = id
            .effects
            .iter()
            .enumerate()
            .filter(|(_, t)| t.applies_to(i))
            .filter_map(|(k, t)| match t.effect {
                Effect::Slip { at_s, mm } => Some((k, at_s, mm)),
                _ => None,
            })
            .filter(|s| {
                let after = rows_of(&s.1);
                after >= MIN_STEP_SIDE_ROWS && visible - after >= MIN_STEP_SIDE_ROWS
            })
            .collect();
        // The points with the slips' steps added back, fitted with them.
        let (all, times): (StringPoints, Vec<f64>) = points[i]
            .iter()
            .zip(&times_s)
            .filter_map(|(p, &t)| {
                let (c, r) = (*p)?;
                let back: f64 = slips.iter().filter(|s| t >= s.1).map(|s| s.2).sum();
                Some(((c, r + back), t))
            })
            .unzip();
        let at_s: Vec<f64> = slips.iter().map(|s| s.1).collect();
        let Some((table, steps_mm)) =
            fit_table_with_slips(&all, &times, &at_s, id.laws[i].counts_per_rev, s, level)
        else {
            return LayerTable::NONE;
        };
        let law = StringLaw {
            layers: table,
            ..id.laws[i]
        };
        if compile_string_law(&id.frame, i, &law).is_ok() {
            slip_steps.extend(slips.iter().zip(steps_mm).map(|(s, mm)| (s.0, mm)));
            table
        } else {
            LayerTable::NONE
        }
    });
    (tables, slip_steps)
}

/// The identification of `rows` with layer tables of the spacings `steps`:
/// from `from` (whose tables are replaced), [`REFINE_ROUNDS`] times fit the
/// tables on the residuals, then refit the geometry with them held.
pub fn identify_with_layers<O: Borrow<Observation> + Sync>(
    rows: &[O],
    nominal: &Frame<f64>,
    from: &Identification,
    structure: &Structure,
    steps: &[Option<u8>; STRINGS],
    level: TableLevel,
) -> Result<Identification, IdentifyError> {
    let mut id = from.clone();
    for _ in 0..REFINE_ROUNDS {
        let mut start = Start::from_identification(&id);
        let (tables, slip_steps) = fit_all(&id, rows, steps, level);
        start.winding.layers = tables;
        for (k, step_mm) in slip_steps {
            if let Some(EffectTerm {
                effect: Effect::Slip { mm, .. },
                ..
            }) = start.effects.get_mut(k)
            {
                *mm = step_mm;
            }
        }
        id = identify(rows, nominal, &start, structure)?;
    }
    Ok(id)
}

/// The spacings of `choice`, by string.
pub fn steps_of(choice: &[StringLayers]) -> [Option<u8>; STRINGS] {
    let mut steps = [None; STRINGS];
    for c in choice {
        if let Some(s) = steps.get_mut(usize::from(c.string)) {
            *s = c.step_log2();
        }
    }
    steps
}

/// The spacings of the tables `id` holds, by string.
pub fn steps_in(id: &Identification) -> [Option<u8>; STRINGS] {
    core::array::from_fn(|i| {
        let table = &id.laws[i].layers;
        (!table.is_empty()).then_some(table.step_log2)
    })
}

/// `id` without layer tables (what a fold starts from).
pub fn without_layers(id: &Identification) -> Start {
    let mut start = Start::from_identification(id);
    start.winding.layers = [LayerTable::NONE; STRINGS];
    start
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A layered spool's departure: straight within a layer, kinks every
    /// `layer` counts, 3 mm peak to peak (zero mean).
    fn staircase(c: i32, layer: f64) -> f64 {
        let phase = (f64::from(c) / layer).rem_euclid(1.0);
        3.0 * (phase * (1.0 - phase) * 4.0) - 2.0
    }

    fn noise(k: usize) -> f64 {
        // Deterministic, zero-mean, sd ~0.3 mm.
        let x = ((k as f64) * 12.9898).sin() * 43_758.545_3;
        0.6 * (x - x.floor() - 0.5) * 3f64.sqrt()
    }

    /// Least squares of `y` on `1, u, u^2` (u in rad), the residuals' rms.
    fn rms_after_quadratic(points: &[(i32, f64)], cpr: u32) -> f64 {
        let law = StringLaw::polynomial(cpr, [1.0, 0.0, 0.0, 0.0]);
        let a = DMatrix::from_fn(points.len(), 3, |r, c| {
            pulley_angle(&law, points[r].0).powi(c as i32) / 100f64.powi(c as i32)
        });
        let y = DVector::from_iterator(points.len(), points.iter().map(|p| p.1));
        let x = (a.transpose() * &a)
            .cholesky()
            .unwrap()
            .solve(&(a.transpose() * &y));
        ((&a * x - y).norm_squared() / points.len() as f64).sqrt()
    }

    #[test]
    fn a_table_follows_a_layer_staircase_and_leaves_the_smooth_part() {
        let cpr = 4096;
        let points: Vec<(i32, f64)> = (0..2000)
            .map(|k| {
                let c = -50_000 + (k as i32 * 997) % 200_000;
                let theta = f64::from(c) * std::f64::consts::TAU / f64::from(cpr);
                // Departure + a smooth part the geometry would absorb + noise.
                (
                    c,
                    staircase(c, 45_000.0) + 2.0 + 0.01 * theta - 1e-4 * theta * theta + noise(k),
                )
            })
            .collect();
        assert!(
            rms_after_quadratic(&points, cpr) > 0.7,
            "the staircase is there"
        );
        assert!(fit_table(&points, cpr, 12).is_none(), "49 knots: too many");
        let table = fit_table(&points, cpr, 13).expect("25 knots");
        assert_eq!(table.knots_mm.len(), 26);
        assert_eq!(table.start_counts, -50_000); // the lowest count
        let left: Vec<(i32, f64)> = points
            .iter()
            .map(|&(c, r)| (c, r - table.departure_mm(c)))
            .collect();
        let rms = rms_after_quadratic(&left, cpr);
        assert!(rms < 0.4, "left after the table: {rms} mm (noise 0.3)");
        // The smooth part stayed out of the table: its knots have no offset
        // of 2 mm and no trend.
        let v = table.knots_mm.as_slice();
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        assert!(mean.abs() < 1.0, "mean knot {mean}");
        // Held beyond the fitted counts.
        assert_eq!(table.departure_mm(i32::MIN), v[0]);
        assert_eq!(table.departure_mm(10_000_000), v[v.len() - 1]);
        // Too few points per knot: no table.
        assert!(fit_table(&points[..100], cpr, 13).is_none());
        assert!(fit_table(&[], cpr, 13).is_none());
    }

    /// A slip early in the session, while the end-effector was in one
    /// region (few counts, few rows): fitted with the table, the step comes
    /// out at its size; the table alone, fitted on the rows with the step in
    /// them, bends to follow the rows before it.
    #[test]
    fn a_table_fitted_with_a_slip_sizes_the_step_from_the_counts_visited_on_both_sides() {
        let cpr = 4096;
        let slip_mm = -4.2;
        let slip_at_s = 100.0;
        // 100 rows in one count range before the slip, then 2000 rows over
        // the whole range (that range again included).
        let (points, times): (Vec<(i32, f64)>, Vec<f64>) = (0..2100)
            .map(|k| {
                let (c, t) = if k < 100 {
                    (-40_000 + (k as i32 * 397) % 20_000, k as f64 * 0.9)
                } else {
                    (-50_000 + (k as i32 * 997) % 200_000, 100.0 + k as f64)
                };
                let step = if t >= slip_at_s { slip_mm } else { 0.0 };
                ((c, staircase(c, 45_000.0) + step + noise(k)), t)
            })
            .unzip();
        let (table, steps) =
            fit_table_with_slips(&points, &times, &[slip_at_s], cpr, 13, TableLevel::Kept)
                .expect("a table and a step");
        assert!((steps[0] - slip_mm).abs() < 0.1, "step {} mm", steps[0]);
        // The level is the string's before the slip: the table is the
        // staircase (its level and smooth part aside).
        let before: Vec<f64> = points[..100]
            .iter()
            .map(|&(c, r)| r - table.departure_mm(c))
            .collect();
        let mean = before.iter().sum::<f64>() / before.len() as f64;
        assert!(mean.abs() < 0.3, "rows before the slip left at {mean} mm");
        // Without the step in the fit the table takes the level after the
        // slip and leaves the rows before it several mm off.
        let (alone, _) =
            fit_table_with_slips(&points, &[], &[], cpr, 13, TableLevel::Kept).unwrap();
        let off = points[..100]
            .iter()
            .map(|&(c, r)| r - alone.departure_mm(c))
            .sum::<f64>()
            / 100.0;
        assert!(
            off > 2.0,
            "the table alone leaves the early rows {off} mm off"
        );
    }

    #[test]
    fn spacing_limits() {
        assert_eq!(knot_count(0, 1, 10), None, "a line");
        assert_eq!(knot_count(0, 2048, 10), Some(3));
        assert_eq!(knot_count(0, 2049, 10), Some(4));
        assert_eq!(finest_step(0, 31 * 1024), 10);
        assert_eq!(finest_step(0, 31 * 1024 + 1), 11);
        assert_eq!(finest_step(5, 5), 0);
    }
}
