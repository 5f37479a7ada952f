//! What a calibration refuses and warns about: sessions that do not fit the
//! geometry or one another, a tracker in another unit, a clock the motion
//! could not align, too few tracked rows, the tracker's glitches, and a
//! held-out figure that is not what it seems (test points outside the
//! training volume, anchors that determine the position poorly, a final
//! model above the plain least-squares reference). The identified
//! geometry against the drawing is `geometry`'s; the tracker's glitches,
//! named by line, `outliers`'.

use std::path::Path;

use spidar_core::geometry::{device_from_room, distance};
use spidar_core::STRINGS;

use crate::data::dataset::{Geometry, Session};
use crate::data::impossible::{
    first_of, frame_span_mm, median_position, SetAside, NOMINAL_SCALE_LIMIT,
};
use crate::data::observe::{Observation, DIRECTION_HYSTERESIS_COUNTS};
use crate::model::identify::Structure;

use super::corrections::shows_above;
use super::{align, report, trust, CalibrateError, NamedSession, StagePoints};
use crate::procedures::plural;

/// Both sessions' facts for the report, after checking their strings
/// against the geometry, and the warnings they call for: test rows that are
/// training rows, columns nobody reads, rows set aside as impossible
/// (`set_aside`, found on the sessions `as_read`, whose positions
/// `train` and `test` no longer hold; a session most of whose rows are
/// impossible is refused).
pub(super) fn checked_sessions(
    geometry: &Geometry,
    geometry_path: &Path,
    train: NamedSession<'_>,
    test: NamedSession<'_>,
    set_aside: [&SetAside; 2],
    as_read: [&Session; 2],
) -> Result<(report::SessionInfo, report::SessionInfo, Vec<String>), CalibrateError> {
    let mut warnings: Vec<String> = Vec::new();
    for s in [&train, &test] {
        s.session.check_strings(s.path, geometry, geometry_path)?;
        check_dead_encoders(s)?;
    }
    for ((s, found), read) in [&train, &test].into_iter().zip(set_aside).zip(as_read) {
        check_set_aside(s, found, geometry_in_metres(read, geometry), geometry_path)?;
    }
    let train_info = session_info(train, set_aside[0])?;
    let test_info = report::SessionInfo {
        home: Some(crate::data::home::LaterHome::of(
            train.session,
            test.session,
        )),
        ..session_info(test, set_aside[1])?
    };
    match trust::shared_rows(train.session, test.session) {
        (0, _) => {}
        (shared, rows) if shared == rows => warnings.push(format!(
            "the test session {} holds only rows of the training session {}: the held-out \
             figures are training errors, not a test; record a separate test session",
            test.path.display(),
            train.path.display()
        )),
        (shared, rows) => warnings.push(format!(
            "{shared} of the {rows} test rows also appear in the training session: the \
             held-out figures are partly training errors; remove them from one of the files"
        )),
    }
    for (info, s) in [(&train_info, &train), (&test_info, &test)] {
        if !info.ignored_columns.is_empty() {
            warnings.push(format!(
                "{}: ignored unknown columns {}",
                s.path.display(),
                info.ignored_columns.join(", ")
            ));
        }
    }
    // Named by their keys in the JSON report's `inputs`.
    for ((s, found), name) in [&train, &test]
        .into_iter()
        .zip(set_aside)
        .zip(["train", "test"])
    {
        warnings.extend(set_aside_warning(s.path, found, name));
        warnings.extend(repeated_rows_warning(s.path, found, name));
        warnings.extend(coarse_times_warning(s.path, s.session));
    }
    Ok((train_info, test_info, warnings))
}

/// Fewest rows over which an encoder that never changes while the others
/// do is taken for a dead one (fewer rows may all sit at one length).
const DEAD_ENCODER_ROWS: usize = 10;

