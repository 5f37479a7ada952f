//! The paper's own procedure, for comparison (`--blackbox`): the legacy
//! controller's `dev_*` position plus the eq. 6 translation in, the tracker
//! out, NN and SVR in absolute mode.

use std::time::Instant;

use spidar_core::correction::CorrectionModel;
use spidar_core::geometry::device_from_room;

use crate::data::dataset::{Geometry, Session};
use crate::data::observe::{meeting_point, rotation_of_quaternion};
use crate::data::stats::error_stats_checked;
use crate::model::learn::outliers;
use crate::model::learn::search;
use crate::model::learn::thin::thin_evenly;

use super::evaluate::{stage, subset};
use super::{
    learn, report, CalibrateConfig, CalibrateError, PairSet, PointErrors, Run, StagePoints,
};

/// Legacy position in the room (eq. 6: `p_room = p_device + t`), paired with
/// the tracker, over the rows that have both.
fn legacy_pairs(
    geometry: &Geometry,
    session: &Session,
    skipped: &[usize],
    marker_body_mm: Option<[f64; 3]>,
) -> (Vec<usize>, Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let t = geometry.room_from_device_translation_mm;
    let mut rows = Vec::new();
    let mut x = Vec::new();
    let mut y = Vec::new();
    for (row, s) in session.samples.iter().enumerate() {
        if skipped.binary_search(&row).is_ok() {
            continue;
        }
        if let (Some(d), Some(o)) = (s.legacy, s.tracker) {
            rows.push(row);
            x.push([d[0] + t[0], d[1] + t[1], d[2] + t[2]]);
            y.push(match (marker_body_mm, s.orientation) {
                (Some(m), Some(q)) => meeting_point(&o, &rotation_of_quaternion(q), &m),
                _ => o,
            });
        }
    }
    (rows, x, y)
}

/// The black-box data: all legacy pairs of both sessions (with their rows),
/// Tukey's box plot on the training ones, and the kept training pairs.
pub(super) struct LegacyPairs {
    rows_tr: Vec<usize>,
    x_tr: Vec<[f64; 3]>,
    y_tr: Vec<[f64; 3]>,
    rows_te: Vec<usize>,
    outliers: outliers::OutlierReport,
    pub(super) kept: PairSet,
    nominal: spidar_core::model::Frame<f64>,
}

fn blackbox_pairs(
    geometry: &Geometry,
    [train, test]: [&Session; 2],
    skipped: [&[usize]; 2],
    marker_body_mm: Option<[f64; 3]>,
) -> Result<LegacyPairs, CalibrateError> {
    let (rows_tr, x_tr, y_tr) = legacy_pairs(geometry, train, skipped[0], marker_body_mm);
    let (rows_te, x_te, y_te) = legacy_pairs(geometry, test, skipped[1], marker_body_mm);
    let outl =
        outliers::tukey(&x_tr, &y_tr).map_err(learn("black-box outliers (Tukey box plot)"))?;
    let (xk, yk) = outliers::select(&outl, &x_tr, &y_tr);
    Ok(LegacyPairs {
        rows_tr,
        x_tr,
        y_tr,
        rows_te,
        outliers: outl,
        kept: PairSet {
            train_inputs: xk,
            train_targets: yk,
            test_inputs: x_te,
            test_targets: y_te,
        },
        nominal: geometry.nominal_frame(),
    })
}

