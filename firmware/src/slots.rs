//! Model-slot bookkeeping: pure logic, no hardware.
//!
//! Internal flash holds two model slots (sectors 6 and 7, 128 KiB each, see
//! `memory.x`). Each slot is laid out as
//!
//! ```text
//! offset        size   content
//! 0             32     commit record (one H7 flash word), written LAST
//! 32            len    the model blob (protocol::blob header + body)
//! ```
//!
//! An upload goes into the *staging* slot (the one that is not active): erase,
//! write the blob, read it back and check its CRC-32 and blob header, then
//! write the commit record with a sequence number one above the active one.
//! The active model is never touched, so an upload interrupted at any point
//! (power loss, reset, cable pulled) leaves the active model in place: at boot
//! the slot whose record is valid, whose blob matches the record's CRC and
//! whose sequence number is newest wins.
//!
//! Everything here is pure (no flash, no embassy) so it can be tested on the
//! host (`rustc --test src/slots.rs`, see docs/hardware.md) and moved into
//! `spidar-core` for the virtual device. The CRC-32 is passed in (the firmware
//! uses `spidar_protocol::blob::CRC32`), so this file has no dependencies.

/// Size of one flash sector = one slot.
pub const SLOT_SIZE: u32 = 128 * 1024;
/// Flash programming unit of the STM32H7 (256-bit flash word).
pub const FLASH_WORD: usize = 32;
/// Size of the commit record at the start of a slot.
pub const RECORD_LEN: usize = FLASH_WORD;
/// Offset of the blob inside a slot.
pub const BLOB_OFFSET: u32 = RECORD_LEN as u32;
/// Largest blob a slot holds.
pub const MAX_BLOB_LEN: u32 = SLOT_SIZE - BLOB_OFFSET;
/// Magic of a commit record.
pub const RECORD_MAGIC: [u8; 4] = *b"SPDC";
/// Layout version of the commit record.
pub const RECORD_VERSION: u16 = 1;

/// A CRC-32 function (ISO-HDLC, as `spidar_protocol::blob::CRC32`).
pub type Crc32Fn = fn(&[u8]) -> u32;

/// One of the two model slots.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(all(not(test), target_os = "none"), derive(defmt::Format))]
pub enum Slot {
    A,
    B,
}

impl Slot {
    pub const fn other(self) -> Slot {
        match self {
            Slot::A => Slot::B,
            Slot::B => Slot::A,
        }
    }
    pub const fn index(self) -> u8 {
        match self {
            Slot::A => 0,
            Slot::B => 1,
        }
    }
}

/// The commit record: says "the blob in this slot is complete and checked".
///
/// ```text
/// offset size field
///  0     4    magic        b"SPDC"
///  4     2    version      RECORD_VERSION
///  6     2    reserved     0xFFFF
///  8     4    sequence     newer commit = larger (wrapping) sequence
/// 12     4    blob_len     bytes of the blob after the record
/// 16     4    blob_crc32   CRC-32 of the whole blob (header + body)
/// 20     4    model_id     the blob header's model_id (informative)
/// 24     4    reserved     0xFFFF_FFFF
/// 28     4    record_crc32 CRC-32 of bytes 0..28
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(all(not(test), target_os = "none"), derive(defmt::Format))]
pub struct CommitRecord {
    pub sequence: u32,
    pub blob_len: u32,
    pub blob_crc32: u32,
    pub model_id: u32,
}

fn le_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

impl CommitRecord {
    pub fn encode(&self, crc: Crc32Fn) -> [u8; RECORD_LEN] {
        let mut b = [0xFFu8; RECORD_LEN];
        b[0..4].copy_from_slice(&RECORD_MAGIC);
        b[4..6].copy_from_slice(&RECORD_VERSION.to_le_bytes());
        b[8..12].copy_from_slice(&self.sequence.to_le_bytes());
        b[12..16].copy_from_slice(&self.blob_len.to_le_bytes());
        b[16..20].copy_from_slice(&self.blob_crc32.to_le_bytes());
        b[20..24].copy_from_slice(&self.model_id.to_le_bytes());
        let c = crc(&b[0..28]);
        b[28..32].copy_from_slice(&c.to_le_bytes());
        b
    }