/// Refuses a session one of whose encoder columns reads one value on every
/// row while another's changes: a dead encoder or an unplugged channel,
/// which no string model can take (a 5-string lattice with `enc2` all 0
/// was calibrated with warnings on string 2's radius and anchor, and the
/// calibration did not compile).
fn check_dead_encoders(s: &NamedSession<'_>) -> Result<(), CalibrateError> {
    let samples = &s.session.samples;
    if samples.len() < DEAD_ENCODER_ROWS {
        return Ok(());
    }
    let changes = |i: usize| samples.iter().any(|r| r.counts[i] != samples[0].counts[i]);
    let strings = 0..s.session.strings;
    if !strings.clone().any(changes) {
        return Ok(());
    }
    let dead: Vec<String> = strings
        .filter(|&i| !changes(i))
        .map(|i| format!("enc{i} = {}", samples[0].counts[i]))
        .collect();
    if dead.is_empty() {
        return Ok(());
    }
    Err(CalibrateError::Session {
        file: s.path.to_path_buf(),
        problem: format!(
            "{} on every one of its {} rows while the other encoders change: a dead encoder \
             or an unplugged channel, whose string no calibration can place. Check the encoder \
             and its wiring, and record the session again",
            dead.join(", "),
            samples.len()
        ),
    })
}

/// How many set-aside rows a message lists (the JSON report has them all).
const SET_ASIDE_SHOWN: usize = 12;

/// Refuses a session most of whose rows no device of the geometry could
/// produce: not bad rows, but a geometry or a unit that does not fit it.
/// `in_metres`: what [`geometry_in_metres`] found of the session as read.
fn check_set_aside(
    s: &NamedSession<'_>,
    found: &SetAside,
    in_metres: Option<String>,
    geometry_path: &Path,
) -> Result<(), CalibrateError> {
    let rows = s.session.samples.len();
    if !found.is_most_of(rows) {
        return Ok(());
    }
    let check = in_metres.unwrap_or_else(|| {
        "check the geometry's anchors, pulley_radius_mm, counts_per_rev and \
         mechanical_advantage against the device, and that the tracker gives millimetres"
            .to_string()
    });
    Err(CalibrateError::Session {
        file: s.path.to_path_buf(),
        problem: format!(
            "{} of its {rows} rows hold values no device of the geometry {} could produce, too \
             many to be bad rows: {check}. {}",
            found.impossible().count(),
            geometry_path.display(),
            found.lines(SET_ASIDE_SHOWN)
        ),
    })
}

/// What to check when the session's tracked positions spread over far more
/// than the geometry's frame (a device's end-effector stays inside it) by
/// about the factor of metres: the geometry's lengths read as metres (a
/// geometry typed in metres was refused with the rows' message, which
/// named the tracker's unit). `None` otherwise. `session`: as read (the
/// rows set aside as impossible keep their positions).
fn geometry_in_metres(session: &Session, geometry: &Geometry) -> Option<String> {
    let span = frame_span_mm(geometry);
    if span <= 0.0 || !span.is_finite() {
        return None;
    }
    let tracked = session.samples.iter().filter_map(|r| r.tracker);
    let centre = median_position(tracked.clone())?;
    // Twice the median distance from the median position: the extent of
    // the positions, a tracker's glitches aside.
    let spread = 2.0
        * crate::data::stats::median(&mut tracked.map(|p| distance(p, centre)).collect::<Vec<_>>());
    // A session spans a tenth of its frame to the whole of it; in metres,
    // the frame reads a thousand times smaller.
    let in_metres = (50.0..=20_000.0).contains(&(spread / span));
    in_metres.then(|| {
        format!(
            "the geometry's anchors and home span {span:.3} mm where the tracked positions spread \
             over {spread:.0} mm: the geometry's lengths look like metres (`anchors_mm`, \
             `home_mm` and `pulley_radius_mm` are millimetres)"
        )
    })
}

/// The warning that names the rows of a session set aside as impossible
/// (`key`: the session's name in the JSON report's `inputs`).
fn set_aside_warning(path: &Path, found: &SetAside, key: &str) -> Option<String> {
    let count = found.impossible().count();
    if count == 0 {
        return None;
    }
    Some(format!(
        "{}: {count} row{} set aside, holding values no device of this geometry could produce \
         (a row whose counts cannot be is left out of the calibration and its figures; one \
         whose position cannot be reads as occluded, or without its legacy position); the JSON \
         report's `inputs.{key}.set_aside` lists them all: {}",
        path.display(),
        if count == 1 { "" } else { "s" },
        found.lines(SET_ASIDE_SHOWN)
    ))
}

