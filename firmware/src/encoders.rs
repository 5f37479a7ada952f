//! Eight quadrature encoders on hardware counters.
//!
//! | string | counter | A (CH1/IN1) | B (CH2/IN2) |
//! |---|---|---|---|
//! | 0 | TIM2   | PA15 AF1  | PB3 AF1   |
//! | 1 | TIM3   | PB4 AF2   | PB5 AF2   |
//! | 2 | TIM4   | PD12 AF2  | PD13 AF2  |
//! | 3 | TIM5   | PA0 AF2   | PA1 AF2 (open SB57) |
//! | 4 | TIM8   | PC6 AF3   | PC7 AF3   |
//! | 5 | TIM23  | PF0 AF13  | PF1 AF13  |
//! | 6 | TIM24  | PF11 AF14 | PF12 AF14 |
//! | 7 | LPTIM2 | PB10 AF3  | PD11 AF3  |
//!
//! All count x4 (both edges of both channels) modulo 2^16; the 32-bit
//! TIM2/5/23/24 are set to wrap at 2^16 too, so every channel looks the same
//! to the extender. embassy-stm32 0.6 has no LPTIM encoder driver, so LPTIM2
//! is set up on its registers here.

use embassy_stm32::gpio::{AfType, Flex, Pull};
use embassy_stm32::pac;
use embassy_stm32::pac::lptim::vals::{Ckpol, ClockSource, Filter, Presc};
use embassy_stm32::peripherals::*;
use embassy_stm32::timer::qei::{Config as QeiConfig, Qei, QeiMode};
use embassy_stm32::Peri;

use spidar_core::STRINGS;

/// Counting direction of each channel: +1 if the counter counts up when the
/// string pays out, -1 if the wiring makes it count down. Set per device.
pub const SIGN: [i8; STRINGS] = [1, 1, 1, 1, 1, 1, 1, 1];

/// LPTIM2 in encoder mode (RM0468, LPTIM "Encoder mode").
pub struct LptimEncoder {
    _in1: Flex<'static>,
    _in2: Flex<'static>,
}

impl LptimEncoder {
    pub fn new(
        _lptim: Peri<'static, LPTIM2>,
        in1: Peri<'static, PB10>,
        in2: Peri<'static, PD11>,
    ) -> Self {
        embassy_stm32::rcc::enable_and_reset::<LPTIM2>();
        let mut a = Flex::new(in1);
        let mut b = Flex::new(in2);
        a.set_as_af_unchecked(3, AfType::input(Pull::None));
        b.set_as_af_unchecked(3, AfType::input(Pull::None));

        let r = pac::LPTIM2;
        r.cr().write(|w| w.set_enable(false));
        // CFGR is written with the counter disabled: internal kernel clock
        // (pclk4, 130 MHz), encoder mode counting on both edges of both
        // inputs (x4), 4-sample glitch filter on the inputs.
        r.cfgr().write(|w| {
            w.set_cksel(ClockSource::INTERNAL);
            w.set_presc(Presc::DIV1);
            w.set_ckpol(Ckpol::BOTH);
            w.set_ckflt(Filter::COUNT4);
            w.set_enc(true);
        });
        r.cr().write(|w| w.set_enable(true));
        // ARR is written with the counter enabled; wait for ARROK.
        r.arr().write(|w| w.set_arr(0xFFFF));
        let mut spins = 0u32;
        while !r.isr().read().arrok() && spins < 100_000 {
            spins += 1;
        }
        r.icr().write(|w| w.set_arrokcf(true));
        r.cr().write(|w| {
            w.set_enable(true);
            w.set_cntstrt(true);
        });
        Self { _in1: a, _in2: b }
    }

    /// The counter, read until two consecutive reads agree (the LPTIM counter
    /// may be asynchronous to the bus clock).
    pub fn count(&self) -> u16 {
        let r = pac::LPTIM2;
        let mut prev = r.cnt().read().cnt();
        for _ in 0..4 {
            let now = r.cnt().read().cnt();
            if now == prev {
                return now;
            }
            prev = now;
        }
        prev
    }
}

/// The pins of all eight encoders, as handed over by `main`.
pub struct EncoderPins {
    pub tim2: Peri<'static, TIM2>,
    pub pa15: Peri<'static, PA15>,
    pub pb3: Peri<'static, PB3>,
    pub tim3: Peri<'static, TIM3>,
    pub pb4: Peri<'static, PB4>,
    pub pb5: Peri<'static, PB5>,
    pub tim4: Peri<'static, TIM4>,
    pub pd12: Peri<'static, PD12>,
    pub pd13: Peri<'static, PD13>,
    pub tim5: Peri<'static, TIM5>,
    pub pa0: Peri<'static, PA0>,
    pub pa1: Peri<'static, PA1>,
    pub tim8: Peri<'static, TIM8>,
    pub pc6: Peri<'static, PC6>,
    pub pc7: Peri<'static, PC7>,
    pub tim23: Peri<'static, TIM23>,
    pub pf0: Peri<'static, PF0>,
    pub pf1: Peri<'static, PF1>,
    pub tim24: Peri<'static, TIM24>,
    pub pf11: Peri<'static, PF11>,
    pub pf12: Peri<'static, PF12>,
    pub lptim2: Peri<'static, LPTIM2>,
    pub pb10: Peri<'static, PB10>,
    pub pd11: Peri<'static, PD11>,
}

pub struct Encoders {
    e0: Qei<'static, TIM2>,
    e1: Qei<'static, TIM3>,
    e2: Qei<'static, TIM4>,
    e3: Qei<'static, TIM5>,
    e4: Qei<'static, TIM8>,
    e5: Qei<'static, TIM23>,
    e6: Qei<'static, TIM24>,
    e7: LptimEncoder,
}

impl Encoders {
    pub fn new(p: EncoderPins) -> Self {
        // Encoder outputs are push-pull 3.3 V or open-collector with external
        // pull-ups; the weak internal pull-ups keep an unplugged encoder quiet.
        let cfg = QeiConfig {
            ch1_pull: Pull::Up,
            ch2_pull: Pull::Up,
            mode: QeiMode::Mode3,
            auto_reload: u16::MAX,
        };
        Self {
            e0: Qei::new(p.tim2, p.pa15, p.pb3, cfg),
            e1: Qei::new(p.tim3, p.pb4, p.pb5, cfg),
            e2: Qei::new(p.tim4, p.pd12, p.pd13, cfg),
            e3: Qei::new(p.tim5, p.pa0, p.pa1, cfg),
            e4: Qei::new(p.tim8, p.pc6, p.pc7, cfg),
            e5: Qei::new(p.tim23, p.pf0, p.pf1, cfg),
            e6: Qei::new(p.tim24, p.pf11, p.pf12, cfg),
            e7: LptimEncoder::new(p.lptim2, p.pb10, p.pd11),
        }
    }

    /// Raw 16-bit counts of all eight encoders, sign-corrected so that paying
    /// out counts up.
    pub fn read(&self) -> [u16; STRINGS] {
        let raw = [
            self.e0.count(),
            self.e1.count(),
            self.e2.count(),
            self.e3.count(),
            self.e4.count(),
            self.e5.count(),
            self.e6.count(),
            self.e7.count(),
        ];
        let mut out = [0u16; STRINGS];
        for i in 0..STRINGS {
            out[i] = if SIGN[i] < 0 {
                raw[i].wrapping_neg()
            } else {
                raw[i]
            };
        }
        out
    }
}
