//! The tracker's glitches: training rows the loop set aside, test rows
//! whose tracker disagrees with most of their strings, named by line.

use std::path::Path;

use crate::procedures::plural;

/// The warning for the training rows whose tracker the loop set aside
/// (or found far off in too great a number to set aside), naming their
/// lines.
pub(in crate::procedures::calibrate) fn tracker_outlier_warning(
    train_path: &Path,
    outliers: &crate::model::diagnose::TrackerOutliers,
) -> Option<String> {
    if outliers.kept_too_many > 0 {
        return Some(format!(
            "{}: the tracker of {} disagrees with most of {} strings by more than {:.1} \
             mm ({}x the median {:.3} mm) under the identified model: too many to be the \
             tracker's glitches, so all are kept; the model does not fit this session",
            train_path.display(),
            plural(outliers.kept_too_many, "row", "rows"),
            their(outliers.kept_too_many),
            outliers.threshold_mm,
            crate::model::diagnose::GROSS_TRACKER_MEDIANS,
            outliers.median_mm
        ));
    }
    if outliers.rows.is_empty() {
        return None;
    }
    Some(format!(
        "{}: the tracker of {} disagrees with most of {} strings by more than {:.1} mm \
         ({}x the median {:.3} mm) under the identified model: a tracker's glitch (a reflection, \
         a swapped or lost marker), not a position; {} (out of the \
         fit, the loop's judgement and the training figures; the raw stage still has them): \
         {} {}",
        train_path.display(),
        plural(outliers.rows.len(), "row", "rows"),
        their(outliers.rows.len()),
        outliers.threshold_mm,
        crate::model::diagnose::GROSS_TRACKER_MEDIANS,
        outliers.median_mm,
        if outliers.rows.len() == 1 {
            "it is read as an occluded row"
        } else {
            "they are read as occluded rows"
        },
        if outliers.rows.len() == 1 {
            "line"
        } else {
            "lines"
        },
        outlier_lines(
            outliers,
            Some("the JSON report's `identification.tracker_outliers`")
        ),
    ))
}

/// The warning for the test rows whose tracker disagrees with most of
/// their strings under the final model beyond the training session's
/// threshold: the held-out figures keep them (they are the test), and the
/// user learns which lines to look at.
pub(in crate::procedures::calibrate) fn test_outlier_warning(
    test_path: &Path,
    outliers: &crate::model::diagnose::TrackerOutliers,
) -> Option<String> {
    if outliers.rows.is_empty() && outliers.kept_too_many == 0 {
        return None;
    }
    let count = outliers.rows.len().max(outliers.kept_too_many);
    Some(format!(
        "{}: the tracker of {} disagrees with most of {} strings by more than {:.1} mm (the \
         training session's threshold) under the final model: a tracker's glitch, or a model \
         that does not hold there; the held-out figures include {}{}",
        test_path.display(),
        plural(count, "row", "rows"),
        their(count),
        outliers.threshold_mm,
        if count == 1 { "it" } else { "them" },
        if outliers.rows.is_empty() {
            String::new()
        } else {
            format!(
                ": {} {}",
                if outliers.rows.len() == 1 {
                    "line"
                } else {
                    "lines"
                },
                outlier_lines(outliers, None)
            )
        }
    ))
}

/// "its" for one row's strings, "their" for more.
fn their(rows: usize) -> &'static str {
    if rows == 1 {
        "its"
    } else {
        "their"
    }
}

/// The first lines of `outliers` with their disagreement, and how many
/// more there are (`where_all`: where the rest is listed).
fn outlier_lines(
    outliers: &crate::model::diagnose::TrackerOutliers,
    where_all: Option<&str>,
) -> String {
    const SHOWN: usize = 12;
    let lines: Vec<String> = outliers
        .lines
        .iter()
        .zip(&outliers.errors_mm)
        .take(SHOWN)
        .map(|(line, e)| format!("{line} ({e:.0} mm)"))
        .collect();
    let more = outliers.lines.len().saturating_sub(SHOWN);
    match (more, where_all) {
        (0, _) => lines.join(", "),
        (_, Some(place)) => format!("{} and {more} more ({place})", lines.join(", ")),
        (_, None) => format!("{} and {more} more", lines.join(", ")),
    }
}