/// The warning that names the rows of a session that repeat the row
/// before them exactly, set aside whole (`key`: the session's name in the
/// JSON report's `inputs`).
fn repeated_rows_warning(path: &Path, found: &SetAside, key: &str) -> Option<String> {
    let count = found.repeats().count();
    if count == 0 {
        return None;
    }
    Some(format!(
        "{}: {} set aside: {} (the same `t_s` and every value): a row duplicated on its way to \
         the file, which would weigh its pose twice, is left out of the calibration and its \
         figures; the JSON report's `inputs.{key}.set_aside` lists {}",
        path.display(),
        plural(count, "row", "rows"),
        found.repeat_lines(SET_ASIDE_SHOWN),
        if count == 1 { "it" } else { "them all" }
    ))
}

/// The warning that names the rows of a session stamped with the time of
/// the row before though its strings moved between them (by a tenth of a
/// millimetre's counts or more, [`DIRECTION_HYSTERESIS_COUNTS`]): a 100 Hz
/// stream stamped to 20 ms calibrated with its speed's structure blamed on
/// lagging encoders (14 mm on every string) and 120 rows' tracker on
/// glitches, and nothing said the times were coarse.
fn coarse_times_warning(path: &Path, session: &Session) -> Option<String> {
    let found = session.rows_at_one_time_moving(DIRECTION_HYSTERESIS_COUNTS);
    if found.is_empty() {
        return None;
    }
    let largest = found.iter().map(|f| f.2).max().unwrap_or(0);
    let lines = first_of(
        found
            .iter()
            .map(|&(row, before, _)| format!("{} and {}", before + 2, row + 2)),
        SET_ASIDE_SHOWN,
    );
    Some(format!(
        "{}: {} the `t_s` of the row before though the strings moved between them (up to \
         {largest} counts): the log's timestamps are coarser than its rows. A stream's speed, \
         its strings' latency and the clocks' alignment read time from `t_s` and see such rows \
         at one instant; log the time at the rows' own resolution. Lines {lines}",
        path.display(),
        plural(found.len(), "row carries", "rows carry"),
    ))
}

/// Session facts for the report; refuses a session the tracker never saw
/// (after the rows set aside).
fn session_info(
    s: NamedSession<'_>,
    set_aside: &SetAside,
) -> Result<report::SessionInfo, CalibrateError> {
    let rows = s.session.samples.len();
    let skipped = set_aside.rows();
    let tracked = s
        .session
        .samples
        .iter()
        .enumerate()
        .filter(|(row, r)| r.tracker.is_some() && skipped.binary_search(row).is_err())
        .count();
    if tracked == 0 {
        return Err(CalibrateError::Session {
            file: s.path.to_path_buf(),
            problem: format!(
                "none of its {rows} rows has a tracker position (ots_x, ots_y, ots_z){}: \
                 nothing to calibrate or evaluate against",
                if set_aside.is_empty() {
                    String::new()
                } else {
                    format!(" after {} set aside as impossible", set_aside.values.len())
                }
            ),
        });
    }
    Ok(report::SessionInfo {
        path: s.path.display().to_string(),
        rows,
        tracked,
        occluded: rows - skipped.len() - tracked,
        has_legacy: s.session.has_legacy(),
        has_tension: s.session.has_tension(),
        ignored_columns: s.session.ignored_columns.clone(),
        unread_columns: s.session.unread_columns.clone(),
        set_aside: set_aside.values.clone(),
        home: None,
    })
}

/// A warning for each session whose clock alignment left rows without a
/// tracker position.
pub(super) fn unpaired_rows_warnings(timing: &report::Timing) -> Vec<String> {
    let mut warnings = Vec::new();
    for (name, t) in [("training", &timing.train), ("test", &timing.test)] {
        if let align::SessionTiming::Aligned(a) = t {
            if a.rows_unpaired > 0 {
                warnings.push(format!(
                    "{name} session: {} rows lost their tracker position when re-paired by the \
                     {:+.2} ms clock offset (before the tracker's first or after its last frame, \
                     or across a gap)",
                    a.rows_unpaired,
                    a.offset_s * 1e3
                ));
            }
        }
    }
    warnings
}

/// How far the tracker's spread may be from the nominal model's before a
/// calibration refuses the sessions: a unit mistake (metres, centimetres or
/// inches against the millimetres of the format) is a factor of 10 or more,
/// which the identification would otherwise fit away (into pulley radii a
/// thousandth of the device's, reporting errors in the wrong unit). The
/// simulated paper-sized devices, whose nominal pulley radius is half the
/// wound one, are at 1.9 to 2.4; the Hangprinter at 1.01; other simulated
/// devices at 1.3 to 1.4.
const TRACKER_SCALE_REFUSED: f64 = NOMINAL_SCALE_LIMIT;

