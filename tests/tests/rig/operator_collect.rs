//! Lattice collection end to end: a virtual device whose end-effector is in
//! a simulated operator's hand, the operator reaching for the cell the
//! procedure shows, a simulated DTrack2 tracker on loopback (noise,
//! occlusion, datagram loss), and `spidar::procedures::collect::collect`
//! between them over the serial link, writing the session CSV.

use spidar_tests::eventually;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use spidar::data::dataset::{Session, SessionAppender};
use spidar::device::cues::{CueSink, Cues, SharedCues};
use spidar::device::link::{Client, ClientOptions};
use spidar::device::tracker::{DtrackReceiver, ReceiverConfig};
use spidar::procedures::collect::{
    collect, summary, CollectConfig, CollectError, CollectReport, Lattice, Stop,
};
use spidar::sim::operator::{HandSample, SimulatedRig};
use spidar::sim::virtual_device::{spawn, Hand, Pace, Plant, Trajectory, VirtualDeviceConfig};
use spidar::sim::{SimConfig, SimulatedDevice};
use spidar_core::kinematics::{forward_kinematics, FkConfig};

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn temp_csv(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spidar-collect-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    let _ = std::fs::remove_file(&path);
    path
}

/// Records every cue and passes it on to the simulated operator; raises
/// `cancel` once `cancel_at` cells are done.
struct Recorder {
    to_operator: SharedCues,
    shown: Vec<Cues>,
    cancel: Option<(Arc<AtomicBool>, usize)>,
}

impl Recorder {
    fn new(cues: &SharedCues) -> Recorder {
        Recorder {
            to_operator: cues.clone(),
            shown: Vec::new(),
            cancel: None,
        }
    }
}

impl CueSink for Recorder {
    fn show(&mut self, cues: &Cues) {
        self.to_operator.show(cues);
        if let (Some((flag, at)), Some(p)) = (&self.cancel, cues.progress) {
            if p.done >= *at {
                flag.store(true, Ordering::SeqCst);
            }
        }
        self.shown.push(cues.clone());
    }
}

/// A device as built (seed 3) with the end-effector at its true home, a
/// steady operator and a tracker with some occlusion and loss.
fn rig(seed: u64) -> SimulatedRig {
    let device = SimulatedDevice::new(&SimConfig::default(), 3).unwrap();
    SimulatedRig::start(device, [0.0; 3], |c| {
        c.seed = seed;
        c.occlusion = 0.05;
        c.loss = 0.02;
        c.max_duration = Duration::from_secs(20);
    })
    .unwrap()
}

/// 3^3 cells over 300 mm around the nominal frame centre.
fn small_lattice(rig: &SimulatedRig) -> Lattice {
    Lattice::new(rig.device.volume_centre_room(), 300.0, 3).unwrap()
}

fn config(rig: &SimulatedRig) -> CollectConfig {
    CollectConfig {
        tracker_label: "the simulated tracker".into(),
        host_clock: rig.host_clock(),
        // A machine busy with other work may leave the simulated device's
        // thread unscheduled for a while: that is not a silent device.
        device_timeout: Duration::from_secs(10),
        tracker_timeout: Duration::from_secs(10),
        ..CollectConfig::for_geometry(&rig.device.nominal)
    }
}

/// A collection on `rig` into `path` (what the operator is shown recorded
/// as in every run).
fn collect_on(
    rig: &mut SimulatedRig,
    client: &mut Client,
    lattice: &Lattice,
    cfg: &CollectConfig,
    path: &std::path::Path,
) -> Result<CollectReport, CollectError> {
    collect(
        client,
        &mut rig.receiver,
        lattice,
        cfg,
        path,
        &mut Recorder::new(&rig.cues),
    )
}

/// The report of a collection that must complete its part (the rig's
/// state in the message when it fails).
fn collected(
    rig: &mut SimulatedRig,
    client: &mut Client,
    lattice: &Lattice,
    cfg: &CollectConfig,
    path: &std::path::Path,
) -> CollectReport {
    let result = collect_on(rig, client, lattice, cfg, path);
    result.unwrap_or_else(|e| panic!("collect: {e}; {}", rig.describe()))
}

/// The error of a collection that must fail.
fn refused(
    rig: &mut SimulatedRig,
    client: &mut Client,
    lattice: &Lattice,
    cfg: &CollectConfig,
    path: &std::path::Path,
) -> CollectError {
    collect_on(rig, client, lattice, cfg, path).unwrap_err()
}

