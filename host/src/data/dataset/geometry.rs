//! The geometry format (TOML, [`Geometry`]): the device as designed, read,
//! checked and written.

use std::fmt::Write as _;
use std::fs;
use std::path::Path;

use serde::de::{self, Deserializer, SeqAccess, Visitor};
use serde::Deserialize;
use spidar_core::geometry::distance;
use spidar_core::model::{Frame, StringLaw, StringLayout, Vec3, WINDING_ORDER};
use spidar_core::plausible::MIN_ANCHOR_SEPARATION_MM;
use spidar_core::STRINGS;

use super::{io_error, DatasetError, MIN_STRINGS};

/// Nominal geometry of a device, as its designers give it (never as built).
///
/// Arrays have the controller's [`STRINGS`] entries (index = encoder
/// channel); a device with N strings uses channels `0..N` (`layout`), and the
/// entries of the other channels repeat string N-1's values: they are never
/// read, but stay valid numbers for code that walks all 8.
#[derive(Clone, Debug, PartialEq)]
pub struct Geometry {
    /// Which channels carry a string (`0..N`), planar or 3-D.
    pub layout: StringLayout,
    /// Quadrature counts per pulley (spool) revolution, per string.
    pub counts_per_rev: [u32; STRINGS],
    /// Nominal pulley (spool) radius of each string (mm), index = encoder index.
    pub pulley_radius_mm: [f64; STRINGS],
    /// Spool payout per mm of string length change (1 for a string straight
    /// from its pulley to the end-effector, 2 or 4 for a line doubled through
    /// pulley blocks).
    pub mechanical_advantage: [f64; STRINGS],
    /// End-effector position at initialization (device frame, mm).
    pub home_mm: Vec3<f64>,
    /// String exit points (device frame, mm), index = encoder index.
    pub anchors_mm: [Vec3<f64>; STRINGS],
    /// `t` of `p_room = p_device + t` (mm), the paper's eq. 6.
    pub room_from_device_translation_mm: Vec3<f64>,
    /// Tension every string held when home was captured (N): the pretension
    /// the initialization holds (`spidar init` records it). The strings'
    /// stretch is counted from it; `None`: the firmware's default, 1 N,
    /// within 1 N.
    pub home_tension_n: Option<f64>,
    /// How far each anchor (string exit point) may be from where the
    /// geometry puts it, per coordinate, mm (one sd; a hand-measured rig's
    /// tolerance): the identification's prior. `None`: the calibration's
    /// default ([`crate::model::identify::Priors::anchor_sd_mm`]).
    pub anchor_sd_mm: Option<[f64; STRINGS]>,
    /// How far home may be from `home_mm`, per coordinate, mm (one sd).
    /// `None`: the calibration's default.
    pub home_sd_mm: Option<f64>,
}

/// Largest home tension a geometry may declare, N (the firmware's tension
/// ceiling is 20 N).
pub const MAX_HOME_TENSION_N: f64 = 50.0;

/// A key that is one number for all strings or an array of one per string.
#[derive(Debug)]
enum PerString<T> {
    One(T),
    Each(Vec<T>),
}

impl<'de, T: Deserialize<'de>> Deserialize<'de> for PerString<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct PerStringVisitor<T>(std::marker::PhantomData<T>);
        impl<'de, T: Deserialize<'de>> Visitor<'de> for PerStringVisitor<T> {
            type Value = PerString<T>;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                write!(f, "a number or an array of one number per string")
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Self::Value, E> {
                T::deserialize(de::value::F64Deserializer::new(v)).map(PerString::One)
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Self::Value, E> {
                T::deserialize(de::value::I64Deserializer::new(v)).map(PerString::One)
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Self::Value, E> {
                T::deserialize(de::value::U64Deserializer::new(v)).map(PerString::One)
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
                let mut values = Vec::new();
                while let Some(v) = seq.next_element::<T>()? {
                    values.push(v);
                }
                Ok(PerString::Each(values))
            }
        }
        deserializer.deserialize_any(PerStringVisitor(std::marker::PhantomData))
    }
}

