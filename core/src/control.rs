//! One control-loop iteration: encoder counts in, position and string
//! tensions out. The firmware calls [`Controller::step`] at a fixed rate, the
//! virtual device calls it on the host, and the QEMU benchmark counts its
//! instructions; all three run exactly this code.
//!
//! ```text
//! raw counts -> extended counts, direction -> string law (fixed point, blob)
//!   -> forward kinematics (f32, warm-started, faulty string excluded)
//!   -> room transform -> position correction (fixed point, blob)
//!   -> safety checks (heartbeat, slack, e-stop, FK fault)
//!   -> target force (direct, or the guidance cue toward a room target)
//!   -> tension distribution -> safety clamps -> tensions
//! ```
//!
//! The string law reads the tensions commanded by the previous iteration
//! (the elasticity term), so one iteration never depends on its own output.

use crate::blob::{position_mm, position_q16, BlobHead, CompiledCalibration};
use crate::correction::Correction;
use crate::encoder::{CountRate, DirectionTracker, EncoderExtender};
use crate::geometry::{device_direction, room_from_device};
use crate::guidance::guidance_force;
use crate::kinematics::{forward_kinematics, inverse_kinematics, FkConfig, FkStatus};
use crate::model::{Frame, StringInputs};
use crate::safety::{SafetyConfig, SafetyConfigError, SafetyFaults, SafetyMonitor};
use crate::string_law::{cos2_inclinations, guide_elevations, CompiledEffect};
use crate::tension::{
    distribute_warm, renderable_force, TensionConfig, TensionLimits, TensionSolution, TensionStatus,
};
use crate::STRINGS;

/// The largest residual (N) of a `NotConverged` tension solution the loop
/// still renders (see [`Controller::step`]): 5 mN, far below what a hand
/// feels of forces of newtons. At 1 mN a scaled force at a frame corner
/// (p = [401.9, -468.3, -475.0] mm, 5.2 N) ended 1.02 mN short and the loop
/// commanded a tick of pretension instead (found by the tension proptest).
pub const USABLE_RESIDUAL_N: f32 = 5e-3;

/// Fixed parameters of the loop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ControlConfig {
    pub fk: FkConfig<f32>,
    pub tension_limits: TensionLimits<f32>,
    pub tension: TensionConfig<f32>,
    pub safety: SafetyConfig,
    /// Hysteresis of the direction of motion, counts.
    pub direction_hysteresis_counts: u32,
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            fk: FkConfig::default(),
            tension_limits: TensionLimits {
                t_min: 0.5,
                t_max: 20.0,
            },
            // Closest to a low tension, not to mid-range: internal tension
            // turns every error of the geometry the loop believes into a
            // force the user feels (8 strings x 10 N with directions off by
            // 0.03 rad before homing: 1-2 N, as large as the guidance cue;
            // measured with host/tests/operator_init.rs). 2 N keeps every
            // string clear of t_min while rendering.
            tension: TensionConfig {
                reference: crate::tension::TensionReference::Preferred(2.0),
                ..TensionConfig::default()
            },
            safety: SafetyConfig {
                t_min: 0.5,
                t_max: 20.0,
                f_max: 15.0,
                pretension_n: 1.0,
                heartbeat_timeout_ms: 20,
                slack_threshold_mm: 15.0,
            },
            direction_hysteresis_counts: 8,
        }
    }
}

/// What the end-effector should feel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Target {
    /// No force: pre-tension only (strings taut).
    Idle,
    /// A force in the device frame, N.
    Force([f32; 3]),
    /// The paper's guidance cue (eqs. 2-5) toward a point in the room frame.
    Guidance {
        target_mm: [f32; 3],
        d_min_mm: f32,
        f_max_n: f32,
    },
}

/// Inputs of one iteration, read from the peripherals.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LoopInput {
    /// Raw 16-bit encoder counters.
    pub raw_counts: [u16; STRINGS],
    /// Monotonic device time, ms (wraps).
    pub now_ms: u32,
    /// The same clock in µs (wraps every 71 minutes): the count rate's
    /// ([`CountRate`]).
    pub now_us: u32,
    /// Hardware emergency stop input active.
    pub estop: bool,
}

