//! Refraction paths through a closed surface: a camera ray enters the object, refracts at every
//! interface (Snell, f64), possibly leaves and re-enters, and finally leaves towards the monitor.
//!
//! Rays are traced in batches, one interface at a time for the whole batch (so that Embree sees
//! many rays per call). Which side of the surface a hit is on comes from the geometric normal;
//! after each interface the new ray starts from the hit point recomputed in f64 and moved by the
//! surface's offset along the new direction, an offset proportional to the object's size (never a
//! fixed constant, so it holds from 1 mm to 10 m objects).

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::refract::{refract, IOR_AIR};
use super::{BuildMode, Device, Hit, Ray, Scene, TraceError};
use crate::mesh::TriMesh;

/// Where a ray meets a surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceHit {
    /// Point, in the ray's frame (mm).
    pub point: Point3<f64>,
    /// Unit outward normal of the surface element (flat triangle normal for a mesh).
    pub geometric_normal: Vector3<f64>,
    /// Unit outward normal used for refraction (interpolated, or the geometric one).
    pub shading_normal: Vector3<f64>,
    /// Index of the surface element hit (the triangle of a mesh).
    pub prim: u32,
}

/// A closed, outward-oriented surface that rays can be traced against.
pub trait Surface: Sync {
    /// The first hit of each ray (`out` is as long as `rays`) on the calling thread; `coherent`:
    /// the rays come in image order from one point (camera rays), worth tracing in packets.
    fn intersect_serial(
        &self,
        rays: &[Ray],
        out: &mut [Option<SurfaceHit>],
        coherent: bool,
    ) -> Result<(), TraceError>;
    /// The element each ray meets first (`None`: none), on the calling thread, without the
    /// hit's geometry: for callers that recompute the hit on that element themselves.
    /// `coherent` as for [`Self::intersect_serial`].
    fn first_elements(
        &self,
        rays: &[Ray],
        out: &mut [Option<u32>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        let mut hits = vec![None; rays.len()];
        self.intersect_serial(rays, &mut hits, coherent)?;
        for (o, h) in out.iter_mut().zip(&hits) {
            *o = h.map(|h| h.prim);
        }
        Ok(())
    }
    /// How far a ray restarting at a hit point is moved along its new direction (mm).
    fn offset(&self) -> f64;
}

/// Which normal refraction uses on a mesh.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum NormalModel {
    /// The flat triangle normal (DRT).
    Face,
    /// Area-weighted vertex normals, interpolated with the hit's barycentrics.
    Vertex,
}

/// A triangle mesh as a [`Surface`], through Embree.
pub struct MeshSurface {
    scene: Scene,
    mesh: TriMesh,
    vertex_normals: Option<Vec<Vector3<f64>>>,
    offset: f64,
}

impl MeshSurface {
    /// `mesh` must be closed and outward-oriented (see [`crate::mesh::validate`]).
    pub fn new(mesh: &TriMesh, normals: NormalModel) -> Result<Self, TraceError> {
        Self::with_mode(mesh, normals, BuildMode::Static)
    }

    /// As [`Self::new`] with a chosen BVH mode ([`BuildMode::Refit`] for a mesh that moves).
    pub fn with_mode(
        mesh: &TriMesh,
        normals: NormalModel,
        mode: BuildMode,
    ) -> Result<Self, TraceError> {
        let device = Device::new()?;
        let scene = Scene::new(&device, mesh, mode)?;
        let vertex_normals = (normals == NormalModel::Vertex).then(|| mesh.vertex_normals());
        Ok(Self {
            scene,
            mesh: mesh.clone(),
            vertex_normals,
            offset: restart_offset(mesh),
        })
    }

    /// Moves the vertices (same topology); the scene is refitted or rebuilt per its mode.
    pub fn update_positions(&mut self, positions: &[Point3<f64>]) -> Result<(), TraceError> {
        self.scene.update_vertices(positions)?;
        self.mesh.positions.copy_from_slice(positions);
        if self.vertex_normals.is_some() {
            self.vertex_normals = Some(self.mesh.vertex_normals());
        }
        self.offset = restart_offset(&self.mesh);
        Ok(())
    }

    /// The mesh as currently placed.
    pub fn mesh(&self) -> &TriMesh {
        &self.mesh
    }

