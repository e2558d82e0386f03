//! The silhouette term, DRT's contour-edge formulation (docs/architecture.md §4).
//!
//! Per view: contour edges are mesh edges whose two faces face opposite ways from the camera
//! centre. Both endpoints are projected (with the lens model); at the projected midpoint M two
//! probe rays are cast at ±δ px along the edge's 2D normal N = (a_y − b_y, b_x − a_x), and
//! f = hit(+) − hit(−) keeps only true, unoccluded contour edges (f ≠ 0). The mask enters as its
//! signed distance image sd (pixels, > 0 inside; see [`Silhouette`]).
//!
//! Distances are measured in the *outline unit* u, a length at the object (mm; the run's is a
//! share of the start mesh's diagonal, `silhouette_scale`), not in camera pixels: per view,
//! k = u·f / z pixels make one unit (f the focal length in pixels, z the depth of the mesh's
//! bounding-box centre, held fixed within an evaluation), so the same offset at the object costs
//! the same at every camera resolution. DRT's δ is 1 unit (DRT's 1 px); the presets' is 0.03
//! (`silhouette_probe`), which also drops the edges a mesh's zigzag contour hides just inside
//! its own outline: they would pull outward with nothing to balance them.
//!
//! Two forms, with s = sd(M) / k:
//! - [`SilhouetteForm::Drt`]: loss |m(M) − 0.5| with m = 0.5 + 0.5·clamp(s, −1, 1), and DRT's
//!   image-space gradient on both endpoints, sign(sd)·f·N / k² — a surrogate (it keeps pushing
//!   where the loss is flat, beyond 1 unit), pulled back to 3D with the depth held fixed. It
//!   points where the exact gradient points but is not the derivative of anything, so it has no
//!   finite-difference test; a test checks its direction instead.
//! - [`SilhouetteForm::Distance`]: loss Huber(s, 1) — squared near the outline, linear beyond —
//!   with its exact gradient through the bilinear sd image and the full projection Jacobian
//!   (depth included). Checked against finite differences.

use nalgebra::{Point3, Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Accumulator, Contributions};
use crate::mesh::{InteriorEdge, TriMesh};
use crate::scan::silhouette::Silhouette;
use crate::trace::{Ray, Scene, TraceError};

type V3 = Vector3<f64>;

/// Which silhouette loss and gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SilhouetteForm {
    Drt,
    Distance,
}

/// A contour edge of one view with what its gradient needs.
#[derive(Clone, Copy, Debug)]
pub struct ContourEdge {
    pub verts: [u32; 2],
    /// f = hit(+) − hit(−), ±1.
    pub side: f64,
}

/// A mesh with what finding its contour edges from any eye needs: its interior edges and each
/// face's plane (the unnormalised normal (b − a) × (c − a) and the first corner a), computed
/// once for all the views of an evaluation rather than twice per edge and view.
pub struct ContourMesh<'a> {
    pub mesh: &'a TriMesh,
    pub edges: &'a [InteriorEdge],
    planes: Vec<(V3, Point3<f64>)>,
}

impl<'a> ContourMesh<'a> {
    /// `edges` must be `mesh`'s interior edges.
    pub fn new(mesh: &'a TriMesh, edges: &'a [InteriorEdge]) -> Self {
        let planes = (0..mesh.faces.len())
            .into_par_iter()
            .map(|f| (mesh.face_cross(f), mesh.corners(f)[0]))
            .collect();
        Self {
            mesh,
            edges,
            planes,
        }
    }

    /// Whether each face shows its front (its outward side) to `eye`.
    fn facing(&self, eye: &Point3<f64>) -> Vec<bool> {
        (self.planes.par_iter())
            .map(|(n, a)| n.dot(&(eye - a)) > 0.0)
            .collect()
    }
}

