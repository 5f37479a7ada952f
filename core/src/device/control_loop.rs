//! Each control-loop iteration of the device ([`Device::tick`]): the
//! controller's step on the active calibration (or the idle output without
//! geometry), the events and the stream decimation after it, the loop's
//! timing ([`Device::record_loop_time`]) and the state frame it streams
//! ([`Device::state_frame`]), with the loop's faults as the protocol names
//! them ([`protocol_faults`]).

use spidar_protocol::blob::CorrectionKind;
use spidar_protocol::{Event, Faults, State};

use super::{ms, Device, TickInput};
use crate::control::{LoopInput, LoopOutput};
use crate::correction::Correction;
use crate::kinematics::FkStatus;
use crate::model_store::ModelFlash;
use crate::safety::SafetyFaults;
use crate::tension::TensionStatus;
use crate::STRINGS;

/// The protocol's fault bits for the loop's faults.
///
/// The faults the wire names share its bits and pass as they are
/// ([`SafetyFaults::ON_THE_WIRE`]); `SLACK`, `FK_FAULT` and `NON_FINITE`
/// all report as `KINEMATICS` (the protocol has no bit of their own;
/// `State::slack` says which strings are slack); `OVERFORCE` is not
/// reported. `TENSION_CLAMPED` is present (not latched) while armed and the
/// tension distribution had to scale the force down.
pub fn protocol_faults(out: &LoopOutput, loop_overrun: bool) -> Faults {
    let f = out.faults;
    let mut bits = f.bits() & SafetyFaults::ON_THE_WIRE.bits();
    let mut set = |cond: bool, bit: Faults| {
        if cond {
            bits |= bit.0;
        }
    };
    set(
        f.intersects(SafetyFaults::SLACK | SafetyFaults::FK_FAULT | SafetyFaults::NON_FINITE),
        Faults::KINEMATICS,
    );
    set(
        out.armed && out.tension_status == TensionStatus::Scaled,
        Faults::TENSION_CLAMPED,
    );
    set(loop_overrun, Faults::LOOP_OVERRUN);
    Faults(bits)
}

/// What the loop outputs while there is no geometry: nothing moves.
pub(super) fn idle_output(estop: bool, model_invalid: bool) -> LoopOutput {
    let mut faults = SafetyFaults::NONE;
    if estop {
        faults.insert(SafetyFaults::ESTOP);
    }
    if model_invalid {
        faults.insert(SafetyFaults::MODEL_INVALID);
    }
    LoopOutput {
        counts: [0; STRINGS],
        direction: [0; STRINGS],
        string_lengths_mm: [0.0; STRINGS],
        position_mm: [0.0; 3],
        fk_status: FkStatus::InvalidInput,
        excluded: None,
        room_q16: [0; 3],
        corrected_q16: [0; 3],
        force_n: [0.0; 3],
        tension_status: TensionStatus::Exact,
        rendered_fraction: 0.0,
        tensions_n: [0.0; STRINGS],
        faults,
        warnings: SafetyFaults::NONE,
        slack_mask: 0,
        armed: false,
    }
}

