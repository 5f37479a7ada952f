//! Two-slot model storage: which stored model is active, and uploads that
//! never put it at risk. Pure logic over a small flash trait, [`ModelFlash`];
//! the firmware implements it on the STM32H7's internal flash, the host and
//! the virtual device on [`RamFlash`], which can also cut the power at any
//! write.
//!
//! # Layout of a slot
//!
//! ```text
//! offset        size   content
//! 0             32     commit record (one flash word), written LAST
//! 32            len    the model blob (protocol::blob header + body)
//! ```
//!
//! The commit record says "the blob in this slot is complete and checked":
//!
//! ```text
//! offset size field
//!  0     4    magic        b"SPDC"
//!  4     2    version      RECORD_VERSION
//!  6     2    reserved     0xFFFF
//!  8     4    sequence     newer commit = larger (wrapping) sequence
//! 12     4    blob_len     bytes of the blob after the record
//! 16     4    blob_crc32   CRC-32 (protocol::blob::CRC32) of the whole blob
//! 20     4    model_id     the blob header's model_id
//! 24     4    reserved     0xFFFF_FFFF
//! 28     4    record_crc32 CRC-32 of bytes 0..28
//! ```
//!
//! # Rules
//!
//! - **Boot** ([`ModelStore::open`]): a slot counts if its record decodes and
//!   its blob matches the record's length and CRC; of the slots that count,
//!   the newest sequence is active.
//! - **Upload** ([`ModelStore::begin`], [`ModelStore::chunk`],
//!   [`ModelStore::commit`]): the blob goes into the *staging* slot, never the
//!   active one: erase, program the chunks word by word, then at commit read
//!   the whole blob back, check its CRC and let the caller validate it
//!   (`CompiledCalibration::from_blob`), and only then program the record,
//!   with the active sequence + 1, and read it back through the boot checks.
//!   Until the record's last byte is programmed the staging slot has no valid
//!   record, so an upload cut at any point (a chunk boundary, mid-chunk,
//!   mid-word, during the erase or the record) leaves the previous model
//!   active and intact at the next boot.
//! - **Clear** ([`ModelStore::clear`]): erases the staging slot first, then
//!   the active one, so a cut clear never brings an older model back.
//!
//! # Flash words
//!
//! The store programs only whole [`FLASH_WORD`]s (32 bytes, the STM32H7's
//! flash word), at offsets that are multiples of 32, and each word at most
//! once between erases (the H7 refuses to reprogram a word: its ECC covers
//! the whole word). Bytes of a chunk that do not complete a word wait in RAM
//! until the next chunk (or the commit) completes it. Any flash whose
//! programming unit divides 32 bytes fits.

use spidar_protocol::blob::CRC32;

/// Programming unit of the store: every write is whole words at word-aligned
/// offsets (the STM32H7's 256-bit flash word).
pub const FLASH_WORD: usize = 32;
/// Length of the commit record at the start of a slot (one flash word).
pub const RECORD_LEN: usize = FLASH_WORD;
/// Offset of the blob inside a slot.
pub const BLOB_OFFSET: usize = RECORD_LEN;
/// Magic of a commit record.
pub const RECORD_MAGIC: [u8; 4] = *b"SPDC";
/// Layout version of the commit record.
pub const RECORD_VERSION: u16 = 1;

/// Bytes read at a time when checking a stored blob's CRC.
const READ_CHUNK: usize = 64;

/// One of the two model slots.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Slot {
    A,
    B,
}

impl Slot {
    /// The other slot.
    pub const fn other(self) -> Slot {
        match self {
            Slot::A => Slot::B,
            Slot::B => Slot::A,
        }
    }

    /// 0 for A, 1 for B (as in `protocol::ModelInfo::slot`).
    pub const fn index(self) -> u8 {
        match self {
            Slot::A => 0,
            Slot::B => 1,
        }
    }
}