/// Every row lies in its cell, in lattice order, each cell once; time never
/// goes back.
fn assert_rows_in_order(lattice: &Lattice, session: &Session) {
    let order = lattice.order();
    assert_eq!(session.samples.len(), order.len());
    for (k, (s, cell)) in session.samples.iter().zip(&order).enumerate() {
        let p = s.tracker.expect("a tracker position");
        assert!(
            lattice.contains(*cell, &p),
            "row {k}: {p:?} is not in cell {cell:?} {:?}",
            lattice.bounds(*cell)
        );
        assert!(s.legacy.is_some() && s.tension_n.is_some());
        if k > 0 {
            assert!(s.t_s >= session.samples[k - 1].t_s, "row {k}");
        }
    }
}

/// The truth a row's tracker columns came from: the hand sample nearest to
/// it in the room.
fn truth_of<'a>(history: &'a [HandSample], p: &[f64; 3]) -> &'a HandSample {
    history
        .iter()
        .min_by(|a, b| distance(&a.room_mm, p).total_cmp(&distance(&b.room_mm, p)))
        .unwrap()
}

/// Least-squares `y = a + b x + c x^2`: the fitted values and the slope at 0.
#[allow(clippy::needless_range_loop)]
fn quadratic_fit(x: &[f64], y: &[f64]) -> (Vec<f64>, f64) {
    let mut m = [[0.0f64; 4]; 3];
    for (&xi, &yi) in x.iter().zip(y) {
        let basis = [1.0, xi, xi * xi];
        for r in 0..3 {
            for c in 0..3 {
                m[r][c] += basis[r] * basis[c];
            }
            m[r][3] += basis[r] * yi;
        }
    }
    for p in 0..3 {
        let pivot = m[p][p];
        for c in p..4 {
            m[p][c] /= pivot;
        }
        for r in 0..3 {
            if r != p {
                let f = m[r][p];
                for c in p..4 {
                    m[r][c] -= f * m[p][c];
                }
            }
        }
    }
    let (a, b, c) = (m[0][3], m[1][3], m[2][3]);
    (x.iter().map(|xi| a + b * xi + c * xi * xi).collect(), b)
}

fn disarmed(rig: &SimulatedRig) -> bool {
    eventually(|| !rig.virtual_device.status().armed)
}

#[test]
fn the_operator_fills_a_small_lattice_cell_by_cell_and_the_rows_are_true() {
    let t0 = Instant::now();
    let mut rig = rig(11);
    let lattice = small_lattice(&rig);
    let path = temp_csv("full.csv");
    let mut client = rig.client().unwrap();
    let mut recorder = Recorder::new(&rig.cues);
    let cfg_here = config(&rig);
    let report = collect(
        &mut client,
        &mut rig.receiver,
        &lattice,
        &cfg_here,
        &path,
        &mut recorder,
    )
    .expect("collect");
    let history = rig.operator.history();
    eprintln!("{report:?} in {:.1} s", t0.elapsed().as_secs_f64());
    assert_eq!(report.stop, Stop::Complete);
    assert_eq!((report.captured, report.done, report.total), (27, 27, 27));
    assert_eq!(report.resumed_from, 0);
    assert!(report.torn.is_none());
    assert!(report.occluded > 0, "the tracker occluded some frames");
    assert!(disarmed(&rig), "the motors are off afterwards");

    // The file reads back with the one reader, rows in lattice order.
    let session = Session::load(&path).unwrap();
    assert_rows_in_order(&lattice, &session);
    // The simulated tracker's `6d` body has the identity rotation: every
    // row records it as the body's orientation.
    assert!(report.orientation_columns);
    assert_eq!((report.oriented, report.improper_rotations), (27, 0));
    assert!(session
        .samples
        .iter()
        .all(|s| s.orientation == Some([1.0, 0.0, 0.0, 0.0])));
    // Every row names its home capture (one: the device homed once) and
    // the time since it, which goes on with the device's clock.
    let home = session.samples[0].home;
    assert!(home.is_some());
    for w in session.samples.windows(2) {
        assert_eq!(w[1].home, home);
        let (a, b) = (w[0].since_home_s.unwrap(), w[1].since_home_s.unwrap());
        assert!(
            ((b - a) - (w[1].t_s - w[0].t_s)).abs() < 1e-6,
            "since_home_s {a} -> {b} against t_s {} -> {}",
            w[0].t_s,
            w[1].t_s
        );
    }

    // Tracker columns: the true marker plus the tracker's noise.
    let truths: Vec<&HandSample> = session
        .samples
        .iter()
        .map(|s| truth_of(&history, &s.tracker.unwrap()))
        .collect();
    let worst_tracker = session
        .samples
        .iter()
        .zip(&truths)
        .map(|(s, t)| distance(&t.room_mm, &s.tracker.unwrap()))
        .fold(0.0, f64::max);
    assert!(worst_tracker < 1.0, "{worst_tracker} mm");
    assert_legacy_columns_are_the_nominal_fk(&rig, &session);
    assert_counts_are_the_tracker_frames_instant(&rig, &session, &truths);
    assert_the_operator_saw_each_cell_in_turn(&recorder, &lattice);
}

