//! Isotropic remeshing (Botsch & Kobbelt 2004, as in pmp-library's `uniform_remeshing` and CGAL's
//! `isotropic_remeshing`), in-house.
//!
//! Each iteration: split every edge longer than 4/3·h at its midpoint; collapse every edge shorter
//! than 4/5·h whose collapse keeps the mesh manifold (link condition), flips no triangle and
//! creates no edge longer than 4/3·h; flip edges where that brings the four vertices' valences
//! closer to 6; then a few passes of tangential relaxation (each vertex moves, within its tangent
//! plane, to the area-weighted centroid of its incident triangles' centroids, as CGAL does) and a
//! projection onto the input surface (closest point through Embree's BVH on the input; the normal
//! there is interpolated from the input's vertex normals and defines the next tangent plane). h is the target edge length in mm:
//! one value (uniform), or a per-vertex field from the input's curvature (adaptive), either
//! optionally bounded per vertex by the caller (where its data asks for shorter edges).
//! The output is closed, manifold and outward-oriented like the input, with the same genus.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::mesh::halfedge::HalfEdgeMesh;
use crate::mesh::validate::{validate, Defect, InvalidMesh};
use crate::mesh::TriMesh;
use crate::trace::{BuildMode, Device, Scene, TraceError};

/// Settings of [`remesh`].
#[derive(Clone, Debug)]
pub struct RemeshOptions {
    /// Target edge length h, mm (the largest target in adaptive mode).
    pub edge_mm: f64,
    /// Split–collapse–flip–relax iterations (pmp and CGAL default to 10; DRT used 3).
    pub iterations: usize,
    /// Tangential relaxation passes per iteration (each iteration ends with one projection).
    pub relax_passes: usize,
    /// Curvature-adaptive sizing instead of a uniform h.
    pub adaptive: Option<AdaptiveSizing>,
    /// Keep the input's sharp edges: edges whose faces meet at a dihedral angle above this
    /// (degrees) become feature lines that are never flipped, are split and collapsed only along
    /// themselves, and along which their vertices relax; where other than two feature edges meet,
    /// the vertex is a corner and stays put. `None` (the default, as in DRT): no features.
    pub feature_angle_deg: Option<f64>,
    /// Per input vertex, the longest target edge there, mm (it may be shorter than the adaptive
    /// mode's smallest edge): where something other than curvature asks for shorter edges, such as data
    /// the input does not yet fit. `None`: no bound. Its length must be the input's vertex count.
    pub edge_bound_mm: Option<Vec<f64>>,
}

impl RemeshOptions {
    /// Uniform remeshing to edge length `edge_mm` with the default iterations.
    pub fn uniform(edge_mm: f64) -> Self {
        Self {
            edge_mm,
            iterations: 10,
            relax_passes: 3,
            adaptive: None,
            feature_angle_deg: None,
            edge_bound_mm: None,
        }
    }
}

/// Curvature-adaptive target edge lengths: h = sqrt(6ε/κ − 3ε²) (the edge length whose chord
/// deviates by ε from a circle of curvature κ) where ε < 1/κ, else the largest; clamped to
/// [min_edge_mm, edge_mm]. A larger ε never gives shorter edges.
#[derive(Clone, Copy, Debug)]
pub struct AdaptiveSizing {
    /// Smallest target edge length, mm.
    pub min_edge_mm: f64,
    /// Largest allowed chord deviation ε from the input surface, mm.
    pub max_error_mm: f64,
}

