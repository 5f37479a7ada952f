//! `spidar flash` and `spidar device ...`: the link's command line.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::bail;
use spidar_protocol::messages::q16_to_mm;
use spidar_protocol::State;

use spidar::device::link::{Client, ClientOptions, FlashPhase, LinkError, StreamOptions};

use crate::interrupt::{self, Interrupted};

mod report;

use report::{force_report, state_line, Hold};

/// Port and link settings shared by the device commands. Global: they may
/// come before or after a subcommand (`spidar device info --port P` as
/// well as `spidar device --port P info`); clap does not allow a global
/// argument to be required, so a missing `--port` is checked in
/// [`PortArgs::open`].
#[derive(Clone, Debug, clap::Args)]
pub struct PortArgs {
    /// Serial port of the device (e.g. /dev/ttyACM0, or the path
    /// `spidar virtual-device` prints). Required.
    #[arg(long, global = true)]
    pub port: Option<String>,
    /// Reply timeout, ms.
    #[arg(long, global = true, default_value_t = 250)]
    pub timeout_ms: u64,
    /// Resends of a request that got no reply.
    #[arg(long, global = true, default_value_t = 3)]
    pub retries: u32,
}

impl PortArgs {
    pub fn options(&self) -> ClientOptions {
        ClientOptions {
            timeout: Duration::from_millis(self.timeout_ms.max(1)),
            retries: self.retries,
            ..ClientOptions::default()
        }
    }

    /// Opens the port; an error if `--port` was not given.
    pub fn open(&self) -> anyhow::Result<Client> {
        let port = self.port.as_deref().ok_or_else(|| anyhow::anyhow!(
            "the device's serial port is required: --port PORT (e.g. /dev/ttyACM0, or the path `spidar virtual-device` prints)",
        ))?;
        Ok(Client::open_with(port, self.options())?)
    }
}

/// `spidar flash --port PORT MODEL`.
#[derive(Clone, Debug, clap::Args)]
pub struct FlashArgs {
    #[command(flatten)]
    pub port: PortArgs,
    /// Model blob written by `spidar compile`.
    pub model: PathBuf,
    /// Flash a model of another string count than the one the device runs
    /// (a rig rebuilt with more or fewer strings). Without it such a blob
    /// is refused before the upload: on the rig as it is, the strings the
    /// model lacks would go slack and the ones it adds would pull nothing.
    #[arg(long)]
    pub string_count_change: bool,
}

/// `spidar device ...`.
#[derive(Clone, Debug, clap::Args)]
pub struct DeviceArgs {
    #[command(flatten)]
    pub port: PortArgs,
    #[command(subcommand)]
    pub command: DeviceCommand,
}

/// The device subcommands.
#[derive(Clone, Debug, clap::Subcommand)]
pub enum DeviceCommand {
    /// Firmware, protocol, active model, link counters, and the state now:
    /// armed or not, motors on or off (they hold pre-tension after a fault
    /// until `disarm`), faults by name.
    Info,
    /// Print the state stream (CSV on stdout); fails if no frame comes.
    Stream {
        /// One frame every N loop iterations.
        #[arg(long, default_value_t = 10)]
        decimation: u16,
        /// Stop after this many frames (at least 1).
        #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
        frames: Option<u64>,
        /// Stop after this many seconds.
        #[arg(long, default_value_t = 1.0, value_parser = crate::args::positive)]
        seconds: f64,
    },
    /// Arm the motors (pre-tension). The device needs a request at least
    /// every heartbeat timeout (20 ms) while armed: this command keeps the
    /// heartbeat for --hold seconds; after it, the device drops to
    /// pre-tension, holds it (the motors stay on: model changes are refused
    /// until `disarm`) and latches HEARTBEAT_LOST until the next `arm`
    /// clears it (`disarm` turns the motors off and leaves it latched).
    /// Fails, naming the faults, if the device did not stay armed through
    /// the hold (a heartbeat lost, a fault). SIGINT (Ctrl-C) or SIGTERM
    /// during the hold disarms the device (motors off) and exits 130
    /// (SIGINT) or 143 (SIGTERM).
    Arm {
        #[arg(long, default_value_t = 0.0, value_parser = crate::args::non_negative)]
        hold: f64,
    },
    /// Disarm the motors.
    Disarm,
    /// Arm and render a force (device frame, N) for --hold seconds, then
    /// go back to no force and disarm. Fails, naming the faults, if the
    /// device did not stay armed to render it (a heartbeat lost, a fault).
    /// SIGINT (Ctrl-C) or SIGTERM during the hold ends it the same way (no
    /// force, disarmed) and exits 130 (SIGINT) or 143 (SIGTERM).
    Force {
        /// Force along x, N.
        #[arg(allow_hyphen_values = true, value_parser = finite_newtons)]
        fx: f32,
        /// Force along y, N.
        #[arg(allow_hyphen_values = true, value_parser = finite_newtons)]
        fy: f32,
        /// Force along z, N.
        #[arg(allow_hyphen_values = true, value_parser = finite_newtons)]
        fz: f32,
        #[arg(long, default_value_t = 1.0, value_parser = crate::args::non_negative)]
        hold: f64,
    },
}

