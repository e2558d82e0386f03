//! Safe wrapper over the Embree C shim (`wrapper/glasscan_embree.h`).
//!
//! A [`Device`] is Embree's context; a [`Scene`] holds one triangle mesh and answers closest-hit
//! ray queries (f32 inside Embree, converted at the boundary) and exact f64 closest-point queries,
//! from many threads at once. Embree errors become [`TraceError`]s.

use std::ffi::CStr;
use std::sync::Arc;

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::mesh::TriMesh;

#[allow(non_camel_case_types, non_upper_case_globals, dead_code)]
mod ffi {
    include!(concat!(env!("OUT_DIR"), "/embree_ffi.rs"));
}

/// Rays or query points handed to Embree per call (per rayon task).
const CHUNK: usize = 1024;

/// An Embree failure, or input Embree cannot take.
#[derive(Debug, thiserror::Error)]
pub enum TraceError {
    #[error("{0}")]
    Embree(String),
    #[error("mesh has {0} vertices/faces, more than Embree's 32-bit indices allow")]
    TooLarge(usize),
    #[error("vertex update has {got} vertices, the scene has {expected}")]
    VertexCount { got: usize, expected: usize },
    #[error("vertex {0} has a non-finite coordinate")]
    NonFinite(usize),
}

fn last_error(fallback: &str) -> TraceError {
    // SAFETY: gs_last_error returns a pointer to a NUL-terminated thread-local buffer.
    let msg = unsafe { CStr::from_ptr(ffi::gs_last_error()) }
        .to_string_lossy()
        .into_owned();
    TraceError::Embree(if msg.is_empty() {
        fallback.to_string()
    } else {
        msg
    })
}

/// The Embree version glasscan was built against, e.g. "3.13.5".
pub fn embree_version() -> String {
    // SAFETY: returns a static NUL-terminated string.
    unsafe { CStr::from_ptr(ffi::gs_embree_version()) }
        .to_string_lossy()
        .into_owned()
}

/// An Embree device (thread pool and allocator). Shared by the scenes made from it.
pub struct Device {
    raw: *mut ffi::gs_device,
}

// SAFETY: Embree devices are thread-safe.
unsafe impl Send for Device {}
unsafe impl Sync for Device {}

impl Device {
    /// A device with Embree's default configuration.
    pub fn new() -> Result<Arc<Self>, TraceError> {
        // SAFETY: a NULL config is allowed.
        let raw = unsafe { ffi::gs_device_new(std::ptr::null()) };
        if raw.is_null() {
            return Err(last_error("Embree: could not create a device"));
        }
        Ok(Arc::new(Self { raw }))
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        // SAFETY: raw came from gs_device_new; scenes hold an Arc, so none outlives it.
        unsafe { ffi::gs_device_free(self.raw) }
    }
}

/// How a scene's acceleration structure is built and updated when its vertices move.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuildMode {
    /// High-quality BVH for a mesh that never moves.
    Static,
    /// Medium-quality BVH, rebuilt after every vertex update.
    Rebuild,
    /// Low-quality dynamic BVH, refitted after every vertex update (topology fixed).
    Refit,
}

impl BuildMode {
    fn raw(self) -> ffi::gs_build_mode {
        match self {
            BuildMode::Static => ffi::gs_build_mode::GS_BUILD_STATIC,
            BuildMode::Rebuild => ffi::gs_build_mode::GS_BUILD_REBUILD,
            BuildMode::Refit => ffi::gs_build_mode::GS_BUILD_REFIT,
        }
    }
}

/// A ray `origin + t·dir`, accepting hits with `tnear <= t <= tfar` (mm if `dir` is unit).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Point3<f64>,
    pub dir: Vector3<f64>,
    pub tnear: f64,
    pub tfar: f64,
}

impl Ray {
    /// A ray accepting every hit in front of its origin.
    pub fn new(origin: Point3<f64>, dir: Vector3<f64>) -> Self {
        Self {
            origin,
            dir,
            tnear: 0.0,
            tfar: f64::INFINITY,
        }
    }

    fn raw(&self) -> ffi::gs_ray {
        ffi::gs_ray {
            org: [
                self.origin.x as f32,
                self.origin.y as f32,
                self.origin.z as f32,
            ],
            tnear: self.tnear as f32,
            dir: [self.dir.x as f32, self.dir.y as f32, self.dir.z as f32],
            tfar: self.tfar as f32,
        }
    }
}

