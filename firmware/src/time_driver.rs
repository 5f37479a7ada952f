//! embassy-time's driver on three timers whose count survives a flash erase.
//!
//! Replaces embassy-stm32's `time-driver-tim12` (16-bit, needs an interrupt
//! every 32.8 ms, so a model upload's sector erase, which stalls every
//! instruction fetch with interrupts masked for up to ~4 s, made time lose
//! seconds). Design and the choice of timers: docs/hardware.md, "Time base".
//! The arithmetic is `spidar_core::time_base`, tested on the host through a
//! model of these counters and an upload that stalls the CPU.
//!
//! - TIM13 (low counter): 1 MHz, wraps at 2^16; channel 1 in PWM mode 1 at
//!   0x8000, so its `tim13_oc1` reference rises at every wrap. No interrupt.
//! - TIM12 (high counter): external clock mode 1 from ITR2 = `tim13_oc1`
//!   (RM0468, TIM12 internal trigger connections), i.e. it counts the wraps.
//!   Its update (count wrapped at 2^32) and channel-1 compare at 0x8000
//!   (count passed 2^31) interrupts extend the count to 64 bits.
//! - TIM14 (alarm): 1 MHz one-shot of `min(at - now, 2^16)` µs.
//!
//! TIM8 (encoder 4) shares the three vectors; it raises no interrupt.

use core::cell::{Cell, RefCell};
use core::sync::atomic::{compiler_fence, AtomicU32, Ordering};

use critical_section::CriticalSection;
use embassy_stm32::interrupt;
use embassy_stm32::interrupt::{InterruptExt, Priority};
use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::{OcmLimited, Sms, Ts, Urs};
use embassy_stm32::peripherals::{TIM12, TIM13, TIM14};
use embassy_stm32::{rcc, Peri};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embassy_time_driver::Driver;
use embassy_time_queue_utils::Queue;
use spidar_core::time_base::{
    extend_count, half_periods_after, plan_alarm, read_count, AlarmPlan, TICK_HZ,
};

/// Priority of the time base's interrupts: above the control loop's
/// executor (UART4, P6), like embassy's own time drivers (which use P0).
const PRIORITY: Priority = Priority::P1;

struct CascadeDriver {
    /// Half periods (2^31 µs) of the 32-bit count seen by the TIM12 interrupt.
    half_periods: AtomicU32,
    /// The alarm's time (u64::MAX: none).
    alarm_at: Mutex<CriticalSectionRawMutex, Cell<u64>>,
    queue: Mutex<CriticalSectionRawMutex, RefCell<Queue>>,
}

embassy_time_driver::time_driver_impl!(static DRIVER: CascadeDriver = CascadeDriver {
    half_periods: AtomicU32::new(0),
    alarm_at: Mutex::const_new(CriticalSectionRawMutex::new(), Cell::new(u64::MAX)),
    queue: Mutex::new(RefCell::new(Queue::new())),
});

/// Reads the 32-bit count: TIM12, TIM13, TIM12 (see `combine_count`).
fn count() -> u32 {
    read_count(|| {
        let high_before = pac::TIM12.cnt().read().cnt();
        let low = pac::TIM13.cnt().read().cnt();
        let high_after = pac::TIM12.cnt().read().cnt();
        (high_before, low, high_after)
    })
}

impl CascadeDriver {
    /// Plans the alarm at `at`; `false` if it has passed already (the caller
    /// then runs the expired timers and asks again), like embassy's drivers.
    fn set_alarm(&self, cs: CriticalSection, at: u64) -> bool {
        let r = pac::TIM14;
        r.cr1().modify(|w| w.set_cen(false));
        r.sr().write(|w| w.set_uif(false));
        self.alarm_at.borrow(cs).set(at);
        if at == u64::MAX {
            return true;
        }
        match plan_alarm(self.now(), at) {
            AlarmPlan::Due => {
                self.alarm_at.borrow(cs).set(u64::MAX);
                false
            }
            AlarmPlan::OneShot { reload } => {
                r.arr().write(|w| w.set_arr(reload));
                // UG: counter and prescaler to 0 (URS: no update flag).
                r.egr().write(|w| w.set_ug(true));
                r.cr1().modify(|w| w.set_cen(true));
                true
            }
        }
    }

    fn on_alarm(&self) {
        let r = pac::TIM14;
        r.sr().write(|w| w.set_uif(false));
        critical_section::with(|cs| {
            let mut queue = self.queue.borrow(cs).borrow_mut();
            let mut next = queue.next_expiration(self.now());
            while !self.set_alarm(cs, next) {
                next = queue.next_expiration(self.now());
            }
        });
    }

