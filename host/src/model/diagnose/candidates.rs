//! The candidate effects diagnosis tests on the residual: each family's
//! columns on the rows (per string, shared by every string, the tracked
//! body's offset, the tracker's scale), the rivals some must explain the
//! residual beyond, and the anchors the data pull beyond their tolerance.

use spidar_core::model::{Effect, EffectTerm, Frame, StringLayout, EVERY_STRING};
use spidar_core::string_law::{creep_variable, guide_slope, sag_home_variable, sag_variable};
use spidar_core::STRINGS;

use crate::data::observe::{
    observes_speed, speed_observation, Observation, MAX_STREAM_SPEED_CHANGE,
};
use crate::data::stats::chi_square_p001;
use crate::model::identify::{Identification, Structure};

use super::evidence::{Columns, Evidence, OffSpan, Row, RowColumn};
use super::vocabulary::{Change, Family, Finding, LoopConfig, Variable};

#[cfg(test)]
mod tests;

/// Turns fitted coefficients into the model change a candidate proposes.
pub(super) type BuildChange = Box<dyn Fn(&[f64]) -> Change>;

/// A candidate effect: its regressors on the rows and what adding it means.
pub(super) struct Candidate {
    pub(super) family: Family,
    pub(super) strings: Vec<u8>,
    pub(super) variable: Variable,
    pub(super) columns: Vec<RowColumn>,
    /// The string whose rows alone the columns (and the rival's) are not
    /// zero on, for a term of one string.
    pub(super) on_string: Option<usize>,
    /// Extra chi-square demanded for a searched parameter (a slip's time).
    pub(super) search_penalty: f64,
    /// Columns of a simpler explanation the candidate must explain the
    /// residual beyond (nested test at its own dof); empty: none.
    pub(super) rival: Vec<RowColumn>,
    pub(super) build: BuildChange,
    pub(super) describe: String,
}

impl Candidate {
    /// Its columns, to test off the model's span.
    pub(super) fn own(&self) -> Columns<'_> {
        Columns {
            columns: self.columns.iter().collect(),
            string: self.on_string,
        }
    }

    /// The rival's columns, then its own.
    fn with_rival(&self) -> Columns<'_> {
        Columns {
            columns: self.rival.iter().chain(&self.columns).collect(),
            string: self.on_string,
        }
    }
}

/// The column of a term of string `string`: `f` on its rows.
fn string_column(string: usize, f: RowColumn) -> RowColumn {
    Box::new(move |r| if r.string == string { f(r) } else { 0.0 })
}

/// The column of a term shared by every string: `f` on the active
/// strings' rows.
fn shared_column(
    strings: StringLayout,
    f: impl Fn(&Row) -> f64 + Send + Sync + 'static,
) -> RowColumn {
    Box::new(move |r| {
        if strings.is_active(r.string) {
            f(r)
        } else {
            0.0
        }
    })
}

