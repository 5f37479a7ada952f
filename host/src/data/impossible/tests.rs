//! Tests of the impossible rows: what is set aside, by line, and what stays.

use super::*;
use crate::data::dataset::Sample;
use spidar_core::STRINGS;

/// A 4-string 3-D rig of a 1.4 m span and a session of `rows`
/// rows around its centre.
fn rig(rows: usize) -> (Geometry, Session) {
    let text = "anchors_mm = [[0, 0, 0], [1000, 0, 0], [0, 1000, 0], [0, 0, 1000]]\n\
                counts_per_rev = 4096\npulley_radius_mm = 10\nhome_mm = [250, 250, 250]\n\
                room_from_device_translation_mm = [0, 0, 0]\n";
    let geometry = Geometry::from_toml_str(text, std::path::Path::new("g.toml")).unwrap();
    let samples = (0..rows)
        .map(|k| {
            let x = 200.0 + k as f64;
            let mut counts = [0i32; STRINGS];
            for (i, c) in counts.iter_mut().take(4).enumerate() {
                *c = (k as i32) * (i as i32 + 1);
            }
            Sample {
                t_s: k as f64 * 0.1,
                counts,
                tracker: Some([x, 250.0, 250.0]),
                orientation: None,
                legacy: Some([x, 250.0, 250.0]),
                tension_n: None,
                since_home_s: None,
                home: None,
            }
        })
        .collect();
    let session = Session {
        strings: 4,
        samples,
        ..Session::default()
    };
    (geometry, session)
}

#[test]
fn a_session_that_can_be_sets_nothing_aside() {
    let (g, s) = rig(50);
    assert!(SetAside::find(&s, &g).is_empty());
}

#[test]
fn a_count_beyond_the_frame_sets_its_row_aside_by_line() {
    let (g, mut s) = rig(50);
    s.samples[19].counts[2] = i32::MIN;
    let found = SetAside::find(&s, &g);
    assert_eq!(found.values.len(), 1, "{found:?}");
    let v = &found.values[0];
    assert_eq!((v.row, v.line, v.column.as_str()), (19, 21, "enc2"));
    assert_eq!(v.part, SetAsidePart::Row);
    assert_eq!(found.rows(), vec![19]);
    assert!(found.lines(12).contains("line 21 (`enc2` = -2147483648"));
}

#[test]
fn a_tracker_far_outside_the_frame_empties_that_position_only() {
    let (g, mut s) = rig(50);
    s.samples[5].tracker = Some([1e6, 250.0, 250.0]);
    s.samples[7].tracker = Some([250.0, 1e300, 250.0]);
    let found = SetAside::find(&s, &g);
    let named: Vec<(u64, &str, SetAsidePart)> = found
        .values
        .iter()
        .map(|v| (v.line, v.column.as_str(), v.part))
        .collect();
    assert_eq!(
        named,
        vec![
            (7, "ots_x", SetAsidePart::Tracker),
            (9, "ots_y", SetAsidePart::Tracker)
        ]
    );
    assert!(found.rows().is_empty());
    let kept = found.without_positions(&s);
    assert_eq!(kept.samples.len(), 50);
    assert!(kept.samples[5].tracker.is_none() && kept.samples[7].tracker.is_none());
    assert_eq!(kept.samples[5].counts, s.samples[5].counts);
}

#[test]
fn a_position_within_the_bounds_stays_even_if_odd() {
    // A tracker glitch of 300 mm is the loop's to judge (its strings
    // disagree), not impossible: 5 spans of this frame are ~7 m.
    let (g, mut s) = rig(50);
    s.samples[5].tracker = Some([550.0, 250.0, 250.0]);
    assert!(SetAside::find(&s, &g).is_empty());
}

#[test]
fn legacy_positions_are_judged_when_read() {
    let (g, mut s) = rig(50);
    s.samples[3].legacy = Some([0.0, 0.0, 1e300]);
    let found = SetAside::find(&s, &g);
    assert_eq!(found.values.len(), 1);
    assert_eq!(
        (found.values[0].column.as_str(), found.values[0].part),
        ("dev_z", SetAsidePart::Legacy)
    );
    assert!(found.without_positions(&s).samples[3].legacy.is_none());
}

#[test]
fn most_rows_impossible_is_the_geometry_not_the_rows() {
    let (g, mut s) = rig(10);
    for sample in s.samples.iter_mut().take(6) {
        sample.tracker = Some([1e8, 0.0, 0.0]);
    }
    let found = SetAside::find(&s, &g);
    assert!(found.is_most_of(10), "{found:?}");
    assert!(!SetAside {
        values: found.values[..5].to_vec()
    }
    .is_most_of(10));
}

#[test]
fn the_span_is_the_largest_distance_across_the_frame() {
    let (g, _) = rig(1);
    assert!((frame_span_mm(&g) - 1000.0 * 2f64.sqrt()).abs() < 1e-9);
}

/// A row that repeats the row before it exactly is set aside whole, named
/// with the line it repeats; it is not counted among the values no device
/// could produce (nor towards refusing the geometry).
#[test]
fn a_repeated_row_is_set_aside_naming_the_line_it_repeats() {
    let (g, mut s) = rig(50);
    let copy = s.samples[5].clone();
    s.samples.insert(6, copy);
    assert_eq!(s.repeated_rows(), vec![(6, 5)]);
    let found = SetAside::find(&s, &g);
    assert_eq!(found.rows(), vec![6], "{found:?}");
    let v = &found.values[0];
    assert_eq!(
        (v.line, v.column.as_str(), v.part),
        (8, "t_s", SetAsidePart::Row)
    );
    assert_eq!(v.repeats_line, Some(7));
    assert_eq!(found.repeat_lines(12), "line 8 repeats line 7");
    assert_eq!(found.lines(12), "");
    assert_eq!(found.impossible().count(), 0);
    assert!(!found.is_most_of(2));
}

/// Rows stamped with the time of the row before while a string moved are
/// listed with the largest move; an exact repeat, and a row of one time
/// whose counts moved less than asked, are not.
#[test]
fn rows_stamped_at_the_time_before_while_moving_are_found() {
    let (_, mut s) = rig(20);
    for k in [4, 9] {
        s.samples[k].t_s = s.samples[k - 1].t_s;
    }
    let copy = s.samples[14].clone();
    s.samples.insert(15, copy);
    s.samples[17].t_s = s.samples[16].t_s;
    s.samples[17].counts = s.samples[16].counts;
    s.samples[17].counts[0] += 3;
    // Row k moved k * (i + 1) counts on string i: 4 on the fourth string.
    assert_eq!(s.rows_at_one_time_moving(4), vec![(4, 3, 4), (9, 8, 4)]);
    assert_eq!(
        s.rows_at_one_time_moving(3),
        vec![(4, 3, 4), (9, 8, 4), (17, 16, 3)]
    );
}