    /// Its unit vertex normals (vertex-normal model only), kept current by
    /// [`Self::update_positions`].
    pub fn vertex_normals(&self) -> Option<&[Vector3<f64>]> {
        self.vertex_normals.as_deref()
    }

    /// The Embree scene holding it.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }
}

/// Embree works in f32: a restarting ray must clear the float error of the surface, which scales
/// with the coordinates' magnitude, and stay well below any real thickness.
fn restart_offset(mesh: &TriMesh) -> f64 {
    let (lo, hi) = mesh.bbox().expect("a mesh with vertices");
    let extent = (hi - lo).norm().max(lo.coords.amax()).max(hi.coords.amax());
    1e-6 * extent
}

impl MeshSurface {
    fn surface_hit(&self, h: &Hit) -> SurfaceHit {
        let [a, b, c] = self.mesh.corners(h.prim as usize);
        let w = 1.0 - h.u - h.v;
        let point = Point3::from(a.coords * w + b.coords * h.u + c.coords * h.v);
        let geometric_normal = self.mesh.face_cross(h.prim as usize).normalize();
        let shading_normal = match &self.vertex_normals {
            None => geometric_normal,
            Some(n) => {
                let [i, j, k] = self.mesh.faces[h.prim as usize].map(|v| v as usize);
                (n[i] * w + n[j] * h.u + n[k] * h.v)
                    .try_normalize(0.0)
                    .unwrap_or(geometric_normal)
            }
        };
        SurfaceHit {
            point,
            geometric_normal,
            shading_normal,
            prim: h.prim,
        }
    }
}

impl Surface for MeshSurface {
    fn intersect_serial(
        &self,
        rays: &[Ray],
        out: &mut [Option<SurfaceHit>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        let mut hits = vec![None; rays.len()];
        self.scene.intersect_serial(rays, &mut hits, coherent)?;
        for (o, h) in out.iter_mut().zip(&hits) {
            *o = h.as_ref().map(|h| self.surface_hit(h));
        }
        Ok(())
    }

    fn first_elements(
        &self,
        rays: &[Ray],
        out: &mut [Option<u32>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        self.scene.first_prims_serial(rays, out, coherent)
    }

    fn offset(&self) -> f64 {
        self.offset
    }
}

/// Optical settings of a path.
#[derive(Clone, Copy, Debug)]
pub struct PathSettings {
    /// Refractive index of the object.
    pub ior: f64,
    /// Refractive index of the surrounding air.
    pub ior_air: f64,
    /// Most refractions a path may have; a path needing more ends as `TooManyInterfaces`.
    pub max_refractions: u32,
}

impl PathSettings {
    /// Index `ior` in air, at most `max_refractions` refractions.
    pub fn new(ior: f64, max_refractions: u32) -> Self {
        Self {
            ior,
            ior_air: IOR_AIR,
            max_refractions,
        }
    }
}

/// How a path ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
pub enum PathEnd {
    /// Left the object (or never met it: `refractions == 0`); `ray` is the final ray.
    Left,
    /// Total internal reflection at an interface.
    TotalInternalReflection,
    /// Met more interfaces than `max_refractions` allows.
    TooManyInterfaces,
    /// The shading normal faced away from the ray (interpolated normals at grazing incidence).
    GrazingNormal,
}

/// A traced path: how it ended, its refractions, its last ray and its Fresnel transmittance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Path {
    pub end: PathEnd,
    pub refractions: u32,
    /// Origin (mm) and unit direction of the last ray: the exit ray for `Left`.
    pub origin: Point3<f64>,
    pub dir: Vector3<f64>,
    /// Product of the Fresnel transmittances along the path.
    pub transmittance: f64,
}

/// Most interfaces a [`Trail`] records.
pub const MAX_TRAIL: usize = 8;

/// The surface elements a path refracted at, in order (the first `len` of `prims`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Trail {
    pub prims: [u32; MAX_TRAIL],
    pub len: u8,
}

impl Trail {
    pub fn prims(&self) -> &[u32] {
        &self.prims[..self.len as usize]
    }
}

/// Rays traced together on one thread: every interface of the chunk is one batch for Embree,
/// small enough to stay in cache.
pub const TRACE_CHUNK: usize = 2048;

