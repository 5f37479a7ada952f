//! The C structs the library fills, and the pure conversions into them:
//! a state frame in the room frame, faults by name, the device's answer to
//! `Hello`, a model's info; forces between the room and device frames.

#![allow(non_camel_case_types)]

use std::ffi::c_char;
use std::time::Instant;

use host::device::link::Received;
use spidar_core::geometry::{mat_t_vec, mat_vec};
use spidar_protocol::messages::q16_to_mm;
use spidar_protocol::{Faults, HelloAck, ModelInfo, STRINGS};

/// Rotation of `p_room = s R p_device + t`, row-major (a model's frame).
pub(crate) type Rotation = [[f32; 3]; 3];

/// No rotation: the frame of a device without a model (its nominal
/// geometry is its room frame).
pub(crate) const IDENTITY: Rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Strings (channels) of the controller: the length of the per-string
/// arrays.
pub const SPIDAR_STRINGS: usize = 8;
const _: () = assert!(SPIDAR_STRINGS == STRINGS);

/// Bytes of `spidar_state::fault_names`, its NUL included.
pub const SPIDAR_FAULT_NAMES_LEN: usize = 128;

/// Bytes of `spidar_info::device_id`, its NUL included (24 hex digits).
pub const SPIDAR_DEVICE_ID_LEN: usize = 25;

/// One state frame of the device, as the application reads it.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct spidar_state {
    /// Device time of the sample, µs since boot.
    pub time_us: u64,
    /// The same instant, µs since home was declared.
    pub since_home_us: u64,
    /// The home capture the counts are from: the boot's random id in the
    /// upper 32 bits, the home captures since that boot in the lower 32
    /// (a session's `home` column).
    pub home_id: u64,
    /// State frames received since the handle was opened, this one
    /// included (1 for the first).
    pub index: u64,
    /// Host time since the library received this frame, µs (at the call).
    pub age_us: u64,
    /// State frames lost on the link since the handle was opened.
    pub lost: u64,
    /// Corrected end-effector position, room frame, mm.
    pub position_mm: [f64; 3],
    /// Force the device renders, room frame, N (NaN while the model's
    /// room frame is unknown: see `SPIDAR_E_FRAME_UNKNOWN`).
    pub rendered_force_n: [f64; 3],
    /// Encoder counts since home, per string.
    pub counts: [i32; SPIDAR_STRINGS],
    /// Commanded tension per string after the safety clamp, N.
    pub tensions_n: [f32; SPIDAR_STRINGS],
    /// Fault bits (latched and present).
    pub faults: u16,
    /// The loop renders forces (armed, no fault since).
    pub armed: u8,
    /// The motor drivers are on (they hold pre-tension after a fault).
    pub motors_on: u8,
    /// Bit i set: string i is slack.
    pub slack: u8,
    /// String left out of forward kinematics, or -1.
    pub excluded: i8,
    /// 1 if the device has a model (then `model_id` is its id).
    pub has_model: u8,
    pub model_id: u32,
    /// The faults by name, comma-separated ("" when none; an unnamed bit
    /// as `0x0200`), NUL-terminated.
    pub fault_names: [c_char; SPIDAR_FAULT_NAMES_LEN],
}

/// What the device says about itself.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct spidar_info {
    pub protocol_version: u16,
    /// Firmware version: major, minor, patch.
    pub firmware_version: [u16; 3],
    /// The device's unique id as 24 hex digits, NUL-terminated.
    pub device_id: [c_char; SPIDAR_DEVICE_ID_LEN],
    /// Capability bits (`spidar_protocol::Capabilities`).
    pub capabilities: u32,
    /// Largest model blob the device stores, bytes.
    pub max_blob_len: u32,
    /// Control-loop period, µs.
    pub loop_period_us: u32,
    /// Strings (channels) of the controller.
    pub strings: u32,
}

