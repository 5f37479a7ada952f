//! The errors of a stage: a model's room positions against the tracker on
//! both sessions (eq. 7, [`crate::data::stats`]), kept per point for the
//! figures and as statistics for the report's stages.

use spidar_core::correction::CorrectionModel;
use spidar_core::geometry::device_from_room;

use crate::data::observe::Observation;
use crate::data::stats::{error_stats_checked, ErrorStats, StatsError};
use crate::model::predict::{predict, KinematicModel};

use super::report;

/// Per-point errors of one stage on one session, for the figures.
#[derive(Clone, Debug, Default)]
pub struct PointErrors {
    /// Session row of each point (CSV line = row + 2).
    pub rows: Vec<usize>,
    /// Tracker position (room frame, mm).
    pub tracker: Vec<[f64; 3]>,
    /// Distance of the tracker position to the device origin, mm (figs. 15, 17).
    pub distance_mm: Vec<f64>,
    /// Eq. 7 error, mm.
    pub errors: Vec<f64>,
}

/// Stage errors kept for the figures (train and test).
#[derive(Clone, Debug)]
pub struct StagePoints {
    pub name: String,
    pub train: PointErrors,
    pub test: PointErrors,
}

/// The tracked rows of a session's observations, with positions from `f`.
fn point_errors(
    what: &str,
    obs: &[Observation],
    positions: &[[f64; 3]],
    frame: &spidar_core::model::Frame<f64>,
) -> Result<(PointErrors, ErrorStats), StatsError> {
    // Each stage keeps its points for the figures: sized to them, not
    // grown by doubling (a long session's are megabytes a stage).
    let tracked = obs
        .iter()
        .zip(positions)
        .filter(|(o, _)| o.tracker.is_some())
        .count();
    let mut pe = PointErrors {
        rows: Vec::with_capacity(tracked),
        tracker: Vec::with_capacity(tracked),
        distance_mm: Vec::with_capacity(tracked),
        errors: Vec::with_capacity(tracked),
    };
    for (o, p) in obs.iter().zip(positions) {
        if let Some(t) = o.tracker {
            pe.rows.push(o.row);
            pe.tracker.push(t);
            let d = device_from_room(frame, t);
            pe.distance_mm
                .push((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt());
            pe.errors.push(crate::data::stats::position_error(*p, t));
        }
    }
    let stats = error_stats_checked(what, &pe.errors)?;
    Ok((pe, stats))
}

pub(super) fn room_positions(model: KinematicModel<'_>, obs: &[Observation]) -> Vec<[f64; 3]> {
    predict(model, obs).iter().map(|p| p.room).collect()
}

pub(super) fn subset(points: &[[f64; 3]], idx: &[usize]) -> Vec<[f64; 3]> {
    idx.iter().filter_map(|&i| points.get(i).copied()).collect()
}

/// Eq. 7 errors of corrected positions `x` against the tracker `t`.
pub(super) fn point_error_list(
    correct: impl Fn([f64; 3]) -> [f64; 3],
    x: &[[f64; 3]],
    t: &[[f64; 3]],
) -> Vec<f64> {
    x.iter()
        .zip(t)
        .map(|(p, r)| crate::data::stats::position_error(correct(*p), *r))
        .collect()
}

/// Tracked pairs (model room position, tracker) of the training session.
pub(super) fn tracked_pairs(
    obs: &[Observation],
    positions: &[[f64; 3]],
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    obs.iter()
        .zip(positions)
        .filter_map(|(o, p)| o.tracker.map(|t| (*p, t)))
        .unzip()
}

pub(super) fn stage(
    name: &str,
    kind: report::StageKind,
    train: ErrorStats,
    test: ErrorStats,
) -> report::Stage {
    report::Stage {
        name: name.to_string(),
        kind,
        train,
        test,
    }
}

/// Training and test values side by side: the sessions' observations, the
/// positions a model predicts on them.
#[derive(Clone, Copy)]
pub(super) struct PerSession<T> {
    pub(super) train: T,
    pub(super) test: T,
}

/// One stage's per-point errors and statistics on both sessions.
pub(super) struct StageErrors {
    train: PointErrors,
    pub(super) train_stats: ErrorStats,
    test: PointErrors,
    pub(super) test_stats: ErrorStats,
}

impl StageErrors {
    /// The errors of `positions` (one per observation) against the tracker;
    /// `what` names the stage in an error.
    pub(super) fn of(
        what: &str,
        obs: PerSession<&[Observation]>,
        positions: PerSession<&[[f64; 3]]>,
        frame: &spidar_core::model::Frame<f64>,
    ) -> Result<StageErrors, StatsError> {
        let (train, train_stats) = point_errors(
            &format!("{what}, training session"),
            obs.train,
            positions.train,
            frame,
        )?;
        let (test, test_stats) = point_errors(
            &format!("{what}, test session"),
            obs.test,
            positions.test,
            frame,
        )?;
        Ok(StageErrors {
            train,
            train_stats,
            test,
            test_stats,
        })
    }

    pub(super) fn stage(&self, name: &str, kind: report::StageKind) -> report::Stage {
        stage(name, kind, self.train_stats, self.test_stats)
    }

    pub(super) fn points(self, name: String) -> StagePoints {
        StagePoints {
            name,
            train: self.train,
            test: self.test,
        }
    }
}

/// The report's stages and the figures' per-point errors, in the order the
/// stages are computed.
#[derive(Default)]
pub(super) struct StageList {
    pub(super) stages: Vec<report::Stage>,
    pub(super) points: Vec<StagePoints>,
}

impl StageList {
    /// A stage with its figures' points.
    pub(super) fn push(&mut self, name: String, kind: report::StageKind, errors: StageErrors) {
        self.stages.push(errors.stage(&name, kind));
        self.points.push(errors.points(name));
    }

    /// A stage with its figures' points, at `index` of both lists.
    pub(super) fn insert(
        &mut self,
        index: usize,
        name: String,
        kind: report::StageKind,
        errors: StageErrors,
    ) {
        self.stages.insert(index, errors.stage(&name, kind));
        self.points.insert(index, errors.points(name));
    }
}

/// The errors of a correction on top of the final identified model.
pub(super) fn correction_errors(
    name: &str,
    corr: &CorrectionModel,
    obs: PerSession<&[Observation]>,
    fin_positions: PerSession<&[[f64; 3]]>,
    frame: &spidar_core::model::Frame<f64>,
) -> Result<StageErrors, StatsError> {
    let ptr = crate::model::predict::corrected_positions(corr, fin_positions.train);
    let pte = crate::model::predict::corrected_positions(corr, fin_positions.test);
    StageErrors::of(
        name,
        obs,
        PerSession {
            train: &ptr,
            test: &pte,
        },
        frame,
    )
}
