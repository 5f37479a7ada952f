//! Tests of the pairing: where the tracker is read, and the glitch gate.

use super::*;
use crate::device::tracker::BodyPose;

/// Without a marker offset the tracker is read at the body's origin;
/// with one, at the meeting point the body's rotation puts it; a frame
/// without the rotation then has no meeting point.
#[test]
fn the_tracker_is_read_at_the_meeting_point_the_calibration_found() {
    let quarter_turn_about_z = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    let body = BodyPose {
        rotation: Some(quarter_turn_about_z),
        ..BodyPose::at(0, [100.0, 200.0, 300.0])
    };
    assert_eq!(tracked_point(&body, None), Some([100.0, 200.0, 300.0]));
    assert_eq!(
        tracked_point(&body, Some([10.0, 0.0, 5.0])),
        Some([100.0, 190.0, 295.0])
    );
    let blind = BodyPose {
        rotation: None,
        ..body
    };
    assert_eq!(tracked_point(&blind, Some([10.0, 0.0, 5.0])), None);
    assert_eq!(tracked_point(&blind, None), Some([100.0, 200.0, 300.0]));
}

/// Before the baseline every pair is admitted; after it, a lone pair
/// beyond the threshold is set aside, and far pairs in more than a
/// quarter of the window are admitted (the position did change).
#[test]
fn the_glitch_gate_sets_lone_far_pairs_aside_and_admits_persistent_ones() {
    let mut gate = GlitchGate::new(40);
    assert!(gate.admit(500.0), "no threshold before the baseline");
    assert_eq!(gate.set_baseline(0.2), 10.0, "the floor");
    assert_eq!(GlitchGate::new(40).set_baseline(1.0), 20.0);
    for k in 0..100 {
        // One far pair in 20: set aside, the others admitted.
        let far = k % 20 == 0;
        let e = if far { 200.0 } else { 0.3 };
        assert_eq!(gate.admit(e), !far, "pair {k}");
    }
    assert!(!gate.admit(f64::NAN), "a pair the device cannot place");
    // From here on every pair is 30 mm off: set aside until far pairs
    // are more than a quarter of the last 40, admitted after.
    let admitted: Vec<bool> = (0..20).map(|_| gate.admit(30.0)).collect();
    let first = admitted.iter().position(|&a| a).expect("admitted at last");
    assert!(admitted[first..].iter().all(|&a| a), "{admitted:?}");
    assert!((7..=10).contains(&first), "{admitted:?}");
}
