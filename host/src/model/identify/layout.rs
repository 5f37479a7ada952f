//! The parameter vector: what the fit varies ([`State`], in physical
//! units) and its columns in the LM variables ([`Layout`]: order, scales,
//! which are free, their names).

use nalgebra::DVector;
use spidar_core::geometry::vector_from_rotation;
use spidar_core::model::{EffectTerm, Frame, StringLayout, EVERY_STRING};
use spidar_core::STRINGS;

use super::structure::{anchor_prior_sd, effect_parameter_info, effect_prior, Structure};
use super::winding::WindingPhysics;
use crate::model::normal::ArrowColumns;

/// Everything the fit varies, in physical units.
#[derive(Clone, Debug)]
pub(super) struct State {
    pub(super) frame: Frame<f64>,
    pub(super) winding: WindingPhysics,
    pub(super) effects: Vec<EffectTerm>,
}

/// Layout of the LM parameter vector.
pub(super) struct Layout {
    pub(super) fit_scale: bool,
    /// (effect index, parameter index within the effect) per effect column.
    pub(super) effect_columns: Vec<(usize, usize)>,
    /// Typical size of each column's parameter (LM variable = value / scale).
    pub(super) scale: Vec<f64>,
    /// The columns each string's residuals touch, in the order
    /// [`Problem::string_rows`](super::problem::Problem::string_rows) gives
    /// their values.
    pub(super) arrow: ArrowColumns,
}

pub(super) const ANCHORS: usize = 0;
pub(super) const HOME: usize = 24;
pub(super) const ROTATION: usize = 27;
pub(super) const TRANSLATION: usize = 30;
pub(super) const SCALE: usize = 33;

impl Layout {
    pub(super) fn new(structure: &Structure) -> Layout {
        let fit_scale = structure.fit_room_scale;
        let mut scale = vec![1.0; 27];
        scale.extend([1e-3; 3]);
        scale.extend([1.0; 3]);
        if fit_scale {
            scale.push(1e-4);
        }
        scale.extend([0.1; STRINGS]); // r_home per string
        scale.push(1e-3); // kappa
        scale.extend([1e-3; STRINGS]); // kappa_each
        let mut effect_columns = Vec::new();
        for (e, term) in structure.effects.iter().enumerate() {
            for (p, (_, s, _)) in effect_parameter_info(&term.effect).iter().enumerate() {
                effect_columns.push((e, p));
                scale.push(*s);
            }
        }
        let mut layout = Layout {
            fit_scale,
            effect_columns,
            scale,
            arrow: ArrowColumns {
                n: 0,
                shared: Vec::new(),
                own: Default::default(),
            },
        };
        layout.arrow = layout.arrow_columns(structure);
        layout
    }

    /// A string's residual touches its anchor, winding radius, spool rate
    /// and the terms on it (its own columns), and the home, the tracker
    /// frame, the shared thinning rate and the every-string terms (the
    /// shared ones).
    fn arrow_columns(&self, structure: &Structure) -> ArrowColumns {
        let terms_on = |owner: u8| -> Vec<usize> {
            self.term_columns(structure, owner)
                .map(|c| self.first_effect() + c)
                .collect()
        };
        let mut shared: Vec<usize> = (HOME..TRANSLATION + 3).collect();
        if self.fit_scale {
            shared.push(SCALE);
        }
        shared.push(self.kappa());
        shared.extend(terms_on(EVERY_STRING));
        let own = core::array::from_fn(|i| {
            let mut own = vec![
                ANCHORS + 3 * i,
                ANCHORS + 3 * i + 1,
                ANCHORS + 3 * i + 2,
                self.r_home() + i,
                self.kappa_each() + i,
            ];
            own.extend(terms_on(i as u8));
            own
        });
        ArrowColumns {
            n: self.len(),
            shared,
            own,
        }
    }

    /// The effect columns (counted from the first) of the terms on
    /// `owner`, a string or [`EVERY_STRING`].
    pub(super) fn term_columns<'s>(
        &'s self,
        structure: &'s Structure,
        owner: u8,
    ) -> impl Iterator<Item = usize> + 's {
        self.effect_columns
            .iter()
            .enumerate()
            .filter(move |(_, &(e, _))| structure.effects[e].string == owner)
            .map(|(c, _)| c)
    }
    pub(super) fn r_home(&self) -> usize {
        SCALE + usize::from(self.fit_scale)
    }
    pub(super) fn kappa(&self) -> usize {
        self.r_home() + STRINGS
    }
    pub(super) fn kappa_each(&self) -> usize {
        self.kappa() + 1
    }
    pub(super) fn first_effect(&self) -> usize {
        self.kappa_each() + STRINGS
    }
    pub(super) fn len(&self) -> usize {
        self.scale.len()
    }
}

/// LM variables of a state (rotation encoded as zero on top of the state's own).
pub(super) fn encode(state: &State, layout: &Layout) -> DVector<f64> {
    let mut x = DVector::zeros(layout.len());
    let mut put = |i: usize, v: f64| x[i] = v / layout.scale[i];
    for i in 0..STRINGS {
        for c in 0..3 {
            put(ANCHORS + 3 * i + c, state.frame.anchors[i][c]);
        }
    }
    for c in 0..3 {
        put(HOME + c, state.frame.home[c]);
        put(TRANSLATION + c, state.frame.room_translation[c]);
    }
    if layout.fit_scale {
        put(SCALE, state.frame.room_scale - 1.0);
    }
    for i in 0..STRINGS {
        put(layout.r_home() + i, state.winding.r_home_mm[i]);
    }
    put(layout.kappa(), state.winding.kappa_mm);
    for i in 0..STRINGS {
        put(layout.kappa_each() + i, state.winding.kappa_each_mm[i]);
    }
    let mut col = layout.first_effect();
    for term in &state.effects {
        for v in term.effect.parameters() {
            put(col, v);
            col += 1;
        }
    }
    x
}

