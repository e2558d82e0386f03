//! The terms of the loss at one iteration, each a weighted mean with its gradient per vertex:
//! refraction, silhouette, smoothness and the membrane on what no ray sees.

use super::config::Settings;
use super::coverage::Coverage;
use super::validation::Split;
use crate::loss::membrane::{add_membrane, along_normals};
use crate::loss::refraction::{add_view, MeshState, RefractionSettings};
use crate::loss::silhouette::{self, ContourMesh, SilhouetteSettings};
use crate::loss::smoothness::add_smoothness;
use crate::loss::{Accumulator, Drops};
use crate::mesh::{InteriorEdge, TriMesh};
use crate::trace::path::MeshSurface;
use crate::trace::refract::IOR_AIR;
use crate::util::scatter_seed;
use anyhow::Result;
use nalgebra::{Point3, Vector3};
use rand::seq::index::sample;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

type V3 = Vector3<f64>;

use super::{Inputs, IterationRecord};

/// One term's value at an iteration: its weighted sum, the weight it is a mean over, what it
/// used and dropped, and its gradient per vertex.
pub(super) struct TermValue {
    pub(super) loss: f64,
    pub(super) weight: f64,
    pub(super) used: usize,
    pub(super) drops: Drops,
    pub(super) grad: Vec<V3>,
    /// ∂(weighted sum)/∂ the object's refractive index.
    pub(super) ior_grad: f64,
}

impl TermValue {
    pub(super) fn from(acc: Accumulator, mesh: &TriMesh) -> Self {
        let (loss, weight, used, drops, ior_grad) =
            (acc.loss, acc.weight, acc.used, acc.drops, acc.ior);
        Self {
            loss,
            weight,
            used,
            drops,
            grad: acc.finish(mesh),
            ior_grad,
        }
    }
}

/// The three terms at one iteration.
pub(super) struct Terms {
    pub(super) refraction: TermValue,
    pub(super) silhouette: TermValue,
    pub(super) smoothness: TermValue,
    pub(super) membrane: TermValue,
}

impl Terms {
    /// Each term as a weighted mean over what it used, times its setting's weight: the record of
    /// the iteration (stage `s`, iteration `it`) and the total gradient.
    pub(super) fn combine(
        &self,
        settings: &Settings,
        (s, it): (usize, usize),
    ) -> (IterationRecord, Vec<V3>) {
        let per_weight = |t: &TermValue| if t.weight > 0.0 { 1.0 / t.weight } else { 0.0 };
        let (wr, ws, wm, wu) = (
            settings.weight_refraction * per_weight(&self.refraction),
            settings.weight_silhouette * per_weight(&self.silhouette),
            settings.weight_smoothness * per_weight(&self.smoothness),
            settings.weight_membrane * per_weight(&self.membrane),
        );
        let mut record = IterationRecord {
            stage: s,
            iteration: it,
            refraction: wr * self.refraction.loss,
            silhouette: ws * self.silhouette.loss,
            smoothness: wm * self.smoothness.loss,
            membrane: wu * self.membrane.loss,
            total: 0.0,
        };
        record.total = record.refraction + record.silhouette + record.smoothness + record.membrane;
        let grad = (self.refraction.grad.iter())
            .zip(&self.silhouette.grad)
            .zip(&self.smoothness.grad)
            .zip(&self.membrane.grad)
            .map(|(((a, b), c), d)| a * wr + b * ws + c * wm + d * wu)
            .collect();
        (record, grad)
    }
}

/// The seed of the random choices (views, sample offsets) of iteration `it` of the run's stage
/// `s`: the run's seed scattered ([`scatter_seed`]), because with the bare seed `seed ^ it` two
/// seeds below the iteration count shared their draws in another order (seed 1's iteration 0
/// drew seed 0's iteration 1): runs with different seeds were not independent.
pub(super) fn iteration_seed(seed: u64, s: usize, it: usize) -> u64 {
    scatter_seed(seed) ^ ((s as u64) << 40) ^ it as u64
}

