//! Atomic file output: write to a temporary file in the destination folder, then rename it over
//! the destination, so a crash never leaves a half-written output behind.

use std::io::{self, BufWriter, Write};
use std::path::Path;

/// Writes a file atomically: `fill` writes the whole content into a buffered temporary file in
/// the same folder as `path` (made first if missing, as a folder output is), which is then
/// flushed, synced and renamed to `path`. On any error the temporary file is removed and `path`
/// is left as it was.
pub fn write_atomic<F>(path: &Path, fill: F) -> io::Result<()>
where
    F: FnOnce(&mut dyn Write) -> io::Result<()>,
{
    let dir = super::paths::parent_or_here(path);
    std::fs::create_dir_all(dir).map_err(|e| in_folder(dir, &e))?;
    let tmp = tempfile::Builder::new()
        .prefix(".glasscan-")
        .suffix(".tmp")
        .tempfile_in(dir)
        .map_err(|e| in_folder(dir, &e))?;
    {
        let mut w = BufWriter::new(tmp.as_file());
        fill(&mut w)?;
        w.flush()?;
    }
    // Temporary files are created private (0600); the output gets ordinary permissions.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))?;
    }
    tmp.as_file().sync_all()?;
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}

/// Why no file can be made in folder `dir`, in words that name the folder rather than the
/// temporary file's name.
fn in_folder(dir: &Path, e: &io::Error) -> io::Error {
    let why: std::borrow::Cow<str> = match e.kind() {
        io::ErrorKind::PermissionDenied => {
            "permission denied: choose a folder you can write to".into()
        }
        io::ErrorKind::ReadOnlyFilesystem => "the file system is read-only".into(),
        io::ErrorKind::StorageFull => "the disk is full".into(),
        io::ErrorKind::NotADirectory | io::ErrorKind::AlreadyExists => {
            "a file stands where a folder is needed".into()
        }
        kind => kind.to_string().into(),
    };
    io::Error::new(
        e.kind(),
        format!("no file can be made in {}: {why}", dir.display()),
    )
}

/// Writes `value` as pretty JSON to `path`, atomically.
pub fn write_json(path: &Path, value: &serde_json::Value) -> anyhow::Result<()> {
    use anyhow::Context;
    write_atomic(path, |w| {
        serde_json::to_writer_pretty(&mut *w, value)?;
        writeln!(w)
    })
    .with_context(|| format!("cannot write {}", path.display()))
}
