//! The fixed-rate control loop: encoders -> `Device::tick` (spidar-core:
//! encoder extension, string law, forward kinematics, correction, tension
//! distribution, safety) -> PWM.
//!
//! Runs in a high-priority interrupt executor, woken by an `embassy_time`
//! ticker at [`LOOP_HZ`]; measures its own body time with the DWT cycle
//! counter, feeds the watchdog, hands state frames and events to the link.

use cortex_m::peripheral::DWT;
use embassy_time::{Duration, Instant, Ticker};

use spidar_core::device::TickInput;
use spidar_core::STRINGS;

use crate::clocks::SYSCLK_HZ;
use crate::encoders::Encoders;
use crate::motors::{tension_to_duty_q15, Motors};
use crate::shared::{with_device, SharedDevice, StreamItem, STREAM};
use crate::watchdog;

/// Loop rate.
pub const LOOP_HZ: u64 = 10_000;
/// Loop period, µs.
pub const PERIOD_US: u32 = (1_000_000 / LOOP_HZ) as u32;
/// CPU cycles in one period.
pub const PERIOD_CYCLES: u32 = (SYSCLK_HZ as u64 / LOOP_HZ) as u32;
/// CPU cycles per µs.
const CYCLES_PER_US: u32 = SYSCLK_HZ / 1_000_000;

/// Duty (fraction of full scale) per newton of string tension, per motor:
/// depends on the motor, its driver and the pulley radius; measure per
/// device (docs/hardware.md). 1/25: full scale at 25 N.
pub const DUTY_PER_NEWTON: [f32; STRINGS] = [1.0 / 25.0; STRINGS];

/// After a stall longer than this (flash erase), restart the ticker rather
/// than running the missed iterations back to back.
const STALL: Duration = Duration::from_millis(5);

#[embassy_executor::task]
pub async fn control_task(encoders: Encoders, mut motors: Motors, device: &'static SharedDevice) {
    let mut ticker = Ticker::every(Duration::from_hz(LOOP_HZ));
    let mut iterations: u32 = 0;
    let mut report_at = LOOP_HZ as u32;
    let mut last_us: u16 = 0;
    let mut max_cycles: u32 = 0;
    let mut previous = Instant::now();
    loop {
        ticker.next().await;
        let start = DWT::cycle_count();
        let now = Instant::now();
        if now.saturating_duration_since(previous) > STALL {
            ticker.reset();
        }
        previous = now;

        let input = TickInput {
            raw_counts: encoders.read(),
            now_us: now.as_micros(),
            estop: motors.estop(),
        };
        // The critical section: tick, and collect what the link streams.
        let result = with_device(device, |d| {
            d.record_loop_time(last_us);
            let out = d.tick(&input);
            while let Some(e) = d.take_event() {
                if STREAM.try_send(StreamItem::Event(e)).is_err() {
                    d.count_stream_dropped();
                }
            }
            if let Some(s) = d.state_frame() {
                if STREAM.try_send(StreamItem::State(s)).is_err() {
                    d.count_stream_dropped();
                }
            }
            (out, d.motors_enabled())
        });

        // Motors: enabled while the device says so (pre-tension after a
        // fault); the break inputs cut the PWM in hardware on an e-stop.
        let mut duty = [0i16; STRINGS];
        match result {
            Some((out, true)) => {
                if !motors.armed() && !motors.arm() {
                    defmt::warn!("motors: enable refused (emergency stop)");
                }
                for (d, (&t, &k)) in duty
                    .iter_mut()
                    .zip(out.tensions_n.iter().zip(&DUTY_PER_NEWTON))
                {
                    *d = tension_to_duty_q15(t, k);
                }
            }
            _ => {
                if motors.armed() {
                    motors.disarm();
                }
            }
        }
        motors.set_all(&duty);
        watchdog::feed();

        // Timing.
        let cycles = DWT::cycle_count().wrapping_sub(start);
        max_cycles = max_cycles.max(cycles);
        last_us = u16::try_from(cycles / CYCLES_PER_US).unwrap_or(u16::MAX);
        iterations = iterations.wrapping_add(1);
        if iterations >= report_at {
            report_at = iterations.wrapping_add(LOOP_HZ as u32);
            let faults = result.map_or(0, |(o, _)| o.faults.bits());
            defmt::info!(
                "loop: {} it, body last {} max {} cycles ({} ns max of {} ns), motors {}, faults {=u16:#x}",
                iterations,
                cycles,
                max_cycles,
                (max_cycles as u64 * 1_000_000_000 / SYSCLK_HZ as u64) as u32,
                (1_000_000_000 / LOOP_HZ) as u32,
                motors.armed(),
                faults
            );
        }
    }
}

/// `PERIOD_CYCLES` is for reference in logs and docs.
const _: () = assert!(PERIOD_CYCLES > 0 && PERIOD_US > 0);
