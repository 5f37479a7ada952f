//! The STM32H7's internal flash as the model store's [`ModelFlash`]: sectors
//! 6 and 7 (128 KiB each, see `memory.x`) are slots A and B. The slot logic
//! (commit records, which slot is active, uploads that survive a power cut)
//! is `spidar_core::model_store`; this is only the flash I/O.
//!
//! Single-bank part: while a sector is erased (~1-2 s, up to ~4 s) or a
//! word programmed, every flash read stalls, i.e. the whole program including
//! the control loop, and the device lock (a critical section) masks
//! interrupts too. The device refuses uploads while armed, the watchdog is
//! stretched around an erase (see `watchdog`), and the time base counts on
//! in hardware (see `time_driver`).

use embassy_stm32::flash::{Blocking, Error, Flash};
use spidar_core::model_store::{FlashError, ModelFlash, Slot, FLASH_WORD};

use crate::watchdog;

/// Offsets of the slots from the start of flash (sectors 6 and 7; see memory.x).
pub const SLOT_A_OFFSET: u32 = 0x000C_0000;
pub const SLOT_B_OFFSET: u32 = 0x000E_0000;
/// One sector per slot.
pub const SLOT_LEN: usize = 128 * 1024;

/// embassy's flash error as a code for `DeviceError::Storage`: `0x100 | kind`.
fn hardware(e: Error) -> FlashError {
    FlashError::Hardware {
        code: 0x100 | e as u32,
    }
}

/// Sectors 6 and 7 of the internal flash.
pub struct H7Flash {
    flash: Flash<'static, Blocking>,
}

impl H7Flash {
    pub fn new(flash: Flash<'static, Blocking>) -> Self {
        Self { flash }
    }

    /// Flash offset of `offset..offset + len` in `slot`, or `OutOfBounds`.
    fn at(slot: Slot, offset: usize, len: usize) -> Result<u32, FlashError> {
        let base = match slot {
            Slot::A => SLOT_A_OFFSET,
            Slot::B => SLOT_B_OFFSET,
        };
        match offset.checked_add(len) {
            Some(end) if end <= SLOT_LEN => Ok(base + offset as u32),
            _ => Err(FlashError::OutOfBounds {
                offset: offset as u32,
                len: len as u32,
            }),
        }
    }
}

impl ModelFlash for H7Flash {
    const SLOT_LEN: usize = SLOT_LEN;

    fn read(&mut self, slot: Slot, offset: usize, buf: &mut [u8]) -> Result<(), FlashError> {
        let at = Self::at(slot, offset, buf.len())?;
        self.flash.blocking_read(at, buf).map_err(hardware)
    }

    fn erase(&mut self, slot: Slot) -> Result<(), FlashError> {
        let at = Self::at(slot, 0, SLOT_LEN)?;
        watchdog::set_timeout_ms(watchdog::FLASH_ERASE_TIMEOUT_MS);
        let r = self.flash.blocking_erase(at, at + SLOT_LEN as u32);
        watchdog::set_timeout_ms(watchdog::NORMAL_TIMEOUT_MS);
        r.map_err(hardware)
    }

    fn write(&mut self, slot: Slot, offset: usize, data: &[u8]) -> Result<(), FlashError> {
        let at = Self::at(slot, offset, data.len())?;
        if offset % FLASH_WORD != 0 || data.len() % FLASH_WORD != 0 {
            return Err(FlashError::Misaligned {
                offset: offset as u32,
                len: data.len() as u32,
            });
        }
        self.flash.blocking_write(at, data).map_err(hardware)
    }
}
