//! `spidar simulate`.

use std::path::PathBuf;

use spidar::sim::{Physics, SessionPath, SimulateRequest};

/// `spidar simulate`: write a simulated device's nominal geometry, one session
/// and the truth.
#[derive(Clone, Debug, clap::Args)]
pub struct SimulateArgs {
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Device seed: the same seed gives the same device (as-built errors)
    /// whatever the session kind, so a lattice and a random session of one
    /// device are two runs with the same seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Simulator configuration TOML (every key optional).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// A named device of the independent simulator instead of `--config`:
    /// `wall-robot` (a planar 4-cable wall robot: 2 m x 1.5 m frame, cable
    /// exits tens of mm off its corners, 30 mm spools, a 100 mm carriage
    /// that yaws, a tracker clock 1.8 s ahead; its sessions are streams);
    /// `hangprinter` (a 3-D 4-line robot whose lines run through pulley
    /// blocks 2, 2, 2 and 4 times, 75 mm spools that build up in layers,
    /// anchors tens of mm off the tape's, a camera of 0.8 mm that places one
    /// pose in five 3 mm further off; static poses:
    /// `--kind random --points 25`). The presets are configuration files in
    /// `host/src/sim/physics/presets/`.
    #[arg(long)]
    pub preset: Option<String>,
    /// Path of the end-effector: the paper's lattice, random test points,
    /// or (independent simulator) a stream at a tracker's rate over the
    /// training part of the workspace (`stream`) or the whole of it
    /// (`wide-stream`), `[stream]` of the configuration.
    #[arg(long, value_enum, default_value_t = KindArg::Lattice)]
    pub kind: KindArg,
    /// Number of captures of a random session or a stream (default:
    /// `random.points`, `stream.rows`).
    #[arg(long)]
    pub points: Option<usize>,
    /// Injected effect (repeatable), `KIND:STRING:KEY=VALUE,...` with STRING
    /// an index or `*`. Model physics: offset (mm), scale (relative), winding
    /// (power, mm_per_rad_pow), eccentricity (sin_mm, cos_mm), elasticity
    /// (per_newton), backlash (half_width_mm), drift (mm_per_s), slip (at_s,
    /// mm), speed (latency_s), anchor (dx, dy, dz, mm), and
    /// `tracker_scale:relative=VALUE` (no string); e.g.
    /// `offset:3:mm=10`, `slip:2:at_s=2000,mm=5`. Independent physics
    /// (`NAME[:KEY=VALUE,...]`): drift-all, drift-each (`ppm_per_h`,
    /// `spread_ppm_per_h`: each string its own creep), frame-flex,
    /// marker-offset, slip, heavy-string, latency (`ms`, `string`: one
    /// string's index, or every string without it); e.g.
    /// `latency:string=2,ms=6`.
    #[arg(long = "effect", value_name = "SPEC")]
    pub effects: Vec<String>,
    /// File stem of the session CSV (default: `lattice` or `random`).
    #[arg(long)]
    pub name: Option<String>,
    /// Session seed (default: the device seed + 1 for lattice, + 2 for
    /// random, + 3 for stream, + 4 for wide-stream).
    #[arg(long)]
    pub session_seed: Option<u64>,
    /// Which simulator: `model` (the calibration model's own equations) or
    /// `independent` (other physics, `host/src/sim/physics`: layered spools, guide
    /// pulleys, elastic sagging strings, frame flex, an offset marker; its
    /// own `--config` keys and `--effect` names).
    #[arg(long, value_enum, default_value_t = PhysicsArg::Model)]
    pub physics: PhysicsArg,
}

/// `--physics`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PhysicsArg {
    Model,
    Independent,
}

/// `--kind`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum KindArg {
    Lattice,
    Random,
    Stream,
    WideStream,
}

impl SimulateArgs {
    /// What the library is asked to simulate.
    pub fn request(&self) -> SimulateRequest {
        SimulateRequest {
            out: self.out.clone(),
            seed: self.seed,
            config: self.config.clone(),
            preset: self.preset.clone(),
            kind: match self.kind {
                KindArg::Lattice => SessionPath::Lattice,
                KindArg::Random => SessionPath::Random,
                KindArg::Stream => SessionPath::Stream,
                KindArg::WideStream => SessionPath::WideStream,
            },
            points: self.points,
            effects: self.effects.clone(),
            name: self.name.clone(),
            session_seed: self.session_seed,
            physics: match self.physics {
                PhysicsArg::Model => Physics::Model,
                PhysicsArg::Independent => Physics::Independent,
            },
        }
    }
}

/// Runs `spidar simulate`; returns what to print.
pub fn run(args: &SimulateArgs) -> anyhow::Result<String> {
    Ok(spidar::sim::run_simulate(&args.request())?.to_string())
}