    /// Decodes a record; `None` for erased flash (all 0xFF), a torn write, a
    /// foreign layout or an impossible length.
    pub fn decode(b: &[u8; RECORD_LEN], crc: Crc32Fn) -> Option<CommitRecord> {
        if b[0..4] != RECORD_MAGIC || b[4..6] != RECORD_VERSION.to_le_bytes() {
            return None;
        }
        if le_u32(b, 28) != crc(&b[0..28]) {
            return None;
        }
        let r = CommitRecord {
            sequence: le_u32(b, 8),
            blob_len: le_u32(b, 12),
            blob_crc32: le_u32(b, 16),
            model_id: le_u32(b, 20),
        };
        (r.blob_len > 0 && r.blob_len <= MAX_BLOB_LEN).then_some(r)
    }
}

/// `a` was committed after `b` (sequence numbers compare with wrap-around).
pub fn is_newer(a: u32, b: u32) -> bool {
    (a.wrapping_sub(b) as i32) > 0
}

/// What the boot scan found in one slot: its record if the record decoded
/// *and* the blob's CRC matched it (the caller checks the CRC).
pub type Checked = Option<CommitRecord>;

/// Picks the active slot from the two checked records: the newest valid one.
/// Equal sequences (never written by this firmware) resolve to slot A.
pub fn select_active(a: Checked, b: Checked) -> Option<(Slot, CommitRecord)> {
    match (a, b) {
        (Some(ra), Some(rb)) => {
            if is_newer(rb.sequence, ra.sequence) {
                Some((Slot::B, rb))
            } else {
                Some((Slot::A, ra))
            }
        }
        (Some(ra), None) => Some((Slot::A, ra)),
        (None, Some(rb)) => Some((Slot::B, rb)),
        (None, None) => None,
    }
}

/// The slot an upload goes to: never the active one.
pub fn staging_slot(active: Option<Slot>) -> Slot {
    match active {
        Some(s) => s.other(),
        None => Slot::A,
    }
}

/// Sequence number of the next commit.
pub fn next_sequence(active: Option<&CommitRecord>) -> u32 {
    match active {
        Some(r) => r.sequence.wrapping_add(1),
        None => 1,
    }
}

/// Why an upload step was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(all(not(test), target_os = "none"), derive(defmt::Format))]
pub enum UploadError {
    /// Zero length or more than [`MAX_BLOB_LEN`].
    BadLength { len: u32, max: u32 },
    /// No upload in progress.
    NotStarted,
    /// A chunk that neither continues the upload nor repeats an old chunk.
    OutOfOrder { expected: u32, got: u32 },
    /// A chunk running past `total_len`.
    PastEnd { total_len: u32 },
    /// Commit before every byte arrived.
    Incomplete { received: u32, total_len: u32 },
    /// The CRC given at commit differs from the one given at begin.
    CrcMismatch { begin: u32, commit: u32 },
}

/// Progress of one upload into the staging slot.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Upload {
    pub slot: Slot,
    pub total_len: u32,
    pub crc32: u32,
    pub model_id: u32,
    /// Bytes received so far = offset of the next chunk.
    pub received: u32,
}

/// What to do with a chunk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ChunkAction {
    /// Append `data[skip..]` at `received` (a chunk overlapping what was
    /// received has its old part skipped).
    Append { skip: usize },
    /// A resend of bytes already stored: acknowledge without effect.
    Duplicate,
}

impl Upload {
    /// Begins an upload, or resumes the one in progress if it is the same
    /// blob (same length, CRC and model id).
    pub fn begin(
        current: Option<Upload>,
        staging: Slot,
        total_len: u32,
        crc32: u32,
        model_id: u32,
    ) -> Result<(Upload, bool), UploadError> {
        if total_len == 0 || total_len > MAX_BLOB_LEN {
            return Err(UploadError::BadLength {
                len: total_len,
                max: MAX_BLOB_LEN,
            });
        }
        if let Some(u) = current {
            if u.slot == staging
                && u.total_len == total_len
                && u.crc32 == crc32
                && u.model_id == model_id
            {
                return Ok((u, true));
            }
        }
        Ok((
            Upload {
                slot: staging,
                total_len,
                crc32,
                model_id,
                received: 0,
            },
            false,
        ))
    }

