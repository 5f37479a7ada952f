//! Building a device of the independent simulator: its as-built physics
//! drawn from the device seed, each part from its own random stream (the
//! guides' exit points, the guides, the spools and strings, the frame's
//! flex, the marker and the hand's posture, the tracker's room frame), with
//! the configured undeclared effects applied.

use rand::rngs::ChaCha8Rng;
use rand::RngExt;
use rand_distr::Distribution;
use spidar_core::model::Vec3;
use std::f64::consts::TAU;

use super::{
    parse_effects, CarriageConfig, Guide, PhysicsAsBuilt, PhysicsConfig, PhysicsDevice,
    PhysicsEffect, PhysicsString, Posture, Spool, SpoolParams,
};
use crate::data::dataset::Geometry;
use crate::sim::simulated_device::{declaring_pretension, draw_home, normal, stream};
use crate::sim::SimError;
use spidar_core::geometry::{dot, mat_vec, norm, rotation_about_axis, rotation_from_vector, sub};

/// Uniform in `[r[0], r[1]]`; always one draw, so that narrowing one range
/// (to a point, say) leaves every other parameter of the device unchanged.
pub(super) fn uniform(rng: &mut ChaCha8Rng, r: [f64; 2]) -> f64 {
    r[0] + (r[1] - r[0]) * rng.random_range(0.0..=1.0)
}

fn unit(v: Vec3<f64>) -> Vec3<f64> {
    let n = norm(v);
    v.map(|x| x / n)
}

/// A unit vector at `angle` rad from the unit vector `axis`, in a random direction.
fn tilted(axis: Vec3<f64>, angle: f64, rng: &mut ChaCha8Rng) -> Vec3<f64> {
    let trial = if axis[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let t = dot(trial, axis);
    let a = unit(core::array::from_fn(|k| trial[k] - t * axis[k]));
    let b = [
        axis[1] * a[2] - axis[2] * a[1],
        axis[2] * a[0] - axis[0] * a[2],
        axis[0] * a[1] - axis[1] * a[0],
    ];
    let psi = rng.random_range(0.0..TAU);
    let (s, c) = angle.sin_cos();
    unit(core::array::from_fn(|k| {
        c * axis[k] + s * (psi.cos() * a[k] + psi.sin() * b[k])
    }))
}

pub(super) fn string_error(string: usize, what: impl std::fmt::Display) -> SimError {
    SimError::Config(crate::ConfigError::new(
        format!("string {string}"),
        what.to_string(),
    ))
}

/// The as-built guides' exit points (stream 101): each 3 mm sd off its
/// design anchor (in the anchors' plane on a planar device).
fn draw_exits(
    nominal: &Geometry,
    ab: &PhysicsAsBuilt,
    seed: u64,
) -> Result<Vec<Vec3<f64>>, SimError> {
    let planar = nominal.layout.planar;
    let mut rng = stream(seed, 101);
    let anchor_noise = normal("as_built.anchor_sigma_mm", ab.anchor_sigma_mm)?;
    Ok(nominal
        .anchors_mm
        .iter()
        .take(nominal.strings())
        .map(|a| {
            let mut e = a.map(|x| x + anchor_noise.sample(&mut rng));
            if planar {
                e[2] = a[2];
            }
            e
        })
        .collect())
}

/// The guides (stream 103): swivel axis along the frame edge, away from the
/// home height; entry point placed so that the string to the nominal home
/// leaves at the as-built exit point.
fn place_guides(
    nominal: &Geometry,
    ab: &PhysicsAsBuilt,
    exits: &[Vec3<f64>],
    seed: u64,
) -> Result<Vec<Guide>, SimError> {
    let mut rng = stream(seed, 103);
    let mut guides = Vec::with_capacity(exits.len());
    for (i, exit) in exits.iter().enumerate() {
        let up = if exit[2] >= nominal.home_mm[2] {
            1.0
        } else {
            -1.0
        };
        let axis = tilted([0.0, 0.0, up], ab.guide_tilt_deg.to_radians(), &mut rng);
        let mut guide = Guide {
            entry_mm: *exit,
            axis,
            radius_mm: uniform(&mut rng, ab.guide_radius_mm),
        };
        for _ in 0..6 {
            let path = guide
                .path(&[0.0; 3], &nominal.home_mm)
                .map_err(|e| string_error(i, e))?;
            for ((a, x), t) in guide.entry_mm.iter_mut().zip(exit).zip(path.exit_mm) {
                *a += x - t;
            }
        }
        guides.push(guide);
    }
    Ok(guides)
}

/// What every string is built against: the design, the as-built spreads,
/// the true home, the tension the strings hold there and the undeclared
/// effects on the strings and the frame.
struct StringBuild<'a> {
    nominal: &'a Geometry,
    ab: &'a PhysicsAsBuilt,
    /// Where each string is tied at the home capture.
    home_attachments: Vec<Vec3<f64>>,
    home_tension_n: f64,
    /// `heavy-string`: every string's linear mass, g/m.
    heavy: Option<f64>,
    /// `frame-flex`: the factor on every guide's compliance.
    flex: f64,
}

