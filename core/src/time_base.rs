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
mod tests {
    use super::*;
    use std::vec::Vec;

    /// Timer kernel clocks per tick (260 MHz timer clock, prescaler 260).
    const CLOCKS_PER_TICK: u64 = 260;
    /// Ticks per wrap of the low counter.
    const LOW_PERIOD: u64 = 1 << 16;

    /// A model of the cascaded counters: time is in timer kernel clocks
    /// since the counters started; the high counter counts a wrap of the low
    /// counter `lag` clocks after it (trigger resynchronization).
    #[derive(Clone, Copy)]
    struct Counters {
        lag: u64,
    }

    impl Counters {
        fn ticks(t: u64) -> u64 {
            t / CLOCKS_PER_TICK
        }
        fn low(&self, t: u64) -> u16 {
            (Self::ticks(t) % LOW_PERIOD) as u16
        }
        fn high(&self, t: u64) -> u16 {
            let seen = Self::ticks(t.saturating_sub(self.lag)) / LOW_PERIOD;
            (seen % (1 << 16)) as u16
        }
        /// The true 32-bit count at `t`.
        fn count(t: u64) -> u32 {
            (Self::ticks(t) % (1 << 32)) as u32
        }
    }

    /// Read times around every kind of wrap: gaps between the three reads of
    /// 1..40 clocks, lags of 0..6 clocks, read times from 2 ticks before to
    /// 2 ticks after a wrap, clock by clock.
    #[test]
    fn combined_count_is_the_count_when_low_was_read() {
        for lag in 0..=6 {
            let hw = Counters { lag };
            for wrap in [1u64, 2, 0x7FFF, 0x8000, 0xFFFF, 0x1_0000] {
                let at = wrap * LOW_PERIOD * CLOCKS_PER_TICK;
                for t1 in (at - 2 * CLOCKS_PER_TICK)..(at + 2 * CLOCKS_PER_TICK) {
                    for gap in [1u64, 2, 3, 5, 8, 13, 40] {
                        let (t2, t3) = (t1 + gap, t1 + 2 * gap);
                        let got = combine_count(hw.high(t1), hw.low(t2), hw.high(t3));
                        match got {
                            Some(c) => {
                                assert_eq!(c, Counters::count(t2), "lag {lag} t {t1} gap {gap}")
                            }
                            None => assert_eq!(hw.low(t2), 0),
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn read_count_retries_until_the_low_counter_moves_on() {
        let hw = Counters { lag: 6 };
        let wrap = 3 * LOW_PERIOD * CLOCKS_PER_TICK;
        // Each read of three registers takes 30 clocks; start just after a
        // wrap that the high counter has already counted: both high reads
        // agree while low reads 0, so the count is read again.
        let mut t = wrap + 7;
        let mut reads = 0;
        let count = read_count(|| {
            let r = (hw.high(t), hw.low(t + 10), hw.high(t + 20));
            t += 30;
            reads += 1;
            r
        });
        assert_eq!(count, Counters::count(t - 20));
        assert_eq!(count, (3 << 16) | 1);
        assert_eq!(reads, 10);
        // Stopped counters: a bounded number of reads, then the last one.
        reads = 0;
        assert_eq!(
            read_count(|| {
                reads += 1;
                (5, 0, 5)
            }),
            5 << 16
        );
        assert_eq!(reads, COMBINE_RETRIES);
    }

    #[test]
    fn extension_never_goes_back_whatever_the_interrupt_delay() {
        // The count crosses 2^31 and 2^32; the interrupt runs `delay` ticks
        // late; `now` is computed at every tick around the crossings.
        for delay in [0u64, 1, 1000, 4_000_000, HALF_RANGE - 1] {
            for crossing in [HALF_RANGE, 2 * HALF_RANGE, 3 * HALF_RANGE] {
                let mut last = 0u64;
                let start = crossing - 3;
                let samples = (0..6).chain([delay, delay + 1, delay + 2]);
                let mut times: Vec<u64> = samples.map(|s| start + s).collect();
                times.sort_unstable();
                for time in times {
                    // Half periods the interrupt has counted by `time`.
                    let seen = |edge: u64| time >= edge + delay;
                    let half_periods = (1..=4).filter(|&k| seen(k * HALF_RANGE)).count() as u32;
                    let now = extend_count(half_periods, time as u32);
                    assert_eq!(now, time, "delay {delay} crossing {crossing}");
                    assert!(now >= last);
                    last = now;
                }
            }
        }
        assert_eq!(half_periods_after(6, true, false), 7);
        assert_eq!(half_periods_after(6, false, false), 6);
        assert_eq!(half_periods_after(u32::MAX, true, false), 0);
    }

    #[test]
    fn alarms_never_fire_early() {
        assert_eq!(plan_alarm(100, 100), AlarmPlan::Due);
        assert_eq!(plan_alarm(100, 99), AlarmPlan::Due);
        assert_eq!(plan_alarm(100, 101), AlarmPlan::OneShot { reload: 1 });
        assert_eq!(plan_alarm(100, 102), AlarmPlan::OneShot { reload: 1 });
        assert_eq!(plan_alarm(100, 200), AlarmPlan::OneShot { reload: 99 });
        assert_eq!(
            plan_alarm(0, MAX_ONE_SHOT),
            AlarmPlan::OneShot { reload: u16::MAX }
        );
        assert_eq!(
            plan_alarm(0, u64::MAX),
            AlarmPlan::OneShot { reload: u16::MAX }
        );
        // Fired = started (>= now) + reload + 1; re-planned until due.
        for (now, at) in [(5u64, 6u64), (0, 100), (7, 65_543), (0, 1_000_000)] {
            let mut started = now;
            let mut wakeups = 0;
            loop {
                match plan_alarm(started, at) {
                    AlarmPlan::Due => break,
                    AlarmPlan::OneShot { reload } => {
                        started += u64::from(reload) + 1;
                        wakeups += 1;
                    }
                }
            }
            assert!(started >= at && started <= at + 1, "{now} {at} {started}");
            assert!(wakeups <= (at - now) / MAX_ONE_SHOT + 1);
        }
    }

    // ---- A model upload: the CPU stalls with interrupts masked -----------

    /// What the CPU sees of a time base, in the firmware's order: the
    /// interrupts that were due run first (unless masked), then `now`.
    trait Clock {
        /// The interrupts run that are pending at `t` (clocks).
        fn service(&mut self, t: u64);
        /// `now()` read at `t` (clocks), ticks.
        fn now(&mut self, t: u64) -> u64;
    }

    /// This time base: the cascaded counters + the half-period interrupt.
    struct Cascade {
        hw: Counters,
        half_periods: u32,
        /// Half periods whose flags the interrupt has cleared.
        serviced: u64,
    }

    impl Clock for Cascade {
        fn service(&mut self, t: u64) {
            // Flags set by the hardware by `t`; one interrupt handles all.
            let halves = Counters::ticks(t) / HALF_RANGE;
            while self.serviced < halves {
                self.serviced += 1;
                let wrapped = self.serviced % 2 == 0;
                self.half_periods = half_periods_after(self.half_periods, wrapped, !wrapped);
            }
        }
        fn now(&mut self, t: u64) -> u64 {
            let p = self.half_periods;
            let mut at = t;
            let hw = self.hw;
            let count = read_count(|| {
                let r = (hw.high(at), hw.low(at + 8), hw.high(at + 16));
                at += 24;
                r
            });
            extend_count(p, count)
        }
    }

    /// embassy-stm32 0.6's 16-bit timer driver (`time_driver/gp16.rs`), the
    /// one the firmware used: a period counter advanced by the update and
    /// the half-way compare interrupts, `now = period << 15 + (cnt ^ parity)`.
    struct Gp16 {
        period: u32,
        /// Update / half-way flags the interrupt has cleared.
        serviced: u64,
    }

    impl Clock for Gp16 {
        fn service(&mut self, t: u64) {
            // At most one update and one half-way flag are pending however
            // long the interrupt was held off: the rest are lost.
            let halves = Counters::ticks(t) / (1 << 15);
            if self.serviced < halves {
                let update_pending = (self.serviced + 1..=halves).any(|h| h % 2 == 0);
                let half_pending = (self.serviced + 1..=halves).any(|h| h % 2 == 1);
                self.period += u32::from(update_pending) + u32::from(half_pending);
                self.serviced = halves;
            }
        }
        fn now(&mut self, t: u64) -> u64 {
            let cnt = (Counters::ticks(t) % LOW_PERIOD) as u32;
            (u64::from(self.period) << 15) + u64::from(cnt ^ ((self.period & 1) << 15))
        }
    }

    /// The loop reads the clock every 100 µs for 1 s, an upload then stalls
    /// the CPU (no fetch, interrupts masked) for `stall_us`, then the loop
    /// goes on for 1 s. Returns the largest |now - true time| (µs) and
    /// whether `now` ever went back.
    fn across_upload(clock: &mut dyn Clock, stall_us: u64) -> (u64, bool) {
        let us = |t: u64| t / CLOCKS_PER_TICK;
        let mut t = 0u64;
        let mut last = 0u64;
        let mut worst = 0u64;
        let mut went_back = false;
        let mut sample = |clock: &mut dyn Clock, t: u64| {
            clock.service(t);
            let now = clock.now(t);
            worst = worst.max(now.abs_diff(us(t)));
            went_back |= now < last;
            last = now;
        };
        for _ in 0..10_000 {
            t += 100 * CLOCKS_PER_TICK;
            sample(clock, t);
        }
        // The upload begins: the erase starts 37 µs into a loop period.
        t += 37 * CLOCKS_PER_TICK + stall_us * CLOCKS_PER_TICK;
        // The erase ends: pending interrupts run first, then the loop.
        sample(clock, t);
        for _ in 0..10_000 {
            t += 100 * CLOCKS_PER_TICK;
            sample(clock, t);
        }
        (worst, went_back)
    }

    /// The acceptance: monotonic and within 1 ms across an upload,
    /// for erase stalls up to the datasheet's 4 s maximum (and far beyond:
    /// 10 minutes), at any phase of the counters' wraps.
    #[test]
    fn the_clock_survives_an_upload() {
        for stall_us in [
            1_000_000,
            2_000_000,
            4_000_000,
            4_000_000 + 32_768,
            600_000_000,
        ] {
            for lag in [0, 3, 6] {
                let mut clock = Cascade {
                    hw: Counters { lag },
                    half_periods: 0,
                    serviced: 0,
                };
                let (worst, went_back) = across_upload(&mut clock, stall_us);
                assert!(!went_back, "stall {stall_us}");
                // Exact to the tick: `now` is the count when low was read.
                assert!(worst <= 1, "stall {stall_us}: off by {worst} µs");
            }
        }
    }

    /// The same upload with the 16-bit driver the firmware had: time loses
    /// all but one wrap of the stall, so it is off by seconds after a 4 s
    /// erase (what this time base fixes).
    #[test]
    fn the_previous_16_bit_time_base_does_not() {
        let mut old = Gp16 {
            period: 0,
            serviced: 0,
        };
        let (worst, _) = across_upload(&mut old, 4_000_000);
        assert!(worst > 3_800_000, "off by {worst} µs");
        // A stall below the 32.8 ms it tolerates is fine.
        let mut old = Gp16 {
            period: 0,
            serviced: 0,
        };
        let (worst, went_back) = across_upload(&mut old, 30_000);
        assert!(worst <= 1 && !went_back);
    }

    // ---- The same through the device: an upload's erase and programming --

    use crate::device::{Device, DeviceConfig, ModelBuffer, TickInput};
    use crate::model_store::{FlashError, ModelFlash, RamFlash, Slot};
    use spidar_protocol::{Request, Response};
    use std::cell::Cell;
    use std::rc::Rc;

    const SLOT: usize = 16 * 1024;

    /// Flash whose erase and programming stall the CPU: the true time
    /// (timer clocks, shared with the test's loop) jumps while nothing runs.
    struct StallingFlash {
        flash: RamFlash<SLOT>,
        time: Rc<Cell<u64>>,
        erase_us: u64,
        word_us: u64,
    }

    impl ModelFlash for StallingFlash {
        const SLOT_LEN: usize = SLOT;
        fn read(&mut self, slot: Slot, offset: usize, buf: &mut [u8]) -> Result<(), FlashError> {
            self.flash.read(slot, offset, buf)
        }
        fn erase(&mut self, slot: Slot) -> Result<(), FlashError> {
            self.time
                .set(self.time.get() + self.erase_us * CLOCKS_PER_TICK);
            self.flash.erase(slot)
        }
        fn write(&mut self, slot: Slot, offset: usize, data: &[u8]) -> Result<(), FlashError> {
            let words = (data.len() / crate::model_store::FLASH_WORD) as u64;
            self.time
                .set(self.time.get() + words * self.word_us * CLOCKS_PER_TICK);
            self.flash.write(slot, offset, data)
        }
    }

    fn blob() -> Vec<u8> {
        use crate::correction::CorrectionModel;
        use crate::model::{Calibration, Frame, StringLaw, StringLayout};
        let h = 1100.0;
        let mut anchors = [[0.0; 3]; crate::STRINGS];
        for (i, a) in anchors.iter_mut().enumerate() {
            *a = [i & 1, i & 2, i & 4].map(|b| if b == 0 { -h } else { h });
        }
        let calibration = Calibration {
            frame: Frame {
                layout: StringLayout::ALL,
                anchors,
                home: [0.0; 3],
                room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                room_translation: [0.0; 3],
                room_scale: 1.0,
            },
            strings: [StringLaw::polynomial(4096, [10.0, 0.0, 0.0, 0.0]); crate::STRINGS],
            effects: std::vec![],
            correction: CorrectionModel::None,
        };
        crate::blob::compile(&calibration, 7, 1_700_000_000).unwrap()
    }

    /// A whole upload (begin: erase 4 s; chunks: 200 µs per flash word;
    /// commit: the record) between control-loop ticks every 100 µs, the time
    /// of every tick and request read from `clock`. Returns the state
    /// frames' `time_us` (what the host sees) with the true time (µs).
    fn upload_through_the_device(clock: &mut dyn Clock) -> Vec<(u64, u64)> {
        let time = Rc::new(Cell::new(0u64));
        let flash = StallingFlash {
            flash: RamFlash::new(),
            time: time.clone(),
            erase_us: 4_000_000,
            word_us: 200,
        };
        let now = |clock: &mut dyn Clock| {
            clock.service(time.get());
            clock.now(time.get())
        };
        let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
        let config = DeviceConfig {
            firmware_version: [0, 1, 0],
            device_id: [7; 12],
            loop_period_us: 100,
            control: crate::control::ControlConfig::default(),
        };
        let raw = [1000u16; crate::STRINGS];
        let start = now(clock);
        let mut dev = Device::new(config, flash, ram.bytes(), spare.bytes(), raw, start).unwrap();
        assert!(matches!(
            dev.handle(&Request::StreamOn { decimation: 1 }, now(clock)),
            Response::Ack
        ));

        let blob = blob();
        let crc = spidar_protocol::blob::CRC32.checksum(&blob);
        let mut requests = std::vec![Request::UploadBegin {
            total_len: blob.len() as u32,
            crc32: crc,
            model_id: 7,
        }];
        let chunk = spidar_protocol::MAX_CHUNK;
        for (k, data) in blob.chunks(chunk).enumerate() {
            requests.push(Request::UploadChunk {
                offset: (k * chunk) as u32,
                data,
            });
        }
        requests.push(Request::UploadCommit { crc32: crc });

        let mut streamed: Vec<(u64, u64)> = Vec::new();
        let mut tick = |dev: &mut Device<'_, StallingFlash>, clock: &mut dyn Clock| {
            time.set(time.get() + 100 * CLOCKS_PER_TICK);
            let now_us = now(clock);
            dev.tick(&TickInput {
                raw_counts: raw,
                now_us,
                estop: false,
            });
            if let Some(state) = dev.state_frame() {
                streamed.push((state.time_us, time.get() / CLOCKS_PER_TICK));
            }
        };
        for _ in 0..1000 {
            tick(&mut dev, clock);
        }
        let mut last = Response::Ack;
        for request in &requests {
            // The link reads the time, then handles the request (which may
            // stall the CPU), then the loop goes on.
            let now_us = now(clock);
            last = dev.handle(request, now_us);
            assert!(!matches!(last, Response::Error(_)), "{request:?}: {last:?}");
            for _ in 0..10 {
                tick(&mut dev, clock);
            }
        }
        assert_eq!(last, Response::Committed { model_id: 7 });
        for _ in 0..1000 {
            tick(&mut dev, clock);
        }

        streamed
    }

    /// This time base through a whole upload: the streamed clock is
    /// monotonic and within 1 ms of the true time throughout.
    #[test]
    fn an_upload_through_the_device_keeps_the_streamed_clock() {
        let mut clock = Cascade {
            hw: Counters { lag: 6 },
            half_periods: 0,
            serviced: 0,
        };
        let streamed = upload_through_the_device(&mut clock);
        // The upload took its 4 s erase and the programming...
        let (first, end) = (streamed[0].1, streamed.last().unwrap().1);
        assert!(end - first > 4_000_000);
        // ...and the streamed clock followed: monotonic, within 1 ms.
        for pair in streamed.windows(2) {
            assert!(pair[1].0 > pair[0].0, "{pair:?}");
        }
        for &(time_us, true_us) in &streamed {
            assert!(time_us.abs_diff(true_us) < 1000, "{time_us} vs {true_us}");
        }
        // The 16-bit time base the firmware had falls seconds behind.
        let mut old = Gp16 {
            period: 0,
            serviced: 0,
        };
        let streamed = upload_through_the_device(&mut old);
        let worst = streamed.iter().map(|&(t, u)| t.abs_diff(u)).max().unwrap();
        assert!(worst > 3_800_000, "off by {worst} µs");
    }
}
