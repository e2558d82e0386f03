//! Edges where the data keeps pulling: before a graded stage remeshes, the refraction rays of a
//! spread of the fitted views are traced through the mesh the stage starts from, and where their
//! mean penalty at a vertex is well above the surface's typical one the vertex's next edges are
//! bounded, so that the stage has the vertices to follow what the coarser mesh could not
//! (docs/decisions.md#edges-where-the-data-keeps-pulling).
//!
//! The rule is in shares, not camera pixels: a penalty is a per-ray mean (unitless for the
//! direction residual), compared with the area median of the same means. A vertex whose mean
//! penalty `m` exceeds the target `t` gets edges `t / m` times its current ones, never shorter
//! than the stage's edge. On a piecewise-flat surface a ray's direction residual grows with the
//! edge (a facet's normal error is about edge × curvature), its squared residual with the
//! edge squared, which would ask for `sqrt(t / m)`; but the robust penalty grows more slowly
//! than the squared residual where the residual is large, and the square root moved too few
//! edges to matter (the decision's entry gives both measurements).

use anyhow::Result;

use super::confidence::MIN_RAYS;
use super::config::Settings;
use super::terms::{add_refraction, IndexSlope, Sample};
use super::validation::Split;
use super::Inputs;
use crate::loss::Accumulator;
use crate::mesh::TriMesh;
use crate::trace::path::MeshSurface;
use crate::trace::BuildMode;
use crate::util::weighted_median;

/// Every how many of the fitted views the pass traces: 72 views, 7 held out, give 17 views
/// spread around the turntable, about four iterations' worth of `balanced`'s rays.
const VIEW_STEP: usize = 4;

/// Per vertex of `mesh` (the stage's start, world frame, mm), the longest edge the data asks
/// for there, mm: infinite where the rays' mean penalty is at most `settings.sizing_pull` times
/// the area median (the target), else the vertex's mean edge length × target / mean penalty,
/// at least `edge_mm` (the stage's edge, mm). `None` when the rule is off or no vertex has rays
/// enough to judge.
pub fn data_edge_bounds(
    (inputs, ior): (&Inputs, f64),
    split: &Split,
    (mesh, edge_mm): (&TriMesh, f64),
    settings: &Settings,
) -> Result<Option<Vec<f64>>> {
    if settings.sizing_pull <= 0.0 {
        return Ok(None);
    }
    let means = mean_penalties((inputs, ior), split, mesh, settings)?;
    let areas = mesh.vertex_areas();
    let known = (means.iter().zip(&areas)).filter_map(|(m, &a)| m.map(|m| (m, a)));
    let Some(median) = weighted_median(known.collect()) else {
        return Ok(None);
    };
    let target = settings.sizing_pull * median;
    let lengths = mean_edge_lengths(mesh);
    Ok(Some(
        means
            .iter()
            .zip(&lengths)
            .map(|(m, &len)| match m {
                Some(m) if *m > target && len > 0.0 => (len * target / m).max(edge_mm),
                _ => f64::INFINITY,
            })
            .collect(),
    ))
}

/// Per vertex, the mean penalty of the refraction rays at its faces over every `VIEW_STEP`-th
/// fitted view (each view's own ray sample at offset ½); `None` with fewer than [`MIN_RAYS`].
fn mean_penalties(
    (inputs, ior): (&Inputs, f64),
    split: &Split,
    mesh: &TriMesh,
    settings: &Settings,
) -> Result<Vec<Option<f64>>> {
    let surface = MeshSurface::with_mode(mesh, settings.normals, BuildMode::Static)?;
    let mut acc = Accumulator::counting(mesh.positions.len(), surface.vertex_normals().is_some());
    let views: Vec<(usize, Sample)> = (split.fit_targets.iter().step_by(VIEW_STEP))
        .map(|&t| (t, Sample::Offset(0.5)))
        .collect();
    let slope = IndexSlope::Unneeded;
    add_refraction(
        (inputs, ior),
        &surface,
        mesh,
        settings,
        &views,
        slope,
        &mut acc,
    )?;
    Ok((acc.touches.iter().zip(&acc.penalty))
        .map(|(&n, &p)| (n >= MIN_RAYS).then(|| p / n as f64))
        .collect())
}

/// Per vertex, the mean length of its edges, mm (0 for an isolated vertex).
fn mean_edge_lengths(mesh: &TriMesh) -> Vec<f64> {
    let n = mesh.positions.len();
    let (mut sum, mut count) = (vec![0.0; n], vec![0u32; n]);
    for [u, v] in crate::mesh::stats::unique_edges(mesh) {
        let len = (mesh.positions[u as usize] - mesh.positions[v as usize]).norm();
        for w in [u as usize, v as usize] {
            sum[w] += len;
            count[w] += 1;
        }
    }
    sum.iter()
        .zip(&count)
        .map(|(s, &c)| if c > 0 { s / c as f64 } else { 0.0 })
        .collect()
}