fn blackbox(
    lp: &LegacyPairs,
    cfg: &CalibrateConfig,
    points: &mut Vec<StagePoints>,
) -> Result<report::Blackbox, CalibrateError> {
    let thinning = thin_evenly(&lp.kept.train_inputs, cfg.max_learning_points);
    let xk = &subset(&lp.kept.train_inputs, &thinning.indices);
    let yk = &subset(&lp.kept.train_targets, &thinning.indices);
    let sweep = search::nn_sweep(xk, yk, &cfg.blackbox_nn).map_err(learn("black-box NN sweep"))?;
    let svr_search =
        search::svr_search(xk, yk, &cfg.blackbox_svr).map_err(learn("black-box SVR search"))?;
    let nn_corr = CorrectionModel::Nn(sweep.fit.model.clone());
    let svr_corr = CorrectionModel::Svr(svr_search.fit.model.clone());
    let mut stages = Vec::new();
    let pe =
        |rows: &[usize], x: &[[f64; 3]], y: &[[f64; 3]], corr: &CorrectionModel, what: &str| {
            let mut p = PointErrors::default();
            for ((row, xi), yi) in rows.iter().zip(x).zip(y) {
                p.rows.push(*row);
                p.tracker.push(*yi);
                let d = device_from_room(&lp.nominal, *yi);
                p.distance_mm
                    .push((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt());
                p.errors
                    .push(crate::data::stats::position_error(corr.evaluate(*xi), *yi));
            }
            error_stats_checked(what, &p.errors).map(|s| (p, s))
        };
    let (x_te, y_te) = (&lp.kept.test_inputs, &lp.kept.test_targets);
    for (name, corr) in [
        ("legacy", &CorrectionModel::None),
        ("blackbox nn", &nn_corr),
        ("blackbox svr", &svr_corr),
    ] {
        let (a, sa) = pe(
            &lp.rows_tr,
            &lp.x_tr,
            &lp.y_tr,
            corr,
            &format!("{name}, training session"),
        )?;
        let (b, sb) = pe(
            &lp.rows_te,
            x_te,
            y_te,
            corr,
            &format!("{name}, test session"),
        )?;
        let kind = if name == "legacy" {
            report::StageKind::Raw
        } else {
            report::StageKind::Correction
        };
        stages.push(stage(name, kind, sa, sb));
        points.push(StagePoints {
            name: name.to_string(),
            train: a,
            test: b,
        });
    }
    Ok(report::Blackbox {
        mode: "absolute",
        input: "legacy controller position dev_x, dev_y, dev_z + eq. 6 translation (mm)",
        stages,
        outliers: report::Outliers::of(
            &lp.outliers,
            "legacy position vs tracker, training session",
        ),
        learning_points: report::LearningPoints::of(&thinning, lp.kept.train_inputs.len()),
        nn: report::NnReport::of(&sweep),
        svr: report::SvrReport::of(&svr_search),
    })
}

impl Run<'_> {
    /// The black-box data when both sessions have the legacy controller's
    /// columns, and the black-box comparison when asked for (a warning when
    /// asked for without them). The tracker is read where the model's
    /// stages read it: at the strings' meeting point when the loop found
    /// the tracked body's origin off it (`marker_body_mm`, through each
    /// row's orientation), so that every stage of the report is measured
    /// against the same point.
    pub(super) fn blackbox_comparison(
        &mut self,
        train: &Session,
        test: &Session,
        marker_body_mm: Option<[f64; 3]>,
        points: &mut Vec<StagePoints>,
    ) -> Result<(Option<LegacyPairs>, Option<report::Blackbox>), CalibrateError> {
        let skipped = [&self.train_info, &self.test_info].map(|info| info.rows_set_aside());
        let legacy = (self.train_info.has_legacy && self.test_info.has_legacy)
            .then(|| {
                blackbox_pairs(
                    self.geometry,
                    [train, test],
                    [&skipped[0], &skipped[1]],
                    marker_body_mm,
                )
            })
            .transpose()?;
        if !self.cfg.blackbox {
            return Ok((legacy, None));
        }
        let blackbox = if let Some(lp) = &legacy {
            let t = Instant::now();
            let bb = blackbox(lp, &self.cfg, points)?;
            self.timings.blackbox_s = Some(t.elapsed().as_secs_f64());
            Some(bb)
        } else {
            self.warnings.push(
                "black-box comparison skipped: it needs the legacy controller's dev_x, dev_y, \
                 dev_z columns in both sessions"
                    .into(),
            );
            None
        };
        Ok((legacy, blackbox))
    }
}

#[cfg(test)]
mod tests;
