//! Injected ("undeclared") effects for the loop-closing tests.
//!
//! Model families use exactly the definitions of [`spidar_core::model::Effect`],
//! evaluated by the core's own f64 reference
//! ([`Effect::contribution_f64`](spidar_core::model::Effect) with
//! [`spidar_core::string_law::EffectContext`]), so that identification can
//! recover them: the simulated string obeys
//!
//! `true length = |home - anchor| + payout(theta) + sum of effect terms`
//!
//! with the device's true frame and true base winding law. Besides those, a
//! speed-dependent effect that no family models (for "unexplained" tests) and
//! two "geometry" effects (an anchor displacement, a tracker scale error).
//!
//! # Syntax (`--effect SPEC`, or `effects = ["SPEC", ...]` in the config)
//!
//! `KIND:STRING:NAME=VALUE,NAME=VALUE...` where `STRING` is an encoder index
//! `0..7` or `*` for all eight strings; `tracker_scale` takes no string
//! (`tracker_scale:relative=0.002`). Parameter names are the field names of
//! [`Effect`]:
//!
//! | kind | parameters | length term |
//! |---|---|---|
//! | `offset` | `mm` | `+ mm` |
//! | `scale` | `relative` | `+ relative * payout` |
//! | `winding` | `power`, `mm_per_rad_pow` | `+ mm_per_rad_pow * theta^power` |
//! | `eccentricity` | `sin_mm`, `cos_mm` (each default 0) | `+ sin_mm sin(theta) + cos_mm (cos(theta) - 1)` |
//! | `elasticity` | `per_newton` | `+ per_newton * T * (home_length + payout)` |
//! | `backlash` | `half_width_mm` | `+ half_width_mm * direction` |
//! | `drift` | `mm_per_s` | `+ mm_per_s * t` |
//! | `creep` | `per_s` | `+ per_s * t * (home_length + payout)` (the string's natural length grows by `per_s t` of itself) |
//! | `slip` | `at_s`, `mm` | `+ mm * [t >= at_s]` |
//! | `sag` | `mm_at_1m_1n`, `home_mm_at_1m` (default 0) | `- mm_at_1m_1n * cos^2(a) (l / 1 m)^3 / (T / 1 N)^2 + home_mm_at_1m * cos^2(a_home) (home_length / 1 m)^3`, `l = home_length + payout` |
//! | `stretch` | `per_newton`, `mm_per_newton` (default 0), `home_tension_n` | `+ per_newton (T (home_length + payout) - T_home home_length) + mm_per_newton (T - T_home)` |
//! | `frame_flex` | `mm_per_newton`, `home_mm` (default 0) | `+ mm_per_newton * sum_j T_j - home_mm` (the total over the active strings) |
//! | `guide` | `radius_mm` | `+` the path over a guide pulley of that radius swivelling about the frame edge, less the chord (`spidar_core::string_law::guide_mm`) |
//! | `speed` (unexplained) | `latency_s` | `+ latency_s * dL/dt` (encoder latency) |
//! | `anchor` (geometry) | `dx`, `dy`, `dz` (each default 0) | anchor moved by `[dx, dy, dz]` mm |
//! | `tracker_scale` (geometry) | `relative` | tracker scale times `1 + relative` |
//!
//! Example: `--effect offset:3:mm=10 --effect backlash:*:half_width_mm=0.4`.

use serde::{Deserialize, Serialize};
use spidar_core::model::{Effect, EffectTerm, Vec3};
use spidar_core::STRINGS;

use super::SimError;

/// One injected effect, resolved to one string (a `*` spec gives eight).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum InjectedEffect {
    /// A term of a model family, exactly as `model::Effect` defines it.
    Model(EffectTerm),
    /// Unexplained: the encoder reading lags the string by `latency_s`, so
    /// the length gains `latency_s * dL/dt` (string speed, mm/s).
    Speed { string: u8, latency_s: f64 },
    /// Geometry: the string's anchor is displaced by `mm` from its as-built place.
    AnchorShift { string: u8, mm: Vec3<f64> },
    /// Geometry: the tracker scale is multiplied by `1 + relative`.
    TrackerScale { relative: f64 },
}

