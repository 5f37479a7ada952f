//! Encoder counts: extending a 16-bit hardware counter to a wrap-safe count
//! since home, and the direction of the last motion of a string.
//!
//! Both types are integer only and cheap enough to run on every control-loop
//! iteration. The host uses [`DirectionTracker`] on recorded sessions to
//! derive the direction column, so it must give the same answer on sparse
//! samples as on every-iteration samples (it only compares counts to the last
//! extreme, never to the previous sample).

/// Extends a 16-bit hardware quadrature counter (which wraps) into an `i32`
/// count since home.
///
/// Each [`update`](Self::update) adds the signed 16-bit difference between the
/// new and the previous raw value, so the count is exact as long as fewer than
/// 32768 counts pass between two updates. The count saturates at `i32::MIN` /
/// `i32::MAX` instead of overflowing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EncoderExtender {
    last_raw: u16,
    count: i32,
}

impl EncoderExtender {
    /// Starts at count 0 with the counter reading `raw` (home).
    pub const fn new(raw: u16) -> Self {
        Self {
            last_raw: raw,
            count: 0,
        }
    }

    /// Feeds a new raw counter value; returns the count since home.
    pub fn update(&mut self, raw: u16) -> i32 {
        // Signed 16-bit difference: the shortest way around the wrap.
        let delta = raw.wrapping_sub(self.last_raw) as i16;
        self.last_raw = raw;
        self.count = self.count.saturating_add(i32::from(delta));
        self.count
    }

    /// Count since home (counts; increases as string is paid out).
    pub const fn count(&self) -> i32 {
        self.count
    }

    /// Declares home: the count becomes 0 with the counter reading `raw`.
    pub fn rezero(&mut self, raw: u16) {
        *self = Self::new(raw);
    }
}

/// Direction of the last motion of a string, with a hysteresis so that
/// encoder jitter does not flip it.
///
/// Directions: `+1` paying out (counts increasing), `-1` reeling in (counts
/// decreasing), `0` unknown (no motion since home / [`reset`](Self::reset)).
///
/// Rule: the tracker keeps the extreme count reached in the current direction
/// (the highest count while `+1`, the lowest while `-1`; the reset count while
/// `0`). A new direction is declared only when the count is at least
/// `hysteresis_counts` away from that extreme, against the current direction
/// (or either way while `0`). A hysteresis of 0 behaves like 1: any change of
/// count is a motion. Since only the extreme is compared, sparse samples give
/// the same direction as dense ones whenever the motion between samples is
/// monotonic.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DirectionTracker {
    hysteresis: i64,
    extreme: i32,
    direction: i8,
}

impl DirectionTracker {
    /// A tracker at count 0 with direction unknown. `hysteresis_counts` in counts.
    pub fn new(hysteresis_counts: u32) -> Self {
        Self {
            hysteresis: i64::from(hysteresis_counts.max(1)),
            extreme: 0,
            direction: 0,
        }
    }

    /// Direction unknown again, with `counts` as the reference (home).
    pub fn reset(&mut self, counts: i32) {
        self.extreme = counts;
        self.direction = 0;
    }

    /// Feeds the count since home; returns the direction (+1, -1 or 0).
    pub fn update(&mut self, counts: i32) -> i8 {
        // i64: the difference of two i32 never overflows.
        let away = i64::from(counts) - i64::from(self.extreme);
        match self.direction {
            1 => {
                if away > 0 {
                    self.extreme = counts;
                } else if -away >= self.hysteresis {
                    self.direction = -1;
                    self.extreme = counts;
                }
            }
            -1 => {
                if away < 0 {
                    self.extreme = counts;
                } else if away >= self.hysteresis {
                    self.direction = 1;
                    self.extreme = counts;
                }
            }
            _ => {
                if away >= self.hysteresis {
                    self.direction = 1;
                    self.extreme = counts;
                } else if -away >= self.hysteresis {
                    self.direction = -1;
                    self.extreme = counts;
                }
            }
        }
        self.direction
    }

    /// Current direction (+1, -1 or 0).
    pub const fn direction(&self) -> i8 {
        self.direction
    }

    /// Hysteresis in counts (at least 1).
    pub const fn hysteresis_counts(&self) -> u32 {
        self.hysteresis as u32
    }
}

/// Samples a [`CountRate`] keeps (the window is up to this many
/// [`RATE_SLOT_US`] slots).
pub const RATE_SLOTS: usize = 8;

/// Least device time between two samples a [`CountRate`] keeps, µs.
pub const RATE_SLOT_US: u32 = 400;

