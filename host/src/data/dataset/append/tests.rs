use super::*;
use crate::data::dataset::session_header;

fn sample(t_s: f64, x: f64) -> Sample {
    Sample {
        t_s,
        counts: [1, -2, 3, -4, 5, -6, 7, -8],
        tracker: Some([x, 0.25, -1e-3]),
        orientation: None,
        legacy: Some([0.1, 0.2, 0.3]),
        tension_n: Some([1.0; STRINGS]),
        since_home_s: None,
        home: None,
    }
}

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spidar-append-{}", std::process::id()));
    let _ = fs::create_dir_all(&dir);
    let path = dir.join(name);
    let _ = fs::remove_file(&path);
    path
}

#[test]
fn rows_appended_one_at_a_time_read_back_and_reopen_where_they_stopped() {
    let path = temp("rows.csv");
    let mut opened = SessionAppender::open(&path).unwrap();
    assert!(opened.created && opened.torn.is_none());
    assert_eq!(opened.appender.append(&sample(1.0, 10.0)).unwrap(), 2);
    assert_eq!(opened.appender.append(&sample(1.0, 11.5)).unwrap(), 3);
    // Time going backwards is refused, naming the line and column.
    let e = opened.appender.append(&sample(0.5, 0.0)).unwrap_err();
    assert!(e.to_string().contains("line 4, column `t_s`"), "{e}");
    drop(opened);
    let read = Session::load(&path).unwrap();
    assert_eq!(read.samples, vec![sample(1.0, 10.0), sample(1.0, 11.5)]);
    let mut again = SessionAppender::open(&path).unwrap();
    assert!(!again.created && again.torn.is_none());
    assert_eq!(again.existing, read);
    assert_eq!(again.appender.last_t_s(), Some(1.0));
    assert_eq!(again.appender.append(&sample(2.0, 12.0)).unwrap(), 4);
    assert_eq!(Session::load(&path).unwrap().samples.len(), 3);
}

fn oriented(t_s: f64, x: f64, q: [f64; 4]) -> Sample {
    Sample {
        orientation: Some(q),
        ..sample(t_s, x)
    }
}

/// A file as an older `spidar collect` started it: the header without
/// the orientation columns, and `rows` rows.
fn old_file(path: &Path, rows: &[Sample]) -> String {
    let columns = SessionAppender::COLUMNS_WITHOUT_ORIENTATION;
    let mut text = format!("{}\n", session_header(columns).join(","));
    let mut fields = Vec::new();
    for s in rows {
        row_fields(s, STRINGS, columns, &mut fields);
        text.push_str(&fields.join(","));
        text.push('\n');
    }
    fs::write(path, &text).unwrap();
    text
}

#[test]
fn a_new_file_has_the_orientation_columns_and_rows_with_and_without_one_read_back() {
    let path = temp("oriented.csv");
    let mut opened = SessionAppender::open(&path).unwrap();
    assert!(opened.appender.has_orientation_columns());
    let q = [0.5, -0.5, 0.5, 0.5];
    let tilted = [0.996195, 0.0, 0.087156, 0.0];
    assert_eq!(opened.appender.append(&oriented(1.0, 10.0, q)).unwrap(), 2);
    assert_eq!(opened.appender.append(&sample(1.5, 11.0)).unwrap(), 3);
    drop(opened);
    let text = fs::read_to_string(&path).unwrap();
    let header = text.lines().next().unwrap();
    assert_eq!(header, SessionAppender::header_line());
    // As `Session::write_to` places them: after `ots_z`.
    assert!(
        header.contains("ots_x,ots_y,ots_z,ots_qw,ots_qx,ots_qy,ots_qz,dev_x"),
        "{header}"
    );
    // A row without an orientation leaves its columns empty.
    assert!(
        text.lines().nth(2).unwrap().contains(",-0.001,,,,,0.1,"),
        "{text}"
    );
    let mut again = SessionAppender::open(&path).unwrap();
    assert!(again.appender.has_orientation_columns() && !again.created);
    assert_eq!(
        again.existing.samples,
        vec![oriented(1.0, 10.0, q), sample(1.5, 11.0)]
    );
    assert_eq!(
        again.appender.append(&oriented(2.0, 12.0, tilted)).unwrap(),
        4
    );
    // What the reader refuses is refused before anything is written.
    let e = again
        .appender
        .append(&oriented(3.0, 13.0, [1.0, 1.0, 0.0, 0.0]))
        .unwrap_err();
    assert!(e.to_string().contains("line 5, column `ots_qw`"), "{e}");
    let e = again
        .appender
        .append(&Sample {
            tracker: None,
            ..oriented(3.0, 13.0, q)
        })
        .unwrap_err();
    assert!(e.to_string().contains("line 5, column `ots_qw`"), "{e}");
    drop(again);
    assert_eq!(
        Session::load(&path).unwrap().samples,
        vec![
            oriented(1.0, 10.0, q),
            sample(1.5, 11.0),
            oriented(2.0, 12.0, tilted)
        ]
    );
}