pub(super) fn candidates(
    ev: &Evidence,
    structure: &Structure,
    time_split: &[Option<f64>],
    config: &LoopConfig,
) -> Vec<Candidate> {
    let mut out = Vec::new();
    let has_effect = |string: usize, f: fn(&Effect) -> bool| {
        structure
            .effects
            .iter()
            .any(|t| t.string as usize == string && f(&t.effect))
    };
    let strings = ev.layout;
    for (i, split) in time_split.iter().enumerate().take(STRINGS) {
        if !strings.is_active(i) {
            continue;
        }
        let rows = ev.rows_of_string(i);
        for term in string_terms(rows, i, *split, ev.speed_observed, !strings.planar) {
            if !has_effect(i, term.is_term) {
                out.push(term.candidate(i));
            }
        }
    }
    // One drift shared by every string (creep or temperature of the whole
    // device): one parameter where per-string drifts take one each, and the
    // same value on every string, which the per-string terms, added one at a
    // time, do not find.
    let shared = usize::from(EVERY_STRING);
    if !has_effect(shared, |e| matches!(e, Effect::Drift { .. })) {
        out.push(shared_drift_candidate(strings));
    }
    // A drift on every string, each its own rate (spools or strings that
    // warm and creep each their own way): added one string at a time, on a
    // lattice whose time goes with position, each string's term takes the
    // others' share of what the model's position terms take too, and the
    // shared drift the strings' mean rate. Offered while no string drifts.
    let drifting = structure
        .effects
        .iter()
        .any(|t| matches!(t.effect, Effect::Drift { .. }));
    if !drifting && strings.count() > 1 {
        out.push(each_string_drift_candidate(strings));
    }
    // One creep shared by every string (strings of one kind warming
    // alike): the drift of each string in proportion to its length.
    if !has_effect(shared, |e| matches!(e, Effect::Creep { .. })) {
        out.push(shared_creep_candidate(strings));
    }
    if !has_effect(shared, |e| matches!(e, Effect::Stretch { .. })) {
        out.push(shared_stretch_candidate(
            ev,
            strings,
            structure.priors.home_tension_n,
        ));
    }
    // A stretch of each string, its own stiffness and lead (strings cut
    // from other reels, leads of other lengths): where one stiffness for
    // every string differs between the session's halves, a sag many times
    // what the strings weigh stood in for it (decision record 0061).
    let stretched = structure
        .effects
        .iter()
        .any(|t| matches!(t.effect, Effect::Stretch { .. }));
    if config.stretches_of_each_string && !stretched && strings.count() > 1 {
        out.push(each_string_stretch_candidate(
            strings,
            structure.priors.home_tension_n,
        ));
    }
    if !has_effect(shared, |e| matches!(e, Effect::FrameFlex { .. })) {
        out.push(frame_flex_candidate(strings));
    }
    if !has_effect(shared, |e| matches!(e, Effect::Sag { .. })) {
        out.push(shared_sag_candidate(strings));
    }
    // A latency only where the rows observe the speed: a lattice's rows
    // are captured seconds apart, and a difference between them is not the
    // speed at the capture (the loop says so, `latency_not_tested`).
    if ev.speed_observed && !has_effect(shared, |e| matches!(e, Effect::Latency { .. })) {
        out.push(shared_latency_candidate(strings, config.clock_aligned));
    }
    // Guides where the strings leave the frame in space: in a plane every
    // chord is level with its swivel axis's normal plane, and the term is a
    // constant on each string (an offset's).
    if !strings.planar && !has_effect(shared, |e| matches!(e, Effect::Guide { .. })) {
        out.push(shared_guide_candidate(strings));
    }
    // The tracked body's origin off the strings' meeting point, seen through
    // the body's orientation (a tracker of rigid bodies gives it): the
    // meeting point is `p - R_body d`. Tried when every tracked row has an
    // orientation; a found offset is refined by the next diagnosis.
    if ev.every_row_oriented() {
        out.push(marker_offset_candidate(
            strings,
            structure.marker_body_mm.unwrap_or([0.0; 3]),
        ));
    }
    if !structure.fit_room_scale {
        out.push(Candidate {
            family: Family::Geometry,
            strings: Vec::new(),
            variable: Variable::Position,
            columns: vec![Box::new(|r| r.scale_gradient)],
            on_string: None,
            search_penalty: 0.0,
            rival: Vec::new(),
            build: Box::new(|_| Change::RoomScale),
            describe: "the tracker's scale differs from the device's (frame error)".into(),
        });
    }
    out
}

/// A term's effect from its fitted parameters.
type BuildEffect = Box<dyn Fn(&[f64]) -> Effect>;

/// One string's term a candidate would add: what differs between the
/// per-string candidates.
struct StringTerm {
    family: Family,
    variable: Variable,
    /// Whether an effect of the structure is this term already.
    is_term: fn(&Effect) -> bool,
    /// The term's columns, each read off the string's rows.
    columns: Vec<RowColumn>,
    /// Columns of a simpler explanation on the same rows the term must
    /// explain the residual beyond ([`Candidate::rival`]); empty: none.
    rival: Vec<RowColumn>,
    search_penalty: f64,
    /// The fitted parameters as the effect.
    effect: BuildEffect,
    describe: String,
}

impl StringTerm {
    /// The candidate adding this term on string `i`.
    fn candidate(self, i: usize) -> Candidate {
        let s = i as u8;
        let effect = self.effect;
        Candidate {
            family: self.family,
            strings: vec![s],
            variable: self.variable,
            columns: self
                .columns
                .into_iter()
                .map(|f| string_column(i, f))
                .collect(),
            on_string: Some(i),
            search_penalty: self.search_penalty,
            rival: self
                .rival
                .into_iter()
                .map(|f| string_column(i, f))
                .collect(),
            build: Box::new(move |b| {
                Change::Effect(EffectTerm {
                    string: s,
                    effect: effect(b),
                })
            }),
            describe: self.describe,
        }
    }
}