/// Contour edges of `shape` seen from view `sil` that the probe rays, `probe_px` camera pixels
/// to either side, confirm (batched through `scene`, which must hold the mesh).
pub fn contour_edges(
    shape: &ContourMesh,
    sil: &Silhouette,
    scene: &Scene,
    probe_px: f64,
) -> Result<Vec<ContourEdge>, TraceError> {
    let mesh = shape.mesh;
    let to_world = sil.pose.inverse();
    let eye = to_world * Point3::origin();
    let front = shape.facing(&eye);
    let front = |f: u32| front[f as usize];
    let candidates: Vec<(InteriorEdge, [Ray; 2])> = (shape.edges)
        .par_iter()
        .filter(|e| front(e.faces[0]) != front(e.faces[1]))
        .filter_map(|e| {
            let [a, b] = e
                .verts
                .map(|v| sil.camera.project(&(sil.pose * mesh.positions[v as usize])));
            let (a, b) = (a?, b?);
            let n = Vector2::new(a.y - b.y, b.x - a.x);
            let len = n.norm();
            if len < 1e-9 {
                return None;
            }
            let m = nalgebra::center(&a, &b);
            let probe = |s: f64| {
                let p = m + n * (s / len);
                sil.camera
                    .pixel_ray(p.x, p.y)
                    .map(|d| Ray::new(eye, to_world * d))
            };
            Some((*e, [probe(probe_px)?, probe(-probe_px)?]))
        })
        .collect();
    let rays: Vec<Ray> = candidates.iter().flat_map(|(_, r)| *r).collect();
    // Each edge's two probes run side by side: packets of four edges.
    let hits = scene.hits_any(&rays, true)?;
    Ok(candidates
        .iter()
        .zip(hits.chunks_exact(2))
        .filter_map(|((e, _), h)| {
            let side = h[0] as i32 - h[1] as i32;
            (side != 0).then_some(ContourEdge {
                verts: e.verts,
                side: side as f64,
            })
        })
        .collect())
}

/// How many pixels of view `sil` the mesh in `scene` (which must hold `mesh`) and the mask
/// disagree on: covered by the mesh (the pixel-centre ray hits it) and outside the mask, or the
/// other way round. Unlike the contour-edge loss, whose mean over edges changes with the
/// number and the zigzag of the mesh's contour edges, it measures the outline alike at every
/// edge length (the held-out views' test of whether a finer stage fits better).
/// Rays are traced only within the mesh's projected bounding box, through every `stride`-th
/// pixel of every `stride`-th row, each standing for stride² pixels (the same lattice for every
/// mesh compared); the mask's object pixels outside the box are counted as they are.
pub fn outline_disagreement(
    mesh: &TriMesh,
    sil: &Silhouette,
    scene: &Scene,
    stride: usize,
) -> Result<usize, TraceError> {
    let stride = stride.max(1);
    let (w, h) = (sil.camera.width as usize, sil.camera.height as usize);
    let projected = mesh
        .positions
        .iter()
        .filter_map(|p| sil.camera.project(&(sil.pose * p)));
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for q in projected {
        (lo, hi) = (
            [lo[0].min(q.x), lo[1].min(q.y)],
            [hi[0].max(q.x), hi[1].max(q.y)],
        );
    }
    if !(lo[0] <= hi[0] && lo[1] <= hi[1]) {
        return Ok(sil.area_px);
    }
    let clip = |v: f64, n: usize| (v.max(0.0) as usize).min(n);
    let (x0, x1) = (clip(lo[0].floor() - 1.0, w), clip(hi[0].ceil() + 2.0, w));
    let (y0, y1) = (clip(lo[1].floor() - 1.0, h), clip(hi[1].ceil() + 2.0, h));
    let to_world = sil.pose.inverse();
    let eye = to_world * Point3::origin();
    let pixels: Vec<(usize, usize)> = (y0..y1)
        .step_by(stride)
        .flat_map(|y| (x0..x1).step_by(stride).map(move |x| (x, y)))
        .collect();
    let rays: Vec<Ray> = pixels
        .iter()
        .map(|&(x, y)| {
            let d = sil.camera.pixel_ray(x as f64, y as f64);
            // A pixel without a ray (outside the lens model's range) sees nothing.
            Ray::new(eye, to_world * d.unwrap_or_else(|| -V3::z()))
        })
        .collect();
    let hits = scene.hits_any(&rays, true)?;
    let disagree = (pixels.iter().zip(&hits))
        .filter(|(&(x, y), &hit)| sil.is_object_px(x, y) != hit)
        .count();
    let object_in_box = (y0..y1)
        .flat_map(|y| (x0..x1).map(move |x| (x, y)))
        .filter(|&(x, y)| sil.is_object_px(x, y))
        .count();
    Ok(disagree * stride * stride + (sil.area_px - object_in_box))
}