    fn on_half_period(&self) {
        let r = pac::TIM12;
        let sr = r.sr().read();
        // Clear exactly the flags read (write 0 to clear, 1 leaves a flag).
        r.sr().write_value(pac::timer::regs::Sr2ch(!sr.0));
        let p = self.half_periods.load(Ordering::Relaxed);
        let p = half_periods_after(p, sr.uif(), sr.ccif(0));
        self.half_periods.store(p, Ordering::Relaxed);
    }
}

impl Driver for CascadeDriver {
    fn now(&self) -> u64 {
        let p = self.half_periods.load(Ordering::Relaxed);
        compiler_fence(Ordering::Acquire);
        extend_count(p, count())
    }

    fn schedule_wake(&self, at: u64, waker: &core::task::Waker) {
        critical_section::with(|cs| {
            let mut queue = self.queue.borrow(cs).borrow_mut();
            if queue.schedule_wake(at, waker) {
                let mut next = queue.next_expiration(self.now());
                while !self.set_alarm(cs, next) {
                    next = queue.next_expiration(self.now());
                }
            }
        })
    }
}

/// Starts the time base. Call right after `embassy_stm32::init` (which sets
/// the clocks) and before anything reads the time: until then `now()` is 0.
pub fn init(
    _tim12: Peri<'static, TIM12>,
    _tim13: Peri<'static, TIM13>,
    _tim14: Peri<'static, TIM14>,
) {
    rcc::enable_and_reset::<TIM12>();
    rcc::enable_and_reset::<TIM13>();
    rcc::enable_and_reset::<TIM14>();
    let timer_hz = rcc::frequency::<TIM13>().0 as u64;
    let psc = (timer_hz / TICK_HZ).saturating_sub(1) as u16;

    // Low counter: 1 MHz, wraps at 2^16, OC1REF high in 0..0x8000.
    let low = pac::TIM13;
    low.psc().write_value(psc);
    low.arr().write(|w| w.set_arr(0xFFFF));
    low.ccr(0).write(|w| w.set_ccr(0x8000));
    low.ccmr_output(0).modify(|w| {
        w.set_ocm(0, OcmLimited::PWM_MODE1);
        w.set_ocpe(0, true);
    });
    // Channel output enabled (no pin is mapped to it), active high, so
    // that `tim13_oc1` is the reference whichever the trigger taps.
    low.ccer().modify(|w| {
        w.set_cce(0, true);
        w.set_ccp(0, false);
    });
    low.cr1().modify(|w| w.set_urs(Urs::COUNTER_ONLY));
    low.egr().write(|w| w.set_ug(true));

    // High counter: one count per rising edge of ITR2 (= tim13_oc1).
    let high = pac::TIM12;
    high.psc().write_value(0);
    high.arr().write(|w| w.set_arr(0xFFFF));
    high.ccr(0).write(|w| w.set_ccr(0x8000));
    high.cr1().modify(|w| w.set_urs(Urs::COUNTER_ONLY));
    high.egr().write(|w| w.set_ug(true));
    high.smcr().modify(|w| {
        w.set_ts(Ts::ITR2);
        w.set_sms(Sms::EXT_CLOCK_MODE);
    });
    high.sr().write_value(pac::timer::regs::Sr2ch(0));
    high.dier().write(|w| {
        w.set_uie(true);
        w.set_ccie(0, true);
    });

    // Alarm: 1 MHz one-shot, update interrupt only on overflow.
    let alarm = pac::TIM14;
    alarm.psc().write_value(psc);
    alarm.arr().write(|w| w.set_arr(0xFFFF));
    alarm.cr1().modify(|w| {
        w.set_opm(true);
        w.set_urs(Urs::COUNTER_ONLY);
    });
    alarm.egr().write(|w| w.set_ug(true));
    alarm.sr().write_value(pac::timer::regs::Sr1ch(0));
    alarm.dier().write(|w| w.set_uie(true));

    // Start: the high counter first (it only counts edges), then the low.
    high.cr1().modify(|w| w.set_cen(true));
    low.cr1().modify(|w| w.set_cen(true));
    // Starting TIM13 may raise its reference (a rising edge the high counter
    // counts); the first real wrap is 65 ms away, so zero the high counter
    // once the low one has moved.
    let mut spins = 0u32;
    while low.cnt().read().cnt() == 0 && spins < 100_000 {
        spins += 1;
    }
    high.cnt().write(|w| w.set_cnt(0));

    for irq in [interrupt::TIM8_BRK_TIM12, interrupt::TIM8_TRG_COM_TIM14] {
        irq.set_priority(PRIORITY);
        irq.unpend();
        // SAFETY: the handlers below only touch this driver's state and
        // timers; enabling them cannot break a critical section (none is
        // held here, and they take their own).
        unsafe { irq.enable() };
    }
}

#[interrupt]
fn TIM8_BRK_TIM12() {
    DRIVER.on_half_period();
}

#[interrupt]
fn TIM8_TRG_COM_TIM14() {
    DRIVER.on_alarm();
}