/// The terms one string `i` (of `rows` rows) can gain, in the order they
/// are tried; a latency when the rows observe the speed; a guide on a
/// device in space (`guides`); a slip when the string's residual steps at
/// `split` (its most likely slip time).
///
/// No scale of the payout ([`Effect::Scale`]): the base model carries one
/// in the string's radius, and in its own thinning rate once the spool
/// rates are free (`scale_is_carried_by_the_base_model` in
/// `host/tests/model/loop_closing.rs`). What a scale's column keeps off the
/// radius's is its thinning part, so the loop proposed scales of -0.6 for
/// a spool that thins at its own rate, and fitted them along the valley
/// `(1 + s) r_home` (record 0078).
fn string_terms(
    rows: usize,
    i: usize,
    split: Option<f64>,
    speed_observed: bool,
    guides: bool,
) -> Vec<StringTerm> {
    let mut terms = vec![
        StringTerm {
            family: Family::Offset,
            variable: Variable::Length,
            is_term: |e| matches!(e, Effect::Offset { .. }),
            columns: vec![Box::new(|_| 1.0)],
            rival: Vec::new(),
            search_penalty: 0.0,
            effect: Box::new(|b| Effect::Offset { mm: b[0] }),
            describe: format!("string {i} reads a constant length error (its home length is off)"),
        },
        StringTerm {
            family: Family::Winding,
            variable: Variable::WoundLength,
            is_term: |e| matches!(e, Effect::Winding { power: 3, .. }),
            columns: vec![Box::new(|r| r.ctx.theta.powi(3))],
            rival: Vec::new(),
            search_penalty: 0.0,
            effect: Box::new(|b| Effect::Winding {
                power: 3,
                mm_per_rad_pow: b[0],
            }),
            describe: format!("string {i}'s winding law needs a third-order term (uneven layers)"),
        },
        StringTerm {
            family: Family::Eccentricity,
            variable: Variable::PulleyAngle,
            is_term: |e| matches!(e, Effect::Eccentricity { .. }),
            columns: vec![
                Box::new(|r| r.ctx.theta.sin()),
                Box::new(|r| r.ctx.theta.cos() - 1.0),
            ],
            rival: Vec::new(),
            search_penalty: 3.0,
            effect: Box::new(|b| Effect::Eccentricity {
                sin_mm: b[0],
                cos_mm: b[1],
            }),
            describe: format!(
                "string {i}'s error is periodic in its pulley angle (eccentric pulley)"
            ),
        },
        StringTerm {
            family: Family::Elasticity,
            variable: Variable::Tension,
            is_term: |e| matches!(e, Effect::Elasticity { .. }),
            columns: vec![Box::new(|r| {
                r.ctx.tension_n * (r.ctx.home_length_mm + r.ctx.payout_mm)
            })],
            rival: Vec::new(),
            search_penalty: 0.0,
            effect: Box::new(|b| Effect::Elasticity { per_newton: b[0] }),
            describe: format!("string {i} stretches with its tension (elastic string)"),
        },
        StringTerm {
            family: Family::Backlash,
            variable: Variable::Direction,
            is_term: |e| matches!(e, Effect::Backlash { .. }),
            columns: vec![direction_column()],
            // Both read the motion: where the rows observe the speed, a
            // backlash must explain the residual beyond a latency's (and a
            // latency beyond a backlash's, below).
            rival: if speed_observed {
                vec![speed_column()]
            } else {
                Vec::new()
            },
            search_penalty: 0.0,
            effect: Box::new(|b| Effect::Backlash {
                half_width_mm: b[0],
            }),
            describe: format!("string {i}'s error depends on its direction of motion (backlash)"),
        },
        StringTerm {
            family: Family::Drift,
            variable: Variable::Time,
            is_term: |e| matches!(e, Effect::Drift { .. }),
            columns: vec![Box::new(|r| r.ctx.time_s)],
            rival: position_columns(),
            search_penalty: 0.0,
            effect: Box::new(|b| Effect::Drift { mm_per_s: b[0] }),
            describe: format!("string {i}'s length drifts with time since initialization"),
        },
        creep_term(i),
    ];
    if speed_observed {
        terms.push(StringTerm {
            family: Family::Latency,
            variable: Variable::Speed,
            is_term: |e| matches!(e, Effect::Latency { .. }),
            columns: vec![speed_column()],
            rival: vec![direction_column()],
            search_penalty: 0.0,
            effect: Box::new(|b| Effect::Latency { latency_s: b[0] }),
            describe: format!(
                "string {i}'s error follows its speed (its encoder is read late: latency)"
            ),
        });
    }
    if guides {
        terms.push(guide_term(i));
    }
    if let Some(at_s) = split {
        terms.push(slip_term(rows, i, at_s));
    }
    terms
}

