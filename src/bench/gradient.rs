//! `glasscan bench gradient`: the cost of the refraction term's loss and gradient over a scan,
//! against the bare Embree queries the same evaluation makes.
//!
//! One evaluation = for every view, trace all object pixels with a decoded point through the
//! mesh (batched per interface, each hit and refraction computed in f64 on the triangle Embree
//! found), differentiate each kept path backwards, and sum the gradients (then through the
//! vertex normals, for that model). The yardstick replays
//! exactly the ray batches that evaluation sent to Embree, in the same mode (packets for the
//! camera rays), through Embree alone (closest hit, no f64 refinement, nothing done with the
//! hits). Between the two, the evaluation's forward pass alone (the same trace, nothing
//! differentiated or summed) splits glasscan's share of the time.

use std::sync::Mutex;
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::loss::refraction::{add_view, trace_view, MeshState, RefractionSettings, ViewTargets};
use crate::loss::{Accumulator, Drops};
use crate::mesh::TriMesh;
use crate::trace::path::{MeshSurface, NormalModel, Surface, SurfaceHit};
use crate::trace::{BuildMode, Ray, TraceError};
use crate::util::median;

/// What [`run`] measured (times are medians over the repeats).
#[derive(Clone, Debug, Serialize)]
pub struct GradientBenchReport {
    pub threads: usize,
    pub faces: usize,
    pub views: usize,
    /// Camera rays (object pixels with a decoded point) per evaluation.
    pub camera_rays: usize,
    /// Embree queries per evaluation (camera rays and every later segment).
    pub queries: usize,
    pub used: usize,
    pub drops: Drops,
    /// The term's weighted mean over the rays used (screen form: mm² on the monitor; direction
    /// form: unitless), on the mesh given: on the true shape, how far the data model is from
    /// the captures.
    pub mean_loss: f64,
    pub seconds_per_gradient: f64,
    pub seconds_per_view: f64,
    /// The forward pass alone (Embree's queries and the f64 hits and refractions, nothing
    /// differentiated or summed), over all views.
    pub seconds_trace_only: f64,
    pub seconds_embree_only: f64,
    pub camera_rays_per_s: f64,
    pub queries_per_s: f64,
    pub embree_queries_per_s: f64,
    /// queries_per_s / embree_queries_per_s.
    pub ratio: f64,
    /// seconds_embree_only / seconds_trace_only: the forward pass's own rate against Embree's.
    pub ratio_trace_only: f64,
}

/// A surface that records every batch it is asked to intersect.
struct Recording<'a> {
    inner: &'a MeshSurface,
    batches: Mutex<Vec<(Vec<Ray>, bool)>>,
}

impl Recording<'_> {
    fn record(&self, rays: &[Ray], coherent: bool) {
        self.batches
            .lock()
            .expect("not poisoned")
            .push((rays.to_vec(), coherent));
    }
}

impl Surface for Recording<'_> {
    fn intersect_serial(
        &self,
        rays: &[Ray],
        out: &mut [Option<SurfaceHit>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        self.record(rays, coherent);
        self.inner.intersect_serial(rays, out, coherent)
    }
    fn first_elements(
        &self,
        rays: &[Ray],
        out: &mut [Option<u32>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        self.record(rays, coherent);
        self.inner.first_elements(rays, out, coherent)
    }
    fn offset(&self) -> f64 {
        self.inner.offset()
    }
}

/// Measures `repeats` evaluations of the refraction term of `views` on `mesh`.
pub fn run(
    mesh: &TriMesh,
    views: &[ViewTargets],
    s: &RefractionSettings,
    repeats: usize,
    mut progress: impl FnMut(usize),
) -> Result<GradientBenchReport, TraceError> {
    let surface = MeshSurface::with_mode(mesh, s.normals, BuildMode::Refit)?;
    let normals = (s.normals == NormalModel::Vertex).then(|| mesh.vertex_normals());
    // Both passes compute the mesh's face planes once per evaluation, as the optimisation does
    // once per iteration.
    let evaluate = |surface: &dyn Surface| -> Result<Accumulator, TraceError> {
        let state = MeshState::new(mesh, normals.as_deref());
        let mut acc = Accumulator::new(mesh.positions.len(), normals.is_some());
        for v in views {
            add_view(surface, &state, s, v, &mut acc)?;
        }
        Ok(acc)
    };
    // One recorded evaluation: the batches, and the figures.
    let recording = Recording {
        inner: &surface,
        batches: Mutex::new(Vec::new()),
    };
    let acc = evaluate(&recording)?;
    let (used, drops, mean_loss) = (acc.used, acc.drops, acc.loss / acc.weight);
    let batches = recording.batches.into_inner().expect("not poisoned");
    let queries: usize = batches.iter().map(|(b, _)| b.len()).sum();
    let trace = || -> Result<usize, TraceError> {
        let state = MeshState::new(mesh, normals.as_deref());
        views
            .iter()
            .map(|v| trace_view(&surface, &state, s, v))
            .sum()
    };
    let (mut t_full, mut t_trace, mut t_raw) = (Vec::new(), Vec::new(), Vec::new());
    for r in 0..repeats.max(1) {
        let t0 = Instant::now();
        let acc = evaluate(&surface)?;
        std::hint::black_box(acc.finish(mesh));
        t_full.push(t0.elapsed().as_secs_f64());
        let t_start = Instant::now();
        std::hint::black_box(trace()?);
        t_trace.push(t_start.elapsed().as_secs_f64());
        let t1 = Instant::now();
        // The same batches, as many at a time as the evaluation had threads.
        let hits: usize = batches
            .par_iter()
            .map(|(b, coherent)| surface.scene().count_hits_serial(b, *coherent))
            .sum::<Result<usize, TraceError>>()?;
        std::hint::black_box(hits);
        t_raw.push(t1.elapsed().as_secs_f64());
        progress(r + 1);
    }
    let (full, traced, raw) = (median(t_full), median(t_trace), median(t_raw));
    let camera_rays: usize = views.iter().map(|v| v.pixels.len()).sum();
    Ok(GradientBenchReport {
        threads: rayon::current_num_threads(),
        faces: mesh.faces.len(),
        views: views.len(),
        camera_rays,
        queries,
        used,
        drops,
        mean_loss,
        seconds_per_gradient: full,
        seconds_per_view: full / views.len().max(1) as f64,
        seconds_trace_only: traced,
        seconds_embree_only: raw,
        camera_rays_per_s: camera_rays as f64 / full,
        queries_per_s: queries as f64 / full,
        embree_queries_per_s: queries as f64 / raw,
        ratio: raw / full,
        ratio_trace_only: raw / traced,
    })
}
