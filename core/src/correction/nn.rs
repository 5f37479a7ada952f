//! The compiled 3-H-3 network, evaluated in place from its bytes.

use super::*;

/// A compiled 3-H-3 network, read in place from its bytes (see
/// [`NN_HEADER_LEN`] for the layout). Positions in and out are Q15.16 mm.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NnView<'a> {
    summary: NnSummary,
    /// `hidden * NN_NEURON_LEN` bytes.
    neurons: &'a [u8],
}

/// Checks that `bytes` is a network of `hidden` neurons, header included.
fn nn_body_len(bytes: &[u8], hidden: u16) -> Result<(), BlobError> {
    let expected = NN_HEADER_LEN + NN_NEURON_LEN * hidden as usize;
    if bytes.len() == expected {
        Ok(())
    } else {
        Err(BlobError::Dimension {
            field: "nn.body_len",
            found: len_u32(bytes.len()),
            expected: len_u32(expected),
        })
    }
}

/// The checked, borrow-free part of an [`NnView`] (see
/// [`NnView::from_summary`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NnSummary {
    mode: OutputMode,
    /// Fractional bits of the first-layer weights (per mm).
    w1_frac: u8,
    /// Fractional bits of the output weights (mm), per axis.
    w2_frac: [u8; 3],
    /// Input mean, Q15.16 mm.
    mean: [i32; 3],
    /// `b2 * std_out + mean_out`, Q15.16 mm.
    offset: [i32; 3],
    hidden: u16,
}