/// Everything one iteration computed: what the motors get and what the
/// state stream reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopOutput {
    pub counts: [i32; STRINGS],
    pub direction: [i8; STRINGS],
    /// String lengths from the calibrated string law, mm.
    pub string_lengths_mm: [f32; STRINGS],
    /// Forward kinematics, device frame, mm.
    pub position_mm: [f32; 3],
    pub fk_status: FkStatus,
    pub excluded: Option<u8>,
    /// Room-frame position before the learned correction, Q15.16 mm.
    pub room_q16: [i32; 3],
    /// Room-frame position after the learned correction, Q15.16 mm.
    pub corrected_q16: [i32; 3],
    /// Force requested of the tension distribution (device frame, N); on a
    /// planar device its `x, y` only, as the distribution renders it (its
    /// strings cannot pull along `z`: a requested `[0, 0, 5]` was reported
    /// rendered whole).
    pub force_n: [f32; 3],
    pub tension_status: TensionStatus,
    /// Fraction of the requested force the tensions render.
    pub rendered_fraction: f32,
    /// Tensions sent to the motors, N.
    pub tensions_n: [f32; STRINGS],
    pub faults: SafetyFaults,
    pub warnings: SafetyFaults,
    pub slack_mask: u8,
    pub armed: bool,
}

/// The state the loop carries from one iteration to the next.
#[derive(Clone, Debug)]
pub struct Controller {
    config: ControlConfig,
    encoders: [EncoderExtender; STRINGS],
    directions: [DirectionTracker; STRINGS],
    /// Each string's count rate, for a model with a latency term.
    rates: CountRate,
    /// Home was declared: the count rate restarts at the next step.
    rates_from_home: bool,
    home_ms: u32,
    position: [f32; 3],
    multiplier: [f32; 3],
    tensions_mn: [u16; STRINGS],
    safety: SafetyMonitor,
    target: Target,
    /// See [`Controller::set_lengths_calibrated`].
    lengths_calibrated: bool,
    /// See [`Controller::set_home_id`].
    home_id: Option<u64>,
}

impl Controller {
    /// A disarmed controller whose home is the current encoder reading, the
    /// end-effector at `calibration`'s home.
    pub fn new(
        config: ControlConfig,
        calibration: &CompiledCalibration<'_>,
        raw_counts: [u16; STRINGS],
        now_ms: u32,
    ) -> Result<Controller, SafetyConfigError> {
        let safety = SafetyMonitor::new(config.safety)?;
        let mut c = Controller {
            config,
            encoders: raw_counts.map(EncoderExtender::new),
            directions: [DirectionTracker::new(config.direction_hysteresis_counts); STRINGS],
            rates: CountRate::new([0; STRINGS], 0),
            rates_from_home: true,
            home_ms: now_ms,
            position: calibration.head.frame.home,
            multiplier: [0.0; 3],
            tensions_mn: [0; STRINGS],
            safety,
            target: Target::Idle,
            lengths_calibrated: true,
            home_id: None,
        };
        c.home(calibration, raw_counts, now_ms);
        Ok(c)
    }

    /// Declares home: the end-effector is at the calibration's home point now.
    pub fn home(
        &mut self,
        calibration: &CompiledCalibration<'_>,
        raw_counts: [u16; STRINGS],
        now_ms: u32,
    ) {
        for (e, raw) in self.encoders.iter_mut().zip(raw_counts) {
            e.rezero(raw);
        }
        for d in self.directions.iter_mut() {
            d.reset(0);
        }
        self.rates_from_home = true;
        self.home_ms = now_ms;
        self.position = calibration.head.frame.home;
        self.multiplier = [0.0; 3];
    }

    /// Whether the string law stepped with is calibrated (default) or
    /// nominal: with nominal lengths forward kinematics looks for no faulty
    /// string and the length-consistency faults are off
    /// ([`SafetyMonitor::set_lengths_calibrated`] says why).
    pub fn set_lengths_calibrated(&mut self, calibrated: bool) {
        self.lengths_calibrated = calibrated;
    }

