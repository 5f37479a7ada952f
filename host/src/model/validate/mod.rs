//! Held-out validation: whether a change to the model helps on data it was
//! not fitted on. Below the diagnosis loop (`diagnose`) and the layer
//! tables (`layers`), which both judge their changes here; it knows neither.
//!
//! - folds: the folds of a session, interleaved and blocked (in time: the
//!   later and the earlier half; in space: the outer shell), which see
//!   extrapolation;
//! - errors: a model's position errors on tracked rows, as the device
//!   solves them ([`model_errors`]) and as the judge does (held out), and
//!   the sampling noise of their tail ([`tail_noise`]);
//! - held out: a structure refitted on each fold and its errors on the rows
//!   the fold holds out ([`validate`], [`Validation`]);
//! - preferred: a choice among alternatives by their held-out means, the
//!   first being the default ([`preferred`]);
//! - the verdict: [`judge`] on the figures before and after a change
//!   ([`Check`]), and the tests particular to steps in time, drifts and
//!   terms on one string.

mod errors;
mod folds;
mod held_out;
mod judge;
mod preferred;

pub(crate) use errors::held_out_error_list;
pub use errors::{later_session_errors, model_errors, predict_later, tail_noise};
pub(crate) use folds::{choice_folds, folds, judgeable_folds};
pub use folds::{Folds, MIN_BLOCKED_ROWS, MIN_STEP_SIDE_ROWS, SMALL_SESSION_FOLDS};
pub use held_out::{cross_validated_error, validate, validate_forward, FoldScope, Validation};
pub(crate) use held_out::{
    fold_fits, interleaved_fold_errors, judged_fold_fits, validate_by, validate_fits,
};
pub use judge::{judge, Check, FAILING_ROW_FACTOR, FAILING_ROW_RISE};
pub(crate) use judge::{
    judge_step, refuse_a_fold_repair, refuse_on_fold_rise, refused, stability,
    IN_SAMPLE_SHARE_OF_GAIN,
};
pub use preferred::{preferred, Preferred};
