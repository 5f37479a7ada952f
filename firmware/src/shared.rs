//! State shared between the control loop (interrupt executor) and the link
//! tasks (thread executor), all through embassy-sync.
//!
//! The [`Device`] sits in a blocking mutex over a critical section. Why a
//! critical section, and why it is short enough for the 10 kHz loop:
//! - the loop runs in an interrupt executor that preempts the link; a lock
//!   that the loop could find taken would make it skip iterations (or
//!   deadlock if it waited), so the link's `handle` must not be preemptible
//!   by the loop while it mutates the device: a critical section does that;
//! - `Device::tick` (the loop's side) and ordinary requests take a few to
//!   tens of µs, so the loop's start jitters by at most one request's
//!   handling (< the 100 µs period);
//! - the long requests (erase, programming, commit read-back) are only
//!   accepted while disarmed, and on this single-bank flash they stall every
//!   instruction fetch, the loop's included, whether or not interrupts are
//!   masked; the hardware e-stop (timer break inputs) works regardless.
//!
//! Stream frames go the other way through a channel, so the loop never waits
//! for USB.

use core::cell::RefCell;
use core::sync::atomic::AtomicU32;

use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::channel::Channel;
use spidar_core::device::Device;
use spidar_protocol::{Event, State, MAX_FRAME};

use crate::storage::H7Flash;

/// The device, shared by the control loop and the link.
pub type SharedDevice = Mutex<CriticalSectionRawMutex, RefCell<Device<'static, H7Flash>>>;

/// Locks the device for `f` (a short critical section). `None` only if the
/// device is already borrowed, which the critical section rules out.
pub fn with_device<R>(
    device: &SharedDevice,
    f: impl FnOnce(&mut Device<'static, H7Flash>) -> R,
) -> Option<R> {
    device.lock(|d| d.try_borrow_mut().ok().map(|mut d| f(&mut d)))
}

/// What the loop hands to the link to stream.
#[derive(Clone, Copy, Debug)]
pub enum StreamItem {
    State(State),
    Event(Event),
}

/// Control loop -> link writer. Full: the item is dropped and counted
/// (`LinkStats::tx_dropped`).
pub static STREAM: Channel<CriticalSectionRawMutex, StreamItem, 8> = Channel::new();

/// A reply frame on its way to USB.
pub type Frame = heapless::Vec<u8, MAX_FRAME>;

/// Link reader -> link writer: encoded reply frames.
pub static REPLIES: Channel<CriticalSectionRawMutex, Frame, 2> = Channel::new();

/// Stream frames the writer sent (replies are counted by the reader's
/// `DeviceLink`).
pub static STREAM_FRAMES_SENT: AtomicU32 = AtomicU32::new(0);
