//! The device's strings in the calibration report: how many, what their
//! number lets calibration and tracking check ([`StringsReport`]), how much
//! forward kinematics trusts each one ([`StringWeight`]) and what it did
//! with each row of a session ([`Rejections`]).

use serde::Serialize;

/// The strings of the calibrated device and what their number means for
/// what calibration and tracking can check.
#[derive(Clone, Debug, Serialize)]
pub struct StringsReport {
    /// Number of strings (anchors), 3..=8.
    pub strings: usize,
    /// Encoder channels that carry them.
    pub channels: Vec<usize>,
    /// The end-effector moves in the anchors' plane.
    pub planar: bool,
    /// Degrees of freedom of the position (2 or 3).
    pub dof: usize,
    /// Strings beyond the degrees of freedom.
    pub redundancy: usize,
    /// Whether forward kinematics can exclude a faulty string (needs 2 spare
    /// strings).
    pub fault_rejection: bool,
    /// Smallest constant error of one string that diagnosis would find on
    /// this training session (mm; `sigma * sqrt(chi2 threshold / rows)`,
    /// before the loss of power to what the model already absorbs).
    pub smallest_detectable_offset_mm: f64,
    /// What the number of strings and rows leaves unchecked, in words.
    pub limits: Vec<String>,
    /// What forward kinematics did with each row of the final identified
    /// model, per session: strings excluded as faulty, rows whose strings
    /// disagree with no single culprit.
    pub rejections: SessionRejections,
    /// Each string's measured scale and its weight in forward kinematics,
    /// in channel order.
    pub string_weights: Vec<StringWeight>,
    /// The typical string's scale, which the others are weighed against
    /// (mm; 0 when not measured).
    pub typical_scale_mm: f64,
}

/// How much forward kinematics trusts one string
/// ([`spidar_core::kinematics::residual_weights`]).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StringWeight {
    pub channel: usize,
    /// Robust scale of the part of its length residual that changes from
    /// row to row on the training session, mm.
    pub scale_mm: f64,
    /// Its residual's weight in forward kinematics (1: as the typical
    /// string; at least `MIN_RESIDUAL_WEIGHT`).
    pub weight: f64,
}

/// Below this weight the report names the string: it pulls the position
/// noticeably less than the others.
const NOTABLE_WEIGHT: f64 = 0.8;

/// [`Rejections`] of the training and the test session.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SessionRejections {
    pub train: Rejections,
    pub test: Rejections,
}

/// How forward kinematics treated the rows of one session.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Rejections {
    /// Rows predicted.
    pub rows: usize,
    /// Rows where this channel's string was excluded as faulty, per
    /// channel (0..8; channels without a string stay 0).
    pub excluded_by_channel: [usize; spidar_core::STRINGS],
    /// Rows whose strings disagree and no single exclusion is trusted (the
    /// device turns force off there), `inconsistent_excluded_by_channel`
    /// among them.
    pub inconsistent: usize,
    /// Of the inconsistent rows, those whose position leaves this channel's
    /// string out (the exclusion that fits clearly best, not trusted), per
    /// channel; the others are the all-string compromise.
    pub inconsistent_excluded_by_channel: [usize; spidar_core::STRINGS],
    /// Rows where the solve did not converge.
    pub not_converged: usize,
    /// Rows with an invalid length (NaN, negative).
    pub invalid: usize,
}

impl Rejections {
    pub fn of(predictions: &[crate::model::predict::Prediction]) -> Rejections {
        use spidar_core::kinematics::FkStatus;
        let mut r = Rejections {
            rows: predictions.len(),
            ..Rejections::default()
        };
        for p in predictions {
            match p.status {
                FkStatus::Ok => {}
                FkStatus::FaultyStringExcluded => {
                    if let Some(c) = p
                        .excluded
                        .and_then(|s| r.excluded_by_channel.get_mut(usize::from(s)))
                    {
                        *c += 1;
                    }
                }
                FkStatus::Inconsistent => {
                    r.inconsistent += 1;
                    if let Some(c) = p
                        .excluded
                        .and_then(|s| r.inconsistent_excluded_by_channel.get_mut(usize::from(s)))
                    {
                        *c += 1;
                    }
                }
                FkStatus::NotConverged => r.not_converged += 1,
                FkStatus::InvalidInput => r.invalid += 1,
            }
        }
        r
    }

    /// Rows not solved from all strings in agreement.
    pub fn flagged(&self) -> usize {
        self.excluded_by_channel.iter().sum::<usize>()
            + self.inconsistent
            + self.not_converged
            + self.invalid
    }

    /// One line in words, e.g. `3 of 2197 rows: string 2 excluded 3 times`.
    pub fn describe(&self) -> String {
        let mut parts: Vec<String> = self
            .excluded_by_channel
            .iter()
            .enumerate()
            .filter(|(_, &n)| n > 0)
            .map(|(s, &n)| {
                format!(
                    "string {s} excluded {n} time{}",
                    if n == 1 { "" } else { "s" }
                )
            })
            .collect();
        let placed: usize = self.inconsistent_excluded_by_channel.iter().sum();
        if self.inconsistent > 0 {
            let mut line = format!(
                "{} inconsistent (strings disagreeing, no exclusion trusted",
                self.inconsistent
            );
            let without: Vec<String> = self
                .inconsistent_excluded_by_channel
                .iter()
                .enumerate()
                .filter(|(_, &n)| n > 0)
                .map(|(s, &n)| format!("{n} without string {s}"))
                .collect();
            if !without.is_empty() {
                line += &format!(
                    "; placed {}, {} by all strings",
                    without.join(", "),
                    self.inconsistent - placed
                );
            }
            parts.push(line + ")");
        }
        for (n, what) in [
            (self.not_converged, "not converged"),
            (self.invalid, "invalid lengths"),
        ] {
            if n > 0 {
                parts.push(format!("{n} {what}"));
            }
        }
        if parts.is_empty() {
            format!("all {} rows solved with every string", self.rows)
        } else {
            format!(
                "{} of {} rows: {}",
                self.flagged(),
                self.rows,
                parts.join(", ")
            )
        }
    }
}

