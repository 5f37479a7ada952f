//! A large training session thinned evenly through its volume before a
//! correction learns from it.
//!
//! The SVR's kernel matrix grows with the square of its points and the
//! NN's Levenberg-Marquardt step with their number: a session recorded
//! while the device is used (10 000 rows and more, many of them where the
//! hand rested) would take minutes, or exceed the dense kernel's cap, where
//! a lattice of 2197 points takes seconds. A correction of the position
//! needs the volume covered, not every row of it, so it learns from at most
//! a set number of points, one per cell of a cubic grid.

use std::collections::HashMap;

/// Which points of a session a correction learns from.
#[derive(Clone, Debug, PartialEq)]
pub struct Thinning {
    /// Indices of the points kept, ascending.
    pub indices: Vec<usize>,
    /// Edge of the grid's cubic cells, mm; `None`: every point kept (there
    /// were no more than the cap).
    pub cell_mm: Option<f64>,
}

/// At most `cap` of `points` (mm), spread through their volume: the grid
/// cell (cubic, its origin at the points' lowest corner) is the smallest,
/// to 1 part in 10^6 of the points' extent, that leaves `cap` or fewer
/// cells occupied, and each occupied cell keeps its point nearest the
/// cell's centre (of equal ones, the first). All points when there are no
/// more than `cap`; none when `cap` is 0. Deterministic: the same points
/// give the same indices on every machine. A non-finite coordinate does not
/// fail here (it lands in the corner's cell); the learners refuse it.
pub fn thin_evenly(points: &[[f64; 3]], cap: usize) -> Thinning {
    if points.len() <= cap {
        return Thinning {
            indices: (0..points.len()).collect(),
            cell_mm: None,
        };
    }
    if cap == 0 {
        return Thinning {
            indices: Vec::new(),
            cell_mm: None,
        };
    }
    let mut low = [f64::INFINITY; 3];
    let mut high = [f64::NEG_INFINITY; 3];
    for p in points.iter().filter(|p| p.iter().all(|x| x.is_finite())) {
        for k in 0..3 {
            low[k] = low[k].min(p[k]);
            high[k] = high[k].max(p[k]);
        }
    }
    if !low[0].is_finite() {
        low = [0.0; 3];
        high = [0.0; 3];
    }
    let extent = (0..3).map(|k| high[k] - low[k]).fold(0.0, f64::max);
    // One cell a little larger than the extent holds every point: the
    // bisection's upper end, which always leaves `cap` (>= 1) cells or fewer.
    let mut too_small = 0.0;
    let mut fits = if extent > 0.0 { extent * 1.001 } else { 1.0 };
    let tolerance = fits * 1e-6;
    while fits - too_small > tolerance {
        let mid = 0.5 * (too_small + fits);
        if occupied(points, &low, mid).len() <= cap {
            fits = mid;
        } else {
            too_small = mid;
        }
    }
    let mut indices: Vec<usize> = occupied(points, &low, fits)
        .into_values()
        .map(|(i, _)| i)
        .collect();
    indices.sort_unstable();
    Thinning {
        indices,
        cell_mm: Some(fits),
    }
}

/// Grid cell of edge `cell` (origin `low`) -> (index of its point nearest
/// the centre, that point's squared distance to it).
fn occupied(points: &[[f64; 3]], low: &[f64; 3], cell: f64) -> HashMap<[i64; 3], (usize, f64)> {
    let mut cells: HashMap<[i64; 3], (usize, f64)> = HashMap::new();
    for (i, p) in points.iter().enumerate() {
        // `as` saturates, and NaN becomes 0: no panic on any input.
        let key: [i64; 3] = core::array::from_fn(|k| ((p[k] - low[k]) / cell).floor() as i64);
        let d2: f64 = (0..3)
            .map(|k| {
                let centre = low[k] + (key[k] as f64 + 0.5) * cell;
                (p[k] - centre).powi(2)
            })
            .sum();
        let d2 = if d2.is_finite() { d2 } else { f64::MAX };
        cells
            .entry(key)
            .and_modify(|best| {
                if d2 < best.1 {
                    *best = (i, d2);
                }
            })
            .or_insert((i, d2));
    }
    cells
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A session that rests: `per_place` rows at each of `places` places on
    /// a line, then one row at each of 10 other places.
    fn resting_session(places: usize, per_place: usize) -> Vec<[f64; 3]> {
        let mut out = Vec::new();
        for k in 0..places {
            for j in 0..per_place {
                out.push([k as f64 * 10.0 + j as f64 * 1e-3, 0.0, 0.0]);
            }
        }
        for k in 0..10 {
            out.push([0.0, 100.0 + k as f64 * 10.0, 50.0]);
        }
        out
    }

    #[test]
    fn a_session_within_the_cap_is_kept_whole() {
        let points = resting_session(5, 3);
        let t = thin_evenly(&points, points.len());
        assert_eq!(t.indices, (0..points.len()).collect::<Vec<_>>());
        assert_eq!(t.cell_mm, None);
    }

    #[test]
    fn where_the_hand_rested_one_point_stands_for_the_place() {
        // 20 places x 100 rows, and 10 lone rows: 2010 points, cap 30.
        let points = resting_session(20, 100);
        let t = thin_evenly(&points, 30);
        assert_eq!(t.indices.len(), 30, "{t:?}");
        // Every lone row is kept: the rested places do not crowd them out.
        for k in 0..10 {
            assert!(t.indices.contains(&(2000 + k)), "{t:?}");
        }
        // One row of each rested place.
        for place in 0..20 {
            let n = t
                .indices
                .iter()
                .filter(|&&i| i / 100 == place && i < 2000)
                .count();
            assert_eq!(n, 1, "place {place}: {t:?}");
        }
    }

    #[test]
    fn no_cap_keeps_nothing_and_bad_coordinates_do_not_fail() {
        assert!(thin_evenly(&[[0.0; 3]; 4], 0).indices.is_empty());
        let mut points = resting_session(3, 4);
        points[1] = [f64::NAN, 0.0, f64::INFINITY];
        let t = thin_evenly(&points, 5);
        assert!(!t.indices.is_empty() && t.indices.len() <= 5);
        // All points at one place: one cell.
        let t = thin_evenly(&[[1.0, 2.0, 3.0]; 50], 7);
        assert_eq!(t.indices.len(), 1);
    }

    proptest! {
        #[test]
        fn at_most_the_cap_ascending_distinct_and_every_point_near_a_kept_one(
            points in prop::collection::vec(
                prop::array::uniform3(-500.0f64..500.0), 1..400),
            cap in 1usize..120,
        ) {
            let t = thin_evenly(&points, cap);
            prop_assert!(t.indices.len() <= cap.min(points.len()));
            prop_assert!(!t.indices.is_empty());
            prop_assert!(t.indices.windows(2).all(|w| w[0] < w[1]));
            prop_assert!(t.indices.iter().all(|&i| i < points.len()));
            // Each point's cell has a kept point: within a cell's diagonal.
            let reach = t.cell_mm.map_or(0.0, |c| c * 3f64.sqrt()) + 1e-9;
            for p in &points {
                let nearest = t
                    .indices
                    .iter()
                    .map(|&i| {
                        let q = points[i];
                        ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2))
                            .sqrt()
                    })
                    .fold(f64::INFINITY, f64::min);
                prop_assert!(nearest <= reach, "{nearest} > {reach}");
            }
            // The same points, the same choice.
            prop_assert_eq!(thin_evenly(&points, cap), t);
        }
    }
}
