//! Independent watchdog (IWDG1, clocked by the 32 kHz LSI).
//!
//! Started in `main` with [`NORMAL_TIMEOUT_MS`] and fed by the control loop
//! every iteration: if the loop stops (hang, fault, overrun storm) the MCU
//! resets, every timer output goes high-impedance and the motor drivers'
//! pull-downs stop the motors (docs/hardware.md).
//!
//! Erasing a 128 KiB flash sector stalls every flash read (so the whole
//! program) for up to ~2 s on this single-bank part; [`set_timeout_ms`] lets
//! the storage code stretch the timeout around an erase, which it only does
//! with the motors disarmed. Free functions on the register block rather than
//! embassy's `IndependentWatchdog` because two tasks need them.

use embassy_stm32::pac;
use embassy_stm32::pac::iwdg::vals::{Key, Pr};

/// Timeout while the control loop runs.
pub const NORMAL_TIMEOUT_MS: u32 = 50;
/// Timeout around a flash sector erase (max erase time of a 128 KiB sector
/// with margin; see docs/hardware.md).
pub const FLASH_ERASE_TIMEOUT_MS: u32 = 8_000;

const LSI_HZ: u32 = 32_000;

/// Prescaler and reload for a timeout, the smallest prescaler that fits.
fn divider(timeout_ms: u32) -> (Pr, u16) {
    const PRS: [(Pr, u32); 7] = [
        (Pr::DIVIDE_BY4, 4),
        (Pr::DIVIDE_BY8, 8),
        (Pr::DIVIDE_BY16, 16),
        (Pr::DIVIDE_BY32, 32),
        (Pr::DIVIDE_BY64, 64),
        (Pr::DIVIDE_BY128, 128),
        (Pr::DIVIDE_BY256, 256),
    ];
    for (pr, div) in PRS {
        let ticks = (timeout_ms as u64 * LSI_HZ as u64) / (1000 * div as u64);
        if ticks <= 0xFFF {
            return (pr, ticks.max(1) as u16);
        }
    }
    (Pr::DIVIDE_BY256, 0xFFF)
}

fn configure(timeout_ms: u32) {
    let (pr, rl) = divider(timeout_ms);
    let w = pac::IWDG1;
    w.kr().write(|r| r.set_key(Key::ENABLE));
    w.pr().write(|r| r.set_pr(pr));
    w.rlr().write(|r| r.set_rl(rl));
    // Wait until the new prescaler and reload have reached the LSI domain
    // (a few LSI periods).
    while w.sr().read().pvu() || w.sr().read().rvu() {}
    w.kr().write(|r| r.set_key(Key::RESET));
}

/// Starts the watchdog. It cannot be stopped until reset.
pub fn start(timeout_ms: u32) {
    pac::IWDG1.kr().write(|r| r.set_key(Key::START));
    configure(timeout_ms);
}

/// Reloads the counter.
pub fn feed() {
    pac::IWDG1.kr().write(|r| r.set_key(Key::RESET));
}

/// Changes the timeout of the running watchdog (and feeds it).
pub fn set_timeout_ms(timeout_ms: u32) {
    configure(timeout_ms);
}