/// Device columns, one state: `dev_*` is the forward kinematics of the
/// row's counts on the nominal model.
fn assert_legacy_columns_are_the_nominal_fk(rig: &SimulatedRig, session: &Session) {
    let nominal = &rig.device.nominal;
    let mm_per_count = nominal.nominal_mm_per_count();
    let home_lengths = nominal.home_lengths_mm();
    let worst_fk = session
        .samples
        .iter()
        .map(|s| {
            let lengths: [f64; 8] = core::array::from_fn(|i| {
                home_lengths[i] + f64::from(s.counts[i]) * mm_per_count[i]
            });
            let fk = forward_kinematics(
                &nominal.anchors_mm,
                spidar_core::model::StringLayout::ALL,
                &lengths,
                nominal.home_mm,
                // The legacy controller solves with every string (no
                // faulty-string search), as the black box it stands for.
                &FkConfig {
                    fault_threshold_mm: f64::INFINITY,
                    exclusion_threshold_mm: f64::INFINITY,
                    ..FkConfig::default()
                },
            );
            distance(&fk.position, &s.legacy.unwrap())
        })
        .fold(0.0, f64::max);
    assert!(worst_fk < 0.5, "dev_* vs FK of the counts: {worst_fk} mm");
}

/// Counts of the moment of the tracker frame.
fn assert_counts_are_the_tracker_frames_instant(
    rig: &SimulatedRig,
    session: &Session,
    truths: &[&HandSample],
) {
    let mm_per_count = rig.device.nominal.nominal_mm_per_count();
    // The counts of the moment of the tracker frame: each string's counts follow
    // its true length change (the winding law, smooth: a quadratic) within
    // a few mm (the simulated device's own effects, and what the hand moves
    // in a few milliseconds; a state one tracker frame off would be ~5 mm
    // more at the operator's speed, a wrong one tens of mm).
    // Pairing: each row's counts are the device's at the tracker frame's
    // capture instant. The truth is the plant's counts at that simulated
    // instant; the difference, in mm of string, is the pairing error.
    let pairing: Vec<f64> = session
        .samples
        .iter()
        .zip(truths)
        .flat_map(|(s, t)| {
            (0..8)
                .map(|i| f64::from(s.counts[i] - t.counts[i]).abs() * mm_per_count[i])
                .collect::<Vec<_>>()
        })
        .collect();
    let mean = pairing.iter().sum::<f64>() / pairing.len() as f64;
    let max = pairing.iter().copied().fold(0.0, f64::max);
    eprintln!("pairing error: mean {mean:.4} mm, max {max:.4} mm of string");
    assert!(
        max <= 0.1,
        "pairing error up to {max:.3} mm of string (mean {mean:.3})"
    );
    let anchors = rig.device.frame.anchors;
    let home = rig.device.frame.home;
    for (i, anchor) in anchors.iter().enumerate() {
        let true_change: Vec<f64> = truths
            .iter()
            .map(|t| distance(&t.device_mm, anchor) - distance(&home, anchor))
            .collect();
        let counts: Vec<f64> = session
            .samples
            .iter()
            .map(|s| f64::from(s.counts[i]))
            .collect();
        let (fit, slope) = quadratic_fit(&true_change, &counts);
        let worst = counts
            .iter()
            .zip(&fit)
            .map(|(c, f)| (c - f).abs() / slope.abs())
            .fold(0.0, f64::max);
        if std::env::var_os("TRACE").is_some() {
            let r: Vec<String> = counts
                .iter()
                .zip(&fit)
                .map(|(c, f)| format!("{:.1}", (c - f) / slope))
                .collect();
            eprintln!("string {i}: {}", r.join(" "));
        }
        assert!(slope > 0.0, "string {i}: counts grow as string is paid out");
        assert!(
            worst < 8.0,
            "string {i}: counts off the true length by {worst:.2} mm"
        );
    }
}