/// A force component: a finite number of newtons (an argument error, not a
/// link error, for `nan` or `inf`).
fn finite_newtons(text: &str) -> Result<f32, String> {
    match text.parse::<f32>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(v) => Err(format!("{v} is not a finite force in newtons")),
        Err(e) => Err(format!("`{text}` is not a number of newtons: {e}")),
    }
}

/// The device id as text when it is printable ASCII (a name such as
/// `VIRTUAL-0001`), else as hex.
fn device_name(id: &[u8]) -> String {
    let trimmed: Vec<u8> = id.iter().copied().take_while(|&b| b != 0).collect();
    if !trimmed.is_empty() && trimmed.iter().all(|b| b.is_ascii_graphic()) {
        String::from_utf8_lossy(&trimmed).into_owned()
    } else {
        hex(id)
    }
}

/// `YYYY-MM-DD hh:mm:ss UTC` of seconds since 1970 (civil-from-days, the
/// proleptic Gregorian calendar; no time-zone database needed for UTC).
fn utc_date(unix_s: u64) -> String {
    let days = (unix_s / 86_400) as i64;
    let secs = unix_s % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02} UTC",
        secs / 3600,
        secs / 60 % 60,
        secs % 60
    )
}

/// The link statistics in words.
fn link_line(s: &spidar_protocol::LinkStats) -> String {
    let r = &s.rx;
    format!(
        "link: {} frames received ({} rejected: crc {}, cobs {}, too short {}, payload {}, \
         invalid {}, overlong {}, version {}), {} sent, {} stream frames dropped, {} loop \
         overruns, {} heartbeat losses, up {:.1} s",
        r.ok,
        r.rejected(),
        r.crc,
        r.cobs,
        r.too_short,
        r.payload,
        r.invalid,
        r.overlong,
        r.version,
        s.tx_frames,
        s.tx_dropped,
        s.loop_overruns,
        s.heartbeat_losses,
        s.uptime_us as f64 / 1e6
    )
}

/// A duration option: an argument error (naming the option), not a link
/// error.
fn seconds(s: f64, field: &'static str) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(s)
        .map_err(|_| anyhow::anyhow!("{field}: {s} is not a duration in seconds (>= 0)"))
}

