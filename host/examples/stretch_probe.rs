// Scratch: the identification's shared elasticity on a clean independent
// device (lattice), against the truths (mean 1/EA, mean (lead + arc) / EA,
// the home tension), and the shared sag beside it.
//
// `cargo run --release -p spidar --example stretch_probe -- SEED`
use spidar::identify::{identify, Start, Structure};
use spidar::observe::observations;
use spidar::sim::physics::{self, PhysicsConfig, PhysicsDevice};
use spidar::sim::SessionKind;
use spidar_core::model::{Effect, EffectTerm, EVERY_STRING};

fn main() {
    let seed: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse().unwrap())
        .unwrap_or(1);
    let device = PhysicsDevice::new(&PhysicsConfig::default(), seed).unwrap();
    let (train, _) = physics::simulate_session(&device, SessionKind::Lattice, seed + 1).unwrap();
    let n = device.string_count();
    let th = device.home_tension_n;
    let (mut k, mut m) = (0.0, 0.0);
    for i in 0..n {
        let s = &device.strings[i];
        let home = device
            .natural_length(i, &device.home_mm, th, th * n as f64, 0.0)
            .unwrap();
        let arc = home.path.length_mm - home.path.free_mm;
        k += 1.0 / s.stiffness_n / n as f64;
        m += (s.lead_mm + arc) / s.stiffness_n / n as f64;
    }
    println!(
        "seed {seed} truth: mean 1/EA {k:.3e}, mean (lead + arc)/EA {m:.4} mm/N, home tension {th}"
    );
    let obs = observations(&train.samples);
    let nominal = device.nominal.nominal_frame();
    let start = Start::from_geometry(&device.nominal);
    let elasticity = EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Elasticity {
            per_newton: 5e-5,
            mm_per_newton: 0.01,
            home_tension_n: 1.0,
        },
    };
    let free_span_only = EffectTerm {
        string: EVERY_STRING,
        effect: Effect::elasticity(5e-5),
    };
    let sag = EffectTerm {
        string: EVERY_STRING,
        effect: Effect::Sag {
            mm_at_1m_1n: 0.0,
            home_mm_at_1m: 0.0,
        },
    };
    let variants: Vec<(&str, Vec<EffectTerm>)> = vec![
        ("none", vec![]),
        ("sag", vec![sag]),
        ("elasticity (free start 0,0)", vec![free_span_only]),
        ("elasticity", vec![elasticity]),
        ("elasticity + sag", vec![elasticity, sag]),
    ];
    for (name, effects) in variants {
        let structure = Structure {
            effects,
            ..Structure::default()
        };
        let id = identify(&obs, &nominal, &start, &structure).unwrap();
        let ps: Vec<String> = id
            .parameters
            .iter()
            .filter(|p| p.name.contains("elasticity") || p.name.contains("sag"))
            .map(|p| format!("{} {:.4e} (sd {:.1e})", p.name, p.value, p.sd))
            .collect();
        println!(
            "{name:30} residual scale {:.4} mm  {}",
            id.residual_scale_mm,
            ps.join(", ")
        );
    }
}
