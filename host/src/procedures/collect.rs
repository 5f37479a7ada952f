//! Lattice data collection (paper, section 4.3.1; `spidar collect`).
//!
//! A virtual cube of `n^3` cells ([`Lattice`], 13^3 over 1 m in the paper)
//! is shown cell by cell in the paper's order (front plane first, through
//! the x-z plane, then the next plane). The operator moves the end-effector
//! until its marker, as the optical tracker sees it, lies inside the
//! highlighted cell; at that tracker frame the program records the
//! tracker's position and the device's state, and the next cell is shown.
//!
//! 1. The device runs its nominal string model (`SetNominalGeometry`, from
//!    [`CollectConfig::string_model`]) unless it has a calibration blob, and
//!    is armed at pre-tension (no target: the strings stay taut, nothing
//!    pulls). `Limits::heartbeat_timeout_ms` must exceed the tracker's frame
//!    period; a `Heartbeat` goes out every [`CollectConfig::heartbeat_every`],
//!    and a device that disarms itself (a `Disarmed` or `HeartbeatLost`
//!    event, or states that keep saying "disarmed") is re-armed, up to
//!    [`CollectConfig::max_rearms`] times without a capture in between.
//! 2. The state stream runs throughout; each state is stamped with its host
//!    arrival time. Every tracker frame shows [`Cues`](crate::device::cues::Cues): the target cell's
//!    centre and half edge, the marker, its distance to the cell, progress
//!    and the time left (from the rate of the last captures).
//! 3. Capture: the first frame whose **visible** marker lies inside the
//!    target cell (faces included; an occluded frame or a lost datagram
//!    never captures) is paired with the device state nearest to it in host
//!    arrival time (waiting at most [`CollectConfig::max_pairing_gap`] for a
//!    state after it); a pair further apart than that, or a state of a
//!    disarmed device, does not capture: the next frame is tried. The row:
//!    `t_s` = device time (`State::time_us`, s) plus the clock offset below,
//!    `enc0..7` = counts since home, `ots_*` = the tracker position,
//!    `ots_qw..ots_qz` = the body's orientation from the same frame when the
//!    tracker gives its rotation (a DTrack `6d` body does), as the unit
//!    quaternion with `w >= 0` rounded to 1e-6 ([`orientation_of_rotation`](crate::data::observe::orientation_of_rotation);
//!    empty when the source gives a position only, and for a rotation that
//!    is not a proper one, counted in [`CollectReport::improper_rotations`]),
//!    `dev_*` = the device's forward kinematics (device frame), `tension0..7`
//!    = commanded tensions.
//! 4. Each row is appended to the session CSV and flushed to the disk
//!    before the next cell is shown ([`SessionAppender`](crate::data::dataset::SessionAppender)): a crash or a
//!    power loss loses at most the current cell.
//!
//! **Resume.** An existing output file is read strictly; an unterminated
//! last line (a write cut short) is cut off and reported; each row's tracker
//! position marks the cell it lies in as done (a row outside the lattice, or
//! a second row in a cell, is an error naming the line: the file was
//! collected over another volume). Collection goes on with the first cell
//! not done, in order. A file started without the orientation columns (by
//! an older `spidar`) is resumed as it is: its new rows have no
//! orientation either ([`CollectReport::orientations_not_recorded`]).
//!
//! **Device time.** `t_s` must not decrease through the file. The device
//! clock counts from its boot; a resumed session whose device clock is now
//! behind the file's last `t_s` was rebooted (a power loss): `t_s` then
//! continues from the last row (`clock_offset_s` in the report: device time
//! plus that offset), since the interval is unknown. A reboot also loses
//! home: run `spidar init` again before resuming. The clock going back
//! *during* a run is an error.
//!
//! **Home capture.** Each row records the device's home capture (`home`,
//! `State::home_id`) and the time since it (`since_home_s`). A resumed
//! session goes on under the device's capture as it is now: the file's own
//! (no reboot, no `spidar init` between the runs), whose time since home
//! goes on from the file's last row, or a new one (a reboot, a new `Home`,
//! and every `--simulate` run, whose simulated device boots anew), whose id
//! is new and whose time since home starts again. A device that reports
//! the file's last capture but an earlier time since it than that row has
//! an id naming two captures (a boot id drawn twice): refused before the
//! first capture ([`CollectError::HomeIdReused`]).
//!
//! **Reach.** A lattice that reaches outside the anchors' convex hull
//! ([`CollectConfig::reach`]; a planar device's polygon), where the strings
//! cannot hold the end-effector, is refused before the file is opened or
//! the device armed, naming the largest `--size-mm` that fits around its
//! centre ([`CollectError::LatticeBeyondReach`]).
//!
//! The device is disarmed and its stream stopped on every exit.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use spidar_protocol::{Limits, NominalGeometry};