/// The closest hit of a ray: parameter `t` and barycentrics (`u`, `v`) on triangle `prim`, both
/// computed in f64 on the triangle Embree found; the hit point is `(1−u−v)·v0 + u·v1 + v·v2`.
/// Near an edge, `u`, `v` may stray outside [0, 1] by Embree's float tolerance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f64,
    pub u: f64,
    pub v: f64,
    pub prim: u32,
}

/// The closest surface point to a query point (exact, f64): the point, its distance (mm) and
/// the triangle it lies on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClosestPoint {
    pub point: Point3<f64>,
    pub dist: f64,
    pub prim: u32,
}

/// One triangle mesh in an Embree scene, with an f64 copy of its geometry for exact
/// closest-point queries.
pub struct Scene {
    raw: *mut ffi::gs_scene,
    _device: Arc<Device>,
    verts: Vec<f64>,
    tris: Vec<u32>,
}

// SAFETY: a committed Embree scene may be queried from many threads; mutation (`update_vertices`)
// takes `&mut self`, so it never overlaps a query.
unsafe impl Send for Scene {}
unsafe impl Sync for Scene {}

impl Scene {
    /// Builds a scene from `mesh` (indices must be in range, as [`crate::mesh::io`] guarantees).
    pub fn new(device: &Arc<Device>, mesh: &TriMesh, mode: BuildMode) -> Result<Self, TraceError> {
        let n = mesh.positions.len().max(mesh.faces.len());
        if n >= u32::MAX as usize {
            return Err(TraceError::TooLarge(n));
        }
        check_finite(mesh.positions.iter())?;
        let vf = mesh.positions_f32();
        let tris: Vec<u32> = mesh.faces.iter().flatten().copied().collect();
        // SAFETY: the buffers hold nverts·3 floats and ntris·3 indices; the shim copies them.
        let raw = unsafe {
            ffi::gs_scene_new(
                device.raw,
                mode.raw(),
                vf.as_ptr(),
                mesh.positions.len(),
                tris.as_ptr(),
                mesh.faces.len(),
            )
        };
        if raw.is_null() {
            return Err(last_error("Embree: could not build the scene"));
        }
        let verts = mesh
            .positions
            .iter()
            .flat_map(|p| [p.x, p.y, p.z])
            .collect();
        Ok(Self {
            raw,
            _device: device.clone(),
            verts,
            tris,
        })
    }

    /// Moves every vertex (same count and topology) and recommits: a refit or a rebuild,
    /// depending on the scene's [`BuildMode`].
    pub fn update_vertices(&mut self, positions: &[Point3<f64>]) -> Result<(), TraceError> {
        let expected = self.verts.len() / 3;
        if positions.len() != expected {
            return Err(TraceError::VertexCount {
                got: positions.len(),
                expected,
            });
        }
        check_finite(positions.iter())?;
        let vf: Vec<f32> = positions
            .iter()
            .flat_map(|p| [p.x as f32, p.y as f32, p.z as f32])
            .collect();
        // SAFETY: vf holds positions.len()·3 floats; raw is a live scene, not queried meanwhile.
        let rc = unsafe { ffi::gs_scene_update_vertices(self.raw, vf.as_ptr(), positions.len()) };
        if rc != 0 {
            return Err(last_error("Embree: scene update failed"));
        }
        for (dst, p) in self.verts.chunks_exact_mut(3).zip(positions) {
            dst.copy_from_slice(&[p.x, p.y, p.z]);
        }
        Ok(())
    }

