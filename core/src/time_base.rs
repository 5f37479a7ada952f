//! The firmware's time base: µs since boot from two cascaded 16-bit hardware
//! timers, extended to 64 bits, and the arithmetic of its one-shot alarm.
//!
//! Why (docs/hardware.md, "Time base"): a model upload erases a flash sector
//! of the bank the program runs from. For the whole erase (up to ~4 s) every
//! instruction fetch stalls and, because the erase runs under the device
//! lock, interrupts are masked too. A time base that needs an interrupt
//! every half wrap of a 16-bit counter (embassy's 16-bit timer drivers: every
//! 32.8 ms at 1 MHz) loses those wraps and steps. Here the *hardware* keeps
//! the count across the stall:
//!
//! - the **low counter** (TIM13) counts µs and wraps every 65.536 ms; its
//!   compare output rises at each wrap;
//! - the **high counter** (TIM12, external clock mode from that output
//!   through its internal trigger input) counts the wraps;
//! - together a 32-bit count of µs that wraps every 71.6 minutes. Software
//!   extends it to 64 bits with a half-period counter that an interrupt
//!   advances at each half of the 32-bit range (every 35.8 minutes), so the
//!   interrupts may be held off for up to 35 minutes without a step;
//! - the **alarm** is a third timer (TIM14) run as a one-shot for
//!   `min(at - now, 65 536)` µs, started after `now` was read, so it never
//!   fires before `at` and needs no periodic interrupt.
//!
//! Everything here is pure (no registers): the firmware's time driver
//! (`firmware/src/time_driver.rs`) reads the registers and calls these
//! functions; the tests below drive them through a model of the timers,
//! including an upload that stalls the CPU with interrupts masked.

/// Ticks of the time base per second (1 µs ticks, embassy's `tick-hz-1_000_000`).
pub const TICK_HZ: u64 = 1_000_000;

/// One half of the 32-bit hardware count: the interrupt that extends the
/// count to 64 bits must run at least once per this many ticks (35.8 min).
pub const HALF_RANGE: u64 = 1 << 31;

/// Longest one-shot alarm the 16-bit alarm timer runs (ticks). A later
/// alarm fires after this long and is planned again from the interrupt.
pub const MAX_ONE_SHOT: u64 = 1 << 16;

/// How many times [`read_count`] reads the counters again when a read falls
/// right on a wrap of the low counter (see [`combine_count`]). One retry
/// suffices once the low counter has moved on (1 µs); the bound only
/// matters if the counters are stopped.
pub const COMBINE_RETRIES: u32 = 64;

/// The 32-bit count from the high counter read before the low counter
/// (`high_before`), the low counter, and the high counter read after it
/// (`high_after`): the count at the moment `low` was read.
///
/// The high counter counts wraps of the low counter a few timer clocks
/// *after* the wrap (its trigger input is resynchronized), so a read pair
/// can be torn either way. Assuming the three reads take less than half a
/// low period (32.8 ms):
/// - `low >= 0x8000`: the last wrap was more than 32 768 µs before `low`
///   was read, so before `high_before` too, and the next one after: use
///   `high_before`;
/// - `1 <= low < 0x8000`: the last wrap was at least 1 µs (far more than
///   the trigger delay) before `low` was read, the next one is half a period
///   away: use `high_after`;
/// - `low == 0` and both high reads equal: the wrap happened less than 1 µs
///   before; whether the high counter has counted it yet is unknown:
///   `None`, read again (after the low counter moves on, 1 µs).
pub fn combine_count(high_before: u16, low: u16, high_after: u16) -> Option<u32> {
    let high = if low >= 0x8000 {
        high_before
    } else if low == 0 && high_before == high_after {
        return None;
    } else {
        high_after
    };
    Some((u32::from(high) << 16) | u32::from(low))
}

/// Reads the 32-bit count with `read`, which returns (high, low, high) read
/// in that order, until [`combine_count`] can tell (at most
/// [`COMBINE_RETRIES`] reads; counters that never move give the last read
/// taken as wrapped, i.e. `high_after`).
pub fn read_count(mut read: impl FnMut() -> (u16, u16, u16)) -> u32 {
    let mut last = (0, 0, 0);
    for _ in 0..COMBINE_RETRIES {
        last = read();
        if let Some(count) = combine_count(last.0, last.1, last.2) {
            return count;
        }
    }
    u32::from(last.2) << 16
}

/// The 64-bit time (ticks since boot) from the number of half periods of the
/// 32-bit count the interrupt has seen (`half_periods`, read *before* the
/// count) and the 32-bit `count`.
///
/// `half_periods` is even while the count is in `0..2^31` and odd in
/// `2^31..2^32`. A count in the other half than the parity says means a half
/// period started after `half_periods` was read (or its interrupt is still
/// pending): the count is taken as the next half, so the result never goes
/// back. Valid while the interrupt runs within 2^31 ticks (35.8 min) of each
/// half period's start. Wraps after 2^32 * 2^31 µs (292 000 years).
pub fn extend_count(half_periods: u32, count: u32) -> u64 {
    let parity = (half_periods & 1) << 31;
    (u64::from(half_periods) << 31) + u64::from(count ^ parity)
}

/// What the half-period interrupt adds to the half-period counter for the
/// events it found flagged: the 32-bit count wrapped to 0 (`wrapped`) and/or
/// passed 2^31 (`passed_half`). Both at once only if the interrupt was held
/// off for more than a half period (the count is then one half behind, which
/// the parity of [`extend_count`] cannot tell: a documented limit, 35.8 min).
pub fn half_periods_after(half_periods: u32, wrapped: bool, passed_half: bool) -> u32 {
    half_periods
        .wrapping_add(u32::from(wrapped))
        .wrapping_add(u32::from(passed_half))
}

/// What to do for an alarm at `at` when the time is `now`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AlarmPlan {
    /// `at` has passed (or is now): run the expired timers, no alarm.
    Due,
    /// Start the one-shot alarm timer with this auto-reload value: it counts
    /// `0..=reload` and fires `reload + 1` ticks after it is started.
    OneShot { reload: u16 },
}

/// Plans the alarm at `at` (ticks) at time `now`.
///
/// The one-shot fires `reload + 1 = min(at - now, 2^16)` ticks after it is
/// started (at least 2: an auto-reload of 0 stops a timer). Since the timer
/// is started after `now` was read, it fires at or after `at` (never early),
/// late by at most 1 tick plus the time from reading `now` to starting it.
/// An alarm more than 65.536 ms away fires early as a wake-up; the
/// interrupt then finds nothing due and plans it again.
pub fn plan_alarm(now: u64, at: u64) -> AlarmPlan {
    if at <= now {
        return AlarmPlan::Due;
    }
    let ticks = (at - now).min(MAX_ONE_SHOT);
    let reload = ticks.saturating_sub(1).clamp(1, u64::from(u16::MAX));
    AlarmPlan::OneShot {
        reload: reload as u16,
    }
}

#[cfg(test)]
mod tests;
