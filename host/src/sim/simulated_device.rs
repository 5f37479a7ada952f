//! The as-built device: its true parameters, drawn once per device seed, and
//! the string physics (true length -> encoder counts).

use rand::rngs::ChaCha8Rng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use spidar_core::geometry::{
    device_from_room, mat_t_vec, mat_vec, norm, room_from_device, rotation_about_axis, sub,
};
use spidar_core::model::{EffectTerm, Frame, StringLaw, StringLayout, Vec3, WINDING_ORDER};
use spidar_core::STRINGS;

use super::config::{AsBuiltConfig, SimConfig, TrackerConfig};
use spidar_core::string_law::{
    cos2_inclination_q16, guide_elevation_q32, guide_elevation_rad, EffectContext,
};

use super::effects::{parse_effects, InjectedEffect};
use super::SimError;
use crate::data::dataset::Geometry;

/// Independent random streams derived from one seed (splitmix64), so that
/// e.g. switching tracker occlusion off does not change the trajectory.
pub(crate) fn stream(seed: u64, purpose: u64) -> ChaCha8Rng {
    let mut z = seed ^ purpose.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    ChaCha8Rng::seed_from_u64(z)
}

/// `N(0, sigma)`; `field` names the configuration key in the error.
pub(crate) fn normal(field: &str, sigma: f64) -> Result<Normal<f64>, SimError> {
    Normal::new(0.0, sigma).map_err(|e| {
        SimError::Config(crate::ConfigError::new(
            field.to_string(),
            format!("{sigma} is not a standard deviation: {e}"),
        ))
    })
}

/// One simulated device as built. The same device gives any number of
/// sessions (train and test) with the same as-built errors.
#[derive(Clone, Debug)]
pub struct SimulatedDevice {
    pub config: SimConfig,
    /// The device seed.
    pub seed: u64,
    /// The design, as written to `geometry.toml`.
    pub nominal: Geometry,
    /// True anchors, true home, true room-from-device transform.
    pub frame: Frame<f64>,
    /// True base winding law of each string: `[r_home, -d^2/(4 pi), 0, 0]`.
    pub laws: [StringLaw; STRINGS],
    /// True bare pulley radius `r0`, mm.
    pub bare_radius_mm: [f64; STRINGS],
    /// String wound on each pulley at initialization, `w_home`, mm.
    pub home_wound_mm: [f64; STRINGS],
    /// True total length of each string, mm.
    pub string_total_mm: [f64; STRINGS],
    /// All injected effects, resolved per string, in order.
    pub injected: Vec<InjectedEffect>,
    /// The model-family terms among them, in order (what identification should find).
    pub effects: Vec<EffectTerm>,
}

/// True anchors (stream 1): each coordinate off the design (a planar
/// device's anchors stay in its plane).
fn draw_anchors(
    nominal: &Geometry,
    ab: &AsBuiltConfig,
    seed: u64,
) -> Result<[Vec3<f64>; STRINGS], SimError> {
    let mut rng = stream(seed, 1);
    let anchor_noise = normal("as_built.anchor_sigma_mm", ab.anchor_sigma_mm)?;
    let planar = nominal.layout.planar;
    let mut anchors = nominal.anchors_mm;
    for a in anchors.iter_mut() {
        for (k, x) in a.iter_mut().enumerate() {
            let e = anchor_noise.sample(&mut rng);
            // A planar device's anchors stay in its plane.
            if !(planar && k == 2) {
                *x += e;
            }
        }
    }
    Ok(anchors)
}

/// The nominal geometry a simulator writes, declaring the pretension its
/// initialization commands at the home capture (`home_tension_n`; none for
/// a pretension of 0).
pub(crate) fn declaring_pretension(nominal: Geometry, pretension_n: f64) -> Geometry {
    Geometry {
        home_tension_n: (pretension_n > 0.0).then_some(pretension_n),
        anchor_sd_mm: None,
        home_sd_mm: None,
        ..nominal
    }
}

/// A true home off the nominal one by `sigma_mm` per axis, drawn from the
/// device's random stream `stream_id` (in the anchors' plane on a planar
/// device): where the built-in initialization really is. Both simulators
/// draw it so (the model's stream 2, the independent one's 102).
pub(crate) fn draw_home(
    nominal: &Geometry,
    sigma_mm: f64,
    seed: u64,
    stream_id: u64,
) -> Result<Vec3<f64>, SimError> {
    let mut rng = stream(seed, stream_id);
    let home_noise = normal("as_built.home_sigma_mm", sigma_mm)?;
    let mut home: Vec3<f64> =
        core::array::from_fn(|k| nominal.home_mm[k] + home_noise.sample(&mut rng));
    if nominal.layout.planar {
        home[2] = nominal.home_mm[2];
    }
    Ok(home)
}

