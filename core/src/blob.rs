//! The compiled calibration: one versioned blob that the device evaluates.
//!
//! ```text
//! blob = protocol::blob header (40 bytes: magic, version, kind, dimensions, Q formats, CRCs)
//!      + body
//! body = postcard(BlobHead { frame: Frame<f32>, laws: [CompiledStringLaw; 8],
//!                            effects: heapless::Vec<CompiledEffect, MAX_EFFECTS>,
//!                            residual_weight: [f32; 8],
//!                            exclusion_threshold_mm: f32, fault_threshold_mm: f32,
//!                            home: Option<CompiledHomeSlips> })
//!      + 0 to 3 zero bytes, so that the correction starts at a multiple of
//!        CORRECTION_ALIGN = 4 bytes from the blob start (format version 2)
//!      + correction bytes (layout in `correction`, read in place, zero-copy)
//! ```
//!
//! The padding lets a device that keeps the blob in a 4-byte aligned buffer
//! read the SVR records as aligned words (see `docs/fixed-point.md`); a blob
//! at any other address still parses and evaluates the same, more slowly.
//!
//! The device parses a blob once at load ([`CompiledCalibration::from_blob`]:
//! every dimension, Q format and parameter range is checked, and a blob it
//! does not understand is refused with a [`BlobError`] naming the field), then
//! evaluates it every control-loop iteration. The host compiles a
//! [`crate::model::Calibration`] with [`compile`] and links the same parser to
//! check the blob bit for bit before flashing.

use serde::{Deserialize, Serialize};
use spidar_protocol::blob::{split_blob, BlobError, ModelHeader, HEADER_LEN};

use crate::correction::{check_header_formats, Correction, POSITION_FRAC};
use crate::model::{Frame, StringInputs, MAX_EFFECTS, MAX_HOME_SLIPS};
use crate::string_law::{string_lengths, CompiledEffect, CompiledStringLaw};
use crate::STRINGS;

/// Fractional bits of string lengths in the blob (header `q_length`): Q47.16 mm.
pub const LENGTH_FRAC: u8 = 16;

/// Alignment, from the blob start, of the correction bytes in the body: the
/// compiler pads the body after the string model with zero bytes up to it.
pub const CORRECTION_ALIGN: usize = 4;

/// Zero bytes between the string model, which ends `offset` bytes after the
/// blob start, and the correction.
pub const fn correction_padding(offset: usize) -> usize {
    (CORRECTION_ALIGN - offset % CORRECTION_ALIGN) % CORRECTION_ALIGN
}

/// Splits a blob body (as returned by `split_blob`) into its decoded string
/// model and its correction bytes, checking the padding between them (present
/// and zero). Does not check the string model's values.
pub fn split_body(body: &[u8]) -> Result<(BlobHead, &[u8]), BlobError> {
    let (head, rest): (BlobHead, &[u8]) =
        postcard::take_from_bytes(body).map_err(|_| BlobError::Body {
            field: "string model",
        })?;
    let pad = correction_padding(HEADER_LEN + (body.len() - rest.len()));
    match rest.split_at_checked(pad) {
        Some((padding, correction)) if padding.iter().all(|&b| b == 0) => Ok((head, correction)),
        _ => Err(BlobError::Body { field: "padding" }),
    }
}

