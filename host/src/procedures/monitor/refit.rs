//! The refit and reflash: the check's findings added as terms where the
//! cross-validated error says they help, the model identified again on the
//! window (and the training session), compiled, flashed and verified.

use std::path::Path;
use std::time::Instant;

use spidar_core::model::{Calibration, Effect, MAX_HOME_SLIPS};

use crate::data::dataset::{Sample, Session};
use crate::data::observe::{observations, Observation};
use crate::data::stats::ErrorStats;
use crate::device::link::Client;
use crate::model::compile::{compile_checked, model_id_of};
use crate::model::diagnose::{cross_validated_error, model_errors};
use crate::model::identify::{identify, Identification, IdentifyError, Start, Structure};

use super::check::every_string_errors;
use super::{describe_finding, Check, Monitor, MonitorError, StringsSeen};

/// A refit and reflash.
#[derive(Clone, Debug)]
pub struct Refit {
    /// The window at detection (the device's error before).
    pub before: ErrorStats,
    /// What the strings showed then.
    pub before_strings: StringsSeen,
    /// The first full window after the reflash (the error after); `None`
    /// when the run ended first (see `after_partial`).
    pub after: Option<ErrorStats>,
    /// The pairs after the reflash when the run ended before a full window.
    pub after_partial: Option<ErrorStats>,
    /// What the strings show on the window of `after` (or
    /// `after_partial`).
    pub after_strings: Option<StringsSeen>,
    /// What was added, in the device's terms.
    pub added: Vec<String>,
    /// Host (f64) mean error on the window of the old and the new model,
    /// every string in the position ([`StringsSeen::every_string`]), mm:
    /// what the refit is judged by (a refit that does not lower it is not
    /// flashed).
    pub host_before_mm: f64,
    pub host_after_mm: f64,
    /// The same as the device solves the position (a string that
    /// disagrees left out, before the learned correction), mm: blind to a
    /// slip of one string the device leaves out.
    pub device_kinematics_before_mm: f64,
    pub device_kinematics_after_mm: f64,
    pub model_id: u32,
    pub blob_len: u32,
    /// Tracked rows the refit was fitted on: `window_pairs +
    /// training_rows`.
    pub rows: usize,
    /// The window's pairs among them (the last of the run's pairs).
    pub window_pairs: usize,
    /// The training session's tracked rows among them (0 without a
    /// training session, or when the model has a time drift term).
    pub training_rows: usize,
    pub calibration: Calibration,
    /// Refit, compile and flash, s of wall time (a simulated rig's world
    /// waits meanwhile).
    pub seconds: f64,
}

/// A refit's model before it is flashed: the identification, its
/// structure, the data it was fitted on and the terms added (in words).
struct RefitModel {
    id: Identification,
    structure: Structure,
    data: Vec<Observation>,
    added: Vec<String>,
}

/// The training session's rows as the refit reads them beside a window of
/// home capture `home_id`: at their own time since home when they are of
/// that capture (the run goes on from the training under it: the
/// training's slips are in them, and what happened at run time came
/// after), else at time since home 0, before anything of the window's
/// capture (a slip found after a new `Home`, at a time since it, is not
/// in them whatever their own time since their capture).
fn training_rows(training: &Session, home_id: Option<u64>) -> Vec<Sample> {
    training
        .samples
        .iter()
        .map(|s| {
            if s.home.is_some() && s.home == home_id && s.since_home_s.is_some() {
                s.clone()
            } else {
                Sample {
                    t_s: 0.0,
                    since_home_s: None,
                    ..s.clone()
                }
            }
        })
        .collect()
}

