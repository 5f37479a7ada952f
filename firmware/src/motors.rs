//! Eight PWM motor channels with direction pins and a hardware emergency stop.
//!
//! | motor | timer ch | PWM pin | DIR pin |
//! |---|---|---|---|
//! | 0 | TIM1 CH1  | PE9 AF1  | PE7  |
//! | 1 | TIM1 CH2  | PE11 AF1 | PE8  |
//! | 2 | TIM1 CH3  | PE13 AF1 | PE10 |
//! | 3 | TIM1 CH4  | PE14 AF1 | PE12 |
//! | 4 | TIM15 CH1 | PE5 AF4  | PE0  |
//! | 5 | TIM15 CH2 | PE6 AF4  | PE2  |
//! | 6 | TIM16 CH1 | PF6 AF1  | PE4  |
//! | 7 | TIM17 CH1 | PF7 AF1  | PG12 |
//!
//! Driver enable (all drivers): PG14, high = enabled.
//!
//! Every PWM channel sits on a timer with a break input (TIM1, TIM15, TIM16,
//! TIM17), and the four break inputs (PE15, PE3, PF10, PG6) are wired to one
//! emergency-stop line: a normally-closed switch to GND with pull-ups, so
//! pressing it *or* a broken wire drives the line high and the timers' break
//! logic clears MOE within a few timer clocks, in hardware, whatever the
//! software does. The outputs then go to their idle level (low = no drive).
//! The control loop sees the break flag, latches the ESTOP fault and
//! disarms; re-arming needs the line back low and an explicit `Arm`.

use embassy_stm32::gpio::{AfType, Flex, Level, Output, OutputType, Pull, Speed};
use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals::{Bkp, FilterValue, Ossi, Ossr};
use embassy_stm32::peripherals::*;
use embassy_stm32::time::khz;
use embassy_stm32::timer::simple_pwm::{PwmPin, SimplePwm};
use embassy_stm32::timer::{low_level::CountingMode, Channel};
use embassy_stm32::Peri;

use spidar_core::STRINGS;

/// PWM frequency: above hearing, within what common H-bridges take.
pub const PWM_KHZ: u32 = 20;

/// Full-scale signed duty.
pub const DUTY_FULL: i16 = i16::MAX;