    /// Classifies a chunk of `len` bytes at `offset`.
    pub fn chunk(&self, offset: u32, len: usize) -> Result<ChunkAction, UploadError> {
        let len = len as u32;
        let end = offset.checked_add(len).ok_or(UploadError::PastEnd {
            total_len: self.total_len,
        })?;
        if end > self.total_len {
            return Err(UploadError::PastEnd {
                total_len: self.total_len,
            });
        }
        if end <= self.received {
            return Ok(ChunkAction::Duplicate);
        }
        if offset > self.received {
            return Err(UploadError::OutOfOrder {
                expected: self.received,
                got: offset,
            });
        }
        Ok(ChunkAction::Append {
            skip: (self.received - offset) as usize,
        })
    }

    /// Checks that the upload may be committed.
    pub fn ready_to_commit(&self, crc32: u32) -> Result<(), UploadError> {
        if crc32 != self.crc32 {
            return Err(UploadError::CrcMismatch {
                begin: self.crc32,
                commit: crc32,
            });
        }
        if self.received != self.total_len {
            return Err(UploadError::Incomplete {
                received: self.received,
                total_len: self.total_len,
            });
        }
        Ok(())
    }
}

/// Splits `pending` bytes (not yet a whole flash word) plus `data` into whole
/// flash words to program; returns how many bytes of `data` complete the
/// pending word. Helper for the word-buffered writer.
pub fn fill_word(pending_len: usize, data_len: usize) -> usize {
    (FLASH_WORD - pending_len).min(data_len)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn crc32(data: &[u8]) -> u32 {
        let mut c = 0xFFFF_FFFFu32;
        for &b in data {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    (c >> 1) ^ 0xEDB8_8320
                } else {
                    c >> 1
                };
            }
        }
        !c
    }

    fn rec(seq: u32) -> CommitRecord {
        CommitRecord {
            sequence: seq,
            blob_len: 1000,
            blob_crc32: 0x1234_5678,
            model_id: 7,
        }
    }

    #[test]
    fn crc_is_iso_hdlc() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn record_round_trip_and_rejections() {
        let r = rec(42);
        let b = r.encode(crc32);
        assert_eq!(CommitRecord::decode(&b, crc32), Some(r));
        assert_eq!(CommitRecord::decode(&[0xFF; RECORD_LEN], crc32), None);
        assert_eq!(CommitRecord::decode(&[0x00; RECORD_LEN], crc32), None);
        for i in 0..RECORD_LEN {
            let mut bad = b;
            bad[i] ^= 0x01;
            // Reserved bytes are not covered by meaning but are by the CRC,
            // except the CRC bytes themselves, where the CRC no longer matches.
            assert_eq!(CommitRecord::decode(&bad, crc32), None, "flip at {i}");
        }
        // A torn write: the first half programmed, the rest still erased.
        let mut torn = [0xFFu8; RECORD_LEN];
        torn[..16].copy_from_slice(&b[..16]);
        assert_eq!(CommitRecord::decode(&torn, crc32), None);
        let mut too_long = rec(1);
        too_long.blob_len = MAX_BLOB_LEN + 1;
        assert_eq!(CommitRecord::decode(&too_long.encode(crc32), crc32), None);
    }

    #[test]
    fn newest_valid_slot_wins() {
        assert_eq!(select_active(None, None), None);
        assert_eq!(select_active(Some(rec(3)), None), Some((Slot::A, rec(3))));
        assert_eq!(select_active(None, Some(rec(3))), Some((Slot::B, rec(3))));
        assert_eq!(
            select_active(Some(rec(3)), Some(rec(4))),
            Some((Slot::B, rec(4)))
        );
        assert_eq!(
            select_active(Some(rec(5)), Some(rec(4))),
            Some((Slot::A, rec(5)))
        );
        // Wrap-around: u32::MAX then 0.
        assert_eq!(
            select_active(Some(rec(u32::MAX)), Some(rec(0))),
            Some((Slot::B, rec(0)))
        );
        assert_eq!(
            select_active(Some(rec(9)), Some(rec(9))),
            Some((Slot::A, rec(9)))
        );
    }

    /// Walks an upload through every point where it could be interrupted and
    /// checks that the boot scan still finds the old model until the commit
    /// record is written, and the new one after.
    #[test]
    fn interrupted_upload_keeps_the_active_model() {
        let old = rec(10);
        // Boot state: A holds the active model, B an older one.
        let active = select_active(Some(old), Some(rec(9))).unwrap();
        assert_eq!(active, (Slot::A, old));
        let staging = staging_slot(Some(active.0));
        assert_eq!(staging, Slot::B);
        // Interrupted after erase / during blob write / during verification:
        // slot B has no valid record (erased, or a record that fails its CRC).
        for b_state in [None, CommitRecord::decode(&[0xFF; 32], crc32)] {
            assert_eq!(select_active(Some(old), b_state), Some((Slot::A, old)));
        }
        // Commit record written: the new model wins.
        let new = CommitRecord {
            sequence: next_sequence(Some(&old)),
            ..rec(0)
        };
        assert_eq!(select_active(Some(old), Some(new)), Some((Slot::B, new)));
        // Next upload goes to A, the old model's slot, never to B.
        assert_eq!(staging_slot(Some(Slot::B)), Slot::A);
        assert_eq!(next_sequence(None), 1);
    }

    #[test]
    fn upload_chunks() {
        let (u, resumed) = Upload::begin(None, Slot::B, 100, 0xAB, 1).unwrap();
        assert!(!resumed);
        assert_eq!(u.chunk(0, 40), Ok(ChunkAction::Append { skip: 0 }));
        let mut u = u;
        u.received = 40;
        assert_eq!(u.chunk(0, 40), Ok(ChunkAction::Duplicate));
        assert_eq!(u.chunk(20, 40), Ok(ChunkAction::Append { skip: 20 }));
        assert_eq!(
            u.chunk(41, 10),
            Err(UploadError::OutOfOrder {
                expected: 40,
                got: 41
            })
        );
        assert_eq!(
            u.chunk(90, 20),
            Err(UploadError::PastEnd { total_len: 100 })
        );
        assert_eq!(
            u.chunk(u32::MAX, 20),
            Err(UploadError::PastEnd { total_len: 100 })
        );
        assert_eq!(
            u.ready_to_commit(0xAB),
            Err(UploadError::Incomplete {
                received: 40,
                total_len: 100
            })
        );
        u.received = 100;
        assert_eq!(u.ready_to_commit(0xAB), Ok(()));
        assert_eq!(
            u.ready_to_commit(0xAC),
            Err(UploadError::CrcMismatch {
                begin: 0xAB,
                commit: 0xAC
            })
        );
        // Same blob again resumes; another blob starts over.
        assert_eq!(Upload::begin(Some(u), Slot::B, 100, 0xAB, 1), Ok((u, true)));
        assert_eq!(
            Upload::begin(Some(u), Slot::B, 100, 0xAC, 1)
                .unwrap()
                .0
                .received,
            0
        );
        assert!(Upload::begin(None, Slot::A, 0, 0, 0).is_err());
        assert!(Upload::begin(None, Slot::A, MAX_BLOB_LEN + 1, 0, 0).is_err());
        assert!(Upload::begin(None, Slot::A, MAX_BLOB_LEN, 0, 0).is_ok());
    }

    #[test]
    fn word_filling() {
        assert_eq!(fill_word(0, 100), 32);
        assert_eq!(fill_word(30, 100), 2);
        assert_eq!(fill_word(5, 3), 3);
    }
}
