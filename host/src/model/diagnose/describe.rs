//! The report's words: the names of variables, families and stages, and
//! fitted values in physical terms.

use spidar_core::model::{Effect, EffectTerm};

use crate::model::identify::Identification;

use super::vocabulary::{Change, Family, Finding, Variable};

/// The report's name of a variable.
pub fn variable_name(v: Variable) -> &'static str {
    match v {
        Variable::Position => "position",
        Variable::Length => "length",
        Variable::WoundLength => "wound_length",
        Variable::PulleyAngle => "pulley_angle",
        Variable::Tension => "tension",
        Variable::Direction => "direction",
        Variable::Speed => "speed",
        Variable::Time => "time",
        Variable::Order => "order",
        Variable::Orientation => "orientation",
        Variable::Elevation => "elevation",
    }
}

/// The report's name of a family.
pub fn family_name(f: Family) -> &'static str {
    match f {
        Family::Offset => "offset",
        Family::Scale => "scale",
        Family::Winding => "winding",
        Family::Eccentricity => "eccentricity",
        Family::Elasticity => "elasticity",
        Family::Backlash => "backlash",
        Family::Drift => "drift",
        Family::Creep => "creep",
        Family::Slip => "slip",
        Family::Sag => "sag",
        Family::FrameFlex => "frame flex",
        Family::Latency => "latency",
        Family::Guide => "guide pulley",
        Family::Layers => "layers",
        Family::Geometry => "geometry",
        Family::Marker => "marker offset",
        Family::Unexplained => "unexplained",
    }
}

/// A stage's name in the report, after its finding's family and strings
/// (e.g. "offset string 3").
pub(super) fn stage_name(f: &Finding) -> String {
    match (f.family, f.strings.as_slice()) {
        (Family::Geometry, []) => "geometry (tracker scale)".into(),
        (Family::Geometry, [s]) => format!("geometry anchor {s}"),
        (Family::Marker, _) => "marker offset (tracked body)".into(),
        (family, []) => format!("{} (every string)", family_name(family)),
        (family, [s]) => format!("{} string {s}", family_name(family)),
        (family, s) => format!("{} strings {s:?}", family_name(family)),
    }
}

/// A fitted sag or stretch in the device's terms; `None` for another
/// effect. A sag: the strings' weight (`c = w^2 / 24`) and the tension they
/// held at the home capture (`h = c / T_home^2`). A stretch: the strings'
/// stiffness `EA = 1 / per_newton`, the length between spool and exit point
/// it stretches beside the free span (`mm_per_newton * EA`), and the home
/// tension.
fn in_physical_terms(effect: &Effect) -> Option<String> {
    match *effect {
        Effect::Sag {
            mm_at_1m_1n: c,
            home_mm_at_1m: h,
        } => {
            // c mm = w^2 (1 m)^3 / (24 (1 N)^2), w in N/m.
            let grams_per_m = (24.0 * c.max(0.0) / 1000.0).sqrt() / 9.80665 * 1000.0;
            let home = if c > 0.0 && h > 0.0 {
                format!("{:.2} N", (c / h).sqrt())
            } else {
                "not a tension (the home part's sign is not a sag's)".into()
            };
            Some(format!(
                " (fitted: {c:.3} mm at 1 m and 1 N, strings of {grams_per_m:.1} g/m; tension at \
                 the home capture {home})"
            ))
        }
        Effect::Stretch {
            per_newton,
            mm_per_newton,
            home_tension_n,
        } => {
            let stiffness = if per_newton > 0.0 {
                format!(
                    "EA {:.0} N, {:.0} mm of string between spool and exit point",
                    1.0 / per_newton,
                    mm_per_newton / per_newton
                )
            } else {
                format!("{mm_per_newton:.4} mm/N (no stretch of the free span)")
            };
            // A home tension below 0 is not one: the home part, a length
            // on every string, then also takes a constant the strings share
            // for another reason (seen on clean independent devices).
            let home = if home_tension_n > 0.0 {
                format!("{home_tension_n:.2} N")
            } else {
                format!(
                    "{home_tension_n:.2} N, not a tension: its home part also takes a length \
                     shared by every string"
                )
            };
            Some(format!(
                " (fitted: {per_newton:.3e} per N, strings of {stiffness}; tension at the home \
                 capture {home})"
            ))
        }
        Effect::FrameFlex {
            mm_per_newton,
            home_mm,
        } => {
            let home_total = if mm_per_newton != 0.0 {
                format!("{:.1} N", home_mm / mm_per_newton)
            } else {
                "none".into()
            };
            Some(format!(
                " (fitted: {mm_per_newton:.4} mm per N of total tension; total tension at the \
                 home capture {home_total})"
            ))
        }
        Effect::Latency { latency_s } => Some(format!(
            " (fitted: the encoder read {:.2} ms {})",
            1000.0 * latency_s.abs(),
            if latency_s >= 0.0 { "late" } else { "early" }
        )),
        Effect::Creep { per_s } => Some(format!(
            " (fitted: the string's natural length {} by {:.0} ppm of itself an hour, {:.3} mm \
             a metre after an hour)",
            if per_s >= 0.0 { "grows" } else { "shrinks" },
            per_s.abs() * 3.6e9,
            per_s.abs() * 3.6e6
        )),
        Effect::Guide { radius_mm } => Some(format!(
            " (fitted: a guide pulley of radius {radius_mm:.1} mm{})",
            if radius_mm < 0.0 {
                ", not a radius: it takes a length that falls as the string rises toward its \
                 guide's axis"
            } else {
                ""
            }
        )),
        _ => None,
    }
}