/// Why a flash operation failed.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlashError {
    /// `offset..offset + len` does not lie inside the slot.
    OutOfBounds { offset: u32, len: u32 },
    /// A write not made of whole [`FLASH_WORD`]s at a word-aligned offset.
    Misaligned { offset: u32, len: u32 },
    /// A write to a word that is not erased (the H7 cannot reprogram a word).
    NotErased { offset: u32 },
    /// The flash controller reported an error: its status bits.
    Hardware { code: u32 },
    /// The power went (simulated by [`RamFlash`]); nothing works until
    /// [`RamFlash::power_cycle`].
    PowerLost,
}

impl FlashError {
    /// A number for `protocol::DeviceError::Storage { code }`: the hardware
    /// status bits, or `0x8000_0000 | kind` for the other kinds.
    pub fn code(&self) -> u32 {
        match *self {
            FlashError::Hardware { code } => code,
            FlashError::OutOfBounds { .. } => 0x8000_0001,
            FlashError::Misaligned { .. } => 0x8000_0002,
            FlashError::NotErased { .. } => 0x8000_0003,
            FlashError::PowerLost => 0x8000_0004,
        }
    }
}

/// The flash holding the two model slots.
///
/// Contract the store relies on:
/// - `write` is only called with `offset` and `data.len()` multiples of
///   [`FLASH_WORD`], on words erased since their last write;
/// - after `erase(slot)` every byte of the slot reads `0xFF`;
/// - `read` returns what was programmed (a word whose programming was cut by
///   a power loss may read as anything; see `docs/hardware.md` for the H7's
///   ECC caveat).
pub trait ModelFlash {
    /// Bytes per slot (a multiple of [`FLASH_WORD`], more than [`RECORD_LEN`]).
    const SLOT_LEN: usize;

    /// Reads `buf.len()` bytes of `slot` at `offset`.
    fn read(&mut self, slot: Slot, offset: usize, buf: &mut [u8]) -> Result<(), FlashError>;

    /// Erases the whole slot to `0xFF`.
    fn erase(&mut self, slot: Slot) -> Result<(), FlashError>;

    /// Programs whole flash words of `slot` at `offset` (see the contract).
    fn write(&mut self, slot: Slot, offset: usize, data: &[u8]) -> Result<(), FlashError>;
}

/// The commit record of a slot (layout in the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CommitRecord {
    pub sequence: u32,
    pub blob_len: u32,
    pub blob_crc32: u32,
    pub model_id: u32,
}

fn le_u32(b: &[u8; RECORD_LEN], at: usize) -> u32 {
    let mut w = [0u8; 4];
    for (i, x) in w.iter_mut().enumerate() {
        *x = b.get(at + i).copied().unwrap_or(0xFF);
    }
    u32::from_le_bytes(w)
}

fn crc32(data: &[u8]) -> u32 {
    CRC32.checksum(data)
}

impl CommitRecord {
    /// The record's bytes.
    pub fn encode(&self) -> [u8; RECORD_LEN] {
        let mut b = [0xFFu8; RECORD_LEN];
        b[0..4].copy_from_slice(&RECORD_MAGIC);
        b[4..6].copy_from_slice(&RECORD_VERSION.to_le_bytes());
        b[8..12].copy_from_slice(&self.sequence.to_le_bytes());
        b[12..16].copy_from_slice(&self.blob_len.to_le_bytes());
        b[16..20].copy_from_slice(&self.blob_crc32.to_le_bytes());
        b[20..24].copy_from_slice(&self.model_id.to_le_bytes());
        let c = crc32(&b[0..28]);
        b[28..32].copy_from_slice(&c.to_le_bytes());
        b
    }

    /// Decodes a record; `None` for erased flash (all `0xFF`), a torn write,
    /// a foreign layout, or a length that is 0 or above `max_blob_len`.
    pub fn decode(b: &[u8; RECORD_LEN], max_blob_len: u32) -> Option<CommitRecord> {
        if b[0..4] != RECORD_MAGIC || b[4..6] != RECORD_VERSION.to_le_bytes() {
            return None;
        }
        if le_u32(b, 28) != crc32(&b[0..28]) {
            return None;
        }
        let r = CommitRecord {
            sequence: le_u32(b, 8),
            blob_len: le_u32(b, 12),
            blob_crc32: le_u32(b, 16),
            model_id: le_u32(b, 20),
        };
        (r.blob_len > 0 && r.blob_len <= max_blob_len).then_some(r)
    }
}