/// A creep of string `i`: its length growing with time since home in
/// proportion to itself. A time term, judged as a drift is: beyond an
/// error quadratic in the position, where time goes with it.
fn creep_term(i: usize) -> StringTerm {
    StringTerm {
        family: Family::Creep,
        variable: Variable::Time,
        is_term: |e| matches!(e, Effect::Creep { .. }),
        columns: vec![Box::new(|r| creep_variable(&r.ctx))],
        rival: position_columns(),
        search_penalty: 0.0,
        effect: Box::new(|b| Effect::Creep { per_s: b[0] }),
        describe: format!(
            "string {i}'s length grows with time since home in proportion to itself (creep)"
        ),
    }
}

/// The guide a candidate proposes, refitted from a radius of 0: the
/// guide's entry point (the model's anchor) is about 1.6 radii from the
/// exit point the anchor held without it, so a start at the linear
/// estimate's radius with the anchors where they are lies across the
/// valley, and a fold's refit from there stopped short (a 20 mm guide on
/// every string of an independent device: its blocked folds 0.501 mm from
/// 0, 0.583 from 20 mm, 0.571 without the guide).
const GUIDE_START: Effect = Effect::Guide { radius_mm: 0.0 };

/// A guide pulley on string `i`.
fn guide_term(i: usize) -> StringTerm {
    StringTerm {
        family: Family::Guide,
        variable: Variable::Elevation,
        is_term: |e| matches!(e, Effect::Guide { .. }),
        columns: vec![guide_column()],
        rival: Vec::new(),
        search_penalty: 0.0,
        effect: Box::new(|_| GUIDE_START),
        describe: format!(
            "string {i}'s error follows its elevation from the frame edge: it wraps on a guide \
             pulley swivelling toward the end-effector"
        ),
    }
}

/// A guide's column: the term's slope in its radius at 0, the wrap on a
/// pulley of 1 mm less the chord's saving, `pi/2 - a - cos a`, at the
/// home's elevation less at the row's.
fn guide_column() -> RowColumn {
    Box::new(|r| guide_slope(0.0, &r.ctx))
}

/// One guide radius shared by every string (the frame's corners built
/// alike), each string at its own elevation.
fn shared_guide_candidate(strings: StringLayout) -> Candidate {
    Candidate {
        family: Family::Guide,
        strings: Vec::new(),
        variable: Variable::Elevation,
        columns: vec![shared_column(strings, |r| guide_slope(0.0, &r.ctx))],
        on_string: None,
        search_penalty: 0.0,
        rival: Vec::new(),
        build: Box::new(|_| every_string(GUIDE_START)),
        describe: "every string's error follows its elevation from the frame edge alike: the \
                   strings wrap on guide pulleys of one radius swivelling toward the end-effector"
            .into(),
    }
}

/// A backlash's column: the sign of the string's direction of motion.
fn direction_column() -> RowColumn {
    Box::new(|r| f64::from(r.ctx.direction.signum()))
}

/// A latency's column: the payout's rate of change (mm/s) at the row's
/// count rate, what the term multiplies by its delay.
fn speed_column() -> RowColumn {
    Box::new(|r| r.ctx.payout_rate_mm_s)
}

