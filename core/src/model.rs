//! The calibration model in physical units: what the host identifies and what
//! [`crate::blob`] compiles into fixed point for the device.
//!
//! A calibration is (see `../shared/notes/model-spine.md`):
//! 1. a [`Frame`]: anchors, home and the room-from-device transform;
//! 2. one [`StringLaw`] per string plus an ordered list of [`EffectTerm`]s:
//!    the string length as a function of what the device knows at run time
//!    ([`StringInputs`]);
//! 3. an optional position [`crate::correction`] (NN or SVR).
//!
//! Forward kinematics turns the string lengths into a device-frame position,
//! the frame maps it to the room, and the position correction is applied last.

use serde::{Deserialize, Serialize};

use crate::STRINGS;

pub use crate::geometry::Vec3;

/// Which of the controller's [`STRINGS`] channels carry a string, and whether
/// the end-effector moves in a plane.
///
/// A Scalable-SPIDAR uses all 8 channels; a SPIDAR-G, a planar SPIDAR, a
/// cable robot with 4 lines or a rig with strings removed use 3 to 8 of them.
/// Arrays indexed by string keep their 8 entries (index = encoder channel);
/// entries of inactive channels are ignored by kinematics, string laws,
/// tension distribution and safety.
///
/// Planar: the anchors lie in the plane `z = anchors' z` of the device frame
/// and the end-effector moves in it; kinematics solves `x, y` only.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringLayout {
    /// Bit `i` set: channel `i` carries a string.
    pub active: u8,
    /// The end-effector moves in the anchors' plane (2 degrees of freedom).
    pub planar: bool,
}

impl Default for StringLayout {
    /// All 8 channels, 3-D: a Scalable-SPIDAR.
    fn default() -> Self {
        Self::ALL
    }
}

impl StringLayout {
    /// All [`STRINGS`] channels, 3-D.
    pub const ALL: StringLayout = StringLayout {
        active: u8::MAX,
        planar: false,
    };

    /// The first `n` channels (`n` clamped to `0..=STRINGS`).
    pub const fn first(n: usize, planar: bool) -> StringLayout {
        let n = if n > STRINGS { STRINGS } else { n };
        let active = if n >= 8 { u8::MAX } else { (1u8 << n) - 1 };
        StringLayout { active, planar }
    }

    /// Whether channel `i` carries a string.
    #[inline]
    pub const fn is_active(&self, i: usize) -> bool {
        i < STRINGS && self.active & (1 << i) != 0
    }

    /// Number of strings.
    #[inline]
    pub const fn count(&self) -> usize {
        self.active.count_ones() as usize
    }

    /// Indices of the active channels, ascending.
    pub fn indices(self) -> impl Iterator<Item = usize> + Clone {
        (0..STRINGS).filter(move |&i| self.is_active(i))
    }

    /// Degrees of freedom of the end-effector's position: 2 (planar) or 3.
    #[inline]
    pub const fn dof(&self) -> usize {
        if self.planar {
            2
        } else {
            3
        }
    }

    /// Strings beyond the position's degrees of freedom (`count - dof`,
    /// 0 when there are fewer). One spare string lets forward kinematics see
    /// that the strings disagree; telling which string is faulty needs two.
    #[inline]
    pub const fn redundancy(&self) -> usize {
        self.count().saturating_sub(self.dof())
    }
}

/// Geometry of the device: where the strings leave the frame, where the
/// end-effector was at initialization, and how the device frame sits in the
/// tracker's room frame.
///
/// Generic over the float type: the device runs `Frame<f32>`, the host
/// identifies `Frame<f64>`. This is the one geometry type of the project.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Frame<F> {
    /// String exit points (device frame, mm), index = encoder index;
    /// entries of channels [`StringLayout`] marks inactive are ignored.
    pub anchors: [Vec3<F>; STRINGS],
    /// Which channels carry a string; planar or 3-D. Defaults to all 8, 3-D.
    #[serde(default)]
    pub layout: StringLayout,
    /// End-effector position at initialization (device frame, mm).
    pub home: Vec3<F>,
    /// Rotation part of `p_room = scale * R * p_device + t`, row-major.
    pub room_rotation: [[F; 3]; 3],
    /// Translation `t` of `p_room = scale * R * p_device + t` (mm), the paper's eq. 6.
    pub room_translation: Vec3<F>,
    /// Scale of the tracker relative to the device (1 for a well calibrated tracker).
    pub room_scale: F,
}

