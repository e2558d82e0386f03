//! Folders written as a whole: a command writes into a temporary sibling of its output folder,
//! which replaces the output only once everything in it is written. A failure, a kill or a
//! Ctrl-C at any instant leaves the previous contents as they were, and the next run of any
//! command writing the same folder puts things right before it starts:
//!
//! 1. it takes the output's lock ([`OutputLock`]): one writer per folder, so two runs never
//!    interleave their renames;
//! 2. it recovers: a folder set aside (`.NAME.glasscan-*.old`) by a run killed between its two
//!    renames is put back when `NAME` is missing, and removed when `NAME` is in place (the kill
//!    came after the second rename); temporary siblings (`.NAME.glasscan-*`) of killed runs
//!    are removed;
//! 3. it writes into a new temporary sibling, and [`StagedFolder::commit`] moves the old folder
//!    aside under a name of its own, moves the new one in, and removes the old one.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use super::lock::OutputLock;

/// The hint of commands whose `--force` replaces a non-empty output folder.
pub const FORCE_HINT: &str = "choose a new folder, or replace it with --force";

/// An output folder being written; see the module doc.
#[derive(Debug)]
pub struct StagedFolder {
    target: PathBuf,
    staging: tempfile::TempDir,
    _lock: OutputLock,
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

/// The folder holding `target` and `target`'s name.
fn parent_and_name(target: &Path) -> Result<(PathBuf, String)> {
    let parent = super::paths::parent_or_here(target).to_path_buf();
    let name = target
        .file_name()
        .with_context(|| format!("{}: not a folder name", target.display()))?
        .to_string_lossy()
        .into_owned();
    Ok((parent, name))
}

/// Step 2 of the module doc, run while holding `target`'s lock: puts back or removes a folder
/// set aside by a killed run, and removes the temporary siblings of killed runs.
pub fn recover(target: &Path) -> Result<()> {
    let (parent, name) = parent_and_name(target)?;
    let Ok(entries) = std::fs::read_dir(&parent) else {
        return Ok(());
    };
    let prefix = format!(".{name}.glasscan-");
    let mut leftovers: Vec<PathBuf> = entries
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .map(|e| e.path())
        .collect();
    leftovers.sort();
    for path in leftovers {
        let aside = path.extension().is_some_and(|e| e == "old");
        if aside && !target.exists() {
            std::fs::rename(&path, target).with_context(|| {
                format!(
                    "{} was set aside by a run that was stopped, and cannot be put back: move it back to {} by hand",
                    path.display(),
                    target.display()
                )
            })?;
        } else {
            std::fs::remove_dir_all(&path).with_context(|| {
                format!(
                    "cannot remove {}, left by a run that was stopped: remove it by hand",
                    path.display()
                )
            })?;
        }
    }
    Ok(())
}

impl StagedFolder {
    /// Starts writing `target`. A target that holds anything is refused unless `replace` (the
    /// command's `--force`, or a folder the command owns, such as a scan's `decoded/`): it is
    /// then replaced whole on [`commit`](Self::commit), and kept as it is on any failure.
    /// `hint` tells the user what to do about a refused folder. Refused while another process
    /// writes `target`.
    pub fn new(target: &Path, replace: bool, hint: &str) -> Result<Self> {
        if target.exists() && !target.is_dir() {
            bail!(
                "{} is a file, not a folder: choose a new folder name",
                target.display()
            );
        }
        let (parent, name) = parent_and_name(target)?;
        std::fs::create_dir_all(&parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
        let lock = OutputLock::acquire(target)?;
        recover(target)?;
        if !replace && !is_empty_folder(target)? {
            bail!("{} exists and is not empty: {hint}", target.display());
        }
        let staging = tempfile::Builder::new()
            .prefix(&format!(".{name}.glasscan-"))
            .tempdir_in(&parent)
            .with_context(|| format!("cannot create a temporary folder in {}", parent.display()))?;
        Ok(Self {
            target: target.to_path_buf(),
            staging,
            _lock: lock,
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

    /// Puts the written folder in place of the target: the old target, if any, is moved aside
    /// (to the temporary's name + `.old`) first and removed after. A kill between the two
    /// renames is put right by the next run ([`recover`]).
    pub fn commit(self) -> Result<()> {
        let staging = self.staging.keep();
        let old = if self.target.exists() {
            let mut aside = staging.clone().into_os_string();
            aside.push(".old");
            let aside = PathBuf::from(aside);
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
    fn a_run_killed_between_the_renames_is_put_right_by_the_next() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("decoded");
        // Killed after the first rename: the old folder is only aside; a temporary is left.
        let aside = dir.path().join(".decoded.glasscan-abc.old");
        std::fs::create_dir(&aside).unwrap();
        std::fs::write(aside.join("a.txt"), "old").unwrap();
        std::fs::create_dir(dir.path().join(".decoded.glasscan-abc")).unwrap();
        std::fs::create_dir(dir.path().join(".decoded.glasscan-xyz")).unwrap();
        let staged = StagedFolder::new(&target, false, HINT);
        assert!(staged.is_err(), "the old folder is back, and not empty");
        assert_eq!(
            std::fs::read_to_string(target.join("a.txt")).unwrap(),
            "old"
        );
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["decoded"], "temporaries and the lock are gone");
        // Killed after the second rename: the new folder is in place, the aside is removed.
        std::fs::create_dir(&aside).unwrap();
        let staged = StagedFolder::new(&target, true, HINT).unwrap();
        assert!(!aside.exists());
        std::fs::write(staged.path().join("b.txt"), "new").unwrap();
        staged.commit().unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn two_writers_of_one_folder_are_not_let_in_together() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("scan");
        let first = StagedFolder::new(&target, false, HINT).unwrap();
        let err = StagedFolder::new(&target, false, HINT).unwrap_err();
        assert!(
            err.to_string().contains("another glasscan process"),
            "{err}"
        );
        assert!(
            first.path().is_dir(),
            "the second writer left the first's temporary alone"
        );
        first.commit().unwrap();
    }

    #[test]
    fn a_file_is_not_a_folder() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("x");
        std::fs::write(&f, "x").unwrap();
        assert!(StagedFolder::new(&f, true, HINT).is_err());
    }
}