/// Shortest window a [`CountRate`] gives a rate over, µs (its window once
/// filled at 10 kHz): until then (home, start) the rate is 0. Over 100 µs
/// one count would be 10,000 counts/s, 1.4 mm of a 7.5 ms latency term.
pub const RATE_MIN_WINDOW_US: u32 = (RATE_SLOTS as u32 - 1) * RATE_SLOT_US;

/// Each string's count rate (counts per second), a windowed difference in
/// device time: the counts now less the counts of the oldest of
/// [`RATE_SLOTS`] kept samples, over the device time between them. A
/// sample is kept when [`RATE_SLOT_US`] have passed since the last one, so
/// the window is 2.8 to 3.2 ms at the loop's 10 kHz (7 to 8 ms at 1 kHz).
///
/// What a latency term reads ([`crate::model::StringInputs::count_rate_cps`]).
/// Its own delay is half its window (the rate is the mean over it: about
/// 1.5 ms at 10 kHz); its noise is one count over the window (one count in
/// 3 ms: 330 counts/s, 5 mm/s on a 12 mm spool of 4096 counts a turn, 0.03
/// mm of a 6 ms latency). Integer only, one 32-bit division a call.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CountRate {
    counts: [[i32; crate::STRINGS]; RATE_SLOTS],
    time_us: [u32; RATE_SLOTS],
    /// The slot written last; the oldest is the one after it.
    last: usize,
}

impl CountRate {
    /// Every slot at `counts` at device time `now_us` (a rate of 0 until
    /// the strings move).
    pub fn new(counts: [i32; crate::STRINGS], now_us: u32) -> Self {
        Self {
            counts: [counts; RATE_SLOTS],
            time_us: [now_us; RATE_SLOTS],
            last: 0,
        }
    }

    /// Starts again from `counts` at `now_us` (home: the counts restart).
    pub fn reset(&mut self, counts: [i32; crate::STRINGS], now_us: u32) {
        *self = Self::new(counts, now_us);
    }

    /// Feeds the counts at device time `now_us` (wrapping µs): kept when
    /// [`RATE_SLOT_US`] have passed since the last sample kept.
    #[inline]
    pub fn update(&mut self, counts: &[i32; crate::STRINGS], now_us: u32) {
        if now_us.wrapping_sub(self.time_us[self.last]) >= RATE_SLOT_US {
            self.last = (self.last + 1) % RATE_SLOTS;
            self.counts[self.last] = *counts;
            self.time_us[self.last] = now_us;
        }
    }

