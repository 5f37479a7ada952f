//! Model storage in internal flash: two slots with commit records.
//!
//! The pure rules (record format, which slot is active, where an upload goes,
//! chunk ordering) are in [`crate::slots`]; this module does the flash I/O:
//! erase, word-buffered programming, read-back verification, commit.
//!
//! Single-bank part: while a sector is erased or a word programmed, every
//! flash read stalls, i.e. the whole program including the control loop.
//! Uploads are therefore refused while the motors are armed, and the watchdog
//! is stretched around the erase (see `watchdog`).

use core::sync::atomic::Ordering;

use embassy_stm32::flash::{Blocking, Error as FlashError, Flash};
use spidar_protocol::blob;

use crate::shared::{self, ModelUpdate, MODEL, MODEL_IN_USE};
use crate::slots::{
    self, ChunkAction, CommitRecord, Slot, Upload, UploadError, BLOB_OFFSET, FLASH_WORD,
    RECORD_LEN, SLOT_SIZE,
};
use crate::watchdog;

/// Start of flash in the memory map.
const FLASH_BASE: u32 = 0x0800_0000;
/// Offsets of the slots from the start of flash (sectors 6 and 7; see memory.x).
pub const SLOT_A_OFFSET: u32 = 0x000C_0000;
pub const SLOT_B_OFFSET: u32 = 0x000E_0000;

fn slot_offset(slot: Slot) -> u32 {
    match slot {
        Slot::A => SLOT_A_OFFSET,
        Slot::B => SLOT_B_OFFSET,
    }
}

fn crc32(data: &[u8]) -> u32 {
    blob::CRC32.checksum(data)
}

/// The blob bytes of a slot, memory-mapped.
///
/// The slots lie outside the `FLASH` region of memory.x, so nothing linked
/// aliases them; a slot is only erased or programmed when it is neither the
/// active slot nor the one in `MODEL_IN_USE`, so a slice handed to the
/// control loop stays valid while it is in use.
fn slot_bytes(slot: Slot, len: u32) -> &'static [u8] {
    let len = len.min(slots::MAX_BLOB_LEN) as usize;
    let addr = FLASH_BASE + slot_offset(slot) + BLOB_OFFSET;
    // SAFETY: `addr..addr + len` lies inside sector 6 or 7 of the internal
    // flash (len <= MAX_BLOB_LEN), which is always mapped and readable; see
    // the function comment for why the contents do not change while borrowed.
    unsafe { core::slice::from_raw_parts(addr as *const u8, len) }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StorageError {
    /// Motors armed: flash programming would stall the control loop.
    Armed,
    /// The staging slot is still being read by the control loop.
    SlotInUse,
    Upload(UploadError),
    Flash(FlashErrorKind),
    /// Read-back CRC of the staged blob differs from the announced one.
    Verify {
        expected: u32,
        computed: u32,
    },
    /// The staged blob's header or body does not check (protocol::blob).
    Blob(blob::BlobError),
}

impl defmt::Format for StorageError {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(f, "{}", defmt::Debug2Format(self))
    }
}

#[derive(Clone, Copy, Debug, PartialEq, defmt::Format)]
pub struct FlashErrorKind(pub u8);

impl From<FlashError> for StorageError {
    fn from(e: FlashError) -> Self {
        StorageError::Flash(FlashErrorKind(e as u8))
    }
}

impl From<UploadError> for StorageError {
    fn from(e: UploadError) -> Self {
        StorageError::Upload(e)
    }
}

/// Description of the active model.
#[derive(Clone, Copy, Debug, PartialEq, defmt::Format)]
pub struct Active {
    pub slot: Slot,
    pub record: CommitRecord,
}

impl Active {
    pub fn blob(&self) -> &'static [u8] {
        slot_bytes(self.slot, self.record.blob_len)
    }
}

pub struct Storage {
    flash: Flash<'static, Blocking>,
    active: Option<Active>,
    upload: Option<Upload>,
    /// Bytes of the upload not yet making a whole flash word.
    pending: [u8; FLASH_WORD],
    pending_len: usize,
}

impl Storage {
    /// Scans both slots and picks the active model.
    pub fn new(flash: Flash<'static, Blocking>) -> Self {
        let mut s = Self {
            flash,
            active: None,
            upload: None,
            pending: [0xFF; FLASH_WORD],
            pending_len: 0,
        };
        let a = s.check_slot(Slot::A);
        let b = s.check_slot(Slot::B);
        s.active = slots::select_active(a, b).map(|(slot, record)| Active { slot, record });
        s
    }

    /// The slot's record, if it decodes and the blob matches its CRC and
    /// passes the blob header checks.
    fn check_slot(&mut self, slot: Slot) -> Option<CommitRecord> {
        let mut rec = [0u8; RECORD_LEN];
        self.flash.blocking_read(slot_offset(slot), &mut rec).ok()?;
        let r = CommitRecord::decode(&rec, crc32)?;
        let bytes = slot_bytes(slot, r.blob_len);
        if crc32(bytes) != r.blob_crc32 {
            defmt::warn!("model slot {}: blob CRC mismatch, ignored", slot);
            return None;
        }
        if let Err(e) = blob::split_blob(bytes) {
            defmt::warn!(
                "model slot {}: blob rejected ({})",
                slot,
                defmt::Debug2Format(&e)
            );
            return None;
        }
        Some(r)
    }

    pub fn active(&self) -> Option<Active> {
        self.active
    }

    pub fn upload(&self) -> Option<Upload> {
        self.upload
    }

    fn staging(&self) -> Slot {
        slots::staging_slot(self.active.map(|a| a.slot))
    }

