//! Held-out views: a share of the scan's views, spread evenly over the turntable, that the
//! optimisation never sees. After every stage the mesh's fit to them is measured (the refraction
//! and silhouette terms with the run's own residual forms and weights, over every
//! `pixel_stride`-th pixel), so a run knows without ground truth when a stage made it worse; the
//! stage that fits them best becomes the result.

use anyhow::Result;
use serde::{Deserialize, Serialize};

use super::config::Settings;
use super::Inputs;
use crate::mesh::TriMesh;
use crate::trace::path::MeshSurface;
use crate::trace::BuildMode;

/// Which views fit and which validate, as indices into [`Inputs`]' targets and silhouettes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Split {
    pub fit_targets: Vec<usize>,
    pub fit_silhouettes: Vec<usize>,
    pub held_targets: Vec<usize>,
    pub held_silhouettes: Vec<usize>,
}

impl Split {
    /// Holds out ⌊share · views⌋ of the views (none for a share of 0), evenly spaced, the first
    /// half a spacing in.
    pub fn new(inputs: &Inputs, share: f64) -> Self {
        let mut views: Vec<usize> = inputs
            .silhouettes
            .iter()
            .map(|s| s.view)
            .chain(inputs.targets.iter().map(|t| t.view))
            .collect();
        views.sort_unstable();
        views.dedup();
        let held_count = (share * views.len() as f64).floor() as usize;
        let held: Vec<usize> = (0..held_count)
            .map(|k| views[(2 * k + 1) * views.len() / (2 * held_count)])
            .collect();
        let (held_targets, fit_targets) =
            partition(inputs.targets.iter().map(|t| held.contains(&t.view)));
        let (held_silhouettes, fit_silhouettes) =
            partition(inputs.silhouettes.iter().map(|s| held.contains(&s.view)));
        Split {
            fit_targets,
            fit_silhouettes,
            held_targets,
            held_silhouettes,
        }
    }

    /// Whether any view is held out.
    pub fn validates(&self) -> bool {
        !self.held_targets.is_empty() || !self.held_silhouettes.is_empty()
    }
}

/// Indices where `held` is true, and where it is false.
fn partition(held: impl Iterator<Item = bool>) -> (Vec<usize>, Vec<usize>) {
    let (mut yes, mut no) = (Vec::new(), Vec::new());
    for (i, h) in held.enumerate() {
        if h {
            yes.push(i);
        } else {
            no.push(i);
        }
    }
    (yes, no)
}

/// A mesh's fit to the held-out views: the weighted means of the two data terms (as the run
/// weighs them) and their sum.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ValidationRecord {
    pub refraction: f64,
    pub silhouette: f64,
    pub total: f64,
    /// Held-out views.
    pub views: usize,
}

/// The fit of `mesh` to the held-out views of `split`; `None` when none are held out.
pub fn validate_mesh(
    inputs: &Inputs,
    split: &Split,
    mesh: &TriMesh,
    settings: &Settings,
) -> Result<Option<ValidationRecord>> {
    if !split.validates() {
        return Ok(None);
    }
    let surface = MeshSurface::with_mode(mesh, settings.normals, BuildMode::Static)?;
    let edges = mesh.interior_edges();
    let targets: Vec<(usize, usize)> = split.held_targets.iter().map(|&v| (v, 0)).collect();
    let refraction = super::refraction_over(inputs, &surface, mesh, settings, &targets)?;
    let silhouette = super::silhouette_over(
        inputs,
        &surface,
        mesh,
        &edges,
        settings,
        &split.held_silhouettes,
    )?;
    let mean = |loss: f64, weight: f64| if weight > 0.0 { loss / weight } else { 0.0 };
    let r = settings.weight_refraction * mean(refraction.loss, refraction.weight);
    let s = settings.weight_silhouette * mean(silhouette.loss, silhouette.weight);
    Ok(Some(ValidationRecord {
        refraction: r,
        silhouette: s,
        total: r + s,
        views: split.held_targets.len().max(split.held_silhouettes.len()),
    }))
}

/// The stage (index) among the first `upto` whose held-out fit is best, from stage `first` on
/// (the warm-up's stages carve at the coarsest edge length and are candidates only when no
/// later stage is done); the last of them when the run holds out nothing. `None` when no stage
/// is done.
pub fn best_stage(stages: &[super::StageReport], first: usize, upto: usize) -> Option<usize> {
    let done = &stages[..upto.min(stages.len())];
    let from = if done.len() > first { first } else { 0 };
    let scored = (done.iter().enumerate().skip(from))
        .filter_map(|(i, s)| s.validation.map(|v| (i, v.total)))
        .filter(|(_, t)| t.is_finite());
    scored
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
        .or_else(|| done.len().checked_sub(1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reconstruct::{IterationRecord, StageReport};

    fn stage(stage: usize, total: Option<f64>) -> StageReport {
        StageReport {
            stage,
            edge_mm: 1.0,
            vertices: 0,
            faces: 0,
            seconds: 0.0,
            refraction_rays_used: 0,
            refraction_drops: Default::default(),
            contour_edges_used: 0,
            degenerate_faces: 0,
            last: IterationRecord::default(),
            validation: total.map(|total| ValidationRecord {
                total,
                ..Default::default()
            }),
            averaged: false,
        }
    }

    #[test]
    fn the_best_stage_is_the_lowest_held_out_fit_after_the_warm_up_within_the_stages_done() {
        let stages: Vec<StageReport> = [0.5, 0.2, 0.3, 0.1]
            .iter()
            .enumerate()
            .map(|(i, &t)| stage(i, Some(t)))
            .collect();
        assert_eq!(best_stage(&stages, 0, 4), Some(3));
        assert_eq!(best_stage(&stages, 0, 3), Some(1));
        assert_eq!(best_stage(&stages, 0, 0), None);
        // Stages before `first` (the warm-up) are candidates only when no later one is done.
        assert_eq!(best_stage(&stages, 2, 3), Some(2));
        assert_eq!(best_stage(&stages, 2, 4), Some(3));
        assert_eq!(best_stage(&stages, 3, 3), Some(1));
        let unvalidated: Vec<StageReport> = (0..3).map(|i| stage(i, None)).collect();
        assert_eq!(best_stage(&unvalidated, 0, 3), Some(2));
        let with_nan = vec![stage(0, Some(f64::NAN)), stage(1, Some(0.4))];
        assert_eq!(best_stage(&with_nan, 0, 2), Some(1));
    }
}