/// The string-model part of the body.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BlobHead {
    /// Geometry for forward kinematics and the room transform, f32 (mm).
    pub frame: Frame<f32>,
    pub laws: [CompiledStringLaw; STRINGS],
    pub effects: heapless::Vec<CompiledEffect, MAX_EFFECTS>,
    /// Weight of each string's residual in forward kinematics
    /// ([`crate::kinematics::FkConfig::residual_weight`]), compiled from the
    /// calibration's measured length residual scales by
    /// [`crate::kinematics::residual_weights`]; within
    /// `[MIN_RESIDUAL_WEIGHT, 1]` (1 on inactive channels). Format 8.
    pub residual_weight: [f32; STRINGS],
    /// [`crate::kinematics::FkConfig::exclusion_threshold_mm`] the
    /// calibration chose ([`crate::kinematics::KinematicsRule`]), mm;
    /// positive, at most `fault_threshold_mm`. Format 9.
    pub exclusion_threshold_mm: f32,
    /// [`crate::kinematics::FkConfig::fault_threshold_mm`], mm. Format 9.
    pub fault_threshold_mm: f32,
    /// The training session's slips and its home capture's id
    /// ([`crate::model::HomeSlips`]): applied while the device's home
    /// capture is that one. Format 12.
    pub home: Option<CompiledHomeSlips>,
}

/// One training slip in the blob: `+ mm_q16` (Q47.16 mm) on `string` from
/// `at_ms` (ms since the home capture) on, what a
/// [`CompiledEffect::Slip`] of the same string adds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompiledSlip {
    pub string: u8,
    pub at_ms: u32,
    pub mm_q16: i64,
}

/// The training session's slips ([`crate::model::HomeSlips`]) in the blob,
/// each on one active string: what the device adds to the string lengths
/// while its home capture's id (`State::home_id`) is `home_id`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompiledHomeSlips {
    pub home_id: u64,
    pub slips: heapless::Vec<CompiledSlip, MAX_HOME_SLIPS>,
}

impl CompiledHomeSlips {
    /// Adds the slips due at `time_ms` (ms since the home capture) to
    /// `lengths_q16` (Q47.16 mm), saturating. The same bits as the slips
    /// among the effect terms of [`string_lengths`] (a whole number of
    /// Q47.16 steps added before or after its Q31.32 -> Q47.16 rounding
    /// gives the same result), short of saturation, which lengths of
    /// +-2^31 mm do not reach. Slips on a string out of range are skipped
    /// (the parser refuses them).
    #[inline]
    pub fn add_to(&self, lengths_q16: &mut [i64; STRINGS], time_ms: u32) {
        for slip in self.slips.iter().filter(|s| time_ms >= s.at_ms) {
            if let Some(l) = lengths_q16.get_mut(usize::from(slip.string)) {
                *l = l.saturating_add(slip.mm_q16);
            }
        }
    }
}

impl BlobHead {
    /// The training's slips when `home_id` is their home capture's, else
    /// `None` (a new home capture, or a blob without slips).
    #[inline]
    pub fn home_slips(&self, home_id: u64) -> Option<&CompiledHomeSlips> {
        self.home.as_ref().filter(|h| h.home_id == home_id)
    }

    /// The string lengths (Q47.16 mm) the device computes under home
    /// capture `home_id`: [`string_lengths`] of the laws and effects, plus
    /// the training's slips when `home_id` is theirs
    /// ([`BlobHead::home_slips`]; never under `None`, an unknown capture).
    #[inline]
    pub fn string_lengths(&self, inputs: &StringInputs, home_id: Option<u64>) -> [i64; STRINGS] {
        let mut lengths = string_lengths(self.frame.layout, &self.laws, &self.effects, inputs);
        if let Some(home) = home_id.and_then(|id| self.home_slips(id)) {
            home.add_to(&mut lengths, inputs.time_ms);
        }
        lengths
    }

    /// `config` with the blob's residual weights and thresholds.
    pub fn fk_config(
        &self,
        config: &crate::kinematics::FkConfig<f32>,
    ) -> crate::kinematics::FkConfig<f32> {
        crate::kinematics::FkConfig {
            residual_weight: self.residual_weight,
            exclusion_threshold_mm: self.exclusion_threshold_mm,
            fault_threshold_mm: self.fault_threshold_mm,
            ..*config
        }
    }
}

/// A parsed, checked blob, borrowing the correction's parameters from the
/// blob bytes (in flash on the device).
#[derive(Clone, Debug, PartialEq)]
pub struct CompiledCalibration<'a> {
    pub header: ModelHeader,
    pub head: BlobHead,
    pub correction: Correction<'a>,
}