/// Why a mesh could not be remeshed.
#[derive(Debug, thiserror::Error)]
pub enum RemeshError {
    #[error("the input mesh cannot be remeshed: {0}")]
    Invalid(InvalidMesh),
    #[error("{0}")]
    BadSetting(String),
    #[error(transparent)]
    Trace(#[from] TraceError),
}

/// Remeshes `input` (closed, manifold, oriented; degenerate faces are allowed and removed).
pub fn remesh(input: &TriMesh, opts: &RemeshOptions) -> Result<TriMesh, RemeshError> {
    let report = validate(input);
    let fatal: Vec<Defect> = report
        .defects
        .into_iter()
        .filter(|d| !matches!(d, Defect::Degenerate { .. }))
        .collect();
    if !fatal.is_empty() {
        return Err(RemeshError::Invalid(InvalidMesh(fatal)));
    }
    check_settings(input, opts)?;
    let device = Device::new()?;
    let reference = Reference::new(&device, input, opts)?;
    let mut r = Remesher::new(input, &reference, opts.feature_angle_deg);
    for _ in 0..opts.iterations {
        r.split_long_edges();
        r.collapse_short_edges();
        r.flip_edges();
        r.compact();
        for _ in 0..opts.relax_passes {
            r.relax();
        }
        r.project()?;
    }
    r.improve_angles();
    Ok(r.mesh.to_trimesh())
}

/// A triangle whose edge cross product is below this share of its two edges' squared lengths
/// has (nearly) no area, and so no normal direction to compare.
const DEGENERATE_CROSS: f64 = 1e-9;

/// Face `f`'s unit normal; `None` for a face of (nearly) no area ([`DEGENERATE_CROSS`]).
fn face_direction(m: &HalfEdgeMesh, f: u32) -> Option<Vector3<f64>> {
    let [a, b, c] = m.face_vertices(f).map(|v| m.pos[v as usize]);
    let scale = (b - a).norm_squared() + (c - a).norm_squared();
    (b - a)
        .cross(&(c - a))
        .try_normalize(DEGENERATE_CROSS * scale)
}

/// The most faces a remesh may make.
const MAX_FACES: f64 = 5e7;
/// The most iterations (and relaxation passes per iteration).
pub const MAX_ITERATIONS: usize = 1000;

fn check_settings(input: &TriMesh, opts: &RemeshOptions) -> Result<(), RemeshError> {
    let bad = |m: String| Err(RemeshError::BadSetting(m));
    let diag = input.bbox_diagonal();
    let h = opts.edge_mm;
    if !(h.is_finite() && h > 0.0) {
        return bad(format!(
            "edge length {h} mm: it must be a positive number of mm"
        ));
    }
    if h > diag {
        return bad(format!(
            "edge length {h} mm is larger than the mesh (bounding-box diagonal {diag:.3} mm)"
        ));
    }
    if opts.iterations > MAX_ITERATIONS || opts.relax_passes > MAX_ITERATIONS {
        return bad(format!(
            "{} iterations and {} relaxation passes: at most {MAX_ITERATIONS} each",
            opts.iterations, opts.relax_passes
        ));
    }
    if let Some(a) = opts.adaptive {
        let sane = a.min_edge_mm > 0.0
            && a.min_edge_mm <= h
            && a.max_error_mm > 0.0
            && a.max_error_mm.is_finite();
        if !sane {
            return bad(format!(
                "adaptive sizing needs 0 < min edge ({} mm) <= edge ({h} mm) and a positive error ({} mm)",
                a.min_edge_mm, a.max_error_mm
            ));
        }
    }
    // An equilateral triangle of side h has area √3/4·h²; keep the output below 50 M faces.
    let min_bound = (opts.edge_bound_mm.iter().flatten()).fold(f64::INFINITY, |m, &b| m.min(b));
    let min_h = opts
        .adaptive
        .map_or(h, |a| a.min_edge_mm.min(h))
        .min(min_bound);
    let floor = (input.area() / (3f64.sqrt() / 4.0 * MAX_FACES)).sqrt();
    if min_h < floor {
        return bad(format!(
            "edge length {min_h} mm would give more than {MAX_FACES:.0} faces on this mesh \
             ({:.0} mm²); use at least {floor:.4} mm",
            input.area()
        ));
    }
    if let Some(f) = opts.feature_angle_deg {
        if !(0.0..180.0).contains(&f) {
            return bad(format!("feature angle {f}°: it must lie in [0, 180)"));
        }
    }
    if let Some(bound) = &opts.edge_bound_mm {
        if bound.len() != input.positions.len() || bound.iter().any(|b| b.is_nan() || *b <= 0.0) {
            return bad(format!(
                "edge bounds: {} values for {} vertices; each must be a positive length in mm",
                bound.len(),
                input.positions.len()
            ));
        }
    }
    Ok(())
}

/// The input surface: a BVH for closest points, vertex normals and target edge lengths to
/// interpolate there.
struct Reference<'a> {
    mesh: &'a TriMesh,
    scene: Scene,
    normals: Vec<Vector3<f64>>,
    /// Target edge length at each input vertex, mm.
    sizing: Vec<f64>,
    /// The largest target edge length, mm.
    max_target: f64,
}

