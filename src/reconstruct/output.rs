//! The output folder of a reconstruction: what may be in it before a run, and the checkpoint
//! that is the single commit point of every stage.
//!
//! A run first writes its start mesh, then commits `checkpoint.json` with no stage done; after
//! each stage it writes `stage_NN.ply` and then commits the checkpoint that names it. Every file
//! is written atomically (temporary file + rename), and only what the checkpoint names counts: a
//! run killed at any instant leaves either the previous or the new stage committed, and a
//! `stage_NN.ply` written after the last commit is written again, identically, on resume.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use super::Checkpoint;
use crate::util::atomic::write_atomic;
use crate::util::lock::OutputLock;

/// The checkpoint of a run in `out`.
pub fn checkpoint_path(out: &Path) -> PathBuf {
    out.join("checkpoint.json")
}

/// The mesh of stage `s` of a run in `out`.
pub fn stage_path(out: &Path, s: usize) -> PathBuf {
    out.join(format!("stage_{s:02}.ply"))
}

/// The folder, inside a run's output folder, of the first pass of a run given an unknown
/// refractive index (`ior = "auto"`), which finds where to start it: a run of its own, with its
/// own checkpoint.
pub const INDEX_PASS: &str = "index_pass";

/// The folder, inside a run's output folder, of the pass that estimates an unknown index with
/// the shape when the run is then given the estimate (through curved glass decoded from
/// captures): a run of its own, with its own checkpoint.
pub const INDEX_FIT: &str = "index_fit";

/// The folders of the passes a run may hold ([`INDEX_PASS`], [`INDEX_FIT`]).
const PASSES: [&str; 2] = [INDEX_PASS, INDEX_FIT];

/// True for the name of a pass's folder ([`PASSES`]).
fn is_pass(name: &str) -> bool {
    PASSES.contains(&name)
}

/// What an output folder held when a run was asked to write into it.
#[derive(Debug)]
pub enum Existing {
    /// Nothing (or no folder yet): the run starts from its start mesh.
    Nothing,
    /// A committed run, to be continued (`--resume`).
    Run(Box<Checkpoint>),
}

/// True for a file name that glasscan's reconstruction writes (or a temporary file of it).
fn is_glasscan_file(name: &str) -> bool {
    let stage = name
        .strip_prefix("stage_")
        .and_then(|s| s.strip_suffix(".ply"))
        .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
    let temporary = name.starts_with(".glasscan-") && name.ends_with(".tmp");
    stage
        || temporary
        || [
            "checkpoint.json",
            "start.ply",
            "hull.ply",
            "result.ply",
            "report.json",
            "loss.png",
            "loss.svg",
            "confidence.png",
        ]
        .contains(&name)
}

/// True for an entry of `out` that glasscan's reconstruction writes: one of its files, or a
/// pass's folder holding nothing else.
fn is_glasscan_entry(out: &Path, name: &str) -> Result<bool> {
    let path = out.join(name);
    if is_pass(name) && path.is_dir() {
        return Ok(folder_entries(&path)?.iter().all(|n| is_glasscan_file(n)));
    }
    Ok(is_glasscan_file(name))
}

/// The committed run in `out` (a folder glasscan's reconstruction wrote, or none yet).
pub fn committed_run(out: &Path) -> Result<Existing> {
    Ok(match read_checkpoint(out)? {
        Some(checkpoint) => Existing::Run(Box::new(checkpoint)),
        None => Existing::Nothing,
    })
}

/// The names in `out` (sorted), or none when it does not exist; an error when it is a file.
fn folder_entries(out: &Path) -> Result<Vec<String>> {
    if !out.exists() {
        return Ok(Vec::new());
    }
    if !out.is_dir() {
        bail!(
            "{} is a file: the output of reconstruct is a folder; choose a new folder name",
            out.display()
        );
    }
    let mut names = Vec::new();
    for entry in std::fs::read_dir(out).with_context(|| format!("cannot read {}", out.display()))? {
        let entry = entry.with_context(|| format!("cannot read {}", out.display()))?;
        names.push(entry.file_name().to_string_lossy().into_owned());
    }
    names.sort();
    Ok(names)
}

/// Reads the committed checkpoint of `out`: `None` when there is none, an error naming the
/// file when it cannot be read or parsed (written by another glasscan version, or damaged).
fn read_checkpoint(out: &Path) -> Result<Option<Checkpoint>> {
    let path = checkpoint_path(out);
    let text = match std::fs::read_to_string(&path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => bail!("cannot read {}: {e}", path.display()),
    };
    serde_json::from_str(&text).map(Some).map_err(|e| {
        anyhow::anyhow!(
            "{} cannot be read ({e}): it was written by another glasscan version or is damaged; \
             finish that run with the version that made it, or start it over with --force",
            path.display()
        )
    })
}

/// Commits `checkpoint` as the state of the run in `out` (atomically).
pub fn commit(out: &Path, checkpoint: &Checkpoint) -> Result<()> {
    write_atomic(&checkpoint_path(out), |w| {
        serde_json::to_writer(&mut *w, checkpoint)?;
        Ok(())
    })
    .with_context(|| format!("cannot write {}", checkpoint_path(out).display()))
}

