use nalgebra::DMatrix;
use spidar_core::string_law::EffectContext;
use spidar_core::STRINGS;

use super::evidence::Row;
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

/// One string's rows on the paper's lattice (13^3 cells of 1 m in its
/// order, plane by plane, 80 min with the user's pauses drawn at
/// random) with residual `error(position, t)` (called on the rows in
/// the walk's order) plus 0.2 mm of noise,
/// the model's span its constant (the string's home length), the
/// residual variance that of the noise (the other strings' rows).
pub(super) fn lattice_evidence(error: impl Fn([f64; 3], f64) -> f64) -> Evidence<'static> {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Exp1, StandardNormal};
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(7);
    let lattice = crate::sim::lattice::Lattice::paper([0.0; 3]).unwrap();
    let pause: Vec<f64> = (0..lattice.len()).map(|_| Exp1.sample(&mut rng)).collect();
    let per_pause = 4800.0 / pause.iter().sum::<f64>();
    let ctx = EffectContext {
        theta: 0.0,
        payout_mm: 0.0,
        home_length_mm: 1000.0,
        tension_n: 1.0,
        total_tension_n: 8.0,
        direction: 0,
        time_s: 0.0,
        cos2_inclination: 1.0,
        home_cos2_inclination: 1.0,
        guide_elevation_rad: 0.0,
        home_guide_elevation_rad: 0.0,
        payout_rate_mm_s: 0.0,
    };
    let mut t = 0.0;
    let mut rows = Vec::new();
    let mut residuals = Vec::new();
    for (k, (p, cell)) in pause.iter().zip(lattice.order()).enumerate() {
        let position = lattice.cell_centre(cell);
        t += p * per_pause;
        let noise: f64 = StandardNormal.sample(&mut rng);
        residuals.push(error(position, t) + 0.2 * noise);
        rows.push(Row {
            obs: k,
            string: 0,
            weight: 1.0,
            ctx: EffectContext { time_s: t, ..ctx },
            length: 1000.0,
            speed: 0.0,
            position,
            marker_column: None,
            scale_gradient: 0.0,
        });
    }
    let n = rows.len();
    let basis = DMatrix::from_element(n, 1, 1.0 / (n as f64).sqrt());
    // The noise, as the device's other strings (clean) give it.
    Evidence::of_rows(rows, residuals, basis, 0.2 * 0.2)
}