use crate::data::dataset::{DatasetError, Geometry, Session, TornLine};
use crate::data::observe::ROTATION_TOLERANCE;
use crate::device::link::LinkError;
use crate::device::tracker::{HostClock, TrackerError};

mod collection;
mod reach;

pub use crate::sim::lattice::{Lattice, LatticeError};
pub use collection::collect;
pub use reach::Reach;

/// Settings of lattice collection.
#[derive(Clone, Debug)]
pub struct CollectConfig {
    /// DTrack body id of the marker.
    pub body_id: u32,
    /// How the tracker is named in errors (its address).
    pub tracker_label: String,
    /// Fail when the tracker sends nothing for this long.
    pub tracker_timeout: Duration,
    /// Sent to a device that has no calibration blob.
    pub string_model: Option<NominalGeometry>,
    /// Where the strings can hold the end-effector (the anchors' convex
    /// hull, room frame): a lattice reaching outside it is refused before
    /// the device is armed ([`CollectError::LatticeBeyondReach`]). `None`:
    /// not checked.
    pub reach: Option<Reach>,
    /// Safety limits: pre-tension while armed; the heartbeat timeout must
    /// exceed `heartbeat_every` (and the tracker's frame period).
    pub limits: Limits,
    /// Send a heartbeat this often.
    pub heartbeat_every: Duration,
    /// Times a device that disarmed itself is armed again without a capture
    /// in between before it is an error (a long session may see a few in
    /// all: a string gone slack in a fast move, a late heartbeat).
    pub max_rearms: u32,
    /// Device state frames per control-loop iterations.
    pub decimation: u16,
    /// A capture reads the device state at the tracker frame's capture time
    /// between two states at most this far apart in device time (a gap in
    /// the stream is not bridged).
    pub max_pairing_gap: Duration,
    /// Fail when the device sends no state for this long.
    pub device_timeout: Duration,
    /// The time left is estimated from this many recent captures.
    pub eta_window: usize,
    /// Stop cleanly after this many captures in this run.
    pub max_cells: Option<usize>,
    /// Stop cleanly when this becomes true.
    pub cancel: Option<Arc<AtomicBool>>,
    /// The clock arrivals are stamped with for the clock map (the wall
    /// clock; a simulated rig's own, [`crate::sim::operator::SimulatedRig::host_clock`]).
    pub host_clock: HostClock,
}

impl Default for CollectConfig {
    fn default() -> Self {
        CollectConfig {
            body_id: 0,
            tracker_label: "the tracker".into(),
            tracker_timeout: Duration::from_secs(2),
            string_model: None,
            reach: None,
            limits: Limits {
                pre_tension_n: 1.0,
                max_tension_n: 20.0,
                heartbeat_timeout_ms: 100,
            },
            heartbeat_every: Duration::from_millis(25),
            max_rearms: 5,
            decimation: 2,
            max_pairing_gap: Duration::from_millis(20),
            device_timeout: Duration::from_secs(1),
            eta_window: 20,
            max_cells: None,
            cancel: None,
            host_clock: HostClock::Wall,
        }
    }
}

impl CollectConfig {
    /// Defaults, with the nominal string model of `geometry` and the
    /// reach of its anchors.
    pub fn for_geometry(geometry: &Geometry) -> CollectConfig {
        let mut config = CollectConfig::default();
        config.use_geometry(geometry);
        config
    }

    /// Takes the nominal string model of `geometry` and the reach of its
    /// anchors ([`CollectConfig::string_model`], [`CollectConfig::reach`]).
    pub fn use_geometry(&mut self, geometry: &Geometry) {
        self.string_model = Some(geometry.string_model());
        self.reach = Some(Reach::of(geometry));
    }