/// The physical value of column `c` at `state`.
pub(super) fn column_value(layout: &Layout, state: &State, c: usize) -> f64 {
    match c {
        _ if c < HOME => state.frame.anchors[(c - ANCHORS) / 3][(c - ANCHORS) % 3],
        _ if c < ROTATION => state.frame.home[c - HOME],
        _ if c < TRANSLATION => vector_from_rotation(&state.frame.room_rotation)[c - ROTATION],
        _ if c < SCALE => state.frame.room_translation[c - TRANSLATION],
        _ if layout.fit_scale && c == SCALE => state.frame.room_scale,
        _ if c >= layout.r_home() && c < layout.kappa() => {
            state.winding.r_home_mm[c - layout.r_home()]
        }
        _ if c == layout.kappa() => state.winding.kappa_mm,
        _ if c >= layout.kappa_each() && c < layout.first_effect() => {
            state.winding.kappa_each_mm[c - layout.kappa_each()]
        }
        _ => {
            let (e, p) = layout.effect_columns[c - layout.first_effect()];
            state.effects[e].effect.parameters()[p]
        }
    }
}

/// Whether column `c` is a parameter of the device (not a channel without a
/// string, nor a coordinate a planar device holds).
pub(super) fn column_is_free(
    layout: &Layout,
    structure: &Structure,
    strings: StringLayout,
    c: usize,
) -> bool {
    let planar = strings.planar;
    match c {
        _ if c < HOME => {
            strings.is_active((c - ANCHORS) / 3) && !(planar && (c - ANCHORS) % 3 == 2)
        }
        _ if c < ROTATION => !(planar && c == HOME + 2),
        _ if c < TRANSLATION => !(planar && c < ROTATION + 2),
        _ if c < SCALE => !(planar && c == TRANSLATION + 2),
        _ if c >= layout.r_home() && c < layout.kappa() => strings.is_active(c - layout.r_home()),
        _ if c >= layout.kappa_each() && c < layout.first_effect() => {
            !structure.hold_kappa_each && strings.is_active(c - layout.kappa_each())
        }
        _ if c >= layout.first_effect() => {
            let (e, _) = layout.effect_columns[c - layout.first_effect()];
            let string = structure.effects[e].string;
            string == EVERY_STRING || strings.is_active(usize::from(string))
        }
        _ => true,
    }
}

pub(super) fn rows_needed(layout: &Layout, structure: &Structure, strings: StringLayout) -> usize {
    let free = (0..layout.len())
        .filter(|&c| column_is_free(layout, structure, strings, c))
        .count();
    // The frame's gauge, and the spools' own thinning rates' mean.
    let gauge = if strings.planar { 3 } else { 6 } + usize::from(!structure.hold_kappa_each);
    let free = free.saturating_sub(gauge);
    let per_row = strings.count().max(1);
    (2 * free).div_ceil(per_row).max(10)
}

pub(super) fn parameter_names(
    layout: &Layout,
    structure: &Structure,
    strings: StringLayout,
) -> Vec<(String, &'static str, Option<f64>)> {
    let p = &structure.priors;
    let mut names = Vec::new();
    for i in 0..STRINGS {
        let sd = anchor_prior_sd(structure, strings, i);
        for c in ["x", "y", "z"] {
            names.push((format!("anchor{i}.{c}"), "mm", Some(sd)));
        }
    }
    for c in ["x", "y", "z"] {
        names.push((format!("home.{c}"), "mm", Some(p.home_sd_mm)));
    }
    for c in ["x", "y", "z"] {
        names.push((format!("room_rotation.{c}"), "rad", Some(p.rotation_sd_rad)));
    }
    for c in ["x", "y", "z"] {
        names.push((
            format!("room_translation.{c}"),
            "mm",
            Some(p.translation_sd_mm),
        ));
    }
    if layout.fit_scale {
        names.push(("room_scale".into(), "1", None));
    }
    for i in 0..STRINGS {
        names.push((format!("string{i}.r_home"), "mm", None));
    }
    names.push(("winding.kappa".into(), "mm/rad^2", None));
    for i in 0..STRINGS {
        names.push((
            format!("string{i}.kappa_each"),
            "mm/rad^2",
            Some(p.kappa_each_sd_mm),
        ));
    }
    for term in &structure.effects {
        let info = effect_parameter_info(&term.effect);
        for (k, (name, (_, _, unit))) in effect_parameter_names(term)
            .into_iter()
            .zip(info)
            .enumerate()
        {
            let prior = effect_prior(&term.effect, k, p).map(|(_, sd)| sd);
            names.push((name, *unit, prior));
        }
    }
    names
}

/// The names of `term`'s parameters in an identification
/// ([`ParameterEstimate::name`](super::ParameterEstimate)): its owner
/// (`stringN`, or `every_string`) and the parameter, e.g.
/// `every_string.latency`.
pub fn effect_parameter_names(term: &EffectTerm) -> Vec<String> {
    let owner = if term.string == EVERY_STRING {
        "every_string".to_string()
    } else {
        format!("string{}", term.string)
    };
    effect_parameter_info(&term.effect)
        .iter()
        .map(|(name, _, _)| format!("{owner}.{name}"))
        .collect()
}
