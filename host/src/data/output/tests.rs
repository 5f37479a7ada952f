use super::*;

fn folder(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spidar-output-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn leftovers(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".partial"))
        .collect()
}

#[test]
fn a_write_replaces_the_file_and_leaves_nothing_beside_it() {
    let dir = folder("replace");
    let path = dir.join("calibration.json");
    write_atomically(&path, b"old").unwrap();
    write_atomically(&path, b"new").unwrap();
    assert_eq!(std::fs::read(&path).unwrap(), b"new");
    assert!(leftovers(&dir).is_empty());
}

/// An injected writer fault halfway (as a full disk gives): the previous
/// file keeps its bytes, the error names the file, no stub is left.
#[test]
fn a_failed_write_keeps_the_previous_file() {
    let dir = folder("fault");
    let path = dir.join("model.blob");
    write_atomically(&path, b"the previous model").unwrap();
    let e = write_atomically_with(
        &path,
        |w| {
            w.write_all(&[7; 10_000])?;
            Err(io::Error::new(
                io::ErrorKind::StorageFull,
                "no space left on device",
            ))
        },
        |e| e,
    )
    .unwrap_err();
    assert_eq!(std::fs::read(&path).unwrap(), b"the previous model");
    assert!(leftovers(&dir).is_empty(), "{:?}", leftovers(&dir));
    assert!(e.to_string().contains("no space left"), "{e}");
    // A writer that takes a path fails the same way: nothing replaced.
    let png = dir.join("figure.png");
    write_atomically(&png, b"old figure").unwrap();
    let e = write_atomically_via_path(
        &png,
        |tmp| {
            assert_eq!(tmp.extension().unwrap(), "png");
            std::fs::write(tmp, b"half a fig")?;
            Err(io::Error::other("encoder failed"))
        },
        |e| e,
    )
    .unwrap_err();
    assert!(e.to_string().contains("encoder failed"));
    assert_eq!(std::fs::read(&png).unwrap(), b"old figure");
    assert!(leftovers(&dir).is_empty(), "{:?}", leftovers(&dir));
    write_atomically_via_path(&png, |tmp| std::fs::write(tmp, b"new figure"), |e| e).unwrap();
    assert_eq!(std::fs::read(&png).unwrap(), b"new figure");
}

#[test]
fn a_write_into_a_missing_folder_fails() {
    let dir = folder("missing");
    let path = dir.join("no/such/folder/report.json");
    let e = write_atomically(&path, b"{}").unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::NotFound, "{e}");
}

#[test]
fn an_output_over_an_input_is_refused_by_name() {
    let dir = folder("over");
    let calibration = dir.join("calibration.json");
    std::fs::write(&calibration, "{}").unwrap();
    // The same file by another spelling.
    let again = dir.join(".").join("calibration.json");
    let e = refuse_output_over_input(&[("--out", &again)], &[("--calibration", &calibration)])
        .unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains("`--out`") && text.contains("`--calibration`"),
        "{text}"
    );
    // A new file beside it is fine, existing or not.
    let blob = dir.join("model.blob");
    refuse_output_over_input(&[("--out", &blob)], &[("--calibration", &calibration)]).unwrap();
}
