//! Firmware of a Scalable-SPIDAR controller on an STM32H723ZG (Nucleo-H723ZG).
//!
//! The binary only wires peripherals and tasks to `spidar_core::device`:
//! - `control::control_task` (high-priority interrupt executor, 10 kHz
//!   ticker): encoders -> `Device::tick` -> PWM, watchdog, stream;
//! - `link::usb_task`, `link::link_reader`, `link::link_writer` (thread
//!   executor): USB CDC-ACM, `DeviceLink` frames, `Device::handle`;
//! - `storage::H7Flash`: the model slots in internal flash for
//!   `spidar_core::model_store`.
//!
//! Pin map, timers, flash layout and board changes: docs/hardware.md.
#![no_std]
#![no_main]

mod cache;
mod clocks;
mod control;
mod encoders;
mod link;
mod motors;
mod shared;
mod storage;
mod time_driver;
mod watchdog;

use core::cell::RefCell;
use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicBool, Ordering};

use cortex_m::peripheral::DWT;
use defmt_rtt as _;
use embassy_executor::{InterruptExecutor, Spawner};
use embassy_stm32::flash::Flash;
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::{InterruptExt, Priority};
use embassy_sync::blocking_mutex::Mutex;
use embassy_time::Instant;
use panic_probe as _;
use spidar_core::control::ControlConfig;
use spidar_core::device::{Device, DeviceConfig, ModelBuffer};
use static_cell::StaticCell;

use crate::encoders::{EncoderPins, Encoders};
use crate::motors::{MotorPins, Motors};
use crate::shared::SharedDevice;
use crate::storage::H7Flash;

/// RAM copy of the active model blob, and the buffer a commit validates the
/// next one in (they swap on commit). Bounds the model blob the device takes
/// (`HelloAck::max_blob_len`, the smaller of this and a slot's 128 KiB minus
/// the 32-byte commit record); an NN of 64 neurons is ~2.2 KiB, an SVR of
/// 500 support vectors ~12.5 KiB, so 96 KiB is ~3900 support vectors.
/// Aligned (`ModelBuffer`): the SVR records of a blob at the start of the
/// buffer are then read as aligned words.
const MODEL_RAM_LEN: usize = spidar_protocol::blob::REFERENCE_FIRMWARE_BLOB_CAPACITY;

/// Both model buffers, in AXI SRAM (192 KiB, too large for the 128 KiB
/// DTCM next to `.bss` and the stack). No DMA touches them.
#[repr(C)]
struct ModelRam {
    active: ModelBuffer<MODEL_RAM_LEN>,
    spare: ModelBuffer<MODEL_RAM_LEN>,
}

/// `.axisram` is NOLOAD (memory.x): cortex-m-rt neither loads nor zeroes it,
/// so this holds garbage until [`take_model_ram`] zeroes it.
#[link_section = ".axisram"]
static mut MODEL_RAM: MaybeUninit<ModelRam> = MaybeUninit::uninit();
/// Set by the one call of [`take_model_ram`] (in `.bss`, so zeroed at reset).
static MODEL_RAM_TAKEN: AtomicBool = AtomicBool::new(false);

/// Zeroes the AXI SRAM model buffers in place and hands them out, once
/// (panics on a second call). In place: a `ModelRam` by value would be a
/// 192 KiB temporary on the DTCM stack.
fn take_model_ram() -> (&'static mut [u8], &'static mut [u8]) {
    assert!(
        !MODEL_RAM_TAKEN.swap(true, Ordering::AcqRel),
        "model RAM taken twice"
    );
    // SAFETY: the flag above lets this run once, so this is the only
    // reference ever made to `MODEL_RAM` (nothing else names it). The write
    // initializes every byte (all-zero is a valid `ModelRam`: byte arrays)
    // before `assume_init_mut`. AXI SRAM is clocked from reset on the H723
    // (no RCC enable) and exists at these addresses (see memory.x).
    let ram = unsafe {
        let ram = &mut *core::ptr::addr_of_mut!(MODEL_RAM);
        ram.as_mut_ptr().write_bytes(0, 1);
        ram.assume_init_mut()
    };
    (ram.active.bytes(), ram.spare.bytes())
}

