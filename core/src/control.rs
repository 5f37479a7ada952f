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
use crate::encoder::{DirectionTracker, EncoderExtender};
use crate::geometry::{device_direction, room_from_device};
use crate::guidance::guidance_force;
use crate::kinematics::{forward_kinematics, inverse_kinematics, FkConfig, FkStatus};
use crate::model::{Frame, StringInputs};
use crate::safety::{Faults, SafetyConfig, SafetyConfigError, SafetyMonitor};
use crate::string_law::{cos2_inclinations, string_lengths, CompiledEffect};
use crate::tension::{
    distribute_warm, TensionConfig, TensionLimits, TensionSolution, TensionStatus,
};
use crate::STRINGS;

/// The largest residual (N) of a `NotConverged` tension solution the loop
/// still renders (see [`Controller::step`]): a millinewton, ten times the
/// solver's tolerance.
pub const USABLE_RESIDUAL_N: f32 = 1e-3;

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
    /// Force requested of the tension distribution (device frame, N).
    pub force_n: [f32; 3],
    pub tension_status: TensionStatus,
    /// Fraction of the requested force the tensions render.
    pub rendered_fraction: f32,
    /// Tensions sent to the motors, N.
    pub tensions_n: [f32; STRINGS],
    pub faults: Faults,
    pub warnings: Faults,
    pub slack_mask: u8,
    pub armed: bool,
}

/// The state the loop carries from one iteration to the next.
#[derive(Clone, Debug)]
pub struct Controller {
    config: ControlConfig,
    encoders: [EncoderExtender; STRINGS],
    directions: [DirectionTracker; STRINGS],
    home_ms: u32,
    position: [f32; 3],
    multiplier: [f32; 3],
    tensions_mn: [u16; STRINGS],
    safety: SafetyMonitor,
    target: Target,
    /// See [`Controller::set_lengths_calibrated`].
    lengths_calibrated: bool,
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
            home_ms: now_ms,
            position: calibration.head.frame.home,
            multiplier: [0.0; 3],
            tensions_mn: [0; STRINGS],
            safety,
            target: Target::Idle,
            lengths_calibrated: true,
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
        // Tensions and inclinations (sag) are the last tick's: at the loop's
        // rate the position moves by less than 0.1 mm between ticks. Only a
        // model with a term that reads the inclination pays for it.
        let mut inputs = StringInputs {
            tension_mn: self.tensions_mn,
            time_ms: input.now_ms.wrapping_sub(self.home_ms),
            ..StringInputs::default()
        };
        if head.effects.iter().any(CompiledEffect::reads_inclination) {
            inputs.cos2_inclination_q16 = cos2_inclinations(&frame.anchors, &self.position);
        }
        for i in 0..STRINGS {
            inputs.counts[i] = self.encoders[i].update(input.raw_counts[i]);
            inputs.direction[i] = self.directions[i].update(inputs.counts[i]);
        }
        let lengths_q16 = string_lengths(frame.layout, &head.laws, &head.effects, &inputs);
        let lengths = lengths_q16.map(|l| l as f32 / 65536.0);

        let fk_config = if self.lengths_calibrated {
            self.config.fk
        } else {
            FkConfig {
                fault_threshold_mm: f32::INFINITY,
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
            force_n: force,
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
        if solved {
            self.multiplier = solution.multiplier;
            solution.tensions
        } else if usable {
            self.multiplier = [0.0; 3];
            solution.tensions
        } else {
            self.multiplier = [0.0; 3];
            [self.config.safety.pretension_n; STRINGS]
        }
    }
}

#[cfg(all(test, feature = "alloc"))]
mod tests {
    use super::*;
    use crate::blob::compile;
    use crate::correction::CorrectionModel;
    use crate::model::{Calibration, Frame, StringLaw};

    const CPR: u32 = 4096;
    const RADIUS: f64 = 10.0;

    fn calibration() -> Calibration {
        let h = 1100.0;
        let mut anchors = [[0.0; 3]; STRINGS];
        for (i, a) in anchors.iter_mut().enumerate() {
            *a = [
                if i & 1 == 0 { -h } else { h },
                if i & 2 == 0 { -h } else { h },
                if i & 4 == 0 { -h } else { h },
            ];
        }
        Calibration {
            frame: Frame {
                layout: crate::model::StringLayout::ALL,
                anchors,
                home: [0.0; 3],
                room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                room_translation: [0.0, 0.0, 1500.0],
                room_scale: 1.0,
            },
            strings: [StringLaw::polynomial(CPR, [RADIUS, 0.0, 0.0, 0.0]); STRINGS],
            effects: alloc::vec![],
            correction: CorrectionModel::None,
        }
    }

