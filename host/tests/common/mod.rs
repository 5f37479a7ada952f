//! Helpers shared by the integration tests that talk to a device thread.

use std::time::{Duration, Instant};

/// Whether `condition` comes to hold within 5 s (polled every 5 ms): what a
/// device thread does after a call returns is not timed by the test, which
/// must pass on a busy machine (a fixed 50 ms sleep did not, with every
/// core loaded).
pub fn eventually(condition: impl Fn() -> bool) -> bool {
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        if condition() {
            return true;
        }
        if Instant::now() > deadline {
            return false;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}