impl<'a> Reference<'a> {
    fn new(
        device: &std::sync::Arc<Device>,
        mesh: &'a TriMesh,
        opts: &RemeshOptions,
    ) -> Result<Self, TraceError> {
        let scene = Scene::new(device, mesh, BuildMode::Static)?;
        let normals = mesh.vertex_normals();
        let mut sizing = match opts.adaptive {
            None => vec![opts.edge_mm; mesh.positions.len()],
            Some(a) => curvature_sizing(mesh, &normals, opts.edge_mm, a),
        };
        if let Some(bound) = &opts.edge_bound_mm {
            for (h, b) in sizing.iter_mut().zip(bound) {
                *h = h.min(*b);
            }
        }
        Ok(Self {
            mesh,
            scene,
            normals,
            sizing,
            max_target: opts.edge_mm,
        })
    }

    /// Interpolates per-vertex `values` of the input at point `q` on face `f`.
    fn interpolate<T>(&self, values: &[T], f: u32, q: &Point3<f64>) -> T
    where
        T: Copy + std::ops::Mul<f64, Output = T> + std::ops::Add<Output = T>,
    {
        let [a, b, c] = self.mesh.faces[f as usize].map(|v| v as usize);
        let w = barycentric(q, &self.mesh.corners(f as usize));
        values[a] * w[0] + values[b] * w[1] + values[c] * w[2]
    }
}

/// Per vertex of `mesh`, the target edge length (mm) of the adaptive mode with sizing `a` and
/// largest edge `h_max` (mm), before any per-vertex bound: what the surface's curvature alone
/// asks for there.
pub fn curvature_edges(mesh: &TriMesh, h_max: f64, a: AdaptiveSizing) -> Vec<f64> {
    curvature_sizing(mesh, &mesh.vertex_normals(), h_max, a)
}

/// Per-vertex target edge lengths from the largest normal curvature along the vertex's edges,
/// κ ≈ |n_a − n_b| / |p_a − p_b|.
fn curvature_sizing(
    mesh: &TriMesh,
    normals: &[Vector3<f64>],
    h_max: f64,
    a: AdaptiveSizing,
) -> Vec<f64> {
    let mut kappa = vec![0.0f64; mesh.positions.len()];
    for [u, v] in crate::mesh::stats::unique_edges(mesh) {
        let (u, v) = (u as usize, v as usize);
        let len = (mesh.positions[u] - mesh.positions[v]).norm();
        if len > 0.0 {
            let k = (normals[u] - normals[v]).norm() / len;
            kappa[u] = kappa[u].max(k);
            kappa[v] = kappa[v].max(k);
        }
    }
    let e = a.max_error_mm;
    kappa
        .into_iter()
        .map(|k| {
            // Beyond ε = 1/κ (the error as large as the radius) any edge keeps the error.
            let h = if k * e < 1.0 {
                (6.0 * e / k - 3.0 * e * e).sqrt()
            } else {
                h_max
            };
            h.clamp(a.min_edge_mm, h_max)
        })
        .collect()
}

/// Barycentric coordinates of `q` (on or near the triangle) in `t`, clamped to the triangle.
fn barycentric(q: &Point3<f64>, t: &[Point3<f64>; 3]) -> [f64; 3] {
    let (v0, v1, v2) = (t[1] - t[0], t[2] - t[0], q - t[0]);
    let (d00, d01, d11) = (v0.dot(&v0), v0.dot(&v1), v1.dot(&v1));
    let (d20, d21) = (v2.dot(&v0), v2.dot(&v1));
    let den = d00 * d11 - d01 * d01;
    if den.is_nan() || den <= 0.0 {
        return [1.0 / 3.0; 3];
    }
    let v = ((d11 * d20 - d01 * d21) / den).clamp(0.0, 1.0);
    let w = ((d00 * d21 - d01 * d20) / den).clamp(0.0, 1.0 - v);
    [1.0 - v - w, v, w]
}

/// The mesh being remeshed, with per-vertex normals, target edge lengths and feature counts, and
/// per-edge feature flags.
struct Remesher<'r, 'a> {
    mesh: HalfEdgeMesh,
    normal: Vec<Vector3<f64>>,
    target: Vec<f64>,
    /// Feature edges at each vertex: 0 free, 2 on a feature line, anything else a fixed corner.
    crease: Vec<u8>,
    /// Per edge slot: is it a feature edge?
    feature: Vec<bool>,
    reference: &'r Reference<'a>,
    stamp: Vec<u32>,
}

