//! Model blob container: a fixed 40-byte little-endian header followed by the
//! body. The protocol only reads the header (to store, check and describe a
//! blob); the body's layout belongs to `spidar-core::blob`.
//!
//! ```text
//! offset size field
//!  0     4    magic            b"SPDM"
//!  4     2    format_version   FORMAT_VERSION
//!  6     1    kind             CorrectionKind (0 none, 1 NN, 2 SVR)
//!  7     1    strings          number of active strings (3..=8; the frame's layout says which)
//!  8     1    effects          number of effect terms
//!  9     1    q_length         fractional bits of string lengths (mm)
//! 10     1    q_position       fractional bits of positions (mm)
//! 11     1    q_weight         fractional bits of correction weights
//! 12     2    hidden           NN hidden neurons (0 unless kind = NN)
//! 14     2    reserved         0
//! 16     4    support_vectors  SVR support vectors (0 unless kind = SVR)
//! 20     4    body_len         bytes after the header
//! 24     4    body_crc32       CRC-32 (ISO-HDLC) of the body
//! 28     4    model_id         host-chosen identifier (e.g. hash of the calibration)
//! 32     4    created_unix_s   creation time, seconds since 1970 (informative)
//! 36     4    header_crc32     CRC-32 of bytes 0..36
//! ```

use serde::{Deserialize, Serialize};

/// Magic bytes at the start of every model blob.
pub const MAGIC: [u8; 4] = *b"SPDM";
/// Blob format this crate reads and writes. Version 13 (any other is refused
/// with [`BlobError::UnsupportedVersion`]): an effect term may be a creep,
/// read against the time since home and each string's length
/// (`spidar-core::model::Effect::Creep`). Version 12: the string model may carry the
/// training session's slips and the id of their home capture, applied while
/// the device's home capture is that one
/// (`spidar-core::blob::CompiledHomeSlips`). Version 11: an effect term may be a guide
/// pulley, read against each string's elevation from its swivel axis
/// (`spidar-core::model::Effect::Guide`). Version 10: an effect term may be a latency,
/// read against each string's count rate
/// (`spidar-core::model::Effect::Latency`). Version 9: the string model carries the
/// forward kinematics' exclusion and fault thresholds the calibration chose
/// (`spidar-core::kinematics::KinematicsRule`). Version 8: the string model carries each
/// string's weight in forward kinematics, from its measured residual scale
/// (`spidar-core::kinematics::residual_weights`). Version 7: a frame-flex term, read against
/// the total tension of the strings (`spidar-core::model::Effect::FrameFlex`).
/// Version 6: an elasticity term carries the
/// lead and home parts of the strings' stretch
/// (`spidar-core::model::Effect::Stretch`). Version 5: each string law
/// carries its home sag factor and a sag term its home part (the string sagged when home
/// was captured, `spidar-core::model::Effect::Sag`). Version 4: each string law carries its
/// layer table (the spool's departure from the winding polynomial, knots in
/// counts, `spidar-core::model::LayerTable`). Version 3: the frame carries the string
/// layout (which of the 8 channels carry a string, planar or 3-D), so one
/// blob format serves devices with 3 to 8 strings. Version 2 introduced the
/// zero padding after the string model so that the correction starts at a
/// multiple of 4 bytes from the blob start (`spidar-core::blob`), which lets
/// the device read the SVR records as aligned words; version 1 had none.
pub const FORMAT_VERSION: u16 = 13;
/// Size of the header in bytes.
pub const HEADER_LEN: usize = 40;

/// Largest model blob the reference firmware (`firmware/`, Nucleo-H723ZG)
/// takes, bytes: the size of each of its two RAM model buffers, which
/// bounds its `HelloAck::max_blob_len` (a flash slot would hold 128 KiB).
/// The one place this number is written: the firmware sizes its buffers
/// with it, the host prints it.
pub const REFERENCE_FIRMWARE_BLOB_CAPACITY: usize = 96 * 1024;