/// What the operator saw: each cell highlighted in turn, with progress and,
/// after a few captures, the time left.
fn assert_the_operator_saw_each_cell_in_turn(recorder: &Recorder, lattice: &Lattice) {
    let order = lattice.order();
    let mut next = 0;
    for c in &recorder.shown {
        if let (Some(t), Some(p)) = (c.target_room_mm, c.progress) {
            assert_eq!(p.total, 27);
            assert_eq!(c.target_half_size_mm, 50.0);
            assert_eq!(t, lattice.cell_centre(order[p.done]));
            assert!(p.done >= next);
            next = p.done;
        }
    }
    assert_eq!(next, 26);
    assert!(recorder
        .shown
        .iter()
        .any(|c| c.progress.is_some_and(|p| p.time_left.is_some())));
    assert!(recorder
        .shown
        .iter()
        .any(|c| c.message.contains("occluded") && c.marker_room_mm.is_none()));
}

/// A rig like [`rig`] whose tracker reports the marker body turned by
/// `rotation` (row-major body -> room), with `max_cells` captures.
fn turned_rig(seed: u64, rotation: [[f64; 3]; 3]) -> SimulatedRig {
    let device = SimulatedDevice::new(&SimConfig::default(), 3).unwrap();
    SimulatedRig::start(device, [0.0; 3], |c| {
        c.seed = seed;
        c.occlusion = 0.05;
        c.loss = 0.02;
        c.body_rotation = rotation;
        c.max_duration = Duration::from_secs(20);
    })
    .unwrap()
}

fn collect_cells(rig: &mut SimulatedRig, path: &std::path::Path, cells: usize) -> CollectReport {
    let lattice = small_lattice(rig);
    let mut client = rig.client().unwrap();
    let mut recorder = Recorder::new(&rig.cues);
    let cfg = CollectConfig {
        max_cells: Some(cells),
        ..config(rig)
    };
    collect(
        &mut client,
        &mut rig.receiver,
        &lattice,
        &cfg,
        path,
        &mut recorder,
    )
    .unwrap_or_else(|e| panic!("collect: {e}; {}", rig.describe()))
}

#[test]
fn each_row_records_the_body_s_orientation_from_the_tracker_s_rotation() {
    use nalgebra::{Unit, UnitQuaternion, Vector3};
    // A turn of 2.5 rad about a skew axis: no symmetry of the matrix can
    // hide a transposed (column- for row-major) reading.
    let truth =
        UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::new(1.0, -2.0, 0.5)), 2.5);
    let m = truth.to_rotation_matrix();
    let rotation: [[f64; 3]; 3] = core::array::from_fn(|r| core::array::from_fn(|c| m[(r, c)]));
    let expected = {
        let q = [truth.w, truth.i, truth.j, truth.k];
        q.map(|v| if truth.w < 0.0 { -v } else { v })
    };
    let mut rig = turned_rig(15, rotation);
    let path = temp_csv("oriented.csv");
    let report = collect_cells(&mut rig, &path, 6);
    assert_eq!(report.captured, 6);
    assert_eq!((report.oriented, report.improper_rotations), (6, 0));
    let session = Session::load(&path).unwrap();
    assert_eq!(session.samples.len(), 6);
    for (k, s) in session.samples.iter().enumerate() {
        let q = s.orientation.expect("an orientation");
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-5, "row {k}: norm {norm}");
        assert!(q[0] >= 0.0, "row {k}: {q:?}");
        for (a, b) in q.iter().zip(&expected) {
            assert!((a - b).abs() <= 1e-5, "row {k}: {q:?} vs {expected:?}");
        }
    }
    assert!(summary(&report).contains("rows with the body's orientation 6"));
}

#[test]
fn a_rotation_that_is_not_a_proper_one_is_counted_and_its_rows_have_no_orientation() {
    // A mirror: determinant -1.
    let mirror = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
    let mut rig = turned_rig(16, mirror);
    let path = temp_csv("mirrored.csv");
    let report = collect_cells(&mut rig, &path, 3);
    assert_eq!(report.captured, 3);
    assert_eq!((report.oriented, report.improper_rotations), (0, 3));
    let session = Session::load(&path).unwrap();
    assert_eq!(session.samples.len(), 3);
    assert!(session
        .samples
        .iter()
        .all(|s| s.tracker.is_some() && s.orientation.is_none()));
    let text = summary(&report);
    assert!(
        text.contains("3 captured rows had a tracker rotation that is not a proper rotation"),
        "{text}"
    );
}