impl<'r, 'a> Remesher<'r, 'a> {
    fn new(input: &TriMesh, reference: &'r Reference<'a>, feature_angle_deg: Option<f64>) -> Self {
        let mesh = HalfEdgeMesh::from_trimesh(input);
        let feature = match feature_angle_deg {
            None => vec![false; mesh.edge_slots()],
            Some(deg) => {
                let cos_max = deg.to_radians().cos();
                (0..mesh.edge_slots() as u32)
                    .map(|e| {
                        let n0 = face_direction(&mesh, mesh.face(2 * e));
                        let n1 = face_direction(&mesh, mesh.face(2 * e + 1));
                        matches!((n0, n1), (Some(a), Some(b)) if a.dot(&b) < cos_max)
                    })
                    .collect()
            }
        };
        let mut r = Self {
            normal: reference.normals.clone(),
            target: reference.sizing.clone(),
            crease: Vec::new(),
            feature,
            mesh,
            reference,
            stamp: Vec::new(),
        };
        r.count_creases();
        r
    }

    /// Recomputes the per-vertex feature-edge counts from the edge flags.
    fn count_creases(&mut self) {
        self.crease = vec![0; self.mesh.vertex_slots()];
        for e in 0..self.mesh.edge_slots() as u32 {
            if self.feature[e as usize] && !self.mesh.edge_removed(e) {
                for v in self.mesh.edge_vertices(e) {
                    self.crease[v as usize] = self.crease[v as usize].saturating_add(1);
                }
            }
        }
    }

    /// Corners (vertices where other than two feature edges meet) never move.
    fn is_corner(&self, v: u32) -> bool {
        !matches!(self.crease[v as usize], 0 | 2)
    }

    /// Target length of the edge between `a` and `b`, mm.
    fn edge_target(&self, a: u32, b: u32) -> f64 {
        0.5 * (self.target[a as usize] + self.target[b as usize])
    }

    /// Up to 10 passes, each over the edges that exist at its start (as pmp-library does): on
    /// nearly collinear input triangles, splitting can create cross edges as long as the split
    /// one, so an open-ended loop might never finish.
    fn split_long_edges(&mut self) {
        for _pass in 0..10 {
            let mut split_any = false;
            for e in 0..self.mesh.edge_slots() as u32 {
                if !self.mesh.edge_removed(e) {
                    let [a, b] = self.mesh.edge_vertices(e);
                    if self.mesh.edge_length(e) > 4.0 / 3.0 * self.edge_target(a, b) {
                        let (pa, pb) = (self.mesh.pos[a as usize], self.mesh.pos[b as usize]);
                        let (_, half) = self
                            .mesh
                            .split(e, Point3::from((pa.coords + pb.coords) / 2.0));
                        // Three new edges: the second half of e, then two across.
                        let on_feature = self.feature[e as usize];
                        self.feature.resize(self.mesh.edge_slots(), false);
                        self.feature[half as usize] = on_feature;
                        self.crease.push(if on_feature { 2 } else { 0 });
                        let n = self.normal[a as usize] + self.normal[b as usize];
                        self.normal
                            .push(n.try_normalize(0.0).unwrap_or(self.normal[a as usize]));
                        self.target.push(self.edge_target(a, b));
                        split_any = true;
                    }
                }
            }
            if !split_any {
                break;
            }
        }
    }

    fn collapse_short_edges(&mut self) {
        for e in 0..self.mesh.edge_slots() as u32 {
            if self.mesh.edge_removed(e) {
                continue;
            }
            let [v0, v1] = self.mesh.edge_vertices(e);
            if self.mesh.edge_length(e) >= 4.0 / 5.0 * self.edge_target(v0, v1) {
                continue;
            }
            let (h01, h10) = (2 * e, 2 * e + 1);
            let ok01 = self.collapse_ok(h01);
            let ok10 = self.collapse_ok(h10);
            // Both possible: remove the vertex of lower valence (as pmp-library does).
            let h = match (ok01, ok10) {
                (true, true) => {
                    if self.mesh.valence(v0) < self.mesh.valence(v1) {
                        h01
                    } else {
                        h10
                    }
                }
                (true, false) => h01,
                (false, true) => h10,
                (false, false) => continue,
            };
            for (removed, kept) in self.mesh.collapse(h) {
                self.feature[kept as usize] |= self.feature[removed as usize];
            }
        }
        self.count_creases();
    }