/// CRC-32 used for blob bodies, headers and upload checks (ISO-HDLC, as zlib).
pub const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// Which position correction a blob carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[repr(u8)]
pub enum CorrectionKind {
    None = 0,
    Nn = 1,
    Svr = 2,
}

impl CorrectionKind {
    pub fn from_u8(v: u8) -> Option<Self> {
        match v {
            0 => Some(Self::None),
            1 => Some(Self::Nn),
            2 => Some(Self::Svr),
            _ => None,
        }
    }

    /// What the model corrects the position with, in words: what `spidar
    /// compile` and `spidar device info` print.
    pub fn describe(self) -> &'static str {
        match self {
            Self::None => "no position correction",
            Self::Nn => "NN position correction",
            Self::Svr => "SVR position correction",
        }
    }
}

/// Decoded blob header.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModelHeader {
    pub format_version: u16,
    pub kind: CorrectionKind,
    pub strings: u8,
    pub effects: u8,
    pub q_length: u8,
    pub q_position: u8,
    pub q_weight: u8,
    pub hidden: u16,
    pub support_vectors: u32,
    pub body_len: u32,
    pub body_crc32: u32,
    pub model_id: u32,
    pub created_unix_s: u32,
}

/// Why a blob was refused. Each variant names the field at fault: a
/// `&'static str` where the blob is checked, a [`Name`](crate::messages::Name)
/// in the device's answer on the wire
/// ([`BlobRejection`](crate::messages::BlobRejection)), one set of messages
/// for both.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum BlobError<F = &'static str> {
    /// Fewer bytes than a header, or than the header says the body has.
    Truncated {
        needed: u32,
        got: u32,
    },
    /// Bytes after the body.
    TrailingBytes {
        extra: u32,
    },
    BadMagic,
    /// A format this build does not understand (old device, new blob).
    UnsupportedVersion {
        found: u16,
        supported: u16,
    },
    UnknownKind {
        found: u8,
    },
    HeaderCrc {
        stored: u32,
        computed: u32,
    },
    BodyCrc {
        stored: u32,
        computed: u32,
    },
    /// A dimension or Q format that does not fit the evaluator.
    Dimension {
        field: F,
        found: u32,
        expected: u32,
    },
    /// The body does not decode as the header's kind.
    Body {
        field: F,
    },
    /// The frame's string layout (`frame.layout`) has fewer active strings
    /// than the end-effector's degrees of freedom (2 planar, 3 in space):
    /// no position can be found.
    TooFewStrings {
        strings: u8,
        dof: u8,
    },
    /// `field` refers to channel `string`, which the frame's layout marks
    /// as carrying no string (e.g. an effect term on a removed string).
    InactiveString {
        field: F,
        string: u8,
    },
    /// A model larger than the device runs within its control loop's tick:
    /// `field` is `svr.support_vectors` or `nn.hidden` (a correction beyond
    /// the most the device takes), or `tick` (the instructions the model's
    /// tick is estimated to take, `spidar-core::tick_cost`). It would
    /// overrun the 10 kHz loop.
    OverBudget {
        field: F,
        found: u32,
        most: u32,
    },
}