#[test]
fn a_file_started_without_orientation_columns_is_resumed_with_position_only_rows() {
    let mut rig = rig(17);
    let path = temp_csv("old-header.csv");
    // As an older `spidar collect` started it: no ots_q* columns.
    let old_header = SessionAppender::header_line_without_orientation_for(8);
    std::fs::write(&path, format!("{old_header}\n")).unwrap();
    let report = collect_cells(&mut rig, &path, 3);
    assert_eq!(report.captured, 3);
    assert!(!report.orientation_columns);
    assert_eq!((report.oriented, report.orientations_not_recorded), (0, 3));
    let text = std::fs::read_to_string(&path).unwrap();
    assert_eq!(text.lines().next(), Some(old_header.as_str()));
    let session = Session::load(&path).unwrap();
    assert_eq!(session.samples.len(), 3);
    assert!(session.samples.iter().all(|s| s.orientation.is_none()));
    assert!(session
        .samples
        .iter()
        .all(|s| s.home.is_none() && s.since_home_s.is_none()));
    let said = summary(&report);
    assert!(
        said.contains("old-header.csv: started without orientation columns"),
        "{said}"
    );
    // And resumed again where it stopped.
    let report = collect_cells(&mut rig, &path, 2);
    assert_eq!((report.resumed_from, report.captured), (3, 2));
    assert_eq!(Session::load(&path).unwrap().samples.len(), 5);
}

#[test]
fn a_stopped_or_cancelled_collection_resumes_and_every_cell_is_captured_once() {
    let mut rig = rig(12);
    let lattice = small_lattice(&rig);
    let path = temp_csv("resume.csv");
    let mut client = rig.client().unwrap();

    // Stop after 7 cells.
    let mut stop_early = config(&rig);
    stop_early.max_cells = Some(7);
    let mut recorder = Recorder::new(&rig.cues);
    let cfg_here = config(&rig);
    let first = collect(
        &mut client,
        &mut rig.receiver,
        &lattice,
        &stop_early,
        &path,
        &mut recorder,
    )
    .unwrap_or_else(|e| panic!("{e}; {}", rig.describe()));
    assert_eq!(first.stop, Stop::MaxCells);
    assert_eq!((first.captured, first.done), (7, 7));
    assert!(disarmed(&rig));
    assert_eq!(Session::load(&path).unwrap().samples.len(), 7);

    // Cancelled once 15 cells are done.
    let flag = Arc::new(AtomicBool::new(false));
    let mut cancellable = config(&rig);
    cancellable.cancel = Some(flag.clone());
    let mut recorder = Recorder::new(&rig.cues);
    recorder.cancel = Some((flag, 15));
    let second = collect(
        &mut client,
        &mut rig.receiver,
        &lattice,
        &cancellable,
        &path,
        &mut recorder,
    )
    .unwrap_or_else(|e| panic!("{e}; {}", rig.describe()));
    assert_eq!(second.stop, Stop::Cancelled);
    assert_eq!((second.resumed_from, second.done), (7, 15));
    assert_eq!(second.captured, 8);
    assert!(disarmed(&rig));

    // The rest.
    let mut recorder = Recorder::new(&rig.cues);
    let third = collect(
        &mut client,
        &mut rig.receiver,
        &lattice,
        &cfg_here,
        &path,
        &mut recorder,
    )
    .unwrap_or_else(|e| panic!("{e}; {}", rig.describe()));
    assert_eq!(third.stop, Stop::Complete);
    assert_eq!(
        (third.resumed_from, third.captured, third.done),
        (15, 12, 27)
    );
    assert_eq!(third.clock_offset_s, 0.0, "same boot: device time as it is");
    assert_rows_in_order(&lattice, &Session::load(&path).unwrap());

    // Nothing left: a fourth run does nothing.
    let cfg_here = config(&rig);
    let fourth = collected(&mut rig, &mut client, &lattice, &cfg_here, &path);
    assert_eq!((fourth.captured, fourth.done), (0, 27));
}

