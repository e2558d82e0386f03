//! Where the result can be trusted: per vertex, how much of the scan's data touches it — the
//! refraction rays that refract at its faces and the contour edges at it that pull on a
//! silhouette, over every view (those held out included) and every pixel the run keeps
//! (docs/decisions.md#a-result-that-says-where-it-can-be-trusted).
//!
//! A vertex is *constrained by refraction* when at least [`MIN_RAYS`] compared rays refract at
//! its faces, *by silhouettes only* when fewer do but a contour edge at it pulls on some view's
//! silhouette, and *by neither* otherwise: there the regularisers (smoothness, the membrane)
//! placed it. The result's `quality` vertex property, which MeshLab colours, is its refraction
//! rays per mm² of its area (a third of its faces' area) over their mean penalty: many rays
//! that agree with the result hold it more than few, or many that disagree.

use anyhow::Result;
use serde::Serialize;

use super::config::Settings;
use super::terms::{add_refraction, add_silhouettes, IndexSlope, Sample};
use super::Inputs;
use crate::loss::Accumulator;
use crate::trace::path::MeshSurface;
use crate::util::weighted_median;

/// The fewest compared refraction rays at a vertex's faces for the vertex to count as
/// constrained by refraction: a ray pins a point only along its path, a few from different
/// directions pin it in space.
pub const MIN_RAYS: u32 = 3;

/// The least mean penalty [`Confidence::quality`] divides by (the direction residual's penalty
/// is unitless: a residual of 1e-6): it keeps the quality finite, as a float, where the rays
/// fit exactly.
const MIN_MEAN_PENALTY: f64 = 1e-12;

/// What constrains a vertex.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Support {
    Refraction,
    SilhouetteOnly,
    Neither,
}

/// The data that touches each vertex of a mesh.
#[derive(Clone, Debug, PartialEq)]
pub struct Confidence {
    /// Per vertex: compared refraction rays that refract at its faces (a ray counts at each of
    /// its refractions), over every view.
    pub rays: Vec<u32>,
    /// Per vertex: the sum of those rays' penalties (each compared pixel's loss per unit of
    /// its weight, counted once for each of its rays' refractions at the vertex's faces).
    pub penalty: Vec<f64>,
    /// Per vertex: contour edges at it that pull on a silhouette, over every view.
    pub contour_edges: Vec<u32>,
    /// Per vertex: a third of its faces' area, mm².
    pub area_mm2: Vec<f64>,
}

/// The shares of a mesh's area by what constrains it, and the vertices' ray density.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ConfidenceSummary {
    pub refraction_share: f64,
    pub silhouette_only_share: f64,
    pub unconstrained_share: f64,
    /// The median over the area of the refraction rays per mm².
    pub median_rays_per_mm2: f64,
    pub min_rays: u32,
}

impl Confidence {
    /// What constrains vertex `v`.
    pub fn support(&self, v: usize) -> Support {
        if self.rays[v] >= MIN_RAYS {
            Support::Refraction
        } else if self.contour_edges[v] > 0 {
            Support::SilhouetteOnly
        } else {
            Support::Neither
        }
    }

    /// Per vertex, the result's `quality`: refraction rays per mm² of its area over their mean
    /// penalty (0 where no ray refracts). Were each ray's penalty the variance of its residual,
    /// this would be the rays' information about the surface per mm².
    pub fn quality(&self) -> Vec<f64> {
        let density = self.rays_per_mm2();
        (density.iter().zip(&self.rays).zip(&self.penalty))
            .map(|((&d, &r), &p)| {
                let mean = if r > 0 { p / r as f64 } else { 0.0 };
                d / mean.max(MIN_MEAN_PENALTY)
            })
            .collect()
    }

    /// Per vertex, refraction rays per mm² of its area.
    pub fn rays_per_mm2(&self) -> Vec<f64> {
        (self.rays.iter().zip(&self.area_mm2))
            .map(|(&r, &a)| if a > 0.0 { r as f64 / a } else { 0.0 })
            .collect()
    }

    /// The shares of the area by support.
    pub fn summary(&self) -> ConfidenceSummary {
        let total: f64 = self.area_mm2.iter().sum::<f64>().max(f64::MIN_POSITIVE);
        let share = |s: Support| {
            let a: f64 = (0..self.rays.len())
                .filter(|&v| self.support(v) == s)
                .map(|v| self.area_mm2[v])
                .sum();
            a / total
        };
        let density = self.rays_per_mm2();
        let median = weighted_median(
            density
                .into_iter()
                .zip(self.area_mm2.iter().copied())
                .collect(),
        );
        ConfidenceSummary {
            refraction_share: share(Support::Refraction),
            silhouette_only_share: share(Support::SilhouetteOnly),
            unconstrained_share: share(Support::Neither),
            median_rays_per_mm2: median.unwrap_or(0.0),
            min_rays: MIN_RAYS,
        }
    }
}

/// The data that touches each vertex of the mesh `surface` holds (built with the run's
/// `settings`' normals) at refractive index `ior`: every view's every kept pixel and every
/// silhouette, the run's `settings`.
pub fn measure(
    inputs: &Inputs,
    surface: &MeshSurface,
    settings: &Settings,
    ior: f64,
) -> Result<Confidence> {
    let mesh = surface.mesh();
    let n = mesh.positions.len();
    let mut refraction = Accumulator::counting(n, surface.vertex_normals().is_some());
    let views: Vec<(usize, Sample)> = (0..inputs.targets.len())
        .map(|t| (t, Sample::AllKept))
        .collect();
    add_refraction(
        (inputs, ior),
        surface,
        mesh,
        settings,
        &views,
        IndexSlope::Unneeded,
        &mut refraction,
    )?;
    let mut silhouette = Accumulator::counting(n, false);
    let edges = mesh.interior_edges();
    let silhouettes: Vec<usize> = (0..inputs.silhouettes.len()).collect();
    let geometry = (surface, mesh, &edges[..]);
    add_silhouettes(inputs, geometry, settings, &silhouettes, &mut silhouette)?;
    Ok(Confidence {
        // Each refraction adds an entry for each of its triangle's three vertices.
        rays: refraction.touches,
        penalty: refraction.penalty,
        contour_edges: silhouette.touches,
        area_mm2: mesh.vertex_areas(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn support_and_shares_follow_the_counts_and_areas() {
        let c = Confidence {
            rays: vec![10, 2, 0, 0],
            penalty: vec![5.0, 4.0, 0.0, 0.0],
            contour_edges: vec![0, 1, 0, 3],
            area_mm2: vec![1.0, 2.0, 3.0, 4.0],
        };
        let kinds: Vec<Support> = (0..4).map(|v| c.support(v)).collect();
        use Support::*;
        assert_eq!(kinds, [Refraction, SilhouetteOnly, Neither, SilhouetteOnly]);
        let s = c.summary();
        assert!((s.refraction_share - 0.1).abs() < 1e-12, "{s:?}");
        assert!((s.silhouette_only_share - 0.6).abs() < 1e-12, "{s:?}");
        assert!((s.unconstrained_share - 0.3).abs() < 1e-12, "{s:?}");
        assert_eq!(c.rays_per_mm2(), [10.0, 1.0, 0.0, 0.0]);
        // Mean penalties 0.5 and 2: the first vertex's rays hold it 40× as much per mm².
        assert_eq!(c.quality(), [20.0, 0.5, 0.0, 0.0]);
        // Half the area (the 4 mm² vertex and more) has no ray: the median density is 0.
        assert_eq!(s.median_rays_per_mm2, 0.0);
    }
}
