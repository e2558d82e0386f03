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

/// The most faces a remesh tried for [`largest_usable_edge`]'s hint may make: this many per
/// face of the input, and at least [`HINT_MIN_FACES`]. The hint only names an edge; a search
/// down to h/256 on a large surface remeshed to tens of millions of faces for it (a hull of
/// 110 k faces and 45,000 mm² at 1 mm edges ran for over 10 minutes).
const HINT_FACES_PER_INPUT_FACE: f64 = 4.0;
/// See [`HINT_FACES_PER_INPUT_FACE`].
const HINT_MIN_FACES: f64 = 1e6;

/// Remeshes `input` with `opts` and [`check`]s the result. When the result has lost the
/// shape, the error names the largest edge length (of h/2, h/4, … h/256, as far as
/// [`hint_edges`] reaches) whose remesh keeps it.
pub fn remesh_checked(
    input: &TriMesh,
    opts: &RemeshOptions,
    seed: u64,
) -> Result<(TriMesh, Fidelity), FidelityError> {
    let output = remesh(input, opts)?;
    match check(input, &output, opts.edge_mm, seed) {
        Ok(f) => Ok((output, f)),
        Err(FidelityError::Lost(why)) => {
            let edges = hint_edges(input, opts.edge_mm);
            let finest = edges.last().copied().unwrap_or(opts.edge_mm);
            let hint = largest_usable_edge(input, opts, &edges, seed).map_or_else(
                || format!("no edge length down to {finest:.4} mm keeps it"),
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

/// h/2, h/4, … h/256, as long as a remesh of `input`'s area at that edge stays within the
/// hint's face budget ([`HINT_FACES_PER_INPUT_FACE`]; an equilateral triangle of side e has
/// area √3/4·e²).
fn hint_edges(input: &TriMesh, h: f64) -> Vec<f64> {
    let budget = (HINT_FACES_PER_INPUT_FACE * input.faces.len() as f64).max(HINT_MIN_FACES);
    let area = input.area();
    let faces_at = |e: f64| area / (3f64.sqrt() / 4.0 * e * e);
    (1..=8)
        .map(|k| h / f64::powi(2.0, k))
        .take_while(|&e| faces_at(e) <= budget)
        .collect()
}

/// The first of `edges` whose remesh of `input` passes [`check`].
fn largest_usable_edge(
    input: &TriMesh,
    opts: &RemeshOptions,
    edges: &[f64],
    seed: u64,
) -> Option<f64> {
    edges.iter().copied().find(|&h| {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::shapes::icosphere;

    /// The hint's edges halve from h/2 and stop before a remesh would exceed its face budget:
    /// a sphere of radius 100 mm (about 125,000 mm², 1,280 faces: the 10⁶-face floor) at
    /// h = 4 mm takes 2 and 1 mm (about 0.29 M faces at 1), not 0.5 (1.16 M).
    #[test]
    fn the_hint_search_stays_within_its_face_budget() {
        let sphere = icosphere(100.0, 3);
        assert_eq!(hint_edges(&sphere, 4.0), vec![2.0, 1.0]);
        // A small one reaches h/256.
        assert_eq!(hint_edges(&icosphere(1.0, 3), 4.0).len(), 8);
    }
}
