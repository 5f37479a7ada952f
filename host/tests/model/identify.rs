//! Identification on simulated sessions: the paper-sized raw error falls to
//! the tracker's noise, parameters come with uncertainties, and data that
//! cannot determine a parameter produce a warning naming it.

use spidar::data::observe::observations;
use spidar::model::identify::{identify, Start, Structure};
use spidar::sim::{simulate_session, SessionKind, SimConfig, SimulatedDevice};
use spidar_core::model::{Effect, EffectTerm};

fn lattice(
    seed: u64,
) -> (
    Vec<spidar::data::observe::Observation>,
    spidar::data::dataset::Geometry,
) {
    let config = SimConfig::default();
    let device = SimulatedDevice::new(&config, seed).expect("device");
    let session = simulate_session(&device, SessionKind::Lattice, seed + 100).expect("lattice");
    (observations(&session.samples), config.nominal.geometry())
}

#[test]
fn a_full_lattice_determines_every_parameter() {
    let (obs, geometry) = lattice(1);
    let id = identify(
        &obs,
        &geometry.nominal_frame(),
        &Start::from_geometry(&geometry),
        &Structure::default(),
    )
    .expect("identifies");
    assert!(id.warnings.is_empty(), "{:?}", id.warnings);
    assert!(id
        .parameters
        .iter()
        .all(|p| p.determined && p.sd.is_finite()));
    // String residuals at the tracker's noise (0.2 mm per axis).
    assert!(id.residual_scale_mm < 0.3, "{}", id.residual_scale_mm);
}

#[test]
fn an_effect_the_data_cannot_show_is_reported_as_undetermined() {
    // Elasticity needs tension; a session recorded without tension columns
    // cannot determine it (the observations read tension 0).
    let config = SimConfig::default();
    let device = SimulatedDevice::new(&config, 1).expect("device");
    let mut session = simulate_session(&device, SessionKind::Lattice, 101).expect("lattice");
    for s in session.samples.iter_mut() {
        s.tension_n = None;
    }
    let obs = observations(&session.samples);
    let geometry = config.nominal.geometry();
    let structure = Structure {
        effects: vec![EffectTerm {
            string: 2,
            effect: Effect::Elasticity { per_newton: 0.0 },
        }],
        ..Structure::default()
    };
    let id = identify(
        &obs,
        &geometry.nominal_frame(),
        &Start::from_geometry(&geometry),
        &structure,
    )
    .expect("identifies");
    let elasticity = id
        .parameters
        .iter()
        .find(|p| p.name == "string2.elasticity")
        .expect("parameter listed");
    assert!(!elasticity.determined, "{elasticity:?}");
    assert!(
        id.warnings.iter().any(|w| w.contains("string2.elasticity")),
        "{:?}",
        id.warnings
    );
    // The rest of the model is unaffected.
    assert!(id
        .parameters
        .iter()
        .filter(|p| p.name != "string2.elasticity")
        .all(|p| p.determined));
}