    /// Features, topology (link condition) and geometry: moving `from(h)` onto `to(h)` must keep
    /// feature lines, create no edge longer than 4/3 of its target and turn no remaining triangle
    /// over.
    fn collapse_ok(&mut self, h: u32) -> bool {
        let m = &self.mesh;
        let (v0, v1) = (m.from(h), m.to(h));
        // A vertex on a feature line may only slide along it; corners stay.
        match self.crease[v0 as usize] {
            0 => {}
            2 if self.feature[(h / 2) as usize] => {}
            _ => return false,
        }
        let p1 = m.pos[v1 as usize];
        let (f0, f1) = (m.face(h), m.face(h ^ 1));
        let mut ok = true;
        m.for_each_outgoing(v0, |g| {
            if !ok {
                return;
            }
            let w = m.to(g);
            if w != v1 && (m.pos[w as usize] - p1).norm() > 4.0 / 3.0 * self.edge_target(v1, w) {
                ok = false;
                return;
            }
            let f = m.face(g);
            if f == f0 || f == f1 {
                return;
            }
            // Face (v0, w, x) with v0 moved to p1.
            let x = m.to(m.next(g));
            let (pw, px) = (m.pos[w as usize], m.pos[x as usize]);
            let old = m.face_cross(f);
            let new = (pw - p1).cross(&(px - p1));
            if old.norm_squared() > 0.0 && (new.dot(&old) <= 0.0 || new.norm_squared() == 0.0) {
                ok = false;
            }
        });
        ok && self.mesh.is_collapse_ok(h, &mut self.stamp)
    }

    fn flip_edges(&mut self) {
        let mut valence: Vec<i32> = (0..self.mesh.vertex_slots() as u32)
            .map(|v| {
                if self.mesh.vertex_removed(v) {
                    0
                } else {
                    self.mesh.valence(v) as i32
                }
            })
            .collect();
        let dev = |v: i32| (v - 6) * (v - 6);
        for e in 0..self.mesh.edge_slots() as u32 {
            if self.mesh.edge_removed(e) {
                continue;
            }
            let m = &self.mesh;
            let (h0, h1) = (2 * e, 2 * e + 1);
            let [a, b, c, d] =
                [m.from(h0), m.to(h0), m.to(m.next(h0)), m.to(m.next(h1))].map(|v| v as usize);
            let before = dev(valence[a]) + dev(valence[b]) + dev(valence[c]) + dev(valence[d]);
            let after = dev(valence[a] - 1)
                + dev(valence[b] - 1)
                + dev(valence[c] + 1)
                + dev(valence[d] + 1);
            if after < before
                && !self.feature[e as usize]
                && self.flip_geometry_ok(e)
                && self.mesh.is_flip_ok(e)
            {
                self.mesh.flip(e);
                valence[a] -= 1;
                valence[b] -= 1;
                valence[c] += 1;
                valence[d] += 1;
            }
        }
    }