/// Runs `spidar flash`.
pub fn run_flash(args: &FlashArgs) -> anyhow::Result<String> {
    let blob = std::fs::read(&args.model).map_err(|e| {
        anyhow::anyhow!("{}: cannot read the model blob: {e}", args.model.display())
    })?;
    let mut client = args.port.open()?;
    let hello = client.device().copied();
    if let (Ok(new), Some(running)) = (
        spidar_protocol::blob::ModelHeader::parse(&blob),
        client.info()?,
    ) {
        if new.strings != running.header.strings && !args.string_count_change {
            anyhow::bail!(
                "{}: a model of {} strings, and the device runs one of {} (model id {:#010x}): \
                 flashed on the rig as it is, the strings the model lacks go slack and the ones \
                 it adds pull nothing. Compile the calibration of this rig, or pass \
                 --string-count-change if the rig was rebuilt",
                args.model.display(),
                new.strings,
                running.header.strings,
                running.header.model_id
            );
        }
    }
    let mut last = Instant::now();
    let report = client.flash(&blob, |p| {
        let now = Instant::now();
        if p.phase != FlashPhase::Upload || now - last > Duration::from_millis(200) {
            eprint!("\r{:?}: {} / {} bytes   ", p.phase, p.sent, p.total);
            let _ = std::io::stderr().flush();
            last = now;
        }
    });
    eprintln!();
    let report = report.map_err(|e| anyhow::anyhow!("{}: {e}", args.model.display()))?;
    let mut out = String::new();
    if let Some(h) = hello {
        let _ = writeln!(
            out,
            "device {} firmware {}.{}.{}, protocol {}, blob capacity {} bytes",
            device_name(&h.device_id),
            h.firmware_version[0],
            h.firmware_version[1],
            h.firmware_version[2],
            h.protocol_version,
            h.max_blob_len
        );
    }
    let _ = writeln!(
        out,
        "flashed {} ({} bytes, CRC {:#010x}, model id {:#010x}) into slot {}",
        args.model.display(),
        report.blob_len,
        report.blob_crc32,
        report.model_id,
        report.slot
    );
    if let Some(h) = spidar_core::blob::CompiledCalibration::from_blob(&blob)
        .ok()
        .as_ref()
        .and_then(spidar::model::compile::describe_home_slips)
    {
        let _ = writeln!(out, "{h}");
    }
    let _ = writeln!(
        out,
        "upload {:.1} ms ({} chunks, {} resent, resumed at byte {}), commit {:.1} ms, read-back {:.1} ms: verified",
        report.upload.as_secs_f64() * 1e3,
        report.chunks,
        report.resends,
        report.resumed_at,
        report.commit.as_secs_f64() * 1e3,
        report.verify.as_secs_f64() * 1e3
    );
    Ok(out)
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// CSV header of `spidar device stream`.
pub const STREAM_HEADER: &str = "time_us,x_mm,y_mm,z_mm,room_x_mm,room_y_mm,room_z_mm,t0_n,t1_n,t2_n,t3_n,t4_n,t5_n,t6_n,t7_n,faults,armed,motors_on,model_id";

/// One CSV line of a state frame.
pub fn state_csv(s: &State) -> String {
    let mut line = format!(
        "{},{},{},{},{},{},{}",
        s.time_us,
        s.position_mm[0],
        s.position_mm[1],
        s.position_mm[2],
        q16_to_mm(s.corrected_mm[0]),
        q16_to_mm(s.corrected_mm[1]),
        q16_to_mm(s.corrected_mm[2])
    );
    for t in s.tensions_n {
        let _ = write!(line, ",{t}");
    }
    let _ = write!(
        line,
        ",{:#06x},{},{},{}",
        s.faults.0,
        u8::from(s.armed),
        u8::from(s.motors_on),
        s.model_id.map_or(String::new(), |m| format!("{m:#010x}"))
    );
    line
}

/// Runs `spidar device ...`. An error when a request fails, and when the
/// device did not do what was asked (see [`Hold`]).
pub fn run_device(args: &DeviceArgs) -> anyhow::Result<String> {
    // Arguments first: a bad one is an argument error, whatever the port.
    match &args.command {
        DeviceCommand::Stream { seconds: s, .. } => {
            seconds(*s, "--seconds")?;
        }
        DeviceCommand::Arm { hold } | DeviceCommand::Force { hold, .. } => {
            seconds(*hold, "--hold")?;
        }
        DeviceCommand::Info | DeviceCommand::Disarm => {}
    }
    let mut client = args.port.open()?;
    let mut out = String::new();
    match &args.command {
        DeviceCommand::Info => device_info(&mut client, &mut out)?,
        DeviceCommand::Stream {
            decimation,
            frames,
            seconds: secs,
        } => {
            let duration = seconds(*secs, "--seconds")?;
            stream_csv(&mut client, *decimation, *frames, duration)?;
        }
        DeviceCommand::Arm { hold } => {
            let hold = seconds(*hold, "--hold")?;
            arm_and_hold(&mut client, hold, &mut out)?;
        }
        DeviceCommand::Disarm => {
            client.disarm()?;
            let _ = writeln!(out, "disarmed, motors off");
        }
        DeviceCommand::Force { fx, fy, fz, hold } => {
            let hold = seconds(*hold, "--hold")?;
            render_force(&mut client, [*fx, *fy, *fz], hold, &mut out)?;
        }
    }
    Ok(out)
}

/// `spidar device info`: the device, its active model, the link counters
/// and its state now (armed or not, motors on or off, its fault bits by
/// name), into `out`. A device that sends no state frame when asked is an
/// error, after what it did say is printed.
fn device_info(client: &mut Client, out: &mut String) -> anyhow::Result<()> {
    if let Some(h) = client.device().copied() {
        let _ = writeln!(
            out,
            "device {}\nfirmware {}.{}.{}\nprotocol {}\ncapabilities {:#06x}\nmax chunk {} bytes\nmax blob {} bytes\nloop period {} us",
            device_name(&h.device_id),
            h.firmware_version[0],
            h.firmware_version[1],
            h.firmware_version[2],
            h.protocol_version,
            h.capabilities.0,
            h.max_chunk,
            h.max_blob_len,
            h.loop_period_us
        );
    }
    match client.info()? {
        Some(i) => {
            let _ = writeln!(
                out,
                "model id {:#010x} in slot {}: {} strings, {}, {} effects, blob {} bytes, CRC {:#010x}, created {}",
                i.header.model_id,
                i.slot,
                i.header.strings,
                i.header.kind.describe(),
                i.header.effects,
                i.header.blob_len(),
                i.blob_crc32,
                utc_date(u64::from(i.header.created_unix_s))
            );
        }
        None => {
            let _ = writeln!(out, "no model blob (nominal string model, if any)");
        }
    }
    let s = client.stats()?;
    let _ = writeln!(out, "{}", link_line(&s));
    client.stream_on(1)?;
    let last = hold_heartbeat(client, Duration::ZERO, true)?;
    client.stream_off()?;
    match last {
        Some(st) => {
            let _ = writeln!(out, "{}", state_line(&st));
            Ok(())
        }
        None => {
            print!("{out}");
            bail!(
                "{}: the device sent no state frame after StreamOn: its state (armed, motors, faults) is unknown",
                client.port_name()
            )
        }
    }
}

/// `spidar device stream`: the state stream as CSV on stdout, its counters
/// on stderr.
fn stream_csv(
    client: &mut Client,
    decimation: u16,
    frames: Option<u64>,
    duration: Duration,
) -> anyhow::Result<()> {
    let stdout = std::io::stdout();
    let mut lock = stdout.lock();
    let _ = writeln!(lock, "{STREAM_HEADER}");
    // A device with neither a model blob nor a nominal geometry computes no
    // position: its idle loop reports every coordinate as exactly 0.0, which
    // forward kinematics on a real geometry never gives in all three.
    let mut without_geometry = true;
    let report = client.stream(
        StreamOptions {
            decimation,
            duration: Some(duration),
            max_frames: frames,
            ..StreamOptions::default()
        },
        |s| {
            without_geometry &= s.model_id.is_none() && s.position_mm == [0.0; 3];
            writeln!(lock, "{}", state_csv(s)).is_ok()
        },
    )?;
    // On stderr: stdout is the CSV (and may be a closed pipe).
    eprintln!(
        "# {} frames in {:.2} s, {} lost, {} rejected, {} bytes",
        report.frames,
        report.elapsed.as_secs_f64(),
        report.lost,
        report.rejected,
        report.bytes
    );
    if report.frames > 0 && without_geometry {
        eprintln!(
            "# {}: the device has no geometry (no model blob, no nominal geometry): it computes \
             no position, every position column is 0 and no tension is rendered; \
             `spidar flash --port {} MODEL` loads a calibration (`spidar compile` makes one)",
            client.port_name(),
            client.port_name()
        );
    }
    if report.frames == 0 {
        bail!(
            "{}: the device sent no state frame in {:.2} s of streaming",
            client.port_name(),
            report.elapsed.as_secs_f64()
        );
    }
    Ok(())
}

/// `spidar device arm`: arms; with a hold, keeps the heartbeat that long
/// and fails when the device did not stay armed through it.
fn arm_and_hold(client: &mut Client, hold: Duration, out: &mut String) -> anyhow::Result<()> {
    if hold.is_zero() {
        client.arm()?;
        let _ = writeln!(out, "armed");
        return Ok(());
    }
    // SIGINT or SIGTERM ends the hold early: disarmed, then said.
    interrupt::install();
    let losses = client.stats()?.heartbeat_losses;
    if let Some(i) = interrupted_before_arming(client.port_name()) {
        return Err(i.into());
    }
    client.arm()?;
    // State frames (every 10th loop iteration) tell whether it stays armed.
    client.stream_on(10)?;
    eprintln!(
        "armed, holding {:.1} s (Ctrl-C or SIGTERM: disarm now)",
        hold.as_secs_f64()
    );
    let t0 = Instant::now();
    let last = hold_heartbeat(client, hold, true)?;
    let held_for = t0.elapsed();
    let held = Hold {
        last,
        heartbeat_losses: client.stats()?.heartbeat_losses.wrapping_sub(losses),
    };
    client.stream_off()?;
    if interrupt::raised() {
        client.set_force([0.0; 3])?;
        client.disarm()?;
        let i = Interrupted::if_received(String::new(), |signal| {
            format!(
                "{}: armed, held {:.1} of {:.1} s: interrupted by {signal}{}; the device is disarmed, motors off",
                client.port_name(),
                held_for.as_secs_f64().min(hold.as_secs_f64()),
                hold.as_secs_f64(),
                held.shortfall_before_interrupt().map_or(String::new(), |why| format!(" (before that, {why})"))
            )
        });
        if let Some(i) = i {
            return Err(i.into());
        }
    }
    if let Some(why) = held.shortfall() {
        bail!(
            "{}: armed, then {why}; its motors hold pre-tension until `spidar device disarm`, \
             and `spidar device arm` clears the faults and arms again",
            client.port_name()
        );
    }
    let _ = writeln!(out, "armed, held {:.1} s", hold.as_secs_f64());
    Ok(())
}

/// `spidar device force`: arms, renders `requested` (device frame, N) for
/// `hold`, then no force and disarms; what the device rendered into `out`,
/// or an error when the device did not stay armed to render it.
fn render_force(
    client: &mut Client,
    requested: [f32; 3],
    hold: Duration,
    out: &mut String,
) -> anyhow::Result<()> {
    // SIGINT or SIGTERM ends the hold early: no force, disarmed, then said.
    interrupt::install();
    let losses = client.stats()?.heartbeat_losses;
    if let Some(i) = interrupted_before_arming(client.port_name()) {
        return Err(i.into());
    }
    client.arm()?;
    // State frames (every 10th loop iteration) tell what the device
    // renders; the last one taken while holding is reported.
    client.stream_on(10)?;
    client.set_force(requested)?;
    // Frames that came before the force was acknowledged may be
    // from before it was applied.
    client.take_states();
    eprintln!(
        "holding [{}, {}, {}] N for {:.1} s (Ctrl-C or SIGTERM: no force and disarm now)",
        requested[0],
        requested[1],
        requested[2],
        hold.as_secs_f64()
    );
    let t0 = Instant::now();
    let last = hold_heartbeat(client, hold, true)?;
    let held_for = t0.elapsed();
    let held = Hold {
        last,
        heartbeat_losses: client.stats()?.heartbeat_losses.wrapping_sub(losses),
    };
    client.set_force([0.0; 3])?;
    client.stream_off()?;
    client.disarm()?;
    let interrupted = Interrupted::if_received(String::new(), |signal| {
        format!(
            "{}: {} (held {:.1} of {:.1} s): interrupted by {signal}{}; the force is off and the device disarmed",
            client.port_name(),
            force_report(requested, held.last.as_ref()),
            held_for.as_secs_f64().min(hold.as_secs_f64()),
            hold.as_secs_f64(),
            held.shortfall_before_interrupt().map_or(String::new(), |why| format!(" (before that, {why})"))
        )
    });
    if let Some(i) = interrupted {
        return Err(i.into());
    }
    let report = format!(
        "{} (held {:.1} s)",
        force_report(requested, held.last.as_ref()),
        hold.as_secs_f64()
    );
    if let Some(why) = held.shortfall() {
        bail!(
            "{}: {report}: {why}; the force is off and the device disarmed",
            client.port_name()
        );
    }
    let _ = writeln!(out, "{report}, disarmed");
    Ok(())
}

/// A signal that came before the device was armed: nothing to undo.
fn interrupted_before_arming(port: &str) -> Option<Interrupted> {
    Interrupted::if_received(String::new(), |signal| {
        format!("{port}: interrupted by {signal} before arming; the device was not armed")
    })
}

/// Keeps the device armed for `hold` with heartbeats; when streaming, the
/// last state frame that came meanwhile. Stops at once when SIGINT or
/// SIGTERM came ([`interrupt::raised`]; no handler is installed for
/// commands that hold nothing). A state frame is only trusted when
/// another came before it in the hold (the first may have been computed in
/// the loop iteration before the last request took effect): if fewer came
/// (a slow host), the heartbeats go on until two did, for up to
/// [`STATE_WAIT`] more.
fn hold_heartbeat(
    client: &mut Client,
    hold: Duration,
    want_states: bool,
) -> Result<Option<State>, LinkError> {
    let t0 = Instant::now();
    let mut last = None;
    let mut seen = 0usize;
    loop {
        if interrupt::raised() {
            break;
        }
        let elapsed = t0.elapsed();
        let short = want_states && seen < 2;
        if elapsed >= hold && !(short && elapsed < hold + STATE_WAIT) {
            break;
        }
        client.heartbeat()?;
        // Polling waits for bytes up to the port's timeout: only while
        // streaming, or the heartbeats would come too far apart.
        if want_states {
            let states = client.poll_states()?;
            seen += states.len();
            if let Some(s) = states.last() {
                last = Some(*s);
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    Ok(if seen >= 2 { last } else { None })
}

/// How long `device force` waits past its hold for the device's state frames.
const STATE_WAIT: Duration = Duration::from_secs(2);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_names_and_forces_read_as_people_write_them() {
        assert_eq!(utc_date(0), "1970-01-01 00:00:00 UTC");
        assert_eq!(utc_date(951_782_400), "2000-02-29 00:00:00 UTC");
        assert_eq!(utc_date(1_795_430_123), "2026-11-23 10:35:23 UTC");
        assert_eq!(device_name(b"VIRTUAL-0001"), "VIRTUAL-0001");
        assert_eq!(device_name(&[0xde, 0xad, 0x01]), "dead01");
        assert_eq!(finite_newtons("-2.5"), Ok(-2.5));
        assert!(finite_newtons("nan")
            .unwrap_err()
            .contains("not a finite force"));
        assert!(finite_newtons("x")
            .unwrap_err()
            .contains("not a number of newtons"));
    }
}