fn spec_error(spec: &str, problem: impl Into<String>) -> SimError {
    SimError::EffectSpec {
        spec: spec.to_string(),
        problem: problem.into(),
    }
}

/// Parsed `NAME=VALUE` list; every name must be consumed (also the
/// independent simulator's effect parameters, [`super::physics`]).
pub(crate) struct Params<'a> {
    spec: &'a str,
    items: Vec<(&'a str, f64, bool)>,
}

impl<'a> Params<'a> {
    pub(crate) fn parse(spec: &'a str, text: &'a str) -> Result<Self, SimError> {
        let mut items: Vec<(&str, f64, bool)> = Vec::new();
        for item in text.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (name, value) = item
                .split_once('=')
                .ok_or_else(|| spec_error(spec, format!("`{item}` is not NAME=VALUE")))?;
            let (name, value) = (name.trim(), value.trim());
            let v: f64 = value
                .parse()
                .map_err(|_| spec_error(spec, format!("`{name}`: `{value}` is not a number")))?;
            if !v.is_finite() {
                return Err(spec_error(
                    spec,
                    format!("`{name}`: `{value}` is not finite"),
                ));
            }
            if items.iter().any(|(n, _, _)| *n == name) {
                return Err(spec_error(spec, format!("`{name}` given twice")));
            }
            items.push((name, v, false));
        }
        Ok(Params { spec, items })
    }

    pub(crate) fn take(&mut self, name: &str) -> Option<f64> {
        self.items
            .iter_mut()
            .find(|(n, _, _)| *n == name)
            .map(|item| {
                item.2 = true;
                item.1
            })
    }

    pub(crate) fn required(&mut self, name: &str) -> Result<f64, SimError> {
        self.take(name)
            .ok_or_else(|| spec_error(self.spec, format!("missing parameter `{name}`")))
    }

    pub(crate) fn optional(&mut self, name: &str) -> f64 {
        self.take(name).unwrap_or(0.0)
    }

    pub(crate) fn finish(self) -> Result<(), SimError> {
        match self.items.iter().find(|(_, _, used)| !used) {
            Some((name, _, _)) => Err(spec_error(self.spec, format!("unknown parameter `{name}`"))),
            None => Ok(()),
        }
    }
}

const KINDS: &str = "offset, scale, winding, eccentricity, elasticity, backlash, drift, creep, slip, sag, stretch, frame_flex, guide, speed, anchor, tracker_scale";

/// Parse one effect spec (see the module documentation for the syntax).
pub fn parse_effect(spec: &str) -> Result<Vec<InjectedEffect>, SimError> {
    let parts: Vec<&str> = spec.trim().split(':').map(str::trim).collect();
    let kind = parts[0];
    if kind == "tracker_scale" {
        return parse_tracker_scale(spec, &parts);
    }
    if parts.len() != 3 {
        return Err(spec_error(
            spec,
            "expected KIND:STRING:NAME=VALUE,... (STRING 0..7 or *)",
        ));
    }
    let strings = parse_strings(spec, parts[1])?;
    let mut p = Params::parse(spec, parts[2])?;
    let one = per_string_effect(spec, kind, &mut p)?;
    p.finish()?;
    Ok(strings.into_iter().map(one).collect())
}

/// `tracker_scale:relative=VALUE` (`parts`: the spec split at `:`).
fn parse_tracker_scale(spec: &str, parts: &[&str]) -> Result<Vec<InjectedEffect>, SimError> {
    if parts.len() != 2 {
        return Err(spec_error(spec, "expected tracker_scale:relative=VALUE"));
    }
    let mut p = Params::parse(spec, parts[1])?;
    let relative = p.required("relative")?;
    p.finish()?;
    if relative <= -1.0 {
        return Err(spec_error(spec, "`relative` must be > -1"));
    }
    Ok(vec![InjectedEffect::TrackerScale { relative }])
}

/// The strings of a spec: one index 0..7, or `*` for all.
fn parse_strings(spec: &str, s: &str) -> Result<Vec<u8>, SimError> {
    match s {
        "*" => Ok((0..STRINGS as u8).collect()),
        s => match s.parse::<u8>() {
            Ok(i) if usize::from(i) < STRINGS => Ok(vec![i]),
            _ => Err(spec_error(
                spec,
                format!("`{s}` is not a string index 0..7 or *"),
            )),
        },
    }
}

