//! What a calibration holds in memory against the size of its training
//! session (issue 37, finding 9: a 100,000-row session of 15 MB took
//! 1.6 GB). A binary of its own: its allocator counts every byte the
//! process holds, which other tests running beside it would add to.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use spidar::procedures::calibrate::{calibrate, CalibrateConfig, NamedSession};
use spidar::sim::{simulate_session, SessionKind, SimConfig, SimulatedDevice};

/// The system's allocator, counting the bytes held and their peak.
struct Counting;

static HELD: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn held(bytes: usize) {
    let now = HELD.fetch_add(bytes, Ordering::SeqCst) + bytes;
    PEAK.fetch_max(now, Ordering::SeqCst);
}

fn released(bytes: usize) {
    HELD.fetch_sub(bytes, Ordering::SeqCst);
}

// SAFETY: every call is the system allocator's with the same arguments;
// the counts only follow what it hands out and takes back.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            held(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            held(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, p: *mut u8, layout: Layout) {
        unsafe { System.dealloc(p, layout) };
        released(layout.size());
    }

    unsafe fn realloc(&self, p: *mut u8, layout: Layout, size: usize) -> *mut u8 {
        let q = unsafe { System.realloc(p, layout, size) };
        if !q.is_null() {
            held(size);
            released(layout.size());
        }
        q
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// The most bytes held while `f` runs beyond those held when it starts.
fn peak_while<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let start = HELD.load(Ordering::SeqCst);
    PEAK.store(start, Ordering::SeqCst);
    let out = f();
    (out, PEAK.load(Ordering::SeqCst) - start)
}

/// A training session of `rows` random points of the model simulator's
/// device (seed 4), its CSV's size in bytes, and the peak memory of its
/// calibration beyond the session itself (quick searches, the loop on
/// every row, the learners capped at 300 points: a memory that grows with the session is the
/// identification's, the loop's and the figures', not theirs).
fn calibration_peak(rows: usize) -> (usize, usize) {
    let c = SimConfig::default();
    let device = SimulatedDevice::new(&c, 4).expect("device");
    let train = simulate_session(&device, SessionKind::Random { points: rows }, 5).expect("train");
    let test = simulate_session(&device, SessionKind::Random { points: 200 }, 6).expect("test");
    let mut csv = Vec::new();
    train
        .write_to(&mut csv, Path::new("train.csv"))
        .expect("csv");
    let mut cfg = CalibrateConfig::quick();
    cfg.quiet = true;
    cfg.max_learning_points = 300;
    // The loop reads every row: its working rows grow with the session
    // (past its default bound they stop growing, and the rows it reads are
    // a copy of at most that many).
    cfg.max_loop_rows = 0;
    let (calibrated, peak) = peak_while(|| {
        calibrate(
            &c.nominal.geometry(),
            Path::new("geometry.toml"),
            NamedSession {
                path: Path::new("train.csv"),
                session: &train,
            },
            NamedSession {
                path: Path::new("test.csv"),
                session: &test,
            },
            &cfg,
        )
    });
    assert!(calibrated.is_ok(), "{:?}", calibrated.err());
    (csv.len(), peak)
}

/// The peak memory of a calibration grows with its training session by at
/// most a few times what the session's file grows by. Before, diagnosis
/// held every (row, string) residual with its context, the model's span as
/// a dense basis (twice) and every candidate's columns at once: about a
/// hundred times the file. One thread, so that the peak does not depend on
/// how parallel fits overlap (the binary runs two at a time: each fit's
/// working rows count twice there).
#[test]
fn a_calibration_s_peak_memory_grows_a_few_times_its_session_s_file() {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("thread pool");
    // Both beyond the 4000 observations a diagnosis keeps its passes' work
    // for (a bounded 12-20 MB, `diagnose::evidence::KEPT_OBSERVATIONS`):
    // the growth measured is what has no bound.
    let (small, large) = pool.install(|| (calibration_peak(4500), calibration_peak(9000)));
    let file = (large.0 - small.0) as f64;
    let peak = large.1 as f64 - small.1 as f64;
    let ratio = peak / file;
    eprintln!(
        "training file {} -> {} bytes, calibration's peak {} -> {} bytes: {ratio:.1} times the file's growth",
        small.0, large.0, small.1, large.1
    );
    assert!(ratio <= 8.0, "{ratio:.1} times the file's growth");
}