impl Monitor<'_> {
    /// The refit's data: the window, plus the training session
    /// ([`training_rows`]) when given and the model has no time drift term.
    fn refit_data(&self, structure: &Structure) -> Vec<Observation> {
        let has_drift = structure
            .effects
            .iter()
            .any(|t| matches!(t.effect, Effect::Drift { .. }));
        let mut samples: Vec<Sample> = Vec::new();
        if let (Some(train), false) = (self.training, has_drift) {
            samples.extend(training_rows(train, self.home_id));
        }
        samples.extend(self.window.iter().map(|p| p.sample.clone()));
        // The training rows as the calibration read them (the window's are
        // paired at the meeting point already and carry no orientation).
        crate::data::observe::at_meeting_points(&observations(&samples), self.config.marker_body_mm)
            .into_owned()
    }

    pub(super) fn refit_and_flash(
        &mut self,
        client: &mut Client,
        check: &Check,
    ) -> Result<Refit, MonitorError> {
        let t0 = Instant::now();
        let window_obs = self.window_observations();
        let RefitModel {
            mut id,
            structure,
            data,
            added,
        } = self.refit_model(check)?;
        // A window of a few seconds does not measure each string's scale as
        // the calibration's session did: the strings keep their weights.
        id.length_scale_mm = self.calibration.length_scale_mm;
        // Judged with every string in: as the device solves it, the old
        // model leaves a slipped string out and its error is the baseline's
        // already (0.158 -> 0.158 mm on `spidar monitor --simulate 5
        // --effect slip:3:at_s=8,mm=7`, with every string in 2.7 -> 0.16).
        let correction = &self.calibration.correction;
        let every_string_mean = |id: &Identification| {
            ErrorStats::of(&every_string_errors(id, correction, &window_obs)).mean_mm
        };
        let host_before_mm = every_string_mean(&self.identification);
        let host_after_mm = every_string_mean(&id);
        let device_kinematics_before_mm = model_errors(&self.identification, &window_obs).mean_mm;
        let device_kinematics_after_mm = model_errors(&id, &window_obs).mean_mm;
        if host_after_mm.partial_cmp(&host_before_mm) != Some(std::cmp::Ordering::Less) {
            return Err(MonitorError::Identify(IdentifyError::Diverged(format!(
                "the refit does not lower the window error with every string in ({host_before_mm:.3} mm -> {host_after_mm:.3} mm); nothing flashed"
            ))));
        }
        // Slips are the current home capture's: the training's, refitted,
        // while it is theirs, and those found now.
        let (effects, home) =
            super::calibration::split_home_slips(&id.effects, &self.calibration, self.home_id);
        if let Some(h) = home.as_ref().filter(|h| h.slips.len() > MAX_HOME_SLIPS) {
            return Err(MonitorError::Identify(IdentifyError::Diverged(format!(
                "{} slips under home capture {}, a blob carries at most {MAX_HOME_SLIPS}; nothing \
                 flashed (home the device again: a new capture counts the strings as they are)",
                h.slips.len(),
                h.home_id
            ))));
        }
        let calibration = Calibration {
            frame: id.frame,
            strings: id.laws,
            effects,
            correction: self.calibration.correction.clone(),
            // A calibration whose strings weigh alike (its rule, chosen on
            // held-out folds) keeps them alike.
            length_scale_mm: if self.calibration.length_scale_mm.iter().all(|&s| s == 0.0) {
                self.calibration.length_scale_mm
            } else {
                id.length_scale_mm
            },
            kinematics: self.calibration.kinematics,
            home,
        };
        let rows = data.iter().filter(|o| o.tracker.is_some()).count();
        let window_pairs = window_obs.iter().filter(|o| o.tracker.is_some()).count();
        let model_id = model_id_of(&calibration);
        let flashed = self.flash_calibration(client, &calibration, model_id)?;
        self.calibration = calibration.clone();
        self.identification = id;
        self.structure = structure;
        Ok(Refit {
            before: check.window,
            before_strings: check.strings.clone(),
            after: None,
            after_partial: None,
            after_strings: None,
            added,
            host_before_mm,
            host_after_mm,
            device_kinematics_before_mm,
            device_kinematics_after_mm,
            model_id,
            blob_len: flashed.blob_len,
            rows,
            window_pairs,
            training_rows: rows - window_pairs,
            calibration,
            seconds: t0.elapsed().as_secs_f64(),
        })
    }

    /// The refitted model: the check's findings added as terms where they
    /// lower the cross-validated error enough, else the model as it is
    /// refitted.
    fn refit_model(&self, check: &Check) -> Result<RefitModel, MonitorError> {
        let nominal = self.geometry.nominal_frame();
        let mut structure = self.structure.clone();
        let mut id = self.identification.clone();
        let mut data = self.refit_data(&structure);
        let mut validation = cross_validated_error(&data, &nominal, &id, &structure)?;
        let mut added = Vec::new();
        // One new term per string per refit, the strongest (findings come
        // strongest first): a step on a string also scores as an offset and
        // as a drift, and a drift fitted across a step inside a few seconds
        // of data extrapolates wildly (the error after the reflash rises
        // instead of falling; decision record 0042,
        // `docs/decisions/0042-monitor-refits-once-settled.md`).
        let mut strings_changed: Vec<u8> = Vec::new();
        let weaker = check.weaker.iter().filter(|_| check.error_exceeded);
        for f in check.findings.iter().chain(weaker) {
            if added.len() >= self.config.loop_config.max_effects {
                break;
            }
            let Some(change) = f.change else { continue };
            // A term shared by every string (no strings named) touches them
            // all.
            let touched: Vec<u8> = if f.strings.is_empty() {
                self.geometry.layout.indices().map(|i| i as u8).collect()
            } else {
                f.strings.clone()
            };
            if touched.iter().any(|s| strings_changed.contains(s)) {
                continue;
            }
            let candidate = structure.with(change);
            let candidate_data = self.refit_data(&candidate);
            let after = cross_validated_error(&candidate_data, &nominal, &id, &candidate)?;
            if after < validation * (1.0 - self.config.loop_config.min_relative_gain) {
                id = identify(
                    &candidate_data,
                    &nominal,
                    &Start::from_identification(&id),
                    &candidate,
                )?;
                structure = candidate;
                data = candidate_data;
                validation = after;
                strings_changed.extend(&touched);
                added.push(describe_finding(f));
            }
        }
        if added.is_empty() {
            // Nothing the diagnosis named helps: refit the model as it is
            // (the error rule fired, or the effect is already a term).
            id = identify(
                &data,
                &nominal,
                &Start::from_identification(&id),
                &structure,
            )?;
            added.push("no new term: the model's parameters refitted".into());
        }
        Ok(RefitModel {
            id,
            structure,
            data,
            added,
        })
    }

    /// Compiles `calibration` and flashes it with the motors off and the
    /// stream paused; checks that the device runs it, then streams again.
    fn flash_calibration(
        &self,
        client: &mut Client,
        calibration: &Calibration,
        model_id: u32,
    ) -> Result<crate::device::link::FlashReport, MonitorError> {
        let blob = compile_checked(
            calibration,
            model_id,
            crate::model::compile::created_now(),
            Path::new("(runtime refit)"),
        )?;
        // Flashing needs the motors off; the stream pauses meanwhile.
        client.stream_off()?;
        client.disarm()?;
        let flashed = client.flash(&blob, |_| {})?;
        match client.info()? {
            Some(info) if info.header.model_id == model_id => {}
            other => {
                return Err(MonitorError::Verify {
                    what: match other {
                        Some(i) => format!(
                            "model {:#010x}, flashed {model_id:#010x}",
                            i.header.model_id
                        ),
                        None => "no model".into(),
                    },
                })
            }
        }
        client.stream_on(self.config.decimation)?;
        Ok(flashed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Training rows of the window's capture keep their time since home;
    /// rows of another capture (or that do not say) read as time 0, so that
    /// a slip found after a new `Home` is not in them.
    #[test]
    fn training_rows_keep_their_time_only_under_the_window_s_capture() {
        let row = Sample::at_home;
        let training = Session {
            samples: vec![
                row(10.0, Some(12.0), Some(7)),
                row(20.0, Some(22.0), Some(7)),
            ],
            ..Session::default()
        };
        let time = |rows: Vec<Sample>| {
            crate::data::observe::observations(&rows)
                .iter()
                .map(|o| o.inputs.time_ms)
                .collect::<Vec<_>>()
        };
        assert_eq!(time(training_rows(&training, Some(7))), [12_000, 22_000]);
        assert_eq!(time(training_rows(&training, Some(8))), [0, 0]);
        assert_eq!(time(training_rows(&training, None)), [0, 0]);
        let untold = Session {
            samples: vec![row(10.0, None, None)],
            ..Session::default()
        };
        assert_eq!(time(training_rows(&untold, None)), [0]);
    }
}