impl<'m, F: ModelFlash> Device<'m, F> {
    /// One control-loop iteration: [`Controller::step`] on the active
    /// calibration (or idle without geometry), events, stream decimation.
    ///
    /// [`Controller::step`]: crate::control::Controller::step
    pub fn tick(&mut self, input: &TickInput) -> LoopOutput {
        self.last_raw = input.raw_counts;
        self.last_now_us = input.now_us;
        self.estop = input.estop;
        if input.estop {
            self.energized = false;
        }
        let loop_input = LoopInput {
            raw_counts: input.raw_counts,
            now_ms: ms(input.now_us),
            now_us: input.now_us as u32,
            estop: input.estop,
        };
        let Device {
            controller,
            active,
            nominal,
            model_ram,
            model_invalid,
            target,
            ..
        } = self;
        let out = match controller.as_mut() {
            None => idle_output(input.estop, *model_invalid),
            Some(c) => {
                c.set_target(*target);
                // Only a flashed model's string law is calibrated.
                c.set_lengths_calibrated(active.is_some());
                match (active.as_ref(), nominal.as_ref()) {
                    (Some(a), _) => {
                        let kind = a.calibration.header.kind;
                        if kind == CorrectionKind::None {
                            c.step(&a.calibration, &loop_input)
                        } else {
                            let bytes = model_ram.get(a.correction_at..a.len).unwrap_or(&[]);
                            match Correction::from_summary(&a.correction, bytes) {
                                Ok(correction) => {
                                    c.step_with(&a.calibration.head, &correction, &loop_input)
                                }
                                Err(_) => {
                                    // The RAM copy no longer checks: fault,
                                    // pre-tension, no correction.
                                    *model_invalid = true;
                                    c.safety().set_model_valid(false);
                                    c.step(&a.calibration, &loop_input)
                                }
                            }
                        }
                    }
                    (None, Some(n)) => c.step(n, &loop_input),
                    (None, None) => idle_output(input.estop, *model_invalid),
                }
            }
        };
        self.after_tick(&out);
        self.last_out = out;
        out
    }

    fn after_tick(&mut self, out: &LoopOutput) {
        let faults = protocol_faults(out, self.loop_overrun);
        // Latched faults only: TENSION_CLAMPED comes and goes with the force.
        let raised = Faults(faults.0 & !self.prev_faults.0 & !Faults::TENSION_CLAMPED.0);
        if raised.0 != 0 {
            self.push_event(Event::Fault { raised });
        }
        if self.prev_armed && !out.armed && !out.faults.is_empty() {
            if raised.contains(Faults::HEARTBEAT_LOST) {
                self.stats.heartbeat_losses = self.stats.heartbeat_losses.wrapping_add(1);
                self.push_event(Event::HeartbeatLost);
            }
            self.push_event(Event::Disarmed { faults });
        }
        self.prev_faults = faults;
        self.prev_armed = out.armed;
        if let Some(s) = self.stream.as_mut() {
            s.count = s.count.saturating_add(1);
            if s.count >= s.decimation {
                s.count = 0;
                self.frame_due = true;
            }
        }
    }

    /// Records the duration of the last loop iteration (µs, measured by the
    /// caller around `tick` and the I/O); one longer than the loop period
    /// counts an overrun and latches `LOOP_OVERRUN` (cleared by
    /// `ClearFaults`/`Arm`; it does not disarm).
    pub fn record_loop_time(&mut self, loop_us: u16) {
        self.loop_us = loop_us;
        self.loop_max_us = self.loop_max_us.max(loop_us);
        if u32::from(loop_us) > self.config.loop_period_us {
            self.stats.loop_overruns = self.stats.loop_overruns.wrapping_add(1);
            self.loop_overrun = true;
        }
    }

    /// The state frame due after the last tick, if streaming and the
    /// decimation says so (at most one per `decimation` ticks).
    pub fn state_frame(&mut self) -> Option<State> {
        if !core::mem::take(&mut self.frame_due) {
            return None;
        }
        let out = &self.last_out;
        let state = State {
            time_us: self.last_now_us,
            since_home_us: self.last_now_us.saturating_sub(self.home_us),
            home_id: self.home_id(),
            counts: out.counts,
            position_mm: out.position_mm,
            corrected_mm: out.corrected_q16,
            tensions_n: out.tensions_n,
            rendered_force_n: if out.armed {
                out.force_n.map(|f| f * out.rendered_fraction)
            } else {
                [0.0; 3]
            },
            faults: protocol_faults(out, self.loop_overrun),
            slack: out.slack_mask,
            excluded: out.excluded.filter(|&i| usize::from(i) < STRINGS),
            loop_us: self.loop_us,
            loop_max_us: self.loop_max_us,
            armed: out.armed,
            motors_on: self.motors_enabled(),
            model_id: self.active.as_ref().map(|a| a.calibration.header.model_id),
        };
        self.loop_max_us = 0;
        Some(state)
    }
}