/// Beyond this factor (and within [`TRACKER_SCALE_REFUSED`]) the report
/// warns.
const TRACKER_SCALE_WARNED: f64 = 3.0;

/// Refuses a session (training or test, read from `path`) whose tracker
/// positions spread a factor of [`TRACKER_SCALE_REFUSED`] or more off the
/// nominal model's positions of the same rows, naming the likely unit;
/// beyond [`TRACKER_SCALE_WARNED`], a warning.
pub(super) fn check_tracker_scale(
    path: &Path,
    geometry_path: &Path,
    rows: &[Observation],
    raw: &[[f64; 3]],
) -> Result<Option<String>, CalibrateError> {
    let Some((tracker_mm, nominal_mm)) = tracker_spread_ratio(rows, raw) else {
        return Ok(None);
    };
    let ratio = tracker_mm / nominal_mm;
    let factor = ratio.max(1.0 / ratio);
    if factor < TRACKER_SCALE_WARNED {
        return Ok(None);
    }
    let unit = [(1000.0, "metres"), (25.4, "inches"), (10.0, "centimetres")]
        .iter()
        .find(|(k, _)| (factor / k - 1.0).abs() < 0.2)
        .map(|(_, unit)| unit);
    let what = format!(
        "the tracker's positions spread {tracker_mm:.3} (root mean square distance from their \
         centroid) where the nominal geometry {} puts the same rows {nominal_mm:.3} mm from \
         theirs: {ratio:.4} times",
        geometry_path.display()
    );
    let hint = match unit {
        Some(unit) if ratio < 1.0 => {
            format!("the session's `ots_*` columns look like {unit}; the format is in millimetres")
        }
        Some(unit) => format!(
            "the geometry's lengths (anchors, home, pulley radius) look like {unit}, or the \
             tracker's `ots_*` columns like a unit finer than millimetres; the format is in \
             millimetres"
        ),
        None => "check the geometry's pulley_radius_mm, counts_per_rev and mechanical_advantage \
                 against the device, and that the tracker gives millimetres"
            .to_string(),
    };
    if factor >= TRACKER_SCALE_REFUSED {
        return Err(CalibrateError::Session {
            file: path.to_path_buf(),
            problem: format!("{what}: {hint}"),
        });
    }
    Ok(Some(format!("{}: {what}: {hint}", path.display())))
}

/// The tracker's spread over the training session against the nominal
/// model's over the same rows: the root mean square distance of the tracked
/// positions from their centroid, over that of the nominal model's room
/// positions of those rows. `None` with fewer than 3 tracked rows or no
/// spread.
fn tracker_spread_ratio(obs: &[Observation], raw: &[[f64; 3]]) -> Option<(f64, f64)> {
    let (tracked, nominal): (Vec<[f64; 3]>, Vec<[f64; 3]>) = obs
        .iter()
        .zip(raw)
        .filter_map(|(o, p)| o.tracker.map(|t| (t, *p)))
        .filter(|(t, p)| t.iter().chain(p).all(|x| x.is_finite()))
        .unzip();
    if tracked.len() < 3 {
        return None;
    }
    let (t, m) = (rms_spread(&tracked), rms_spread(&nominal));
    (t > 0.0 && m > 0.0).then_some((t, m))
}

/// The root mean square distance of `points` from their centroid (0 for
/// none).
fn rms_spread(points: &[[f64; 3]]) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let n = points.len() as f64;
    let c: [f64; 3] = core::array::from_fn(|k| points.iter().map(|p| p[k]).sum::<f64>() / n);
    (points
        .iter()
        .map(|p| (0..3).map(|k| (p[k] - c[k]).powi(2)).sum::<f64>())
        .sum::<f64>()
        / n)
        .sqrt()
}