/// The spools' and strings' spreads: the spool radius error shared by every
/// spool, and the distributions of each one's own errors.
struct SpoolSpreads {
    shared: f64,
    each: rand_distr::Normal<f64>,
    diameter: rand_distr::Normal<f64>,
    total_noise: rand_distr::Normal<f64>,
}

impl StringBuild<'_> {
    /// Every string with its guide, spool and home spool angle (spools,
    /// string dimensions and stiffness from stream 104, frame flex from 106).
    fn strings(
        &self,
        guides: Vec<Guide>,
        seed: u64,
    ) -> Result<(Vec<PhysicsString>, Vec<Spool>), SimError> {
        let ab = self.ab;
        let mut rng = stream(seed, 104);
        let shared = 1.0
            + normal(
                "as_built.spool_radius_shared_sigma",
                ab.spool_radius_shared_sigma,
            )?
            .sample(&mut rng);
        let each = normal(
            "as_built.spool_radius_each_sigma",
            ab.spool_radius_each_sigma,
        )?;
        let diameter = normal("as_built.string_diameter_sigma", ab.string_diameter_sigma)?;
        let total_noise = normal("as_built.string_total_sigma_mm", ab.string_total_sigma_mm)?;
        let spreads = SpoolSpreads {
            shared,
            each,
            diameter,
            total_noise,
        };
        let home_total_tension = self.home_tension_n * guides.len() as f64;

        let mut out = Vec::with_capacity(guides.len());
        let mut spools = Vec::with_capacity(guides.len());
        let mut flex_rng = stream(seed, 106);
        for (i, guide) in guides.into_iter().enumerate() {
            let (s, spool) = self.string(
                i,
                guide,
                &spreads,
                home_total_tension,
                &mut rng,
                &mut flex_rng,
            )?;
            out.push(s);
            spools.push(spool);
        }
        Ok((out, spools))
    }

    /// String `i` on `guide`: its spool wound in layers until it holds the
    /// whole string, its lead, stiffness, weight and frame flex, and the
    /// spool angle at the home capture.
    fn string(
        &self,
        i: usize,
        guide: Guide,
        spreads: &SpoolSpreads,
        home_total_tension: f64,
        rng: &mut ChaCha8Rng,
        flex_rng: &mut ChaCha8Rng,
    ) -> Result<(PhysicsString, Spool), SimError> {
        let ab = self.ab;
        let d = ab.string_diameter_mm * (1.0 + spreads.diameter.sample(rng)).max(0.5);
        let bare =
            self.nominal.pulley_radius_mm[i] * spreads.shared * (1.0 + spreads.each.sample(rng));
        let width = uniform(rng, ab.spool_width_mm);
        let lead_mm = uniform(rng, ab.lead_mm);
        let total_mm = ab.string_total_mm + spreads.total_noise.sample(rng) + lead_mm;
        let mut params = SpoolParams {
            bare_radius_mm: bare,
            string_diameter_mm: d,
            layer_packing: uniform(rng, ab.layer_packing),
            turns_per_layer: Vec::new(),
            layer_change_rad: uniform(rng, ab.layer_change_rad),
            crossover_rise_mm: uniform(rng, ab.crossover_rise_mm),
            crossover_rad: uniform(rng, ab.crossover_rad),
        };
        wind_layers(&mut params, width, total_mm, ab.pitch_excess, rng)
            .map_err(|e| string_error(i, e))?;
        let spool = Spool::new(params.clone());
        let towards_centre = unit(sub(self.nominal.home_mm, guide.entry_mm));
        let mut s = PhysicsString {
            guide,
            lead_mm,
            spool: params,
            stiffness_n: uniform(rng, ab.string_stiffness_n),
            mass_g_per_m: {
                let drawn = uniform(rng, ab.string_mass_g_per_m);
                self.heavy.unwrap_or(drawn)
            },
            total_mm,
            compliance_mm_per_n: self.flex * uniform(flex_rng, ab.frame_compliance_mm_per_n),
            flex_direction: tilted(towards_centre, 0.5, flex_rng),
            home_spool_rad: 0.0,
            line_runs: self.nominal.mechanical_advantage[i],
        };
        let home = s
            .natural_length(
                &self.home_attachments[i],
                self.home_tension_n,
                home_total_tension,
                0.0,
            )
            .map_err(|e| string_error(i, e))?;
        let wound = total_mm - home.natural_mm;
        s.home_spool_rad = spool
            .angle_for_wound(wound)
            .map_err(|e| string_error(i, format!("at home ({:.1} mm wound): {e}", wound)))?;
        Ok((s, spool))
    }
}