pub struct MotorPins {
    pub tim1: Peri<'static, TIM1>,
    pub pe9: Peri<'static, PE9>,
    pub pe11: Peri<'static, PE11>,
    pub pe13: Peri<'static, PE13>,
    pub pe14: Peri<'static, PE14>,
    pub tim15: Peri<'static, TIM15>,
    pub pe5: Peri<'static, PE5>,
    pub pe6: Peri<'static, PE6>,
    pub tim16: Peri<'static, TIM16>,
    pub pf6: Peri<'static, PF6>,
    pub tim17: Peri<'static, TIM17>,
    pub pf7: Peri<'static, PF7>,
    pub dir: [Peri<'static, embassy_stm32::gpio::AnyPin>; STRINGS],
    pub enable: Peri<'static, PG14>,
    pub bk_tim1: Peri<'static, PE15>,
    pub bk_tim15: Peri<'static, PE3>,
    pub bk_tim16: Peri<'static, PF10>,
    pub bk_tim17: Peri<'static, PG6>,
}

pub struct Motors {
    tim1: SimplePwm<'static, TIM1>,
    tim15: SimplePwm<'static, TIM15>,
    tim16: SimplePwm<'static, TIM16>,
    tim17: SimplePwm<'static, TIM17>,
    dir: [Output<'static>; STRINGS],
    enable: Output<'static>,
    /// The break pins, kept in AF mode; their input level is still readable.
    break_pins: [Flex<'static>; 4],
    armed: bool,
}

fn break_pin(pin: Flex<'static>, af: u8) -> Flex<'static> {
    let mut pin = pin;
    pin.set_as_af_unchecked(af, AfType::input(Pull::Up));
    pin
}

/// Break: active high, filtered (8 samples at f_CK_INT), outputs to their
/// idle level (low) while MOE = 0, no automatic re-arm.
macro_rules! setup_break {
    ($tim:expr) => {{
        let t = $tim;
        t.bdtr().modify(|w| {
            w.set_bkf(0, FilterValue::FCK_INT_N8);
            w.set_bkp(0, Bkp::ACTIVE_HIGH);
            w.set_ossi(Ossi::IDLE_LEVEL);
            w.set_ossr(Ossr::IDLE_LEVEL);
            w.set_aoe(false);
            w.set_bke(0, true);
        });
        t.af1().modify(|w| w.set_bkine(true));
        t.sr().modify(|w| w.set_bif(0, false));
    }};
}

impl Motors {
    pub fn new(p: MotorPins) -> Self {
        let f = khz(PWM_KHZ);
        let mode = CountingMode::EdgeAlignedUp;
        let pp = OutputType::PushPull;
        let mut tim1 = SimplePwm::new(
            p.tim1,
            Some(PwmPin::new(p.pe9, pp)),
            Some(PwmPin::new(p.pe11, pp)),
            Some(PwmPin::new(p.pe13, pp)),
            Some(PwmPin::new(p.pe14, pp)),
            f,
            mode,
        );
        let mut tim15 = SimplePwm::new(
            p.tim15,
            Some(PwmPin::new(p.pe5, pp)),
            Some(PwmPin::new(p.pe6, pp)),
            None,
            None,
            f,
            mode,
        );
        let mut tim16 = SimplePwm::new(
            p.tim16,
            Some(PwmPin::new(p.pf6, pp)),
            None,
            None,
            None,
            f,
            mode,
        );
        let mut tim17 = SimplePwm::new(
            p.tim17,
            Some(PwmPin::new(p.pf7, pp)),
            None,
            None,
            None,
            f,
            mode,
        );

        let break_pins = [
            break_pin(Flex::new(p.bk_tim1), 1),
            break_pin(Flex::new(p.bk_tim15), 4),
            break_pin(Flex::new(p.bk_tim16), 1),
            break_pin(Flex::new(p.bk_tim17), 1),
        ];
        setup_break!(pac::TIM1);
        setup_break!(pac::TIM15);
        setup_break!(pac::TIM16);
        setup_break!(pac::TIM17);

        for ch in [Channel::Ch1, Channel::Ch2, Channel::Ch3, Channel::Ch4] {
            tim1.channel(ch).set_duty_cycle_fully_off();
            tim1.channel(ch).enable();
        }
        for ch in [Channel::Ch1, Channel::Ch2] {
            tim15.channel(ch).set_duty_cycle_fully_off();
            tim15.channel(ch).enable();
        }
        tim16.ch1().set_duty_cycle_fully_off();
        tim16.ch1().enable();
        tim17.ch1().set_duty_cycle_fully_off();
        tim17.ch1().enable();

        let [d0, d1, d2, d3, d4, d5, d6, d7] = p.dir;
        let out = |pin| Output::new(pin, Level::Low, Speed::Low);
        let mut m = Self {
            tim1,
            tim15,
            tim16,
            tim17,
            dir: [
                out(d0),
                out(d1),
                out(d2),
                out(d3),
                out(d4),
                out(d5),
                out(d6),
                out(d7),
            ],
            enable: Output::new(p.enable, Level::Low, Speed::Low),
            break_pins,
            armed: false,
        };
        m.disarm();
        m
    }

    /// True while the emergency-stop line is high or any timer saw a break
    /// since the last [`Self::arm`].
    pub fn estop(&self) -> bool {
        let line = self.break_pins.iter().any(|p| p.is_high());
        let flag = pac::TIM1.sr().read().bif(0)
            || pac::TIM15.sr().read().bif(0)
            || pac::TIM16.sr().read().bif(0)
            || pac::TIM17.sr().read().bif(0);
        let moe_lost = self.armed
            && !(pac::TIM1.bdtr().read().moe()
                && pac::TIM15.bdtr().read().moe()
                && pac::TIM16.bdtr().read().moe()
                && pac::TIM17.bdtr().read().moe());
        line || flag || moe_lost
    }

    pub fn armed(&self) -> bool {
        self.armed
    }

    /// Enables the drivers if the emergency stop is clear. Duties start at 0.
    pub fn arm(&mut self) -> bool {
        self.set_all_zero();
        if self.break_pins.iter().any(|p| p.is_high()) {
            return false;
        }
        for clear in [
            || pac::TIM1.sr().modify(|w| w.set_bif(0, false)),
            || pac::TIM15.sr().modify(|w| w.set_bif(0, false)),
            || pac::TIM16.sr().modify(|w| w.set_bif(0, false)),
            || pac::TIM17.sr().modify(|w| w.set_bif(0, false)),
        ] {
            clear();
        }
        pac::TIM1.bdtr().modify(|w| w.set_moe(true));
        pac::TIM15.bdtr().modify(|w| w.set_moe(true));
        pac::TIM16.bdtr().modify(|w| w.set_moe(true));
        pac::TIM17.bdtr().modify(|w| w.set_moe(true));
        self.enable.set_high();
        self.armed = true;
        true
    }

    /// Zero duty, drivers disabled, timer outputs forced to idle (MOE = 0).
    pub fn disarm(&mut self) {
        self.set_all_zero();
        self.enable.set_low();
        pac::TIM1.bdtr().modify(|w| w.set_moe(false));
        pac::TIM15.bdtr().modify(|w| w.set_moe(false));
        pac::TIM16.bdtr().modify(|w| w.set_moe(false));
        pac::TIM17.bdtr().modify(|w| w.set_moe(false));
        self.armed = false;
    }

    fn set_all_zero(&mut self) {
        for i in 0..STRINGS {
            self.set_duty(i, 0);
        }
    }

    /// Sets one motor: `duty_q15` in -32767..=32767 of full scale; the sign
    /// drives the DIR pin (1 = negative = reel in), the magnitude the PWM.
    pub fn set_duty(&mut self, motor: usize, duty_q15: i16) {
        let mag = duty_q15.unsigned_abs().min(DUTY_FULL as u16) as u32;
        if let Some(d) = self.dir.get_mut(motor) {
            d.set_level(if duty_q15 < 0 {
                Level::High
            } else {
                Level::Low
            });
        }
        match motor {
            0..=3 => {
                let ch = [Channel::Ch1, Channel::Ch2, Channel::Ch3, Channel::Ch4][motor];
                let max = self.tim1.max_duty_cycle();
                self.tim1.channel(ch).set_duty_cycle(scale(mag, max));
            }
            4 | 5 => {
                let ch = if motor == 4 {
                    Channel::Ch1
                } else {
                    Channel::Ch2
                };
                let max = self.tim15.max_duty_cycle();
                self.tim15.channel(ch).set_duty_cycle(scale(mag, max));
            }
            6 => {
                let max = self.tim16.max_duty_cycle();
                self.tim16.ch1().set_duty_cycle(scale(mag, max));
            }
            7 => {
                let max = self.tim17.max_duty_cycle();
                self.tim17.ch1().set_duty_cycle(scale(mag, max));
            }
            _ => {}
        }
    }

    /// Sets all motors; zero everywhere unless armed.
    pub fn set_all(&mut self, duty_q15: &[i16; STRINGS]) {
        for (i, &d) in duty_q15.iter().enumerate() {
            self.set_duty(i, if self.armed { d } else { 0 });
        }
    }
}

fn scale(mag_q15: u32, max: u32) -> u32 {
    (mag_q15 * max) / DUTY_FULL as u32
}

/// Tension (N) to signed duty: strings only pull, so a tension maps to reeling
/// torque (negative duty = reel in); the gain is duty per newton at the
/// motor's winding radius, measured per device (docs/hardware.md). Open loop
/// on voltage until the drivers give current control.
pub fn tension_to_duty_q15(tension_n: f32, duty_per_newton: f32) -> i16 {
    let t = if tension_n.is_finite() {
        tension_n.max(0.0)
    } else {
        0.0
    };
    let d = (t * duty_per_newton * DUTY_FULL as f32).min(DUTY_FULL as f32);
    -(d as i16)
}