/// The device's active model.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct spidar_model_info {
    /// 0: the device has no model (it runs its nominal geometry, if any),
    /// and the other fields are 0.
    pub has_model: u8,
    /// Storage slot (0 or 1).
    pub slot: u8,
    /// Learned correction: 0 none, 1 NN, 2 SVR.
    pub correction: u8,
    /// Strings the model uses.
    pub strings: u8,
    pub model_id: u32,
    /// CRC-32 of the whole blob.
    pub blob_crc32: u32,
    /// When the blob was made, seconds since 1970.
    pub created_unix_s: u32,
    /// Blob body length, bytes.
    pub body_len: u32,
}

/// How the stream fared since the handle was opened: what the host
/// received and missed, and what the device could not send.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct spidar_link_stats {
    /// State frames received.
    pub states: u64,
    /// Stream frames (states, events) missing from the sequence numbers.
    pub lost: u64,
    /// Frames the library's decoder rejected (CRC, framing).
    pub rejected: u64,
    /// Stream frames the device dropped because its link was full (the
    /// host did not read in time). Read after `lost`, it may count a few
    /// more the stream dropped meanwhile; `lost` beyond it went missing on
    /// the way.
    pub device_dropped: u64,
    /// Times the device's heartbeat watchdog tripped.
    pub heartbeat_losses: u32,
    /// Control-loop iterations that overran their period.
    pub loop_overruns: u32,
}

/// A device-frame force in the room frame: `R f`.
pub fn room_from_device_force(r: &Rotation, f: [f32; 3]) -> [f32; 3] {
    mat_vec(r, f)
}

/// A room-frame force in the device frame: `R^T f`.
pub fn device_from_room_force(r: &Rotation, f: [f32; 3]) -> [f32; 3] {
    mat_t_vec(r, f)
}

/// The names of `faults`, comma-separated (bits without a name as hex).
pub fn fault_names(faults: Faults) -> String {
    let mut names: Vec<String> = faults.names().map(str::to_string).collect();
    if faults.unnamed() != 0 {
        names.push(format!("{:#06x}", faults.unnamed()));
    }
    names.join(",")
}

/// Copies `text` into `out` as a NUL-terminated C string, cut to fit.
pub fn copy_c_string(text: &str, out: &mut [c_char]) {
    let n = text.len().min(out.len().saturating_sub(1));
    for (o, b) in out.iter_mut().zip(text.as_bytes()[..n].iter()) {
        *o = *b as c_char;
    }
    if let Some(end) = out.get_mut(n) {
        *end = 0;
    }
}

/// A received state frame as the application reads it at `now`:
/// positions in the room frame, the rendered force turned by `rotation`
/// (NaN when it is unknown), `lost` frames lost so far.
pub fn state_of(
    r: &Received,
    rotation: Option<&Rotation>,
    lost: u64,
    now: Instant,
) -> spidar_state {
    let s = &r.state;
    let rendered = match rotation {
        Some(rot) => room_from_device_force(rot, s.rendered_force_n).map(f64::from),
        None => [f64::NAN; 3],
    };
    let mut out = spidar_state {
        time_us: s.time_us,
        since_home_us: s.since_home_us,
        home_id: s.home_id,
        index: r.index,
        age_us: now.saturating_duration_since(r.at).as_micros() as u64,
        lost,
        position_mm: s.corrected_mm.map(q16_to_mm),
        rendered_force_n: rendered,
        counts: s.counts,
        tensions_n: s.tensions_n,
        faults: s.faults.0,
        armed: u8::from(s.armed),
        motors_on: u8::from(s.motors_on),
        slack: s.slack,
        excluded: s.excluded.map_or(-1, |e| e as i8),
        has_model: u8::from(s.model_id.is_some()),
        model_id: s.model_id.unwrap_or(0),
        fault_names: [0; SPIDAR_FAULT_NAMES_LEN],
    };
    copy_c_string(&fault_names(s.faults), &mut out.fault_names);
    out
}