/// Fits of the geometry (the plain least-squares reference's or the
/// identification's, the better) whose training error is above this share
/// of the tracked positions' spread have found no geometry that puts the
/// strings where the tracker saw the end-effector. Measured on 143
/// calibrations of simulated 3- to 6-string devices (3-D and planar,
/// spread poses and streams, 10 to 1,000 rows) and of the Hangprinter
/// 2022's subsets, on the model simulator's lattice and two 30,000-row
/// sessions of the independent one: at most 0.9 % where the rows were
/// paired right, 30 % and more where they were not (static captures of a
/// moving marker with the tracker's clock 3 s off, streams read as poses,
/// a planar geometry for a 3-D device; decision record 0073,
/// `docs/decisions/0073-short-streams-aligned-and-unfitted-sessions-named.md`).
pub(super) const UNFITTED_SHARE: f64 = 0.05;

/// The warning for a training session `tr` that no geometry fits: the
/// better training mean of the plain least-squares reference and the
/// identification (of `stages`) above [`UNFITTED_SHARE`] of the spread of
/// the session's tracked positions. The rows then pair the strings with
/// the marker from elsewhere, and every stage fitted to them is
/// meaningless however it is chosen.
pub(super) fn unfitted_warning(
    train_path: &Path,
    tr: &[Observation],
    stages: &[report::Stage],
) -> Option<String> {
    let best_fit_mm = stages
        .iter()
        .filter(|s| {
            matches!(
                s.kind,
                report::StageKind::Reference | report::StageKind::Identified
            )
        })
        .map(|s| s.train.mean_mm)
        .reduce(f64::min)?;
    let tracked: Vec<[f64; 3]> = tr.iter().filter_map(|o| o.tracker).collect();
    let spread = rms_spread(&tracked);
    (spread > 0.0 && best_fit_mm > UNFITTED_SHARE * spread).then(|| {
        format!(
            "{}: no geometry fits this session: the best fit of the geometry leaves {:.3} mm on \
             its own training rows, {:.1} % of their spread ({:.1} mm, root mean square from \
             the centroid). Are the tracker's positions paired with the right rows? A tracker \
             whose clock is off on captures made while moving (pair them by a common clock, or \
             record a stream, whose offset is found from the motion), positions of another \
             session, or another device's geometry (a planar one for a device that moves in 3-D)",
            train_path.display(),
            best_fit_mm,
            100.0 * best_fit_mm / spread,
            spread
        )
    })
}

/// Refuses a session whose tracker clock the motion could not align: with
/// the model identified from the data (the last round of the training
/// session's alignment, the test session's), the positions did not confirm
/// the speed profiles' peak ([`align::ClockAlignment::refined`]). Re-paired
/// by such an offset, every row holds the marker from elsewhere, and the
/// calibration fitted to them is meaningless. (The profiles' correlation
/// does not tell: a short test stream that is well aligned still correlates
/// weakly.)
pub(super) fn check_alignment(
    path: &Path,
    timing: &align::SessionTiming,
) -> Result<(), CalibrateError> {
    let align::SessionTiming::Aligned(a) = timing else {
        return Ok(());
    };
    if a.refined {
        return Ok(());
    }
    Err(CalibrateError::Session {
        file: path.to_path_buf(),
        problem: format!(
            "the tracker's clock could not be aligned with the device's from the motion: the \
             speed profiles peak at {:+.3} s (correlation {:.2}), but the positions the \
             identified model gives do not confirm it. The search reaches {} s around the \
             offset it starts from: is the tracker's clock further off (`calibrate \
             --clock-offset-s` starts it elsewhere), or did the hand hardly move? Record the \
             session with the tracker's and the device's clocks paired by a common time \
             (`--clocks-paired`)",
            a.offset_s,
            a.correlation,
            align::MAX_OFFSET_S
        ),
    })
}

/// "tracked pose" for one, "tracked poses" for more.
fn poses(n: usize) -> &'static str {
    if n == 1 {
        "tracked pose"
    } else {
        "tracked poses"
    }
}

/// What a training session is large enough for.
#[derive(Clone, Debug)]
pub(super) struct Regime {
    /// The diagnosis loop and the learned corrections run (every change is
    /// judged on two halves, each of which must identify the model).
    pub(super) full: bool,
    /// Why they do not, in the user's terms.
    pub(super) reason: Option<String>,
}