    /// Refuses a lattice that reaches outside [`CollectConfig::reach`].
    fn check_reach(&self, lattice: &Lattice) -> Result<(), CollectError> {
        let Some(reach) = &self.reach else {
            return Ok(());
        };
        let largest_mm = reach.largest_cube_mm(lattice.centre_mm());
        if lattice.size_mm() <= largest_mm {
            return Ok(());
        }
        Err(CollectError::LatticeBeyondReach {
            lattice: describe(lattice),
            size_mm: lattice.size_mm(),
            // Whole tenths of a millimetre, down: a size that fits.
            largest_mm: (largest_mm * 10.0).floor() / 10.0,
            planar: reach.is_planar(),
        })
    }

    fn validate(&self) -> Result<(), CollectError> {
        let bad = |field: &'static str, problem: String| {
            Err(CollectError::Config(crate::ConfigError::new(
                field, problem,
            )))
        };
        let hb = Duration::from_millis(u64::from(self.limits.heartbeat_timeout_ms));
        if self.heartbeat_every.is_zero() || self.heartbeat_every >= hb {
            return bad(
                "heartbeat_every",
                format!(
                    "{} ms must be above 0 and below the device's heartbeat timeout ({} ms)",
                    self.heartbeat_every.as_millis(),
                    hb.as_millis()
                ),
            );
        }
        if self.tracker_timeout.is_zero() {
            return bad("tracker_timeout", "must be positive".into());
        }
        if self.device_timeout.is_zero() {
            return bad("device_timeout", "must be positive".into());
        }
        if self.decimation == 0 {
            return bad("decimation", "must be at least 1".into());
        }
        if self.eta_window < 2 {
            return bad(
                "eta_window",
                format!(
                    "{} captures cannot give a rate (2 or more)",
                    self.eta_window
                ),
            );
        }
        Ok(())
    }
}

/// Why collection stopped without an error.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    /// Every cell is done.
    Complete,
    /// `max_cells` captures were taken.
    MaxCells,
    /// The cancel flag was raised.
    Cancelled,
}

/// What a run of [`collect`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct CollectReport {
    pub path: PathBuf,
    /// Cells in the lattice.
    pub total: usize,
    /// Cells already done in the file when the run started.
    pub resumed_from: usize,
    /// Cells captured in this run.
    pub captured: usize,
    /// Cells done now.
    pub done: usize,
    pub stop: Stop,
    pub elapsed: Duration,
    /// The unterminated last line cut off the file when it was opened.
    pub torn: Option<TornLine>,
    /// Added to the device time to make `t_s` (non-zero after a reboot).
    pub clock_offset_s: f64,
    /// Tracker frames seen, and of those with the marker occluded.
    pub frames: u64,
    pub occluded: u64,
    /// Frames in the target cell that did not capture (no device state
    /// close enough in time, or the device disarmed).
    pub unpaired: u64,
    /// Times the device was armed again after it disarmed itself.
    pub rearms: u32,
    /// Rows captured in this run with the body's orientation.
    pub oriented: u64,
    /// Rows captured in this run whose tracker rotation was not a proper
    /// rotation (a value not finite, a determinant off 1 or axes not
    /// orthonormal by more than [`ROTATION_TOLERANCE`]): recorded without an
    /// orientation.
    pub improper_rotations: u64,
    /// The file has the orientation columns (false: it was started without
    /// them, by an older `spidar`, and is resumed as it is).
    pub orientation_columns: bool,
    /// Rows captured in this run whose orientation the tracker gave but the
    /// file, having no orientation columns, could not take.
    pub orientations_not_recorded: u64,
}