    fn check_may_write(&self, slot: Slot) -> Result<(), StorageError> {
        if shared::telemetry().armed {
            return Err(StorageError::Armed);
        }
        if MODEL_IN_USE.load(Ordering::Acquire) == slot.index() {
            return Err(StorageError::SlotInUse);
        }
        Ok(())
    }

    /// Starts (or resumes) an upload; returns the offset the host sends next.
    pub fn begin(&mut self, total_len: u32, crc: u32, model_id: u32) -> Result<u32, StorageError> {
        let staging = self.staging();
        let (u, resumed) = Upload::begin(self.upload, staging, total_len, crc, model_id)?;
        if resumed {
            return Ok(u.received);
        }
        self.check_may_write(staging)?;
        self.upload = None;
        self.pending_len = 0;
        let off = slot_offset(staging);
        watchdog::set_timeout_ms(watchdog::FLASH_ERASE_TIMEOUT_MS);
        let r = self.flash.blocking_erase(off, off + SLOT_SIZE);
        watchdog::set_timeout_ms(watchdog::NORMAL_TIMEOUT_MS);
        r?;
        self.upload = Some(u);
        Ok(0)
    }

    /// Stores one chunk; returns the offset the host sends next.
    pub fn chunk(&mut self, offset: u32, data: &[u8]) -> Result<u32, StorageError> {
        let mut u = self.upload.ok_or(UploadError::NotStarted)?;
        let skip = match u.chunk(offset, data.len())? {
            ChunkAction::Duplicate => return Ok(u.received),
            ChunkAction::Append { skip } => skip,
        };
        self.check_may_write(u.slot)?;
        let mut rest = &data[skip..];
        while !rest.is_empty() {
            let n = slots::fill_word(self.pending_len, rest.len());
            self.pending[self.pending_len..self.pending_len + n].copy_from_slice(&rest[..n]);
            self.pending_len += n;
            rest = &rest[n..];
            if self.pending_len == FLASH_WORD {
                self.flush_word(&u)?;
            }
            u.received += n as u32;
            self.upload = Some(u);
        }
        Ok(u.received)
    }

    /// Programs the pending word (padded with 0xFF) at its place in the slot.
    fn flush_word(&mut self, u: &Upload) -> Result<(), StorageError> {
        if self.pending_len == 0 {
            return Ok(());
        }
        // The pending word starts at the last word boundary at or below the
        // bytes already programmed.
        let word_start = (u.received / FLASH_WORD as u32) * FLASH_WORD as u32;
        let addr = slot_offset(u.slot) + BLOB_OFFSET + word_start;
        self.pending[self.pending_len..].fill(0xFF);
        let word = self.pending;
        self.pending_len = 0;
        self.pending = [0xFF; FLASH_WORD];
        self.flash.blocking_write(addr, &word)?;
        Ok(())
    }

    /// Checks the staged blob and makes it active. On any error the active
    /// model stays as it was.
    pub fn commit(&mut self, crc: u32) -> Result<Active, StorageError> {
        let u = self.upload.ok_or(UploadError::NotStarted)?;
        u.ready_to_commit(crc)?;
        self.check_may_write(u.slot)?;
        // The last partial word: `received` already counts its bytes.
        if self.pending_len > 0 {
            let start = u.received - self.pending_len as u32;
            let tmp = Upload {
                received: start,
                ..u
            };
            self.flush_word(&tmp)?;
        }
        let bytes = slot_bytes(u.slot, u.total_len);
        let computed = crc32(bytes);
        if computed != u.crc32 {
            return Err(StorageError::Verify {
                expected: u.crc32,
                computed,
            });
        }
        blob::split_blob(bytes).map_err(StorageError::Blob)?;
        let record = CommitRecord {
            sequence: slots::next_sequence(self.active.as_ref().map(|a| &a.record)),
            blob_len: u.total_len,
            blob_crc32: u.crc32,
            model_id: u.model_id,
        };
        self.flash
            .blocking_write(slot_offset(u.slot), &record.encode(crc32))?;
        // Read back through the same checks as at boot.
        let checked = self.check_slot(u.slot).ok_or(StorageError::Verify {
            expected: u.crc32,
            computed: 0,
        })?;
        let active = Active {
            slot: u.slot,
            record: checked,
        };
        self.active = Some(active);
        self.upload = None;
        MODEL.signal(ModelUpdate::Use {
            slot: active.slot,
            blob: active.blob(),
        });
        Ok(active)
    }

    /// Drops the staged upload (the staging slot keeps no valid record).
    pub fn abort(&mut self) {
        self.upload = None;
        self.pending_len = 0;
    }

    /// Forgets every stored model (the device falls back to its nominal
    /// string model): tells the control loop to let go of the active blob,
    /// then erases both slots. Returns `SlotInUse` until the loop has let go
    /// (at its next iteration): call again.
    pub fn clear(&mut self) -> Result<(), StorageError> {
        MODEL.signal(ModelUpdate::None);
        self.upload = None;
        self.pending_len = 0;
        for slot in [Slot::A, Slot::B] {
            self.check_may_write(slot)?;
        }
        for slot in [Slot::A, Slot::B] {
            let off = slot_offset(slot);
            watchdog::set_timeout_ms(watchdog::FLASH_ERASE_TIMEOUT_MS);
            let r = self.flash.blocking_erase(off, off + SLOT_SIZE);
            watchdog::set_timeout_ms(watchdog::NORMAL_TIMEOUT_MS);
            r?;
        }
        self.active = None;
        Ok(())
    }
}
