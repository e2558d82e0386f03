//! Reconstruction metrics against a reference mesh (docs/architecture.md §9).
//!
//! Both meshes are sampled uniformly by area (seeded); each sample's exact distance to the other
//! surface (closest point on its triangles, f64, pruned by Embree's BVH) gives
//! - accuracy: mean distance result → reference (mm),
//! - the signed accuracy: the same with the distance counted negative where the result lies
//!   inside the reference (the side of the closest triangle's plane), and the share of the
//!   result's area outside — whether a result is too large (say, a hull not carved away) or too
//!   small,
//! - completeness: mean distance reference → result (mm),
//! - F-score at threshold τ: harmonic mean of precision (share of result samples within τ of the
//!   reference) and recall (share of reference samples within τ of the result),
//! - DRT's figure: mean distance from the result's vertices to the reference surface (mm),
//! - Hausdorff: the largest distance seen in either direction, vertices included (mm).

pub mod confidence;
pub mod error_map;
pub mod fidelity;

use std::collections::BTreeMap;

use nalgebra::Point3;
use serde::Serialize;

use crate::mesh::sample::sample_surface;
use crate::mesh::TriMesh;
use crate::trace::{BuildMode, ClosestPoint, Device, Scene, TraceError};

/// What [`evaluate`] samples and reports.
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Surface samples drawn on each mesh.
    pub samples: usize,
    /// F-score thresholds, mm.
    pub thresholds_mm: Vec<f64>,
    /// Seed of the sampling.
    pub seed: u64,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            samples: 1_000_000,
            thresholds_mm: vec![0.5, 1.0],
            seed: 0,
        }
    }
}

/// Precision, recall and F-score at one threshold.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FScore {
    pub threshold_mm: f64,
    pub precision: f64,
    pub recall: f64,
    pub fscore: f64,
}

/// The metrics of a result mesh against a reference (mm).
#[derive(Clone, Debug, PartialEq)]
pub struct EvalReport {
    pub accuracy_mm: f64,
    /// Mean signed distance result → reference (mm, > 0 outside the reference).
    pub signed_accuracy_mm: f64,
    /// Share of the result's samples outside the reference.
    pub outside_share: f64,
    pub completeness_mm: f64,
    pub fscores: Vec<FScore>,
    pub drt_mean_mm: f64,
    pub hausdorff_mm: f64,
    /// Samples drawn on each mesh.
    pub samples: usize,
}

impl EvalReport {
    /// The JSON form `glasscan eval --json` writes: exactly the keys `accuracy_mm`,
    /// `signed_accuracy_mm`, `outside_share`, `completeness_mm`, `fscore` (threshold in mm as a
    /// decimal string → F-score), `drt_mean_mm`, `hausdorff_mm`.
    pub fn to_json(&self) -> serde_json::Value {
        let fscore: BTreeMap<String, f64> = self
            .fscores
            .iter()
            .map(|f| (threshold_key(f.threshold_mm), f.fscore))
            .collect();
        serde_json::json!({
            "accuracy_mm": self.accuracy_mm,
            "signed_accuracy_mm": self.signed_accuracy_mm,
            "outside_share": self.outside_share,
            "completeness_mm": self.completeness_mm,
            "fscore": fscore,
            "drt_mean_mm": self.drt_mean_mm,
            "hausdorff_mm": self.hausdorff_mm,
        })
    }
}

/// A threshold as a JSON key: `0.5` → "0.5", `1.0` → "1.0".
pub fn threshold_key(t: f64) -> String {
    format!("{t:?}")
}

/// Refuses meshes without area and sample counts beyond the memory budget.
fn check_inputs(
    result: &TriMesh,
    reference: &TriMesh,
    options: &EvalOptions,
) -> Result<(), EvalError> {
    for (name, m) in [("result", result), ("reference", reference)] {
        if m.area().is_nan() || m.area() <= 0.0 {
            return Err(EvalError::NoArea(name));
        }
    }
    crate::util::budget::check(
        &format!("{} samples per mesh", options.samples),
        options.samples as u128,
        BYTES_PER_SAMPLE,
        "use fewer --samples",
    )?;
    Ok(())
}

/// Evaluates `result` against `reference`; see the module documentation for the metrics.
pub fn evaluate(
    result: &TriMesh,
    reference: &TriMesh,
    options: &EvalOptions,
) -> Result<EvalReport, EvalError> {
    check_inputs(result, reference, options)?;
    let device = Device::new()?;
    let res_scene = Scene::new(&device, result, BuildMode::Static)?;
    let ref_scene = Scene::new(&device, reference, BuildMode::Static)?;
    evaluate_on((result, &res_scene), (reference, &ref_scene), options)
}

