//! What one tick of the device's control loop costs, estimated from what a
//! model blob holds, and the budget it must stay within.
//!
//! The reference device (STM32H723 at 550 MHz, about one instruction a
//! cycle) runs its loop at 10 kHz: a tick has 100 µs, [`TICK_BUDGET`]
//! instructions (decision record 0002). What a tick costs grows with the
//! model: each effect term the string law evaluates, each training slip,
//! and above all the position correction. The device refuses a blob whose
//! estimate is over the budget (`BlobError::OverBudget`, field `tick`), the
//! compiler refuses to make one, and the host sizes the learned correction
//! to what the model leaves of the budget.
//!
//! The figures are instruction counts under QEMU (`scripts/qemu-bench`, the
//! rows `tick cost, Controller::step: ...`; decision record 0068): the most
//! over 32 calls of `Controller::step` with the benchmark's frame and
//! layered laws and nothing else (the bare model), and what each family of
//! effect terms, on each of the 8 strings or shared by every string, adds
//! to that most. Every figure is rounded up to the next 10. The bench
//! measures `Device::tick` with its two models (18 terms, 8 training slips,
//! an NN or an SVR of [`MAX_SUPPORT_VECTORS`](crate::correction::MAX_SUPPORT_VECTORS))
//! against this estimate as its target, so a change of the code that makes
//! a tick cost more than the estimate says fails the test command.

use crate::blob::BlobHead;
use crate::model::EVERY_STRING;
use crate::string_law::CompiledEffect;
use spidar_protocol::blob::CorrectionKind;

/// Instructions a tick may take: 100 µs at 550 MHz, one instruction a
/// cycle (decision record 0002).
pub const TICK_BUDGET: u32 = 55_000;

/// A tick whose model has no effect term, no training slip and no
/// correction, on 8 strings with layer tables (the most measured, 15,890,
/// and `Device::tick`'s own work beside `Controller::step`, 372 at most).
pub const BARE_TICK: u32 = 16_270;

/// Each training slip applied under the device's home capture (8: 179).
pub const PER_SLIP: u32 = 30;

/// The NN correction: a fixed part and each hidden neuron (3-20-3: 1,438;
/// 63 instructions a neuron, `docs/fixed-point.md`).
pub const NN_BASE: u32 = 200;
/// See [`NN_BASE`].
pub const PER_NEURON: u32 = 64;

/// The SVR correction: a fixed part and each support vector (1,000:
/// 24,017; 23 instructions a support vector in the inner loop, and the
/// blocks' own).
pub const SVR_BASE: u32 = 200;
/// See [`SVR_BASE`].
pub const PER_SUPPORT_VECTOR: u32 = 24;

/// What an effect term adds to a tick: the family's cost on one string, or
/// shared by every string. A stretch compiles to an elasticity term with a
/// lead part; both are counted at the stretch's cost.
pub fn term_instructions(effect: &CompiledEffect) -> u32 {
    let shared = effect.string() == EVERY_STRING;
    // (one string, shared by every string): the measured row less the bare
    // model's, one string's an eighth of its row's.
    let (one, every) = match effect {
        CompiledEffect::Offset { .. } => (70, 320),
        CompiledEffect::Scale { .. } => (100, 570),
        CompiledEffect::Winding { .. } => (180, 1_410),
        CompiledEffect::Eccentricity { .. } => (230, 1_790),
        CompiledEffect::Elasticity { .. } => (210, 1_370),
        CompiledEffect::Backlash { .. } => (90, 440),
        CompiledEffect::Drift { .. } => (100, 570),
        CompiledEffect::Creep { .. } => (140, 820),
        CompiledEffect::Slip { .. } => (60, 250),
        CompiledEffect::Sag { .. } => (490, 3_710),
        CompiledEffect::FrameFlex { .. } => (100, 500),
        CompiledEffect::Latency { .. } => (200, 1_380),
        CompiledEffect::Guide { .. } => (670, 5_340),
    };
    if shared {
        every
    } else {
        one
    }
}

