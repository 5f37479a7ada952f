use super::*;
use crate::test_fixtures::cube_frame;

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

fn laws() -> [StringLaw; STRINGS] {
    // A spool whose radius shrinks as it pays out, as real ones do.
    [StringLaw::polynomial(4096, [12.0, -0.004, 0.0, 0.0]); STRINGS]
}

#[test]
fn a_device_passes() {
    let mut frame = cube_frame([30.0, -20.0, 10.0]);
    let c = libm::cos(0.3);
    let s = libm::sin(0.3);
    frame.room_rotation = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
    assert_eq!(check_device(&frame, &laws()), Ok(()));
}

#[test]
fn a_rotation_that_is_not_one_is_refused() {
    let mut frame = cube_frame([0.0; 3]);
    frame.room_rotation = IDENTITY;
    frame.room_rotation[0][1] = 0.01;
    let e = check_device(&frame, &laws()).unwrap_err();
    assert!(matches!(e, Implausible::RoomRotation { .. }), "{e}");
    assert!(e.to_string().contains("frame.room_rotation"), "{e}");
    frame.room_rotation[0][1] = f64::NAN;
    assert!(matches!(
        check_device(&frame, &laws()),
        Err(Implausible::RoomRotation { .. })
    ));
}

#[test]
fn coincident_anchors_are_refused_by_index() {
    let mut frame = cube_frame([0.0; 3]);
    frame.anchors[6] = frame.anchors[2];
    let e = check_device(&frame, &laws()).unwrap_err();
    assert_eq!(
        e,
        Implausible::CoincidentAnchors {
            a: 2,
            b: 6,
            apart_mm: 0.0
        }
    );
    assert!(e
        .to_string()
        .contains("frame.anchors[2] and frame.anchors[6]"));
}

#[test]
fn an_anchor_orders_of_magnitude_away_is_refused() {
    let mut frame = cube_frame([0.0; 3]);
    frame.anchors[3] = [1e12, 0.0, 0.0];
    let e = check_device(&frame, &laws()).unwrap_err();
    assert!(
        matches!(e, Implausible::AnchorFarBeyond { string: 3, .. }),
        "{e}"
    );
    assert!(e.to_string().contains("frame.anchors[3]"), "{e}");
}

#[test]
fn a_home_orders_of_magnitude_beyond_the_frame_is_refused() {
    // Below and beside the anchors (a suspended robot's home): a device.
    let mut frame = cube_frame([0.0; 3]);
    let extent = frame
        .anchors
        .iter()
        .map(|a| distance(a, &[0.0; 3]))
        .fold(0.0, f64::max);
    frame.home = [0.0, 0.0, -3.0 * extent];
    assert_eq!(check_device(&frame, &laws()), Ok(()));
    frame.home = [0.0, 200.0 * extent, 0.0];
    let e = check_device(&frame, &laws()).unwrap_err();
    assert!(matches!(e, Implausible::HomeFarBeyond { .. }), "{e}");
    assert!(e.to_string().contains("frame.home"), "{e}");
    frame.home = [f64::NAN, 0.0, 0.0];
    assert!(matches!(
        check_device(&frame, &laws()),
        Err(Implausible::HomeFarBeyond { .. })
    ));
}

#[test]
fn a_payout_that_falls_is_refused() {
    let frame = cube_frame([0.0; 3]);
    // A negative winding rate: the payout falls as the counts rise.
    // It falls from home on: the string's counts fall as it pays out, and
    // the message says so (not "stops rising at 0.0 mm, inside 0.0 mm").
    let mut strings = laws();
    strings[5].winding_mm = [-12.0, 0.0, 0.0, 0.0];
    let e = check_device(&frame, &strings).unwrap_err();
    assert_eq!(
        e,
        Implausible::CountsFallAtHome {
            string: 5,
            radius_mm: -12.0
        }
    );
    let message = e.to_string();
    assert!(message.contains("strings[5].winding_mm"), "{message}");
    assert!(message.contains("-12.000 mm"), "{message}");
    assert!(message.contains("counts fall as it pays out"), "{message}");
    assert!(message.contains("reversed encoder"), "{message}");
    assert!(message.contains("channels swapped"), "{message}");
    assert!(!message.contains("0.0 mm this frame needs"), "{message}");
    // A spool that stands still at home is no device either.
    strings[5].winding_mm = [0.0, 0.0, 0.0, 0.0];
    assert!(matches!(
        check_device(&frame, &strings),
        Err(Implausible::CountsFallAtHome { string: 5, .. })
    ));
    // A spool that empties before the string crosses the frame: the
    // payout peaks at 12^2 / (4 x 0.1) = 360 mm.
    let mut strings = laws();
    strings[1].winding_mm = [12.0, -0.1, 0.0, 0.0];
    let Err(Implausible::PayoutFalls {
        string,
        paid_out_mm,
        needed_mm,
    }) = check_device(&frame, &strings)
    else {
        panic!("a spool that empties at 360 mm passed");
    };
    assert_eq!(string, 1);
    assert!((paid_out_mm - 360.0).abs() < 5.0, "{paid_out_mm}");
    assert!(needed_mm > 360.0, "{needed_mm}");
    // Winding up toward the anchor: a slope that vanishes before the
    // string is wound to its anchor.
    let mut strings = laws();
    strings[4].winding_mm = [12.0, 0.1, 0.0, 0.0];
    assert!(matches!(
        check_device(&frame, &strings),
        Err(Implausible::PayoutFalls { string: 4, needed_mm, .. }) if needed_mm < 0.0
    ));
}

#[test]
fn inactive_channels_are_not_checked() {
    let mut frame = cube_frame([0.0; 3]);
    frame.layout = crate::model::StringLayout::first(4, false);
    frame.anchors[7] = frame.anchors[0];
    let mut strings = laws();
    strings[6].winding_mm = [-1.0, 0.0, 0.0, 0.0];
    assert_eq!(check_device(&frame, &strings), Ok(()));
}

/// A room scale of another unit, or not positive, is refused by name; the
/// scales of a tracker in millimetres pass.
#[test]
fn a_room_scale_of_another_unit_is_refused() {
    let mut frame = cube_frame([0.0; 3]);
    frame.room_rotation = IDENTITY;
    for scale in [1.0, 1.003, 0.2, 5.0] {
        frame.room_scale = scale;
        assert_eq!(check_device(&frame, &laws()), Ok(()), "{scale}");
    }
    for scale in [1000.0, 25.4, 1e-30, 0.0, -1.0, f64::NAN] {
        frame.room_scale = scale;
        let e = check_device(&frame, &laws()).unwrap_err();
        assert!(matches!(e, Implausible::RoomScale { .. }), "{scale}: {e}");
        assert!(e.to_string().contains("frame.room_scale"), "{e}");
    }
}