/// Decides what a run may do with `out` before any work is done.
///
/// - A new or empty folder: the run starts.
/// - A folder with a committed run: continued with `resume`, cleared and started anew with
///   `force`, refused otherwise.
/// - A folder holding only glasscan's files but no committed checkpoint (a run killed before its
///   first commit): started anew with `resume` or `force` (the files are leftovers), refused
///   otherwise; but with `resume`, committed passes ([`INDEX_PASS`], [`INDEX_FIT`]) are kept,
///   to be continued.
/// - A folder holding other files: always refused (`force` never deletes what glasscan did not
///   write).
///
/// The folder is locked for this process first ([`OutputLock`], held by the caller until the run
/// ends): a second run on it, or a `--resume` or `--force` while a run writes it, is refused.
/// The folder is created, so that a run that cannot write it stops before any work.
pub fn prepare(out: &Path, resume: bool, force: bool) -> Result<(Existing, OutputLock)> {
    let lock = OutputLock::acquire(out)?;
    let existing = existing_run(out, resume, force)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    Ok((existing, lock))
}

/// [`prepare`]'s decision, once the folder is locked.
fn existing_run(out: &Path, resume: bool, force: bool) -> Result<Existing> {
    let names = folder_entries(out)?;
    if names.is_empty() {
        return Ok(Existing::Nothing);
    }
    let mut foreign = None;
    for n in &names {
        if !is_glasscan_entry(out, n)? {
            foreign = Some(n);
            break;
        }
    }
    if let Some(other) = foreign {
        bail!(
            "{} holds files that are not a glasscan reconstruction (e.g. {other}): choose a new or \
             empty output folder",
            out.display()
        );
    }
    let committed = match read_checkpoint(out) {
        Err(_) if force => None,
        other => other?,
    };
    let committed_pass =
        (PASSES.iter().map(|n| out.join(n))).rfind(|p| checkpoint_path(p).is_file());
    match committed {
        Some(checkpoint) if resume && !force => Ok(Existing::Run(Box::new(checkpoint))),
        Some(checkpoint) if !force => bail!(
            "{} holds a run ({} of {} stages done): continue it with --resume, start it over with \
             --force, or choose another output folder",
            out.display(),
            checkpoint.stages_done,
            checkpoint.settings.total_stages()
        ),
        None if committed_pass.is_some() && !(resume || force) => bail!(
            "{} holds a run that is estimating the refractive index ({}): continue it with \
             --resume, start it over with --force, or choose another output folder",
            out.display(),
            committed_pass.unwrap_or_default().display()
        ),
        None if !(resume || force) => bail!(
            "{} holds the files of a run that stopped before its first checkpoint: start it over \
             with --resume or --force, or choose another output folder",
            out.display()
        ),
        None if committed_pass.is_some() && resume && !force => {
            let main: Vec<String> = names.into_iter().filter(|n| !is_pass(n)).collect();
            clear(out, &main)?;
            Ok(Existing::Nothing)
        }
        _ => {
            clear(out, &names)?;
            Ok(Existing::Nothing)
        }
    }
}

/// Removes glasscan's entries `names` from `out` (a pass's folder with its files).
fn clear(out: &Path, names: &[String]) -> Result<()> {
    for n in names {
        let p = out.join(n);
        if is_pass(n) && p.is_dir() {
            clear(&p, &folder_entries(&p)?)?;
            std::fs::remove_dir(&p)
        } else {
            std::fs::remove_file(&p)
        }
        .with_context(|| format!("cannot remove {}", p.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glasscan_files_are_recognised_by_name() {
        for n in [
            "stage_00.ply",
            "stage_123.ply",
            "checkpoint.json",
            ".glasscan-x1.tmp",
        ] {
            assert!(is_glasscan_file(n), "{n}");
        }
        for n in [
            "stage_.ply",
            "stage_0a.ply",
            "notes.txt",
            "scan.toml",
            "stage_01.obj",
        ] {
            assert!(!is_glasscan_file(n), "{n}");
        }
    }

    #[test]
    fn a_folder_with_foreign_files_is_refused_even_with_force() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("thesis.tex"), "x").unwrap();
        let e = prepare(dir.path(), true, true).unwrap_err().to_string();
        assert!(e.contains("thesis.tex"), "{e}");
        assert!(dir.path().join("thesis.tex").is_file());
    }

    #[test]
    fn leftovers_without_a_checkpoint_need_resume_or_force() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("hull.ply"), "x").unwrap();
        let e = prepare(dir.path(), false, false).unwrap_err().to_string();
        assert!(e.contains("before its first checkpoint"), "{e}");
        assert!(matches!(
            prepare(dir.path(), true, false).unwrap().0,
            Existing::Nothing
        ));
        assert!(!dir.path().join("hull.ply").exists());
    }

    #[test]
    fn a_file_is_not_an_output_folder() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("out");
        std::fs::write(&f, "x").unwrap();
        let e = prepare(&f, false, false).unwrap_err().to_string();
        assert!(e.contains("is a file"), "{e}");
    }
}
