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

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

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