/// `a` was committed after `b` (sequence numbers compare with wrap-around).
pub fn is_newer(a: u32, b: u32) -> bool {
    (a.wrapping_sub(b) as i32) > 0
}

/// Picks the active slot from the two slots' checked records (record decoded
/// and blob CRC matched): the newest. Equal sequences (never written by the
/// store) resolve to slot A.
pub fn select_active(
    a: Option<CommitRecord>,
    b: Option<CommitRecord>,
) -> Option<(Slot, CommitRecord)> {
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

/// The active model as stored: its slot and commit record.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StoredModel {
    pub slot: Slot,
    pub record: CommitRecord,
}

/// Progress of one upload into the staging slot.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Upload {
    pub slot: Slot,
    pub total_len: u32,
    pub crc32: u32,
    pub model_id: u32,
    /// Bytes received so far = offset of the next chunk. The last
    /// `received % FLASH_WORD` of them wait in RAM for their word to fill.
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
    /// Classifies a chunk of `len` bytes at `offset`.
    pub fn classify(&self, offset: u32, len: usize) -> Result<ChunkAction, StoreError> {
        let len = u32::try_from(len).unwrap_or(u32::MAX);
        let end = offset.saturating_add(len);
        if end > self.total_len {
            return Err(StoreError::PastEnd {
                end,
                total_len: self.total_len,
            });
        }
        if end <= self.received {
            return Ok(ChunkAction::Duplicate);
        }
        if offset > self.received {
            return Err(StoreError::OutOfOrder {
                expected_offset: self.received,
            });
        }
        Ok(ChunkAction::Append {
            skip: (self.received - offset) as usize,
        })
    }
}

/// Why a store operation was refused. On every error the active model is
/// unchanged.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StoreError {
    /// The flash failed; an upload in progress is dropped (begin again).
    Flash(FlashError),
    /// `UploadBegin` with `total_len` 0.
    EmptyBlob,
    /// The blob does not fit a slot (or the caller's buffer).
    TooLarge { total_len: u32, capacity: u32 },
    /// `chunk`/`commit` without `begin`.
    NoUpload,
    /// A chunk that neither continues the upload nor repeats an old chunk.
    OutOfOrder { expected_offset: u32 },
    /// A chunk ending past `total_len`.
    PastEnd { end: u32, total_len: u32 },
    /// Commit before every byte arrived.
    Incomplete { next_offset: u32, total_len: u32 },
    /// The CRC at commit is not the one announced at begin (`computed` is
    /// the commit's), or the blob read back from flash does not match the
    /// announced CRC (`computed` is the read-back's).
    CrcMismatch { expected: u32, computed: u32 },
    /// The commit record did not read back through the boot checks.
    RecordVerify,
}

impl core::fmt::Display for FlashError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Self::OutOfBounds { offset, len } => {
                write!(
                    f,
                    "flash: {len} bytes at {offset:#x} do not lie inside the slot"
                )
            }
            Self::Misaligned { offset, len } => write!(
                f,
                "flash: a write of {len} bytes at {offset:#x} is not made of whole flash words"
            ),
            Self::NotErased { offset } => write!(f, "flash: the word at {offset:#x} is not erased"),
            Self::Hardware { code } => write!(f, "flash controller error, status {code:#010x}"),
            Self::PowerLost => write!(f, "flash: the power went"),
        }
    }
}

impl core::error::Error for FlashError {}