/// The spool's layers of `width` mm: layers until the spool holds the whole
/// string (`total_mm`), and one more; each layer's turns drawn with its
/// uneven pitch (`pitch_excess`).
fn wind_layers(
    params: &mut SpoolParams,
    width: f64,
    total_mm: f64,
    pitch_excess: [f64; 2],
    rng: &mut ChaCha8Rng,
) -> Result<(), &'static str> {
    let d = params.string_diameter_mm;
    let bare = params.bare_radius_mm;
    let mut capacity = 0.0;
    while capacity <= total_mm {
        let k = params.turns_per_layer.len();
        let turns = width / (d * (1.0 + uniform(rng, pitch_excess)));
        params.turns_per_layer.push(turns);
        capacity += TAU * turns * (bare + d / 2.0 + k as f64 * params.layer_packing * d);
        if params.turns_per_layer.len() > 100_000 {
            return Err("the spool would need over 100000 layers");
        }
    }
    params.turns_per_layer.push(width / d);
    Ok(())
}

/// The marker in the end-effector's body and the hand's posture (stream
/// 107); `marker-offset` sets the marker's distance and the posture's
/// amplitude.
fn draw_marker_and_posture(
    ab: &PhysicsAsBuilt,
    effects: &[PhysicsEffect],
    seed: u64,
) -> (Vec3<f64>, Posture) {
    let mut rng = stream(seed, 107);
    // Drawn whatever the effects, so that an effect changes only itself.
    let drawn = uniform(&mut rng, ab.marker_offset_mm);
    let offset = match effects.iter().rev().find_map(|e| match e {
        PhysicsEffect::MarkerOffset { mm, deg } => Some((*mm, *deg)),
        _ => None,
    }) {
        Some((mm, deg)) => (mm, deg.to_radians()),
        None => (drawn, ab.posture_amplitude_deg.to_radians()),
    };
    let direction = tilted(
        [0.0, 0.0, 1.0],
        rng.random_range(0.0..std::f64::consts::PI),
        &mut rng,
    );
    let marker_body_mm = direction.map(|x| x * offset.0);
    let k = TAU / ab.posture_wavelength_mm;
    let mut wave = [[0.0; 3]; 3];
    for w in wave.iter_mut() {
        let dir = tilted(
            [0.0, 0.0, 1.0],
            rng.random_range(0.0..std::f64::consts::PI),
            &mut rng,
        );
        *w = dir.map(|x| x * k);
    }
    let posture = Posture {
        amplitude_rad: offset.1,
        wave,
        phase: core::array::from_fn(|_| rng.random_range(0.0..TAU)),
        jitter_rad: ab.posture_jitter_deg.to_radians(),
    };
    (marker_body_mm, posture)
}