    /// The id of the home capture the counts are from (the device's
    /// `State::home_id`, set at each home capture): the blob's training
    /// slips apply while it is theirs ([`BlobHead::home_slips`]), never
    /// while it is `None` (the default).
    pub fn set_home_id(&mut self, home_id: Option<u64>) {
        self.home_id = home_id;
    }

    pub fn set_target(&mut self, target: Target) {
        self.target = target;
    }

    pub fn target(&self) -> Target {
        self.target
    }

    /// The safety state (heartbeat, arm, disarm, clear).
    pub fn safety(&mut self) -> &mut SafetyMonitor {
        &mut self.safety
    }

    pub fn config(&self) -> &ControlConfig {
        &self.config
    }

    /// The end-effector position the loop holds (device frame, mm): the last
    /// forward kinematics solution, or home.
    pub fn position(&self) -> [f32; 3] {
        self.position
    }

    /// New tension bounds for the distribution (the host's `SetLimits`), so
    /// the distribution and the safety clamp agree and the rendered force
    /// stays exact. The safety monitor's own limits are set with it by the
    /// caller.
    pub fn set_tension_limits(&mut self, limits: TensionLimits<f32>, pretension_n: f32) {
        self.config.tension_limits = limits;
        self.config.safety.t_min = limits.t_min;
        self.config.safety.t_max = limits.t_max;
        self.config.safety.pretension_n = pretension_n;
        self.multiplier = [0.0; 3];
    }

    /// One iteration.
    pub fn step(&mut self, calibration: &CompiledCalibration<'_>, input: &LoopInput) -> LoopOutput {
        self.step_with(&calibration.head, &calibration.correction, input)
    }