/// Why collection failed (the device is disarmed in every case; the rows
/// written stay in the file).
#[derive(Debug, thiserror::Error)]
pub enum CollectError {
    #[error("collect: {0}")]
    Config(#[from] crate::ConfigError),
    #[error("collect: {0}")]
    Lattice(#[from] LatticeError),
    #[error("collect: {0}")]
    Link(#[from] LinkError),
    #[error("collect: tracker: {0}")]
    Tracker(#[from] TrackerError),
    #[error("collect: {0}")]
    Dataset(#[from] DatasetError),
    #[error(
        "collect: {tracker} sent nothing for {seconds:.1} s (is DTrack sending to this host and port?)"
    )]
    TrackerSilent { tracker: String, seconds: f64 },
    #[error("collect: {tracker}: the tracker source ended")]
    TrackerEnded { tracker: String },
    #[error("collect: serial port {port}: the device sent no state for {seconds:.1} s")]
    DeviceSilent { port: String, seconds: f64 },
    #[error("collect: the device keeps disarming itself ({events} times without a capture; the last: {last}): {advice}")]
    KeepsDisarming {
        events: u32,
        last: String,
        /// What happened and what to do, for the faults seen and the rig.
        advice: String,
    },
    #[error(
        "collect: serial port {port}: the device clock went back from {previous_s} s to {now_s} s during the run (a reboot? home is lost: run `spidar init`, then collect again to resume)"
    )]
    ClockWentBack {
        port: String,
        previous_s: f64,
        now_s: f64,
    },
    #[error(
        "collect: {}: line {line} was captured {file_s} s after home capture {home}, and the device now reports the same capture only {device_s} s after it: its id names another capture (a boot id drawn twice); nothing was captured: run `spidar init` (a new home capture has an id of its own), then collect again to resume",
        file.display()
    )]
    HomeIdReused {
        file: PathBuf,
        line: u64,
        home: u64,
        file_s: f64,
        device_s: f64,
    },
    #[error("collect: {}: line {line}: the row has no tracker position (not a collected session?)", file.display())]
    RowWithoutTracker { file: PathBuf, line: u64 },
    #[error(
        "collect: {}: line {line}: the tracker position [{:.3}, {:.3}, {:.3}] mm lies outside the lattice ({lattice}): was the file collected over another volume (--centre, --size-mm, --cells)?",
        file.display(), position[0], position[1], position[2]
    )]
    RowOutsideLattice {
        file: PathBuf,
        line: u64,
        position: [f64; 3],
        lattice: String,
    },
    #[error(
        "collect: {}: line {line}: cell {cell:?} was already captured on line {first_line} (was the file collected with another lattice?)",
        file.display()
    )]
    CellTwice {
        file: PathBuf,
        line: u64,
        cell: [u32; 3],
        first_line: u64,
    },
    #[error("collect: {}: {message}", file.display())]
    InitRecord { file: PathBuf, message: String },
    #[error("collect: {}", beyond_reach(lattice, *size_mm, *largest_mm, *planar))]
    LatticeBeyondReach {
        /// [`describe`] of the lattice.
        lattice: String,
        size_mm: f64,
        /// The largest edge that fits around the lattice's centre (not
        /// above 0: the centre itself is outside).
        largest_mm: f64,
        planar: bool,
    },
}

fn beyond_reach(lattice: &str, size_mm: f64, largest_mm: f64, planar: bool) -> String {
    let hull = if planar {
        "the anchors' polygon (the strings' convex hull in their plane)"
    } else {
        "the anchors' convex hull"
    };
    let why = "(outside it the strings all pull one way and cannot hold the end-effector)";
    if largest_mm > 0.0 {
        format!(
            "the lattice ({lattice}) reaches outside {hull} {why}: --size-mm {size_mm} is too large; the largest that fits around this centre is --size-mm {largest_mm:.1} (or move --centre)"
        )
    } else {
        format!(
            "the lattice ({lattice}) is centred outside {hull} {why}: no --size-mm fits around it; move --centre (or check --init, the geometry's home and room translation)"
        )
    }
}

/// What a device that keeps disarming itself with `faults` means, and what
/// to do (a simulated rig has no power switch or init to run again).
pub fn disarm_advice(faults: u16, simulated: bool) -> String {
    use spidar_protocol::Faults;
    let f = Faults(faults);
    let resume = if simulated {
        "the captured cells are saved; run the same command again to resume"
    } else {
        "the captured cells are saved; fix the cause, then run the same command to resume"
    };
    if f.contains(Faults::KINEMATICS) {
        format!(
            "the device cannot place the end-effector from its string lengths here (fault 0x0004: forward kinematics failed, or a string reads longer than the position allows, i.e. slack); check the strings near the highlighted cell; {resume}"
        )
    } else if f.contains(Faults::HEARTBEAT_LOST) {
        format!("the device stopped hearing from this host (heartbeat lost): is the host overloaded or the link unplugged? {resume}")
    } else if f.contains(Faults::ENCODER) {
        format!("an encoder count jumped: check the encoder cables; {resume}")
    } else if simulated {
        resume.to_string()
    } else {
        format!("after a reboot, run `spidar init` to declare home first; {resume}")
    }
}

