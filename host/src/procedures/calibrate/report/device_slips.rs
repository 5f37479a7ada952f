//! The training session's slips in the calibration report
//! ([`DeviceSlips`]): which of them the flashed model applies, under which
//! home capture, and why the others are left out.

use serde::Serialize;

use spidar_core::model::EffectTerm;

/// Whether the model flashed from the calibration applies the training
/// session's slips (`calibration.json`'s `home`), and under which home
/// capture: while the device's `State::home_id` is `home_id`, until its
/// next `Home` or a reboot (decision record 0049, "Device side").
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DeviceSlips {
    /// The home capture the slips apply under; `null` when the model
    /// carries none.
    pub home_id: Option<u64>,
    /// The slips carried (each on one string, `at_s` since the capture).
    pub slips: Vec<EffectTerm>,
    /// The final model's slips not carried (of a capture that is over,
    /// fitted across captures, or none carried at all: `reason` says why).
    pub not_carried: Vec<EffectTerm>,
    /// Why, in a sentence (the summary prints it).
    pub reason: String,
}

/// A slip as the report lists it.
fn describe_slip(t: &EffectTerm) -> String {
    match t.effect {
        spidar_core::model::Effect::Slip { at_s, mm } => {
            format!("string {} {mm:+.2} mm from {at_s:.1} s", t.string)
        }
        _ => String::new(),
    }
}

impl DeviceSlips {
    /// The slips among the final identified model's `effects` that the
    /// device can apply under `training`'s home capture: those of its last
    /// capture ([`crate::data::home::TrainingHome::slip_is_of_last_capture`]),
    /// each on one string, at most [`spidar_core::model::MAX_HOME_SLIPS`].
    pub fn of(training: &crate::data::home::TrainingHome, effects: &[EffectTerm]) -> DeviceSlips {
        use crate::data::home::SlipRows;
        use spidar_core::model::{Effect, MAX_HOME_SLIPS};
        let all: Vec<EffectTerm> = effects
            .iter()
            .filter(|t| matches!(t.effect, Effect::Slip { .. }))
            .copied()
            .collect();
        let listed = |slips: &[EffectTerm]| {
            slips
                .iter()
                .map(describe_slip)
                .collect::<Vec<_>>()
                .join(", ")
        };
        let not_carried = |why: &str| DeviceSlips {
            home_id: None,
            slips: Vec::new(),
            not_carried: all.clone(),
            reason: format!(
                "the training session's slips ({}) are not carried to the device: {why}; it runs \
                 the model for its next home capture",
                listed(&all)
            ),
        };
        if all.is_empty() {
            return DeviceSlips {
                home_id: None,
                slips: Vec::new(),
                not_carried: Vec::new(),
                reason: "the training session has no slip to carry".into(),
            };
        }
        let Some(home_id) = training.home_id else {
            return not_carried(&training.reason);
        };
        if all
            .iter()
            .any(|t| usize::from(t.string) >= spidar_core::STRINGS)
        {
            return not_carried("a slip shared by every string is not a slip of one string");
        }
        let (slips, earlier): (Vec<EffectTerm>, Vec<EffectTerm>) =
            all.iter().partition(|t| match t.effect {
                Effect::Slip { at_s, .. } => training.slip_is_of_last_capture(at_s),
                _ => false,
            });
        // Why each slip left out is not the last capture's.
        let why_left = || {
            earlier
                .iter()
                .map(|t| {
                    let at_s = match t.effect {
                        Effect::Slip { at_s, .. } => at_s,
                        _ => 0.0,
                    };
                    let why = match training.rows_of_slip(at_s) {
                        SlipRows::Earlier => {
                            "a slip of an earlier capture, over with it (only rows of the earlier \
                             captures are that long after their own)"
                        }
                        _ => {
                            "fitted across captures (it shifted rows of the earlier captures and \
                             of the last alike, each that long after its own)"
                        }
                    };
                    format!("{} is {why}", describe_slip(t))
                })
                .collect::<Vec<_>>()
                .join("; ")
        };
        if slips.is_empty() {
            return not_carried(&format!("{}; {}", training.reason, why_left()));
        }
        if slips.len() > MAX_HOME_SLIPS {
            return not_carried(&format!("a blob carries at most {MAX_HOME_SLIPS}"));
        }
        let whose = if training.captures > 1 {
            format!(
                "the last of the training session's {} (from line {} on)",
                training.captures,
                training.first_row + 2
            )
        } else {
            "the training session's".into()
        };
        let left = if earlier.is_empty() {
            String::new()
        } else {
            format!("; not carried: {}", why_left())
        };
        DeviceSlips {
            home_id: Some(home_id),
            reason: format!(
                "the flashed model applies {} of the training session's slips ({}) while the \
                 device stays under home capture {home_id}, {whose}; from its next `Home` or a \
                 reboot it runs without them{left}",
                slips.len(),
                listed(&slips)
            ),
            slips,
            not_carried: earlier,
        }
    }

    /// What `calibration.json` carries: the slips and their capture, or
    /// nothing.
    pub fn home_slips(&self) -> Option<spidar_core::model::HomeSlips> {
        self.home_id.map(|home_id| spidar_core::model::HomeSlips {
            home_id,
            slips: self.slips.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slip(string: u8, at_s: f64) -> EffectTerm {
        EffectTerm {
            string,
            effect: spidar_core::model::Effect::Slip { at_s, mm: 5.0 },
        }
    }

    /// A training session homed again at row 2 (the earlier capture's rows
    /// 0 and 40 s after it): a slip from 60 s since home is the last
    /// capture's and carried under it; one from 30 s also shifted the
    /// earlier capture's row at 40 s, and is not.
    #[test]
    fn only_the_slips_of_the_training_s_last_home_capture_are_carried() {
        use crate::data::dataset::{Sample, Session};
        use crate::data::home::TrainingHome;
        let row = |t_s: f64, since_home_s: f64, home: u64| {
            Sample::at_home(t_s, Some(since_home_s), Some(home))
        };
        let training = TrainingHome::of(&Session {
            samples: vec![
                row(0.0, 0.0, 7),
                row(40.0, 40.0, 7),
                row(50.0, 1.0, 8),
                row(120.0, 71.0, 8),
            ],
            ..Session::default()
        });
        let d = DeviceSlips::of(&training, &[slip(2, 60.0), slip(5, 30.0)]);
        assert_eq!(d.home_id, Some(8), "{}", d.reason);
        assert_eq!(
            (d.slips.clone(), d.not_carried.clone()),
            (vec![slip(2, 60.0)], vec![slip(5, 30.0)])
        );
        for said in [
            "applies 1 of the training session's slips (string 2 +5.00 mm from 60.0 s)",
            "home capture 8, the last of the training session's 2 (from line 4 on)",
            "not carried: string 5 +5.00 mm from 30.0 s is fitted across captures",
        ] {
            assert!(d.reason.contains(said), "{said}: {}", d.reason);
        }
        let none = DeviceSlips::of(&training, &[slip(5, 30.0)]);
        assert_eq!((none.home_id, none.not_carried.len()), (None, 1));
        assert!(
            none.reason.contains("spans 2 home captures")
                && none.reason.contains("are not carried"),
            "{}",
            none.reason
        );
    }
}
