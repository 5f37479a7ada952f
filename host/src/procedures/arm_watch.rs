//! Keeps the device armed through a procedure.

use std::time::Duration;

/// A device that disarmed itself while armed by a procedure: an event says
/// so, or its states have said so for [`UNARMED_GRACE`] (after a reboot it
/// may hold a latched fault and send no event).
const UNARMED_GRACE: Duration = Duration::from_millis(250);

/// Keeps the device armed through a procedure: re-arms it when it disarmed
/// itself (a late heartbeat, a slack string), at most `max` times without
/// progress in between, then gives up naming the last cause.
pub(crate) struct ArmWatch {
    max: u32,
    since_progress: u32,
    unarmed_since: Option<std::time::Instant>,
    /// Re-arms over the whole procedure.
    pub rearms: u32,
}

/// Why [`ArmWatch::check`] gave up.
pub(crate) enum ArmWatchError {
    Link(crate::device::link::LinkError),
    KeepsDisarming { events: u32, last: String },
}

impl ArmWatch {
    pub(crate) fn new(max: u32) -> ArmWatch {
        ArmWatch {
            max,
            since_progress: 0,
            unarmed_since: None,
            rearms: 0,
        }
    }

    /// The procedure got somewhere (a capture): the count starts again.
    pub(crate) fn progress(&mut self) {
        self.since_progress = 0;
    }

    /// Looks at the link's events and the latest state (armed, faults) and
    /// re-arms if needed; true when it did.
    pub(crate) fn check(
        &mut self,
        client: &mut crate::device::link::Client,
        latest: Option<(bool, spidar_protocol::Faults)>,
    ) -> Result<bool, ArmWatchError> {
        use spidar_protocol::Event;
        let event = client
            .take_events()
            .into_iter()
            .rfind(|e| matches!(e, Event::Disarmed { .. } | Event::HeartbeatLost))
            .map(|e| format!("{e:?}"));
        let unarmed = match latest {
            Some((false, faults)) => {
                let since = *self
                    .unarmed_since
                    .get_or_insert_with(std::time::Instant::now);
                (since.elapsed() > UNARMED_GRACE)
                    .then(|| format!("states say disarmed, faults {:#06x}", faults.0))
            }
            _ => {
                self.unarmed_since = None;
                None
            }
        };
        let Some(last) = event.or(unarmed) else {
            return Ok(false);
        };
        self.rearms += 1;
        self.since_progress += 1;
        if self.since_progress > self.max {
            return Err(ArmWatchError::KeepsDisarming {
                events: self.since_progress,
                last,
            });
        }
        client.clear_faults().map_err(ArmWatchError::Link)?;
        client.arm().map_err(ArmWatchError::Link)?;
        self.unarmed_since = None;
        Ok(true)
    }
}