impl<F: core::fmt::Display> core::fmt::Display for BlobError<F> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Truncated { needed, got } => {
                write!(f, "model blob truncated: needs {needed} bytes, got {got}")
            }
            Self::TrailingBytes { extra } => {
                write!(f, "model blob has {extra} bytes after its body")
            }
            Self::BadMagic => write!(f, "not a model blob (magic is not \"SPDM\")"),
            Self::UnsupportedVersion { found, supported } => write!(
                f,
                "model blob format version {found} is not supported (the reader takes version {supported})"
            ),
            Self::UnknownKind { found } => {
                write!(f, "model blob has unknown correction kind {found}")
            }
            Self::HeaderCrc { stored, computed } => write!(
                f,
                "model blob header CRC mismatch: stored {stored:#010x}, computed {computed:#010x}"
            ),
            Self::BodyCrc { stored, computed } => write!(
                f,
                "model blob body CRC mismatch: stored {stored:#010x}, computed {computed:#010x}"
            ),
            Self::Dimension {
                field,
                found,
                expected,
            } => write!(
                f,
                "model blob field `{field}` is {found}, the evaluator needs {expected}"
            ),
            Self::Body { field } => {
                write!(f, "model blob body does not decode at field `{field}`")
            }
            Self::TooFewStrings { strings, dof } => write!(
                f,
                "model blob field `frame.layout` has {strings} active strings, a position with {dof} degrees of freedom needs at least {dof}"
            ),
            Self::InactiveString { field, string } => write!(
                f,
                "model blob field `{field}` refers to string {string}, which `frame.layout` marks inactive"
            ),
            Self::OverBudget { field, found, most } => write!(
                f,
                "model blob field `{field}` is {found}, over the {most} the device runs within its control loop's tick"
            ),
        }
    }
}

impl<F: core::fmt::Debug + core::fmt::Display> core::error::Error for BlobError<F> {}

fn le_u16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}

fn le_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