#[test]
fn a_file_started_without_orientation_columns_reopens_and_takes_position_only_rows() {
    let path = temp("old.csv");
    let text = old_file(&path, &[sample(1.0, 10.0)]);
    let mut opened = SessionAppender::open(&path).unwrap();
    assert!(!opened.created && opened.torn.is_none());
    assert!(!opened.appender.has_orientation_columns());
    assert_eq!(opened.existing.samples, vec![sample(1.0, 10.0)]);
    assert_eq!(opened.appender.last_t_s(), Some(1.0));
    assert_eq!(opened.appender.append(&sample(2.0, 11.0)).unwrap(), 3);
    drop(opened);
    // The old header stays, and the row is in its columns.
    let now = fs::read_to_string(&path).unwrap();
    assert!(now.starts_with(&text), "{now}");
    assert!(!now.contains("ots_q"), "{now}");
    assert_eq!(
        Session::load(&path).unwrap().samples,
        vec![sample(1.0, 10.0), sample(2.0, 11.0)]
    );
    // Reopened again, with a torn last line cut off as for a new file.
    fs::write(&path, format!("{now}3,1,2")).unwrap();
    let mut opened = SessionAppender::open(&path).unwrap();
    assert_eq!(opened.torn.as_ref().map(|t| t.line), Some(4));
    assert!(!opened.appender.has_orientation_columns());
    assert_eq!(opened.appender.append(&sample(3.0, 12.0)).unwrap(), 4);
    drop(opened);
    assert_eq!(Session::load(&path).unwrap().samples.len(), 3);
    // An old header cut short (no row yet) starts again with the new one.
    let old_header = SessionAppender::header_line_without_orientation_for(STRINGS);
    let cut = &old_header[..old_header.len() - 3];
    assert!(!SessionAppender::header_line().starts_with(cut));
    fs::write(&path, cut).unwrap();
    let opened = SessionAppender::open(&path).unwrap();
    assert!(opened.created && opened.appender.has_orientation_columns());
    assert_eq!(opened.torn.map(|t| t.line), Some(1));
    assert_eq!(
        fs::read_to_string(&path).unwrap(),
        format!("{}\n", SessionAppender::header_line())
    );
}

#[test]
fn a_file_started_without_orientation_columns_refuses_a_row_with_one() {
    let path = temp("old-oriented.csv");
    let text = old_file(&path, &[sample(1.0, 10.0)]);
    let mut opened = SessionAppender::open(&path).unwrap();
    let e = opened
        .appender
        .append(&oriented(2.0, 11.0, [1.0, 0.0, 0.0, 0.0]))
        .unwrap_err();
    assert!(
        matches!(e, DatasetError::OrientationNotAppended { line: 3, .. }),
        "{e}"
    );
    let message = e.to_string();
    assert!(message.contains("old-oriented.csv: line 3"), "{message}");
    assert!(
        message.contains("started without orientation columns"),
        "{message}"
    );
    // Nothing was written, and the next position-only row goes on line 3.
    assert_eq!(fs::read_to_string(&path).unwrap(), text);
    assert_eq!(opened.appender.append(&sample(2.0, 11.0)).unwrap(), 3);
}