/// Whether the frame's values are finite (anchors of active strings only:
/// the others are never read) and its scale positive.
fn frame_is_finite(frame: &Frame<f32>) -> bool {
    let layout = frame.layout;
    let anchors_ok = frame
        .anchors
        .iter()
        .enumerate()
        .all(|(i, a)| !layout.is_active(i) || a.iter().all(|v| v.is_finite()));
    let mut values = frame
        .home
        .iter()
        .chain(frame.room_rotation.iter().flatten())
        .chain(frame.room_translation.iter());
    anchors_ok
        && values.all(|v| v.is_finite())
        && frame.room_scale.is_finite()
        && frame.room_scale > 0.0
}

/// Checks a frame's string layout against the strings the header announces
/// and the end-effector's degrees of freedom, and the effect terms against
/// the layout (none on an inactive channel).
fn check_layout(header: &ModelHeader, head: &BlobHead) -> Result<(), BlobError> {
    let layout = head.frame.layout;
    let count = layout.count();
    if count < layout.dof() {
        return Err(BlobError::TooFewStrings {
            strings: count as u8,
            dof: layout.dof() as u8,
        });
    }
    if header.strings as usize != count {
        return Err(BlobError::Dimension {
            field: "strings",
            found: header.strings as u32,
            expected: count as u32,
        });
    }
    for effect in head.effects.iter() {
        let s = effect.string();
        if s != crate::model::EVERY_STRING && !layout.is_active(usize::from(s)) {
            return Err(BlobError::InactiveString {
                field: "effects",
                string: s,
            });
        }
    }
    // A training slip is on one active string (never shared).
    for slip in head.home.iter().flat_map(|h| h.slips.iter()) {
        if !layout.is_active(usize::from(slip.string)) {
            return Err(BlobError::InactiveString {
                field: "home.slips",
                string: slip.string,
            });
        }
    }
    Ok(())
}

impl CompiledCalibration<'_> {
    /// The instructions the device's tick is estimated to take with this
    /// model and its correction ([`crate::tick_cost::tick_instructions`]);
    /// within [`crate::tick_cost::TICK_BUDGET`], or the blob was refused.
    pub fn tick_instructions(&self) -> u32 {
        crate::tick_cost::tick_instructions(
            &self.head,
            self.header.kind,
            self.header.hidden,
            self.header.support_vectors,
        )
    }
}

