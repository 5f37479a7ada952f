use spidar::identify::{identify, Start, Structure};
use spidar::observe::observations;
use spidar::predict::{paired_with_tracker, predict, StringModel};
use spidar::sim::config::SimConfig;
use spidar::sim::{simulate_session, Device, SessionKind};
use spidar::stats::{position_errors, ErrorStats};

fn main() {
    let seed: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse().unwrap())
        .unwrap_or(1);
    let mut config = SimConfig::default();
    config.effects = std::env::args().skip(2).collect();
    let device = Device::new(&config, seed).unwrap();
    let geometry = config.nominal.geometry();
    let t0 = std::time::Instant::now();
    let train = simulate_session(&device, SessionKind::Lattice, seed + 100).unwrap();
    let test = simulate_session(&device, SessionKind::Random { points: 500 }, seed + 200).unwrap();
    println!("simulate {:?}", t0.elapsed());
    let tr = observations(&train.samples);
    let te = observations(&test.samples);
    let nominal = geometry.nominal_frame();
    let laws = geometry.nominal_string_laws();
    let report = |name: &str, frame, laws, effects: &[_]| {
        for (set, obs) in [("train", &tr), ("test", &te)] {
            let pred = predict(
                StringModel {
                    frame,
                    laws,
                    effects,
                },
                obs,
            );
            let room: Vec<_> = pred.iter().map(|p| p.room).collect();
            let (p, t) = paired_with_tracker(&room, obs);
            let s = ErrorStats::of(&position_errors(&p, &t));
            let excl = pred.iter().filter(|p| p.excluded.is_some()).count();
            println!(
                "{name:12} {set:5} n={} mean={:.3} sd={:.3} max={:.3} excluded={excl}",
                s.n, s.mean_mm, s.sd_mm, s.max_mm
            );
        }
    };
    report("nominal", &nominal, &laws, &[]);
    let r = laws.map(|l| l.winding_mm[0]);
    let start = Start::nominal(nominal, r, geometry.counts_per_rev);
    let t0 = std::time::Instant::now();
    let id = identify(&tr, &nominal, &start, &Structure::default()).unwrap();
    println!(
        "identify {:?} evals={} scale={:.4} rejected={:.4}",
        t0.elapsed(),
        id.evaluations,
        id.residual_scale_mm,
        id.rejected_fraction
    );
    report("identified", &id.frame, &id.laws, &id.effects);
    for p in id.parameters.iter().take(12).skip(9) {
        println!(
            "  {:24} {:12.3} ± {:.3} (nominal {:.1}, true {:.1})",
            p.name, p.value, p.sd, nominal.anchors[3][0], device.frame.anchors[3][0]
        );
    }
    for p in id.parameters.iter().skip(24) {
        println!("  {:24} {:12.6} ± {:.6} {}", p.name, p.value, p.sd, p.unit);
    }
    for w in &id.warnings {
        println!("warning: {w}");
    }
}