    /// Raw 16-bit counters for the end-effector at `p` (device frame), with
    /// the linear law of `calibration()` and counters that read 1000 at home.
    fn raw_counts_at(cal: &Calibration, p: [f64; 3]) -> [u16; STRINGS] {
        let lengths = inverse_kinematics(&cal.frame.anchors, p);
        let home = inverse_kinematics(&cal.frame.anchors, cal.frame.home);
        let mut raw = [0u16; STRINGS];
        for i in 0..STRINGS {
            let theta = (lengths[i] - home[i]) / RADIUS;
            let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
            raw[i] = (1000 + counts) as u16;
        }
        raw
    }

    #[test]
    fn tracks_a_trajectory_and_renders_a_force_when_armed() {
        let cal = calibration();
        let blob = compile(&cal, 1, 0).unwrap();
        let compiled = CompiledCalibration::from_blob(&blob).unwrap();
        let mut ctl = Controller::new(
            ControlConfig::default(),
            &compiled,
            raw_counts_at(&cal, [0.0; 3]),
            0,
        )
        .unwrap();
        ctl.safety().heartbeat(0);
        ctl.safety().arm().unwrap();
        ctl.set_target(Target::Force([0.0, 0.0, 2.0]));
        let mut out = None;
        for k in 1..=300 {
            let t = k as f64 / 300.0;
            let p = [300.0 * t, -200.0 * t, 400.0 * t];
            ctl.safety().heartbeat(k);
            let o = ctl.step(
                &compiled,
                &LoopInput {
                    raw_counts: raw_counts_at(&cal, p),
                    now_ms: k,
                    estop: false,
                },
            );
            let err = (0..3)
                .map(|c| (o.position_mm[c] as f64 - p[c]).powi(2))
                .sum::<f64>()
                .sqrt();
            // Quantization: one count is 2 pi 10 / 4096 = 0.015 mm of string.
            assert!(err < 0.05, "step {k}: error {err} mm");
            out = Some(o);
        }
        let o = out.unwrap();
        assert!(o.armed && o.faults.is_empty());
        assert_eq!(o.tension_status, TensionStatus::Exact);
        let f = crate::tension::resultant_force(
            &compiled.head.frame.anchors,
            o.position_mm,
            &o.tensions_n,
        );
        assert!((f[2] - 2.0).abs() < 1e-3 && f[0].abs() < 1e-3 && f[1].abs() < 1e-3);
        // Room frame: eq. 6 translation.
        let room = position_mm(o.room_q16);
        assert!((room[2] - (400.0 + 1500.0)).abs() < 0.05);
    }

    /// Counters of a spool whose radius grows with the wound string (the
    /// paper's pulley) read with the linear law: 700 mm from home the
    /// strings disagree by tens of mm. With the law taken as calibrated that
    /// is a forward-kinematics fault and the device drops to pre-tension;
    /// taken as nominal (before calibration) it is the model's own error,
    /// and the loop goes on armed with its least-squares position.
    #[test]
    fn uncalibrated_lengths_raise_no_consistency_fault() {
        let cal = calibration();
        let blob = compile(&cal, 1, 0).unwrap();
        let compiled = CompiledCalibration::from_blob(&blob).unwrap();
        let home = inverse_kinematics(&cal.frame.anchors, cal.frame.home);
        // payout = r theta - kappa theta^2: theta from the true payout.
        let kappa = 0.03;
        let raw_at = |p: [f64; 3]| -> [u16; STRINGS] {
            let lengths = inverse_kinematics(&cal.frame.anchors, p);
            core::array::from_fn(|i| {
                let payout = lengths[i] - home[i];
                let theta =
                    2.0 * payout / (RADIUS + libm::sqrt(RADIUS * RADIUS - 4.0 * kappa * payout));
                let counts = (theta / (2.0 * core::f64::consts::PI) * CPR as f64).round() as i32;
                (1000 + counts) as u16
            })
        };
        let run = |calibrated: bool| {
            let mut ctl =
                Controller::new(ControlConfig::default(), &compiled, raw_at([0.0; 3]), 0).unwrap();
            ctl.set_lengths_calibrated(calibrated);
            ctl.safety().heartbeat(0);
            ctl.safety().arm().unwrap();
            let mut last = None;
            for k in 1..=200u32 {
                let t = f64::from(k) / 200.0;
                ctl.safety().heartbeat(k);
                last = Some(ctl.step(
                    &compiled,
                    &LoopInput {
                        raw_counts: raw_at([-400.0 * t, -400.0 * t, -400.0 * t]),
                        now_ms: k,
                        estop: false,
                    },
                ));
            }
            last.unwrap()
        };
        let calibrated = run(true);
        assert!(calibrated.faults.contains(Faults::FK_FAULT));
        assert!(!calibrated.armed);
        let nominal = run(false);
        assert!(nominal.faults.is_empty(), "{:?}", nominal.faults);
        assert!(nominal.armed);
        assert_eq!(nominal.fk_status, FkStatus::Ok);
    }