impl<T: Copy> PerString<T> {
    /// One value per string of `n`, the rest of the channels repeating the
    /// last; `None` when an array has another length than `n`.
    fn per_channel(&self, n: usize) -> Result<[T; STRINGS], usize> {
        let values: Vec<T> = match self {
            PerString::One(v) => vec![*v; n],
            PerString::Each(v) if v.len() == n => v.clone(),
            PerString::Each(v) => return Err(v.len()),
        };
        Ok(core::array::from_fn(|i| values[i.min(n - 1)]))
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct GeometryFile {
    counts_per_rev: PerString<u32>,
    pulley_radius_mm: PerString<f64>,
    #[serde(default)]
    mechanical_advantage: Option<PerString<f64>>,
    #[serde(default)]
    planar: bool,
    home_mm: Vec<f64>,
    anchors_mm: Vec<Vec<f64>>,
    // Read as a list, its length checked: serde reads the first 3 values
    // of a longer TOML array into `[f64; 3]` and drops the rest unsaid.
    room_from_device_translation_mm: Vec<f64>,
    #[serde(default)]
    home_tension_n: Option<f64>,
    #[serde(default)]
    anchor_sd_mm: Option<PerString<f64>>,
    // Read as a number or a list, so a list is refused in words.
    #[serde(default)]
    home_sd_mm: Option<PerString<f64>>,
}

fn field_error(file: &Path, field: impl Into<String>, problem: impl Into<String>) -> DatasetError {
    DatasetError::GeometryField {
        file: file.to_path_buf(),
        field: field.into(),
        problem: problem.into(),
    }
}

fn check_finite3(file: &Path, field: &str, v: &Vec3<f64>) -> Result<(), DatasetError> {
    for (axis, x) in v.iter().enumerate() {
        if !x.is_finite() {
            return Err(field_error(
                file,
                format!("{field}[{axis}]"),
                format!("{x} is not a finite number"),
            ));
        }
    }
    Ok(())
}

impl Geometry {
    /// Read a geometry TOML file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, DatasetError> {
        let path = path.as_ref();
        let text = fs::read_to_string(path).map_err(|e| io_error(path, "cannot read", e))?;
        Self::from_toml_str(&text, path)
    }

    /// Parse geometry TOML text; `file` names it in errors.
    pub fn from_toml_str(text: &str, file: &Path) -> Result<Self, DatasetError> {
        let raw: GeometryFile = toml::from_str(text).map_err(|e| DatasetError::Toml {
            file: file.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let n = raw.anchors_mm.len();
        if !(MIN_STRINGS..=STRINGS).contains(&n) {
            return Err(field_error(
                file,
                "anchors_mm",
                format!(
                    "{n} anchors given: a device has {MIN_STRINGS} to {STRINGS} strings, one anchor each"
                ),
            ));
        }
        let planar = raw.planar;
        let point = |field: String, v: &[f64]| -> Result<Vec3<f64>, DatasetError> {
            match (v.len(), planar) {
                (3, _) => Ok([v[0], v[1], v[2]]),
                (2, true) => Ok([v[0], v[1], 0.0]),
                (len, true) => Err(field_error(
                    file,
                    field,
                    format!("{len} coordinates: [x, y] or [x, y, z] (mm) expected"),
                )),
                (len, false) => Err(field_error(
                    file,
                    field,
                    format!(
                        "{len} coordinates: [x, y, z] (mm) expected (2-D points need `planar = true`)"
                    ),
                )),
            }
        };
        let mut given = Vec::with_capacity(n);
        for (i, a) in raw.anchors_mm.iter().enumerate() {
            given.push(point(format!("anchors_mm[{i}]"), a)?);
        }
        let mut home_mm = point("home_mm".to_string(), &raw.home_mm)?;
        let room_from_device_translation_mm = match raw.room_from_device_translation_mm[..] {
            [x, y, z] => [x, y, z],
            ref v => {
                return Err(field_error(
                    file,
                    "room_from_device_translation_mm",
                    format!("{} values: [x, y, z] (mm) expected", v.len()),
                ))
            }
        };
        if planar && raw.home_mm.len() == 2 {
            // A 2-D home lies in the anchors' plane.
            home_mm[2] = given[0][2];
        }
        let anchors_mm: [Vec3<f64>; STRINGS] = core::array::from_fn(|i| given[i.min(n - 1)]);
        let per_string = |field: &str, len: usize| {
            field_error(
                file,
                field,
                format!("{len} values given, {n} expected (one per anchor, or one number for all)"),
            )
        };
        let counts_per_rev = raw
            .counts_per_rev
            .per_channel(n)
            .map_err(|len| per_string("counts_per_rev", len))?;
        let pulley_radius_mm = raw
            .pulley_radius_mm
            .per_channel(n)
            .map_err(|len| per_string("pulley_radius_mm", len))?;
        let mechanical_advantage = match &raw.mechanical_advantage {
            None => [1.0; STRINGS],
            Some(m) => m
                .per_channel(n)
                .map_err(|len| per_string("mechanical_advantage", len))?,
        };
        let anchor_sd_mm = raw
            .anchor_sd_mm
            .as_ref()
            .map(|sd| sd.per_channel(n))
            .transpose()
            .map_err(|len| per_string("anchor_sd_mm", len))?;
        let home_sd_mm = match &raw.home_sd_mm {
            None => None,
            Some(PerString::One(sd)) => Some(*sd),
            Some(PerString::Each(sds)) => {
                return Err(field_error(
                    file,
                    "home_sd_mm",
                    format!(
                        "{} values given, one number expected (the sd of each of the home's \
                         coordinates, e.g. `home_sd_mm = 5`)",
                        sds.len()
                    ),
                ))
            }
        };
        let geometry = Geometry {
            layout: StringLayout::first(n, planar),
            counts_per_rev,
            pulley_radius_mm,
            mechanical_advantage,
            home_mm,
            anchors_mm,
            room_from_device_translation_mm,
            home_tension_n: raw.home_tension_n,
            anchor_sd_mm,
            home_sd_mm,
        };
        geometry.validate(file)?;
        Ok(geometry)
    }

    /// Number of strings (anchors), 3..=8.
    pub fn strings(&self) -> usize {
        self.layout.count()
    }

    /// Check the values: positive counts per revolution and radii, finite
    /// coordinates, anchors apart from home. `file` names the file in errors.
    pub fn validate(&self, file: &Path) -> Result<(), DatasetError> {
        self.check_channels(file)?;
        check_finite3(file, "home_mm", &self.home_mm)?;
        check_finite3(
            file,
            "room_from_device_translation_mm",
            &self.room_from_device_translation_mm,
        )?;
        self.check_anchors(file)?;
        if self.layout.planar && self.home_mm[2] != self.anchors_mm[0][2] {
            return Err(field_error(
                file,
                "home_mm",
                format!(
                    "z = {} is not the anchors' plane z = {}: the end-effector of a planar device moves in that plane",
                    self.home_mm[2], self.anchors_mm[0][2]
                ),
            ));
        }
        Ok(())
    }

    /// The strings are on channels 0..N (N in 3..=8), the home tension is a
    /// tension, and each channel's counts per revolution, pulley radius and
    /// mechanical advantage are positive.
    fn check_channels(&self, file: &Path) -> Result<(), DatasetError> {
        let n = self.strings();
        if n < MIN_STRINGS || self.layout != StringLayout::first(n, self.layout.planar) {
            return Err(field_error(
                file,
                "anchors_mm",
                format!(
                    "strings on channels {:?}: a device has {MIN_STRINGS} to {STRINGS} strings on channels 0..N",
                    self.layout.indices().collect::<Vec<_>>()
                ),
            ));
        }
        if let Some(t) = self.home_tension_n {
            if !(t.is_finite() && t > 0.0 && t <= MAX_HOME_TENSION_N) {
                return Err(field_error(
                    file,
                    "home_tension_n",
                    format!(
                        "{t} N: the tension the strings held at the home capture is above 0 and \
                         at most {MAX_HOME_TENSION_N} N"
                    ),
                ));
            }
        }
        let tolerance = |field: String, sd: f64| {
            if sd.is_finite() && sd > 0.0 {
                Ok(())
            } else {
                Err(field_error(
                    file,
                    field,
                    format!("{sd} mm: a tolerance (one standard deviation) is a positive number"),
                ))
            }
        };
        if let Some(sd) = self.home_sd_mm {
            tolerance("home_sd_mm".into(), sd)?;
        }
        if let Some(sd) = self.anchor_sd_mm {
            for i in self.layout.indices() {
                tolerance(format!("anchor_sd_mm[{i}]"), sd[i])?;
            }
        }
        for i in self.layout.indices() {
            if self.counts_per_rev[i] == 0 {
                return Err(field_error(
                    file,
                    format!("counts_per_rev[{i}]"),
                    "must be positive",
                ));
            }
            let r = self.pulley_radius_mm[i];
            if !(r.is_finite() && r > 0.0) {
                return Err(field_error(
                    file,
                    format!("pulley_radius_mm[{i}]"),
                    format!("{r} is not a positive finite radius"),
                ));
            }
            let m = self.mechanical_advantage[i];
            if !(m.is_finite() && m > 0.0) {
                return Err(field_error(
                    file,
                    format!("mechanical_advantage[{i}]"),
                    format!("{m} is not a positive finite ratio"),
                ));
            }
        }
        Ok(())
    }

    /// Each anchor is finite, apart from home and (planar) in the first
    /// one's plane; together they are not at one point or on one line.
    fn check_anchors(&self, file: &Path) -> Result<(), DatasetError> {
        for i in self.layout.indices() {
            let a = &self.anchors_mm[i];
            let field = format!("anchors_mm[{i}]");
            check_finite3(file, &field, a)?;
            if distance(*a, self.home_mm) == 0.0 {
                return Err(field_error(
                    file,
                    field,
                    "the anchor coincides with home_mm",
                ));
            }
            if self.layout.planar && a[2] != self.anchors_mm[0][2] {
                return Err(field_error(
                    file,
                    field,
                    format!(
                        "z = {} but anchors_mm[0] has z = {}: the anchors of a planar device lie in one plane z = const",
                        a[2], self.anchors_mm[0][2]
                    ),
                ));
            }
        }
        let active: Vec<usize> = self.layout.indices().collect();
        for (k, &a) in active.iter().enumerate() {
            for &b in &active[k + 1..] {
                let apart_mm = distance(self.anchors_mm[a], self.anchors_mm[b]);
                if apart_mm < MIN_ANCHOR_SEPARATION_MM {
                    return Err(field_error(
                        file,
                        format!("anchors_mm[{b}]"),
                        format!(
                            "{apart_mm:.3} mm from anchors_mm[{a}]: two strings cannot leave \
                             one point (one anchor copied over another?)"
                        ),
                    ));
                }
            }
        }
        if let Some(why) = self.degenerate_anchors() {
            return Err(field_error(
                file,
                "anchors_mm",
                format!(
                    "the geometry is degenerate: {why}, so string lengths cannot fix a \
                     position (copied one anchor into every row?)"
                ),
            ));
        }
        Ok(())
    }

    /// Why no position can be solved from the anchors: all at one point, or
    /// all on one line (None: they span a plane or more).
    fn degenerate_anchors(&self) -> Option<&'static str> {
        let active: Vec<Vec3<f64>> = self.layout.indices().map(|i| self.anchors_mm[i]).collect();
        let far = active
            .iter()
            .map(|a| distance(*a, active[0]))
            .fold(0.0, f64::max);
        if far == 0.0 {
            Some("all anchors are at one point")
        } else {
            let (k, _) = active
                .iter()
                .enumerate()
                .map(|(k, a)| (k, distance(*a, active[0])))
                .fold((0, 0.0), |b, x| if x.1 > b.1 { x } else { b });
            let u = [0, 1, 2].map(|c| (active[k][c] - active[0][c]) / far);
            let off_line = active
                .iter()
                .map(|a| {
                    let d = [0, 1, 2].map(|c| a[c] - active[0][c]);
                    let along = d[0] * u[0] + d[1] * u[1] + d[2] * u[2];
                    let p = [0, 1, 2].map(|c| d[c] - along * u[c]);
                    (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
                })
                .fold(0.0, f64::max);
            (off_line <= 1e-9 * far).then_some("all anchors lie on one line")
        }
    }

    /// TOML text of this geometry, in the layout of the shared example
    /// (the N-string keys only where they differ from a Scalable-SPIDAR's).
    pub fn to_toml_string(&self) -> String {
        let n = self.strings();
        let mut s = String::from("# Nominal geometry of the device (as designed, not as built)\n");
        let one_or_each = |s: &mut String, key: &str, v: &[String]| {
            if v.iter().all(|x| *x == v[0]) {
                let _ = writeln!(s, "{key} = {}", v[0]);
            } else {
                let _ = writeln!(s, "{key} = [{}]", v.join(", "));
            }
        };
        let cpr: Vec<String> = self.counts_per_rev[..n]
            .iter()
            .map(u32::to_string)
            .collect();
        one_or_each(&mut s, "counts_per_rev", &cpr);
        let radii: Vec<String> = self.pulley_radius_mm[..n]
            .iter()
            .map(|r| format!("{r:?}"))
            .collect();
        one_or_each(&mut s, "pulley_radius_mm", &radii);
        if self.mechanical_advantage[..n].iter().any(|m| *m != 1.0) {
            let m: Vec<String> = self.mechanical_advantage[..n]
                .iter()
                .map(|m| format!("{m:?}"))
                .collect();
            let _ = writeln!(s, "mechanical_advantage = [{}]", m.join(", "));
        }
        if self.layout.planar {
            s.push_str("planar = true\n");
        }
        let _ = writeln!(s, "home_mm = {:?}", self.home_mm);
        s.push_str("anchors_mm = [\n");
        for a in &self.anchors_mm[..n] {
            let _ = writeln!(s, "  {a:?},");
        }
        s.push_str("]\n");
        let _ = writeln!(
            s,
            "room_from_device_translation_mm = {:?}",
            self.room_from_device_translation_mm
        );
        if let Some(t) = self.home_tension_n {
            let _ = writeln!(s, "home_tension_n = {t:?}");
        }
        if let Some(sd) = self.anchor_sd_mm {
            let sd: Vec<String> = sd[..n].iter().map(|v| format!("{v:?}")).collect();
            one_or_each(&mut s, "anchor_sd_mm", &sd);
        }
        if let Some(sd) = self.home_sd_mm {
            let _ = writeln!(s, "home_sd_mm = {sd:?}");
        }
        s
    }

    /// Write this geometry as TOML (after [`Geometry::validate`]).
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), DatasetError> {
        let path = path.as_ref();
        self.validate(path)?;
        crate::data::output::write_atomically(path, self.to_toml_string().as_bytes())
            .map_err(|e| io_error(path, "cannot write", e))
    }

    /// The nominal frame: nominal anchors and home, identity rotation, unit
    /// scale and the eq. 6 translation.
    pub fn nominal_frame(&self) -> Frame<f64> {
        Frame {
            layout: self.layout,
            anchors: self.anchors_mm,
            home: self.home_mm,
            room_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            room_translation: self.room_from_device_translation_mm,
            room_scale: 1.0,
        }
    }

    /// The nominal string laws: a constant winding radius, the nominal pulley
    /// radius over the mechanical advantage (`winding_mm = [r / m, 0, 0, 0]`:
    /// a spool paying out `r theta` shortens a line doubled `m` times by
    /// `r theta / m`).
    pub fn nominal_string_laws(&self) -> [StringLaw; STRINGS] {
        core::array::from_fn(|i| {
            let mut winding_mm = [0.0; WINDING_ORDER];
            winding_mm[0] = self.pulley_radius_mm[i] / self.mechanical_advantage[i];
            StringLaw::polynomial(self.counts_per_rev[i], winding_mm)
        })
    }

    /// Nominal string payout per encoder count, mm, per channel (the
    /// nominal law's payout of one count: `r 2 pi / counts_per_rev` over
    /// the mechanical advantage).
    pub fn nominal_mm_per_count(&self) -> [f64; STRINGS] {
        self.nominal_string_laws()
            .map(|law| spidar_core::string_law::payout_f64(&law, 1))
    }

    /// The device's nominal string model (`SetNominalGeometry`): what a device
    /// without a calibration blob runs on.
    pub fn string_model(&self) -> spidar_protocol::NominalGeometry {
        let layout = self.nominal_frame().layout;
        spidar_protocol::NominalGeometry {
            counts_per_rev: self.counts_per_rev,
            pulley_radius_mm: core::array::from_fn(|i| {
                (self.pulley_radius_mm[i] / self.mechanical_advantage[i]) as f32
            }),
            anchors_mm: self.anchors_mm.map(|a| a.map(|v| v as f32)),
            home_mm: self.home_mm.map(|v| v as f32),
            active_strings: layout.active,
            planar: layout.planar,
        }
    }

    /// Nominal string length of each string at home (mm).
    pub fn home_lengths_mm(&self) -> [f64; STRINGS] {
        core::array::from_fn(|i| distance(self.anchors_mm[i], self.home_mm))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GEOMETRY: &str = "counts_per_rev = 4096\npulley_radius_mm = 7.5\nhome_mm = [0, 0, 0]\n\
        anchors_mm = [[-1100, -1100, -1100], [1100, -1100, -1100], [0, 1100, -1100], [0, 0, 1100]]\n\
        room_from_device_translation_mm = [0, 0, 1500]\n";

    fn geometry(extra: &str) -> Result<Geometry, DatasetError> {
        Geometry::from_toml_str(
            &format!("{GEOMETRY}{extra}"),
            Path::new("mem/geometry.toml"),
        )
    }

    /// `home_sd_mm` is one number, the sd of each of the home's
    /// coordinates; an array (a survey's user read the README's "one sd per
    /// coordinate" as one) is refused naming the key and what it takes, as
    /// `anchor_sd_mm`'s wrong lengths are, not with serde's "invalid type:
    /// sequence, expected f64".
    #[test]
    fn home_sd_mm_is_one_number_and_an_array_is_refused_in_words() {
        assert_eq!(geometry("home_sd_mm = 5\n").unwrap().home_sd_mm, Some(5.0));
        let err = geometry("home_sd_mm = [5, 5, 5]\n").unwrap_err();
        let msg = err.to_string();
        assert!(
            matches!(err, DatasetError::GeometryField { ref field, .. } if field == "home_sd_mm")
                && msg.contains("3 values given, one number expected")
                && !msg.contains("invalid type"),
            "{msg}"
        );
    }
}
