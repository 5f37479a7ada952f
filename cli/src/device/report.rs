//! What the device did with what a device command asked: the lines the
//! commands print, and the verdict their exit status follows. A command
//! whose requests were all answered still fails when the device did not do
//! what was asked (it disarmed itself, it lost the heartbeat, it sent no
//! state to tell), with the faults by name and what to do.

use std::fmt::Write as _;

use spidar_protocol::{Faults, State};

/// What a command that holds the device armed (`device arm --hold`,
/// `device force`) saw during the hold.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hold {
    /// The last state frame of the hold (`None`: fewer than two came, see
    /// `hold_heartbeat`).
    pub last: Option<State>,
    /// Heartbeat losses the device counted during the hold
    /// (`LinkStats::heartbeat_losses`, after minus before).
    pub heartbeat_losses: u32,
}

impl Hold {
    /// What went wrong in a hold a signal cut short: [`Hold::shortfall`],
    /// but no state frame is no news then (the hold may have lasted less
    /// than two frames).
    pub fn shortfall_before_interrupt(&self) -> Option<String> {
        if self.last.is_none() && self.heartbeat_losses == 0 {
            return None;
        }
        self.shortfall()
    }

    /// Why the device did not stay armed through the hold, or `None`.
    pub fn shortfall(&self) -> Option<String> {
        if self.heartbeat_losses > 0 {
            let faults = self.last.map_or(Faults::HEARTBEAT_LOST, |s| {
                s.faults.union(Faults::HEARTBEAT_LOST)
            });
            return Some(format!(
                "the device lost the heartbeat during the hold and disarmed itself ({}); \
                 this host did not send a request within the device's heartbeat timeout \
                 (a busy machine can hold it back that long)",
                fault_help(faults)
            ));
        }
        match &self.last {
            None => Some(
                "no state frame came while holding: whether the device stayed armed is \
                 unknown"
                    .to_string(),
            ),
            Some(s) if !s.armed => Some(format!(
                "the device disarmed itself ({})",
                fault_help(s.faults)
            )),
            Some(_) => None,
        }
    }
}

/// The fault bits of a state by name (`none` when clear).
pub fn fault_names(faults: Faults) -> String {
    let mut names: Vec<String> = faults.names().map(str::to_string).collect();
    if faults.unnamed() != 0 {
        names.push(format!("unnamed bits {:#06x}", faults.unnamed()));
    }
    if names.is_empty() {
        "none".into()
    } else {
        names.join(", ")
    }
}

/// What a fault means and what to do about it.
fn fault_meaning(fault: Faults) -> Option<&'static str> {
    const MEANINGS: [(Faults, &str); 9] = [
        (
            Faults::HEARTBEAT_LOST,
            "no request came within the heartbeat timeout",
        ),
        (
            Faults::ENCODER,
            "an encoder count jumped further than a string can move in one loop iteration: \
             check the encoder cables",
        ),
        (
            Faults::KINEMATICS,
            "the string lengths do not agree on one position: a slack, slipped or broken \
             string, or home declared with the end-effector elsewhere (bring it home and \
             declare home again, `spidar init`)",
        ),
        (Faults::TENSION_CLAMPED, "a tension reached the maximum"),
        (
            Faults::LOOP_OVERRUN,
            "a control-loop iteration overran its period",
        ),
        (
            Faults::MODEL_INVALID,
            "the stored model failed its checks: flash it again",
        ),
        (
            Faults::DRIVER,
            "a motor driver reported a fault: check the drivers and their supply",
        ),
        (Faults::ESTOP, "the emergency stop is pressed: release it"),
        (
            Faults::WORKSPACE,
            "the end-effector left the workspace the anchors span: bring it back inside",
        ),
    ];
    MEANINGS
        .iter()
        .find(|(f, _)| *f == fault)
        .map(|(_, meaning)| *meaning)
}

/// Each fault of `faults` by name with what it means (`no fault named`
/// when none is set).
pub fn fault_help(faults: Faults) -> String {
    let mut parts: Vec<String> = Faults::NAMED
        .iter()
        .filter(|(f, _)| faults.contains(*f))
        .map(|(f, name)| match fault_meaning(*f) {
            Some(meaning) => format!("{name}: {meaning}"),
            None => (*name).to_string(),
        })
        .collect();
    if faults.unnamed() != 0 {
        parts.push(format!("unnamed bits {:#06x}", faults.unnamed()));
    }
    if parts.is_empty() {
        "no fault named".into()
    } else {
        parts.join("; ")
    }
}

/// `device info`'s state line: whether the loop renders forces, whether the
/// motors are on (they hold pre-tension after a fault until `disarm`, and
/// the device refuses model changes meanwhile), the faults by name.
pub fn state_line(s: &State) -> String {
    let motors = match (s.armed, s.motors_on) {
        (true, _) => "armed, motors on",
        (false, true) => {
            "disarmed by a fault, motors on (holding pre-tension; `spidar device disarm` \
             turns them off, and flashing waits for that)"
        }
        (false, false) => "disarmed, motors off",
    };
    format!("state: {motors}, faults {}", fault_names(s.faults))
}

