//! Tests of the monitor's settings.

use super::*;

/// An offset of the tracked body that is not finite is refused by name.
#[test]
fn a_marker_offset_that_is_not_finite_is_refused() {
    let config = MonitorConfig {
        marker_body_mm: Some([f64::NAN, 0.0, 0.0]),
        ..MonitorConfig::default()
    };
    let e = config.validate().unwrap_err().to_string();
    assert!(e.contains("marker_body_mm"), "{e}");
}