impl core::fmt::Display for StoreError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Self::Flash(e) => write!(f, "model store: {e}"),
            Self::EmptyBlob => write!(f, "model store: an upload of 0 bytes"),
            Self::TooLarge {
                total_len,
                capacity,
            } => write!(
                f,
                "model store: a {total_len}-byte blob does not fit the {capacity}-byte slot"
            ),
            Self::NoUpload => write!(f, "model store: no upload in progress"),
            Self::OutOfOrder { expected_offset } => write!(
                f,
                "model store: a chunk out of order (the upload continues at {expected_offset})"
            ),
            Self::PastEnd { end, total_len } => write!(
                f,
                "model store: a chunk ending at {end}, past the blob's {total_len} bytes"
            ),
            Self::Incomplete {
                next_offset,
                total_len,
            } => write!(
                f,
                "model store: commit with {next_offset} of {total_len} bytes received"
            ),
            Self::CrcMismatch { expected, computed } => write!(
                f,
                "model store: CRC {computed:#010x} where {expected:#010x} was announced"
            ),
            Self::RecordVerify => write!(f, "model store: the commit record did not read back"),
        }
    }
}

impl core::error::Error for StoreError {}

impl From<FlashError> for StoreError {
    fn from(e: FlashError) -> Self {
        StoreError::Flash(e)
    }
}

/// Why a commit failed: the store's checks, or the caller's validation of
/// the staged blob.
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CommitError<E> {
    Store(StoreError),
    /// The caller's validation refused the blob; the upload is dropped.
    Rejected(E),
}

impl<E: core::fmt::Display> core::fmt::Display for CommitError<E> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Store(e) => write!(f, "{e}"),
            Self::Rejected(e) => write!(f, "the blob was refused: {e}"),
        }
    }
}

impl<E: core::fmt::Debug + core::fmt::Display> core::error::Error for CommitError<E> {}

impl<E> From<StoreError> for CommitError<E> {
    fn from(e: StoreError) -> Self {
        CommitError::Store(e)
    }
}

/// The two-slot model store over a [`ModelFlash`].
pub struct ModelStore<F: ModelFlash> {
    flash: F,
    active: Option<StoredModel>,
    upload: Option<Upload>,
    /// Bytes of the upload not yet making a whole flash word.
    pending: [u8; FLASH_WORD],
}

impl<F: ModelFlash> ModelStore<F> {
    /// Compile-time check of the flash geometry.
    const GEOMETRY_OK: () = assert!(
        F::SLOT_LEN > RECORD_LEN
            && F::SLOT_LEN % FLASH_WORD == 0
            && F::SLOT_LEN <= u32::MAX as usize,
        "ModelFlash::SLOT_LEN must be a multiple of FLASH_WORD larger than RECORD_LEN"
    );

    /// Largest blob a slot holds, bytes.
    pub const MAX_BLOB_LEN: u32 = (F::SLOT_LEN - BLOB_OFFSET) as u32;

    /// Scans both slots (boot) and picks the active model. Flash errors make
    /// a slot not count.
    pub fn open(flash: F) -> Self {
        #[allow(clippy::let_unit_value)]
        let () = Self::GEOMETRY_OK;
        let mut s = ModelStore {
            flash,
            active: None,
            upload: None,
            pending: [0xFF; FLASH_WORD],
        };
        let a = s.check_slot(Slot::A);
        let b = s.check_slot(Slot::B);
        s.active = select_active(a, b).map(|(slot, record)| StoredModel { slot, record });
        s
    }

    /// The flash, e.g. to power-cycle a [`RamFlash`] (`ModelStore::open`
    /// again on it) in tests.
    pub fn into_flash(self) -> F {
        self.flash
    }

    /// The flash, borrowed.
    pub fn flash_mut(&mut self) -> &mut F {
        &mut self.flash
    }

    /// The active model.
    pub fn active(&self) -> Option<StoredModel> {
        self.active
    }

    /// The upload in progress.
    pub fn upload(&self) -> Option<Upload> {
        self.upload
    }

    /// The slot's record if it decodes and its blob matches it.
    fn check_slot(&mut self, slot: Slot) -> Option<CommitRecord> {
        let mut rec = [0u8; RECORD_LEN];
        self.flash.read(slot, 0, &mut rec).ok()?;
        let r = CommitRecord::decode(&rec, Self::MAX_BLOB_LEN)?;
        let crc = self.stored_crc(slot, r.blob_len).ok()?;
        (crc == r.blob_crc32).then_some(r)
    }