#[test]
fn a_torn_last_line_is_cut_off_and_after_a_reboot_time_continues_from_the_last_row() {
    let mut rig = rig(13);
    let lattice = small_lattice(&rig);
    let path = temp_csv("torn.csv");
    let mut client = rig.client().unwrap();
    let mut cfg = config(&rig);
    cfg.max_cells = Some(5);
    let cfg_here = config(&rig);
    collected(&mut rig, &mut client, &lattice, &cfg, &path);
    let whole = std::fs::read_to_string(&path).unwrap();
    let last_t_s = Session::load(&path).unwrap().samples[4].t_s;
    // A crash mid-write: half a row, no newline.
    let half_row = &whole.lines().last().unwrap()[..60];
    std::fs::write(&path, format!("{whole}{half_row}")).unwrap();
    // And the device lost power: its clock restarts at 0.
    drop(client);
    rig.virtual_device.power_cycle().unwrap();
    let mut client = rig.client().unwrap();

    let mut recorder = Recorder::new(&rig.cues);
    let report = collect(
        &mut client,
        &mut rig.receiver,
        &lattice,
        &cfg_here,
        &path,
        &mut recorder,
    );
    if report.is_err() {
        for c in recorder.shown.iter().step_by(50) {
            eprintln!("{:?} {:?} {}", c.marker_room_mm, c.distance_mm, c.message);
        }
    }
    let report = report.unwrap_or_else(|e| panic!("{e}; {}", rig.describe()));
    let torn = report.torn.clone().expect("the torn line is reported");
    assert_eq!(torn.line, 7);
    assert_eq!(torn.text, half_row);
    assert_eq!((report.resumed_from, report.captured), (5, 22));
    assert!(report.clock_offset_s > 0.0, "{report:?}");
    let session = Session::load(&path).unwrap();
    assert_rows_in_order(&lattice, &session);
    assert!(session.samples[5].t_s >= last_t_s);
    assert!(session.samples[5].t_s < last_t_s + 1.0, "t_s continues");
    assert!(std::fs::read_to_string(&path).unwrap().starts_with(&whole));
}

#[test]
fn a_file_of_another_layout_or_volume_is_refused_naming_it() {
    let mut rig = rig(14);
    let lattice = small_lattice(&rig);
    let mut client = rig.client().unwrap();

    let other = temp_csv("other-layout.csv");
    std::fs::write(&other, "t_s,enc0,enc1\n0,1,2\n").unwrap();
    let cfg_here = config(&rig);
    let e = refused(&mut rig, &mut client, &lattice, &cfg_here, &other);
    let text = e.to_string();
    assert!(text.contains("other-layout.csv: line 1"), "{text}");
    assert!(text.contains("header"), "{text}");
    assert_eq!(
        std::fs::read_to_string(&other).unwrap(),
        "t_s,enc0,enc1\n0,1,2\n",
        "left as it was"
    );

    // A row outside this lattice: collected over another volume.
    let elsewhere = temp_csv("elsewhere.csv");
    let header = SessionAppender::header_line();
    // No orientation (empty `ots_q*`), then `dev_*`, `tension0..7`,
    // `since_home_s` and `home`.
    let far = format!(
        "0.5,{}9000,9000,9000,,,,,{}\n",
        "0,".repeat(8),
        ["1"; 13].join(",")
    );
    std::fs::write(&elsewhere, format!("{header}\n{far}")).unwrap();
    let cfg_here = config(&rig);
    let e = refused(&mut rig, &mut client, &lattice, &cfg_here, &elsewhere);
    assert!(
        matches!(e, CollectError::RowOutsideLattice { line: 2, .. }),
        "{e}"
    );
    assert!(e.to_string().contains("elsewhere.csv: line 2"), "{e}");
}

/// A virtual device and a tracker receiver nobody sends to.
fn device_without_tracker() -> (
    SimulatedDevice,
    spidar::sim::virtual_device::VirtualDevice,
    DtrackReceiver,
) {
    let device = SimulatedDevice::new(&SimConfig::default(), 3).unwrap();
    let hand = Hand::at(device.frame.home);
    let plant = Plant::new(device.clone(), Trajectory::Held(hand));
    let vd = spawn(
        VirtualDeviceConfig {
            pace: Pace::RealTime { speed: 1.0 },
            ..VirtualDeviceConfig::default()
        },
        plant,
    )
    .unwrap();
    let receiver =
        DtrackReceiver::bind(ReceiverConfig::new(SocketAddr::from(([127, 0, 0, 1], 0)))).unwrap();
    (device, vd, receiver)
}