/// One latency shared by every string (encoders of one kind read by one
/// loop), where the rows observe the speed; `clock_aligned`: the tracker's
/// clock was found from the rows, so the term is that clock's offset
/// refined ([`LoopConfig::clock_aligned`]) and says so.
fn shared_latency_candidate(strings: StringLayout, clock_aligned: bool) -> Candidate {
    let describe = if clock_aligned {
        "every string's error follows its speed alike: the tracker's clock, found from these \
         rows, is off by the fitted time (a latency every string shares cannot be told from \
         the clock's offset: each row is paired with the marker as far off as the strings lag)"
    } else {
        "every string's error follows its speed alike (the encoders are read late)"
    };
    Candidate {
        family: Family::Latency,
        strings: Vec::new(),
        variable: Variable::Speed,
        columns: vec![shared_column(strings, |r| r.ctx.payout_rate_mm_s)],
        on_string: None,
        search_penalty: 0.0,
        rival: Vec::new(),
        build: Box::new(|b| every_string(Effect::Latency { latency_s: b[0] })),
        describe: describe.into(),
    }
}

/// A slip of string `i` (of `rows` rows) at `at_s`: a step in its length,
/// with the search penalty of a time picked among the string's rows.
fn slip_term(rows: usize, i: usize, at_s: f64) -> StringTerm {
    let n = rows.max(2) as f64;
    StringTerm {
        family: Family::Slip,
        variable: Variable::Time,
        // A string may slip again: its next step is looked for off the
        // model, which holds the steps found (a step at their times is
        // in the model's span).
        is_term: |_| false,
        columns: vec![Box::new(
            move |r| {
                if r.ctx.time_s >= at_s {
                    1.0
                } else {
                    0.0
                }
            },
        )],
        rival: Vec::new(),
        search_penalty: 2.0 * n.ln(),
        effect: Box::new(move |b| Effect::Slip { at_s, mm: b[0] }),
        describe: format!("string {i} slipped at t = {at_s:.1} s (a step in its length)"),
    }
}

/// A string's error quadratic in the tracked position (m, device frame):
/// what a drift can stand in for on a lattice walked plane by plane, where
/// time goes with position. A drift must explain the residual beyond it
/// (its nine columns); what tells a drift from a position error within one
/// session is the rows' time off any smooth function of the position (the
/// walk turning back at each row and plane, the user's pauses). Quadratic,
/// not linear: past a linear rival a drift still stands in for what an
/// offset explains, and the model simulator's drifts are found past the
/// quadratic one (decision record 0035,
/// `docs/decisions/0035-drift-beyond-position.md`).
pub(super) fn position_columns() -> Vec<RowColumn> {
    let mut out: Vec<RowColumn> = (0..3)
        .map(|k| Box::new(move |r: &Row| r.position[k] / 1000.0) as RowColumn)
        .collect();
    for a in 0..3 {
        for b in a..3 {
            out.push(Box::new(move |r: &Row| r.position[a] * r.position[b] / 1e6));
        }
    }
    out
}

/// The change of a term shared by every string.
fn every_string(effect: Effect) -> Change {
    Change::Effect(EffectTerm {
        string: EVERY_STRING,
        effect,
    })
}

/// One drift shared by every string.
fn shared_drift_candidate(strings: StringLayout) -> Candidate {
    Candidate {
        family: Family::Drift,
        strings: Vec::new(),
        variable: Variable::Time,
        columns: vec![shared_column(strings, |r| r.ctx.time_s)],
        on_string: None,
        search_penalty: 0.0,
        rival: Vec::new(),
        build: Box::new(|b| every_string(Effect::Drift { mm_per_s: b[0] })),
        describe: "every string's length drifts alike with time since initialization (creep, \
                   temperature of the whole device)"
            .into(),
    }
}