    /// One iteration, with the string model and the correction held apart
    /// (the device keeps the string model parsed and rebuilds the correction
    /// view over its RAM copy of the blob: nothing is copied per tick).
    pub fn step_with(
        &mut self,
        head: &BlobHead,
        correction: &Correction<'_>,
        input: &LoopInput,
    ) -> LoopOutput {
        let frame = &head.frame;
        // Tensions, inclinations (sag) and elevations (guide) are the last
        // tick's: at the loop's rate the position moves by less than 0.1 mm
        // between ticks.
        let mut inputs = StringInputs {
            tension_mn: self.tensions_mn,
            time_ms: input.now_ms.wrapping_sub(self.home_ms),
            ..StringInputs::default()
        };
        // A sag reads the inclination, a guide the elevation: each is
        // computed only for a model that reads it.
        let effects = &head.effects;
        if effects
            .iter()
            .any(|e| matches!(e, CompiledEffect::Sag { .. }))
        {
            inputs.cos2_inclination_q16 = cos2_inclinations(&frame.anchors, &self.position);
        }
        if effects.iter().any(CompiledEffect::reads_elevation) {
            inputs.guide_elevation_q32 =
                guide_elevations(&frame.anchors, &frame.home, &self.position);
        }
        for i in 0..STRINGS {
            inputs.counts[i] = self.encoders[i].update(input.raw_counts[i]);
            inputs.direction[i] = self.directions[i].update(inputs.counts[i]);
        }
        if self.rates_from_home {
            self.rates.reset(inputs.counts, input.now_us);
            self.rates_from_home = false;
        }
        self.rates.update(&inputs.counts, input.now_us);
        // Only a model with a latency term pays for the rates.
        if head.effects.iter().any(CompiledEffect::reads_speed) {
            inputs.count_rate_cps = self.rates.rates(&inputs.counts, input.now_us);
        }
        // The training's slips too while the home capture is theirs.
        let lengths_q16 = head.string_lengths(&inputs, self.home_id);
        let lengths = lengths_q16.map(|l| l as f32 / 65536.0);

        let fk_config = if self.lengths_calibrated {
            head.fk_config(&self.config.fk)
        } else {
            FkConfig {
                fault_threshold_mm: f32::INFINITY,
                exclusion_threshold_mm: f32::INFINITY,
                ..self.config.fk
            }
        };
        let fk = forward_kinematics(
            &frame.anchors,
            frame.layout,
            &lengths,
            self.position,
            &fk_config,
        );
        let fk_ok = matches!(fk.status, FkStatus::Ok | FkStatus::FaultyStringExcluded);
        // An inconsistent or unconverged solve is still the best estimate of
        // the position (the least-squares compromise, what a plain controller
        // reports); it is flagged (FK_FAULT latches, tensions drop to
        // pre-tension) rather than replaced by a stale position. Only
        // invalid lengths (NaN, negative) keep the last position.
        if fk.status != FkStatus::InvalidInput {
            self.position = fk.position;
        }
        let room_q16 = position_q16(room_from_device(frame, self.position));
        let corrected_q16 = correction.evaluate(room_q16);

        let geometric = inverse_kinematics(&frame.anchors, self.position);
        self.safety.set_estop(input.estop);
        self.safety.set_active(frame.layout.active);
        self.safety.set_lengths_calibrated(self.lengths_calibrated);
        let faults = self.safety.check(input.now_ms, &lengths, &geometric, fk_ok);

        let requested = self.requested_force(frame, corrected_q16);
        let force = self.safety.limit_force(requested);
        let solution = distribute_warm(
            &frame.anchors,
            frame.layout,
            self.position,
            force,
            self.config.tension_limits,
            &self.config.tension,
            self.multiplier,
        );
        let wanted = self.tensions_to_render(&solution);
        let tensions = self.safety.apply(wanted);
        for (mn, t) in self.tensions_mn.iter_mut().zip(tensions) {
            *mn = (t * 1000.0).clamp(0.0, u16::MAX as f32) as u16;
        }
        LoopOutput {
            counts: inputs.counts,
            direction: inputs.direction,
            string_lengths_mm: lengths,
            position_mm: self.position,
            fk_status: fk.status,
            excluded: fk.excluded,
            room_q16,
            corrected_q16,
            force_n: renderable_force(frame.layout, force),
            tension_status: solution.status,
            rendered_fraction: solution.rendered_fraction,
            tensions_n: tensions,
            faults,
            warnings: self.safety.warnings(),
            slack_mask: self.safety.slack_mask(),
            armed: self.safety.is_armed(),
        }
    }

    /// The force the target asks for this tick (device frame, N), before
    /// the safety limit.
    #[inline(always)]
    fn requested_force(&self, frame: &Frame<f32>, corrected_q16: [i32; 3]) -> [f32; 3] {
        match self.target {
            Target::Idle => [0.0; 3],
            Target::Force(f) => f,
            Target::Guidance {
                target_mm,
                d_min_mm,
                f_max_n,
            } => {
                let p = position_mm(corrected_q16);
                let v = [
                    target_mm[0] - p[0],
                    target_mm[1] - p[1],
                    target_mm[2] - p[2],
                ];
                device_direction(frame, guidance_force(v, d_min_mm, f_max_n))
            }
        }
    }

    /// The tensions to command from the solver's answer: its tensions when
    /// it rendered the force, pretension when it could not.
    #[inline(always)]
    fn tensions_to_render(&mut self, solution: &TensionSolution<f32>) -> [f32; STRINGS] {
        let solved = matches!(
            solution.status,
            TensionStatus::Exact | TensionStatus::Scaled
        );
        // A force scaled to a vertex of the reachable set can end
        // NotConverged a fraction of a millinewton short of the tolerance
        // (fewer free strings than the last refinement needs): its tensions
        // are within limits and render the force, better than a tick of
        // pretension. Its multiplier is not kept as the next warm start.
        let usable = solution.status == TensionStatus::NotConverged
            && solution.residual_n < USABLE_RESIDUAL_N;
        self.multiplier = if solved {
            solution.multiplier
        } else {
            [0.0; 3]
        };
        if solved || usable {
            solution.tensions
        } else {
            [self.config.safety.pretension_n; STRINGS]
        }
    }
}

#[cfg(all(test, feature = "alloc"))]
mod tests;