/// A found marker offset in the report's words.
fn marker_in_physical_terms(d: &[f64; 3]) -> String {
    let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
    format!(
        " (the body's origin {norm:.1} mm from the meeting point: [{:.1}, {:.1}, {:.1}] mm in \
         the body's frame; the tracker is read at the meeting point from here on)",
        d[0], d[1], d[2]
    )
}

/// An added change's fitted values in the report's words: the refit's
/// last effect, or the marker offset found.
pub(super) fn fitted_in_physical_terms(change: Change, refit: &Identification) -> Option<String> {
    match change {
        Change::Effect(_) => refit
            .effects
            .last()
            .and_then(|t| in_physical_terms(&t.effect)),
        Change::MarkerOffset(d) => Some(marker_in_physical_terms(&d)),
        Change::Drifts(_) => {
            let each = each_added(change, refit, |e| match e {
                Effect::Drift { mm_per_s } => Some(format!("{:+.3}", mm_per_s * 60.0)),
                _ => None,
            })?;
            Some(format!(" (fitted, mm/min: {})", each.join(", ")))
        }
        Change::Stretches(..) => {
            // The refit's stretches, in the order the change added them:
            // each string's stiffness EA = 1 / per_newton and its tension
            // at the home capture, which, free on each string, also takes
            // a constant length of that string (as the shared stretch's
            // takes one of every string).
            let added = added_terms(change, refit)?;
            let (mut each, mut home) = (Vec::new(), Vec::new());
            for t in added {
                if let Effect::Stretch {
                    per_newton,
                    home_tension_n,
                    ..
                } = t.effect
                {
                    if per_newton != 0.0 {
                        each.push(format!("{}: {:.1}", t.string, 1e-3 / per_newton));
                    }
                    home.push(home_tension_n);
                }
            }
            let (low, high) = home
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &t| {
                    (l.min(t), h.max(t))
                });
            let home = if low > 0.0 {
                format!("{low:.2} to {high:.2} N")
            } else {
                format!(
                    "{low:.2} to {high:.2} N, not all tensions: each string's home part also \
                     takes a constant length of its string"
                )
            };
            Some(format!(
                " (fitted stiffness EA, kN: {}; tensions at the home capture {home})",
                each.join(", ")
            ))
        }
        Change::Latencies(_) => {
            let each = each_added(change, refit, |e| match e {
                Effect::Latency { latency_s } => Some(format!("{:.2}", 1e3 * latency_s)),
                _ => None,
            })?;
            Some(format!(" (fitted, ms: {})", each.join(", ")))
        }
        _ => None,
    }
}

/// The refit's terms `change` added: its last ones, in the order the change
/// added them.
fn added_terms(change: Change, refit: &Identification) -> Option<&[EffectTerm]> {
    let n = change.effect_terms().len();
    refit.effects.get(refit.effects.len().checked_sub(n)?..)
}

/// Each of `change`'s added terms as `string: value`, `value` as the term's
/// effect writes it (terms it does not write are left out).
fn each_added(
    change: Change,
    refit: &Identification,
    value: impl Fn(&Effect) -> Option<String>,
) -> Option<Vec<String>> {
    Some(
        added_terms(change, refit)?
            .iter()
            .filter_map(|t| value(&t.effect).map(|v| format!("{}: {v}", t.string)))
            .collect(),
    )
}
