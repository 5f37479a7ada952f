//! Firmware of a Scalable-SPIDAR controller on an STM32H723ZG (Nucleo-H723ZG).
//!
//! Tasks:
//! - `control::control_task` (high-priority interrupt executor, 10 kHz
//!   ticker): encoders, control step, PWM, watchdog, telemetry;
//! - `link::usb_task` + `link::link_task` (thread executor): USB CDC-ACM,
//!   frames, requests, model uploads into flash (`storage`).
//!
//! Pin map, timers, flash layout and board changes: docs/hardware.md.
#![no_std]
#![no_main]

mod clocks;
mod control;
mod encoders;
mod link;
mod motors;
// Parts of these are only reached through `link::dispatch`, which decodes
// requests once spidar-protocol's messages land on main (see link.rs).
#[allow(dead_code)]
mod shared;
#[allow(dead_code)]
mod slots;
#[allow(dead_code)]
mod storage;
mod watchdog;

use cortex_m::peripheral::DWT;
use defmt_rtt as _;
use embassy_executor::{InterruptExecutor, Spawner};
use embassy_stm32::flash::Flash;
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::{InterruptExt, Priority};
use panic_probe as _;

use crate::encoders::{EncoderPins, Encoders};
use crate::motors::{MotorPins, Motors};
use crate::shared::ModelUpdate;
use crate::storage::Storage;

/// Executor of the control loop, preempting the thread-mode tasks.
static EXECUTOR_HIGH: InterruptExecutor = InterruptExecutor::new();

/// UART4 is unused; its interrupt vector runs the high-priority executor.
#[interrupt]
unsafe fn UART4() {
    // SAFETY: called only from this interrupt, which `EXECUTOR_HIGH.start` owns.
    unsafe { EXECUTOR_HIGH.on_interrupt() }
}

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    let p = embassy_stm32::init(clocks::config());
    defmt::info!("spidar firmware, {} MHz", clocks::SYSCLK_HZ / 1_000_000);

    if let Some(mut cp) = cortex_m::Peripherals::take() {
        cp.SCB.enable_icache();
        cp.DCB.enable_trace();
        DWT::unlock();
        cp.DWT.enable_cycle_counter();
    }

    let storage = Storage::new(Flash::new_blocking(p.FLASH));
    let model = storage.active().map(|a| ModelUpdate::Use {
        slot: a.slot,
        blob: a.blob(),
    });

    let encoders = Encoders::new(EncoderPins {
        tim2: p.TIM2,
        pa15: p.PA15,
        pb3: p.PB3,
        tim3: p.TIM3,
        pb4: p.PB4,
        pb5: p.PB5,
        tim4: p.TIM4,
        pd12: p.PD12,
        pd13: p.PD13,
        tim5: p.TIM5,
        pa0: p.PA0,
        pa1: p.PA1,
        tim8: p.TIM8,
        pc6: p.PC6,
        pc7: p.PC7,
        tim23: p.TIM23,
        pf0: p.PF0,
        pf1: p.PF1,
        tim24: p.TIM24,
        pf11: p.PF11,
        pf12: p.PF12,
        lptim2: p.LPTIM2,
        pb10: p.PB10,
        pd11: p.PD11,
    });
    let motors = Motors::new(MotorPins {
        tim1: p.TIM1,
        pe9: p.PE9,
        pe11: p.PE11,
        pe13: p.PE13,
        pe14: p.PE14,
        tim15: p.TIM15,
        pe5: p.PE5,
        pe6: p.PE6,
        tim16: p.TIM16,
        pf6: p.PF6,
        tim17: p.TIM17,
        pf7: p.PF7,
        dir: [
            p.PE7.into(),
            p.PE8.into(),
            p.PE10.into(),
            p.PE12.into(),
            p.PE0.into(),
            p.PE2.into(),
            p.PE4.into(),
            p.PG12.into(),
        ],
        enable: p.PG14,
        bk_tim1: p.PE15,
        bk_tim15: p.PE3,
        bk_tim16: p.PF10,
        bk_tim17: p.PG6,
    });

    // The watchdog starts just before the loop that feeds it.
    watchdog::start(watchdog::NORMAL_TIMEOUT_MS);
    interrupt::UART4.set_priority(Priority::P6);
    let high = EXECUTOR_HIGH.start(interrupt::UART4);
    high.spawn(control::control_task(encoders, motors, model).expect("control task"));

    let (device, class) = link::usb(p.USB_OTG_HS, p.PA12, p.PA11);
    spawner.spawn(link::usb_task(device).expect("usb task"));
    spawner.spawn(link::link_task(class, storage).expect("link task"));
}
