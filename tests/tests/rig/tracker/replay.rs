//! Replay of the shared example session's CSV.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use spidar::device::tracker::{collect, Next, Pacing, ReplaySource, TrackerError, TrackerSource};

fn session_head() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/examples/session-head.csv")
}

#[test]
fn replay_of_the_shared_session_keeps_occlusions() {
    let session = spidar::data::dataset::Session::load(session_head()).unwrap();
    let mut replay = ReplaySource::load(session_head(), Pacing::AsFastAsPossible).unwrap();
    assert_eq!(replay.len(), session.samples.len());
    let frames = collect(&mut replay, usize::MAX, Duration::from_secs(5)).unwrap();
    assert_eq!(replay.next_frame(Duration::ZERO).unwrap(), Next::End);
    assert_eq!(frames.len(), session.samples.len());
    let occluded_rows: Vec<u32> = session
        .samples
        .iter()
        .enumerate()
        .filter(|(_, s)| s.tracker.is_none())
        .map(|(i, _)| i as u32)
        .collect();
    // The example's first row and tenth row have empty ots_* columns.
    assert_eq!(occluded_rows, [0, 9]);
    for (i, (f, s)) in frames.iter().zip(&session.samples).enumerate() {
        assert_eq!(f.frame, i as u32);
        assert_eq!(f.ts_s, s.t_s);
        assert_eq!(f.body.as_ref().map(|b| b.position_mm), s.tracker);
        // The session has no orientation columns: no rotation, not the
        // identity.
        assert!(f.body.as_ref().is_none_or(|b| b.rotation.is_none()));
    }
    assert_eq!(replay.stats().occluded, 2);
    assert_eq!(replay.stats().delivered, 20);
}

#[test]
fn replay_plays_back_a_session_s_orientation_as_the_body_s_rotation() {
    use spidar::data::dataset::{Sample, Session};
    let row = |t_s: f64, tracker: Option<[f64; 3]>, orientation: Option<[f64; 4]>| Sample {
        t_s,
        counts: [0; 8],
        tracker,
        orientation,
        legacy: None,
        tension_n: None,
        since_home_s: None,
        home: None,
    };
    // A quarter turn about z: x goes to y.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let session = Session {
        samples: vec![
            row(0.0, Some([1.0, 2.0, 3.0]), Some([h, 0.0, 0.0, h])),
            row(0.1, Some([4.0, 5.0, 6.0]), None),
            row(0.2, None, None),
        ],
        ..Session::default()
    };
    let mut replay = ReplaySource::from_session(&session, Pacing::AsFastAsPossible).unwrap();
    let frames = collect(&mut replay, usize::MAX, Duration::from_secs(5)).unwrap();
    assert_eq!(frames.len(), 3);
    let turned = frames[0].body.as_ref().unwrap();
    assert_eq!(turned.position_mm, [1.0, 2.0, 3.0]);
    let r = turned.rotation.expect("the row's orientation");
    let expected = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    for (a, b) in r.iter().flatten().zip(expected.iter().flatten()) {
        assert!((a - b).abs() < 1e-12, "{r:?}");
    }
    assert_eq!(frames[1].body.as_ref().unwrap().rotation, None);
    assert_eq!(frames[2].body, None);
}

#[test]
fn replay_paced_in_real_time() {
    // 45 s of session at 1500x: about 30 ms.
    let mut replay =
        ReplaySource::load(session_head(), Pacing::RealTime { speed: 1500.0 }).unwrap();
    let start = Instant::now();
    let frames = collect(&mut replay, usize::MAX, Duration::from_secs(5)).unwrap();
    let took = start.elapsed();
    assert_eq!(frames.len(), 20);
    let span = frames[19].ts_s - frames[0].ts_s;
    assert!(
        took >= Duration::from_secs_f64(span / 1500.0 * 0.9),
        "{took:?}"
    );
    for w in frames.windows(2) {
        assert!(w[1].received_at >= w[0].received_at);
    }
    // A timeout shorter than the next frame's due time gives Timeout.
    let mut slow = ReplaySource::load(session_head(), Pacing::RealTime { speed: 1.0 }).unwrap();
    assert!(matches!(
        slow.next_frame(Duration::ZERO).unwrap(),
        Next::Frame(_)
    ));
    assert_eq!(
        slow.next_frame(Duration::from_millis(5)).unwrap(),
        Next::Timeout
    );
    let err = ReplaySource::load(session_head(), Pacing::RealTime { speed: 0.0 }).unwrap_err();
    assert!(matches!(&err, TrackerError::Config(c) if c.field == "pacing.speed"));
}

#[test]
fn replay_of_a_missing_file_names_it() {
    let err = ReplaySource::load("no/such/session.csv", Pacing::AsFastAsPossible).unwrap_err();
    assert!(err.to_string().contains("no/such/session.csv"), "{err}");
}