    /// CRC-32 of the first `len` blob bytes of `slot`, read in small pieces.
    fn stored_crc(&mut self, slot: Slot, len: u32) -> Result<u32, FlashError> {
        let mut digest = CRC32.digest();
        let mut buf = [0u8; READ_CHUNK];
        let mut at = 0usize;
        let len = len as usize;
        while at < len {
            let n = (len - at).min(READ_CHUNK);
            let piece = &mut buf[..n];
            self.flash.read(slot, BLOB_OFFSET + at, piece)?;
            digest.update(piece);
            at += n;
        }
        Ok(digest.finalize())
    }

    /// Reads the active blob into `buf`; returns the bytes read.
    pub fn read_active<'b>(&mut self, buf: &'b mut [u8]) -> Result<&'b [u8], StoreError> {
        let active = self.active.ok_or(StoreError::NoUpload)?;
        let len = active.record.blob_len;
        let capacity = u32::try_from(buf.len()).unwrap_or(u32::MAX);
        let out = buf.get_mut(..len as usize).ok_or(StoreError::TooLarge {
            total_len: len,
            capacity,
        })?;
        self.flash.read(active.slot, BLOB_OFFSET, out)?;
        let computed = crc32(out);
        if computed != active.record.blob_crc32 {
            return Err(StoreError::CrcMismatch {
                expected: active.record.blob_crc32,
                computed,
            });
        }
        Ok(out)
    }

    fn staging(&self) -> Slot {
        staging_slot(self.active.map(|a| a.slot))
    }

    /// Starts an upload of a `total_len`-byte blob (erasing the staging slot),
    /// or resumes the one in progress if it is the same blob (same length, CRC
    /// and model id). `capacity` is the caller's own limit (its RAM buffer).
    /// Returns the offset the host sends next.
    pub fn begin(
        &mut self,
        total_len: u32,
        crc32: u32,
        model_id: u32,
        capacity: u32,
    ) -> Result<u32, StoreError> {
        if total_len == 0 {
            return Err(StoreError::EmptyBlob);
        }
        let capacity = capacity.min(Self::MAX_BLOB_LEN);
        if total_len > capacity {
            return Err(StoreError::TooLarge {
                total_len,
                capacity,
            });
        }
        let staging = self.staging();
        if let Some(u) = self.upload {
            if u.slot == staging
                && u.total_len == total_len
                && u.crc32 == crc32
                && u.model_id == model_id
            {
                return Ok(u.received);
            }
        }
        self.upload = None;
        self.pending = [0xFF; FLASH_WORD];
        self.flash.erase(staging)?;
        self.upload = Some(Upload {
            slot: staging,
            total_len,
            crc32,
            model_id,
            received: 0,
        });
        Ok(0)
    }

    /// Stores one chunk at `offset`; returns the offset the host sends next.
    pub fn chunk(&mut self, offset: u32, data: &[u8]) -> Result<u32, StoreError> {
        let mut u = self.upload.ok_or(StoreError::NoUpload)?;
        let skip = match u.classify(offset, data.len())? {
            ChunkAction::Duplicate => return Ok(u.received),
            ChunkAction::Append { skip } => skip,
        };
        let mut rest = data.get(skip..).unwrap_or(&[]);
        while !rest.is_empty() {
            let fill = u.received as usize % FLASH_WORD;
            let n = (FLASH_WORD - fill).min(rest.len());
            let (now, later) = rest.split_at(n);
            self.pending[fill..fill + n].copy_from_slice(now);
            rest = later;
            if fill + n == FLASH_WORD {
                let word_start = u.received as usize - fill;
                if let Err(e) = self.program_pending(u.slot, word_start) {
                    self.upload = None;
                    return Err(e.into());
                }
            }
            u.received += n as u32;
            self.upload = Some(u);
        }
        Ok(u.received)
    }

    /// Programs the pending word (padded with `0xFF`) at blob offset
    /// `word_start`.
    fn program_pending(&mut self, slot: Slot, word_start: usize) -> Result<(), FlashError> {
        let word = core::mem::replace(&mut self.pending, [0xFF; FLASH_WORD]);
        self.flash.write(slot, BLOB_OFFSET + word_start, &word)
    }

    /// Finishes the upload: programs the last partial word, reads the whole
    /// blob back into `buf` and checks its CRC, runs `validate` on it, then
    /// programs the commit record and reads it back through the boot checks.
    /// On success the new model is active and `buf` holds its blob (`buf`
    /// must hold `total_len` bytes). On any error the previous model stays
    /// active; the upload is kept only for `Incomplete` and a commit CRC that
    /// differs from the announced one (the host may still fix those).
    pub fn commit<T, E>(
        &mut self,
        crc32: u32,
        buf: &mut [u8],
        validate: impl FnOnce(&[u8]) -> Result<T, E>,
    ) -> Result<(StoredModel, T), CommitError<E>> {
        let u = self.upload.ok_or(StoreError::NoUpload)?;
        if crc32 != u.crc32 {
            return Err(StoreError::CrcMismatch {
                expected: u.crc32,
                computed: crc32,
            }
            .into());
        }
        if u.received != u.total_len {
            return Err(StoreError::Incomplete {
                next_offset: u.received,
                total_len: u.total_len,
            }
            .into());
        }
        // From here on the upload is consumed whatever happens.
        self.upload = None;
        let fill = u.received as usize % FLASH_WORD;
        if fill != 0 {
            self.program_pending(u.slot, u.received as usize - fill)
                .map_err(StoreError::Flash)?;
        }
        let capacity = u32::try_from(buf.len()).unwrap_or(u32::MAX);
        let staged = buf
            .get_mut(..u.total_len as usize)
            .ok_or(StoreError::TooLarge {
                total_len: u.total_len,
                capacity,
            })?;
        self.flash
            .read(u.slot, BLOB_OFFSET, staged)
            .map_err(StoreError::Flash)?;
        let computed = CRC32.checksum(staged);
        if computed != u.crc32 {
            return Err(StoreError::CrcMismatch {
                expected: u.crc32,
                computed,
            }
            .into());
        }
        let validated = validate(staged).map_err(CommitError::Rejected)?;
        let record = CommitRecord {
            sequence: next_sequence(self.active.as_ref().map(|a| &a.record)),
            blob_len: u.total_len,
            blob_crc32: u.crc32,
            model_id: u.model_id,
        };
        self.flash
            .write(u.slot, 0, &record.encode())
            .map_err(StoreError::Flash)?;
        let checked = self.check_slot(u.slot).ok_or(StoreError::RecordVerify)?;
        let stored = StoredModel {
            slot: u.slot,
            record: checked,
        };
        self.active = Some(stored);
        Ok((stored, validated))
    }

    /// Drops the upload in progress (the staging slot keeps no valid record).
    pub fn abort(&mut self) {
        self.upload = None;
        self.pending = [0xFF; FLASH_WORD];
    }

    /// Forgets every stored model: erases the staging slot, then the active
    /// one (so a cut clear never brings an older model back).
    pub fn clear(&mut self) -> Result<(), StoreError> {
        self.abort();
        let staging = self.staging();
        self.flash.erase(staging)?;
        self.flash.erase(staging.other())?;
        self.active = None;
        Ok(())
    }
}