/// What the training session's tracked rows allow: a refusal below what
/// identifies the base model (rows x strings against its free parameters,
/// twice over), identification only below twice that, else everything.
pub(super) fn check_enough_tracked_rows(
    train_path: &Path,
    tr: &[Observation],
    nominal: &spidar_core::model::Frame<f64>,
) -> Result<Regime, CalibrateError> {
    let needed = crate::model::identify::rows_needed_for(&Structure::default(), nominal.layout);
    let tracked = tr.iter().filter(|o| o.tracker.is_some()).count();
    if tracked < needed {
        return Err(CalibrateError::Session {
            file: train_path.to_path_buf(),
            problem: format!(
                "{tracked} rows with tracker positions; identifying the model of {} strings \
                 needs at least {needed} (twice as many string lengths as free parameters): \
                 collect {} more {} spread through the volume",
                nominal.layout.count(),
                needed - tracked,
                poses(needed - tracked)
            ),
        });
    }
    if tracked < 2 * needed {
        return Ok(Regime {
            full: false,
            reason: Some(format!(
                "identification only: the training session has {tracked} tracked rows; the \
                 diagnosis loop and the learned corrections need {} ({needed} to identify the \
                 model in each half of the 2-fold validation that judges every change): collect \
                 {} more {} to enable them",
                2 * needed,
                2 * needed - tracked,
                poses(2 * needed - tracked)
            )),
        });
    }
    Ok(Regime {
        full: true,
        reason: None,
    })
}

/// Where the held-out figure is not what it seems: test points outside the
/// training volume, and anchors that determine the position poorly.
pub(super) fn trust_warnings(
    frame: &spidar_core::model::Frame<f64>,
    tr: &[Observation],
    final_points: Option<&StagePoints>,
    reference_points: Option<&StagePoints>,
) -> Vec<String> {
    let mut warnings = Vec::new();
    let train_room: Vec<[f64; 3]> = tr.iter().filter_map(|o| o.tracker).collect();
    const BOX_MARGIN_MM: f64 = 1.0;
    if let (Some(bx), Some(fp)) = (
        trust::TrainingBox::of(frame, &train_room, BOX_MARGIN_MM),
        final_points,
    ) {
        let x = trust::extrapolation(frame, &bx, &fp.test.tracker, &fp.test.errors);
        if x.outside.n > 0 {
            // The floor beside it: the plain least-squares reference on the
            // same points, where the final model is another.
            let plain = reference_points
                .filter(|r| r.name != fp.name)
                .map(|r| trust::extrapolation(frame, &bx, &r.test.tracker, &r.test.errors))
                .map_or(String::new(), |r| {
                    format!(
                        " (the plain least-squares reference: outside {:.3} mean, inside {:.3})",
                        r.outside.mean_mm, r.inside.mean_mm
                    )
                });
            warnings.push(format!(
                "{} of {} test points lie outside the volume the training session covers (its \
                 box, {BOX_MARGIN_MM} mm margin): the model extrapolates there; final error \
                 outside {:.3} mm mean, {:.3} max, inside {:.3} mean, {:.3} max{plain}",
                x.outside.n,
                x.outside.n + x.inside.n,
                x.outside.mean_mm,
                x.outside.max_mm,
                x.inside.mean_mm,
                x.inside.max_mm
            ));
        }
    }
    let train_device: Vec<[f64; 3]> = train_room
        .iter()
        .map(|r| device_from_room(frame, *r))
        .collect();
    if let Some(d) = trust::determination(frame, &train_device) {
        if d.gain > trust::POOR_DETERMINATION_GAIN {
            warnings.push(format!(
                "the anchors determine the position poorly along ({:+.2}, {:+.2}, {:+.2}) \
                 (device frame): there a string-length error moves the position {:.1} times as \
                 much (median over the training points; a cube SPIDAR: ~0.6). Anchors nearly in \
                 one plane or line? Spread them, or expect errors along that direction",
                d.direction[0], d.direction[1], d.direction[2], d.gain
            ));
        }
    }
    warnings
}