/// The views an iteration's terms look at, drawn from the iteration's generator: first the
/// refraction term's `refraction_views` random views of those `split` fits, each with a random
/// sample offset ([`Sample::Offset`]), then the silhouette term's `silhouette_views` (none at
/// weight 0).
pub(super) struct Draws {
    pub(super) refraction: Vec<(usize, Sample)>,
    pub(super) silhouettes: Vec<usize>,
}

impl Draws {
    pub(super) fn new(split: &Split, settings: &Settings, rng: &mut ChaCha8Rng) -> Self {
        let fit = &split.fit_targets;
        let k = settings.refraction_views.min(fit.len());
        let refraction = sample(rng, fit.len(), k)
            .into_iter()
            .map(|v| (fit[v], Sample::Offset(rng.random::<f64>())))
            .collect();
        let fit = &split.fit_silhouettes;
        let k = settings.silhouette_views.min(fit.len());
        let silhouettes = if settings.weight_silhouette > 0.0 {
            sample(rng, fit.len(), k)
                .into_iter()
                .map(|v| fit[v])
                .collect()
        } else {
            Vec::new()
        };
        Self {
            refraction,
            silhouettes,
        }
    }
}

/// Each term's own wall time in one iteration, s; they ran at the same time, so they overlap.
pub(super) struct TermTimes {
    pub(super) refraction: f64,
    pub(super) silhouette: f64,
    /// The smoothness and the membrane terms.
    pub(super) regularisers: f64,
}

/// Every term of an iteration over the views `draws` chose, the refraction term at refractive
/// index `ior`, evaluated at the same time: the refraction term and after it the membrane term
/// (which acts where `coverage`, recording the refraction gradient, says no ray has been), beside
/// the silhouette term, beside the smoothness term. Each runs on the threads the others leave
/// idle and is the same bits as alone. Returns the terms, the share of the vertices the membrane
/// term acted on, and each term's own time.
pub(super) fn iteration_terms(
    (inputs, ior): (&Inputs, f64),
    (surface, mesh, edges): (&MeshSurface, &TriMesh, &[InteriorEdge]),
    (settings, edge_mm): (&Settings, f64),
    draws: &Draws,
    coverage: &mut Coverage,
) -> Result<(Terms, f64, TermTimes)> {
    let refraction_then_membrane = || -> Result<_> {
        let (refraction, t_refraction) = timed(|| {
            let slope = if inputs.ior.is_auto() {
                IndexSlope::Wanted
            } else {
                IndexSlope::Unneeded
            };
            refraction_over(
                (inputs, ior),
                surface,
                mesh,
                settings,
                &draws.refraction,
                slope,
            )
        });
        let refraction = refraction?;
        let (membrane, t_membrane) = timed(|| {
            coverage.record(&refraction.grad);
            let geometry = (mesh, surface.vertex_normals(), edges);
            membrane_term(geometry, coverage, settings, edge_mm)
        });
        Ok((refraction, membrane, t_refraction, t_membrane))
    };
    let silhouette =
        || timed(|| silhouette_over(inputs, surface, mesh, edges, settings, &draws.silhouettes));
    let smoothness = || timed(|| smoothness_term(mesh, edges, settings));
    let (first, (silhouette, (smoothness, t_smoothness))) =
        rayon::join(refraction_then_membrane, || {
            rayon::join(silhouette, smoothness)
        });
    let (refraction, (membrane, share), t_refraction, t_membrane) = first?;
    let (silhouette, t_silhouette) = silhouette;
    let silhouette = silhouette?;
    let times = TermTimes {
        refraction: t_refraction,
        silhouette: t_silhouette,
        regularisers: t_smoothness + t_membrane,
    };
    let terms = Terms {
        refraction,
        silhouette,
        smoothness,
        membrane,
    };
    Ok((terms, share, times))
}

