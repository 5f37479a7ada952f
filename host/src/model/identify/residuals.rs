//! The string-space residual of one row: the tracker's geometric string
//! length less the model's.

use std::borrow::Borrow;

use spidar_core::geometry::{device_from_room, distance};
use spidar_core::model::{EffectTerm, Frame, StringInputs, StringLaw};
use spidar_core::string_law::{
    cos2_inclinations, guide_elevations, string_lengths_at_homes, StringHome,
};
use spidar_core::STRINGS;

use crate::data::observe::Observation;

/// The tracker position of `o` in the device frame (mm); on a planar
/// device, in the anchors' plane whatever the tracker's z.
pub fn device_position(frame: &Frame<f64>, o: &Observation) -> [f64; 3] {
    let mut p = device_from_room(frame, o.tracker.unwrap_or([0.0; 3]));
    if frame.layout.planar {
        p[2] = frame.anchors[0][2];
    }
    p
}

/// `o`'s inputs with each string's inclination and elevation (what a sag
/// and a guide term read) at
/// `p`, the tracker's position in the device frame ([`device_position`]).
pub fn inputs_at(frame: &Frame<f64>, o: &Observation, p: &[f64; 3]) -> StringInputs {
    StringInputs {
        cos2_inclination_q16: cos2_inclinations(&frame.anchors, p),
        guide_elevation_q32: guide_elevations(&frame.anchors, &frame.home, p),
        ..o.inputs
    }
}

/// [`inputs_at`] when one of `effects` reads the strings' inclination or
/// elevation (a sag, a guide), else `o`'s inputs as they are: no other term
/// reads those two, and working them out is a tenth of a long
/// identification's time.
pub(crate) fn inputs_for(
    frame: &Frame<f64>,
    effects: &[EffectTerm],
    o: &Observation,
    p: &[f64; 3],
) -> StringInputs {
    if effects.iter().any(|t| t.effect.reads_inclination()) {
        inputs_at(frame, o, p)
    } else {
        o.inputs
    }
}

/// String-space residuals (geometric minus model, mm) of one observation; 0
/// on channels without a string. `homes`: the frame's home terms
/// ([`StringHome::of_every_string`], worked out once per frame).
pub(crate) fn residuals_at_homes(
    frame: &Frame<f64>,
    homes: &[Option<StringHome>; STRINGS],
    laws: &[StringLaw; STRINGS],
    effects: &[EffectTerm],
    o: &Observation,
) -> [f64; STRINGS] {
    let p = device_position(frame, o);
    let inputs = inputs_for(frame, effects, o, &p);
    let lengths = string_lengths_at_homes(homes, frame.layout.active, laws, effects, &inputs);
    let mut r = [0.0; STRINGS];
    for i in frame.layout.indices() {
        r[i] = distance(p, frame.anchors[i]) - lengths[i];
    }
    r
}

/// String-space residuals (geometric minus model, mm) of every observation
/// with a tracker position under an identified model; `None` for occluded
/// rows. Each row on its own, on every core.
pub fn string_residuals<O: Borrow<Observation> + Sync>(
    frame: &Frame<f64>,
    laws: &[StringLaw; STRINGS],
    effects: &[EffectTerm],
    observations: &[O],
) -> Vec<Option<[f64; STRINGS]>> {
    use rayon::prelude::*;
    let homes = StringHome::of_every_string(frame);
    observations
        .par_iter()
        .map(|o| {
            let o = o.borrow();
            o.tracker?;
            Some(residuals_at_homes(frame, &homes, laws, effects, o))
        })
        .collect()
}

/// String residuals larger than this (mm) are gross failures (a string off
/// its pulley, a jammed motor), not calibration effects: diagnosis leaves them
/// out. Everything smaller stays in, even what the robust fit down-weighted:
/// a systematic effect the model lacks (a slip, say) looks like outliers to
/// the fit, and diagnosis must see it to name it.
pub const GROSS_RESIDUAL_MM: f64 = 25.0;