static DEVICE: StaticCell<SharedDevice> = StaticCell::new();

/// `[major, minor, patch]` of this crate.
const FIRMWARE_VERSION: [u16; 3] = [
    parse_u16(env!("CARGO_PKG_VERSION_MAJOR")),
    parse_u16(env!("CARGO_PKG_VERSION_MINOR")),
    parse_u16(env!("CARGO_PKG_VERSION_PATCH")),
];

const fn parse_u16(s: &str) -> u16 {
    let b = s.as_bytes();
    let mut v: u16 = 0;
    let mut i = 0;
    while i < b.len() {
        v = v
            .wrapping_mul(10)
            .wrapping_add((b[i].wrapping_sub(b'0')) as u16);
        i += 1;
    }
    v
}

embassy_stm32::bind_interrupts!(struct RngIrqs {
    RNG => embassy_stm32::rng::InterruptHandler<embassy_stm32::peripherals::RNG>;
});

/// This boot's id ([`DeviceConfig::boot_id`]): a random number from the
/// RNG (HSI48, `clocks`), so that home captures of two boots never share an
/// id. The RNG is dropped (clock off) once read.
fn boot_id(rng: embassy_stm32::Peri<'static, embassy_stm32::peripherals::RNG>) -> u32 {
    embassy_stm32::rng::Rng::new(rng, RngIrqs).next_u32()
}

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
    // The time base first: everything after reads the time.
    time_driver::init(p.TIM12, p.TIM13, p.TIM14);
    defmt::info!("spidar firmware, {} MHz", clocks::SYSCLK_HZ / 1_000_000);

    if let Some(mut cp) = cortex_m::Peripherals::take() {
        cp.SCB.enable_icache();
        // Before anything reads the model slots: they become uncached, the
        // rest of memory cached (docs/hardware.md, "Caches").
        cache::model_slots_uncached(&mut cp.MPU);
        cp.SCB.enable_dcache(&mut cp.CPUID);
        cp.DCB.enable_trace();
        DWT::unlock();
        cp.DWT.enable_cycle_counter();
    }

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

    // Boot the device: model store scan, active model into RAM, home here.
    let config = DeviceConfig {
        firmware_version: FIRMWARE_VERSION,
        device_id: embassy_stm32::uid::uid(),
        loop_period_us: control::PERIOD_US,
        boot_id: boot_id(p.RNG),
        control: ControlConfig::default(),
    };
    let (model_ram, spare_ram) = take_model_ram();
    let device = match Device::new(
        config,
        H7Flash::new(Flash::new_blocking(p.FLASH)),
        model_ram,
        spare_ram,
        encoders.read(),
        Instant::now().as_micros(),
    ) {
        Ok(d) => d,
        Err(e) => {
            // Only a bad constant ControlConfig gets here; motors stay off.
            defmt::error!("invalid control config: {}", e);
            loop {
                cortex_m::asm::wfi();
            }
        }
    };
    defmt::info!(
        "device: models up to {} bytes",
        device.hello_ack().max_blob_len
    );
    let device: &'static SharedDevice = DEVICE.init(Mutex::new(RefCell::new(device)));

    // The watchdog starts just before the loop that feeds it.
    watchdog::start(watchdog::NORMAL_TIMEOUT_MS);
    interrupt::UART4.set_priority(Priority::P6);
    let high = EXECUTOR_HIGH.start(interrupt::UART4);
    high.spawn(control::control_task(encoders, motors, device).expect("control task"));

    let (usb, class) = link::usb(p.USB_OTG_HS, p.PA12, p.PA11);
    let (sender, receiver) = class.split();
    spawner.spawn(link::usb_task(usb).expect("usb task"));
    spawner.spawn(link::link_reader(receiver, device).expect("link reader"));
    spawner.spawn(link::link_writer(sender).expect("link writer"));
}