/// What `device force` says: the force asked for, the force the device's
/// last state frame says its tensions render, and why an armed device
/// rendered less (a disarmed one is [`Hold::shortfall`]'s to explain).
pub fn force_report(requested: [f32; 3], last: Option<&State>) -> String {
    let norm = |f: [f32; 3]| (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt();
    let show = |f: [f32; 3]| format!("[{:.3}, {:.3}, {:.3}] N", f[0], f[1], f[2]);
    let asked = format!(
        "requested [{}, {}, {}] N",
        requested[0], requested[1], requested[2]
    );
    let Some(s) = last else {
        return format!("{asked}; rendered: unknown (no state frame came while holding)");
    };
    let rendered = s.rendered_force_n;
    let mut line = format!("{asked}; rendered {} (device frame)", show(rendered));
    let (r, q) = (norm(rendered), norm(requested));
    let limited = r + 1e-3 < 0.99 * q;
    if !s.armed {
        return line;
    }
    if limited {
        let _ = write!(
            line,
            ": the device limited it to {:.1} % ({}; faults {})",
            100.0 * r / q.max(f32::MIN_POSITIVE),
            if s.faults.contains(Faults::TENSION_CLAMPED) {
                "a tension reached the maximum"
            } else {
                "its force limit or the tension range"
            },
            fault_names(s.faults)
        );
    } else if !s.faults.is_empty() {
        let _ = write!(line, " (faults {})", fault_names(s.faults));
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(rendered: [f32; 3], faults: Faults, armed: bool) -> State {
        State {
            time_us: 0,
            since_home_us: 0,
            home_id: 0,
            counts: [0; 8],
            position_mm: [0.0; 3],
            corrected_mm: [0; 3],
            tensions_n: [1.0; 8],
            rendered_force_n: rendered,
            faults,
            slack: 0,
            excluded: None,
            loop_us: 0,
            loop_max_us: 0,
            armed,
            motors_on: armed,
            model_id: None,
        }
    }

    #[test]
    fn the_force_report_says_what_was_rendered_and_why() {
        let r = force_report(
            [0.0, 0.0, 2.0],
            Some(&state([0.0, 0.0, 2.0], Faults(0), true)),
        );
        assert_eq!(
            r,
            "requested [0, 0, 2] N; rendered [0.000, 0.000, 2.000] N (device frame)"
        );
        let r = force_report(
            [1e9, 0.0, 0.0],
            Some(&state([10.0, 0.0, 0.0], Faults::TENSION_CLAMPED, true)),
        );
        assert!(
            r.starts_with("requested [1000000000, 0, 0] N; rendered [10.000, 0.000, 0.000] N"),
            "{r}"
        );
        assert!(r.contains("limited it to 0.0 %"), "{r}");
        assert!(
            r.contains("a tension reached the maximum; faults TENSION_CLAMPED"),
            "{r}"
        );
        let r = force_report(
            [3.0, 0.0, 0.0],
            Some(&state([0.0; 3], Faults(1 | 1 << 12), false)),
        );
        assert_eq!(
            r,
            "requested [3, 0, 0] N; rendered [0.000, 0.000, 0.000] N (device frame)"
        );
        assert!(force_report([1.0, 0.0, 0.0], None).contains("unknown"));
        assert_eq!(fault_names(Faults(0)), "none");
        assert_eq!(
            fault_names(Faults::ESTOP.union(Faults::WORKSPACE)),
            "ESTOP, WORKSPACE"
        );
        assert_eq!(
            fault_names(Faults(1 | 1 << 12)),
            "HEARTBEAT_LOST, unnamed bits 0x1000"
        );
    }

    /// A hold fails when the device lost the heartbeat, disarmed itself or
    /// sent nothing to tell; a force it only limited is what it could do.
    #[test]
    fn a_hold_fails_when_the_device_did_not_stay_armed() {
        let armed = state([1.0, 0.0, 0.0], Faults(0), true);
        let clamped = state([10.0, 0.0, 0.0], Faults::TENSION_CLAMPED, true);
        for last in [armed, clamped] {
            let hold = Hold {
                last: Some(last),
                heartbeat_losses: 0,
            };
            assert_eq!(hold.shortfall(), None);
        }
        let lost = Hold {
            last: Some(armed),
            heartbeat_losses: 1,
        }
        .shortfall()
        .unwrap();
        assert!(
            lost.contains("lost the heartbeat")
                && lost.contains("HEARTBEAT_LOST: no request came within the heartbeat timeout"),
            "{lost}"
        );
        let faulted = Hold {
            last: Some(state([0.0; 3], Faults::KINEMATICS, false)),
            heartbeat_losses: 0,
        }
        .shortfall()
        .unwrap();
        assert!(
            faulted.starts_with("the device disarmed itself (KINEMATICS: the string lengths")
                && faulted.contains("`spidar init`"),
            "{faulted}"
        );
        let silent = Hold {
            last: None,
            heartbeat_losses: 0,
        };
        assert!(silent.shortfall().unwrap().contains("no state frame"));
        assert_eq!(
            fault_help(Faults::ESTOP.union(Faults(1 << 13))),
            "ESTOP: the emergency stop is pressed: release it; unnamed bits 0x2000"
        );
    }

    #[test]
    fn the_state_line_says_whether_the_motors_are_on() {
        let mut s = state([0.0; 3], Faults::HEARTBEAT_LOST, false);
        s.motors_on = true;
        let line = state_line(&s);
        assert!(
            line.starts_with("state: disarmed by a fault, motors on (holding pre-tension")
                && line.ends_with("faults HEARTBEAT_LOST"),
            "{line}"
        );
        s.motors_on = false;
        assert_eq!(
            state_line(&s),
            "state: disarmed, motors off, faults HEARTBEAT_LOST"
        );
        assert_eq!(
            state_line(&state([0.0; 3], Faults(0), true)),
            "state: armed, motors on, faults none"
        );
    }
}