impl<'a> CompiledCalibration<'a> {
    /// Checks and parses a whole blob (header, CRCs, dimensions, Q formats,
    /// every parameter). Never panics, whatever the bytes.
    pub fn from_blob(bytes: &'a [u8]) -> Result<CompiledCalibration<'a>, BlobError> {
        let (header, body) = split_blob(bytes)?;
        if header.q_length != LENGTH_FRAC {
            return Err(BlobError::Dimension {
                field: "q_length",
                found: header.q_length as u32,
                expected: LENGTH_FRAC as u32,
            });
        }
        check_header_formats(header.q_position, header.q_weight)?;
        let (head, correction_bytes) = split_body(body)?;
        if head.effects.len() != header.effects as usize {
            return Err(BlobError::Dimension {
                field: "effects",
                found: head.effects.len() as u32,
                expected: header.effects as u32,
            });
        }
        if !frame_is_finite(&head.frame) {
            return Err(BlobError::Body { field: "frame" });
        }
        for effect in head.effects.iter() {
            effect
                .validate()
                .map_err(|_| BlobError::Body { field: "effects" })?;
        }
        check_layout(&header, &head)?;
        let lowest = crate::kinematics::MIN_RESIDUAL_WEIGHT as f32;
        if head
            .residual_weight
            .iter()
            .any(|w| !(lowest..=1.0).contains(w))
        {
            return Err(BlobError::Body {
                field: "residual_weight",
            });
        }
        let (exclusion, fault) = (head.exclusion_threshold_mm, head.fault_threshold_mm);
        if !(exclusion.is_finite() && exclusion > 0.0) {
            return Err(BlobError::Body {
                field: "exclusion_threshold_mm",
            });
        }
        if !(fault.is_finite() && fault >= exclusion) {
            return Err(BlobError::Body {
                field: "fault_threshold_mm",
            });
        }
        // Laws of inactive channels are never evaluated (the compiler writes
        // zeros there).
        for (i, law) in head.laws.iter().enumerate() {
            if head.frame.layout.is_active(i) {
                law.validate(i)
                    .map_err(|_| BlobError::Body { field: "laws" })?;
            }
        }
        if let Some(tick) =
            crate::tick_cost::over_budget(&head, header.kind, header.hidden, header.support_vectors)
        {
            return Err(BlobError::OverBudget {
                field: "tick",
                found: tick,
                most: crate::tick_cost::TICK_BUDGET,
            });
        }
        let correction = Correction::parse(
            header.kind,
            header.hidden,
            header.support_vectors,
            correction_bytes,
        )?;
        Ok(CompiledCalibration {
            header,
            head,
            correction,
        })
    }
}

#[cfg(feature = "alloc")]
pub use compiler::{compile, BlobCompileError, HomeSlipProblem};

#[cfg(feature = "alloc")]
mod compiler {
    use super::*;
    use crate::model::Calibration;
    use crate::string_law::{compile_effect, compile_string_law};
    use alloc::vec::Vec;
    use spidar_protocol::blob::{write_blob, FORMAT_VERSION};

    /// Why a calibration does not compile into a blob; names the part.
    #[cfg_attr(feature = "defmt", derive(defmt::Format))]
    #[derive(Clone, Copy, Debug, PartialEq)]
    pub enum BlobCompileError {
        /// A frame value that is not finite or does not fit f32.
        Frame {
            field: &'static str,
        },
        StringLaw(crate::string_law::StringLawCompileError),
        TooManyEffects {
            found: usize,
            max: usize,
        },
        Correction(crate::correction::CorrectionCompileError),
        /// The frame's string layout has fewer active strings than the
        /// end-effector's degrees of freedom (`frame.layout`), or an effect
        /// term is on a channel it marks inactive (`effects`, `string`).
        Layout {
            field: &'static str,
            string: Option<u8>,
        },
        /// An active string's measured residual scale (`length_scale_mm`)
        /// is not a positive finite number while others are measured
        /// (a calibration that did not measure them has zeros on every
        /// string).
        LengthScale {
            string: u8,
        },
        /// The kinematics rule's thresholds are not positive numbers with
        /// the exclusion's at most the fault's (`kinematics`).
        KinematicsRule {
            exclusion_threshold_mm: f64,
            fault_threshold_mm: f64,
        },
        /// The calibration cannot be a device (a rotation that is not one,
        /// coincident or far-flung anchors, a payout that falls).
        Implausible(crate::plausible::Implausible),
        /// More training slips (`home.slips`) than a blob carries.
        TooManyHomeSlips {
            found: usize,
            max: usize,
        },
        /// Training slip `home.slips[index]` does not fit the blob.
        HomeSlip {
            index: usize,
            problem: HomeSlipProblem,
        },
        /// The model's tick is estimated to take more instructions than the
        /// device has in one ([`crate::tick_cost`]): its effect terms, slips
        /// and correction together.
        TickOverBudget {
            instructions: u32,
            most: u32,
        },
        /// The body could not be encoded (should not happen).
        Encode,
    }