    /// Final clean-up: flip the edges of badly shaped triangles (smallest angle below 30°) where
    /// that raises the smallest angle of the pair and the pair is nearly flat (dihedral below
    /// 30°), so the surface does not change shape. Vertices do not move.
    fn improve_angles(&mut self) {
        // Compared through the cosine of the smallest angle (larger cosine: worse triangle).
        let worst_cos = |p: [Point3<f64>; 3]| -> f64 {
            (0..3)
                .map(|k| {
                    let (u, v) = (p[(k + 1) % 3] - p[k], p[(k + 2) % 3] - p[k]);
                    u.dot(&v) / (u.norm() * v.norm())
                })
                .fold(f64::NEG_INFINITY, f64::max)
        };
        let cos30 = 30f64.to_radians().cos();
        let is_bad = |p: [Point3<f64>; 3]| {
            let c = worst_cos(p);
            c.is_nan() || c >= cos30
        };
        for _sweep in 0..2 {
            let m = &self.mesh;
            let mut bad_face: Vec<bool> = (0..m.face_slots() as u32)
                .into_par_iter()
                .map(|f| {
                    !m.face_removed(f) && is_bad(m.face_vertices(f).map(|v| m.pos[v as usize]))
                })
                .collect();
            for e in 0..self.mesh.edge_slots() as u32 {
                let m = &self.mesh;
                let (h0, h1) = (2 * e, 2 * e + 1);
                let (f0, f1) = (m.face(h0), m.face(h1));
                if m.edge_removed(e)
                    || self.feature[e as usize]
                    || !(bad_face[f0 as usize] || bad_face[f1 as usize])
                {
                    continue;
                }
                let [a, b, c, d] = [m.from(h0), m.to(h0), m.to(m.next(h0)), m.to(m.next(h1))]
                    .map(|v| m.pos[v as usize]);
                let before = worst_cos([a, b, c]).max(worst_cos([b, a, d]));
                let after = worst_cos([d, c, a]).max(worst_cos([c, d, b]));
                // A face of (nearly) no area has no direction to keep: a cap whose corner lies
                // on its long edge is removed by flipping that edge.
                let dihedral_ok = match (face_direction(m, f0), face_direction(m, f1)) {
                    (Some(x), Some(y)) => x.dot(&y) > cos30,
                    _ => true,
                };
                if dihedral_ok
                    && after < before
                    && self.flip_geometry_ok(e)
                    && self.mesh.is_flip_ok(e)
                {
                    self.mesh.flip(e);
                    bad_face[f0 as usize] = is_bad([d, c, a]);
                    bad_face[f1 as usize] = is_bad([c, d, b]);
                }
            }
        }
    }

    /// Both triangles after flipping edge `e` face the same way as the pair before.
    fn flip_geometry_ok(&self, e: u32) -> bool {
        let m = &self.mesh;
        let (h0, h1) = (2 * e, 2 * e + 1);
        let [a, b, c, d] =
            [m.from(h0), m.to(h0), m.to(m.next(h0)), m.to(m.next(h1))].map(|v| m.pos[v as usize]);
        let old = m.face_cross(m.face(h0)) + m.face_cross(m.face(h1));
        let n1 = (c - d).cross(&(a - d));
        let n2 = (d - c).cross(&(b - c));
        n1.dot(&old) > 0.0 && n2.dot(&old) > 0.0
    }

    /// One pass of tangential relaxation towards the area-weighted centroid of the incident
    /// triangles' centroids.
    fn relax(&mut self) {
        let m = &self.mesh;
        let normal = &self.normal;
        let moved: Vec<Point3<f64>> = (0..m.vertex_slots() as u32)
            .into_par_iter()
            .map(|v| {
                let p = m.pos[v as usize];
                if m.vertex_removed(v) || self.is_corner(v) {
                    return p;
                }
                if self.crease[v as usize] == 2 {
                    return self.slide_along_feature(v);
                }
                let (mut sum, mut weight) = (Vector3::zeros(), 0.0);
                m.for_each_outgoing(v, |h| {
                    let f = m.face(h);
                    let [a, b, c] = m.face_vertices(f).map(|x| m.pos[x as usize].coords);
                    let area = m.face_cross(f).norm();
                    sum += (a + b + c) * (area / 3.0);
                    weight += area;
                });
                if weight.is_nan() || weight <= 0.0 {
                    return p;
                }
                let n = normal[v as usize];
                let u = sum / weight - p.coords;
                p + (u - n * n.dot(&u))
            })
            .collect();
        self.mesh.pos = moved;
    }

    /// A vertex on a feature line moves along the line towards the midpoint of its two feature
    /// neighbours.
    fn slide_along_feature(&self, v: u32) -> Point3<f64> {
        let m = &self.mesh;
        let mut ends = Vec::with_capacity(2);
        m.for_each_outgoing(v, |h| {
            if self.feature[(h / 2) as usize] {
                ends.push(m.pos[m.to(h) as usize]);
            }
        });
        let p = m.pos[v as usize];
        let (a, b) = (ends[0], ends[1]);
        match (b - a).try_normalize(0.0) {
            Some(d) => p + d * d.dot(&(Point3::from((a.coords + b.coords) / 2.0) - p)),
            None => p,
        }
    }