/// The effect of `kind` with the parameters `p` (what is left of them is
/// unknown), as a function of the string it is on.
fn per_string_effect(
    spec: &str,
    kind: &str,
    p: &mut Params<'_>,
) -> Result<Box<dyn Fn(u8) -> InjectedEffect>, SimError> {
    match kind {
        "offset" => {
            let mm = p.required("mm")?;
            Ok(model(Effect::Offset { mm }))
        }
        "scale" => {
            let relative = p.required("relative")?;
            Ok(model(Effect::Scale { relative }))
        }
        "winding" => {
            let power = p.required("power")?;
            if !(power.fract() == 0.0 && (1.0..=16.0).contains(&power)) {
                return Err(spec_error(
                    spec,
                    format!("`power`: {power} is not an integer 1..=16"),
                ));
            }
            let mm_per_rad_pow = p.required("mm_per_rad_pow")?;
            Ok(model(Effect::Winding {
                power: power as u8,
                mm_per_rad_pow,
            }))
        }
        "eccentricity" => {
            let sin_mm = p.optional("sin_mm");
            let cos_mm = p.optional("cos_mm");
            Ok(model(Effect::Eccentricity { sin_mm, cos_mm }))
        }
        "elasticity" => {
            let per_newton = p.required("per_newton")?;
            Ok(model(Effect::Elasticity { per_newton }))
        }
        "backlash" => {
            let half_width_mm = p.required("half_width_mm")?;
            Ok(model(Effect::Backlash { half_width_mm }))
        }
        "drift" => {
            let mm_per_s = p.required("mm_per_s")?;
            Ok(model(Effect::Drift { mm_per_s }))
        }
        "creep" => {
            let per_s = p.required("per_s")?;
            Ok(model(Effect::Creep { per_s }))
        }
        "slip" => {
            let at_s = p.required("at_s")?;
            let mm = p.required("mm")?;
            Ok(model(Effect::Slip { at_s, mm }))
        }
        "sag" => {
            let mm_at_1m_1n = p.required("mm_at_1m_1n")?;
            let home_mm_at_1m = p.optional("home_mm_at_1m");
            Ok(model(Effect::Sag {
                mm_at_1m_1n,
                home_mm_at_1m,
            }))
        }
        "stretch" => {
            let per_newton = p.required("per_newton")?;
            let mm_per_newton = p.optional("mm_per_newton");
            let home_tension_n = p.required("home_tension_n")?;
            Ok(model(Effect::Stretch {
                per_newton,
                mm_per_newton,
                home_tension_n,
            }))
        }
        "frame_flex" => {
            let mm_per_newton = p.required("mm_per_newton")?;
            let home_mm = p.optional("home_mm");
            Ok(model(Effect::FrameFlex {
                mm_per_newton,
                home_mm,
            }))
        }
        "guide" => {
            let radius_mm = p.required("radius_mm")?;
            Ok(model(Effect::Guide { radius_mm }))
        }
        "speed" => {
            let latency_s = p.required("latency_s")?;
            Ok(Box::new(move |string| InjectedEffect::Speed {
                string,
                latency_s,
            }))
        }
        "anchor" => {
            let mm = [p.optional("dx"), p.optional("dy"), p.optional("dz")];
            Ok(Box::new(move |string| InjectedEffect::AnchorShift {
                string,
                mm,
            }))
        }
        other => Err(spec_error(
            spec,
            format!("unknown kind `{other}` (kinds: {KINDS})"),
        )),
    }
}

fn model(effect: Effect) -> Box<dyn Fn(u8) -> InjectedEffect> {
    Box::new(move |string| InjectedEffect::Model(EffectTerm { string, effect }))
}

/// Parse a list of specs, in order.
pub fn parse_effects(specs: &[String]) -> Result<Vec<InjectedEffect>, SimError> {
    let mut out = Vec::new();
    for spec in specs {
        out.extend(parse_effect(spec)?);
    }
    Ok(out)
}