/// One-line description of a lattice (for messages).
pub fn describe(lattice: &Lattice) -> String {
    let c = lattice.centre_mm();
    format!(
        "{n}^3 cells of {e:.1} mm over {s} mm centred on [{:.1}, {:.1}, {:.1}] mm",
        c[0],
        c[1],
        c[2],
        n = lattice.cells_per_axis(),
        e = lattice.cell_mm(),
        s = lattice.size_mm(),
    )
}

/// The line (1-based, header = 1) of the row that captured each cell, by
/// position in [`Lattice::order`]; `None`: not done. Each row lies in its
/// cell; a row on a shared face counts for the first of its cells (in
/// order) not yet done.
pub fn done_cells(
    lattice: &Lattice,
    session: &Session,
    file: &Path,
) -> Result<Vec<Option<u64>>, CollectError> {
    let mut done: Vec<Option<u64>> = vec![None; lattice.len()];
    for (row, s) in session.samples.iter().enumerate() {
        let line = row as u64 + 2;
        let p = s.tracker.ok_or_else(|| CollectError::RowWithoutTracker {
            file: file.to_path_buf(),
            line,
        })?;
        let mut candidates: Vec<(usize, [u32; 3])> = lattice
            .cells_containing(&p)
            .into_iter()
            .filter_map(|c| lattice.index_of(c).map(|i| (i, c)))
            .collect();
        candidates.sort_unstable();
        let Some(&(first_index, first_cell)) = candidates.first() else {
            return Err(CollectError::RowOutsideLattice {
                file: file.to_path_buf(),
                line,
                position: p,
                lattice: describe(lattice),
            });
        };
        match candidates.iter().find(|(i, _)| done[*i].is_none()) {
            Some(&(i, _)) => done[i] = Some(line),
            None => {
                return Err(CollectError::CellTwice {
                    file: file.to_path_buf(),
                    line,
                    cell: first_cell,
                    first_line: done[first_index].unwrap_or(0),
                })
            }
        }
    }
    Ok(done)
}

/// Reads an init record (`spidar init --out`).
pub fn load_init_record(path: &Path) -> Result<super::init::InitRecord, CollectError> {
    let text = std::fs::read_to_string(path).map_err(|e| CollectError::InitRecord {
        file: path.to_path_buf(),
        message: format!("cannot read: {e}"),
    })?;
    toml::from_str(&text).map_err(|e| CollectError::InitRecord {
        file: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })
}

