//! The monitor's text: a finding in the device's terms, one line per
//! event, and the run's summary.

use spidar_core::model::{Effect, EffectTerm, EVERY_STRING};

use crate::data::stats::ErrorStats;
use crate::model::diagnose::{family_name, Change, Finding};

use super::{MonitorEvent, MonitorReport, StringsSeen};

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

/// What a window's strings show, in words: the error with every string
/// in, and the strings the device left out.
fn strings_line(s: &StringsSeen) -> String {
    let e = &s.every_string;
    let mut line = format!(
        "every string in: mean {:.3} mm, p95 {:.3}, max {:.3}",
        e.mean_mm, e.p95_mm, e.max_mm
    );
    if !s.left_out.is_empty() {
        let strings: Vec<String> = s
            .left_out
            .iter()
            .map(|(string, n)| format!("string {string} on {n}"))
            .collect();
        line.push_str(&format!(
            "; the device left out {} of {} pairs",
            strings.join(", "),
            e.n
        ));
    }
    line
}

/// One line per monitor event. A window's figures are the error of the
/// position the device reports ("device error") and what its strings show
/// ([`StringsSeen`]); times are device time since home, durations of the
/// machine's work wall time.
pub fn event_line(e: &MonitorEvent) -> String {
    let stats = |s: &ErrorStats| {
        format!(
            "mean {:.3} mm, sd {:.3}, p95 {:.3}, max {:.3} (n {})",
            s.mean_mm, s.sd_mm, s.p95_mm, s.max_mm, s.n
        )
    };
    match e {
        MonitorEvent::Baseline(s, strings) => format!(
            "baseline window: device error {}; {}",
            stats(s),
            strings_line(strings)
        ),
        MonitorEvent::Check(c) => format!(
            "check at t = {:.1} s (device time since home): device error {} ({:.2} x baseline); {}; no drift",
            c.device_time_s,
            stats(&c.window),
            c.error_ratio,
            strings_line(&c.strings)
        ),
        MonitorEvent::Drift { check: c, refit } => {
            let mut s = format!(
                "DRIFT at t = {:.1} s (device time since home): device error {} ({:.2} x baseline{}); {}",
                c.device_time_s,
                stats(&c.window),
                c.error_ratio,
                if c.error_exceeded { ", above the limit" } else { "" },
                strings_line(&c.strings)
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
            "refit on {} rows (the window's {} pairs and {} rows of the training session): {}; window error on the host with every string in {:.3} -> {:.3} mm (as the device solves it, a string that disagrees left out: {:.3} -> {:.3} mm); flashed model {:#010x} ({} bytes) in {:.1} s of wall time{}",
            r.rows,
            r.window_pairs,
            r.training_rows,
            r.added.join("; "),
            r.host_before_mm,
            r.host_after_mm,
            r.device_kinematics_before_mm,
            r.device_kinematics_after_mm,
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
        MonitorEvent::After {
            before,
            after,
            strings_before,
            strings_after,
        } => format!(
            "after the reflash: device error {}; {} (before: device error mean {:.3} mm, every string in {:.3} mm)",
            stats(after),
            strings_line(strings_after),
            before.mean_mm,
            strings_before.every_string.mean_mm
        ),
        MonitorEvent::Note(n) => n.clone(),
    }
}

/// The run's summary.
pub fn summary(r: &MonitorReport) -> String {
    let mut s = format!(
        "monitored {:.1} s of tracker time{} in {:.1} s of wall time\n",
        r.tracker_seconds(),
        r.device_span_s
            .map_or(String::new(), |(first, last)| format!(
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
        s.push_str(&format!(
            "baseline: device error mean {:.3} mm (n {})",
            b.mean_mm, b.n
        ));
        if let Some(strings) = &r.baseline_strings {
            s.push_str(&format!(
                ", every string in {:.3} mm",
                strings.every_string.mean_mm
            ));
        }
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
            "refit {}: device error before mean {:.3} mm, after {}; every string in: before {:.3} mm, after {}\n",
            k + 1,
            f.before.mean_mm,
            after.map_or("(no pairs)".into(), |a| format!(
                "mean {:.3} mm (n {})",
                a.mean_mm, a.n
            )),
            f.before_strings.every_string.mean_mm,
            f.after_strings
                .as_ref()
                .map_or("(no pairs)".into(), |a| format!(
                    "{:.3} mm",
                    a.every_string.mean_mm
                ))
        ));
    }
    s
}
