//! Undeclared effects of the independent simulator, selected by name:
//! `--effect NAME` (default parameters) or `--effect NAME:KEY=VALUE,...`.
//! They are physical causes, not model terms: each changes the physics the
//! counts are computed from, so what the calibration sees is whatever that
//! cause does to every string.
//!
//! | name | parameters (default) | physics |
//! |---|---|---|
//! | `drift-all` | `ppm_per_h` (300) | thermal creep: every string's natural length grows by `ppm_per_h * 1e-6 * t / 3600` of itself (common to all strings, proportional to each one's length) |
//! | `drift-each` | `ppm_per_h` (300), `spread_ppm_per_h` (200) | thermal creep of strings of different batches: each string's natural length grows by its own rate, `ppm_per_h` plus a uniform `-spread..spread` drawn per string from the device's seed, `* 1e-6 * t / 3600` of itself |
//! | `frame-flex` | `factor` (10) | the frame compliance of every corner times `factor` |
//! | `marker-offset` | `mm` (40), `deg` (6) | the marker `mm` from the strings' meeting point, the hand's posture rotation amplitude `deg` |
//! | `slip` | `per_h` (2), `mm` (5) | one string at a time slips on its spool: events at Poisson times (`per_h` an hour), each on a random string, by `mm` times a uniform 0.5..1 and a random sign; slips add up |
//! | `heavy-string` | `g_per_m` (20) | every string this heavy: sag `w^2 cos^2(a) l^3 / (24 T^2)` (inverse square of the tension, cube of the free length: no model family) |
//! | `latency` | `ms` (6), `string` (every string) | encoder latency: the counts of string `string` (or of every string) reach the controller `ms` late, so each row holds that string as it was `ms` earlier: the hand's position then, back along its velocity |

use serde::{Deserialize, Serialize};

use crate::sim::effects::Params;
use crate::sim::SimError;

/// One undeclared effect.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum PhysicsEffect {
    DriftAll {
        ppm_per_h: f64,
    },
    DriftEach {
        ppm_per_h: f64,
        spread_ppm_per_h: f64,
    },
    FrameFlex {
        factor: f64,
    },
    MarkerOffset {
        mm: f64,
        deg: f64,
    },
    Slip {
        per_h: f64,
        mm: f64,
    },
    HeavyString {
        g_per_m: f64,
    },
    /// `string` None: every string.
    Latency {
        string: Option<usize>,
        ms: f64,
    },
}

/// The names `--effect` accepts.
pub const EFFECT_NAMES: [&str; 7] = [
    "drift-all",
    "drift-each",
    "frame-flex",
    "marker-offset",
    "slip",
    "heavy-string",
    "latency",
];

fn spec_error(spec: &str, problem: impl Into<String>) -> SimError {
    SimError::EffectSpec {
        spec: spec.to_string(),
        problem: problem.into(),
    }
}

/// Parse one `NAME[:KEY=VALUE,...]`.
pub fn parse_effect(spec: &str) -> Result<PhysicsEffect, SimError> {
    let (name, params) = match spec.trim().split_once(':') {
        Some((n, p)) => (n.trim(), p),
        None => (spec.trim(), ""),
    };
    let mut p = Params::parse(spec, params)?;
    let mut get = |key: &str, default: f64| p.take(key).unwrap_or(default);
    let effect = match name {
        "drift-all" => PhysicsEffect::DriftAll {
            ppm_per_h: get("ppm_per_h", 300.0),
        },
        "drift-each" => PhysicsEffect::DriftEach {
            ppm_per_h: get("ppm_per_h", 300.0),
            spread_ppm_per_h: get("spread_ppm_per_h", 200.0),
        },
        "frame-flex" => PhysicsEffect::FrameFlex {
            factor: get("factor", 10.0),
        },
        "marker-offset" => PhysicsEffect::MarkerOffset {
            mm: get("mm", 40.0),
            deg: get("deg", 6.0),
        },
        "slip" => PhysicsEffect::Slip {
            per_h: get("per_h", 2.0),
            mm: get("mm", 5.0),
        },
        "heavy-string" => PhysicsEffect::HeavyString {
            g_per_m: get("g_per_m", 20.0),
        },
        "latency" => {
            let ms = get("ms", 6.0);
            let string = match p.take("string") {
                None => None,
                Some(s) if s >= 0.0 && s.fract() == 0.0 && s < 256.0 => Some(s as usize),
                Some(s) => {
                    return Err(spec_error(
                        spec,
                        format!("`string` must be a string's index (0, 1, ...), not {s}"),
                    ))
                }
            };
            PhysicsEffect::Latency { string, ms }
        }
        other => {
            return Err(spec_error(
                spec,
                format!(
                    "unknown effect `{other}` of the independent simulator (effects: {})",
                    EFFECT_NAMES.join(", ")
                ),
            ))
        }
    };
    p.finish()?;
    let negative = |what: &str, v: f64| {
        if v < 0.0 {
            Err(spec_error(spec, format!("`{what}` must be >= 0")))
        } else {
            Ok(())
        }
    };
    match effect {
        // A negative rate is a cooling device.
        PhysicsEffect::DriftAll { .. } => {}
        PhysicsEffect::DriftEach {
            spread_ppm_per_h, ..
        } => negative("spread_ppm_per_h", spread_ppm_per_h)?,
        PhysicsEffect::FrameFlex { factor } => negative("factor", factor)?,
        PhysicsEffect::MarkerOffset { mm, deg } => {
            negative("mm", mm)?;
            negative("deg", deg)?;
            if deg > 45.0 {
                return Err(spec_error(spec, "`deg` must be at most 45"));
            }
        }
        PhysicsEffect::Slip { per_h, mm } => {
            negative("per_h", per_h)?;
            negative("mm", mm)?;
        }
        PhysicsEffect::HeavyString { g_per_m } => negative("g_per_m", g_per_m)?,
        PhysicsEffect::Latency { ms, .. } => {
            negative("ms", ms)?;
            if ms > 1000.0 {
                return Err(spec_error(spec, "`ms` must be at most 1000"));
            }
        }
    }
    Ok(effect)
}

/// Parse a list of specs, in order.
pub fn parse_effects(specs: &[String]) -> Result<Vec<PhysicsEffect>, SimError> {
    specs.iter().map(|s| parse_effect(s)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_defaults_and_errors() {
        assert_eq!(
            parse_effect("frame-flex").unwrap(),
            PhysicsEffect::FrameFlex { factor: 10.0 }
        );
        assert_eq!(
            parse_effect("slip:mm=3").unwrap(),
            PhysicsEffect::Slip {
                per_h: 2.0,
                mm: 3.0
            }
        );
        let e = parse_effect("offset:3:mm=8").unwrap_err().to_string();
        assert!(e.contains("unknown effect `offset`"), "{e}");
        let e = parse_effect("slip:size=3").unwrap_err().to_string();
        assert!(e.contains("unknown parameter `size`"), "{e}");
        assert!(parse_effect("heavy-string:g_per_m=-1").is_err());
        assert_eq!(
            parse_effect("latency:string=2").unwrap(),
            PhysicsEffect::Latency {
                string: Some(2),
                ms: 6.0
            }
        );
        assert_eq!(
            parse_effect("latency:ms=4").unwrap(),
            PhysicsEffect::Latency {
                string: None,
                ms: 4.0
            }
        );
        let e = parse_effect("latency:string=1.5").unwrap_err().to_string();
        assert!(e.contains("`string` must be a string's index"), "{e}");
        assert!(parse_effect("latency:ms=-1").is_err());
    }
}