/// True bare pulley radii (stream 3): a machining error shared by every
/// pulley and each one's own.
fn draw_bare_radii(
    nominal: &Geometry,
    ab: &AsBuiltConfig,
    seed: u64,
) -> Result<[f64; STRINGS], SimError> {
    let mut rng = stream(seed, 3);
    let shared = 1.0
        + normal(
            "as_built.pulley_radius_shared_sigma",
            ab.pulley_radius_shared_sigma,
        )?
        .sample(&mut rng);
    let each = normal(
        "as_built.pulley_radius_each_sigma",
        ab.pulley_radius_each_sigma,
    )?;
    Ok(core::array::from_fn(|i| {
        nominal.pulley_radius_mm[i] * shared * (1.0 + each.sample(&mut rng))
    }))
}

/// True total length of each string (stream 4), mm.
fn draw_string_totals(ab: &AsBuiltConfig, seed: u64) -> Result<[f64; STRINGS], SimError> {
    let mut rng = stream(seed, 4);
    let total_noise = normal("as_built.string_total_sigma_mm", ab.string_total_sigma_mm)?;
    Ok(core::array::from_fn(|_| {
        ab.string_total_mm + total_noise.sample(&mut rng)
    }))
}

/// The tracker's true room-from-device rotation and translation (stream 5).
fn draw_room_transform(
    nominal: &Geometry,
    tr: &TrackerConfig,
    seed: u64,
) -> Result<([[f64; 3]; 3], Vec3<f64>), SimError> {
    let planar = nominal.layout.planar;
    let mut rng = stream(seed, 5);
    let axis_draw = normal("tracker.rotation_deg", 1.0)?;
    let mut axis: Vec3<f64> = core::array::from_fn(|_| axis_draw.sample(&mut rng));
    let n = norm(axis);
    axis = if n > 0.0 && !planar {
        axis.map(|x| x / n)
    } else {
        // A planar device's tracker frame turns about the plane's normal.
        [0.0, 0.0, 1.0]
    };
    let room_rotation = rotation_about_axis(axis, tr.rotation_deg.to_radians());
    let t_noise = normal("tracker.translation_sigma_mm", tr.translation_sigma_mm)?;
    let room_translation: Vec3<f64> = core::array::from_fn(|k| {
        let e = t_noise.sample(&mut rng);
        nominal.room_from_device_translation_mm[k] + if planar && k == 2 { 0.0 } else { e }
    });
    Ok((room_rotation, room_translation))
}

/// Every injected effect on a string is on one of the device's strings.
fn check_effect_strings(
    injected: &[InjectedEffect],
    layout: &StringLayout,
) -> Result<(), SimError> {
    for e in injected {
        let string = match *e {
            InjectedEffect::Model(term) => Some(term.string),
            InjectedEffect::AnchorShift { string, .. } | InjectedEffect::Speed { string, .. } => {
                Some(string)
            }
            InjectedEffect::TrackerScale { .. } => None,
        };
        if let Some(s) = string.filter(|&s| !layout.is_active(usize::from(s))) {
            return Err(SimError::Config(crate::ConfigError::new(
                "effects",
                format!(
                    "an effect on string {s}, but the device has {} strings (0..{})",
                    layout.count(),
                    layout.count() - 1
                ),
            )));
        }
    }
    Ok(())
}

/// Apply the injected effects on the frame (anchor shifts, tracker scale)
/// to `frame`; the model-family terms among them, in order.
fn apply_effects(injected: &[InjectedEffect], frame: &mut Frame<f64>) -> Vec<EffectTerm> {
    let mut effects = Vec::new();
    for e in injected {
        match *e {
            InjectedEffect::Model(term) => effects.push(term),
            InjectedEffect::AnchorShift { string, mm } => {
                let a = &mut frame.anchors[usize::from(string)];
                for k in 0..3 {
                    a[k] += mm[k];
                }
            }
            InjectedEffect::TrackerScale { relative } => frame.room_scale *= 1.0 + relative,
            InjectedEffect::Speed { .. } => {}
        }
    }
    effects
}