    /// Moves every vertex but the corners to its closest point on the input; takes the input's
    /// interpolated normal and target length there.
    fn project(&mut self) -> Result<(), TraceError> {
        let closest = self
            .reference
            .scene
            .closest_points_near(&self.mesh.pos, 2.0 * self.reference.max_target)?;
        for (v, c) in closest.iter().enumerate() {
            if self.mesh.vertex_removed(v as u32) || self.is_corner(v as u32) || c.prim == u32::MAX
            {
                continue;
            }
            self.mesh.pos[v] = c.point;
            let n: Vector3<f64> =
                self.reference
                    .interpolate(&self.reference.normals, c.prim, &c.point);
            if let Some(n) = n.try_normalize(0.0) {
                self.normal[v] = n;
            }
            self.target[v] = self
                .reference
                .interpolate(&self.reference.sizing, c.prim, &c.point);
        }
        Ok(())
    }

    /// Drops removed elements (vertex ids change; per-vertex data follow).
    fn compact(&mut self) {
        let map = self.mesh.garbage_collect();
        self.normal = map.vertex_data(&self.normal);
        self.target = map.vertex_data(&self.target);
        self.crease = map.vertex_data(&self.crease);
        self.feature = map.edge_data(&self.feature);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed mesh of 6 faces: a cap ABE — a triangle whose corner E lies (to rounding,
    /// 1e-15 mm off) on its long edge AB, as projecting onto a flat face can leave one —, ABE's
    /// two neighbours in its plane towards C, and a tent to the apex T (vertices 0–4: A, B, C,
    /// E, T).
    fn capped_tent() -> TriMesh {
        let p = |x, y, z| Point3::new(x, y, z);
        let [a, b, c, e, t] = [0, 1, 2, 3, 4];
        TriMesh::new(
            vec![
                p(0.0, 0.0, 0.0),
                p(2.0, 0.0, 0.0),
                p(1.0, -1.0, 0.0),
                p(1.0, 1e-15, 0.0),
                p(1.0, 0.5, 1.0),
            ],
            vec![
                [a, b, e],
                [a, e, c],
                [e, b, c],
                [b, a, t],
                [a, c, t],
                [c, b, t],
            ],
        )
    }

    /// The cap of [`capped_tent`] has no direction, so the edges it shares with its flat
    /// neighbours (AE, EB; their normals 180° from the cap's cross product's) are no feature
    /// lines, while the tent's edges to the flat base (AC, CB) are.
    #[test]
    fn a_cap_of_no_area_makes_no_feature_line() {
        let mesh = capped_tent();
        let device = Device::new().unwrap();
        let reference = Reference::new(&device, &mesh, &RemeshOptions::uniform(1.0)).unwrap();
        let r = Remesher::new(&mesh, &reference, Some(45.0));
        let feature = |u: u32, v: u32| {
            (0..r.mesh.edge_slots() as u32)
                .find(|&e| {
                    let [x, y] = r.mesh.edge_vertices(e);
                    (x, y) == (u, v) || (x, y) == (v, u)
                })
                .map(|e| r.feature[e as usize])
                .unwrap()
        };
        let [a, b, c, e] = [0, 1, 2, 3];
        assert!(!feature(a, e) && !feature(e, b));
        assert!(feature(a, c) && feature(c, b));
    }

    /// A cap — a triangle whose corner E lies (to rounding, 1e-15 mm off) on its long edge AB,
    /// as projecting onto a flat face can leave one — is flipped away by the last flips, although
    /// its normal, from a cross product of no size, points anywhere (here 117° from its
    /// neighbour's across AB, beyond the flips' 30° dihedral limit; [`capped_tent`]).
    #[test]
    fn a_cap_of_no_area_is_flipped_away() {
        let mesh = capped_tent();
        let degenerate = |m: &TriMesh| {
            validate(m)
                .defects
                .iter()
                .any(|d| matches!(d, Defect::Degenerate { .. }))
        };
        assert!(degenerate(&mesh), "the input holds the cap");
        let device = Device::new().unwrap();
        let reference = Reference::new(&device, &mesh, &RemeshOptions::uniform(1.0)).unwrap();
        let mut r = Remesher::new(&mesh, &reference, None);
        r.improve_angles();
        let out = r.mesh.to_trimesh();
        assert!(!degenerate(&out), "{:?}", validate(&out).defects);
    }
}