#[test]
fn a_silent_tracker_is_an_error_naming_it_and_the_device_is_left_disarmed() {
    let (device, vd, mut receiver) = device_without_tracker();
    let lattice = Lattice::new(device.volume_centre_room(), 300.0, 3).unwrap();
    let mut client =
        Client::open_with(vd.port_path(), ClientOptions::for_simulated_device()).unwrap();
    let mut cfg = CollectConfig::for_geometry(&device.nominal);
    cfg.tracker_label = format!("the tracker (UDP {})", receiver.local_addr());
    cfg.tracker_timeout = Duration::from_millis(300);
    // The device runs in real time on a thread of this machine: a busy
    // machine may leave it unscheduled for over a second (the default
    // timeout), which is not the silence this test is about (1 failure in
    // 60 runs with both cores busy).
    cfg.device_timeout = Duration::from_secs(10);
    let path = temp_csv("silent.csv");
    let e = collect(
        &mut client,
        &mut receiver,
        &lattice,
        &cfg,
        &path,
        &mut SharedCues::new(),
    )
    .unwrap_err();
    assert!(matches!(e, CollectError::TrackerSilent { .. }), "{e}");
    assert!(
        e.to_string()
            .contains(&format!("UDP {}", receiver.local_addr())),
        "{e}"
    );
    assert!(eventually(|| !vd.status().armed));
    // Nothing was captured: the file holds its header only.
    assert!(Session::load(&path).unwrap().samples.is_empty());
}

#[test]
fn a_device_that_stops_answering_is_the_link_error() {
    let rig = rig(15);
    let mut cfg = config(&rig);
    let SimulatedRig {
        device,
        cues,
        virtual_device,
        mut receiver,
        operator,
        ..
    } = rig;
    let lattice = Lattice::new(device.volume_centre_room(), 300.0, 3).unwrap();
    let path = temp_csv("device-gone.csv");
    let port = virtual_device.port_path().to_string();
    // The simulated device's link options: with the default 4 tries of
    // 250 ms a busy machine made the device look gone before it was (1 in
    // 60 runs with both cores busy).
    let mut client = Client::open_with(&port, ClientOptions::for_simulated_device()).unwrap();
    // The device falls silent two cells in (a lost USB link).
    let mut device = Some(virtual_device);
    let mut sink = AtCell {
        recorder: Recorder {
            to_operator: cues,
            shown: Vec::new(),
            cancel: None,
        },
        at: 2,
        action: Some(|| {
            if let Some(d) = device.take() {
                d.shutdown();
            }
        }),
    };
    cfg.tracker_label = format!("the tracker (UDP {})", receiver.local_addr());
    let started = Instant::now();
    let e = collect(&mut client, &mut receiver, &lattice, &cfg, &path, &mut sink).unwrap_err();
    assert!(
        sink.action.is_none(),
        "the collection failed before the device was shut down: {e}"
    );
    drop(operator);
    assert!(
        matches!(e, CollectError::Link(_) | CollectError::DeviceSilent { .. }),
        "{e}"
    );
    assert!(e.to_string().contains(&port), "{e}");
    // It fails instead of waiting for ever (timeouts are wall time: a busy
    // machine may take seconds more).
    assert!(started.elapsed() < Duration::from_secs(30));
    // The rows captured before stay on disk.
    assert!(Session::load(&path).unwrap().samples.len() >= 2);
}

/// Passes the cues on and does `action` once, when `at` cells are
/// captured (from inside the collection, so the moment is the same in every
/// run, however busy the machine).
struct AtCell<F: FnMut()> {
    recorder: Recorder,
    at: usize,
    action: Option<F>,
}

impl<F: FnMut()> CueSink for AtCell<F> {
    fn show(&mut self, cues: &Cues) {
        self.recorder.show(cues);
        if cues.progress.is_some_and(|p| p.done >= self.at) {
            if let Some(mut action) = self.action.take() {
                action();
            }
        }
    }
}

#[test]
fn a_reboot_during_the_collection_stops_it_naming_the_lost_home() {
    let mut rig = rig(16);
    let lattice = small_lattice(&rig);
    let path = temp_csv("reboot.csv");
    let mut client = rig.client().unwrap();
    let cfg = config(&rig);
    let device = &rig.virtual_device;
    let mut sink = AtCell {
        recorder: Recorder::new(&rig.cues),
        at: 3,
        action: Some(|| device.power_cycle().unwrap()),
    };
    let e = collect(
        &mut client,
        &mut rig.receiver,
        &lattice,
        &cfg,
        &path,
        &mut sink,
    )
    .unwrap_err();
    assert!(sink.action.is_none(), "the device was power-cycled");
    assert!(matches!(e, CollectError::ClockWentBack { .. }), "{e}");
    let text = e.to_string();
    assert!(text.contains("spidar init"), "{text}");
    // The cells captured before the reboot stay on disk, in order.
    let session = Session::load(&path).unwrap();
    assert!(session.samples.len() >= 3, "{} rows", session.samples.len());
}