#[test]
fn an_unterminated_last_line_is_cut_off_and_reported() {
    let path = temp("torn.csv");
    let mut opened = SessionAppender::open(&path).unwrap();
    opened.appender.append(&sample(1.0, 10.0)).unwrap();
    drop(opened);
    let whole = fs::read_to_string(&path).unwrap();
    // A second row cut short (it even parses: its last number is cut).
    let row = whole.lines().nth(1).unwrap();
    fs::write(&path, format!("{whole}{}", &row[..row.len() - 2])).unwrap();
    let opened = SessionAppender::open(&path).unwrap();
    let torn = opened.torn.clone().expect("torn line reported");
    assert_eq!(torn.line, 3);
    assert_eq!(torn.text, row[..row.len() - 2]);
    assert_eq!(opened.existing.samples, vec![sample(1.0, 10.0)]);
    assert_eq!(fs::read_to_string(&path).unwrap(), whole);
    // A header cut short is started again.
    let header = SessionAppender::header_line();
    fs::write(&path, &header[..20]).unwrap();
    let opened = SessionAppender::open(&path).unwrap();
    assert!(opened.created);
    assert_eq!(opened.torn.map(|t| t.line), Some(1));
    assert_eq!(fs::read_to_string(&path).unwrap(), format!("{header}\n"));
}

#[test]
fn another_header_or_a_bad_complete_row_is_an_error_naming_the_file() {
    let path = temp("other.csv");
    fs::write(&path, "t_s,enc0\n1,2\n").unwrap();
    let e = SessionAppender::open(&path).err().expect("refused");
    assert!(matches!(e, DatasetError::HeaderMismatch { .. }), "{e}");
    assert!(e.to_string().contains("other.csv: line 1"), "{e}");
    assert_eq!(fs::read_to_string(&path).unwrap(), "t_s,enc0\n1,2\n");
    let header = SessionAppender::header_line();
    let fields = header.split(',').count();
    let bad = format!("{header}\n1,x{}\n", ",0".repeat(fields - 2));
    fs::write(&path, &bad).unwrap();
    let e = SessionAppender::open(&path).err().expect("refused");
    assert!(e.to_string().contains("line 2, column `enc0`"), "{e}");
    assert_eq!(fs::read_to_string(&path).unwrap(), bad);
}

#[test]
fn a_four_string_device_appends_its_own_columns_and_refuses_an_eight_string_file() {
    let dir = std::env::temp_dir().join(format!("spidar-append4-{}", std::process::id()));
    let _ = fs::create_dir_all(&dir);
    let path = dir.join("four.csv");
    let _ = fs::remove_file(&path);
    let mut opened = SessionAppender::open_for(&path, 4).unwrap();
    let sample = Sample {
        t_s: 0.5,
        counts: [1, 2, 3, 4, 0, 0, 0, 0],
        tracker: Some([1.0, 2.0, 3.0]),
        orientation: None,
        legacy: None,
        tension_n: Some([1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]),
        since_home_s: None,
        home: None,
    };
    opened.appender.append(&sample).unwrap();
    drop(opened);
    let text = fs::read_to_string(&path).unwrap();
    assert!(text.starts_with("t_s,enc0,enc1,enc2,enc3,ots_x"), "{text}");
    let read = Session::load(&path).unwrap();
    assert_eq!(read.strings, 4);
    assert_eq!(read.samples, vec![sample]);
    assert_eq!(SessionAppender::open_for(&path, 4).unwrap().existing, read);
    let e = SessionAppender::open(&path)
        .err()
        .expect("8-string writer refused");
    assert!(matches!(e, DatasetError::HeaderMismatch { .. }), "{e}");
}
