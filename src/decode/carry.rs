//! What a decode of some views keeps of the previous decode: every file it does not write again
//! (the other views, the user's own files), and the other views' summaries, so that
//! `decode --views 0-1` updates those views and loses nothing.

use std::path::Path;

use anyhow::{Context, Result};

use crate::scan::decoded::{is_view_file, read_summary, ViewSummary};
use crate::util::fixed::FixedPoint;

/// Links (or, across file systems, copies) into `new` every file of the previous decoded folder
/// `old` except `summary.json` and the files of the views in `redone`; returns the previous
/// summaries of the views kept. Views of a previous decode made with another fixed-point scale
/// (another monitor) are not kept: their points would be read wrongly.
pub fn carry_over(
    old: &Path,
    new: &Path,
    redone: &[usize],
    fixed: &FixedPoint,
) -> Result<Vec<ViewSummary>> {
    if !old.is_dir() {
        return Ok(Vec::new());
    }
    let kept = match read_summary(old) {
        Ok(s) if s.fixed.scale == fixed.scale => s.views,
        _ => Vec::new(),
    };
    let stale = |name: &str| {
        redone.iter().any(|&k| is_view_file(name, k))
            || (!kept.iter().any(|s| is_view_file(name, s.view)) && name.starts_with("view_"))
    };
    link_tree(old, new, &|name| name == "summary.json" || stale(name))?;
    Ok(kept
        .into_iter()
        .filter(|s| !redone.contains(&s.view))
        .collect())
}

/// Links every file below `from` into the same place below `to`, except top-level and nested
/// files whose name `skip` names.
fn link_tree(from: &Path, to: &Path, skip: &dyn Fn(&str) -> bool) -> Result<()> {
    let entries =
        std::fs::read_dir(from).with_context(|| format!("cannot read {}", from.display()))?;
    for e in entries {
        let e = e.with_context(|| format!("cannot read {}", from.display()))?;
        let (src, dst) = (e.path(), to.join(e.file_name()));
        let name = e.file_name().to_string_lossy().into_owned();
        if e.file_type()?.is_dir() {
            std::fs::create_dir_all(&dst)
                .with_context(|| format!("cannot create {}", dst.display()))?;
            link_tree(&src, &dst, skip)?;
        } else if !skip(&name) && !dst.exists() {
            std::fs::hard_link(&src, &dst)
                .or_else(|_| std::fs::copy(&src, &dst).map(|_| ()))
                .with_context(|| format!("cannot keep {} in the new decode", src.display()))?;
        }
    }
    Ok(())
}
