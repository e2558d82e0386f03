//! `glasscan bench trace`: Embree throughput and BVH update cost on one mesh.
//!
//! - coherent rays: a `width`×`height` pinhole view of the mesh (camera 3 bbox diagonals from the
//!   centre, the bbox filling 95 % of the image), traced in packets of 8 and one by one;
//! - incoherent rays: uniformly random directions from points just inside the surface (the
//!   second-hit rays of refraction tracing);
//! - each on 1 thread and on all threads;
//! - BVH commit time after moving every vertex: a full rebuild (medium quality) against a refit
//!   (dynamic scene), and the packet throughput after each.

use std::time::Instant;

use nalgebra::{Point3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::mesh::sample::sample_surface;
use crate::mesh::TriMesh;
use crate::trace::{BuildMode, Device, Ray, Scene, TraceError};

/// Settings of [`run`].
#[derive(Clone, Debug)]
pub struct TraceBenchOptions {
    /// Image size of the coherent view, pixels.
    pub width: u32,
    pub height: u32,
    /// Number of incoherent rays.
    pub incoherent_rays: usize,
    /// Each throughput figure repeats its workload for at least this long, seconds.
    pub min_seconds: f64,
    /// Vertex updates timed per build mode.
    pub updates: usize,
    pub seed: u64,
}

impl Default for TraceBenchOptions {
    fn default() -> Self {
        Self {
            width: 1280,
            height: 960,
            incoherent_rays: 1_000_000,
            min_seconds: 1.0,
            updates: 20,
            seed: 0,
        }
    }
}

/// One throughput measurement.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Throughput {
    pub workload: String,
    pub threads: usize,
    pub mrays_per_s: f64,
    /// Share of the rays that hit the mesh.
    pub hit_share: f64,
}

/// BVH cost of one build mode.
#[derive(Clone, Debug, serde::Serialize)]
pub struct UpdateCost {
    pub mode: String,
    /// Initial build, ms.
    pub build_ms: f64,
    /// Mean commit time after moving every vertex, ms.
    pub update_ms: f64,
    /// Coherent packet throughput (all threads) after the updates, Mrays/s.
    pub mrays_per_s_after: f64,
}

/// Everything [`run`] measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct TraceBenchReport {
    pub faces: usize,
    pub threads: usize,
    pub throughput: Vec<Throughput>,
    pub updates: Vec<UpdateCost>,
}

/// Runs the benchmark on `mesh`.
pub fn run(mesh: &TriMesh, opts: &TraceBenchOptions) -> Result<TraceBenchReport, TraceError> {
    let device = Device::new()?;
    let all = rayon::current_num_threads();
    let single = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a 1-thread pool");
    let (lo, hi) = mesh.bbox().expect("a mesh with vertices");
    let centre = Point3::from((lo.coords + hi.coords) / 2.0);
    let radius = (hi - lo).norm() / 2.0;

    let camera = camera_rays(centre, hi - lo, opts.width, opts.height);
    let inner = inner_rays(mesh, opts.incoherent_rays, opts.seed);

    let scene = Scene::new(&device, mesh, BuildMode::Static)?;
    let mut throughput = Vec::new();
    for (workload, rays, coherent) in [
        ("camera rays, packets of 8", &camera, true),
        ("camera rays, one by one", &camera, false),
        ("inner rays, random directions", &inner, false),
    ] {
        for threads in [1, all] {
            let measure = || timed_throughput(&scene, rays, coherent, opts.min_seconds);
            let (mrays_per_s, hit_share) = if threads == 1 {
                single.install(measure)?
            } else {
                measure()?
            };
            throughput.push(Throughput {
                workload: workload.into(),
                threads,
                mrays_per_s,
                hit_share,
            });
        }
    }

    let mut updates = Vec::new();
    let moved = jittered_copies(mesh, radius * 1e-3, opts.seed);
    for (name, mode) in [
        ("rebuild (medium quality)", BuildMode::Rebuild),
        ("refit (dynamic)", BuildMode::Refit),
    ] {
        let t0 = Instant::now();
        let mut s = Scene::new(&device, mesh, mode)?;
        let build_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t0 = Instant::now();
        for k in 0..opts.updates {
            s.update_vertices(&moved[k % 2])?;
        }
        let update_ms = t0.elapsed().as_secs_f64() * 1e3 / opts.updates.max(1) as f64;
        let (mrays_per_s_after, _) = timed_throughput(&s, &camera, true, opts.min_seconds)?;
        updates.push(UpdateCost {
            mode: name.into(),
            build_ms,
            update_ms,
            mrays_per_s_after,
        });
    }
    Ok(TraceBenchReport {
        faces: mesh.faces.len(),
        threads: all,
        throughput,
        updates,
    })
}