/// Traces `rays` (unit directions) through `surface`, in parallel chunks.
pub fn trace_paths(
    surface: &dyn Surface,
    rays: &[Ray],
    settings: &PathSettings,
) -> Result<Vec<Path>, TraceError> {
    let chunks: Vec<Vec<Path>> = rays
        .par_chunks(TRACE_CHUNK)
        .map(|c| trace_chunk(surface, c, settings, None))
        .collect::<Result<_, _>>()?;
    Ok(chunks.concat())
}

/// Traces `rays` on the calling thread, one interface at a time for all of them (the first
/// batch, the caller's rays in their order, in packets); records the elements refracted at into
/// `trails` if given (then `settings.max_refractions` must not exceed [`MAX_TRAIL`]).
pub fn trace_chunk(
    surface: &dyn Surface,
    rays: &[Ray],
    settings: &PathSettings,
    mut trails: Option<&mut [Trail]>,
) -> Result<Vec<Path>, TraceError> {
    if trails.is_some() {
        assert!(settings.max_refractions as usize <= MAX_TRAIL);
    }
    let mut paths: Vec<Path> = rays
        .iter()
        .map(|r| Path {
            end: PathEnd::Left,
            refractions: 0,
            origin: r.origin,
            dir: r.dir,
            transmittance: 1.0,
        })
        .collect();
    let mut active: Vec<usize> = (0..rays.len()).collect();
    let mut batch = rays.to_vec();
    let mut hits = vec![None; rays.len()];
    let offset = surface.offset();
    let mut first = true;
    while !active.is_empty() {
        if !first {
            batch.clear();
            batch.extend(
                active
                    .iter()
                    .map(|&i| Ray::new(paths[i].origin, paths[i].dir)),
            );
        }
        let hits = &mut hits[..batch.len()];
        surface.intersect_serial(&batch, hits, first)?;
        first = false;
        let mut next = 0;
        for k in 0..active.len() {
            let i = active[k];
            let Some(h) = &hits[k] else { continue };
            let p = step(&paths[i], h, settings, offset);
            if let Some(t) = trails.as_deref_mut() {
                if p.refractions > paths[i].refractions {
                    let t = &mut t[i];
                    t.prims[t.len as usize] = h.prim;
                    t.len += 1;
                }
            }
            paths[i] = p;
            if p.end == PathEnd::Left {
                active[next] = i;
                next += 1;
            }
        }
        active.truncate(next);
    }
    Ok(paths)
}

/// The path after meeting the surface at `h`.
fn step(p: &Path, h: &SurfaceHit, s: &PathSettings, offset: f64) -> Path {
    let entering = p.dir.dot(&h.geometric_normal) < 0.0;
    let (n_i, n_t) = if entering {
        (s.ior_air, s.ior)
    } else {
        (s.ior, s.ior_air)
    };
    let n = if entering {
        h.shading_normal
    } else {
        -h.shading_normal
    };
    let ended = |end| Path {
        end,
        origin: h.point,
        ..*p
    };
    if p.refractions >= s.max_refractions {
        return ended(PathEnd::TooManyInterfaces);
    }
    if p.dir.dot(&n) >= 0.0 {
        return ended(PathEnd::GrazingNormal);
    }
    match refract(&p.dir, &n, n_i, n_t) {
        None => ended(PathEnd::TotalInternalReflection),
        Some(r) => {
            let dir = r.dir.normalize();
            Path {
                end: PathEnd::Left,
                refractions: p.refractions + 1,
                origin: restart_origin(&h.point, &dir, &h.geometric_normal, offset),
                dir,
                transmittance: p.transmittance * r.transmittance,
            }
        }
    }
}

/// Where a ray leaving the surface point `point` along unit `dir` restarts: moved along the ray
/// far enough to be `offset` (mm) off the surface's plane (unit normal `normal`) even when it
/// leaves at a grazing angle, so that Embree does not find the same surface again (the origin
/// stays on the exact path).
pub fn restart_origin(
    point: &Point3<f64>,
    dir: &Vector3<f64>,
    normal: &Vector3<f64>,
    offset: f64,
) -> Point3<f64> {
    point + dir * (offset / dir.dot(normal).abs().max(1e-3))
}