/// What the device knows about one string at run time, besides geometry.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringInputs {
    /// Encoder counts since initialization (home); increases as string is paid out.
    pub counts: [i32; STRINGS],
    /// Direction of the last motion of each string: +1 paying out, -1 reeling
    /// in, 0 unknown (no motion since home). See [`crate::encoder::DirectionTracker`].
    pub direction: [i8; STRINGS],
    /// Commanded tension of each string, in millinewtons.
    pub tension_mn: [u16; STRINGS],
    /// Time since initialization, milliseconds.
    pub time_ms: u32,
    /// `cos^2` of each string's inclination from the horizontal (the
    /// device frame's z axis is up) at the position the loop holds, Q0.16
    /// (65535 for a level string, 0 for a plumb one), what a sag term scales
    /// with ([`Effect::Sag`]); see
    /// [`cos2_inclinations`](crate::string_law::cos2_inclinations).
    pub cos2_inclination_q16: [u16; STRINGS],
    /// Each string's encoder count rate, counts per second (positive paying
    /// out), what a latency term scales with ([`Effect::Latency`]): the
    /// device's windowed difference over the last few milliseconds
    /// ([`crate::encoder::CountRate`]), the host's from the neighbouring
    /// rows of a streamed session; 0 where the speed is not observed (a
    /// static session's rows, captured at rest seconds apart). Absent in
    /// files written before it existed (zeros).
    #[serde(default)]
    pub count_rate_cps: [i32; STRINGS],
    /// The elevation of each string's chord from its anchor to the
    /// position the loop holds, out of the plane across the string's guide
    /// swivel axis (the frame edge: device `z`, pointing away from the home
    /// height), Q0.32 turns, what a guide term reads ([`Effect::Guide`]);
    /// taken where [`cos2_inclination_q16`](Self::cos2_inclination_q16) is,
    /// see [`guide_elevations`](crate::string_law::guide_elevations). Absent
    /// in files written before it existed (zeros).
    #[serde(default)]
    pub guide_elevation_q32: [i32; STRINGS],
}

/// Highest power of the pulley angle in a winding law.
pub const WINDING_ORDER: usize = 4;

/// Base winding law of one string: the length paid out since home as a
/// polynomial in the pulley angle `theta = 2 pi counts / counts_per_rev` (rad):
///
/// `payout(theta) = sum_{k=1..=WINDING_ORDER} winding_mm[k-1] * theta^k`.
///
/// For a pulley whose winding radius shrinks linearly as string is paid out
/// (`r(theta) = r_home - d^2/(2 pi) theta`, string of diameter `d` in level
/// layers) the law is exactly quadratic: `winding_mm = [r_home, -d^2/(4 pi), 0, 0]`.
///
/// A spool wound in layers departs from any smooth polynomial: within a layer
/// the radius is constant, at a layer change it steps by about one string
/// diameter, so the payout is a staircase of slopes around the polynomial
/// (1.7 to 4.7 mm peak to peak on the independent simulator's spools, one
/// period per layer). [`StringLaw::layers`] holds that departure as a table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StringLaw {
    /// Quadrature counts per pulley revolution.
    pub counts_per_rev: u32,
    /// Coefficients of theta^1 .. theta^WINDING_ORDER, mm / rad^k.
    pub winding_mm: [f64; WINDING_ORDER],
    /// The spool's departure from the polynomial, added to the payout
    /// (empty: none; absent in files written before it existed).
    #[serde(default)]
    pub layers: LayerTable,
}

impl StringLaw {
    /// A law that is the polynomial alone (no layer table).
    pub const fn polynomial(counts_per_rev: u32, winding_mm: [f64; WINDING_ORDER]) -> StringLaw {
        StringLaw {
            counts_per_rev,
            winding_mm,
            layers: LayerTable::NONE,
        }
    }
}

/// Most knots of a [`LayerTable`].
pub const LAYER_KNOTS: usize = 32;

/// Largest `|knot|` of a [`LayerTable`], mm: a layer departure is a few mm;
/// the bound keeps the fixed-point interpolation far from overflow.
pub const MAX_LAYER_MM: f64 = 100.0;