/// A warning when the geometry declares the anchors' tolerance
/// (`anchor_sd_mm`) and the data contradict it: the plain least-squares
/// reference, which has no prior, places an anchor beyond the 0.1 %
/// chi-square of that tolerance from the drawing, and the identified model
/// (held to the tolerance) is worse than the reference on the test session
/// (by more than the report's micrometre, [`super::corrections::SELECTION_TIE_MM`]).
/// The warning names the anchor, how far, in sds, and both figures.
pub(super) fn declared_tolerance_warning(
    declared_sd_mm: Option<&[f64; STRINGS]>,
    drawing: &spidar_core::model::Frame<f64>,
    reference: &spidar_core::model::Frame<f64>,
    stages: &[report::Stage],
) -> Option<String> {
    let sd = declared_sd_mm?;
    let test_mean = |kind| {
        stages
            .iter()
            .find(|s: &&report::Stage| s.kind == kind)
            .map(|s| s.test.mean_mm)
    };
    let identified = test_mean(report::StageKind::Identified)?;
    let plain = test_mean(report::StageKind::Reference)?;
    // Not where the identified model is as good as the report shows the
    // two, nor on figures not finite.
    if !shows_above(identified, plain) {
        return None;
    }
    // Exceeded with probability 0.001 when the tolerance is right: 2
    // degrees of freedom in a plane, 3 in space.
    let limit = crate::data::stats::chi_square_p001(if drawing.layout.planar { 2 } else { 3 });
    let (string, distance_mm, sds) = (0..STRINGS)
        .filter(|&i| drawing.layout.is_active(i) && sd[i] > 0.0)
        .map(|i| {
            let d = spidar_core::geometry::distance(reference.anchors[i], drawing.anchors[i]);
            (i, d, d / sd[i])
        })
        .filter(|&(_, _, k)| k * k > limit)
        .max_by(|a, b| a.2.total_cmp(&b.2))?;
    Some(format!(
        "the geometry's `anchor_sd_mm` ({:.3} mm for string {string}) is contradicted by the \
         data: the plain least-squares reference places anchor {string} {distance_mm:.1} mm from \
         the drawing ({sds:.0} sds), and the identified model, held to the declared tolerance, \
         has a held-out mean of {identified:.3} mm against the reference's {plain:.3}; widen \
         `anchor_sd_mm`, or leave it out and the calibration chooses the tolerance on its folds",
        sd[string]
    ))
}

/// A warning when the final model's held-out mean is above the plain
/// least-squares reference's (by more than the report's micrometre,
/// [`super::corrections::SELECTION_TIE_MM`]; each comparison below too), naming what the calibration adds to a plain
/// fit that lost on this test session: the learned correction (the final
/// stage above the model it corrects), the kinematics' rule (the final
/// identified model placing the rows as the reference does beats the
/// reference), the loop's terms (the base identification beats the
/// reference) or, failing those, the identification's robust weights and
/// priors. `plain_rule_test_mm`: the final identified model's held-out
/// mean under the reference's rule.
pub(super) fn reference_warning(
    stages: &[report::Stage],
    plain_rule_test_mm: f64,
) -> Option<String> {
    let of = |kind| {
        stages
            .iter()
            .filter(move |s: &&report::Stage| s.kind == kind)
    };
    let reference = of(report::StageKind::Reference).next()?.test.mean_mm;
    let fin = of(report::StageKind::Final).next()?;
    // Above as the report shows the figures: a difference it cannot show
    // is no loss, here as in the selection.
    if !shows_above(fin.test.mean_mm, reference) {
        return None;
    }
    let identified = of(report::StageKind::Identified).next()?.test.mean_mm;
    let model = of(report::StageKind::Effect)
        .next_back()
        .map_or(identified, |s| s.test.mean_mm);
    let lost = if shows_above(fin.test.mean_mm, model) && !shows_above(model, reference) {
        format!("the learned correction ({} on {model:.3} mm)", fin.name)
    } else if !shows_above(plain_rule_test_mm, reference) {
        format!(
            "the kinematics' rule (the same model placing every row with all its strings alike: \
             {plain_rule_test_mm:.3} mm)"
        )
    } else if !shows_above(identified, reference) {
        format!("the loop's terms (the base identification: {identified:.3} mm)")
    } else {
        format!(
            "the identification's robust weights and priors (the base identification: \
             {identified:.3} mm; `anchor_sd_mm` in the geometry sets the anchors' tolerance)"
        )
    };
    Some(format!(
        "the final model's held-out mean {:.3} mm is above the plain least-squares reference's \
         {reference:.3} mm: what lost is {lost}",
        fin.test.mean_mm
    ))
}

mod geometry;
mod outliers;
#[cfg(test)]
mod tests;

pub(in crate::procedures::calibrate) use geometry::{
    anchor_departure_warnings, planar_session_warnings, radius_warnings,
};
pub(in crate::procedures::calibrate) use outliers::{
    test_outlier_warning, tracker_outlier_warning,
};
