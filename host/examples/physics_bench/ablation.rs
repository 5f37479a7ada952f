//! `--ablation`: the clean independent device with one part of its physics
//! switched off at a time.

use super::runs::{physics_run, run_calibration, Sessions};
use super::table::{stage_of, three};
use spidar::procedures::calibrate::report::StageKind;
use spidar::procedures::calibrate::CalibrateConfig;
use spidar::sim::physics::{PhysicsConfig, PhysicsDevice};

/// The clean independent device of seed 1 with one part of its physics
/// switched off at a time.
pub(super) fn ablation(quick: bool) {
    let mut config = if quick {
        CalibrateConfig::quick()
    } else {
        CalibrateConfig::full()
    };
    config.quiet = true;
    type Switch = fn(&mut PhysicsConfig);
    let parts: [(&str, Switch); 10] = [
        ("all physics (clean device)", |_| {}),
        ("no abnormal motor", |c| c.abnormal_motor.enabled = false),
        ("point guides (rho 0.001 mm)", |c| {
            c.as_built.guide_radius_mm = [0.001, 0.001]
        }),
        (
            "near-continuous spool (1.5 turns a layer, no cross-over)",
            |c| {
                c.as_built.spool_width_mm = [0.75, 0.75];
                c.as_built.crossover_rise_mm = [0.0, 0.0];
            },
        ),
        ("no cross-over only", |c| {
            c.as_built.crossover_rise_mm = [0.0, 0.0]
        }),
        ("rigid strings (EA 1e9 N)", |c| {
            c.as_built.string_stiffness_n = [1e9, 1e9]
        }),
        ("weightless strings (no sag)", |c| {
            c.as_built.string_mass_g_per_m = [0.0, 0.0]
        }),
        ("rigid frame", |c| {
            c.as_built.frame_compliance_mm_per_n = [0.0, 0.0]
        }),
        ("marker at the meeting point", |c| {
            c.as_built.marker_offset_mm = [0.0, 0.0]
        }),
        ("everything above off", |c| {
            c.abnormal_motor.enabled = false;
            c.as_built.guide_radius_mm = [0.001, 0.001];
            c.as_built.spool_width_mm = [0.75, 0.75];
            c.as_built.crossover_rise_mm = [0.0, 0.0];
            c.as_built.string_stiffness_n = [1e9, 1e9];
            c.as_built.string_mass_g_per_m = [0.0, 0.0];
            c.as_built.frame_compliance_mm_per_n = [0.0, 0.0];
            c.as_built.marker_offset_mm = [0.0, 0.0];
        }),
    ];
    println!(
        "ablation, independent device seed 1, held-out mean / p95 / max, mm; config {}",
        if quick { "quick" } else { "full" }
    );
    println!();
    println!("| physics | identified | added by the loop | final stage | final |");
    println!("|---|---|---|---|---|");
    for (name, switch) in parts {
        let mut c = PhysicsConfig::default();
        switch(&mut c);
        let device = PhysicsDevice::new(&c, 1).expect("independent device");
        let (run, _, _) = physics_run(&device, 1, Sessions::Lattice);
        let cal = run_calibration(&run, &config);
        let stages = &cal.report.stages;
        let added: Vec<&str> = stages
            .iter()
            .filter(|s| s.kind == StageKind::Effect)
            .map(|s| s.name.as_str())
            .collect();
        let last = stages.last().expect("final stage");
        println!(
            "| {name} | {} | {} | {} | {} |",
            three(&stage_of(&cal, StageKind::Identified).test),
            if added.is_empty() {
                "none".to_string()
            } else {
                added.join(", ")
            },
            last.name,
            three(&last.test)
        );
    }
}