/// Largest `step_log2` of a [`LayerTable`] (knots 2^30 counts apart).
pub const MAX_LAYER_STEP_LOG2: u8 = 30;

/// The departure of a string's payout from its winding polynomial, piecewise
/// linear in the encoder counts (the flexible part of the winding law, see
/// `docs/design.md`, "Layer tables").
///
/// Knot `k` sits at `start_counts + k 2^step_log2` counts since home and holds
/// `knots_mm[k]`; between knots the departure is interpolated linearly, and
/// outside the knots it is held at the first or last knot's value, so that
/// beyond the payout range it was fitted on the law is the polynomial shifted
/// by a bounded constant: nothing in it can grow there. Knots a power of two
/// counts apart let the device find the segment with a shift (no 64-bit
/// division on a Cortex-M). Counts, not angles, so that host and device place
/// the knots at exactly the same counts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerTable {
    /// Counts since home of the first knot.
    pub start_counts: i32,
    /// Knots are `2^step_log2` counts apart, `0..=MAX_LAYER_STEP_LOG2`.
    pub step_log2: u8,
    /// Departure at each knot, mm (at most [`LAYER_KNOTS`]).
    pub knots_mm: Knots<f64>,
}

impl Default for LayerTable {
    fn default() -> Self {
        Self::NONE
    }
}

impl LayerTable {
    /// No table: the law is its polynomial.
    pub const NONE: LayerTable = LayerTable {
        start_counts: 0,
        step_log2: 0,
        knots_mm: Knots::EMPTY,
    };

    /// Whether the table has no knots (adds nothing).
    pub const fn is_empty(&self) -> bool {
        self.knots_mm.len == 0
    }

    /// Counts since home of knot `k`.
    pub fn knot_counts(&self, k: usize) -> i64 {
        i64::from(self.start_counts) + ((k as i64) << self.step_log2.min(MAX_LAYER_STEP_LOG2))
    }

    /// Where `counts` falls: the segment's first knot and how far along it
    /// (`0..2^step_log2` counts), or the end knot it is held at
    /// (`(k, 0)`). `None` when the table is empty.
    pub fn locate(&self, counts: i32) -> Option<(usize, u32)> {
        locate_knot(
            self.start_counts,
            self.step_log2,
            self.knots_mm.len(),
            counts,
        )
    }

    /// The departure at `counts` (mm), f64 reference of the device's table.
    pub fn departure_mm(&self, counts: i32) -> f64 {
        let Some((k, along)) = self.locate(counts) else {
            return 0.0;
        };
        let v = self.knots_mm.as_slice();
        if along == 0 {
            return v[k];
        }
        // 2^step_log2 exactly (a power of two below 2^31), without a libm
        // call per row and string.
        let step = f64::from(1u32 << self.step_log2.min(MAX_LAYER_STEP_LOG2));
        v[k] + (v[k + 1] - v[k]) * (f64::from(along) / step)
    }
}

/// Where `counts` falls in a table of `len` knots from `start_counts`,
/// `2^step_log2` counts apart (see [`LayerTable::locate`]); integer only, the
/// same on host and device.
#[inline]
pub fn locate_knot(
    start_counts: i32,
    step_log2: u8,
    len: usize,
    counts: i32,
) -> Option<(usize, u32)> {
    if len == 0 {
        return None;
    }
    let s = u32::from(step_log2.min(MAX_LAYER_STEP_LOG2));
    let u = i64::from(counts) - i64::from(start_counts);
    if u <= 0 {
        return Some((0, 0));
    }
    let k = (u >> s) as u64;
    if k >= (len - 1) as u64 {
        return Some((len - 1, 0));
    }
    Some((k as usize, (u & ((1i64 << s) - 1)) as u32))
}

/// Up to [`LAYER_KNOTS`] values in a fixed array (so that laws stay `Copy`),
/// serialized as a sequence of the values present.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Knots<T> {
    values: [T; LAYER_KNOTS],
    len: u8,
}

impl<T: Copy + Default> Knots<T> {
    /// The values, or `None` when there are more than [`LAYER_KNOTS`].
    pub fn from_slice(values: &[T]) -> Option<Knots<T>> {
        if values.len() > LAYER_KNOTS {
            return None;
        }
        let mut out = [T::default(); LAYER_KNOTS];
        out[..values.len()].copy_from_slice(values);
        Some(Knots {
            values: out,
            len: values.len() as u8,
        })
    }
}