    /// Closest hits of `rays` on the calling thread. `coherent`: trace in packets of 8 (for
    /// camera rays in scanline order). `out` must be as long as `rays`.
    pub fn intersect_serial(
        &self,
        rays: &[Ray],
        out: &mut [Option<Hit>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        self.query_serial(rays, coherent, |i, h| {
            out[i] = (h.prim != ffi::GS_INVALID_ID).then(|| self.refine(&rays[i], h));
        })
    }

    /// The triangle each of `rays` meets first (`None`: none), on the calling thread, without
    /// the hit's geometry: for callers that recompute it on that triangle themselves. As
    /// [`Self::intersect_serial`] otherwise.
    pub fn first_prims_serial(
        &self,
        rays: &[Ray],
        out: &mut [Option<u32>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        self.query_serial(rays, coherent, |i, h| {
            out[i] = (h.prim != ffi::GS_INVALID_ID).then_some(h.prim);
        })
    }

    /// Embree's closest hits of `rays`, [`CHUNK`] at a time, handed to `each` with the ray's
    /// index.
    fn query_serial(
        &self,
        rays: &[Ray],
        coherent: bool,
        mut each: impl FnMut(usize, &ffi::gs_hit),
    ) -> Result<(), TraceError> {
        let mut raw_rays = Vec::with_capacity(CHUNK.min(rays.len()));
        let mut raw_hits = vec![ffi::gs_hit::default(); CHUNK.min(rays.len())];
        for (c, rc) in rays.chunks(CHUNK).enumerate() {
            raw_rays.clear();
            raw_rays.extend(rc.iter().map(Ray::raw));
            let hits = &mut raw_hits[..rc.len()];
            // SAFETY: both buffers hold rc.len() elements; the scene is committed.
            let status = unsafe {
                ffi::gs_intersect(
                    self.raw,
                    raw_rays.as_ptr(),
                    hits.as_mut_ptr(),
                    rc.len(),
                    coherent as i32,
                )
            };
            if status != 0 {
                return Err(last_error("Embree: ray query failed"));
            }
            for (k, h) in hits.iter().enumerate() {
                each(c * CHUNK + k, h);
            }
        }
        Ok(())
    }

    /// Embree's bare closest-hit queries for `rays` on the calling thread (packets of 8 if
    /// `coherent`), with nothing done with the hits but counting them: the yardstick of
    /// `bench gradient`.
    pub fn count_hits_serial(&self, rays: &[Ray], coherent: bool) -> Result<usize, TraceError> {
        let raw_rays: Vec<ffi::gs_ray> = rays.iter().map(Ray::raw).collect();
        let mut hits = vec![ffi::gs_hit::default(); rays.len()];
        // SAFETY: both buffers hold rays.len() elements; the scene is committed.
        let status = unsafe {
            ffi::gs_intersect(
                self.raw,
                raw_rays.as_ptr(),
                hits.as_mut_ptr(),
                rays.len(),
                coherent as i32,
            )
        };
        if status != 0 {
            return Err(last_error("Embree: ray query failed"));
        }
        Ok(hits.iter().filter(|h| h.prim != ffi::GS_INVALID_ID).count())
    }

    /// Embree picks the triangle (in f32); the hit's `t` and barycentrics are recomputed here in
    /// f64 on that triangle (Möller–Trumbore), so they do not carry Embree's float error, which
    /// grows as 1/cos at grazing incidence.
    fn refine(&self, ray: &Ray, h: &ffi::gs_hit) -> Hit {
        let corner = |k: usize| {
            let i = self.tris[3 * h.prim as usize + k] as usize * 3;
            Vector3::new(self.verts[i], self.verts[i + 1], self.verts[i + 2])
        };
        let (a, b, c) = (corner(0), corner(1), corner(2));
        let (e1, e2) = (b - a, c - a);
        let p = ray.dir.cross(&e2);
        let det = e1.dot(&p);
        let embree = Hit {
            t: h.t as f64,
            u: h.u as f64,
            v: h.v as f64,
            prim: h.prim,
        };
        if det == 0.0 {
            return embree;
        }
        let s = ray.origin.coords - a;
        let q = s.cross(&e1);
        let refined = Hit {
            t: e2.dot(&q) / det,
            u: s.dot(&p) / det,
            v: ray.dir.dot(&q) / det,
            prim: h.prim,
        };
        if refined.t.is_finite() {
            refined
        } else {
            embree
        }
    }

    /// Closest hits of `rays` into `out` (same length), traced in parallel on the current rayon
    /// pool.
    pub fn intersect_into(
        &self,
        rays: &[Ray],
        out: &mut [Option<Hit>],
        coherent: bool,
    ) -> Result<(), TraceError> {
        assert_eq!(rays.len(), out.len(), "one output per ray");
        rays.par_chunks(CHUNK)
            .zip(out.par_chunks_mut(CHUNK))
            .try_for_each(|(r, o)| self.intersect_serial(r, o, coherent))
    }

    /// Closest hits of `rays`, traced in parallel on the current rayon pool.
    pub fn intersect(&self, rays: &[Ray], coherent: bool) -> Result<Vec<Option<Hit>>, TraceError> {
        let mut out = vec![None; rays.len()];
        self.intersect_into(rays, &mut out, coherent)?;
        Ok(out)
    }

    /// Whether each of `rays` meets the surface at all, sooner than [`Self::intersect`] (any
    /// triangle ends a ray's search), in parallel on the current rayon pool; `coherent`: the
    /// rays come in groups that run close together, worth tracing in packets. The answer is
    /// [`Self::intersect`]'s but for a ray that grazes a triangle's edge within float precision,
    /// where Embree's two traversals may disagree.
    pub fn hits_any(&self, rays: &[Ray], coherent: bool) -> Result<Vec<bool>, TraceError> {
        let mut out = vec![false; rays.len()];
        rays.par_chunks(CHUNK)
            .zip(out.par_chunks_mut(CHUNK))
            .try_for_each(|(r, o)| {
                let raw: Vec<ffi::gs_ray> = r.iter().map(Ray::raw).collect();
                let mut hit = vec![0u8; r.len()];
                // SAFETY: both buffers hold r.len() elements; the scene is committed.
                let status = unsafe {
                    ffi::gs_occluded(
                        self.raw,
                        raw.as_ptr(),
                        hit.as_mut_ptr(),
                        r.len(),
                        coherent as i32,
                    )
                };
                if status != 0 {
                    return Err(last_error("Embree: occlusion query failed"));
                }
                for (o, h) in o.iter_mut().zip(&hit) {
                    *o = *h != 0;
                }
                Ok(())
            })?;
        Ok(out)
    }

    /// Exact closest surface points to `points` (mm), in parallel on the current rayon pool.
    pub fn closest_points(&self, points: &[Point3<f64>]) -> Result<Vec<ClosestPoint>, TraceError> {
        self.closest_points_near(points, f64::INFINITY)
    }

    /// As [`Self::closest_points`], faster when most points lie within `radius_hint` (mm) of the
    /// surface; the result does not depend on the hint.
    pub fn closest_points_near(
        &self,
        points: &[Point3<f64>],
        radius_hint: f64,
    ) -> Result<Vec<ClosestPoint>, TraceError> {
        let mut out = vec![
            ClosestPoint {
                point: Point3::origin(),
                dist: f64::INFINITY,
                prim: u32::MAX
            };
            points.len()
        ];
        points
            .par_chunks(CHUNK)
            .zip(out.par_chunks_mut(CHUNK))
            .try_for_each(|(p, o)| {
                let flat: Vec<f64> = p.iter().flat_map(|q| [q.x, q.y, q.z]).collect();
                let mut raw = vec![ffi::gs_closest::default(); p.len()];
                // SAFETY: verts/tris describe the committed mesh; flat holds p.len()·3 doubles and
                // raw p.len() results.
                let status = unsafe {
                    ffi::gs_closest_points(
                        self.raw,
                        self.verts.as_ptr(),
                        self.tris.as_ptr(),
                        flat.as_ptr(),
                        p.len(),
                        radius_hint,
                        raw.as_mut_ptr(),
                    )
                };
                if status != 0 {
                    return Err(last_error("Embree: closest-point query failed"));
                }
                for (o, r) in o.iter_mut().zip(&raw) {
                    *o = ClosestPoint {
                        point: Point3::from(r.point),
                        dist: r.dist,
                        prim: r.prim,
                    };
                }
                Ok(())
            })?;
        Ok(out)
    }
}

impl Drop for Scene {
    fn drop(&mut self) {
        // SAFETY: raw came from gs_scene_new and is dropped once; the device outlives it (Arc).
        unsafe { ffi::gs_scene_free(self.raw) }
    }
}

fn check_finite<'a>(points: impl Iterator<Item = &'a Point3<f64>>) -> Result<(), TraceError> {
    for (i, p) in points.enumerate() {
        if !p.iter().all(|c| c.is_finite()) {
            return Err(TraceError::NonFinite(i));
        }
    }
    Ok(())
}
