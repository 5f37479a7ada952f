//! `spidar collect`: lattice data collection on a rig or a simulated one.

use std::path::PathBuf;
use std::time::Duration;

use spidar::data::dataset::Geometry;
use spidar::device::cues::Tee;
use spidar::procedures::collect::{
    collect, load_init_record, summary, CollectConfig, CollectError, Stop,
};
use spidar::sim::lattice::Lattice;
use spidar::sim::operator::SimulatedRig;

use crate::audio::{AudioChoice, AudioOut};
use crate::interrupt::{self, Interrupted};
use crate::rig::RigArgs;
use crate::view::TerminalView;

/// `spidar collect`.
#[derive(Clone, Debug, clap::Args)]
pub struct CollectArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Init record of `spidar init` (TOML): the lattice is centred on the
    /// home it measured, unless --centre is given.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// The session CSV: appended to, one row per cell, flushed as it goes;
    /// an existing file is resumed where it stopped.
    #[arg(long)]
    pub out: PathBuf,
    /// Cells per axis.
    #[arg(long, default_value_t = 13)]
    pub cells: u32,
    /// Edge of the sampled cube, mm.
    #[arg(long, default_value_t = 1000.0, value_parser = crate::args::positive)]
    pub size_mm: f64,
    /// Centre of the cube, room frame, mm, `x,y,z` (default: the home of
    /// --init, else the geometry's frame centre through eq. 6).
    #[arg(long, allow_hyphen_values = true, value_parser = crate::init::parse_point)]
    pub centre: Option<[f64; 3]>,
    /// Stop after this many cells (resume later with the same command).
    #[arg(long)]
    pub max_cells: Option<usize>,
    /// Fail when the tracker sends nothing for this long, s.
    #[arg(long, default_value_t = 5.0, value_parser = crate::args::positive)]
    pub tracker_timeout_s: f64,
    /// Audio cue output (collection plays no beep; the view is visual):
    /// auto (a PCM player if one is installed, else the terminal bell), player
    /// (`aplay` or `pacat`; fails if neither is on PATH), bell (the terminal
    /// bell), off.
    #[arg(long, value_enum, default_value_t = AudioChoice::Off)]
    pub audio: AudioChoice,
}

/// Runs `spidar collect`; returns the summary for standard output, or,
/// when SIGINT or SIGTERM stopped the run (between two frames: motors off,
/// every captured cell on disk), [`Interrupted`] with that summary.
pub fn run(args: &CollectArgs) -> anyhow::Result<String> {
    let audio = AudioOut::open(args.audio)?;
    let mut view = TerminalView::new(audio, 10.0);
    let init = match &args.init {
        Some(p) => Some(load_init_record(p)?),
        None => None,
    };
    let mut config = CollectConfig {
        body_id: args.rig.body,
        tracker_timeout: Duration::from_secs_f64(args.tracker_timeout_s.clamp(0.1, 3600.0)),
        max_cells: args.max_cells,
        // SIGINT or SIGTERM stops between two frames: motors off, the
        // count, how to resume.
        cancel: interrupt::install(),
        ..CollectConfig::default()
    };
    let centre_of = |geometry: &Geometry| -> [f64; 3] {
        args.centre
            .or(init.as_ref().map(|r| r.home_room_mm))
            .unwrap_or_else(|| {
                core::array::from_fn(|k| {
                    geometry.home_mm[k] + geometry.room_from_device_translation_mm[k]
                })
            })
    };
    let report = match args.rig.simulate {
        Some(seed) => {
            let device = args.rig.simulated_device(seed)?;
            let mut rig = SimulatedRig::start(device, [0.0; 3], |c| {
                c.seed = seed;
                c.max_duration = Duration::from_secs(6 * 3600);
            })?;
            let mut client = rig.client().map_err(CollectError::from)?;
            let geometry = rig.device.nominal.clone();
            config.use_geometry(&geometry);
            config.tracker_label = format!("the simulated tracker ({})", rig.receiver.local_addr());
            config.host_clock = rig.host_clock();
            // A busy machine may not run the simulated device's thread for
            // a while: that is not a silent device.
            config.device_timeout = Duration::from_secs(10);
            let lattice = Lattice::new(centre_of(&geometry), args.size_mm, args.cells)
                .map_err(CollectError::from)?;
            let mut to_operator = rig.cues.clone();
            let mut sinks = Tee(vec![&mut view, &mut to_operator]);
            collect(
                &mut client,
                &mut rig.receiver,
                &lattice,
                &config,
                &args.out,
                &mut sinks,
            )?
        }
        None => {
            let geometry = args.rig.geometry().map_err(CollectError::from)?;
            config.use_geometry(&geometry);
            config.tracker_label = format!("the tracker (UDP {})", args.rig.tracker);
            let lattice = Lattice::new(centre_of(&geometry), args.size_mm, args.cells)
                .map_err(CollectError::from)?;
            let mut client = args.rig.client().map_err(CollectError::from)?;
            let mut receiver = args.rig.receiver().map_err(CollectError::from)?;
            collect(
                &mut client,
                &mut receiver,
                &lattice,
                &config,
                &args.out,
                &mut view,
            )?
        }
    };
    if report.stop == Stop::Cancelled {
        if let Some(i) = Interrupted::if_received(summary(&report), |signal| {
            format!("collect: interrupted by {signal}")
        }) {
            return Err(i.into());
        }
    }
    Ok(summary(&report))
}