/// A drift on each active string, each its own rate ([`Change::Drifts`]):
/// one column per string, its time since home on its own rows, beyond the
/// shared drift.
fn each_string_drift_candidate(strings: StringLayout) -> Candidate {
    let active: Vec<usize> = strings.indices().collect();
    let columns = active
        .iter()
        .map(|&i| string_column(i, Box::new(|r| r.ctx.time_s)))
        .collect();
    // One rate shared by every string, which the strings' own rates must
    // explain the residual beyond: where they drift alike, one parameter,
    // not one per string. Not each string's position error (a one-string
    // drift's rival, [`position_columns`]): past those 73 columns the
    // model simulator's drifts around a shared rate are left at a
    // chi-square of 35 while the revisits show them at 10,000.
    let rival = vec![shared_column(strings, |r| r.ctx.time_s)];
    let on = active.clone();
    Candidate {
        family: Family::Drift,
        strings: active.iter().map(|&i| i as u8).collect(),
        variable: Variable::Time,
        columns,
        on_string: None,
        search_penalty: 0.0,
        rival,
        build: Box::new(move |b| {
            let mut drifts = [None; STRINGS];
            for (&i, &mm_per_s) in on.iter().zip(b) {
                drifts[i] = Some(mm_per_s);
            }
            Change::Drifts(drifts)
        }),
        describe: "every string's length drifts with time since home, each string at its own \
                   rate (spools or strings that warm or creep each their own way)"
            .into(),
    }
}

/// One creep shared by every string: each string's natural length grows
/// by one share of itself with time since home ([`Effect::Creep`]).
fn shared_creep_candidate(strings: StringLayout) -> Candidate {
    Candidate {
        family: Family::Creep,
        strings: Vec::new(),
        variable: Variable::Time,
        columns: vec![shared_column(strings, |r| creep_variable(&r.ctx))],
        on_string: None,
        search_penalty: 0.0,
        rival: Vec::new(),
        build: Box::new(|b| every_string(Effect::Creep { per_s: b[0] })),
        describe: "every string's length grows with time since home in proportion to itself \
                   alike (thermal creep of strings of one kind)"
            .into(),
    }
}

/// One stretch shared by every string (strings of one kind: one
/// stiffness, a similar lead from spool to guide, one tension at the home
/// capture): `k (T l - T_home l_home) + m (T - T_home)`. Detected with the
/// linear columns `T l`, `T` and `-1` (`T_home (k l_home + m)` at the mean
/// home length); the refit frees `T_home` around the pretension. With its
/// lead and home parts: without them the shared sag stands in for it
/// (decision record 0022, `docs/decisions/0022-stretch.md`).
fn shared_stretch_candidate(ev: &Evidence, strings: StringLayout, pretension: f64) -> Candidate {
    let (mut sum_lh, mut n_lh) = (0.0, 0usize);
    ev.for_each_row(None, |_, r| {
        if strings.is_active(r.string) {
            sum_lh += r.ctx.home_length_mm;
            n_lh += 1;
        }
    });
    let mean_lh = sum_lh / n_lh.max(1) as f64;
    Candidate {
        family: Family::Elasticity,
        strings: Vec::new(),
        variable: Variable::Tension,
        columns: stretch_columns(strings),
        on_string: None,
        search_penalty: 0.0,
        rival: Vec::new(),
        build: Box::new(move |b| {
            let home_tension_n = b[2] / (b[0] * mean_lh + b[1]);
            every_string(Effect::Stretch {
                per_newton: b[0],
                mm_per_newton: b[1],
                home_tension_n: if (0.0..=2.0 * pretension + 1.0).contains(&home_tension_n) {
                    home_tension_n
                } else {
                    pretension
                },
            })
        }),
        describe: "every string stretches with its tension, over its free span and its \
                   lead, less its stretch at the home capture (elastic strings of one kind)"
            .into(),
    }
}

/// A stretch on each active string, each its own stiffness and lead
/// ([`Change::Stretches`]): `T l` and `T` on each string's rows (its
/// constant, the home part, is the string's home length's); beyond the
/// shared stretch's columns.
fn each_string_stretch_candidate(strings: StringLayout, pretension: f64) -> Candidate {
    let active: Vec<usize> = strings.indices().collect();
    let mut columns: Vec<RowColumn> = Vec::new();
    for &i in &active {
        columns.push(string_column(
            i,
            Box::new(|r| r.ctx.tension_n * (r.ctx.home_length_mm + r.ctx.payout_mm)),
        ));
        columns.push(string_column(i, Box::new(|r| r.ctx.tension_n)));
    }
    let on = active.clone();
    Candidate {
        family: Family::Elasticity,
        strings: active.iter().map(|&i| i as u8).collect(),
        variable: Variable::Tension,
        columns,
        on_string: None,
        search_penalty: 0.0,
        rival: stretch_columns(strings),
        build: Box::new(move |b| {
            let mut each = [None; STRINGS];
            for (k, &i) in on.iter().enumerate() {
                each[i] = Some((b[2 * k], b[2 * k + 1]));
            }
            Change::Stretches(each, pretension)
        }),
        describe: "every string stretches with its tension, each its own stiffness and lead \
                   (strings of other kinds or lengths of lead)"
            .into(),
    }
}