/// The summary `spidar collect` prints.
pub fn summary(report: &CollectReport) -> String {
    let mut out = String::new();
    if let Some(t) = &report.torn {
        out.push_str(&format!(
            "{}: line {}: cut off an unterminated last line (a write cut short; its cell was collected again): `{}`\n",
            report.path.display(),
            t.line,
            t.text
        ));
    }
    if report.clock_offset_s != 0.0 {
        out.push_str(&format!(
            "the device clock restarted (a reboot): t_s continues from the last row (device time + {:.3} s)\n",
            report.clock_offset_s
        ));
    }
    if report.improper_rotations > 0 {
        out.push_str(&format!(
            "{} captured rows had a tracker rotation that is not a proper rotation (determinant or axes off by more than {}): recorded without the body's orientation\n",
            report.improper_rotations, ROTATION_TOLERANCE
        ));
    }
    if report.orientations_not_recorded > 0 {
        out.push_str(&format!(
            "{}: started without orientation columns (ots_qw..ots_qz): the body's orientation of {} captured rows is not recorded; collect into a new file to record it\n",
            report.path.display(),
            report.orientations_not_recorded
        ));
    }
    out.push_str(&format!(
        "captured {} cells in {:.1} s (resumed from {} of {}); {}/{} done{}\n\
         tracker frames {} ({} occluded), captures deferred for want of a device state {}, re-arms {}; rows with the body's orientation {}\n\
         wrote {}\n",
        report.captured,
        report.elapsed.as_secs_f64(),
        report.resumed_from,
        report.total,
        report.done,
        report.total,
        match report.stop {
            Stop::Complete => String::from(": complete"),
            Stop::MaxCells => String::from(": stopped after --max-cells; run again to resume"),
            Stop::Cancelled => String::from(
                ": interrupted; the motors are off and every captured cell is on disk; run the same command again to resume"
            ),
        },
        report.frames,
        report.occluded,
        report.unpaired,
        report.rearms,
        report.oriented,
        report.path.display()
    ));
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::dataset::Sample;
    use crate::data::observe::orientation_of_rotation;

    fn row(p: [f64; 3]) -> Sample {
        Sample {
            t_s: 0.0,
            counts: [0; 8],
            tracker: Some(p),
            orientation: None,
            legacy: None,
            tension_n: None,
            since_home_s: None,
            home: None,
        }
    }

    #[test]
    fn done_cells_come_from_the_rows_tracker_positions() {
        let lattice = Lattice::new([0.0, 0.0, 0.0], 300.0, 3).unwrap();
        let file = Path::new("s.csv");
        let order = lattice.order();
        // Cells 0, 1 and 2 of the order, each somewhere inside.
        let mut session = Session {
            strings: 8,
            samples: vec![
                row([-120.0, -140.0, -101.0]),
                row([10.0, -60.0, -149.0]),
                row([130.0, -100.0, -100.0]),
            ],
            ignored_columns: Vec::new(),
            unread_columns: Vec::new(),
            tracker_z: true,
        };
        let done = done_cells(&lattice, &session, file).unwrap();
        assert_eq!(&done[..4], &[Some(2), Some(3), Some(4), None]);
        assert_eq!(order[3], [2, 0, 1]);
        // On the face shared by cells 3 ([2,0,1]) and 4 ([1,0,1]): the first
        // not done, then the other.
        session.samples.push(row([50.0, -100.0, 0.0]));
        session.samples.push(row([50.0, -100.0, 0.0]));
        let done = done_cells(&lattice, &session, file).unwrap();
        assert_eq!(&done[3..6], &[Some(5), Some(6), None]);
        // A third row there: that cell was done twice.
        session.samples.push(row([50.0, -100.0, 0.0]));
        let e = done_cells(&lattice, &session, file).unwrap_err();
        assert!(
            matches!(
                e,
                CollectError::CellTwice {
                    line: 7,
                    first_line: 5,
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("s.csv: line 7"), "{e}");
        // Outside the cube, or without a tracker position.
        session.samples.truncate(5);
        session.samples.push(row([0.0, 0.0, 151.0]));
        let e = done_cells(&lattice, &session, file).unwrap_err();
        assert!(
            matches!(e, CollectError::RowOutsideLattice { line: 7, .. }),
            "{e}"
        );
        session.samples.pop();
        session.samples.push(Sample {
            tracker: None,
            ..row([0.0; 3])
        });
        let e = done_cells(&lattice, &session, file).unwrap_err();
        assert!(
            matches!(e, CollectError::RowWithoutTracker { line: 7, .. }),
            "{e}"
        );
    }

    /// `v` turned by the quaternion `q = [w, x, y, z]`.
    fn turn(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
        let [w, x, y, z] = q;
        let u = [x, y, z];
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        // v + 2 w (u x v) + 2 u x (u x v)
        let uv = cross(u, v);
        let uuv = cross(u, uv);
        core::array::from_fn(|k| v[k] + 2.0 * w * uv[k] + 2.0 * uuv[k])
    }

    /// `r v` for a row-major `r`.
    fn apply(r: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
        core::array::from_fn(|k| r[k][0] * v[0] + r[k][1] * v[1] + r[k][2] * v[2])
    }

    fn assert_same_rotation(q: [f64; 4], r: &[[f64; 3]; 3], tolerance: f64) {
        for v in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] {
            let (a, b) = (turn(q, v), apply(r, v));
            assert!(
                a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= tolerance),
                "{q:?} turns {v:?} to {a:?}, the matrix {r:?} to {b:?}"
            );
        }
    }

    #[test]
    fn a_rotation_s_orientation_is_its_unit_quaternion_with_w_not_negative() {
        use nalgebra::{Unit, UnitQuaternion, Vector3};
        let h = std::f64::consts::FRAC_1_SQRT_2;
        // Row-major: a quarter turn about z takes x to y.
        let quarter_z = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(
            orientation_of_rotation(&quarter_z),
            Some([h, 0.0, 0.0, h].map(|v| (v * 1e6).round() / 1e6))
        );
        assert_eq!(
            orientation_of_rotation(&crate::device::tracker::dtrack::IDENTITY),
            Some([1.0, 0.0, 0.0, 0.0])
        );
        for (axis, angle) in [
            ([1.0, 0.0, 0.0], std::f64::consts::PI),
            ([0.0, 1.0, 0.0], std::f64::consts::PI),
            ([0.0, 0.0, 1.0], -std::f64::consts::PI),
            ([1.0, 1.0, 0.0], std::f64::consts::PI),
            ([1.0, -2.0, 0.5], 2.5),
            ([0.2, 0.1, -1.0], -1.2),
            ([0.3, 0.4, 0.5], 3.1),
            ([-1.0, 0.0, 2.0], 1e-9),
        ] {
            let q =
                UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::from(axis)), angle);
            let m = q.to_rotation_matrix();
            let r: [[f64; 3]; 3] = core::array::from_fn(|i| core::array::from_fn(|j| m[(i, j)]));
            let got = orientation_of_rotation(&r).expect("a rotation");
            assert!(got[0] >= 0.0, "{got:?}");
            let norm = got.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!((norm - 1.0).abs() < 2e-6, "{norm}");
            // Rounded to 1e-6.
            assert!(got
                .iter()
                .all(|v| (v * 1e6 - (v * 1e6).round()).abs() < 1e-6));
            assert_same_rotation(got, &r, 1e-5);
            // As a tracker writes it: six decimals, so not quite orthonormal.
            let written = r.map(|row| row.map(|v| (v * 1e6).round() / 1e6));
            let again = orientation_of_rotation(&written).expect("a rotation to six decimals");
            assert_same_rotation(again, &r, 1e-5);
        }
    }

    #[test]
    fn a_matrix_that_is_not_a_proper_rotation_has_no_orientation() {
        let identity = crate::device::tracker::dtrack::IDENTITY;
        let mut reflection = identity;
        reflection[2][2] = -1.0;
        let scaled = identity.map(|row| row.map(|v| 1.01 * v));
        let mut sheared = identity;
        sheared[0][1] = 0.01;
        let mut not_finite = identity;
        not_finite[1][1] = f64::NAN;
        let mut infinite = identity;
        infinite[0][2] = f64::INFINITY;
        for r in [
            reflection,
            scaled,
            sheared,
            not_finite,
            infinite,
            [[0.0; 3]; 3],
            identity.map(|row| row.map(|v| -v)),
        ] {
            assert_eq!(orientation_of_rotation(&r), None, "{r:?}");
        }
    }

    #[test]
    fn the_orientation_of_a_dtrack_body_turns_as_its_column_wise_matrix() {
        // The DTrack2 manual's example body: b0..b8 given column-wise.
        let datagram = b"fr 21753\r\n6d 1 [0 1.000][326.848 -187.216 109.503 -160.4704 -3.6963 -7.0913][-0.940508 -0.339238 0.019025 0.333599 -0.932599 -0.137735 0.064467 -0.123194 0.990286]\r\n";
        let frame = crate::device::tracker::dtrack::parse_datagram(datagram).unwrap();
        let r = frame.bodies[0].rotation.unwrap();
        let q = orientation_of_rotation(&r).expect("the manual's rotation");
        assert_same_rotation(q, &r, 1e-5);
        // The first column is the image of the body's x axis.
        let x = turn(q, [1.0, 0.0, 0.0]);
        for (a, b) in x.iter().zip([-0.940508, -0.339238, 0.019025]) {
            assert!((a - b).abs() < 1e-5, "{x:?}");
        }
    }

    #[test]
    fn a_heartbeat_slower_than_the_device_timeout_is_refused() {
        let config = CollectConfig {
            heartbeat_every: Duration::from_millis(150),
            ..CollectConfig::default()
        };
        let e = config.validate().unwrap_err();
        assert!(e.to_string().contains("heartbeat_every"), "{e}");
    }
}
