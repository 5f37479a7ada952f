use spidar_core::model::{Effect, EffectTerm};
use spidar_core::STRINGS;

use super::*;

/// A change that would give the model more effect terms than the
/// device's blob holds is refused, saying so.
#[test]
fn a_model_beyond_the_device_s_effect_terms_is_refused() {
    let slips = |n: usize| Structure {
        effects: (0..n)
            .map(|k| EffectTerm {
                string: (k % STRINGS) as u8,
                effect: Effect::Slip {
                    at_s: k as f64,
                    mm: 1.0,
                },
            })
            .collect(),
        ..Structure::default()
    };
    assert_eq!(beyond_the_device(&slips(MAX_EFFECTS)), None);
    let reason = beyond_the_device(&slips(MAX_EFFECTS + 1)).unwrap();
    assert!(
        reason.contains("33 effect terms") && reason.contains("at most 32"),
        "{reason}"
    );
}
