//! Atomic file output: write to a temporary file in the destination folder, then rename it over
//! the destination, so a crash never leaves a half-written output behind.

use std::io::{self, BufWriter, Write};
use std::path::Path;

/// Writes a file atomically: `fill` writes the whole content into a buffered temporary file in
/// the same folder as `path`, which is then flushed, synced and renamed to `path`. On any error
/// the temporary file is removed and `path` is left as it was.
pub fn write_atomic<F>(path: &Path, fill: F) -> io::Result<()>
where
    F: FnOnce(&mut dyn Write) -> io::Result<()>,
{
    let dir = super::paths::parent_or_here(path);
    let tmp = tempfile::Builder::new()
        .prefix(".glasscan-")
        .suffix(".tmp")
        .tempfile_in(dir)?;
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

/// Writes `value` as pretty JSON to `path`, atomically.
pub fn write_json(path: &Path, value: &serde_json::Value) -> anyhow::Result<()> {
    use anyhow::Context;
    write_atomic(path, |w| {
        serde_json::to_writer_pretty(&mut *w, value)?;
        writeln!(w)
    })
    .with_context(|| format!("cannot write {}", path.display()))
}
