//! The module graph goes one way down: the layering table of docs/architecture.md §10, checked
//! against every `crate::` path in the sources (and every `glasscan::` path of the command
//! line, which lives in the binary).

use std::collections::BTreeMap;
use std::path::Path;

/// Level of each top-level module (docs/architecture.md §10).
const LEVELS: &[(&str, u32)] = &[
    ("util", 0),
    ("mesh", 1),
    ("rig", 1),
    ("patterns", 1),
    ("trace", 2),
    ("scan", 2),
    ("remesh", 3),
    ("eval", 3),
    ("decode", 3),
    ("capture", 3),
    ("calibrate", 4),
    ("simulate", 5),
    ("hull", 5),
    ("loss", 5),
    ("import", 5),
    ("reconstruct", 6),
    ("bench", 7),
    ("cli", 8),
];

/// Uses that break the table today, each to be removed (and then from here).
const KNOWN_EXCEPTIONS: &[(&str, &str)] = &[];

/// The `crate::NAME` modules named in the sources of `module` (a folder or a file).
fn uses(src: &Path, module: &str) -> Vec<String> {
    let mut files = Vec::new();
    let dir = src.join(module);
    if dir.is_dir() {
        let mut stack = vec![dir];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else if p.extension().is_some_and(|x| x == "rs") {
                    files.push(p);
                }
            }
        }
    } else {
        files.push(src.join(format!("{module}.rs")));
    }
    let mut used = Vec::new();
    for f in files {
        let text = std::fs::read_to_string(&f).unwrap();
        // The command line, in the binary, names the library's modules as `glasscan::`.
        let paths = text
            .match_indices("crate::")
            .chain(text.match_indices("glasscan::"));
        for (i, prefix) in paths {
            let name: String = text[i + prefix.len()..]
                .chars()
                .take_while(|c| c.is_ascii_lowercase() || *c == '_')
                .collect();
            if !name.is_empty() && name != module {
                used.push(name);
            }
        }
    }
    used.sort();
    used.dedup();
    used
}

#[test]
fn no_module_uses_a_module_above_it() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let level: BTreeMap<&str, u32> = LEVELS.iter().copied().collect();
    let mut wrong = Vec::new();
    for &(module, own) in LEVELS {
        for used in uses(&src, module) {
            let Some(&theirs) = level.get(used.as_str()) else {
                wrong.push(format!(
                    "{module} uses crate::{used}, which the table does not list"
                ));
                continue;
            };
            if theirs > own && !KNOWN_EXCEPTIONS.contains(&(module, used.as_str())) {
                wrong.push(format!(
                    "{module} (level {own}) uses {used} (level {theirs})"
                ));
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    // Every module in src/ is in the table.
    for e in std::fs::read_dir(&src).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().replace(".rs", "");
        if !["lib", "main"].contains(&name.as_str()) {
            assert!(
                level.contains_key(name.as_str()),
                "src/{name} is not in the table"
            );
        }
    }
}
