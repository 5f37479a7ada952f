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
    use crate::model::{Calibration, Frame, StringLaw};
    let calibration = Calibration {
        frame: Frame {
            room_translation: [0.0; 3],
            ..crate::test_fixtures::cube_frame([0.0; 3])
        },
        strings: [StringLaw::polynomial(4096, [10.0, 0.0, 0.0, 0.0]); crate::STRINGS],
        effects: std::vec![],
        correction: CorrectionModel::None,
        length_scale_mm: [0.0; crate::STRINGS],
        kinematics: Default::default(),
        home: None,
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
        boot_id: 1,
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