impl ModelHeader {
    /// Encodes the header; `body_len` and `body_crc32` must describe the body.
    pub fn to_bytes(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[0..4].copy_from_slice(&MAGIC);
        b[4..6].copy_from_slice(&self.format_version.to_le_bytes());
        b[6] = self.kind as u8;
        b[7] = self.strings;
        b[8] = self.effects;
        b[9] = self.q_length;
        b[10] = self.q_position;
        b[11] = self.q_weight;
        b[12..14].copy_from_slice(&self.hidden.to_le_bytes());
        b[16..20].copy_from_slice(&self.support_vectors.to_le_bytes());
        b[20..24].copy_from_slice(&self.body_len.to_le_bytes());
        b[24..28].copy_from_slice(&self.body_crc32.to_le_bytes());
        b[28..32].copy_from_slice(&self.model_id.to_le_bytes());
        b[32..36].copy_from_slice(&self.created_unix_s.to_le_bytes());
        let crc = CRC32.checksum(&b[0..36]);
        b[36..40].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Decodes and checks a header (magic, version, kind, header CRC). Does not
    /// look at the body.
    pub fn parse(bytes: &[u8]) -> Result<Self, BlobError> {
        if bytes.len() < HEADER_LEN {
            return Err(BlobError::Truncated {
                needed: HEADER_LEN as u32,
                got: bytes.len() as u32,
            });
        }
        let b = &bytes[..HEADER_LEN];
        if b[0..4] != MAGIC {
            return Err(BlobError::BadMagic);
        }
        let stored = le_u32(b, 36);
        let computed = CRC32.checksum(&b[0..36]);
        if stored != computed {
            return Err(BlobError::HeaderCrc { stored, computed });
        }
        let format_version = le_u16(b, 4);
        if format_version != FORMAT_VERSION {
            return Err(BlobError::UnsupportedVersion {
                found: format_version,
                supported: FORMAT_VERSION,
            });
        }
        let kind = CorrectionKind::from_u8(b[6]).ok_or(BlobError::UnknownKind { found: b[6] })?;
        Ok(ModelHeader {
            format_version,
            kind,
            strings: b[7],
            effects: b[8],
            q_length: b[9],
            q_position: b[10],
            q_weight: b[11],
            hidden: le_u16(b, 12),
            support_vectors: le_u32(b, 16),
            body_len: le_u32(b, 20),
            body_crc32: le_u32(b, 24),
            model_id: le_u32(b, 28),
            created_unix_s: le_u32(b, 32),
        })
    }

    /// Total blob length (header + body).
    pub fn blob_len(&self) -> usize {
        HEADER_LEN + self.body_len as usize
    }
}

/// Checks a whole blob (header, exact length, body CRC) and returns its header
/// and body.
pub fn split_blob(bytes: &[u8]) -> Result<(ModelHeader, &[u8]), BlobError> {
    let header = ModelHeader::parse(bytes)?;
    let total = header.blob_len();
    if bytes.len() < total {
        return Err(BlobError::Truncated {
            needed: total as u32,
            got: bytes.len() as u32,
        });
    }
    if bytes.len() > total {
        return Err(BlobError::TrailingBytes {
            extra: (bytes.len() - total) as u32,
        });
    }
    let body = &bytes[HEADER_LEN..total];
    let computed = CRC32.checksum(body);
    if computed != header.body_crc32 {
        return Err(BlobError::BodyCrc {
            stored: header.body_crc32,
            computed,
        });
    }
    Ok((header, body))
}

/// Writes header + body into `out`, filling in `body_len` and `body_crc32`.
/// Returns the number of bytes written, or `None` if `out` is too small.
pub fn write_blob(header: &ModelHeader, body: &[u8], out: &mut [u8]) -> Option<usize> {
    let total = HEADER_LEN + body.len();
    if out.len() < total || body.len() > u32::MAX as usize {
        return None;
    }
    let mut h = *header;
    h.format_version = FORMAT_VERSION;
    h.body_len = body.len() as u32;
    h.body_crc32 = CRC32.checksum(body);
    out[..HEADER_LEN].copy_from_slice(&h.to_bytes());
    out[HEADER_LEN..total].copy_from_slice(body);
    Some(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> ModelHeader {
        ModelHeader {
            format_version: FORMAT_VERSION,
            kind: CorrectionKind::Nn,
            strings: 8,
            effects: 2,
            q_length: 16,
            q_position: 16,
            q_weight: 24,
            hidden: 20,
            support_vectors: 0,
            body_len: 0,
            body_crc32: 0,
            model_id: 0xdead_beef,
            created_unix_s: 1_790_000_000,
        }
    }

    #[test]
    fn round_trip_and_every_truncation_is_an_error() {
        let body = [7u8; 100];
        let mut out = [0u8; 200];
        let n = write_blob(&header(), &body, &mut out).unwrap();
        let (h, b) = split_blob(&out[..n]).unwrap();
        assert_eq!(b, &body[..]);
        assert_eq!(h.hidden, 20);
        assert_eq!(h.body_len, 100);
        for cut in 0..n {
            assert!(split_blob(&out[..cut]).is_err(), "cut at {cut}");
        }
        assert_eq!(
            split_blob(&out[..n + 1]),
            Err(BlobError::TrailingBytes { extra: 1 })
        );
    }

    #[test]
    fn flipped_bits_are_caught() {
        let body = [1u8, 2, 3, 4, 5];
        let mut out = [0u8; 64];
        let n = write_blob(&header(), &body, &mut out).unwrap();
        for i in 0..n {
            let mut bad = out;
            bad[i] ^= 0x10;
            assert!(split_blob(&bad[..n]).is_err(), "flip at byte {i}");
        }
    }

    #[test]
    fn older_versions_are_refused_by_name() {
        for old in [1u16, 2, 3, 4, 5] {
            let mut bytes = header().to_bytes();
            bytes[4..6].copy_from_slice(&old.to_le_bytes());
            let crc = CRC32.checksum(&bytes[0..36]);
            bytes[36..40].copy_from_slice(&crc.to_le_bytes());
            assert_eq!(
                ModelHeader::parse(&bytes),
                Err(BlobError::UnsupportedVersion {
                    found: old,
                    supported: FORMAT_VERSION
                })
            );
        }
    }

    #[test]
    fn newer_version_is_refused_by_name() {
        let mut bytes = header().to_bytes();
        let newer = FORMAT_VERSION + 1;
        bytes[4..6].copy_from_slice(&newer.to_le_bytes());
        let crc = CRC32.checksum(&bytes[0..36]);
        bytes[36..40].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(
            ModelHeader::parse(&bytes),
            Err(BlobError::UnsupportedVersion {
                found: newer,
                supported: FORMAT_VERSION
            })
        );
    }
}