impl<T> Knots<T> {
    /// The values present.
    pub fn as_slice(&self) -> &[T] {
        &self.values[..self.len()]
    }
    /// The values present, mutable.
    pub fn as_mut_slice(&mut self) -> &mut [T] {
        let n = self.len();
        &mut self.values[..n]
    }
    /// Number of values.
    pub const fn len(&self) -> usize {
        let n = self.len as usize;
        if n > LAYER_KNOTS {
            LAYER_KNOTS
        } else {
            n
        }
    }
    /// Whether there are none.
    pub const fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl Knots<f64> {
    /// No values.
    pub const EMPTY: Knots<f64> = Knots {
        values: [0.0; LAYER_KNOTS],
        len: 0,
    };
}

impl Knots<i64> {
    /// No values.
    pub const EMPTY_I64: Knots<i64> = Knots {
        values: [0; LAYER_KNOTS],
        len: 0,
    };
}

impl<T: Serialize> Serialize for Knots<T> {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_seq(self.as_slice())
    }
}

impl<'de, T: Deserialize<'de> + Copy + Default> Deserialize<'de> for Knots<T> {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Visit<T>(core::marker::PhantomData<T>);
        impl<'de, T: Deserialize<'de> + Copy + Default> serde::de::Visitor<'de> for Visit<T> {
            type Value = Knots<T>;
            fn expecting(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
                write!(f, "at most {LAYER_KNOTS} knot values")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<Self::Value, A::Error> {
                let mut values = [T::default(); LAYER_KNOTS];
                let mut len = 0;
                while let Some(v) = seq.next_element()? {
                    if len == LAYER_KNOTS {
                        return Err(serde::de::Error::invalid_length(len + 1, &self));
                    }
                    values[len] = v;
                    len += 1;
                }
                Ok(Knots {
                    values,
                    len: len as u8,
                })
            }
        }
        deserializer.deserialize_seq(Visit(core::marker::PhantomData))
    }
}