    /// Why a training slip (`home.slips[index]`) does not fit the blob.
    #[cfg_attr(feature = "defmt", derive(defmt::Format))]
    #[derive(Clone, Copy, Debug, PartialEq)]
    pub enum HomeSlipProblem {
        /// The term is not a slip (`Effect::Slip`).
        NotASlip,
        /// Its string is out of range, shared ([`crate::model::EVERY_STRING`])
        /// or a channel `frame.layout` marks inactive: a training slip is on
        /// one string.
        String { string: u8 },
        /// Its time or size does not fit the slip's fixed point.
        Value(crate::string_law::StringLawCompileError),
    }

    impl core::fmt::Display for HomeSlipProblem {
        fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
            match self {
                HomeSlipProblem::NotASlip => write!(f, "is not a slip term"),
                HomeSlipProblem::String { string } => write!(
                    f,
                    "is on string {string}, not one of the strings `frame.layout` marks active \
                     (a training slip is on one string)"
                ),
                HomeSlipProblem::Value(e) => write!(f, "{e}"),
            }
        }
    }

    impl core::fmt::Display for BlobCompileError {
        fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
            match self {
                BlobCompileError::Frame { field } => {
                    write!(f, "frame field `{field}` is not a finite f32")
                }
                BlobCompileError::StringLaw(e) => write!(f, "string model: {e}"),
                BlobCompileError::TooManyEffects { found, max } => {
                    write!(f, "{found} effect terms, a blob carries at most {max}")
                }
                BlobCompileError::Correction(e) => write!(f, "position correction: {e}"),
                BlobCompileError::KinematicsRule {
                    exclusion_threshold_mm,
                    fault_threshold_mm,
                } => write!(
                    f,
                    "`kinematics`: exclusion threshold {exclusion_threshold_mm} mm and fault \
                     threshold {fault_threshold_mm} mm must be positive numbers, the exclusion's \
                     at most the fault's"
                ),
                BlobCompileError::Layout {
                    field,
                    string: Some(s),
                } => write!(
                    f,
                    "`{field}` refers to string {s}, which `frame.layout` marks inactive"
                ),
                BlobCompileError::Layout {
                    field,
                    string: None,
                } => write!(
                    f,
                    "`{field}` has fewer active strings than the end-effector's degrees of freedom"
                ),
                BlobCompileError::LengthScale { string } => write!(
                    f,
                    "`length_scale_mm` of string {string} is not a positive number \
                     (zeros on every string: not measured)"
                ),
                BlobCompileError::Implausible(e) => write!(f, "not a device: {e}"),
                BlobCompileError::TooManyHomeSlips { found, max } => write!(
                    f,
                    "`home.slips` has {found} training slips, a blob carries at most {max}"
                ),
                BlobCompileError::HomeSlip { index, problem } => {
                    write!(f, "`home.slips[{index}]` {problem}")
                }
                BlobCompileError::TickOverBudget { instructions, most } => write!(
                    f,
                    "the device's control loop would take an estimated {instructions} \
                     instructions a tick with this model, over the {most} it has: fewer effect \
                     terms or a smaller correction"
                ),
                BlobCompileError::Encode => write!(f, "blob body could not be encoded"),
            }
        }
    }

    impl core::error::Error for BlobCompileError {}

    fn to_f32(v: f64, field: &'static str) -> Result<f32, BlobCompileError> {
        let x = v as f32;
        if x.is_finite() {
            Ok(x)
        } else {
            Err(BlobCompileError::Frame { field })
        }
    }

    fn frame_f32(frame: &Frame<f64>) -> Result<Frame<f32>, BlobCompileError> {
        let mut out = Frame {
            layout: frame.layout,
            anchors: [[0.0f32; 3]; STRINGS],
            home: [0.0; 3],
            room_rotation: [[0.0; 3]; 3],
            room_translation: [0.0; 3],
            room_scale: to_f32(frame.room_scale, "room_scale")?,
        };
        // Inactive channels' anchors are never read: written as zeros.
        for (i, (o, a)) in out.anchors.iter_mut().zip(&frame.anchors).enumerate() {
            if frame.layout.is_active(i) {
                for c in 0..3 {
                    o[c] = to_f32(a[c], "anchors")?;
                }
            }
        }
        for c in 0..3 {
            out.home[c] = to_f32(frame.home[c], "home")?;
            out.room_translation[c] = to_f32(frame.room_translation[c], "room_translation")?;
            for r in 0..3 {
                out.room_rotation[r][c] = to_f32(frame.room_rotation[r][c], "room_rotation")?;
            }
        }
        // A room scale that is not positive, or is another unit's, is
        // `plausible::check_device`'s to refuse, by what it is.
        Ok(out)
    }

    /// The calibration's training slips ([`crate::model::HomeSlips`]) in
    /// fixed point, each checked: a slip, on one active string, its time
    /// and size within the slip's formats.
    fn compile_home(
        calibration: &Calibration,
    ) -> Result<Option<CompiledHomeSlips>, BlobCompileError> {
        let Some(home) = &calibration.home else {
            return Ok(None);
        };
        if home.slips.len() > MAX_HOME_SLIPS {
            return Err(BlobCompileError::TooManyHomeSlips {
                found: home.slips.len(),
                max: MAX_HOME_SLIPS,
            });
        }
        let mut slips = heapless::Vec::new();
        for (index, term) in home.slips.iter().enumerate() {
            let problem = |problem| BlobCompileError::HomeSlip { index, problem };
            if !matches!(term.effect, crate::model::Effect::Slip { .. }) {
                return Err(problem(HomeSlipProblem::NotASlip));
            }
            if !calibration.frame.layout.is_active(usize::from(term.string)) {
                return Err(problem(HomeSlipProblem::String {
                    string: term.string,
                }));
            }
            let compiled = compile_effect(term, &calibration.frame, &calibration.strings)
                .map_err(|e| problem(HomeSlipProblem::Value(e)))?;
            let crate::string_law::CompiledEffect::Slip {
                string,
                at_ms,
                mm_q16,
            } = compiled
            else {
                return Err(problem(HomeSlipProblem::NotASlip));
            };
            slips
                .push(CompiledSlip {
                    string,
                    at_ms,
                    mm_q16,
                })
                .map_err(|_| BlobCompileError::TooManyHomeSlips {
                    found: home.slips.len(),
                    max: MAX_HOME_SLIPS,
                })?;
        }
        Ok(Some(CompiledHomeSlips {
            home_id: home.home_id,
            slips,
        }))
    }

    /// Compiles a calibration into a model blob (header + body).
    pub fn compile(
        calibration: &Calibration,
        model_id: u32,
        created_unix_s: u32,
    ) -> Result<Vec<u8>, BlobCompileError> {
        let frame = frame_f32(&calibration.frame)?;
        crate::plausible::check_device(&calibration.frame, &calibration.strings)
            .map_err(BlobCompileError::Implausible)?;
        let layout = calibration.frame.layout;
        if layout.count() < layout.dof() {
            return Err(BlobCompileError::Layout {
                field: "frame.layout",
                string: None,
            });
        }
        if let Some(term) = calibration
            .effects
            .iter()
            .find(|t| usize::from(t.string) < STRINGS && !layout.is_active(usize::from(t.string)))
        {
            return Err(BlobCompileError::Layout {
                field: "effects",
                string: Some(term.string),
            });
        }
        // Inactive channels get a zero law: never evaluated.
        let mut laws = [CompiledStringLaw::default(); STRINGS];
        for (i, law) in calibration.strings.iter().enumerate() {
            if layout.is_active(i) {
                laws[i] = compile_string_law(&calibration.frame, i, law)
                    .map_err(BlobCompileError::StringLaw)?;
            }
        }
        if calibration.effects.len() > MAX_EFFECTS {
            return Err(BlobCompileError::TooManyEffects {
                found: calibration.effects.len(),
                max: MAX_EFFECTS,
            });
        }
        let mut effects = heapless::Vec::new();
        for term in &calibration.effects {
            let e = compile_effect(term, &calibration.frame, &calibration.strings)
                .map_err(BlobCompileError::StringLaw)?;
            effects
                .push(e)
                .map_err(|_| BlobCompileError::TooManyEffects {
                    found: calibration.effects.len(),
                    max: MAX_EFFECTS,
                })?;
        }
        let scales = &calibration.length_scale_mm;
        let unmeasured = layout.indices().all(|i| scales[i] == 0.0);
        let measured = |s: f64| s.is_finite() && s > 0.0;
        if !unmeasured {
            if let Some(bad) = layout.indices().find(|&i| !measured(scales[i])) {
                return Err(BlobCompileError::LengthScale { string: bad as u8 });
            }
        }
        let residual_weight = crate::kinematics::residual_weights(layout, scales).map(|w| w as f32);
        let rule = calibration.kinematics;
        if !rule.is_valid() {
            return Err(BlobCompileError::KinematicsRule {
                exclusion_threshold_mm: rule.exclusion_threshold_mm,
                fault_threshold_mm: rule.fault_threshold_mm,
            });
        }
        let head = BlobHead {
            frame,
            laws,
            effects,
            residual_weight,
            exclusion_threshold_mm: rule.exclusion_threshold_mm as f32,
            fault_threshold_mm: rule.fault_threshold_mm as f32,
            home: compile_home(calibration)?,
        };
        let correction = calibration
            .correction
            .compile()
            .map_err(BlobCompileError::Correction)?;
        if let Some(tick) = crate::tick_cost::over_budget(
            &head,
            correction.kind,
            correction.hidden,
            correction.support_vectors,
        ) {
            return Err(BlobCompileError::TickOverBudget {
                instructions: tick,
                most: crate::tick_cost::TICK_BUDGET,
            });
        }
        let mut body = postcard::to_allocvec(&head).map_err(|_| BlobCompileError::Encode)?;
        body.resize(body.len() + correction_padding(HEADER_LEN + body.len()), 0);
        body.extend_from_slice(&correction.bytes);
        let header = ModelHeader {
            format_version: FORMAT_VERSION,
            kind: correction.kind,
            strings: layout.count() as u8,
            effects: head.effects.len() as u8,
            q_length: LENGTH_FRAC,
            q_position: correction.q_position,
            q_weight: correction.q_weight,
            hidden: correction.hidden,
            support_vectors: correction.support_vectors,
            body_len: 0,
            body_crc32: 0,
            model_id,
            created_unix_s,
        };
        let mut out = alloc::vec![0u8; HEADER_LEN + body.len()];
        let n = write_blob(&header, &body, &mut out).ok_or(BlobCompileError::Encode)?;
        out.truncate(n);
        Ok(out)
    }
}

/// Position in Q15.16 mm from f32 mm, saturating; NaN maps to 0 (the caller
/// flags non-finite positions as a fault before using the result).
pub fn position_q16(p: [f32; 3]) -> [i32; 3] {
    let scale = (1u32 << POSITION_FRAC) as f32;
    p.map(|v| {
        if v.is_nan() {
            0
        } else {
            // `as` saturates out-of-range floats.
            (v * scale).round_ties_even_compat() as i32
        }
    })
}

/// f32 mm from Q15.16 mm.
pub fn position_mm(p: [i32; 3]) -> [f32; 3] {
    let scale = (1u32 << POSITION_FRAC) as f32;
    p.map(|v| v as f32 / scale)
}

trait RoundCompat {
    fn round_ties_even_compat(self) -> Self;
}

impl RoundCompat for f32 {
    /// Round half away from zero with + - only, identical on every target
    /// (no libm call, no FPU rounding-mode dependence).
    fn round_ties_even_compat(self) -> f32 {
        if self >= 0.0 {
            libm::floorf(self + 0.5)
        } else {
            -libm::floorf(-self + 0.5)
        }
    }
}

#[cfg(all(test, feature = "alloc"))]
mod tests;
