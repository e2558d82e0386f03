//! Every `glasscan …` command the README shows runs as written: its subcommand and options
//! parse (no usage error, exit 2), and it either succeeds or stops with glasscan's one-line
//! error about the data it lacks (here, in an empty folder). Commands that need no data
//! (`patterns`, `--version`) must succeed.

use crate::common::{glasscan_cmd, markdown_lines, run};

/// The `glasscan …` commands in README.md's code spans and blocks.
fn readme_commands() -> Vec<String> {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    let mut found = Vec::new();
    for (line, in_block) in markdown_lines(&text) {
        if in_block {
            if line.trim_start().starts_with("glasscan ") {
                found.push(line.trim().to_string());
            }
            continue;
        }
        for (i, _) in line.match_indices("`glasscan ") {
            let rest = &line[i + 1..];
            if let Some(end) = rest.find('`') {
                found.push(rest[..end].to_string());
            }
        }
    }
    found
}

/// Splits a command line like a shell would for these examples (single quotes, spaces).
fn words(cmd: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    for c in cmd.chars() {
        match c {
            '\'' => quoted = !quoted,
            ' ' if !quoted => {
                if !cur.is_empty() {
                    out.push(std::mem::take(&mut cur));
                }
            }
            _ => cur.push(c),
        }
    }
    if !cur.is_empty() {
        out.push(cur);
    }
    out
}

#[test]
fn every_readme_command_parses_and_fails_only_for_want_of_data() {
    let commands = readme_commands();
    assert!(commands.len() >= 10, "{commands:?}");
    let dir = tempfile::tempdir().unwrap();
    for cmd in commands {
        let w = words(&cmd);
        // Placeholders for any subcommand are not commands.
        if w.iter().any(|x| x == "COMMAND") {
            continue;
        }
        let o = run(glasscan_cmd().args(&w[1..]).current_dir(dir.path()));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!err.contains("panicked"), "{cmd}: {err}");
        let needs_no_data = w[1] == "patterns" || w[1] == "--version";
        if needs_no_data {
            assert!(o.status.success(), "{cmd}: {err}");
        } else {
            assert!(
                o.status.success() || (o.status.code() == Some(1) && err.starts_with("error: ")),
                "{cmd}: exit {:?}: {err}",
                o.status.code()
            );
        }
    }
}