/// `f`'s value and its wall time, s.
fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let value = f();
    (value, t.elapsed().as_secs_f64())
}

/// Which of a view's kept pixels a term traces.
#[derive(Clone, Copy, Debug)]
pub(super) enum Sample {
    /// The share of its decoded pixels that puts the rays an iteration's spacing apart at the
    /// mesh's centre ([`iteration_spacing_mm`]), drawn from those the run keeps from this offset
    /// in [0, 1) ([`crate::loss::sample`]).
    Offset(f64),
    /// All it keeps (the held-out views' measure, which decides the result).
    AllKept,
}

/// Whether a refraction evaluation also computes its derivative with respect to the index: to
/// step a free index, or for the held-out views' best-fitting index.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum IndexSlope {
    Wanted,
    Unneeded,
}

/// The refraction term at refractive index `ior` over `views` (target index, which pixels).
pub(super) fn refraction_over(
    inputs: (&Inputs, f64),
    surface: &MeshSurface,
    mesh: &TriMesh,
    settings: &Settings,
    views: &[(usize, Sample)],
    slope: IndexSlope,
) -> Result<TermValue> {
    let mut acc = Accumulator::new(mesh.positions.len(), surface.vertex_normals().is_some());
    add_refraction(inputs, surface, mesh, settings, views, slope, &mut acc)?;
    Ok(TermValue::from(acc, mesh))
}

/// Adds the refraction term at refractive index `ior` over `views` to `acc`.
pub(super) fn add_refraction(
    (inputs, ior): (&Inputs, f64),
    surface: &MeshSurface,
    mesh: &TriMesh,
    settings: &Settings,
    views: &[(usize, Sample)],
    slope: IndexSlope,
    acc: &mut Accumulator,
) -> Result<()> {
    let rs = RefractionSettings {
        ior,
        ior_air: IOR_AIR,
        max_refractions: settings.max_refractions,
        normals: settings.normals,
        form: settings.residual,
        robust: settings.robust,
        min_cos: settings.min_cos,
        grazing_cell_footprints: settings.grazing_cell_footprints,
        footprint: settings.footprint,
        bit_weight: settings.weight_bits,
        index_gradient: slope == IndexSlope::Wanted,
    };
    let (centre, diagonal) = mesh.bbox().map_or((Point3::origin(), 0.0), |(lo, hi)| {
        (nalgebra::center(&lo, &hi), (hi - lo).norm())
    });
    let spacing_mm = iteration_spacing_mm(mesh, diagonal, settings);
    let state = MeshState::new(mesh, surface.vertex_normals());
    for &(v, sample) in views {
        let view = &inputs.targets[v];
        match sample {
            Sample::Offset(offset) => {
                // The share of the kept pixels (themselves a share of the decoded ones).
                let share = view.share_for_spacing(&centre, spacing_mm) / inputs.kept_shares[v];
                add_view(surface, &state, &rs, &view.sampled(share, offset), acc)?;
            }
            Sample::AllKept => add_view(surface, &state, &rs, view, acc)?,
        }
    }
    Ok(())
}

/// How far apart an iteration's rays lie at `mesh` (bounding-box diagonal `diagonal_mm`), mm:
/// `ray_spacing` of the diagonal, or `ray_edge_spacing` of its mean edge where that is closer.
fn iteration_spacing_mm(mesh: &TriMesh, diagonal_mm: f64, settings: &Settings) -> f64 {
    let coarse = settings.ray_spacing * diagonal_mm;
    if settings.ray_edge_spacing > 0.0 {
        coarse.min(settings.ray_edge_spacing * mesh.mean_edge_length())
    } else {
        coarse
    }
}

/// The silhouette term over the silhouettes `views`.
pub(super) fn silhouette_over(
    inputs: &Inputs,
    surface: &MeshSurface,
    mesh: &TriMesh,
    edges: &[InteriorEdge],
    settings: &Settings,
    views: &[usize],
) -> Result<TermValue> {
    let mut acc = Accumulator::new(mesh.positions.len(), false);
    add_silhouettes(inputs, (surface, mesh, edges), settings, views, &mut acc)?;
    Ok(TermValue::from(acc, mesh))
}