/// What the position correction adds to a tick.
pub fn correction_instructions(kind: CorrectionKind, hidden: u16, support_vectors: u32) -> u32 {
    match kind {
        CorrectionKind::None => 0,
        CorrectionKind::Nn => NN_BASE.saturating_add(PER_NEURON.saturating_mul(u32::from(hidden))),
        CorrectionKind::Svr => {
            SVR_BASE.saturating_add(PER_SUPPORT_VECTOR.saturating_mul(support_vectors))
        }
    }
}

/// A tick's instructions with the model of `head` and no correction.
pub fn model_instructions(head: &BlobHead) -> u32 {
    let terms = head
        .effects
        .iter()
        .fold(0u32, |sum, e| sum.saturating_add(term_instructions(e)));
    let slips = head.home.as_ref().map_or(0, |h| h.slips.len() as u32);
    BARE_TICK
        .saturating_add(terms)
        .saturating_add(PER_SLIP.saturating_mul(slips))
}

/// A tick's instructions with the model of `head` and its correction.
pub fn tick_instructions(
    head: &BlobHead,
    kind: CorrectionKind,
    hidden: u16,
    support_vectors: u32,
) -> u32 {
    model_instructions(head).saturating_add(correction_instructions(kind, hidden, support_vectors))
}

/// The estimate of [`tick_instructions`] when it is over [`TICK_BUDGET`]:
/// a model the device must not run.
pub fn over_budget(
    head: &BlobHead,
    kind: CorrectionKind,
    hidden: u16,
    support_vectors: u32,
) -> Option<u32> {
    let tick = tick_instructions(head, kind, hidden, support_vectors);
    (tick > TICK_BUDGET).then_some(tick)
}

/// The most support vectors an SVR may have beside a model whose tick
/// takes `model` instructions without a correction, within
/// [`TICK_BUDGET`] (and at most
/// [`MAX_SUPPORT_VECTORS`](crate::correction::MAX_SUPPORT_VECTORS)); 0 when
/// the model leaves no room for one.
pub fn support_vectors_left(model: u32) -> u32 {
    let left = TICK_BUDGET.saturating_sub(model).saturating_sub(SVR_BASE);
    (left / PER_SUPPORT_VECTOR).min(crate::correction::MAX_SUPPORT_VECTORS)
}

/// The most hidden neurons an NN may have beside a model whose tick takes
/// `model` instructions without a correction, within [`TICK_BUDGET`] (and
/// at most [`MAX_HIDDEN_NEURONS`](crate::correction::MAX_HIDDEN_NEURONS)).
pub fn neurons_left(model: u32) -> u16 {
    let left = TICK_BUDGET.saturating_sub(model).saturating_sub(NN_BASE);
    (left / PER_NEURON).min(u32::from(crate::correction::MAX_HIDDEN_NEURONS)) as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a correction may be beside a model: as much as the budget
    /// leaves, at most the most a blob takes, nothing beyond the budget.
    #[test]
    fn the_room_a_correction_has_is_what_the_model_leaves_of_the_budget() {
        use crate::correction::{MAX_HIDDEN_NEURONS, MAX_SUPPORT_VECTORS};
        assert_eq!(support_vectors_left(BARE_TICK), MAX_SUPPORT_VECTORS);
        assert_eq!(neurons_left(BARE_TICK), MAX_HIDDEN_NEURONS);
        assert_eq!(
            support_vectors_left(50_000),
            (5_000 - SVR_BASE) / PER_SUPPORT_VECTOR
        );
        assert_eq!(
            u32::from(neurons_left(50_000)),
            (5_000 - NN_BASE) / PER_NEURON
        );
        assert_eq!(support_vectors_left(TICK_BUDGET), 0);
        assert_eq!(neurons_left(TICK_BUDGET + 1), 0);
        // The room, filled, is within the budget; one more is not.
        for model in [BARE_TICK, 40_000, 54_000] {
            let sv = support_vectors_left(model);
            let fill = model + correction_instructions(CorrectionKind::Svr, 0, sv);
            assert!(fill <= TICK_BUDGET, "{model}");
            if sv < crate::correction::MAX_SUPPORT_VECTORS {
                let over = model + correction_instructions(CorrectionKind::Svr, 0, sv + 1);
                assert!(over > TICK_BUDGET, "{model}");
            }
            let h = neurons_left(model);
            assert!(model + correction_instructions(CorrectionKind::Nn, h, 0) <= TICK_BUDGET);
        }
    }
}