impl<'a> NnView<'a> {
    /// Checks and wraps a compiled network of `hidden` neurons (1 to
    /// [`MAX_HIDDEN_NEURONS`]): exact length,
    /// mode, Q formats in range, every first-layer weight within [`W1_MAX`],
    /// every axis' output weights within [`OUTPUT_ABS_SUM_MAX`] (so that the
    /// evaluation cannot overflow). O(hidden), done once at load.
    pub fn parse(bytes: &'a [u8], hidden: u16) -> Result<NnView<'a>, BlobError> {
        if hidden == 0 {
            return Err(BlobError::Dimension {
                field: "hidden",
                found: 0,
                expected: 1,
            });
        }
        if hidden > MAX_HIDDEN_NEURONS {
            return Err(BlobError::OverBudget {
                field: "nn.hidden",
                found: hidden as u32,
                most: MAX_HIDDEN_NEURONS as u32,
            });
        }
        nn_body_len(bytes, hidden)?;
        let mode = mode_from_byte(bytes[0], "nn.mode")?;
        let w1_frac = bytes[1];
        if !W1_FRAC_RANGE.contains(&w1_frac) {
            return Err(BlobError::Body {
                field: "nn.w1_frac",
            });
        }
        let w2_frac = [bytes[2], bytes[3], bytes[4]];
        if w2_frac.iter().any(|f| !OUTPUT_FRAC_RANGE.contains(f)) {
            return Err(BlobError::Body {
                field: "nn.w2_frac",
            });
        }
        if bytes[5..8] != [0, 0, 0] {
            return Err(BlobError::Body {
                field: "nn.reserved",
            });
        }
        let mean = read3(bytes, 8, "nn.mean")?;
        let offset = read3(bytes, 20, "nn.offset")?;
        let neurons = &bytes[NN_HEADER_LEN..];
        let mut sums = [0u64; 3];
        for rec in neurons.chunks_exact(NN_NEURON_LEN) {
            for i in 0..3 {
                let w = read_i32(rec, 4 * i).ok_or(BlobError::Body { field: "nn.w1" })?;
                if w.unsigned_abs() > W1_MAX as u32 {
                    return Err(BlobError::Body { field: "nn.w1" });
                }
            }
            for (a, sum) in sums.iter_mut().enumerate() {
                let w = read_i32(rec, 16 + 4 * a).ok_or(BlobError::Body { field: "nn.w2" })?;
                *sum += w.unsigned_abs() as u64;
                if *sum > OUTPUT_ABS_SUM_MAX {
                    return Err(BlobError::Body { field: "nn.w2" });
                }
            }
        }
        Ok(NnView {
            summary: NnSummary {
                mode,
                w1_frac,
                w2_frac,
                mean,
                offset,
                hidden,
            },
            neurons,
        })
    }

    /// The borrow-free part of this view.
    pub fn summary(&self) -> NnSummary {
        self.summary
    }

    /// The view again over bytes that [`parse`](Self::parse) checked into
    /// `summary` and that have not changed since: O(1) (the length is
    /// checked, the weights' bounds are not read again). A device tick
    /// rebuilds its view this way; re-parsing cost ~1,150 instructions of
    /// the 25,000-cycle tick.
    pub fn from_summary(summary: &NnSummary, bytes: &'a [u8]) -> Result<NnView<'a>, BlobError> {
        nn_body_len(bytes, summary.hidden)?;
        Ok(NnView {
            summary: *summary,
            neurons: &bytes[NN_HEADER_LEN..],
        })
    }

    /// Number of hidden neurons.
    pub fn hidden(&self) -> usize {
        self.neurons.len() / NN_NEURON_LEN
    }

    /// Output mode of the network.
    pub fn mode(&self) -> OutputMode {
        self.summary.mode
    }

    /// Corrected position (Q15.16 mm) of a position `p` (Q15.16 mm). Integer
    /// only, saturating, never panics.
    pub fn evaluate(&self, p: [i32; 3]) -> [i32; 3] {
        let d0 = p[0].saturating_sub(self.summary.mean[0]) as i64;
        let d1 = p[1].saturating_sub(self.summary.mean[1]) as i64;
        let d2 = p[2].saturating_sub(self.summary.mean[2]) as i64;
        // Q(16 + w1_frac) -> Q5.26: half the pre-activation's scale (see
        // below).
        let sh = (self.summary.w1_frac as u32)
            .wrapping_sub(PREACTIVATION_FRAC - 1 - POSITION_FRAC as u32);
        let mut acc = [0i64; 3];
        for rec in self.neurons.chunks_exact(NN_NEURON_LEN) {
            let Ok(rec) = <&[u8; NN_NEURON_LEN]>::try_from(rec) else {
                continue;
            };
            let pre = (d0 * le_i32::<NN_NEURON_LEN, 0>(rec) as i64)
                .wrapping_add(d1 * le_i32::<NN_NEURON_LEN, 4>(rec) as i64)
                .wrapping_add(d2 * le_i32::<NN_NEURON_LEN, 8>(rec) as i64);
            // `w1 . d` saturates at +-32 (Q5.26), where a bias within +-16
            // cannot bring it back below tanh's +-16, and the sum doubles
            // to Q4.27, saturating: a steep neuron (`w1 . d` of 30, a bias
            // of -14) is at tanh(16), as the host has it, not at tanh(2)
            // (decision record 0081).
            let half =
                shr_sat_i64_to_i32(pre, sh).saturating_add(le_i32::<NN_NEURON_LEN, 12>(rec) >> 1);
            let x = half.saturating_add(half);
            let t = tanh_q27(x) as i64;
            acc[0] = acc[0].wrapping_add(le_i32::<NN_NEURON_LEN, 16>(rec) as i64 * t);
            acc[1] = acc[1].wrapping_add(le_i32::<NN_NEURON_LEN, 20>(rec) as i64 * t);
            acc[2] = acc[2].wrapping_add(le_i32::<NN_NEURON_LEN, 24>(rec) as i64 * t);
        }
        let s = &self.summary;
        [
            finish(acc[0], s.w2_frac[0], s.offset[0], s.mode, p[0]),
            finish(acc[1], s.w2_frac[1], s.offset[1], s.mode, p[1]),
            finish(acc[2], s.w2_frac[2], s.offset[2], s.mode, p[2]),
        ]
    }
}
