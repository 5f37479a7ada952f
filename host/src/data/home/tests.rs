use super::*;

fn session(rows: &[(f64, Option<f64>, Option<u64>)]) -> Session {
    Session {
        samples: rows
            .iter()
            .map(|&(t_s, since_home_s, home)| Sample::at_home(t_s, since_home_s, home))
            .collect(),
        ..Session::default()
    }
}

#[test]
fn a_clock_that_continues_shares_the_home_and_one_that_starts_again_does_not() {
    let training = session(&[(0.0, None, None), (100.0, None, None)]);
    let continuing = LaterHome::of(
        &training,
        &session(&[(100.0, None, None), (150.0, None, None)]),
    );
    assert!(continuing.shares_home());
    assert_eq!(continuing.basis, HomeBasis::Clock);
    assert!(
        continuing.reason.contains("continues"),
        "{}",
        continuing.reason
    );
    let again = LaterHome::of(
        &training,
        &session(&[(0.5, None, None), (50.0, None, None)]),
    );
    assert_eq!(again.first_new_home_row, 0);
    assert!(
        again.reason.contains("starts its clock again"),
        "{}",
        again.reason
    );
}

#[test]
fn home_ids_are_trusted_over_clocks_and_a_new_id_ends_the_shared_rows() {
    let training = session(&[(0.0, Some(0.0), Some(7)), (100.0, Some(100.0), Some(7))]);
    // The clock starts again, but the id says the same home: then a new one.
    let later = session(&[
        (1.0, Some(101.0), Some(7)),
        (2.0, Some(102.0), Some(7)),
        (3.0, Some(0.5), Some(8)),
    ]);
    let home = LaterHome::of(&training, &later);
    assert_eq!(home.basis, HomeBasis::HomeId);
    assert_eq!(home.first_new_home_row, 2);
    assert!(home.reason.contains("line 4"), "{}", home.reason);
}

#[test]
fn time_since_home_tells_without_ids() {
    let training = session(&[(0.0, Some(10.0), None), (100.0, Some(110.0), None)]);
    let shared = session(&[(0.0, Some(120.0), None), (1.0, Some(121.0), None)]);
    assert!(LaterHome::of(&training, &shared).shares_home());
    let stepped = session(&[(0.0, Some(120.0), None), (1.0, Some(0.2), None)]);
    let home = LaterHome::of(&training, &stepped);
    assert_eq!(
        (home.basis, home.first_new_home_row),
        (HomeBasis::SinceHome, 1)
    );
    let new = session(&[(200.0, Some(3.0), None)]);
    assert_eq!(LaterHome::of(&training, &new).first_new_home_row, 0);
}

#[test]
fn a_training_session_tells_its_home_capture_only_with_both_columns_on_its_last_capture() {
    let whole = TrainingHome::of(&session(&[
        (0.0, Some(5.0), Some(7)),
        (1.0, Some(6.0), Some(7)),
    ]));
    assert_eq!(whole.home_id, Some(7), "{}", whole.reason);
    for rows in [
        // No `home`, or not on every row.
        &[(0.0, Some(5.0), None), (1.0, Some(6.0), None)][..],
        &[(0.0, Some(5.0), Some(7)), (1.0, Some(6.0), None)],
        // No time since home.
        &[(0.0, None, Some(7)), (1.0, None, Some(7))],
        // Not on the last capture's rows.
        &[(0.0, Some(5.0), Some(7)), (1.0, None, Some(8))],
        // A capture's rows apart.
        &[
            (0.0, Some(5.0), Some(7)),
            (1.0, Some(0.1), Some(8)),
            (2.0, Some(0.2), Some(7)),
        ],
        &[],
    ] {
        let h = TrainingHome::of(&session(rows));
        assert_eq!(h.home_id, None, "{rows:?}: {}", h.reason);
        assert!(!h.reason.is_empty());
    }
}

/// A training session homed again midway ends under its last capture; a
/// slip term is that capture's when no row of the earlier ones is as long
/// after its own capture (the fit applied it to the last capture's rows
/// alone), else it was fitted across them.
#[test]
fn a_training_session_over_two_captures_ends_under_the_last() {
    let h = TrainingHome::of(&session(&[
        (0.0, None, None),
        (40.0, None, None),
        (50.0, Some(2.0), Some(8)),
        (90.0, Some(42.0), Some(8)),
        (130.0, Some(82.0), Some(8)),
    ]));
    assert_eq!(
        (h.home_id, h.captures, h.first_row, h.earlier_until_s),
        (Some(8), 2, 2, Some(40.0)),
        "{}",
        h.reason
    );
    assert!(h.reason.contains("spans 2 home captures"), "{}", h.reason);
    assert!(h.slip_is_of_last_capture(60.0));
    assert!(h.slip_is_of_last_capture(40.001));
    assert_eq!(h.rows_of_slip(40.0), SlipRows::Both);
    assert_eq!(h.rows_of_slip(10.0), SlipRows::Both);
    let short_last = TrainingHome::of(&session(&[
        (0.0, Some(0.0), Some(7)),
        (40.0, Some(40.0), Some(7)),
        (50.0, Some(2.0), Some(8)),
    ]));
    assert_eq!(short_last.rows_of_slip(30.0), SlipRows::Earlier);
    assert_eq!(short_last.rows_of_slip(2.0), SlipRows::Both);
    let one = TrainingHome::of(&session(&[(0.0, Some(5.0), Some(7))]));
    assert_eq!((one.captures, one.earlier_until_s), (1, None));
    assert!(one.slip_is_of_last_capture(0.0));
}