impl StringsReport {
    /// The report of `layout` calibrated from `tracked_rows` rows whose
    /// string residuals scatter by `residual_scale_mm` (each string's own
    /// scale `length_scale_mm`).
    pub fn of(
        layout: spidar_core::model::StringLayout,
        tracked_rows: usize,
        residual_scale_mm: f64,
        length_scale_mm: &[f64; spidar_core::STRINGS],
        chi2_threshold: f64,
        rejections: SessionRejections,
    ) -> StringsReport {
        let weights = spidar_core::kinematics::residual_weights(layout, length_scale_mm);
        let typical_scale_mm =
            spidar_core::kinematics::typical_scale(layout, length_scale_mm).unwrap_or(0.0);
        let string_weights = layout
            .indices()
            .map(|channel| StringWeight {
                channel,
                scale_mm: length_scale_mm[channel],
                weight: weights[channel],
            })
            .collect();
        let redundancy = layout.redundancy();
        let mut limits = Vec::new();
        match redundancy {
            0 => limits.push(
                "no spare string: the strings always agree on a position, so neither tracking \
                 nor calibration can see a string that reads wrong; string errors show only \
                 against the tracker"
                    .to_string(),
            ),
            1 => limits.push(
                "one spare string: the device sees when its strings disagree, but cannot tell \
                 which one is faulty (excluding a string needs 2 spare); a faulty string makes \
                 the position the least-squares compromise, flagged inconsistent"
                    .to_string(),
            ),
            2 => limits.push(
                "two spare strings: a faulty string is left out where its exclusion is the one \
                 set of strings that fits; where another fits by chance too, the row is flagged \
                 inconsistent (force off) and placed by the exclusion that fits clearly best, \
                 else by the least-squares compromise"
                    .to_string(),
            ),
            _ => {}
        }
        let smallest = residual_scale_mm * (chi2_threshold / tracked_rows.max(1) as f64).sqrt();
        if tracked_rows < 200 {
            limits.push(format!(
                "{tracked_rows} tracked rows: diagnosis sees a constant error of one string only \
                 above ~{smallest:.2} mm, and effects that depend on time, direction or speed \
                 are only testable with many rows spread over them"
            ));
        }
        StringsReport {
            strings: layout.count(),
            channels: layout.indices().collect(),
            planar: layout.planar,
            dof: layout.dof(),
            redundancy,
            fault_rejection: redundancy >= 2,
            smallest_detectable_offset_mm: smallest,
            limits,
            rejections,
            string_weights,
            typical_scale_mm,
        }
    }

    /// The strings forward kinematics trusts noticeably less than the
    /// typical one, in words (None when there is none).
    pub(super) fn describe_weights(&self) -> Option<String> {
        let notable: Vec<String> = self
            .string_weights
            .iter()
            .filter(|w| w.weight < NOTABLE_WEIGHT)
            .map(|w| {
                format!(
                    "string {} by {:.2} (its length scatters {:.2} mm)",
                    w.channel, w.weight, w.scale_mm
                )
            })
            .collect();
        if notable.is_empty() {
            return None;
        }
        Some(format!(
            "forward kinematics weighs {} against the typical string's {:.2} mm: \
             a string noisier than the others pulls the position less",
            notable.join(", "),
            self.typical_scale_mm
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::predict::Prediction;
    use spidar_core::kinematics::FkStatus;

    fn row(status: FkStatus, excluded: Option<u8>) -> Prediction {
        Prediction {
            device: [0.0; 3],
            room: [0.0; 3],
            status,
            excluded,
            rms_residual_mm: 0.0,
        }
    }

    #[test]
    fn rejections_are_counted_per_string_and_kind() {
        let rows = [
            row(FkStatus::Ok, None),
            row(FkStatus::FaultyStringExcluded, Some(2)),
            row(FkStatus::FaultyStringExcluded, Some(2)),
            row(FkStatus::FaultyStringExcluded, Some(7)),
            row(FkStatus::Inconsistent, None),
            row(FkStatus::Inconsistent, Some(1)),
            row(FkStatus::NotConverged, None),
            row(FkStatus::InvalidInput, None),
            row(FkStatus::Ok, None),
        ];
        let r = Rejections::of(&rows);
        assert_eq!(r.rows, 9);
        assert_eq!(r.excluded_by_channel, [0, 0, 2, 0, 0, 0, 0, 1]);
        assert_eq!(r.inconsistent_excluded_by_channel, [0, 1, 0, 0, 0, 0, 0, 0]);
        assert_eq!((r.inconsistent, r.not_converged, r.invalid), (2, 1, 1));
        assert_eq!(r.flagged(), 7);
        assert_eq!(
            r.describe(),
            "7 of 9 rows: string 2 excluded 2 times, string 7 excluded 1 time, \
             2 inconsistent (strings disagreeing, no exclusion trusted; placed 1 without \
             string 1, 1 by all strings), 1 not converged, 1 invalid lengths"
        );
        assert_eq!(
            Rejections::of(&rows[4..5]).describe(),
            "1 of 1 rows: 1 inconsistent (strings disagreeing, no exclusion trusted)"
        );
        let clean = Rejections::of(&rows[..1]);
        assert_eq!(clean.describe(), "all 1 rows solved with every string");
    }
}