/// As [`evaluate`], with each mesh's ray-tracing structure (a [`BuildMode::Static`] scene of it)
/// already built, for a caller that uses them again.
pub fn evaluate_on(
    (result, res_scene): (&TriMesh, &Scene),
    (reference, ref_scene): (&TriMesh, &Scene),
    options: &EvalOptions,
) -> Result<EvalReport, EvalError> {
    check_inputs(result, reference, options)?;
    // Different seeds on the two sides, so that evaluating a mesh against itself does not sample
    // the very same points twice.
    let (pts, closest) = sampled_closest(result, ref_scene, options.samples, options.seed)?;
    let d_res_signed: Vec<f64> = pts
        .iter()
        .zip(&closest)
        .map(|(p, c)| signed_distance(p, c, reference))
        .collect();
    let d_res: Vec<f64> = d_res_signed.iter().map(|d| d.abs()).collect();
    let d_ref = sampled_distances(
        reference,
        res_scene,
        options.samples,
        options.seed.wrapping_add(1),
    )?;
    let d_vert: Vec<f64> = ref_scene
        .closest_points(&used_vertices(result))?
        .into_iter()
        .map(|c| c.dist)
        .collect();
    let d_ref_vert: Vec<f64> = res_scene
        .closest_points(&used_vertices(reference))?
        .into_iter()
        .map(|c| c.dist)
        .collect();

    let mean = |d: &[f64]| d.iter().sum::<f64>() / d.len().max(1) as f64;
    let within =
        |d: &[f64], t: f64| d.iter().filter(|&&x| x <= t).count() as f64 / d.len().max(1) as f64;
    let fscores = options
        .thresholds_mm
        .iter()
        .map(|&t| {
            let (p, r) = (within(&d_res, t), within(&d_ref, t));
            let f = if p + r > 0.0 {
                2.0 * p * r / (p + r)
            } else {
                0.0
            };
            FScore {
                threshold_mm: t,
                precision: p,
                recall: r,
                fscore: f,
            }
        })
        .collect();
    let hausdorff_mm = [&d_res, &d_ref, &d_vert, &d_ref_vert]
        .iter()
        .flat_map(|d| d.iter())
        .copied()
        .fold(0.0, f64::max);
    Ok(EvalReport {
        accuracy_mm: mean(&d_res),
        signed_accuracy_mm: mean(&d_res_signed),
        outside_share: d_res_signed.iter().filter(|&&d| d > 0.0).count() as f64
            / d_res_signed.len().max(1) as f64,
        completeness_mm: mean(&d_ref),
        fscores,
        drt_mean_mm: mean(&d_vert),
        hausdorff_mm,
        samples: options.samples,
    })
}

/// Why [`evaluate`] failed.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("the {0} mesh has no area (no face, or only degenerate ones): nothing to measure")]
    NoArea(&'static str),
    #[error(transparent)]
    Budget(#[from] crate::util::budget::OverBudget),
    #[error(transparent)]
    Trace(#[from] TraceError),
}

/// Memory per sample and side: the point and normal, its closest point and distance.
const BYTES_PER_SAMPLE: u128 = 2 * 112;

/// The positions of the vertices some face uses (a stray vertex is no part of the surface).
fn used_vertices(mesh: &TriMesh) -> Vec<Point3<f64>> {
    let mut used = vec![false; mesh.positions.len()];
    for f in &mesh.faces {
        for &v in f {
            used[v as usize] = true;
        }
    }
    mesh.positions
        .iter()
        .zip(used)
        .filter_map(|(p, u)| u.then_some(*p))
        .collect()
}

/// `samples` points drawn uniformly by area on `from` (seeded) and their closest points on the
/// surface in `to`.
fn sampled_closest(
    from: &TriMesh,
    to: &Scene,
    samples: usize,
    seed: u64,
) -> Result<(Vec<Point3<f64>>, Vec<ClosestPoint>), TraceError> {
    let pts: Vec<Point3<f64>> = sample_surface(from, samples, seed)
        .into_iter()
        .map(|(p, _)| p)
        .collect();
    let closest = to.closest_points(&pts)?;
    Ok((pts, closest))
}

/// Distances (mm) from `samples` points drawn uniformly by area on `from` (seeded) to the surface
/// in `to`.
pub fn sampled_distances(
    from: &TriMesh,
    to: &Scene,
    samples: usize,
    seed: u64,
) -> Result<Vec<f64>, TraceError> {
    let (_, closest) = sampled_closest(from, to, samples, seed)?;
    Ok(closest.into_iter().map(|c| c.dist).collect())
}

/// The distance (mm) of `p` to its closest point `c` on the closed, outward-oriented `mesh`,
/// negative where `p` lies inside: behind the plane of the closest triangle. (Where the closest
/// point is an edge or a vertex, `p` lies on the same side of each triangle there, but for a
/// sliver of space at an edge whose faces nearly fold back.)
pub fn signed_distance(p: &Point3<f64>, c: &ClosestPoint, mesh: &TriMesh) -> f64 {
    let inside = (c.prim as usize) < mesh.faces.len()
        && (p - c.point).dot(&mesh.face_cross(c.prim as usize)) < 0.0;
    if inside {
        -c.dist
    } else {
        c.dist
    }
}
