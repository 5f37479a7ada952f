//! The fixed-rate control loop: encoders -> counts -> (string law, FK,
//! correction, tension distribution, safety: spidar-core) -> PWM.
//!
//! Runs in a high-priority interrupt executor, woken by an `embassy_time`
//! ticker at [`LOOP_HZ`]; measures its own body time with the DWT cycle
//! counter, feeds the watchdog, publishes [`Telemetry`].

use core::sync::atomic::Ordering;

use cortex_m::peripheral::DWT;
use embassy_time::{Duration, Ticker};

use spidar_core::STRINGS;

use crate::clocks::SYSCLK_HZ;
use crate::encoders::Encoders;
use crate::motors::Motors;
use crate::shared::{
    self, faults, Command, ModelUpdate, Telemetry, COMMANDS, MODEL, MODEL_IN_USE, NO_SLOT,
};
use crate::watchdog;

/// Loop rate.
pub const LOOP_HZ: u64 = 10_000;
/// CPU cycles in one period.
pub const PERIOD_CYCLES: u32 = (SYSCLK_HZ as u64 / LOOP_HZ) as u32;

/// Extends 16-bit hardware counts to i32 counts since home (boot).
///
/// PLACEHOLDER for `spidar_core::encoder::EncoderExtender` (not on main yet):
/// the same rule, a signed 16-bit difference per iteration, which is exact as
/// long as an encoder moves less than 32767 counts per period.
struct Extender {
    last: [u16; STRINGS],
    counts: [i32; STRINGS],
}

impl Extender {
    fn new(first: [u16; STRINGS]) -> Self {
        Self {
            last: first,
            counts: [0; STRINGS],
        }
    }

    fn update(&mut self, raw: [u16; STRINGS]) -> [i32; STRINGS] {
        for ((&r, last), count) in raw.iter().zip(&mut self.last).zip(&mut self.counts) {
            let delta = r.wrapping_sub(*last) as i16 as i32;
            *count = count.wrapping_add(delta);
            *last = r;
        }
        self.counts
    }
}

/// What the loop renders.
#[derive(Clone, Copy)]
struct Targets {
    force_n: [f32; 3],
}

/// One control step: counts + model + targets -> signed duties.
///
/// PLACEHOLDER until `spidar_core::control` lands: it must run string law ->
/// forward kinematics -> correction -> tension distribution -> safety and
/// return per-string tensions, which `motors::tension_to_duty_q15` turns into
/// duties. Until then it commands zero on every motor (safe: no torque).
fn control_step(
    _counts: &[i32; STRINGS],
    _model: Option<&'static [u8]>,
    _targets: &Targets,
) -> [i16; STRINGS] {
    [0; STRINGS]
}

#[embassy_executor::task]
pub async fn control_task(encoders: Encoders, mut motors: Motors, model: Option<ModelUpdate>) {
    let mut extender = Extender::new(encoders.read());
    let mut targets = Targets { force_n: [0.0; 3] };
    let mut model_blob: Option<&'static [u8]> = None;
    if let Some(m) = model {
        use_model(m, &mut model_blob);
    }
    let mut t = Telemetry::default();
    let mut ticker = Ticker::every(Duration::from_hz(LOOP_HZ));
    let mut report_at = LOOP_HZ as u32;
    loop {
        ticker.next().await;
        let start = DWT::cycle_count();

        // 1. Encoders.
        let raw = encoders.read();
        let counts = extender.update(raw);

        // 2. Commands and model switches from the link.
        while let Ok(cmd) = COMMANDS.try_receive() {
            match cmd {
                Command::Arm => {
                    if t.faults & faults::ESTOP != 0 || !motors.arm() {
                        defmt::warn!("arm refused: emergency stop");
                    }
                }
                Command::Disarm => motors.disarm(),
                Command::SetForce(f) => targets.force_n = f,
                Command::ClearFaults => {
                    if !motors.estop() {
                        t.faults &= !faults::ESTOP;
                    }
                    t.faults &= !faults::LOOP_OVERRUN;
                }
            }
        }
        if let Some(m) = MODEL.try_take() {
            use_model(m, &mut model_blob);
        }

        // 3. Safety: the break inputs already cut the PWM in hardware; latch.
        if motors.estop() {
            if t.faults & faults::ESTOP == 0 {
                defmt::error!("emergency stop");
            }
            t.faults |= faults::ESTOP;
            motors.disarm();
        }

        // 4. Control step and PWM.
        let duty = control_step(&counts, model_blob, &targets);
        motors.set_all(&duty);

        watchdog::feed();

        // 5. Timing and telemetry.
        let cycles = DWT::cycle_count().wrapping_sub(start);
        t.iterations = t.iterations.wrapping_add(1);
        t.raw_counts = raw;
        t.counts = counts;
        t.duty_q15 = if motors.armed() { duty } else { [0; STRINGS] };
        t.armed = motors.armed();
        t.loop_cycles_last = cycles;
        t.loop_cycles_max = t.loop_cycles_max.max(cycles);
        if cycles > PERIOD_CYCLES {
            t.overruns += 1;
            t.faults |= faults::LOOP_OVERRUN;
        }
        shared::TELEMETRY.lock(|c| c.set(t));

        if t.iterations >= report_at {
            report_at = t.iterations.wrapping_add(LOOP_HZ as u32);
            defmt::info!(
                "loop: {} it, body last {} max {} cycles ({} ns max of {} ns), {} overruns, armed {}, faults {=u16:#x}",
                t.iterations,
                t.loop_cycles_last,
                t.loop_cycles_max,
                (t.loop_cycles_max as u64 * 1_000_000_000 / SYSCLK_HZ as u64) as u32,
                (1_000_000_000 / LOOP_HZ) as u32,
                t.overruns,
                t.armed,
                t.faults
            );
        }
    }
}

fn use_model(m: ModelUpdate, model_blob: &mut Option<&'static [u8]>) {
    match m {
        ModelUpdate::Use { slot, blob } => {
            // PLACEHOLDER: parse with `spidar_core::blob` (CompiledCalibration)
            // once it lands; until then the blob is only held.
            *model_blob = Some(blob);
            MODEL_IN_USE.store(slot.index(), Ordering::Release);
            defmt::info!("control: model in slot {} ({} bytes)", slot, blob.len());
        }
        ModelUpdate::None => {
            *model_blob = None;
            MODEL_IN_USE.store(NO_SLOT, Ordering::Release);
            defmt::info!("control: no model");
        }
    }
}
