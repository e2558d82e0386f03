//! Output paths checked before anything is written: an output never overwrites an input, and
//! its name's extension matches what is written into it.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};

/// The folder holding `path`: its parent, or `.` for a bare name.
pub fn parent_or_here(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// `path` made absolute with its symbolic links resolved, as far as it exists (a file or folder
/// still to be written keeps its own name under its resolved parent).
fn resolved(path: &Path) -> PathBuf {
    if let Ok(p) = path.canonicalize() {
        return p;
    }
    match (path.parent(), path.file_name()) {
        (Some(_), Some(name)) => resolved(parent_or_here(path)).join(name),
        _ => path.to_path_buf(),
    }
}

/// Refuses an output that is one of `inputs`, (an output folder) holds one, or lies inside one
/// (an input folder read whole, such as a scan's `decoded/`): writing it would destroy or change
/// what the command reads. Paths are compared with their symbolic links resolved. `option`
/// names the output's option for the message. Every command that writes calls it.
pub fn ensure_output_spares_inputs<P: AsRef<Path>>(
    output: &Path,
    option: &str,
    inputs: &[P],
) -> Result<()> {
    let out = resolved(output);
    for input in inputs {
        let input = input.as_ref();
        let inp = resolved(input);
        if inp == out || inp.starts_with(&out) || out.starts_with(&inp) {
            bail!(
                "{option} {} would overwrite the input {}: choose another output path",
                output.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// Refuses an output file whose extension is none of `extensions` (lower case, without the dot):
/// what is written must match the name (an error map named .jpg holding PNG bytes would mislead).
pub fn ensure_extension(output: &Path, option: &str, extensions: &[&str]) -> Result<()> {
    let ext = output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    if !ext.as_deref().is_some_and(|e| extensions.contains(&e)) {
        bail!(
            "{option} {}: this output is written as {}; give it that extension",
            output.display(),
            extensions
                .iter()
                .map(|e| format!(".{e}"))
                .collect::<Vec<_>>()
                .join(" or ")
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_that_are_or_hold_inputs_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mesh = dir.path().join("a.ply");
        std::fs::write(&mesh, "x").unwrap();
        let refused = |out: &Path| ensure_output_spares_inputs(out, "-o", &[&mesh]).is_err();
        assert!(refused(&mesh));
        assert!(refused(&dir.path().join(".").join("a.ply")));
        assert!(refused(dir.path()));
        assert!(!refused(&dir.path().join("b.ply")));
        assert!(!refused(&dir.path().join("new").join("a.ply")));
        // Inside an input folder.
        let decoded = dir.path().join("decoded");
        std::fs::create_dir(&decoded).unwrap();
        let inside = |out: &Path| ensure_output_spares_inputs(out, "-o", &[&decoded]).is_err();
        assert!(inside(&decoded.join("summary.json")));
        assert!(!inside(&dir.path().join("hull.ply")));
        // Through a symbolic link to the input.
        let link = dir.path().join("link");
        std::os::unix::fs::symlink(&decoded, &link).unwrap();
        assert!(inside(&link.join("x.json")));
    }

    #[test]
    fn extensions_must_match_the_format() {
        assert!(ensure_extension(Path::new("a.PNG"), "--x", &["png"]).is_ok());
        assert!(ensure_extension(Path::new("a.jpg"), "--x", &["png"]).is_err());
        assert!(ensure_extension(Path::new("a"), "--x", &["json"]).is_err());
    }
}
