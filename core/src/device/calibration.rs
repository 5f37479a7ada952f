//! The calibrations the device runs (the module's "Which calibration runs"
//! and "The model bytes and their borrow"): the RAM buffer a blob is copied
//! to ([`ModelBuffer`]), a committed blob parsed once into its owned part
//! and where its correction bytes start (`ActiveModel`, `parse_model`), and
//! the nominal calibration built from `SetNominalGeometry`
//! ([`nominal_calibration`]).

use spidar_protocol::blob::{BlobError, CorrectionKind, ModelHeader, FORMAT_VERSION};
use spidar_protocol::NominalGeometry;

use crate::blob::{split_body, BlobHead, CompiledCalibration, LENGTH_FRAC};
use crate::correction::{Correction, CorrectionSummary, ACTIVATION_FRAC, POSITION_FRAC};
use crate::model::{Frame, StringLaw, StringLayout};
use crate::model_store::StoredModel;
use crate::string_law::{compile_string_law, CompiledStringLaw, StringLawCompileError};
use crate::STRINGS;

/// A model RAM buffer (`model_ram`, `spare_ram` of [`Device::new`]) of `N`
/// bytes, 8-byte aligned: a blob copied to its start has its correction
/// 4-byte aligned (blob format version 2), so the SVR records are read as
/// aligned words (fewer loads per support vector). Any `&mut [u8]` works as
/// a model buffer; an unaligned one gives the same results, more slowly.
///
/// [`Device::new`]: super::Device::new
#[repr(C, align(8))]
pub struct ModelBuffer<const N: usize>(pub [u8; N]);

impl<const N: usize> ModelBuffer<N> {
    /// A zeroed buffer (usable in a `static` initializer).
    pub const fn new() -> Self {
        ModelBuffer([0; N])
    }

    /// The buffer's bytes, to hand to [`Device::new`].
    ///
    /// [`Device::new`]: super::Device::new
    pub fn bytes(&mut self) -> &mut [u8] {
        &mut self.0
    }
}

impl<const N: usize> Default for ModelBuffer<N> {
    fn default() -> Self {
        Self::new()
    }
}

/// The parsed active model: owned part plus where its correction bytes are.
#[derive(Clone, Debug)]
pub(super) struct ActiveModel {
    pub(super) stored: StoredModel,
    /// Header, frame, laws, effects; `correction` is always `None` here.
    pub(super) calibration: CompiledCalibration<'static>,
    /// The correction as checked at load; its view is rebuilt over
    /// `model_ram[correction_at..len]` every tick in O(1).
    pub(super) correction: CorrectionSummary,
    /// The blob's correction bytes are `model_ram[correction_at..len]`.
    pub(super) correction_at: usize,
    pub(super) len: usize,
}

/// A blob checked by `from_blob`, before it is active.
pub(super) struct ParsedModel {
    pub(super) calibration: CompiledCalibration<'static>,
    /// The correction as checked at load; the view is rebuilt from it over
    /// the RAM copy every tick in O(1).
    pub(super) correction: CorrectionSummary,
    pub(super) correction_at: usize,
    pub(super) len: usize,
}

/// Parses a whole blob once: every check of [`CompiledCalibration::from_blob`],
/// then keeps the owned part.
pub(super) fn parse_model(bytes: &[u8]) -> Result<ParsedModel, BlobError> {
    let c = CompiledCalibration::from_blob(bytes)?;
    // `from_blob` accepted it, so this re-split cannot fail; it only finds
    // where the correction bytes start (after the string model's padding).
    let (_, body) = spidar_protocol::blob::split_blob(bytes)?;
    let (_, rest) = split_body(body)?;
    Ok(ParsedModel {
        correction: c.correction.summary(),
        calibration: CompiledCalibration {
            header: c.header,
            head: c.head,
            correction: Correction::None,
        },
        correction_at: bytes.len() - rest.len(),
        len: bytes.len(),
    })
}

const IDENTITY: [[f32; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// The nominal calibration of a [`NominalGeometry`]: its string layout, anchors
/// and home, the device frame as room frame, a linear string law
/// `payout = r theta` per string (`winding_mm = [r, 0, 0, 0]`), no effects,
/// no correction. Channels without a string get a zero anchor and law
/// (never read). Built directly in its compiled form (no blob, no
/// allocation). `Err` names the field of the request that is out of range.
pub fn nominal_calibration(
    model: &NominalGeometry,
) -> Result<CompiledCalibration<'static>, &'static str> {
    let layout = StringLayout {
        active: model.active_strings,
        planar: model.planar,
    };
    if layout.count() < layout.dof() {
        return Err("active_strings");
    }
    let mut anchors = [[0.0f32; 3]; STRINGS];
    for i in layout.indices() {
        if !model.anchors_mm[i].iter().all(|x| x.is_finite()) {
            return Err("anchors_mm");
        }
        anchors[i] = model.anchors_mm[i];
    }
    if !model.home_mm.iter().all(|x| x.is_finite()) {
        return Err("home_mm");
    }
    let frame64 = Frame::<f64> {
        layout,
        anchors: anchors.map(|a| a.map(f64::from)),
        home: model.home_mm.map(f64::from),
        room_rotation: IDENTITY.map(|r| r.map(f64::from)),
        room_translation: [0.0; 3],
        room_scale: 1.0,
    };
    let mut laws = [CompiledStringLaw::default(); STRINGS];
    for (i, law) in laws.iter_mut().enumerate() {
        if !layout.is_active(i) {
            continue;
        }
        let r = model.pulley_radius_mm[i];
        if !(r.is_finite() && r > 0.0) {
            return Err("pulley_radius_mm");
        }
        let nominal = StringLaw::polynomial(model.counts_per_rev[i], [f64::from(r), 0.0, 0.0, 0.0]);
        *law = compile_string_law(&frame64, i, &nominal).map_err(|e| match e {
            StringLawCompileError::NotFinite { field, .. }
            | StringLawCompileError::DoesNotFit { field, .. }
            | StringLawCompileError::OutOfRange { field, .. } => match field {
                "counts_per_rev" => "counts_per_rev",
                "anchor" => "anchors_mm",
                "home" => "home_mm",
                _ => "pulley_radius_mm",
            },
            StringLawCompileError::StringOutOfRange { .. } => "anchors_mm",
        })?;
    }
    let header = ModelHeader {
        format_version: FORMAT_VERSION,
        kind: CorrectionKind::None,
        strings: layout.count() as u8,
        effects: 0,
        q_length: LENGTH_FRAC,
        q_position: POSITION_FRAC,
        q_weight: ACTIVATION_FRAC,
        hidden: 0,
        support_vectors: 0,
        body_len: 0,
        body_crc32: 0,
        model_id: 0,
        created_unix_s: 0,
    };
    let nominal_rule = crate::kinematics::KinematicsRule::default();
    Ok(CompiledCalibration {
        header,
        head: BlobHead {
            frame: Frame {
                layout,
                anchors,
                home: model.home_mm,
                room_rotation: IDENTITY,
                room_translation: [0.0; 3],
                room_scale: 1.0,
            },
            laws,
            effects: heapless::Vec::new(),
            // Nothing measured yet: every string weighs alike, and the
            // thresholds are the device's defaults.
            residual_weight: [1.0; STRINGS],
            exclusion_threshold_mm: nominal_rule.exclusion_threshold_mm as f32,
            fault_threshold_mm: nominal_rule.fault_threshold_mm as f32,
            home: None,
        },
        correction: Correction::None,
    })
}