/// Adds the silhouette term over the silhouettes `views` to `acc`.
pub(super) fn add_silhouettes(
    inputs: &Inputs,
    (surface, mesh, edges): (&MeshSurface, &TriMesh, &[InteriorEdge]),
    settings: &Settings,
    views: &[usize],
    acc: &mut Accumulator,
) -> Result<()> {
    if views.is_empty() {
        return Ok(());
    }
    let s = SilhouetteSettings {
        form: settings.silhouette,
        unit_mm: settings.silhouette_scale * mesh.bbox_diagonal(),
        probe: settings.silhouette_probe,
    };
    let shape = ContourMesh::new(mesh, edges);
    for &v in views {
        silhouette::add_view(&shape, &inputs.silhouettes[v], surface.scene(), &s, acc)?;
    }
    Ok(())
}

/// The smoothness term over every interior edge.
pub(super) fn smoothness_term(
    mesh: &TriMesh,
    edges: &[InteriorEdge],
    settings: &Settings,
) -> TermValue {
    let mut acc = Accumulator::new(mesh.positions.len(), false);
    add_smoothness(mesh, edges, settings.smoothness, &mut acc);
    TermValue::from(acc, mesh)
}

/// The membrane term on the patches of vertices `coverage` says the refraction data has not seen
/// (nothing at weight 0 or before the record is warm), and the share of the vertices it acts on;
/// on a stage graded by `sizing_error`, its gradient along the vertex normals only
/// ([`along_normals`]; `vertex_normals`: the mesh's unit vertex normals when the caller has them
/// current, else they are computed).
pub(super) fn membrane_term(
    (mesh, vertex_normals, edges): (&TriMesh, Option<&[V3]>, &[InteriorEdge]),
    coverage: &Coverage,
    settings: &Settings,
    edge_mm: f64,
) -> (TermValue, f64) {
    let mut acc = Accumulator::new(mesh.positions.len(), false);
    let patches = (settings.weight_membrane > 0.0)
        .then(|| coverage.unseen_patches(edges))
        .flatten();
    let mut share = 0.0;
    if let Some(patches) = patches {
        share = patches.iter().filter(|p| **p).count() as f64 / patches.len().max(1) as f64;
        add_membrane(mesh, edges, &patches, edge_mm, &mut acc);
    }
    let mut term = TermValue::from(acc, mesh);
    if share > 0.0 && settings.sizing_error > 0.0 {
        match vertex_normals {
            Some(normals) => along_normals(&mut term.grad, normals),
            None => along_normals(&mut term.grad, &mesh.vertex_normals()),
        }
    }
    (term, share)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::shapes::icosphere;
    use crate::reconstruct::config::Preset;

    #[test]
    fn an_iterations_rays_follow_the_mesh_where_it_is_finer_than_the_diagonals_spacing() {
        // A 40 mm sphere: mean edges of about 4.9 mm and 0.3 mm.
        let (coarse, fine) = (icosphere(20.0, 2), icosphere(20.0, 6));
        let s = Settings::preset(Preset::Balanced);
        let spacing = |m: &TriMesh, s: &Settings| iteration_spacing_mm(m, m.bbox_diagonal(), s);
        let by_diagonal = |m: &TriMesh| s.ray_spacing * m.bbox_diagonal();
        assert_eq!(spacing(&coarse, &s), by_diagonal(&coarse));
        let by_edge = s.ray_edge_spacing * fine.mean_edge_length();
        assert!(by_edge < by_diagonal(&fine));
        assert_eq!(spacing(&fine, &s), by_edge);
        let off = Settings {
            ray_edge_spacing: 0.0,
            ..s.clone()
        };
        assert_eq!(spacing(&fine, &off), by_diagonal(&fine));
    }
}