/// One physically meaningful correction term of one string's length.
///
/// Each variant names the run-time variable it depends on; its contribution is
/// added to the string length given by the frame and the base winding law.
/// `payout` below means the base winding law's output (mm paid out since home).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Effect {
    /// Constant length error, e.g. a string not taut when home was declared: `+ mm`.
    Offset { mm: f64 },
    /// Relative error of the payout, e.g. a pulley of another diameter or an
    /// encoder of another resolution: `+ relative * payout`.
    Scale { relative: f64 },
    /// Extra winding-law order, e.g. uneven layering: `+ mm_per_rad_pow * theta^power`.
    Winding { power: u8, mm_per_rad_pow: f64 },
    /// Pulley eccentricity, periodic in the pulley angle:
    /// `+ sin_mm * sin(theta) + cos_mm * (cos(theta) - 1)`.
    Eccentricity { sin_mm: f64, cos_mm: f64 },
    /// String elasticity of one string, the stretch of its free span:
    /// `+ per_newton * tension_N * (home_length + payout)`.
    Elasticity { per_newton: f64 },
    /// Direction-dependent backlash / hysteresis: `+ half_width_mm * direction`.
    Backlash { half_width_mm: f64 },
    /// Drift with time since initialization (creep, temperature): `+ mm_per_s * t`.
    Drift { mm_per_s: f64 },
    /// Creep (thermal or plastic) of the whole string: its natural length
    /// grows by `per_s * t` of itself, `t` the time since home (s), so the
    /// counts fall short of the string by that much of its whole length:
    /// `+ per_s * t * (home_length + payout)`. The time analogue of
    /// [`Elasticity`](Effect::Elasticity); a [`Drift`](Effect::Drift) is
    /// the same on every length. `|per_s| <=`
    /// [`MAX_CREEP_PER_S`](crate::string_law::MAX_CREEP_PER_S).
    Creep { per_s: f64 },
    /// String slip: a step at a time since initialization: `+ mm * [t >= at_s]`.
    Slip { at_s: f64, mm: f64 },
    /// Sag of a heavy string: a span of length `l` and linear weight `w`
    /// under tension `T` is longer than its chord by `w^2 cos^2(a) l^3 /
    /// (24 T^2)` (parabolic catenary, `a` the chord's inclination from the
    /// horizontal). The counts measure the string, the model the chord, and
    /// the string already sagged when home was captured, so
    /// `- mm_at_1m_1n * cos^2(a) * (l / 1 m)^3 / (T / 1 N)^2
    ///  + home_mm_at_1m * cos^2(a_home) * (home_length / 1 m)^3`:
    /// `mm_at_1m_1n = w^2 / 24`, the sag of a level 1 m span at 1 N (1.6 mm
    /// for 20 g/m), and `home_mm_at_1m = w^2 / (24 T_home^2)`, that of a
    /// level 1 m span at the home capture's tension (both positive for a
    /// real sag; their ratio is `T_home^2`). `cos^2(a)` from
    /// [`StringInputs::cos2_inclination_q16`], `cos^2(a_home)` from the
    /// frame (quantized the same way); `l = home_length + payout` (clamped to
    /// 0..[`MAX_SAG_LENGTH_MM`](crate::string_law::MAX_SAG_LENGTH_MM)), `T` at
    /// least [`SAG_MIN_TENSION_N`](crate::string_law::SAG_MIN_TENSION_N) (a
    /// slacker string is not a catenary); each of the two parts clamped to
    /// `+-`[`MAX_SAG_MM`](crate::string_law::MAX_SAG_MM).
    Sag {
        mm_at_1m_1n: f64,
        home_mm_at_1m: f64,
    },
    /// The strings' stretch as the encoders count it: a string of stiffness
    /// `EA` under tension `T` is longer than its natural length by `T / EA`
    /// of its whole length from the spool (the lead to the guide and the arc
    /// on it, whose length does not change, and the free span), and the
    /// counts measure the natural length from the home capture, where the
    /// string was already stretched at the home tension, so
    /// `+ per_newton * (T * (home_length + payout) - T_home * home_length)
    ///  + mm_per_newton * (T - T_home)`:
    /// `per_newton = 1 / EA` (1/N), `mm_per_newton = (lead + arc) / EA`
    /// (mm/N), `T_home = home_tension_n` (N, fitted). Zero at the home
    /// capture. Meant for strings of one kind, one term shared by every
    /// string ([`EVERY_STRING`]): one string's home part is a constant on
    /// that string, an [`Offset`](Effect::Offset).
    Stretch {
        per_newton: f64,
        mm_per_newton: f64,
        home_tension_n: f64,
    },
    /// The frame flexing under the strings' pull: each guide moves with the
    /// total tension of the strings, so a string's chord is off by
    /// `+ mm_per_newton * sum_j T_j - home_mm` (`sum_j` over the active
    /// strings; `home_mm` the flex at the home capture, where the anchors
    /// were found, `mm_per_newton * sum_j T_home_j`). Meant as one term
    /// shared by every string ([`EVERY_STRING`]): one string's `home_mm` is
    /// an [`Offset`](Effect::Offset).
    FrameFlex { mm_per_newton: f64, home_mm: f64 },
    /// Encoder latency: a string read `latency_s` late is short of its
    /// length by what it moved meanwhile, `L(t) = L(t - tau) + tau dL/dt`,
    /// so `+ latency_s * d payout/d counts * count_rate`: the winding
    /// polynomial's slope at the counts (mm per count, the layer table's
    /// left out: a few parts per thousand of it) times the string's count
    /// rate ([`StringInputs::count_rate_cps`]). 0 where the speed is not
    /// observed. `|latency_s| <=`
    /// [`MAX_LATENCY_S`](crate::string_law::MAX_LATENCY_S).
    Latency { latency_s: f64 },
    /// A guide pulley of radius `radius_mm` whose plane swivels toward the
    /// end-effector about the frame edge (the model's anchor is its entry
    /// point on the swivel axis): the string wraps `r beta` on it and
    /// leaves along the tangent: its path is longer than the chord `l` by
    /// `g(l, a) = r beta + sqrt(m^2 - r^2) - l` (exact, module
    /// `string_law::guide`), `a` the chord's elevation from
    /// [`StringInputs::guide_elevation_q32`]. The encoders count the path
    /// from the home capture, so `+ g(home_length, a_home) - g(l, a)`, `l =
    /// home_length + payout`; 0 at `r = 0`. `|radius_mm| <=`
    /// [`MAX_GUIDE_RADIUS_MM`](crate::string_law::MAX_GUIDE_RADIUS_MM).
    Guide { radius_mm: f64 },
}