/// Each string's winding at initialization: the string wound on its pulley
/// at the true home (`w_home`, mm) and the true base winding law
/// `[r_home, -d^2/(4 pi), 0, 0]` (level layers) or `[r0, 0, 0, 0]`.
fn home_windings(
    frame: &Frame<f64>,
    string_total_mm: &[f64; STRINGS],
    bare_radius_mm: &[f64; STRINGS],
    ab: &AsBuiltConfig,
    counts_per_rev: u32,
) -> Result<([StringLaw; STRINGS], [f64; STRINGS]), SimError> {
    let d = ab.string_diameter_mm;
    let mut home_wound_mm = [0.0; STRINGS];
    let mut laws = [StringLaw::polynomial(counts_per_rev, [0.0; WINDING_ORDER]); STRINGS];
    for i in 0..STRINGS {
        let home_length = norm(sub(frame.home, frame.anchors[i]));
        let wound = string_total_mm[i] - home_length;
        if wound <= 0.0 {
            return Err(SimError::Config(crate::ConfigError::new(
                "as_built.string_total_mm",
                format!(
                    "string {i} ({:.1} mm) is shorter than its home length {home_length:.1} mm",
                    string_total_mm[i]
                ),
            )));
        }
        home_wound_mm[i] = wound;
        let r0 = bare_radius_mm[i];
        laws[i].winding_mm = if ab.winding_growth {
            let pi = std::f64::consts::PI;
            [
                (r0 * r0 + wound * d * d / pi).sqrt(),
                -d * d / (4.0 * pi),
                0.0,
                0.0,
            ]
        } else {
            [r0, 0.0, 0.0, 0.0]
        };
    }
    Ok((laws, home_wound_mm))
}

impl SimulatedDevice {
    /// Build the device: draw its as-built errors from `seed`, apply the
    /// configured injected effects.
    pub fn new(config: &SimConfig, seed: u64) -> Result<SimulatedDevice, SimError> {
        config.validate()?;
        let nominal = declaring_pretension(config.nominal.geometry(), config.tension.pretension_n);
        let ab = &config.as_built;
        let anchors = draw_anchors(&nominal, ab, seed)?;
        let home = draw_home(&nominal, ab.home_sigma_mm, seed, 2)?;
        let bare_radius_mm = draw_bare_radii(&nominal, ab, seed)?;
        let string_total_mm = draw_string_totals(ab, seed)?;
        let (room_rotation, room_translation) =
            draw_room_transform(&nominal, &config.tracker, seed)?;
        let mut frame = Frame {
            layout: nominal.layout,
            anchors,
            home,
            room_rotation,
            room_translation,
            room_scale: config.tracker.scale,
        };

        let injected = parse_effects(&config.effects)?;
        check_effect_strings(&injected, &nominal.layout)?;
        let effects = apply_effects(&injected, &mut frame);
        let (laws, home_wound_mm) = home_windings(
            &frame,
            &string_total_mm,
            &bare_radius_mm,
            ab,
            nominal.counts_per_rev[0],
        )?;

        Ok(SimulatedDevice {
            config: config.clone(),
            seed,
            nominal,
            frame,
            laws,
            bare_radius_mm,
            home_wound_mm,
            string_total_mm,
            injected,
            effects,
        })
    }

    /// True `|home - anchor_i|`, mm.
    pub fn home_length_mm(&self, string: usize) -> f64 {
        norm(sub(self.frame.home, self.frame.anchors[string]))
    }

    /// Winding radius at initialization, `r_home`, mm.
    pub fn home_winding_radius_mm(&self, string: usize) -> f64 {
        self.laws[string].winding_mm[0]
    }

    /// Pulley angle of `counts`, rad.
    pub fn theta(&self, counts: i32) -> f64 {
        2.0 * std::f64::consts::PI * f64::from(counts) / f64::from(self.nominal.counts_per_rev[0])
    }

    /// The true base winding law: string paid out since home at angle `theta`, mm.
    pub fn payout_mm(&self, string: usize, theta: f64) -> f64 {
        let w = &self.laws[string].winding_mm;
        w[0] * theta + w[1] * theta * theta
    }

    /// True string length the base law gives for `counts` (no effects):
    /// `|home - anchor| + payout(theta(counts))`, mm.
    pub fn base_length_mm(&self, string: usize, counts: i32) -> f64 {
        self.home_length_mm(string) + self.payout_mm(string, self.theta(counts))
    }

    /// Sum of the injected model-family terms of `string`.
    pub fn effects_mm(&self, string: usize, ctx: &EffectContext) -> f64 {
        self.effects
            .iter()
            .filter(|t| usize::from(t.string) == string)
            .map(|t| t.effect.contribution_f64(ctx))
            .sum()
    }

    /// Inverse of the base law: the angle at which `payout` mm are paid out.
    fn theta_for_payout(&self, string: usize, payout: f64) -> Option<f64> {
        if payout > self.home_wound_mm[string] {
            return None; // the pulley would be empty
        }
        let [r, b, ..] = self.laws[string].winding_mm;
        if b == 0.0 {
            return Some(payout / r);
        }
        let disc = r * r + 4.0 * b * payout;
        if disc < 0.0 {
            return None;
        }
        Some(2.0 * payout / (r + disc.sqrt()))
    }

