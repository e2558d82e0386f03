//! Benchmarks behind `glasscan bench …`: they measure what they name and print ratios.

pub mod calibrated;
pub mod gradient;
pub mod reconstruct;
pub mod remesh;
pub mod trace;

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use crate::mesh::io::read_mesh;
use crate::mesh::shapes::glass_block;
use crate::mesh::TriMesh;
use crate::util::atomic::write_atomic;

/// The benchmark object built in rather than read: [`glass_block`] (1 mm marching-cubes steps).
pub const BUILT_IN_BLOCK: &str = "block";

/// Where a benchmark object's mesh comes from: `block` is built in, any other name is
/// `{meshes}/{name}_scan.ply`, which must exist (checked before any work).
pub enum ObjectMesh {
    Block,
    File(PathBuf),
}

impl ObjectMesh {
    pub fn locate(meshes: &Path, name: &str) -> Result<Self> {
        if name == BUILT_IN_BLOCK {
            return Ok(ObjectMesh::Block);
        }
        let path = meshes.join(format!("{name}_scan.ply"));
        if !path.is_file() {
            bail!(
                "{}: no such mesh (--meshes names the folder of {{object}}_scan.ply; `{BUILT_IN_BLOCK}` is built in)",
                path.display()
            );
        }
        Ok(ObjectMesh::File(path))
    }

    /// The mesh (world frame, mm).
    pub fn read(&self) -> Result<TriMesh> {
        match self {
            ObjectMesh::Block => Ok(glass_block(1.0)),
            ObjectMesh::File(p) => Ok(read_mesh(p)?),
        }
    }

    /// What the logs call it.
    pub fn describe(&self) -> String {
        match self {
            ObjectMesh::Block => "the built-in glass block".into(),
            ObjectMesh::File(p) => p.display().to_string(),
        }
    }
}

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