/// `spidar collect --simulate` run again: each run starts a rig of its own
/// (a new boot of the simulated device), and the file goes on under the new
/// run's home capture.
#[test]
fn a_stopped_collection_resumed_on_a_rig_started_again_completes_and_reads_back() {
    let path = temp_csv("resume-new-rig.csv");
    let mut first = rig(18);
    let report = collect_cells(&mut first, &path, 10);
    assert_eq!((report.captured, report.done), (10, 10));
    let before = Session::load(&path).unwrap();
    drop(first);

    // The same command again: a new rig, its device booted anew (before,
    // with the same boot id as the first: refused on the first new row,
    // "time since home goes backwards ... under the same home capture").
    let mut second = rig(18);
    let lattice = small_lattice(&second);
    let mut client = second.client().unwrap();
    let cfg = config(&second);
    let report = collected(&mut second, &mut client, &lattice, &cfg, &path);
    assert_eq!(report.stop, Stop::Complete);
    assert_eq!((report.resumed_from, report.captured), (10, 17));
    assert!(report.clock_offset_s > 0.0, "a new boot: {report:?}");

    // Every cell once, in order, read back by the dataset reader.
    let session = Session::load(&path).unwrap();
    assert_rows_in_order(&lattice, &session);
    assert_eq!(session.samples[..10], before.samples[..]);
    let (old, new) = session.samples.split_at(10);
    // Two home captures, each's time since home going on with t_s.
    assert_ne!(old[0].home, new[0].home);
    for part in [old, new] {
        assert!(part.iter().all(|s| s.home == part[0].home));
        for w in part.windows(2) {
            let (a, b) = (w[0].since_home_s.unwrap(), w[1].since_home_s.unwrap());
            assert!(
                ((b - a) - (w[1].t_s - w[0].t_s)).abs() < 1e-6,
                "since_home_s {a} -> {b} against t_s {} -> {}",
                w[0].t_s,
                w[1].t_s
            );
        }
    }
    // t_s goes on from the last row of the first run.
    assert!(new[0].t_s >= old[9].t_s && new[0].t_s < old[9].t_s + 1.0);
}

/// A file whose last row is later under the device's home capture than the
/// device now is: the id names two captures. Refused before a capture.
#[test]
fn a_home_id_the_file_has_later_than_the_device_is_refused_before_any_capture() {
    let mut rig = rig(19);
    let path = temp_csv("home-reused.csv");
    collect_cells(&mut rig, &path, 2);
    // The last row 1000 s after the same capture.
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    let last = lines.pop().unwrap();
    let mut fields: Vec<&str> = last.split(',').collect();
    let since = fields.len() - 2;
    fields[since] = "1000";
    lines.push(fields.join(","));
    let edited = format!("{}\n", lines.join("\n"));
    std::fs::write(&path, &edited).unwrap();

    let lattice = small_lattice(&rig);
    let mut client = rig.client().unwrap();
    let cfg = config(&rig);
    let e = refused(&mut rig, &mut client, &lattice, &cfg, &path);
    assert!(
        matches!(e, CollectError::HomeIdReused { line: 3, .. }),
        "{e}"
    );
    assert!(e.to_string().contains("spidar init"), "{e}");
    assert_eq!(std::fs::read_to_string(&path).unwrap(), edited);
    assert!(disarmed(&rig));
}

#[test]
fn a_lattice_reaching_outside_the_anchors_is_refused_before_the_device_is_armed() {
    let mut rig = rig(20);
    let path = temp_csv("too-big.csv");
    let centre = rig.device.volume_centre_room();
    let lattice = Lattice::new(centre, 5000.0, 3).unwrap();
    let mut client = rig.client().unwrap();
    let cfg = config(&rig);
    let e = refused(&mut rig, &mut client, &lattice, &cfg, &path);
    let largest_mm = match &e {
        CollectError::LatticeBeyondReach { largest_mm, .. } => *largest_mm,
        other => panic!("{other}"),
    };
    let text = e.to_string();
    assert!(text.contains("--size-mm 5000 is too large"), "{text}");
    assert!(
        text.contains(&format!(
            "the largest that fits around this centre is --size-mm {largest_mm:.1}"
        )),
        "{text}"
    );
    assert!(!path.exists(), "no file was started");
    assert!(!rig.virtual_device.status().armed, "never armed");
    // The largest that fits is taken, and collected.
    let fits = Lattice::new(centre, largest_mm, 3).unwrap();
    let cfg = CollectConfig {
        max_cells: Some(1),
        ..config(&rig)
    };
    let report = collected(&mut rig, &mut client, &fits, &cfg, &path);
    assert_eq!(report.captured, 1);
}
