//! Output files that a failure never spoils: every file the tools write
//! (calibration, report, model blob, figures, simulated sessions) goes to a
//! temporary file in the same folder, is synced, and only then renamed over
//! the old one. A full disk, a killed process or a failing encoder leaves
//! the previous file as it was and no stub beside it. And an output path
//! that names one of the run's inputs is refused before any work.

use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// An output path that names one of the run's inputs.
#[derive(Debug, thiserror::Error)]
#[error(
    "{}: the output `{output}` is the input `{input}`; choose another output path",
    path.display()
)]
pub struct OutputOverInput {
    pub path: PathBuf,
    pub output: &'static str,
    pub input: &'static str,
}

/// Writes `bytes` to `path` atomically (see the module's documentation).
/// The error is the operation's; the caller names the file.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomically_with(path, |w| w.write_all(bytes), |e| e)
}

/// Writes what `fill` writes to `path` atomically: `fill` writes into a
/// temporary file beside `path`, which replaces `path` only once `fill`
/// returned `Ok` and the data is synced to disk. On any error the temporary
/// file is removed and `path` keeps its old content; `io_error` turns the
/// file operations' errors into the caller's.
pub fn write_atomically_with<E>(
    path: &Path,
    fill: impl FnOnce(&mut dyn Write) -> Result<(), E>,
    io_error: impl Fn(io::Error) -> E,
) -> Result<(), E> {
    let mut temporary = temporary_beside(path, "").map_err(&io_error)?;
    {
        let mut writer = io::BufWriter::new(temporary.as_file_mut());
        fill(&mut writer)?;
        writer.flush().map_err(&io_error)?;
    }
    temporary.as_file().sync_all().map_err(&io_error)?;
    temporary.persist(path).map_err(|e| io_error(e.error))?;
    sync_folder(path);
    Ok(())
}

/// For writers that take a path (an image encoder that picks the format by
/// the extension): `write` writes the file at the temporary path it is
/// given, beside `path` and with its extension, which then replaces `path`.
pub fn write_atomically_via_path<E>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_error: impl Fn(io::Error) -> E,
) -> Result<(), E> {
    let partial = PartialFile::beside(path).map_err(&io_error)?;
    write(partial.path())?;
    partial.commit(path).map_err(io_error)
}

/// A file being written beside its final path under a temporary name (with
/// the final name's extension); [`PartialFile::commit`] moves it into place,
/// and dropping it uncommitted removes it.
pub struct PartialFile(tempfile::TempPath);

impl PartialFile {
    /// A new temporary file beside `path`.
    pub fn beside(path: &Path) -> io::Result<PartialFile> {
        let extension = path
            .extension()
            .map(|e| format!(".{}", e.to_string_lossy()))
            .unwrap_or_default();
        Ok(PartialFile(
            temporary_beside(path, &extension)?.into_temp_path(),
        ))
    }

    /// Where to write.
    pub fn path(&self) -> &Path {
        &self.0
    }

    /// Syncs what was written and renames it to `path`.
    pub fn commit(self, path: &Path) -> io::Result<()> {
        std::fs::File::open(&self.0)?.sync_all()?;
        self.0.persist(path).map_err(|e| e.error)?;
        sync_folder(path);
        Ok(())
    }
}

/// A new temporary file in `path`'s folder, named after it, ending in
/// `.partial` and `extension`.
fn temporary_beside(path: &Path, extension: &str) -> io::Result<tempfile::NamedTempFile> {
    // `tempfile` names, creates and (on drop, on every error path) removes
    // the temporary file; it is the crate made for this.
    tempfile::Builder::new()
        .prefix(&format!(
            ".{}.",
            path.file_name().unwrap_or_default().to_string_lossy()
        ))
        .suffix(&format!(".partial{extension}"))
        .tempfile_in(folder_of(path))
}

fn folder_of(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// The rename itself is durable once the folder is synced; a folder that
/// cannot be opened or synced (some filesystems) still holds either the old
/// or the new file, never a stub.
fn sync_folder(path: &Path) {
    if let Ok(dir) = std::fs::File::open(folder_of(path)) {
        let _ = dir.sync_all();
    }
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
) -> Result<(), OutputOverInput> {
    for &(output, out_path) in outputs {
        for &(input, in_path) in inputs {
            if same_file(out_path, in_path) {
                return Err(OutputOverInput {
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
