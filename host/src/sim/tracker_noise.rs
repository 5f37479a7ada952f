//! The tracker's position noise, as both simulators draw it: a normal of
//! `tracker.noise_sigma_mm` on each axis of every capture and, on a share
//! `tracker.tail_share` of the captures, a further normal of
//! `tracker.tail_sigma_mm` (a marker partly hidden, a reflection beside
//! it, a camera that locates a pose well and now and then poorly: the
//! scatter of a real single-camera reference has heavier tails than one
//! normal). The tail draws come from their own stream, so a session
//! without a tail is the same to the bit as before the tail existed.

use rand::rngs::ChaCha8Rng;
use rand::RngExt;
use rand_distr::{Distribution, Normal};

use super::config::TrackerConfig;
use super::simulated_device::normal;
use super::SimError;
use spidar_core::geometry::Vec3;

/// One session's tracker noise ([`TrackerNoise::offset`]).
pub(crate) struct TrackerNoise {
    base: Normal<f64>,
    /// The share of the captures with the tail, and its normal.
    tail: Option<(f64, Normal<f64>)>,
    tail_rng: ChaCha8Rng,
}

impl TrackerNoise {
    /// The noise `cfg` describes; the tail draws from `tail_rng`.
    pub(crate) fn new(cfg: &TrackerConfig, tail_rng: ChaCha8Rng) -> Result<Self, SimError> {
        let tail = if cfg.tail_share > 0.0 {
            Some((
                cfg.tail_share,
                normal("tracker.tail_sigma_mm", cfg.tail_sigma_mm)?,
            ))
        } else {
            None
        };
        Ok(TrackerNoise {
            base: normal("tracker.noise_sigma_mm", cfg.noise_sigma_mm)?,
            tail,
            tail_rng,
        })
    }

    /// One capture's offset of the measured position from the true one,
    /// mm: the base draws from `rng` (the session's noise stream), the
    /// tail's from its own.
    pub(crate) fn offset(&mut self, rng: &mut ChaCha8Rng) -> Vec3<f64> {
        let base = &self.base;
        let mut offset: Vec3<f64> = core::array::from_fn(|_| base.sample(rng));
        if let Some((share, tail)) = &self.tail {
            if self.tail_rng.random_bool(*share) {
                for x in offset.iter_mut() {
                    *x += tail.sample(&mut self.tail_rng);
                }
            }
        }
        offset
    }
}
