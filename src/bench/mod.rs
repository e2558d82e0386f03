//! Benchmarks behind `glasscan bench …`: they measure what they name and print ratios.

pub mod calibrated;
pub mod gradient;
pub mod reconstruct;
pub mod remesh;
pub mod trace;

use std::path::Path;

use anyhow::{Context, Result};

use crate::util::atomic::write_atomic;

/// The runs a benchmark's results file at `path` holds (none when there is no such file), so
/// that a rerun skips them.
fn read_runs<T: serde::de::DeserializeOwned>(path: &Path) -> Result<Vec<T>> {
    if !path.is_file() {
        return Ok(Vec::new());
    }
    serde_json::from_str(&std::fs::read_to_string(path)?)
        .with_context(|| format!("{}: not this benchmark's results file", path.display()))
}

/// Writes `runs` as JSON to `json` and `table` to `md`, both atomically.
fn write_runs<T: serde::Serialize>(json: &Path, runs: &[T], md: &Path, table: &str) -> Result<()> {
    write_atomic(json, |w| {
        serde_json::to_writer_pretty(&mut *w, runs)?;
        Ok(())
    })?;
    write_atomic(md, |w| w.write_all(table.as_bytes()))?;
    Ok(())
}