    /// Each string's rate (counts/s) at `counts` and `now_us` against the
    /// oldest sample kept: `(counts - old) 10^6 / (now - then)`, through
    /// `4.096e9 / dt` (one 32-bit division) and a 64-bit product, rounded,
    /// saturating; 0 until the window spans [`RATE_MIN_WINDOW_US`].
    pub fn rates(&self, counts: &[i32; crate::STRINGS], now_us: u32) -> [i32; crate::STRINGS] {
        let oldest = (self.last + 1) % RATE_SLOTS;
        let dt = now_us.wrapping_sub(self.time_us[oldest]);
        if dt < RATE_MIN_WINDOW_US {
            return [0; crate::STRINGS];
        }
        // 10^6 2^12 / dt fits a u32 for every dt >= 1.
        let scale = i64::from(4_096_000_000u32 / dt);
        let old = &self.counts[oldest];
        core::array::from_fn(|i| {
            // |moved| <= 2^31 and scale < 2^32: |moved scale| < 2^63.
            let moved = i64::from(counts[i].saturating_sub(old[i]));
            ((moved * scale + (1 << 11)) >> 12).clamp(i64::from(i32::MIN), i64::from(i32::MAX))
                as i32
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A string moving at a constant rate reads that rate once the window
    /// has filled, in device time (10 kHz or 1 kHz ticks, across the µs
    /// clock's wrap), 0 at rest, after a reset and over too short a window;
    /// extremes saturate.
    #[test]
    fn count_rate_is_the_rate_over_its_window() {
        for (period_us, start_us) in [(100u32, 0u32), (1000, 5), (100, u32::MAX - 3_000)] {
            // 25,000 counts/s paying out on string 0, reeling in on 7.
            let at = |k: u32| {
                let t = f64::from(k * period_us) * 1e-6;
                let mut c = [0i32; crate::STRINGS];
                c[0] = (25_000.0 * t).round() as i32;
                c[7] = (-12_500.0 * t).round() as i32;
                c
            };
            let mut rate = CountRate::new(at(0), start_us);
            let mut last = [0; crate::STRINGS];
            for k in 1..200 {
                let now = start_us.wrapping_add(k * period_us);
                rate.update(&at(k), now);
                last = rate.rates(&at(k), now);
            }
            assert!((last[0] - 25_000).abs() <= 400, "{period_us}: {last:?}");
            assert!((last[7] + 12_500).abs() <= 400, "{period_us}: {last:?}");
            assert_eq!(last[1], 0);
            rate.reset([0; crate::STRINGS], 7);
            assert_eq!(rate.rates(&[0; crate::STRINGS], 7), [0; crate::STRINGS]);
        }
        // Too short a window gives 0, not one count over 100 µs.
        let rate = CountRate::new([0; crate::STRINGS], 0);
        assert_eq!(rate.rates(&[1; crate::STRINGS], 100), [0; crate::STRINGS]);
        let mut rate = CountRate::new([i32::MIN; crate::STRINGS], 0);
        let w = RATE_MIN_WINDOW_US;
        rate.update(&[i32::MAX; crate::STRINGS], w);
        assert_eq!(
            rate.rates(&[i32::MAX; crate::STRINGS], w),
            [i32::MAX; crate::STRINGS]
        );
    }

    #[test]
    fn extender_wraps_both_ways() {
        let mut e = EncoderExtender::new(65530);
        assert_eq!(e.update(4), 10);
        assert_eq!(e.update(65534), 4);
        assert_eq!(e.update(65520), -10);
        assert_eq!(e.count(), -10);
        e.rezero(100);
        assert_eq!(e.count(), 0);
        assert_eq!(e.update(90), -10);
    }

    #[test]
    fn extender_saturates() {
        let mut e = EncoderExtender::new(0);
        let mut raw: u16 = 0;
        for _ in 0..70_000 {
            raw = raw.wrapping_add(32767);
            e.update(raw);
        }
        assert_eq!(e.count(), i32::MAX);
        raw = raw.wrapping_sub(10);
        assert_eq!(e.update(raw), i32::MAX - 10);
    }

    #[test]
    fn direction_with_hysteresis() {
        let mut d = DirectionTracker::new(3);
        assert_eq!(d.update(0), 0);
        assert_eq!(d.update(2), 0); // jitter at home
        assert_eq!(d.update(-2), 0);
        assert_eq!(d.update(3), 1);
        assert_eq!(d.update(100), 1);
        assert_eq!(d.update(98), 1); // jitter below the extreme
        assert_eq!(d.update(99), 1);
        assert_eq!(d.update(97), -1);
        assert_eq!(d.update(50), -1);
        assert_eq!(d.update(52), -1);
        assert_eq!(d.update(53), 1);
        d.reset(53);
        assert_eq!(d.direction(), 0);
        assert_eq!(d.update(50), -1);
    }

    #[test]
    fn direction_extremes_do_not_overflow() {
        let mut d = DirectionTracker::new(u32::MAX);
        assert_eq!(d.update(i32::MAX), 0);
        assert_eq!(d.update(i32::MIN), 0);
        let mut d = DirectionTracker::new(0);
        assert_eq!(d.hysteresis_counts(), 1);
        assert_eq!(d.update(i32::MAX), 1);
        assert_eq!(d.update(i32::MIN), -1);
    }

    proptest! {
        #[test]
        fn random_walk_through_wraps(start in any::<u16>(),
                                     steps in proptest::collection::vec(-32767i32..=32767, 0..400)) {
            let mut e = EncoderExtender::new(start);
            let mut truth: i64 = 0;
            let mut raw = start;
            for s in steps {
                truth += i64::from(s);
                raw = raw.wrapping_add(s as u16);
                let c = e.update(raw);
                prop_assert_eq!(i64::from(c), truth);
            }
        }

        /// Sparse sampling of a monotonic-between-samples walk gives the same
        /// direction as dense sampling.
        #[test]
        fn direction_sparse_equals_dense(h in 0u32..50,
                                         legs in proptest::collection::vec(-500i32..500, 1..20),
                                         every in 1usize..7) {
            let mut dense = DirectionTracker::new(h);
            let mut sparse = DirectionTracker::new(h);
            let mut c = 0i32;
            // Sample the sparse tracker at every leg end (turning points) and
            // every `every` counts in between.
            for leg in legs {
                let step = leg.signum();
                for k in 0..leg.abs() {
                    c += step;
                    dense.update(c);
                    if (k as usize) % every == 0 {
                        sparse.update(c);
                    }
                }
                sparse.update(c);
                prop_assert_eq!(dense.direction(), sparse.direction());
            }
        }
    }
}