/// Model slots in RAM, `SLOT_LEN` bytes each: the host's and the virtual
/// device's [`ModelFlash`], with the H7's rules (whole 32-byte words, each
/// programmed once after erase) and simulated power loss: after
/// [`RamFlash::cut_after`] `n` more operations (word writes and erases), the
/// next one is torn (a word gets only its first half; an erase clears only
/// the first half of the slot) and every operation fails with
/// [`FlashError::PowerLost`] until [`RamFlash::power_cycle`].
///
/// Plain arrays, no allocation (put a large one in a `Box` on the host).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RamFlash<const SLOT_LEN: usize> {
    slots: [[u8; SLOT_LEN]; 2],
    ops_left: Option<usize>,
    powered: bool,
    ops: usize,
}

impl<const SLOT_LEN: usize> Default for RamFlash<SLOT_LEN> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const SLOT_LEN: usize> RamFlash<SLOT_LEN> {
    /// Both slots erased, power on, no cut planned.
    pub const fn new() -> Self {
        RamFlash {
            slots: [[0xFF; SLOT_LEN]; 2],
            ops_left: None,
            powered: true,
            ops: 0,
        }
    }

    /// Lets `ops` more word writes / erases succeed; the one after is torn
    /// and the power goes.
    pub fn cut_after(&mut self, ops: usize) {
        self.ops_left = Some(ops);
    }