/// The strings' stretch's columns on every active string, `T l`, `T` and
/// `-1` ([`Effect::Stretch`] linearized at the mean home length): the
/// stretch candidate's; the first is what a shared sag must explain the
/// residual beyond. Both grow with the tension's effect on the string, and
/// without that test a sag many times what the strings weigh stands in for
/// the stretch of light elastic strings.
fn stretch_columns(strings: StringLayout) -> Vec<RowColumn> {
    vec![
        shared_column(strings, |r| {
            r.ctx.tension_n * (r.ctx.home_length_mm + r.ctx.payout_mm)
        }),
        shared_column(strings, |r| r.ctx.tension_n),
        shared_column(strings, |_| -1.0),
    ]
}

/// The frame flexing under the strings' total pull: every guide moves
/// with `sum_j T_j`, one compliance for the frame, less the flex at the
/// home capture (a length every string shares).
fn frame_flex_candidate(strings: StringLayout) -> Candidate {
    Candidate {
        family: Family::FrameFlex,
        strings: Vec::new(),
        variable: Variable::Tension,
        columns: vec![
            shared_column(strings, |r| r.ctx.total_tension_n),
            shared_column(strings, |_| -1.0),
        ],
        on_string: None,
        search_penalty: 0.0,
        rival: Vec::new(),
        build: Box::new(|b| {
            every_string(Effect::FrameFlex {
                mm_per_newton: b[0],
                home_mm: b[1],
            })
        }),
        describe: "every string's length moves with the strings' total tension (the frame \
                   flexes under their pull)"
            .into(),
    }
}

/// One sag shared by every string (strings of one kind: one weight per
/// metre, one tension at the home capture), each string at its own
/// length, tension and inclination. Not one string's: its home part is a
/// constant on that string (an offset), and per-string sags stand in for
/// offsets and raise the test error (decision record 0021,
/// `docs/decisions/0021-sag.md`).
fn shared_sag_candidate(strings: StringLayout) -> Candidate {
    Candidate {
        family: Family::Sag,
        strings: Vec::new(),
        variable: Variable::Tension,
        columns: vec![
            shared_column(strings, |r| -sag_variable(&r.ctx)),
            shared_column(strings, |r| sag_home_variable(&r.ctx)),
        ],
        on_string: None,
        search_penalty: 0.0,
        // The stretch's `T l` column only: with its three columns as the
        // rival a different sag gets through, and a drift after it, which
        // raise the test error.
        rival: stretch_columns(strings).into_iter().take(1).collect(),
        build: Box::new(|b| {
            every_string(Effect::Sag {
                mm_at_1m_1n: b[0],
                home_mm_at_1m: b[1],
            })
        }),
        describe: "every string sags under its own weight, by cos^2(inclination) (l / 1 m)^3 \
                   / (T / 1 N)^2 less its sag at the home capture (heavy strings of one kind)"
            .into(),
    }
}

/// The tracked body's origin off the strings' meeting point: three
/// columns, the body's orientation applied to each axis; the change adds
/// the fitted offset to the one found `before`.
fn marker_offset_candidate(strings: StringLayout, before: [f64; 3]) -> Candidate {
    Candidate {
        family: Family::Marker,
        strings: Vec::new(),
        variable: Variable::Orientation,
        columns: (0..3)
            .map(|j| shared_column(strings, move |r| r.marker_column.map_or(0.0, |c| c[j])))
            .collect(),
        on_string: None,
        search_penalty: 0.0,
        rival: Vec::new(),
        build: Box::new(move |b| Change::MarkerOffset(core::array::from_fn(|j| before[j] + b[j]))),
        describe: "the tracked body's origin is off the strings' meeting point: it turns \
                   with the body (the tracker's orientation)"
            .into(),
    }
}

