//! Runs the diagnosis loop on a simulated device with injected effects:
//! `cargo run --release -p spidar --example loop_check -- SEED [EFFECT_SPEC ...]`
use spidar::diagnose::{close_loop, family_name, variable_name, LoopConfig};
use spidar::identify::Start;
use spidar::observe::observations;
use spidar::sim::config::SimConfig;
use spidar::sim::{simulate_session, Device, SessionKind};

fn main() {
    let mut args = std::env::args().skip(1);
    let seed: u64 = args.next().map(|s| s.parse().unwrap()).unwrap_or(1);
    let mut config = SimConfig::default();
    config.effects = args.collect();
    let device = Device::new(&config, seed).unwrap();
    let geometry = config.nominal.geometry();
    let train = simulate_session(&device, SessionKind::Lattice, seed + 100).unwrap();
    let test = simulate_session(&device, SessionKind::Random { points: 500 }, seed + 200).unwrap();
    let tr = observations(&train.samples);
    let te = observations(&test.samples);
    let nominal = geometry.nominal_frame();
    let start = Start::nominal(nominal, geometry.pulley_radius_mm, geometry.counts_per_rev);
    if std::env::var("DIAG").is_ok() {
        use spidar::diagnose::diagnose;
        use spidar::identify::{identify, Structure};
        let id = identify(&tr, &nominal, &start, &Structure::default()).unwrap();
        let cfg = LoopConfig {
            chi2_threshold: 0.0,
            ..LoopConfig::default()
        };
        for f in diagnose(&id, &tr, &nominal, &Structure::default(), &cfg)
            .iter()
            .take(12)
        {
            println!(
                "cand {:12} {:?} chi2 {:.1} amp {:.3} {}",
                family_name(f.family),
                f.strings,
                f.chi2,
                f.amplitude_mm,
                f.description
            );
        }
        return;
    }
    let t0 = std::time::Instant::now();
    let r = close_loop(&tr, Some(&te), &nominal, &start, &LoopConfig::default()).unwrap();
    println!("loop {:?}", t0.elapsed());
    let t = r.base_test.unwrap();
    println!(
        "{:28} train {:.3}/{:.3} test {:.3}/{:.3}",
        "identified", r.base_train.mean_mm, r.base_train.max_mm, t.mean_mm, t.max_mm
    );
    for s in &r.stages {
        let t = s.test.unwrap();
        println!(
            "{:28} train {:.3}/{:.3} test {:.3}/{:.3}  cv {:.4} -> {:.4}",
            s.name,
            s.train.mean_mm,
            s.train.max_mm,
            t.mean_mm,
            t.max_mm,
            s.validation_before_mm,
            s.validation_after_mm
        );
    }
    for f in &r.findings {
        println!(
            "finding {:12} strings {:?} {:12} amp {:.3} mm explained {:.3} chi2 {:.0} added {}  {}",
            family_name(f.family),
            f.strings,
            variable_name(f.variable),
            f.amplitude_mm,
            f.explained,
            f.chi2,
            f.added,
            f.description
        );
    }
}