    /// A 4-line cable robot (three low anchors, one high) on channels 0, 2,
    /// 5, 7; the other channels keep the cube's anchors, which must not be
    /// read, and their encoders turn as if strings were there.
    #[test]
    fn four_strings_track_and_render_with_inactive_channels_at_zero() {
        let mut cal = calibration();
        cal.frame.layout = crate::model::StringLayout {
            active: 0b1010_0101,
            planar: false,
        };
        cal.frame.anchors[0] = [0.0, -1620.0, -150.0];
        cal.frame.anchors[2] = [1272.8, 1272.8, -150.0];
        cal.frame.anchors[5] = [-1403.0, 810.0, -150.0];
        cal.frame.anchors[7] = [0.0, 0.0, 2350.0];
        cal.frame.home = [0.0, 0.0, 300.0];
        let blob = compile(&cal, 1, 0).unwrap();
        let compiled = CompiledCalibration::from_blob(&blob).unwrap();
        let raw_at = |p: [f64; 3]| {
            let mut c = cal.clone();
            c.frame.layout = crate::model::StringLayout::ALL;
            raw_counts_at(&c, p)
        };
        let mut ctl = Controller::new(
            ControlConfig::default(),
            &compiled,
            raw_at(cal.frame.home),
            0,
        )
        .unwrap();
        ctl.safety().heartbeat(0);
        ctl.safety().arm().unwrap();
        ctl.set_target(Target::Force([0.0, 0.0, -2.0]));
        let mut last = None;
        for k in 1..=200 {
            let t = k as f64 / 200.0;
            let p = [200.0 * t, -150.0 * t, 300.0 + 300.0 * t];
            ctl.safety().heartbeat(k);
            let o = ctl.step(
                &compiled,
                &LoopInput {
                    raw_counts: raw_at(p),
                    now_ms: k,
                    estop: false,
                },
            );
            let err = (0..3)
                .map(|c| (o.position_mm[c] as f64 - p[c]).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(err < 0.1, "step {k}: error {err} mm");
            for i in [1, 3, 4, 6] {
                assert_eq!(o.string_lengths_mm[i], 0.0);
                assert_eq!(o.tensions_n[i], 0.0);
            }
            last = Some(o);
        }
        let o = last.unwrap();
        assert!(o.armed && o.faults.is_empty(), "{o:?}");
        assert_eq!(o.tension_status, TensionStatus::Exact);
        let f = crate::tension::resultant_force(
            &compiled.head.frame.anchors,
            o.position_mm,
            &o.tensions_n,
        );
        assert!((f[2] + 2.0).abs() < 1e-3 && f[0].abs() < 1e-3 && f[1].abs() < 1e-3);
        // Disarmed: pre-tension on the 4 strings, 0 on the other channels.
        ctl.safety().disarm();
        let o = ctl.step(
            &compiled,
            &LoopInput {
                raw_counts: raw_at([200.0, -150.0, 600.0]),
                now_ms: 201,
                estop: false,
            },
        );
        let pre = ControlConfig::default().safety.pretension_n;
        assert_eq!(o.tensions_n, [pre, 0.0, pre, 0.0, 0.0, pre, 0.0, pre]);
    }

    #[test]
    fn heartbeat_loss_drops_to_pretension() {
        let cal = calibration();
        let blob = compile(&cal, 1, 0).unwrap();
        let compiled = CompiledCalibration::from_blob(&blob).unwrap();
        let config = ControlConfig::default();
        let raw = raw_counts_at(&cal, [0.0; 3]);
        let mut ctl = Controller::new(config, &compiled, raw, 0).unwrap();
        ctl.safety().heartbeat(0);
        ctl.safety().arm().unwrap();
        ctl.set_target(Target::Force([3.0, 0.0, 0.0]));
        let step = |ctl: &mut Controller, ms| {
            ctl.step(
                &compiled,
                &LoopInput {
                    raw_counts: raw,
                    now_ms: ms,
                    estop: false,
                },
            )
        };
        assert!(step(&mut ctl, 10).armed);
        let late = step(&mut ctl, 10 + config.safety.heartbeat_timeout_ms + 1);
        assert!(late.faults.contains(Faults::HEARTBEAT_LOST));
        assert!(late
            .tensions_n
            .iter()
            .all(|&t| t == config.safety.pretension_n));
    }
}
