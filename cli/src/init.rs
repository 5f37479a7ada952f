//! `spidar init`: guided initialization on a rig or a simulated one.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::anyhow;
use spidar::device::cues::Tee;
use spidar::procedures::init::{initialize, InitConfig, InitError};
use spidar::sim::operator::SimulatedRig;

use crate::audio::{AudioChoice, AudioOut};
use crate::interrupt::{self, EndOnInterrupt, Interrupted};
use crate::rig::RigArgs;
use crate::view::TerminalView;

/// `spidar init`.
#[derive(Clone, Debug, clap::Args)]
pub struct InitArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Where to write the init record (TOML).
    #[arg(long, default_value = "init.toml")]
    pub out: PathBuf,
    /// Also write the geometry with the measured eq. 6 translation here.
    #[arg(long)]
    pub write_geometry: Option<PathBuf>,
    /// Target, room frame, mm, `x,y,z` (default: the nominal frame centre).
    #[arg(long, allow_hyphen_values = true, value_parser = parse_point)]
    pub target: Option<[f64; 3]>,
    /// Cue radius d_min, mm (eqs. 2-5).
    #[arg(long, default_value_t = 150.0)]
    pub d_min_mm: f32,
    /// Largest guidance force F_max, N.
    #[arg(long, default_value_t = 3.0)]
    pub f_max_n: f32,
    /// The marker must hold within this distance of the target, mm.
    #[arg(long, default_value_t = 2.0, value_parser = crate::args::positive)]
    pub tolerance_mm: f64,
    /// ... for this long, s.
    #[arg(long, default_value_t = 0.5, value_parser = crate::args::non_negative)]
    pub hold_s: f64,
    /// Give up after this long, s.
    #[arg(long, default_value_t = 120.0, value_parser = crate::args::positive)]
    pub timeout_s: f64,
    /// Audio cue output: auto (a PCM player if one is installed, else the terminal bell), player
    /// (`aplay` or `pacat`; fails if neither is on PATH), bell (the terminal
    /// bell), off.
    #[arg(long, value_enum, default_value_t = AudioChoice::Auto)]
    pub audio: AudioChoice,
}

/// Parses `x,y,z` (mm).
pub fn parse_point(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e} (expected x,y,z in mm)"))?;
    match v.as_slice() {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([*x, *y, *z]),
        _ => Err(format!("`{s}`: expected three finite numbers x,y,z (mm)")),
    }
}

/// Runs `spidar init`; returns the summary for standard output, or, when
/// SIGINT or SIGTERM stopped it before home was declared (the force off,
/// the device disarmed, nothing written), [`Interrupted`].
pub fn run(args: &InitArgs) -> anyhow::Result<String> {
    // SIGINT or SIGTERM ends the guidance as the tracker's end would: the
    // library turns the force off and disarms on every exit path.
    interrupt::install();
    let audio = AudioOut::open(args.audio)?;
    let mut view = TerminalView::new(audio, 10.0);
    let mut rig = None;
    let (geometry, mut client, mut receiver) = match args.rig.simulate {
        Some(seed) => {
            let device = args.rig.simulated_device(seed)?;
            // The built-in homing left the end-effector ~5 cm off.
            let r = SimulatedRig::start(device, [45.0, -30.0, 25.0], |c| {
                c.seed = seed;
                c.max_duration = Duration::from_secs_f64(args.timeout_s + 5.0);
            })?;
            let client = r.client().map_err(|e| anyhow!("init: {e}"))?;
            let geometry = r.device.nominal.clone();
            // The rig's own receiver is the one its operator sends to.
            rig = Some(r);
            (geometry, client, None)
        }
        None => {
            let geometry = args.rig.geometry()?;
            let client = args.rig.client().map_err(|e| anyhow!("init: {e}"))?;
            let receiver = args
                .rig
                .receiver()
                .map_err(|e| anyhow!("init: tracker: {e}"))?;
            (geometry, client, Some(receiver))
        }
    };
    let mut config = InitConfig::for_geometry(&geometry);
    if let Some(t) = args.target {
        config.target_room_mm = t;
    }
    config.d_min_mm = args.d_min_mm;
    config.f_max_n = args.f_max_n;
    config.tolerance_mm = args.tolerance_mm;
    config.hold = Duration::from_secs_f64(args.hold_s.max(0.0));
    config.timeout = Duration::from_secs_f64(args.timeout_s.max(0.0));
    config.body_id = args.rig.body;
    let result = if let Some(r) = &mut rig {
        let mut to_operator = r.cues.clone();
        let mut sinks = Tee(vec![&mut view, &mut to_operator]);
        let mut tracker = EndOnInterrupt(&mut r.receiver);
        initialize(&mut client, &mut tracker, &geometry, &config, &mut sinks)
    } else if let Some(rx) = &mut receiver {
        initialize(
            &mut client,
            &mut EndOnInterrupt(rx),
            &geometry,
            &config,
            &mut view,
        )
    } else {
        return Err(InitError::TrackerEnded.into());
    };
    let record = match result {
        Err(InitError::TrackerEnded) if interrupt::raised() => {
            let i = Interrupted::if_received(String::new(), |signal| {
                format!(
                    "init: interrupted by {signal} before home was declared; the force is off and \
                     the device disarmed; {} not written",
                    args.out.display()
                )
            });
            return Err(i.map_or(InitError::TrackerEnded.into(), anyhow::Error::from));
        }
        other => other?,
    };
    record.write(&args.out)?;
    let mut out = format!(
        "home declared {:.2} mm from the target (held {} frames within {} mm for {} s, sd {:.2}/{:.2}/{:.2} mm)\n\
         eq. 6 translation t = [{:.2}, {:.2}, {:.2}] mm\n\
         device position after Home: [{:.3}, {:.3}, {:.3}] mm (device frame)\n\
         wrote {}\n",
        record.home_error_mm,
        record.hold_frames,
        record.tolerance_mm,
        record.hold_s,
        record.home_room_sd_mm[0],
        record.home_room_sd_mm[1],
        record.home_room_sd_mm[2],
        record.room_from_device_translation_mm[0],
        record.room_from_device_translation_mm[1],
        record.room_from_device_translation_mm[2],
        record.device_position_after_home_mm[0],
        record.device_position_after_home_mm[1],
        record.device_position_after_home_mm[2],
        args.out.display()
    );
    if let Some(path) = &args.write_geometry {
        record
            .apply_to(&geometry)
            .write(path)
            .map_err(InitError::from)?;
        out.push_str(&format!(
            "wrote {} (geometry with the measured t)\n",
            path.display()
        ));
    }
    Ok(out)
}
