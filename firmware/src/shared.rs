//! State shared between tasks, all through embassy-sync primitives.

use core::cell::Cell;
use core::sync::atomic::AtomicU8;

use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::blocking_mutex::Mutex;
use embassy_sync::channel::Channel;
use embassy_sync::signal::Signal;

use spidar_core::STRINGS;

use crate::slots::Slot;

/// What the link asks the control loop to do.
#[derive(Clone, Copy, Debug, PartialEq, defmt::Format)]
pub enum Command {
    /// Enable the motor drivers (refused while the emergency stop is active).
    Arm,
    /// Zero every duty and disable the motor drivers.
    Disarm,
    /// Render this force at the end-effector (N, device frame).
    SetForce([f32; 3]),
    /// Clear latched faults whose cause has gone.
    ClearFaults,
}

/// Commands from the link task to the control loop (drained every iteration).
pub static COMMANDS: Channel<CriticalSectionRawMutex, Command, 8> = Channel::new();

/// The model the control loop should evaluate: a blob in a flash slot, or none.
#[derive(Clone, Copy, Debug, PartialEq, defmt::Format)]
pub enum ModelUpdate {
    Use { slot: Slot, blob: &'static [u8] },
    None,
}

/// Storage -> control loop: switch models (taken at the next iteration).
pub static MODEL: Signal<CriticalSectionRawMutex, ModelUpdate> = Signal::new();

/// Slot whose blob the control loop currently reads (`NO_SLOT` for none).
/// Storage never erases this slot.
pub static MODEL_IN_USE: AtomicU8 = AtomicU8::new(NO_SLOT);
pub const NO_SLOT: u8 = 0xFF;

/// Latched fault bits (mirror `spidar_protocol` `Faults` once it lands).
pub mod faults {
    pub const ESTOP: u16 = 1 << 7;
    pub const LOOP_OVERRUN: u16 = 1 << 4;
    pub const MODEL_INVALID: u16 = 1 << 5;
}

/// A snapshot the control loop publishes every iteration for the link.
#[derive(Clone, Copy, Debug, Default, defmt::Format)]
pub struct Telemetry {
    pub iterations: u32,
    pub raw_counts: [u16; STRINGS],
    pub counts: [i32; STRINGS],
    /// Signed duty per motor, in 1/32767 of full scale.
    pub duty_q15: [i16; STRINGS],
    pub armed: bool,
    pub faults: u16,
    /// Loop body time in CPU cycles: last and worst since boot.
    pub loop_cycles_last: u32,
    pub loop_cycles_max: u32,
    /// Iterations whose body took longer than the period.
    pub overruns: u32,
}

pub static TELEMETRY: Mutex<CriticalSectionRawMutex, Cell<Telemetry>> =
    Mutex::new(Cell::new(Telemetry {
        iterations: 0,
        raw_counts: [0; STRINGS],
        counts: [0; STRINGS],
        duty_q15: [0; STRINGS],
        armed: false,
        faults: 0,
        loop_cycles_last: 0,
        loop_cycles_max: 0,
        overruns: 0,
    }));

pub fn telemetry() -> Telemetry {
    TELEMETRY.lock(|t| t.get())
}
