//! Output files that a failure never spoils: every file the tools write
//! (calibration, report, model blob, figures, simulated sessions) goes to a
//! temporary file in the same folder, is synced, and only then renamed over
//! the old one. A full disk, a killed process or a failing encoder leaves
//! the previous file as it was and no stub beside it. And an output path
//! that names one of the run's inputs is refused before any work.

use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// Why an output file could not be written, naming it.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// Creating, writing, syncing or renaming the file failed; the previous
    /// file (if any) is untouched.
    #[error("{}: cannot write (the previous file, if any, is kept): {source}", path.display())]
    Write { path: PathBuf, source: io::Error },
    /// An output path is one of the inputs: writing it would destroy the input.
    #[error(
        "{}: the output `{output}` is the input `{input}`; choose another output path",
        path.display()
    )]
    OverInput {
        path: PathBuf,
        output: &'static str,
        input: &'static str,
    },
}

/// Writes `bytes` to `path` atomically (see the module's documentation).
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), OutputError> {
    write_atomically_with(path, |w| w.write_all(bytes))
}

/// Writes what `fill` writes to `path` atomically: `fill` writes into a
/// temporary file beside `path`, which replaces `path` only once `fill`
/// returned `Ok` and the data is synced to disk. On any error the temporary
/// file is removed and `path` keeps its old content.
pub fn write_atomically_with(
    path: &Path,
    fill: impl FnOnce(&mut dyn Write) -> io::Result<()>,
) -> Result<(), OutputError> {
    let err = |source| OutputError::Write {
        path: path.to_path_buf(),
        source,
    };
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    // `tempfile` names, creates and (on drop, on every error path) removes
    // the temporary file; it is the crate made for this.
    let mut temporary = tempfile::Builder::new()
        .prefix(&format!(
            ".{}.",
            path.file_name().unwrap_or_default().to_string_lossy()
        ))
        .suffix(".partial")
        .tempfile_in(folder)
        .map_err(err)?;
    {
        let mut writer = io::BufWriter::new(temporary.as_file_mut());
        fill(&mut writer).map_err(err)?;
        writer.flush().map_err(err)?;
    }
    temporary.as_file().sync_all().map_err(err)?;
    temporary.persist(path).map_err(|e| err(e.error))?;
    // The rename itself is durable once the folder is synced; a folder
    // that cannot be opened or synced (some filesystems) still holds
    // either the old or the new file, never a stub.
    if let Ok(dir) = std::fs::File::open(folder) {
        let _ = dir.sync_all();
    }
    Ok(())
}

/// The same file, whether or not `output` exists yet: both paths made
/// absolute, with the folders resolved (symbolic links followed).
fn same_file(output: &Path, input: &Path) -> bool {
    let resolved = |p: &Path| -> Option<PathBuf> {
        if let Ok(c) = p.canonicalize() {
            return Some(c);
        }
        let parent = match p.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.canonicalize().ok()?,
            _ => std::env::current_dir().ok()?,
        };
        Some(parent.join(p.file_name()?))
    };
    match (resolved(output), resolved(input)) {
        (Some(a), Some(b)) => a == b,
        _ => false,
    }
}

/// Refuses an output path that is one of the inputs (named as the options
/// that gave them, e.g. `("--out", path)` and `("--calibration", path)`).
pub fn refuse_output_over_input(
    outputs: &[(&'static str, &Path)],
    inputs: &[(&'static str, &Path)],
) -> Result<(), OutputError> {
    for &(output, out_path) in outputs {
        for &(input, in_path) in inputs {
            if same_file(out_path, in_path) {
                return Err(OutputError::OverInput {
                    path: out_path.to_path_buf(),
                    output,
                    input,
                });
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
