//! Is a remeshed surface still the input's shape? Checked before a remesh (`glasscan remesh`,
//! the hull's remesh) is written: the same topology (components, genus), an enclosed volume
//! within [`VOLUME_RATIO`] of the input's, and both one-sided mean distances (output → input,
//! input → output) within [`MEAN_DISTANCE_EDGES`] edge lengths. A remesh whose edges are too
//! long for the shape's features fails one of these (a pig remeshed at 30 mm edges keeps
//! 16 faces 2.6 mm across: its volume ratio is about 0).

use crate::mesh::validate::validate;
use crate::mesh::TriMesh;
use crate::remesh::{remesh, RemeshError, RemeshOptions};
use crate::trace::{BuildMode, Device, Scene, TraceError};

use super::sampled_distances;

/// Largest allowed |volume ratio − 1| between output and input.
pub const VOLUME_RATIO: f64 = 0.2;
/// Largest allowed mean distance in either direction, in (target) edge lengths.
pub const MEAN_DISTANCE_EDGES: f64 = 0.25;
/// Surface samples per side for the distances.
const SAMPLES: usize = 20_000;

/// The figures [`check`] compares.
#[derive(Clone, Debug)]
pub struct Fidelity {
    pub volume_ratio: f64,
    /// Mean distance output → input, mm.
    pub mean_out_in_mm: f64,
    /// Mean distance input → output, mm.
    pub mean_in_out_mm: f64,
}

/// Why a remeshed surface was refused.
#[derive(Debug, thiserror::Error)]
pub enum FidelityError {
    #[error("{0}")]
    Lost(String),
    #[error(transparent)]
    Remesh(#[from] RemeshError),
    #[error(transparent)]
    Trace(#[from] TraceError),
}

/// Checks `output` (a remesh of `input` at edge length `edge_mm`) against `input`; see the
/// module doc. Seeded sampling (`seed`).
pub fn check(
    input: &TriMesh,
    output: &TriMesh,
    edge_mm: f64,
    seed: u64,
) -> Result<Fidelity, FidelityError> {
    let lost = |why: String| Err(FidelityError::Lost(why));
    let (vi, vo) = (validate(input), validate(output));
    if !vo.is_valid() {
        let defects: Vec<String> = vo.defects.iter().map(|d| d.to_string()).collect();
        return lost(format!(
            "the result is not a valid surface ({})",
            defects.join("; ")
        ));
    }
    if (vo.components, vo.genus) != (vi.components, vi.genus) {
        return lost(format!(
            "the result has {} component(s) of genus {:?}, the input {} of genus {:?}",
            vo.components, vo.genus, vi.components, vi.genus
        ));
    }
    let volume_ratio = output.signed_volume() / input.signed_volume();
    let off = (volume_ratio - 1.0).abs();
    if off.is_nan() || off > VOLUME_RATIO {
        return lost(format!(
            "the result encloses {:.1} % of the input's volume",
            100.0 * volume_ratio
        ));
    }
    let device = Device::new()?;
    let mean = |from: &TriMesh, to: &TriMesh, seed| -> Result<f64, TraceError> {
        let scene = Scene::new(&device, to, BuildMode::Static)?;
        let d = sampled_distances(from, &scene, SAMPLES, seed)?;
        Ok(d.iter().sum::<f64>() / d.len().max(1) as f64)
    };
    let f = Fidelity {
        volume_ratio,
        mean_out_in_mm: mean(output, input, seed)?,
        mean_in_out_mm: mean(input, output, seed.wrapping_add(1))?,
    };
    let limit = MEAN_DISTANCE_EDGES * edge_mm;
    let worst = f.mean_out_in_mm.max(f.mean_in_out_mm);
    if worst.is_nan() || worst > limit {
        return lost(format!(
            "the result lies {:.3} mm (output → input) and {:.3} mm (input → output) from the \
             input on average, more than {MEAN_DISTANCE_EDGES} edge lengths ({limit:.3} mm)",
            f.mean_out_in_mm, f.mean_in_out_mm
        ));
    }
    Ok(f)
}

/// Remeshes `input` with `opts` and [`check`]s the result. When the result has lost the
/// shape, the error names the largest edge length (of h/2, h/4, … h/256) whose remesh keeps it.
pub fn remesh_checked(
    input: &TriMesh,
    opts: &RemeshOptions,
    seed: u64,
) -> Result<(TriMesh, Fidelity), FidelityError> {
    let output = remesh(input, opts)?;
    match check(input, &output, opts.edge_mm, seed) {
        Ok(f) => Ok((output, f)),
        Err(FidelityError::Lost(why)) => {
            let hint = largest_usable_edge(input, opts, seed).map_or_else(
                || "no edge length down to h/256 keeps it".to_string(),
                |h| format!("the largest usable edge is about {h:.4} mm"),
            );
            Err(FidelityError::Lost(format!(
                "remeshing at {} mm edges loses the shape: {why}; {hint}",
                opts.edge_mm
            )))
        }
        Err(e) => Err(e),
    }
}

/// The first of h/2, h/4, … h/256 whose remesh passes [`check`].
fn largest_usable_edge(input: &TriMesh, opts: &RemeshOptions, seed: u64) -> Option<f64> {
    (1..=8)
        .map(|k| opts.edge_mm / f64::powi(2.0, k))
        .find(|&h| {
            let o = RemeshOptions {
                edge_mm: h,
                adaptive: opts.adaptive.map(|a| crate::remesh::AdaptiveSizing {
                    min_edge_mm: a.min_edge_mm.min(h),
                    ..a
                }),
                ..opts.clone()
            };
            remesh(input, &o).is_ok_and(|out| check(input, &out, h, seed).is_ok())
        })
}
