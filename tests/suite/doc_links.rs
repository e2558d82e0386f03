//! Every pointer into the docs resolves: each Markdown file name followed by `#anchor`, written
//! in the README, the CHANGELOG, docs/ or a source comment, names a file that exists and a
//! heading in it (GitHub's anchors), and so does each `](#anchor)` link within a Markdown file.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use crate::common::markdown_lines;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// GitHub's anchor of a heading: lower case, punctuation and symbols dropped (`-` and `_`
/// kept), spaces turned into hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            '-' | '_' => Some(c),
            c if c.is_alphanumeric() => Some(c.to_lowercase().next().unwrap_or(c)),
            _ => None,
        })
        .collect()
}

/// The anchors of a Markdown file's headings (outside code blocks), with GitHub's `-1`, `-2`
/// suffixes on repeats.
fn anchors(markdown: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    for (line, in_block) in markdown_lines(markdown) {
        let Some(text) = line.strip_prefix('#').map(|l| l.trim_start_matches('#')) else {
            continue;
        };
        if in_block || !text.starts_with(' ') {
            continue;
        }
        let base = slug(text);
        let mut anchor = base.clone();
        let mut n = 0;
        while !found.insert(anchor.clone()) {
            n += 1;
            anchor = format!("{base}-{n}");
        }
    }
    found
}

/// The files whose text may point into the docs.
fn sources() -> Vec<PathBuf> {
    let root = Path::new(ROOT);
    let mut files = vec![root.join("README.md"), root.join("CHANGELOG.md")];
    let mut dirs = vec![root.join("docs"), root.join("src"), root.join("tests")];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
            } else if matches!(path.extension().and_then(|e| e.to_str()), Some("md" | "rs")) {
                files.push(path);
            }
        }
    }
    files.sort();
    files
}

fn is_path_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.' | '/')
}

fn is_anchor_char(c: char) -> bool {
    c.is_alphanumeric() || matches!(c, '_' | '-')
}

/// The (file, anchor) pointers in `text`, read in `file`: a path from the repository's root
/// (`docs/…`), a bare file name (beside `file`, else under docs/), each followed by `#` and the
/// anchor, and in Markdown `](#a)` (into `file` itself).
fn pointers(file: &Path, text: &str) -> Vec<(PathBuf, String)> {
    let mut out = Vec::new();
    for (i, _) in text.match_indices(".md#") {
        let start = text[..i]
            .rfind(|c: char| !is_path_char(c))
            .map_or(0, |p| p + 1);
        let name = &text[start..i + 3];
        let anchor: String = text[i + 4..]
            .chars()
            .take_while(|&c| is_anchor_char(c))
            .collect();
        if start == i || anchor.is_empty() {
            continue; // not a pointer: this file's own search pattern
        }
        let beside = file.parent().unwrap().join(name);
        let target = if name.contains('/') {
            Path::new(ROOT).join(name)
        } else if beside.exists() {
            beside
        } else {
            Path::new(ROOT).join("docs").join(name)
        };
        out.push((target, anchor));
    }
    if file.extension().is_some_and(|e| e == "md") {
        for (i, _) in text.match_indices("](#") {
            let anchor: String = text[i + 3..]
                .chars()
                .take_while(|&c| is_anchor_char(c))
                .collect();
            out.push((file.to_path_buf(), anchor));
        }
    }
    out
}

#[test]
fn headings_give_githubs_anchors() {
    assert_eq!(
        slug("Refraction loss + gradient (`glasscan bench gradient`)"),
        "refraction-loss--gradient-glasscan-bench-gradient"
    );
    assert_eq!(
        slug("Camera resolution (`--size 2448x2048`)"),
        "camera-resolution---size-2448x2048"
    );
    let a = anchors("# A b\n```\n# not a heading\n```\n## A b\n#tag\n");
    assert_eq!(a, BTreeSet::from(["a-b".to_string(), "a-b-1".to_string()]));
}

#[test]
fn every_pointer_into_the_docs_names_a_heading_that_exists() {
    let mut broken = Vec::new();
    let mut checked = 0;
    for file in sources() {
        let text = std::fs::read_to_string(&file).unwrap();
        for (target, anchor) in pointers(&file, &text) {
            checked += 1;
            let here = file.strip_prefix(ROOT).unwrap().display().to_string();
            match std::fs::read_to_string(&target) {
                Err(_) => broken.push(format!("{here}: no file {}", target.display())),
                Ok(md) if !anchors(&md).contains(&anchor) => broken.push(format!(
                    "{here}: no heading #{anchor} in {}",
                    target.display()
                )),
                Ok(_) => {}
            }
        }
    }
    assert!(
        checked > 50,
        "only {checked} pointers found: the scan is broken"
    );
    assert!(
        broken.is_empty(),
        "{} broken:\n{}",
        broken.len(),
        broken.join("\n")
    );
}
