//! One writer per output: an OS advisory lock (`flock`) on a hidden sibling file
//! `.NAME.glasscan.lock` of the output `NAME`, held while a command writes it. The OS releases
//! the lock when the process ends, however it ends, so a killed run never blocks the next one.
//!
//! The lock file is removed when the lock is released. A process that opened the file just
//! before it was removed could lock a file that no longer has a name; [`OutputLock::acquire`]
//! therefore checks, once it holds the lock, that the path still names the file it locked, and
//! tries again otherwise.

use std::fs::{File, OpenOptions, TryLockError};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

/// A held lock on an output path; released (and its file removed) when dropped.
#[derive(Debug)]
pub struct OutputLock {
    path: PathBuf,
    file: File,
}

/// The lock file of `output`: `.NAME.glasscan.lock` beside it.
pub fn lock_path(output: &Path) -> Result<PathBuf> {
    let name = output
        .file_name()
        .with_context(|| format!("{}: not a file or folder name", output.display()))?;
    let parent = super::paths::parent_or_here(output);
    Ok(parent.join(format!(".{}.glasscan.lock", name.to_string_lossy())))
}

impl OutputLock {
    /// Locks `output` for this process; refused, naming it, while another process holds it.
    pub fn acquire(output: &Path) -> Result<Self> {
        let path = lock_path(output)?;
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        for _ in 0..100 {
            let file = OpenOptions::new()
                .create(true)
                .truncate(false)
                .write(true)
                .open(&path)
                .with_context(|| format!("cannot create the lock file {}", path.display()))?;
            match file.try_lock() {
                Ok(()) => {}
                Err(TryLockError::WouldBlock) => bail!(
                    "another glasscan process is writing {} (it holds {}): wait for it to finish, or stop it",
                    output.display(),
                    path.display()
                ),
                Err(TryLockError::Error(e)) => {
                    return Err(e)
                        .with_context(|| format!("cannot lock {}", path.display()))
                }
            }
            if same_file(&file, &path) {
                return Ok(Self { path, file });
            }
        }
        bail!(
            "cannot lock {}: its lock file keeps being replaced",
            output.display()
        )
    }
}

/// True when `path` still names the open `file` (same device and inode).
fn same_file(file: &File, path: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (file.metadata(), std::fs::metadata(path)) {
        (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
        _ => false,
    }
}

impl Drop for OutputLock {
    fn drop(&mut self) {
        // Removed while still held: a waiting process then finds the name gone and retries.
        let _ = std::fs::remove_file(&self.path);
        let _ = self.file.unlock();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_writer_is_refused_until_the_first_lets_go() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("run");
        let first = OutputLock::acquire(&out).unwrap();
        let err = OutputLock::acquire(&out).unwrap_err().to_string();
        assert!(err.contains("another glasscan process is writing"), "{err}");
        drop(first);
        assert!(
            !lock_path(&out).unwrap().exists(),
            "the lock file is removed"
        );
        let again = OutputLock::acquire(&out).unwrap();
        drop(again);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
