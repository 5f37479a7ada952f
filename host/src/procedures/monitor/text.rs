//! The monitor's text: a finding in the device's terms, one line per
//! event, and the run's summary.

use spidar_core::model::{Effect, EffectTerm, EVERY_STRING};

use crate::data::stats::ErrorStats;
use crate::model::diagnose::{family_name, Change, Finding};

use super::{MonitorEvent, MonitorReport};

/// A finding in the device's terms: string, mm, when.
pub fn describe_finding(f: &Finding) -> String {
    let term = match f.change {
        Some(Change::Effect(EffectTerm { string, effect })) => {
            let who = if string == EVERY_STRING {
                "every string".to_string()
            } else {
                format!("string {string}")
            };
            match effect {
                Effect::Slip { at_s, mm } => {
                    format!("{who} slipped by {mm:+.2} mm at {at_s:.2} s of device time since home")
                }
                Effect::Offset { mm } => format!("{who} reads {mm:+.2} mm off"),
                Effect::Drift { mm_per_s } => {
                    format!("{who} drifts {:+.3} mm/min", mm_per_s * 60.0)
                }
                Effect::Scale { relative } => {
                    format!("{who}'s payout is off by {:+.3} %", relative * 100.0)
                }
                other => format!("{who}: {other:?}"),
            }
        }
        _ => f.description.clone(),
    };
    format!(
        "{} ({}; {:.1} mm at most, explains {:.0} % of the residual, chi2 {:.0})",
        family_name(f.family),
        term,
        f.amplitude_mm,
        100.0 * f.explained,
        f.chi2
    )
}

/// One line per monitor event.
pub fn event_line(e: &MonitorEvent) -> String {
    let stats = |s: &ErrorStats| {
        format!(
            "mean {:.3} mm, sd {:.3}, p95 {:.3}, max {:.3} (n {})",
            s.mean_mm, s.sd_mm, s.p95_mm, s.max_mm, s.n
        )
    };
    match e {
        MonitorEvent::Baseline(s) => format!("baseline window: {}", stats(s)),
        MonitorEvent::Check(c) => format!(
            "check at t = {:.1} s (device time since home): window {} ({:.2} x baseline); no drift",
            c.device_time_s,
            stats(&c.window),
            c.error_ratio
        ),
        MonitorEvent::Drift { check: c, refit } => {
            let mut s = format!(
                "DRIFT at t = {:.1} s (device time since home): window {} ({:.2} x baseline{})",
                c.device_time_s,
                stats(&c.window),
                c.error_ratio,
                if c.error_exceeded { ", above the limit" } else { "" }
            );
            for f in &c.findings {
                s.push_str(&format!("\n  found: {}", describe_finding(f)));
            }
            s.push_str(if *refit {
                "\n  refitting and reflashing"
            } else {
                "\n  not refitted"
            });
            s
        }
        MonitorEvent::Refitted(r) => format!(
            "refit on {} rows (the window's {} pairs and {} rows of the training session): {}; window error on the host {:.3} -> {:.3} mm; flashed model {:#010x} ({} bytes) in {:.1} s of wall time{}",
            r.rows,
            r.window_pairs,
            r.training_rows,
            r.added.join("; "),
            r.host_before_mm,
            r.host_after_mm,
            r.model_id,
            r.blob_len,
            r.seconds,
            match &r.calibration.home {
                Some(h) => format!(
                    "; its {} under home capture {} until the device's next `Home`",
                    if h.slips.len() == 1 {
                        "slip applies".to_string()
                    } else {
                        format!("{} slips apply", h.slips.len())
                    },
                    h.home_id
                ),
                None => String::new(),
            }
        ),
        MonitorEvent::RefitFailed(why) => format!("refit failed: {why}"),
        MonitorEvent::After { before, after } => format!(
            "after the reflash: window {} (before: mean {:.3} mm)",
            stats(after),
            before.mean_mm
        ),
        MonitorEvent::Note(n) => n.clone(),
    }
}

/// The run's summary.
pub fn summary(r: &MonitorReport) -> String {
    let mut s = format!(
        "monitored {:.1} s of tracker time{} in {:.1} s of wall time\n",
        r.tracker_seconds(),
        r.device_span_s.map_or(String::new(), |(first, last)| format!(
            " (pairs from {first:.1} to {last:.1} s of device time since boot)"
        )),
        r.wall_seconds
    );
    // Every frame in one count: they add up to `frames`.
    let mut not_paired = vec![format!("{} occluded", r.occluded)];
    if r.unoriented > 0 {
        not_paired.push(format!("{} without the body's rotation", r.unoriented));
    }
    not_paired.push(format!(
        "{} without a device state around their instant",
        r.unpaired
    ));
    not_paired.push(format!(
        "{} of a model or home since replaced",
        r.superseded
    ));
    not_paired.push(format!("{} glitches set aside", r.glitches));
    if r.waiting > 0 {
        not_paired.push(format!("{} waiting for their state at the stop", r.waiting));
    }
    s.push_str(&format!(
        "{} tracker frames: {} paired, {}; {} device states; {} checks, {} drift reports, {} refits\n",
        r.frames,
        r.pairs,
        not_paired.join(", "),
        r.states,
        r.checks.len(),
        r.drifts().count(),
        r.refits.len()
    ));
    if let Some(b) = &r.baseline {
        s.push_str(&format!("baseline: mean {:.3} mm (n {})", b.mean_mm, b.n));
        if let Some(t) = r.glitch_threshold_mm {
            s.push_str(&format!(
                "; a pair more than {t:.1} mm off is the tracker's glitch"
            ));
        }
        s.push('\n');
    }
    for (k, f) in r.refits.iter().enumerate() {
        let after = f.after.or(f.after_partial);
        s.push_str(&format!(
            "refit {}: before mean {:.3} mm, after {}\n",
            k + 1,
            f.before.mean_mm,
            after.map_or("(no pairs)".into(), |a| format!(
                "mean {:.3} mm (n {})",
                a.mean_mm, a.n
            ))
        ));
    }
    s
}