/// The device's answer to `Hello` as the application reads it.
pub fn info_of(hello: &HelloAck) -> spidar_info {
    let mut out = spidar_info {
        protocol_version: hello.protocol_version,
        firmware_version: hello.firmware_version,
        device_id: [0; SPIDAR_DEVICE_ID_LEN],
        capabilities: hello.capabilities.0,
        max_blob_len: hello.max_blob_len,
        loop_period_us: hello.loop_period_us,
        strings: STRINGS as u32,
    };
    let hex: String = hello.device_id.iter().map(|b| format!("{b:02x}")).collect();
    copy_c_string(&hex, &mut out.device_id);
    out
}

/// The active model's info as the application reads it (`None`: no model).
pub fn model_info_of(info: Option<&ModelInfo>) -> spidar_model_info {
    match info {
        None => spidar_model_info {
            has_model: 0,
            slot: 0,
            correction: 0,
            strings: 0,
            model_id: 0,
            blob_crc32: 0,
            created_unix_s: 0,
            body_len: 0,
        },
        Some(i) => spidar_model_info {
            has_model: 1,
            slot: i.slot,
            correction: i.header.kind as u8,
            strings: i.header.strings,
            model_id: i.header.model_id,
            blob_crc32: i.blob_crc32,
            created_unix_s: i.header.created_unix_s,
            body_len: i.header.body_len,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use spidar_protocol::State;

    fn c_str(b: &[c_char]) -> String {
        let bytes: Vec<u8> = b
            .iter()
            .take_while(|&&c| c != 0)
            .map(|&c| c as u8)
            .collect();
        String::from_utf8(bytes).unwrap()
    }

    #[test]
    fn forces_turn_between_the_frames_and_back() {
        // 90 degrees about z: device x is room y.
        let r: Rotation = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(room_from_device_force(&r, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0]);
        assert_eq!(device_from_room_force(&r, [0.0, 1.0, 0.0]), [1.0, 0.0, 0.0]);
        let f = [0.3, -2.0, 1.5];
        assert_eq!(room_from_device_force(&r, device_from_room_force(&r, f)), f);
    }

    #[test]
    fn a_state_reads_in_millimetres_in_the_room_frame_with_faults_by_name() {
        let state = State {
            time_us: 5_000,
            since_home_us: 4_000,
            home_id: 1 << 32,
            corrected_mm: [65536, -32768, 1 << 20],
            rendered_force_n: [1.0, 0.0, 0.0],
            counts: [0; STRINGS],
            position_mm: [0.0; 3],
            tensions_n: [1.0; STRINGS],
            faults: Faults::HEARTBEAT_LOST.union(Faults(1 << 12)),
            slack: 0,
            excluded: Some(3),
            loop_us: 0,
            loop_max_us: 0,
            armed: false,
            motors_on: true,
            model_id: Some(9),
        };
        let at = Instant::now();
        let r = Received {
            state,
            at,
            index: 7,
        };
        let rot: Rotation = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let s = state_of(
            &r,
            Some(&rot),
            2,
            at + std::time::Duration::from_micros(250),
        );
        assert_eq!(s.position_mm, [1.0, -0.5, 16.0]);
        assert_eq!(s.rendered_force_n, [0.0, 1.0, 0.0]);
        assert_eq!((s.index, s.lost, s.age_us), (7, 2, 250));
        assert_eq!(s.excluded, 3);
        assert_eq!((s.has_model, s.model_id), (1, 9));
        assert_eq!(c_str(&s.fault_names), "HEARTBEAT_LOST,0x1000");
        let unknown = state_of(&r, None, 0, at);
        assert!(unknown.rendered_force_n.iter().all(|f| f.is_nan()));
        assert_eq!(unknown.excluded, 3);
    }

    #[test]
    fn every_fault_named_fits_the_field() {
        let all = fault_names(Faults(u16::MAX));
        assert!(all.len() < SPIDAR_FAULT_NAMES_LEN, "{all}");
        let mut out = [1 as c_char; 4];
        copy_c_string("ABCDEFG", &mut out);
        assert_eq!(c_str(&out), "ABC");
    }
}
