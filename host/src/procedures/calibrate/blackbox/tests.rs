//! Tests of the black-box comparison's data.

use super::*;
use crate::data::dataset::Sample;
use spidar_core::STRINGS;

/// The black box reads the tracker where the model's stages do: at the
/// strings' meeting point `p - R_body d` once the loop found the body's
/// origin `d` off it, on the rows with an orientation.
#[test]
fn the_black_box_reads_the_tracker_at_the_meeting_point_the_loop_found() {
    let geometry = crate::sim::SimConfig::default().nominal.geometry();
    let t = geometry.room_from_device_translation_mm;
    // A quarter turn about z: the body's x axis along the room's y.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let row = |orientation| Sample {
        t_s: 0.0,
        counts: [0; STRINGS],
        tracker: Some([100.0, 200.0, 300.0]),
        orientation,
        legacy: Some([1.0, 2.0, 3.0]),
        tension_n: None,
        since_home_s: None,
        home: None,
    };
    let session = Session {
        strings: STRINGS,
        samples: vec![row(Some([h, 0.0, 0.0, h])), row(None)],
        ignored_columns: Vec::new(),
        unread_columns: Vec::new(),
        tracker_z: true,
    };
    let (rows, x, y) = legacy_pairs(&geometry, &session, &[], Some([10.0, 0.0, 0.0]));
    assert_eq!(rows, [0, 1]);
    assert_eq!(x[0], [1.0 + t[0], 2.0 + t[1], 3.0 + t[2]]);
    for (got, want) in y[0].iter().zip([100.0, 190.0, 300.0]) {
        assert!((got - want).abs() < 1e-9, "{:?}", y[0]);
    }
    assert_eq!(y[1], [100.0, 200.0, 300.0], "a row without orientation");
    let (_, _, plain) = legacy_pairs(&geometry, &session, &[], None);
    assert_eq!(plain[0], [100.0, 200.0, 300.0]);
}