/// The tracker's true room-from-device rotation and translation (stream 108).
fn draw_room_transform(
    nominal: &Geometry,
    tr: &crate::sim::config::TrackerConfig,
    seed: u64,
) -> Result<([[f64; 3]; 3], Vec3<f64>), SimError> {
    let mut rng = stream(seed, 108);
    let axis = tilted(
        [0.0, 0.0, 1.0],
        rng.random_range(0.0..std::f64::consts::PI),
        &mut rng,
    );
    let room_rotation = rotation_about_axis(axis, tr.rotation_deg.to_radians());
    let t_noise = normal("tracker.translation_sigma_mm", tr.translation_sigma_mm)?;
    let room_translation_mm: Vec3<f64> = core::array::from_fn(|k| {
        nominal.room_from_device_translation_mm[k] + t_noise.sample(&mut rng)
    });
    Ok((room_rotation, room_translation_mm))
}

/// A turn as the end-effector makes it: on a planar device about the
/// plane's normal only (its yaw).
fn planar_turn(nominal: &Geometry, mut turn: Vec3<f64>) -> Vec3<f64> {
    if nominal.layout.planar {
        turn[0] = 0.0;
        turn[1] = 0.0;
    }
    turn
}

/// Where string `i` is tied when the end-effector's reference point is at
/// `p` and it is turned by `turn`: `p` itself when the strings meet there,
/// else `p + R(turn) attachment_i` (the carriage's corner).
pub(super) fn string_end(
    carriage: &CarriageConfig,
    i: usize,
    p: &Vec3<f64>,
    turn: &Vec3<f64>,
) -> Vec3<f64> {
    match carriage.attachment_mm.get(i) {
        None => *p,
        Some(a) => {
            let r = mat_vec(&rotation_from_vector(*turn), *a);
            core::array::from_fn(|k| p[k] + r[k])
        }
    }
}

impl PhysicsDevice {
    /// Build the device: draw its as-built physics from `seed`, apply the
    /// configured undeclared effects.
    pub fn new(config: &PhysicsConfig, seed: u64) -> Result<PhysicsDevice, SimError> {
        config.validate()?;
        // What the strings hold at the home capture is that and their jitter.
        let nominal = declaring_pretension(config.nominal.geometry(), config.tension.pretension_n);
        let ab = &config.as_built;
        let effects = parse_effects(&config.effects)?;
        // A planar device: the exits, home and the strings' meeting point
        // stay in the anchors' plane (the as-built errors are in it); the
        // guides swivel about the plane's normal, the strings sag out of
        // it, the hand turns about the normal only.
        let exits = draw_exits(&nominal, ab, seed)?;
        let home_mm = draw_home(&nominal, ab.home_sigma_mm, seed, 102)?;
        let guides = place_guides(&nominal, ab, &exits, seed)?;
        let (marker_body_mm, posture) = draw_marker_and_posture(ab, &effects, seed);
        // The carriage at home turned as the posture has it there (no jitter).
        let home_turn = planar_turn(&nominal, posture.rotation_vector(&home_mm));
        let home_attachments = (0..guides.len())
            .map(|i| string_end(&config.carriage, i, &home_mm, &home_turn))
            .collect();

        let home_tension_n = config.tension.pretension_n + config.tension.jitter_n / 2.0;
        let build = StringBuild {
            nominal: &nominal,
            ab,
            home_attachments,
            home_tension_n,
            heavy: effects.iter().find_map(|e| match e {
                PhysicsEffect::HeavyString { g_per_m } => Some(*g_per_m),
                _ => None,
            }),
            flex: effects
                .iter()
                .map(|e| match e {
                    PhysicsEffect::FrameFlex { factor } => *factor,
                    _ => 1.0,
                })
                .product(),
        };
        let (strings, spools) = build.strings(guides, seed)?;
        if let Some(i) = effects.iter().find_map(|e| match e {
            PhysicsEffect::Latency {
                string: Some(i), ..
            } if *i >= strings.len() => Some(*i),
            _ => None,
        }) {
            return Err(SimError::EffectSpec {
                spec: format!("latency:string={i}"),
                problem: format!(
                    "the device has {} strings (0..{})",
                    strings.len(),
                    strings.len()
                ),
            });
        }

        let (room_rotation, room_translation_mm) =
            draw_room_transform(&nominal, &config.tracker, seed)?;

        Ok(PhysicsDevice {
            seed,
            nominal,
            strings,
            home_mm,
            home_tension_n,
            room_rotation,
            room_translation_mm,
            room_scale: config.tracker.scale,
            marker_body_mm,
            posture,
            effects,
            config: config.clone(),
            spools,
        })
    }
}
