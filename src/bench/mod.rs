//! Benchmarks behind `glasscan bench …`: they measure what they name and print ratios.

pub mod calibrated;
pub mod gradient;
pub mod reconstruct;
pub mod remesh;
pub mod trace;

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use crate::mesh::io::read_mesh;
use crate::mesh::shapes::{cut_prism, glass_block};
use crate::mesh::TriMesh;
use crate::trace::path::NormalModel;
use crate::util::atomic::write_atomic;

/// The benchmark objects built in rather than read: [`glass_block`] (1 mm marching-cubes steps,
/// rounded edges) and [`cut_prism`] (flat facets, sharp edges).
pub const BUILT_IN_BLOCK: &str = "block";
pub const BUILT_IN_PRISM: &str = "prism";

/// Where a benchmark object's mesh comes from: `block` and `prism` are built in, any other name
/// is `{meshes}/{name}_scan.ply`, which must exist (checked before any work).
pub enum ObjectMesh {
    Block,
    Prism,
    File(PathBuf),
}

impl ObjectMesh {
    pub fn locate(meshes: &Path, name: &str) -> Result<Self> {
        match name {
            BUILT_IN_BLOCK => return Ok(ObjectMesh::Block),
            BUILT_IN_PRISM => return Ok(ObjectMesh::Prism),
            _ => {}
        }
        let path = meshes.join(format!("{name}_scan.ply"));
        if !path.is_file() {
            bail!(
                "{}: no such mesh (--meshes names the folder of {{object}}_scan.ply; `{BUILT_IN_BLOCK}` and `{BUILT_IN_PRISM}` are built in)",
                path.display()
            );
        }
        Ok(ObjectMesh::File(path))
    }

    /// The mesh (world frame, mm).
    pub fn read(&self) -> Result<TriMesh> {
        match self {
            ObjectMesh::Block => Ok(glass_block(1.0)),
            ObjectMesh::Prism => Ok(cut_prism()),
            ObjectMesh::File(p) => Ok(read_mesh(p)?),
        }
    }

    /// The normals its scans are simulated with: the prism's facets are flat and its edges
    /// sharp; the other objects are smooth glass.
    pub fn normals(&self) -> NormalModel {
        match self {
            ObjectMesh::Prism => NormalModel::Face,
            ObjectMesh::Block | ObjectMesh::File(_) => NormalModel::Vertex,
        }
    }

    /// What the logs call it.
    pub fn describe(&self) -> String {
        match self {
            ObjectMesh::Block => "the built-in glass block".into(),
            ObjectMesh::Prism => "the built-in cut prism".into(),
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
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the earlier results in {}", path.display()))?;
    serde_json::from_str(&text)
        .with_context(|| format!("{}: not this benchmark's results file", path.display()))
}

/// Writes `runs` as JSON to `json` and `table` to `md`, both atomically.
fn write_runs<T: serde::Serialize>(json: &Path, runs: &[T], md: &Path, table: &str) -> Result<()> {
    write_atomic(json, |w| {
        serde_json::to_writer_pretty(&mut *w, runs)?;
        Ok(())
    })
    .with_context(|| format!("cannot write {}", json.display()))?;
    write_atomic(md, |w| w.write_all(table.as_bytes()))
        .with_context(|| format!("cannot write {}", md.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unreadable_results_file_is_named_in_the_error() {
        let dir = tempfile::tempdir().unwrap();
        assert!(
            read_runs::<serde_json::Value>(&dir.path().join("none.json"))
                .unwrap()
                .is_empty()
        );
        let bad = dir.path().join("results.json");
        std::fs::write(&bad, [0xff, 0xfe, b'[', b']']).unwrap();
        let e = format!("{:#}", read_runs::<serde_json::Value>(&bad).unwrap_err());
        assert!(e.starts_with("cannot read the earlier results in "), "{e}");
        assert!(e.contains("results.json"), "{e}");
        std::fs::write(&bad, "{\"a\": 1}").unwrap();
        let e = format!("{:#}", read_runs::<serde_json::Value>(&bad).unwrap_err());
        assert!(e.contains("not this benchmark's results file"), "{e}");
    }
}