    /// The run-time inputs of `string` at `position` that the model's terms
    /// read ([`Self::counts_for_length`]): direction, tension, the total
    /// tension of the active strings, time, and the
    /// inclination and elevation quantized as the device reads them
    /// ([`cos2_inclination_q16`], [`guide_elevation_q32`]).
    pub(crate) fn conditions(
        &self,
        string: usize,
        position: &Vec3<f64>,
        direction: i8,
        tension_n: f64,
        total_tension_n: f64,
        t_s: f64,
    ) -> EffectContext {
        let anchor = &self.frame.anchors[string];
        let cos2 = cos2_inclination_q16(anchor, position);
        let home_cos2 = cos2_inclination_q16(anchor, &self.frame.home);
        EffectContext {
            theta: 0.0,
            payout_mm: 0.0,
            home_length_mm: 0.0,
            direction,
            tension_n,
            total_tension_n,
            time_s: t_s,
            cos2_inclination: f64::from(cos2) / 65536.0,
            home_cos2_inclination: f64::from(home_cos2) / 65536.0,
            // The simulators inject a latency as `speed` (the true length's
            // rate), not as a model term.
            payout_rate_mm_s: 0.0,
            guide_elevation_rad: guide_elevation_rad(guide_elevation_q32(
                anchor,
                &self.frame.home,
                position,
            )),
            home_guide_elevation_rad: guide_elevation_rad(guide_elevation_q32(
                anchor,
                &self.frame.home,
                &self.frame.home,
            )),
        }
    }

    /// Encoder counts of `string` when its true length is `length_mm`,
    /// with `extra_mm` of length not explained by the model families (speed,
    /// abnormal motor) and the model terms evaluated at the true angle. Solves
    /// `length = home_length + payout(theta) + extra + effects(theta)` by
    /// fixed-point iteration, then quantizes to whole counts. `conditions`
    /// holds the string's run-time inputs (direction, tension, time,
    /// inclination); its angle, payout and home length are the solver's.
    pub(crate) fn counts_for_length(
        &self,
        string: usize,
        length_mm: f64,
        extra_mm: f64,
        conditions: EffectContext,
    ) -> Result<i32, SimError> {
        let t_s = conditions.time_s;
        let home_length_mm = self.home_length_mm(string);
        let target = length_mm - home_length_mm - extra_mm;
        let exhausted = || SimError::StringExhausted {
            string,
            length_mm,
            t_s,
        };
        let mut theta = self
            .theta_for_payout(string, target)
            .ok_or_else(exhausted)?;
        let has_terms = self.effects.iter().any(|t| usize::from(t.string) == string);
        if has_terms {
            let mut converged = false;
            for _ in 0..200 {
                let x = EffectContext {
                    theta,
                    payout_mm: self.payout_mm(string, theta),
                    home_length_mm,
                    ..conditions
                };
                let next = self
                    .theta_for_payout(string, target - self.effects_mm(string, &x))
                    .ok_or_else(exhausted)?;
                let step = (next - theta).abs();
                theta = next;
                if step <= 1e-12 * (1.0 + theta.abs()) {
                    converged = true;
                    break;
                }
            }
            if !converged {
                return Err(SimError::NoConvergence { string, t_s });
            }
        }
        let counts = (theta * f64::from(self.nominal.counts_per_rev[0])
            / (2.0 * std::f64::consts::PI))
            .round();
        if counts.abs() > f64::from(i32::MAX) {
            return Err(exhausted());
        }
        Ok(counts as i32)
    }

    /// Room position (tracker frame) of a device-frame position.
    pub fn room_from_device(&self, p: &Vec3<f64>) -> Vec3<f64> {
        room_from_device(&self.frame, *p)
    }

    /// Device-frame position of a room (tracker frame) position.
    pub fn device_from_room(&self, p: &Vec3<f64>) -> Vec3<f64> {
        device_from_room(&self.frame, *p)
    }

    /// Room-frame velocity of a device-frame velocity.
    pub fn room_velocity_from_device(&self, v: &Vec3<f64>) -> Vec3<f64> {
        mat_vec(&self.frame.room_rotation, *v).map(|x| x * self.frame.room_scale)
    }

    /// Device-frame velocity of a room-frame velocity.
    pub fn device_velocity_from_room(&self, v: &Vec3<f64>) -> Vec3<f64> {
        mat_t_vec(&self.frame.room_rotation, *v).map(|x| x / self.frame.room_scale)
    }

    /// Centre of the sampled volume in the room frame: the nominal room image
    /// of the nominal home (what the experimenters would display).
    pub fn volume_centre_room(&self) -> Vec3<f64> {
        core::array::from_fn(|k| {
            self.nominal.home_mm[k] + self.nominal.room_from_device_translation_mm[k]
        })
    }
}