/// Traces `rays` repeatedly for at least `min_seconds`; returns (Mrays/s, hit share).
fn timed_throughput(
    scene: &Scene,
    rays: &[Ray],
    coherent: bool,
    min_seconds: f64,
) -> Result<(f64, f64), TraceError> {
    let mut out = vec![None; rays.len()];
    let t0 = Instant::now();
    let mut traced = 0usize;
    loop {
        scene.intersect_into(rays, &mut out, coherent)?;
        traced += rays.len();
        if t0.elapsed().as_secs_f64() >= min_seconds {
            break;
        }
    }
    let mrays_per_s = traced as f64 / t0.elapsed().as_secs_f64() / 1e6;
    let hits = out.iter().filter(|h| h.is_some()).count();
    Ok((mrays_per_s, hits as f64 / rays.len().max(1) as f64))
}

/// Pinhole camera rays, scanline order, looking down −z at `centre` from 3 bbox diagonals away,
/// zoomed so that the bbox (of size `extent`, mm) fills 95 % of the image's width or height.
fn camera_rays(centre: Point3<f64>, extent: Vector3<f64>, width: u32, height: u32) -> Vec<Ray> {
    let dist = 3.0 * extent.norm();
    let eye = centre + Vector3::new(0.0, 0.0, dist);
    let focal = 0.95 * (width as f64 / extent.x).min(height as f64 / extent.y) * dist;
    let (cx, cy) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
    (0..height)
        .flat_map(|j| {
            (0..width).map(move |i| {
                let d = Vector3::new((i as f64 - cx) / focal, -(j as f64 - cy) / focal, -1.0);
                Ray::new(eye, d.normalize())
            })
        })
        .collect()
}

/// Rays from points just inside the surface (offset 1e-4 of the bbox diagonal against the face
/// normal) in uniformly random directions.
fn inner_rays(mesh: &TriMesh, n: usize, seed: u64) -> Vec<Ray> {
    let offset = 1e-4 * mesh.bbox_diagonal();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
    sample_surface(mesh, n, seed)
        .into_iter()
        .map(|(p, f)| {
            let normal = mesh.face_cross(f as usize).normalize();
            let z: f64 = 2.0 * rng.random::<f64>() - 1.0;
            let phi = std::f64::consts::TAU * rng.random::<f64>();
            let s = (1.0 - z * z).sqrt();
            Ray::new(
                p - normal * offset,
                Vector3::new(s * phi.cos(), s * phi.sin(), z),
            )
        })
        .collect()
}

/// Two copies of the mesh's vertices, each moved by independent uniform noise of ±`amp` mm.
fn jittered_copies(mesh: &TriMesh, amp: f64, seed: u64) -> [Vec<Point3<f64>>; 2] {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x7177e7);
    let mut copy = || -> Vec<Point3<f64>> {
        mesh.positions
            .iter()
            .map(|p| p + Vector3::from_fn(|_, _| amp * (2.0 * rng.random::<f64>() - 1.0)))
            .collect()
    };
    [copy(), copy()]
}