/// Why the latency family had no candidate, as a finding the report
/// lists: the rows carry no count rate (`data::observe`: they do not
/// resolve the motion, [`speed_observation`] of them says how far from it
/// they are). `None` when they do (the family was tested).
pub(super) fn latency_not_tested(observations: &[Observation]) -> Option<Finding> {
    if observes_speed(observations) || observations.is_empty() {
        return None;
    }
    let s = speed_observation(observations);
    let why = if s.moving == 0 {
        "no string moved between its neighbouring rows".to_string()
    } else {
        format!(
            "a moving string's speed changes by {:.0} % of itself from one row interval to the \
             next (median of {} rows and strings; a stream that resolves the motion changes by \
             less than {:.0} %)",
            100.0 * s.speed_change,
            s.moving,
            100.0 * MAX_STREAM_SPEED_CHANGE
        )
    };
    Some(Finding {
        family: Family::Latency,
        strings: Vec::new(),
        variable: Variable::Speed,
        amplitude_mm: 0.0,
        explained: 0.0,
        added: false,
        chi2: 0.0,
        description: format!(
            "not tested: the rows do not observe the strings' speed (static session: rows {:.2} s \
             apart, {why}), so a difference of neighbouring rows is not the speed at a capture \
             and an encoder's latency cannot be told here",
            s.median_interval_s
        ),
        validation: None,
        change: None,
    })
}

/// Whether each candidate explains the residual beyond its rival's
/// columns: its chi-square over the rival's alone, at the candidate's dof.
/// In one pass over the rows for all of them.
pub(super) fn beyond_rivals(ev: &Evidence, tried: &[&Candidate], config: &LoopConfig) -> Vec<bool> {
    let sets: Vec<Columns> = tried.iter().map(|c| c.with_rival()).collect();
    ev.off_span(&sets)
        .iter()
        .zip(tried)
        .map(|(off, c)| beyond_rival(ev, off, c, config))
        .collect()
}

/// [`beyond_rivals`] of `c` from its rival's and its own columns off the
/// model's span (`off`).
fn beyond_rival(ev: &Evidence, off: &OffSpan, c: &Candidate, config: &LoopConfig) -> bool {
    let rival = c.rival.len();
    (off.explained_by_span(0..rival + c.columns.len()) - off.explained_by_span(0..rival))
        / ev.sigma2
        >= chi2_threshold(config, c.columns.len(), c.search_penalty)
}

pub(super) fn chi2_threshold(config: &LoopConfig, dof: usize, penalty: f64) -> f64 {
    config.chi2_threshold + 3.0 * (dof.saturating_sub(1)) as f64 + penalty
}

/// Anchors the data pull far beyond their design tolerance: the fitted
/// anchor's distance from its design position, in prior standard deviations,
/// is beyond what the tolerance explains (chi-square, 3 dof, p = 0.001), so
/// the prior is fighting the data (a bracket mounted in another hole, a frame
/// built off the drawing). Releasing the prior is the geometry change.
pub(super) fn anchors_beyond_tolerance(
    id: &Identification,
    nominal: &Frame<f64>,
    structure: &Structure,
) -> Vec<Finding> {
    (0..STRINGS)
        .filter(|&i| nominal.layout.is_active(i))
        .filter(|&i| structure.anchor_sd_override_mm[i].is_none())
        .filter_map(|i| {
            let sd = structure.priors.anchor_tolerance_mm(i);
            let d = [
                id.frame.anchors[i][0] - nominal.anchors[i][0],
                id.frame.anchors[i][1] - nominal.anchors[i][1],
                id.frame.anchors[i][2] - nominal.anchors[i][2],
            ];
            let chi2 = d.iter().map(|v| (v / sd).powi(2)).sum::<f64>();
            // Mahalanobis distance under the prior beyond chi-square(3 dof)
            // at p = 0.001: the as-built tolerance does not explain it.
            (chi2 > chi_square_p001(3)).then(|| Finding {
                family: Family::Geometry,
                strings: vec![i as u8],
                variable: Variable::Position,
                amplitude_mm: (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt(),
                explained: 0.0,
                added: false,
                chi2,
                description: format!(
                    "anchor {i} sits {:.1} mm from its design position ({:+.1}, {:+.1}, {:+.1}), beyond the {sd} mm tolerance",
                    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt(),
                    d[0],
                    d[1],
                    d[2]
                ),
                validation: None,
                change: Some(Change::ReleaseAnchor(i as u8)),
            })
        })
        .collect()
}
