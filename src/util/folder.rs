//! Folders written as a whole: a command writes into a temporary sibling of its output folder,
//! which replaces the output only once everything in it is written. A failure, a kill or a
//! Ctrl-C leaves the previous contents exactly as they were (and the temporary sibling is
//! removed, or, after a kill, left as a hidden `.NAME.glasscan-*` folder).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

/// The hint of commands whose `--force` replaces a non-empty output folder.
pub const FORCE_HINT: &str = "choose a new folder, or replace it with --force";

/// An output folder being written; see the module doc.
#[derive(Debug)]
pub struct StagedFolder {
    target: PathBuf,
    staging: tempfile::TempDir,
}

/// True when `dir` does not exist or holds nothing.
fn is_empty_folder(dir: &Path) -> Result<bool> {
    if !dir.exists() {
        return Ok(true);
    }
    if !dir.is_dir() {
        bail!(
            "{} is a file, not a folder: choose a new folder name",
            dir.display()
        );
    }
    let mut entries =
        std::fs::read_dir(dir).with_context(|| format!("cannot read {}", dir.display()))?;
    Ok(entries.next().is_none())
}

impl StagedFolder {
    /// Starts writing `target`. A target that holds anything is refused unless `replace` (the
    /// command's `--force`, or a folder the command owns, such as a scan's `decoded/`): it is
    /// then replaced whole on [`commit`](Self::commit), and kept as it is on any failure.
    /// `hint` tells the user what to do about a refused folder.
    pub fn new(target: &Path, replace: bool, hint: &str) -> Result<Self> {
        if !replace && !is_empty_folder(target)? {
            bail!("{} exists and is not empty: {hint}", target.display());
        }
        if target.exists() && !target.is_dir() {
            bail!(
                "{} is a file, not a folder: choose a new folder name",
                target.display()
            );
        }
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
        let name = target
            .file_name()
            .with_context(|| format!("{}: not a folder name", target.display()))?
            .to_string_lossy()
            .into_owned();
        let staging = tempfile::Builder::new()
            .prefix(&format!(".{name}.glasscan-"))
            .tempdir_in(&parent)
            .with_context(|| format!("cannot create a temporary folder in {}", parent.display()))?;
        Ok(Self {
            target: target.to_path_buf(),
            staging,
        })
    }

    /// Where the command writes (the temporary sibling).
    pub fn path(&self) -> &Path {
        self.staging.path()
    }

    /// The folder the contents will have once committed.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Puts the written folder in place of the target (the old target, if any, is moved aside
    /// first and removed after).
    pub fn commit(self) -> Result<()> {
        let staging = self.staging.keep();
        let old = if self.target.exists() {
            let aside = staging.with_extension("old");
            std::fs::rename(&self.target, &aside).with_context(|| {
                format!("cannot move {} aside to replace it", self.target.display())
            })?;
            Some(aside)
        } else {
            None
        };
        if let Err(e) = std::fs::rename(&staging, &self.target) {
            if let Some(aside) = &old {
                // Put the old folder back: nothing is lost.
                let _ = std::fs::rename(aside, &self.target);
            }
            let _ = std::fs::remove_dir_all(&staging);
            return Err(e).with_context(|| format!("cannot create {}", self.target.display()));
        }
        if let Some(aside) = old {
            std::fs::remove_dir_all(&aside)
                .with_context(|| format!("cannot remove the replaced {}", aside.display()))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HINT: &str = "use --force";

    #[test]
    fn a_dropped_folder_leaves_the_old_contents() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("scan");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("a.txt"), "old").unwrap();
        assert!(StagedFolder::new(&target, false, HINT).is_err());
        let staged = StagedFolder::new(&target, true, HINT).unwrap();
        std::fs::write(staged.path().join("b.txt"), "new").unwrap();
        drop(staged);
        assert_eq!(
            std::fs::read_to_string(target.join("a.txt")).unwrap(),
            "old"
        );
        assert!(!target.join("b.txt").exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_committed_folder_replaces_the_old_one_whole() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("scan");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("a.txt"), "old").unwrap();
        let staged = StagedFolder::new(&target, true, HINT).unwrap();
        std::fs::write(staged.path().join("b.txt"), "new").unwrap();
        staged.commit().unwrap();
        assert!(!target.join("a.txt").exists());
        assert_eq!(
            std::fs::read_to_string(target.join("b.txt")).unwrap(),
            "new"
        );
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_file_is_not_a_folder() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("x");
        std::fs::write(&f, "x").unwrap();
        assert!(StagedFolder::new(&f, true, HINT).is_err());
    }
}