    /// Power back on, no cut planned (RAM state of the store is lost: open a
    /// new `ModelStore` on this flash).
    pub fn power_cycle(&mut self) {
        self.powered = true;
        self.ops_left = None;
    }

    /// Word writes and erases carried out so far (torn ones included).
    pub fn operations(&self) -> usize {
        self.ops
    }

    /// A slot's bytes.
    pub fn slot(&self, slot: Slot) -> &[u8; SLOT_LEN] {
        &self.slots[slot.index() as usize]
    }

    /// Whether the power holds for one more operation; tears it if not.
    fn spend(&mut self) -> Result<bool, FlashError> {
        if !self.powered {
            return Err(FlashError::PowerLost);
        }
        self.ops += 1;
        match self.ops_left {
            Some(0) => {
                self.powered = false;
                Ok(false)
            }
            Some(n) => {
                self.ops_left = Some(n - 1);
                Ok(true)
            }
            None => Ok(true),
        }
    }

    fn range(offset: usize, len: usize) -> Result<core::ops::Range<usize>, FlashError> {
        let end = offset.checked_add(len).filter(|&e| e <= SLOT_LEN);
        end.map(|end| offset..end).ok_or(FlashError::OutOfBounds {
            offset: u32::try_from(offset).unwrap_or(u32::MAX),
            len: u32::try_from(len).unwrap_or(u32::MAX),
        })
    }
}

impl<const SLOT_LEN: usize> ModelFlash for RamFlash<SLOT_LEN> {
    const SLOT_LEN: usize = SLOT_LEN;

    fn read(&mut self, slot: Slot, offset: usize, buf: &mut [u8]) -> Result<(), FlashError> {
        if !self.powered {
            return Err(FlashError::PowerLost);
        }
        let r = Self::range(offset, buf.len())?;
        buf.copy_from_slice(&self.slots[slot.index() as usize][r]);
        Ok(())
    }

    fn erase(&mut self, slot: Slot) -> Result<(), FlashError> {
        let whole = self.spend()?;
        let s = &mut self.slots[slot.index() as usize];
        if whole {
            s.fill(0xFF);
            Ok(())
        } else {
            s[..SLOT_LEN / 2].fill(0xFF);
            Err(FlashError::PowerLost)
        }
    }

    fn write(&mut self, slot: Slot, offset: usize, data: &[u8]) -> Result<(), FlashError> {
        if !self.powered {
            return Err(FlashError::PowerLost);
        }
        let r = Self::range(offset, data.len())?;
        if offset % FLASH_WORD != 0 || data.len() % FLASH_WORD != 0 {
            return Err(FlashError::Misaligned {
                offset: offset as u32,
                len: data.len() as u32,
            });
        }
        for (k, word) in data.chunks_exact(FLASH_WORD).enumerate() {
            let at = r.start + k * FLASH_WORD;
            let target = &self.slots[slot.index() as usize][at..at + FLASH_WORD];
            if target.iter().any(|&b| b != 0xFF) {
                return Err(FlashError::NotErased { offset: at as u32 });
            }
            let whole = self.spend()?;
            let target = &mut self.slots[slot.index() as usize][at..at + FLASH_WORD];
            if whole {
                target.copy_from_slice(word);
            } else {
                target[..FLASH_WORD / 2].copy_from_slice(&word[..FLASH_WORD / 2]);
                return Err(FlashError::PowerLost);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