/// An [`Effect`] applied to one string, or to every string at once.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EffectTerm {
    /// Encoder index of the string, `0..STRINGS`; [`EVERY_STRING`]: one term
    /// shared by every active string (one parameter, the same contribution
    /// formula on each string with that string's inputs), e.g. one drift for
    /// the whole device.
    pub string: u8,
    pub effect: Effect,
}

/// [`EffectTerm::string`] of a term shared by every active string. Families
/// whose compiled form needs one string's law (winding, eccentricity) cannot
/// be shared.
pub const EVERY_STRING: u8 = u8::MAX;

impl EffectTerm {
    /// Whether the term applies to string `i`.
    #[inline]
    pub const fn applies_to(&self, i: usize) -> bool {
        self.string == EVERY_STRING || self.string as usize == i
    }
}

/// Most effect terms a calibration may carry (the blob's fixed capacity).
pub const MAX_EFFECTS: usize = 32;

/// Most training slips a calibration's [`HomeSlips`] may carry (the blob's
/// fixed capacity).
pub const MAX_HOME_SLIPS: usize = 8;

#[cfg(feature = "alloc")]
pub use whole::{Calibration, HomeSlips};

#[cfg(feature = "alloc")]
mod whole {
    use super::*;
    use crate::correction::CorrectionModel;
    use alloc::vec::Vec;

    /// The training session's slips and the home capture they belong to:
    /// what the device applies, besides the calibration's effects, while
    /// its home capture is still that one (decision record 0049, "Device
    /// side").
    ///
    /// A slip is an event of its home capture: the string slid on its spool
    /// after the counts were zeroed, so until the next home capture the
    /// counts stay short by the step. The device applies these slips while
    /// its [`home_id`](HomeSlips::home_id) is the one its states report
    /// (`State::home_id`), and not after a new `Home` or a reboot (a new
    /// capture counts the string as it is).
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct HomeSlips {
        /// The home capture's id (`State::home_id`: the boot's id in the
        /// upper 32 bits, the captures since boot in the lower 32), that of
        /// the training session's last row.
        pub home_id: u64,
        /// Slip terms ([`Effect::Slip`], `at_s` in seconds since that home
        /// capture), each on one active string; at most
        /// [`MAX_HOME_SLIPS`].
        pub slips: Vec<EffectTerm>,
    }

    /// A whole calibration in physical units: what `spidar calibrate` writes
    /// and `blob::compile` turns into the device's fixed-point blob.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct Calibration {
        pub frame: Frame<f64>,
        pub strings: [StringLaw; STRINGS],
        /// Applied in order; at most [`MAX_EFFECTS`].
        pub effects: Vec<EffectTerm>,
        pub correction: CorrectionModel,
        /// Each string's measured length residual scale (mm): the robust
        /// standard deviation of its modelled length against the tracked
        /// position on the training session, what the forward kinematics
        /// weighs the strings by ([`crate::kinematics::residual_weights`]).
        /// Zeros (a calibration written before they were measured) weigh
        /// every string alike.
        #[serde(default)]
        pub length_scale_mm: [f64; STRINGS],
        /// When forward kinematics leaves a string out and calls the
        /// strings inconsistent (the calibration chooses it on held-out
        /// data; the default is the device's fixed 1 mm / 2 mm).
        #[serde(default)]
        pub kinematics: crate::kinematics::KinematicsRule,
        /// The training session's slips, applied on the device only under
        /// the home capture they happened in ([`HomeSlips`]); `effects` is
        /// the model for the next home capture, without them. Absent (no
        /// slips to carry: none found, or the training session did not
        /// record its home capture) in calibrations written before it
        /// existed and whenever there are none.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pub home: Option<HomeSlips>,
    }

    impl Calibration {
        /// The calibration as the device runs it under home capture
        /// `home_id` (`State::home_id`; `None`: not known): its effects,
        /// and the slips of [`Calibration::home`] among them while
        /// `home_id` is theirs; the f64 twin of
        /// [`crate::blob::BlobHead::string_lengths`]'s rule.
        pub fn under_home(&self, home_id: Option<u64>) -> Calibration {
            let mut c = self.clone();
            if let Some(home) = c.home.take().filter(|h| Some(h.home_id) == home_id) {
                c.effects.extend(home.slips);
            }
            c
        }
    }
}