/// Camera pixels per `unit_mm` at the object in view `sil`: at the depth of the bounding-box
/// centre of `mesh` (1 when the centre is not in front of the camera).
pub fn pixels_per_unit(mesh: &TriMesh, sil: &Silhouette, unit_mm: f64) -> f64 {
    let Some((lo, hi)) = mesh.bbox() else {
        return 1.0;
    };
    let z = (sil.pose * nalgebra::center(&lo, &hi)).z;
    let f = 0.5 * (sil.camera.fx + sil.camera.fy);
    let k = unit_mm * f / z;
    if k.is_finite() && k > 0.0 {
        k
    } else {
        1.0
    }
}

/// Loss of one contour edge and the gradient on its two endpoints (world frame); `k` camera
/// pixels make one outline unit ([`pixels_per_unit`]).
pub fn edge_gradient(
    mesh: &TriMesh,
    sil: &Silhouette,
    e: &ContourEdge,
    form: SilhouetteForm,
    k: f64,
) -> Option<(f64, [V3; 2])> {
    let cam_pts = e.verts.map(|v| sil.pose * mesh.positions[v as usize]);
    let [(a, ja), (b, jb)] = [
        sil.camera.project_jacobian(&cam_pts[0])?,
        sil.camera.project_jacobian(&cam_pts[1])?,
    ];
    let m = nalgebra::center(&a, &b);
    let (sd_px, gx, gy) = sil.sample_px(m.x, m.y);
    let sd = sd_px / k;
    let rot_t = sil.pose.rotation.inverse();
    let (loss, grads) = match form {
        SilhouetteForm::Distance => {
            let (loss, dl) = if sd.abs() <= 1.0 {
                (sd * sd, 2.0 * sd)
            } else {
                (2.0 * sd.abs() - 1.0, 2.0 * sd.signum())
            };
            // M = (A + B)/2; s = sd / k.
            let g_img = Vector2::new(gx, gy) * (0.5 * dl / k);
            (
                loss,
                [
                    rot_t * (ja.transpose() * g_img),
                    rot_t * (jb.transpose() * g_img),
                ],
            )
        }
        SilhouetteForm::Drt => {
            let loss = 0.5 * sd.abs().min(1.0);
            let n = Vector2::new(a.y - b.y, b.x - a.x);
            let g_img = n * (sd.signum() * e.side / (k * k));
            // Depth held fixed: u = fx·X/Z + cx moves with X and Y only.
            let pull = |q: &Point3<f64>| {
                rot_t
                    * V3::new(
                        g_img.x * sil.camera.fx / q.z,
                        g_img.y * sil.camera.fy / q.z,
                        0.0,
                    )
            };
            (loss, [pull(&cam_pts[0]), pull(&cam_pts[1])])
        }
    };
    (loss.is_finite() && grads.iter().all(|g| g.iter().all(|x| x.is_finite())))
        .then_some((loss, grads))
}

/// How the silhouette term measures: its form, its outline unit (mm at the object) and its
/// probes' distance (outline units).
#[derive(Clone, Copy, Debug)]
pub struct SilhouetteSettings {
    pub form: SilhouetteForm,
    pub unit_mm: f64,
    pub probe: f64,
}

/// Adds view `sil`'s silhouette loss and gradient on `shape` (held by `scene`) to `acc`.
pub fn add_view(
    shape: &ContourMesh,
    sil: &Silhouette,
    scene: &Scene,
    s: &SilhouetteSettings,
    acc: &mut Accumulator,
) -> Result<(), TraceError> {
    let mesh = shape.mesh;
    let k = pixels_per_unit(mesh, sil, s.unit_mm);
    let contour = contour_edges(shape, sil, scene, s.probe * k)?;
    let chunks: Vec<Contributions> = contour
        .par_chunks(1024)
        .map(|chunk| {
            let mut c = Contributions::with_capacity(2 * chunk.len(), 0);
            for e in chunk {
                match edge_gradient(mesh, sil, e, s.form, k) {
                    Some((loss, g)) => {
                        c.loss += loss;
                        c.used += 1;
                        c.weight += 1.0;
                        c.grad.extend([(e.verts[0], g[0]), (e.verts[1], g[1])]);
                    }
                    None => c.drops.non_finite += 1,
                }
            }
            c
        })
        .collect();
    acc.add(&chunks);
    Ok(())
}
