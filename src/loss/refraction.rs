//! The refraction term (docs/architecture.md §4): for each object pixel with a decoded monitor point Q, the
//! modelled path through the current mesh should reach Q. A pixel is modelled by its centre ray
//! or by the mean residual of a grid of rays over its area (its footprint).
//!
//! Per view and chunk of pixels, the rays are traced one interface at a time ([`trace_forward`]):
//! Embree finds the triangle each ray meets, and the hit and the refraction there are computed
//! once, in f64, on that triangle (ray–plane hit, normal, Snell); the same values start the next
//! ray and serve the gradient. Then, per pixel, the path is differentiated backwards by hand
//! ([`super::diff`]), into per-chunk gradient entries that are summed in chunk order. Pixels whose
//! modelled path cannot be compared (no hit, TIR, wrong number of refractions, missing the
//! monitor, a derivative that is unbounded or not finite) are dropped and counted by reason.

use std::sync::Mutex;

use arrayvec::ArrayVec;
use nalgebra::{Point3, Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::bits::{self, PixelBits};
use super::diff::{
    barycentric, barycentric_adjoint, normalize_adjoint, plane_hit_adjoint, plane_hit_on, snell,
    snell_adjoint, snell_eta_adjoint, PlaneHit, Snell, SnellFailure,
};
use super::{Accumulator, Contributions, Drops, Robust};
use crate::mesh::TriMesh;
use crate::trace::path::{restart_origin, NormalModel, Surface, MAX_TRAIL, TRACE_CHUNK};
use crate::trace::{Ray, TraceError};
use crate::util::prefetch::prefetch;

type V3 = Vector3<f64>;

/// What the refraction residual compares.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum ResidualForm {
    /// The paper's ‖Q − Q′‖² with Q′ where the exit ray meets the monitor plane (mm²).
    Screen,
    /// DRT's code: ‖d_out − normalize(Q − p_out)‖² with the exit point p_out held fixed
    /// (unitless).
    Direction,
}

/// Settings of the refraction term.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RefractionSettings {
    /// Refractive index of the object and of the air.
    pub ior: f64,
    pub ior_air: f64,
    /// Paths with 2, 4, … up to this many refractions are used (2: DRT's exactly-two rule).
    pub max_refractions: u32,
    pub normals: NormalModel,
    pub form: ResidualForm,
    pub robust: Robust,
    /// Rays meeting an interface with cos θi or cos θt below this are dropped (their gradients
    /// grow as 1/cos: near grazing and near the critical angle one ray would outweigh
    /// thousands; and through a blurred camera their decoded points lie outward of the centre
    /// ray's); 0 keeps every ray with a usable derivative.
    #[serde(default)]
    pub min_cos: f64,
    /// Pixels whose decoded cell is at most this many direct footprints wide, or one monitor
    /// pixel ([`PixelTarget::cell_px`], [`PixelTarget::direct_px`]), keep their rays below
    /// `min_cos`: the glass then magnified the pixel's footprint little, as a flat face seen
    /// edge-on does, whose rays are
    /// often all that holds it (they still pull outward, less than a curved rim's). 0:
    /// `min_cos` applies to every pixel.
    #[serde(default)]
    pub grazing_cell_footprints: f64,
    /// Rays per pixel side, 1..=[`MAX_FOOTPRINT`]: each pixel is modelled by the mean of an n×n
    /// grid of rays over its area (1: the centre ray).
    pub footprint: u32,
    /// Weight of the per-bit term ([`bits`]: the measured contrasts of the Gray bits around a
    /// pixel's decoded cell against the share of its modelled footprint each pattern lights),
    /// per pixel relative to the residual's robust penalty; 0: off.
    #[serde(default)]
    pub bit_weight: f64,
    /// Whether the derivative with respect to the object's index is computed (to step a free
    /// index, or to find the index the held-out views fit best); otherwise
    /// [`PixelGradient::ior`] and the sums' stay 0.
    #[serde(default)]
    pub index_gradient: bool,
}

/// The most rays per pixel side of a footprint.
pub const MAX_FOOTPRINT: u32 = 4;
/// The most rays of a pixel's footprint.
const MAX_FOOTPRINT_RAYS: usize = (MAX_FOOTPRINT * MAX_FOOTPRINT) as usize;

/// Offsets (px) of an n×n footprint's rays from the pixel centre: the centres of an n×n grid
/// over the pixel.
pub fn footprint_offsets(n: u32) -> Vec<(f64, f64)> {
    let at = |i: u32| (i as f64 + 0.5) / n as f64 - 0.5;
    (0..n * n).map(|k| (at(k % n), at(k / n))).collect()
}

/// How a view's camera turns a pixel offset into a ray, world frame: `right` and `down` are the
/// camera's x and y axes divided by fx and fy (one pixel's step at unit depth, mm per mm),
/// `forward` its optical axis. Lens distortion is taken as constant across a pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelAxes {
    pub right: V3,
    pub down: V3,
    pub forward: V3,
}

impl PixelAxes {
    /// The unit direction of the ray `offset` (px) from the one along unit `dir`.
    pub fn offset(&self, dir: &V3, (dx, dy): (f64, f64)) -> V3 {
        (dir / dir.dot(&self.forward) + self.right * dx + self.down * dy).normalize()
    }
}

/// One object pixel of a view: its camera ray (world frame, unit direction), the decoded monitor
/// point Q (world frame, mm), its weight, its measured Gray bits (none for imported rays) and
/// the wider side of its decoded cell and the width of the pixel's footprint on the monitor seen
/// without the object (its direct footprint, at the decoded point's distance), both monitor
/// pixels (the cell infinite where unknown, as for imported rays). Their ratio is how much the
/// glass magnified the footprint, whatever the camera's resolution. `index_evidence`: whether
/// its derivative with respect to the refractive index counts (not where the camera's blur
/// skews what it decodes, [`crate::loss::blur`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelTarget {
    pub dir: V3,
    pub target: Point3<f64>,
    pub weight: f64,
    pub bits: PixelBits,
    pub cell_px: f32,
    pub direct_px: f32,
    pub index_evidence: bool,
}

impl PixelTarget {
    /// The cos θ below which this pixel's rays are dropped (`min_cos`, or 0 for a pixel whose
    /// decoded cell is fine enough: [`RefractionSettings::grazing_cell_footprints`]; a fully
    /// decoded cell, one monitor pixel, always is).
    fn min_cos(&self, s: &RefractionSettings) -> f64 {
        let fine = (s.grazing_cell_footprints * self.direct_px as f64).max(1.0);
        if s.grazing_cell_footprints > 0.0 && (self.cell_px as f64) <= fine {
            0.0
        } else {
            s.min_cos
        }
    }
}

/// The refraction data of one view, world frame.
#[derive(Clone, Debug)]
pub struct ViewTargets {
    pub view: usize,
    /// Camera centre, mm.
    pub eye: Point3<f64>,
    /// A point of the monitor plane and its unit normal.
    pub monitor_point: Point3<f64>,
    pub monitor_normal: V3,
    /// One monitor pixel's step along its columns (u) and rows (v), world frame, mm (the per-bit
    /// term's monitor coordinates: u = (X − `monitor_point`)·u_axis/|u_axis|²); `None`: no
    /// per-bit term.
    pub monitor_axes: Option<[V3; 2]>,
    /// The camera's pixel axes (footprint rays); `None` models pixels by their centre rays.
    pub pixel_axes: Option<PixelAxes>,
    pub pixels: Vec<PixelTarget>,
}

impl ViewTargets {
    /// The width of one camera pixel (mm) at the depth of `p` (world frame, mm) along the
    /// optical axis: the depth over the focal length, the mean of the two pixel axes; `None`
    /// without pixel axes or with `p` not in front of the camera.
    pub fn pixel_mm_at(&self, p: &Point3<f64>) -> Option<f64> {
        let a = self.pixel_axes?;
        let depth = (p - self.eye).dot(&a.forward);
        (depth > 0.0).then(|| depth * 0.5 * (a.right.norm() + a.down.norm()))
    }

    /// Whether any pixel carries measured Gray bits (decoded from captures by a glasscan that
    /// stores the contrasts; exact correspondences and imported rays carry none).
    pub fn has_measured_bits(&self) -> bool {
        self.pixels.iter().any(|p| p.bits.any())
    }

    /// The same view without pixels.
    pub fn clone_empty(&self) -> Self {
        Self {
            view: self.view,
            eye: self.eye,
            monitor_point: self.monitor_point,
            monitor_normal: self.monitor_normal,
            monitor_axes: self.monitor_axes,
            pixel_axes: self.pixel_axes,
            pixels: Vec::new(),
        }
    }
}

/// One interface of a path, computed in f64, with what its derivative needs (the triangle's
/// corners and vertex normals are read again from the mesh).
#[derive(Clone, Debug)]
struct Interface {
    verts: [u32; 3],
    dir_in: V3,
    hit: PlaneHit,
    /// |hit.n|: the triangle's geometric normal is hit.n / n_len.
    n_len: f64,
    entering: bool,
    /// Vertex-normal model: barycentrics and the interpolated (unnormalised) normal's length.
    bary: (f64, f64),
    interp_norm: f64,
    /// Unit normal facing the incident side.
    n: V3,
    /// Snell's law here: `out` is the outgoing ray's unit direction (unit by construction, for
    /// a unit incoming direction and normal: |out|² = η² sin²θi + cos²θt = 1; not normalised
    /// again, so neither is its adjoint taken).
    snell: Snell,
}

/// Why a pixel was dropped from the refraction term.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DropReason {
    NoHit,
    TotalInternalReflection,
    /// A path with a refraction count the settings exclude (odd, or above `max_refractions`).
    RefractionCount,
    MissedMonitor,
    /// Ray parallel to a triangle, or a shading normal facing away.
    Grazing,
    /// Within reach of the critical angle: the derivative is unbounded.
    NearCritical,
    NonFinite,
}

/// Loss of one pixel and its gradient, recorded into `grad` (vertex, ∂L/∂position) and
/// `ngrad` (vertex, ∂L/∂unit vertex normal), an entry per triangle vertex a ray met, and `ior`
/// (∂L/∂ the object's refractive index).
#[derive(Clone, Debug, Default)]
pub struct PixelGradient {
    pub loss: f64,
    pub grad: Vec<(u32, V3)>,
    pub ngrad: Vec<(u32, V3)>,
    pub ior: f64,
    /// The interfaces of the footprint's paths, kept between pixels so that the hot loop
    /// neither allocates nor moves them.
    interfaces: Vec<Interface>,
}

/// Everything the per-pixel computation reads about the current mesh.
pub struct MeshState<'a> {
    pub positions: &'a [Point3<f64>],
    pub faces: &'a [[u32; 3]],
    /// Unit vertex normals (vertex-normal model only).
    pub vertex_normals: Option<&'a [V3]>,
    /// Per face, its plane, computed once for all the rays that meet it.
    planes: Vec<FacePlane>,
}

impl<'a> MeshState<'a> {
    /// The state of `mesh` (world frame, mm), with its unit `vertex_normals` for the
    /// vertex-normal model.
    pub fn new(mesh: &'a TriMesh, vertex_normals: Option<&'a [V3]>) -> Self {
        let planes = (0..mesh.faces.len())
            .into_par_iter()
            .map(|f| FacePlane::of(mesh, f))
            .collect();
        Self {
            positions: &mesh.positions,
            faces: &mesh.faces,
            vertex_normals,
            planes,
        }
    }

    /// Asks for what refracting at face `f` reads (its plane and corner indices) to be brought
    /// into the caches ([`prefetch`]).
    fn prefetch_face(&self, f: u32) {
        if let (Some(plane), Some(face)) = (self.planes.get(f as usize), self.faces.get(f as usize))
        {
            prefetch(plane);
            prefetch(face);
        }
    }
}

/// A triangle's plane in f64: its first corner (mm), its unnormalised normal (b − a) × (c − a),
/// that normal's length and the unit normal (outward for a mesh wound outward).
#[derive(Clone, Copy, Debug)]
struct FacePlane {
    a: Point3<f64>,
    n: V3,
    n_len: f64,
    unit: V3,
}

impl FacePlane {
    /// The plane of face `f` of `mesh`.
    fn of(mesh: &TriMesh, f: usize) -> Self {
        let n = mesh.face_cross(f);
        let n_len = n.norm();
        Self {
            a: mesh.corners(f)[0],
            n,
            n_len,
            unit: n / n_len,
        }
    }
}

/// Recomputes pixel `px`'s path along `prims` and returns its loss and gradient.
pub fn pixel_gradient(
    mesh: &MeshState,
    s: &RefractionSettings,
    view: &ViewTargets,
    px: &PixelTarget,
    prims: &[u32],
) -> Result<PixelGradient, DropReason> {
    let mut out = PixelGradient::default();
    footprint_gradient_into(mesh, s, view, px, &[(px.dir, Ok(prims))], &mut out).map(|()| out)
}

/// One ray of a pixel's footprint: its unit direction (world frame) and the triangles its
/// traced path refracted at, or why that path cannot be compared.
pub type FootprintRay<'a> = (V3, Result<&'a [u32], DropReason>);

/// The loss and gradient of pixel `px` from the rays of its footprint (into `out`, overwritten;
/// reused across pixels by the hot loop), each path recomputed along the triangles it refracted
/// at. The pixel's modelled residual is the mean of its rays' residuals (for the screen form:
/// the footprint's mean monitor point against the decoded point), over the rays whose paths can
/// be compared; the pixel is dropped, with the first ray's reason, when none can. One ray is the
/// centre-ray term.
pub fn footprint_gradient_into(
    mesh: &MeshState,
    s: &RefractionSettings,
    view: &ViewTargets,
    px: &PixelTarget,
    rays: &[FootprintRay],
    out: &mut PixelGradient,
) -> Result<(), DropReason> {
    let mut interfaces = std::mem::take(&mut out.interfaces);
    interfaces.clear();
    out.grad.clear();
    out.ngrad.clear();
    let min_cos = px.min_cos(s);
    let paths: ArrayVec<Result<Forward, DropReason>, MAX_FOOTPRINT_RAYS> = rays
        .iter()
        .take(MAX_FOOTPRINT_RAYS)
        .map(|(dir, prims)| {
            prims.and_then(|p| forward(mesh, s, min_cos, &view.eye, dir, p, &mut interfaces))
        })
        .collect();
    let r = pixel_from_paths(mesh, s, view, px, (&paths, &interfaces), out);
    out.interfaces = interfaces;
    r
}

/// The loss and gradient of pixel `px` from its footprint's `paths` forward, their interfaces in
/// `interfaces`, as [`footprint_gradient_into`] describes: `out.loss` and `out.ior` are
/// overwritten, the pixel's entries appended to `out.grad` and `out.ngrad` (which may hold the
/// pixels before it: the hot loop writes a chunk's entries where they are summed), and nothing
/// is appended when the pixel is dropped.
fn pixel_from_paths(
    mesh: &MeshState,
    s: &RefractionSettings,
    view: &ViewTargets,
    px: &PixelTarget,
    (paths, interfaces): (&[Result<Forward, DropReason>], &[Interface]),
    out: &mut PixelGradient,
) -> Result<(), DropReason> {
    let mut compared: ArrayVec<(&Forward, Exit), MAX_FOOTPRINT_RAYS> = ArrayVec::new();
    let mut first_drop = None;
    for path in paths.iter().take(MAX_FOOTPRINT_RAYS) {
        let exit = path
            .as_ref()
            .map_err(|r| *r)
            .and_then(|f| exit_residual(s, view, &px.target, &f.o, &f.d).map(|e| (f, e)));
        match exit {
            Ok(p) => compared.push(p),
            Err(r) => _ = first_drop.get_or_insert(r),
        }
    }
    if compared.is_empty() {
        return Err(first_drop.unwrap_or(DropReason::NoHit));
    }
    let m = compared.len() as f64;
    let mean = compared.iter().map(|(_, e)| e.r).sum::<V3>() / m;
    let (loss, dr2) = s.robust.apply(mean.norm_squared());
    let gr = mean * (2.0 * dr2 * px.weight / m);
    let side = if paths.len() > 1 { s.footprint } else { 1 };
    let mut bit_grads = ExitGradients::new();
    let bit_loss = bit_term(s, view, px, &compared, side, &mut bit_grads);
    let start = (out.grad.len(), out.ngrad.len());
    out.ior = 0.0;
    for (k, (f, e)) in compared.iter().enumerate() {
        let (mut gp, mut gd) = exit_adjoint(s, view, e, &f.d, &gr);
        if let Some(Some((bp, bd))) = bit_grads.get(k) {
            gp += bp;
            gd += bd;
        }
        for &i in f.chain.iter().rev() {
            let model = (mesh, s.index_gradient.then_some(s.ior));
            (gp, gd) = interface_adjoint(model, &interfaces[i as usize], &gp, &gd, out);
        }
    }
    let finite = (loss + bit_loss).is_finite()
        && out.ior.is_finite()
        && out.grad[start.0..]
            .iter()
            .chain(&out.ngrad[start.1..])
            .all(|(_, g)| g.iter().all(|x| x.is_finite()));
    if !finite {
        out.grad.truncate(start.0);
        out.ngrad.truncate(start.1);
        return Err(DropReason::NonFinite);
    }
    out.loss = (loss + bit_loss) * px.weight;
    Ok(())
}

/// Per footprint path, the gradient with respect to its exit ray's origin and direction.
type ExitGradients = ArrayVec<Option<(V3, V3)>, MAX_FOOTPRINT_RAYS>;

/// The per-bit term of pixel `px` from its footprint's `paths` (`side` rays per footprint side):
/// its loss times `bit_weight`, and into the empty `grads`, per path, the gradient (times the
/// pixel's weight) with respect to its exit ray (`None` for a path that misses the monitor
/// plane). Nothing when the term is off, the pixel has no measured bits or the view no monitor
/// axes. (`grads` is filled in place: the list is too large to move per pixel.)
fn bit_term(
    s: &RefractionSettings,
    view: &ViewTargets,
    px: &PixelTarget,
    paths: &[(&Forward, Exit)],
    side: u32,
    grads: &mut ExitGradients,
) -> f64 {
    let Some([au, av]) = view
        .monitor_axes
        .filter(|_| s.bit_weight > 0.0 && px.bits.any())
    else {
        return 0.0;
    };
    let (du, dv) = (au / au.norm_squared(), av / av.norm_squared());

    let mut hits: ArrayVec<(usize, f64, f64), MAX_FOOTPRINT_RAYS> = ArrayVec::new();
    let mut points: ArrayVec<Vector2<f64>, MAX_FOOTPRINT_RAYS> = ArrayVec::new();
    for (k, (f, _)) in paths.iter().enumerate() {
        if let Some((sdist, dn)) = screen_hit(view, &f.o, &f.d) {
            hits.push((k, sdist, dn));
            let x = f.o + f.d * sdist - view.monitor_point;
            points.push(Vector2::new(x.dot(&du), x.dot(&dv)));
        }
    }
    if !bits::within_cell(&px.bits, &points) {
        return 0.0;
    }
    let mut g = [Vector2::zeros(); MAX_FOOTPRINT_RAYS];
    let g = &mut g[..points.len()];
    let loss = bits::pixel_loss(&px.bits, &points, side, g);
    let scale = s.bit_weight * px.weight;
    grads.extend((0..paths.len()).map(|_| None));
    for (&(k, sdist, dn), gk) in hits.iter().zip(g.iter()) {
        let gq = (du * gk.x + dv * gk.y) * scale;
        grads[k] = Some(screen_adjoint(view, sdist, dn, &paths[k].0.d, &gq));
    }
    loss * s.bit_weight
}

/// Where the ray (o, d) meets the monitor plane: the distance along it (mm) and d·ν; `None` when
/// it runs parallel to the plane or away from it.
pub(super) fn screen_hit(view: &ViewTargets, o: &Point3<f64>, d: &V3) -> Option<(f64, f64)> {
    let dn = d.dot(&view.monitor_normal);
    let sdist = (view.monitor_point - o).dot(&view.monitor_normal) / dn;
    (sdist > 0.0 && sdist.is_finite()).then_some((sdist, dn))
}

/// From the gradient `gq` with respect to where the ray (o, d) meets the monitor plane,
/// Q′ = o + s·d with s = ((m − o)·ν)/(d·ν) (`sdist`, `dn` = d·ν), to the gradients with respect
/// to o and d.
fn screen_adjoint(view: &ViewTargets, sdist: f64, dn: f64, d: &V3, gq: &V3) -> (V3, V3) {
    let (mut gp, mut gd) = (*gq, gq * sdist);
    let gs = gq.dot(d);
    gp -= view.monitor_normal * (gs / dn);
    gd -= view.monitor_normal * (gs * sdist / dn);
    (gp, gd)
}

/// A ray's path recomputed forward: where its interfaces are in the footprint's (or the
/// chunk's) list, in order, and the exit ray (origin, unit direction).
struct Forward {
    chain: ArrayVec<u32, MAX_TRAIL>,
    o: Point3<f64>,
    d: V3,
}

/// The ray from `eye` along `dir` through the triangles `prims`, its interfaces appended to
/// `interfaces`; dropped where it meets one with cos θi or cos θt below `min_cos`.
fn forward(
    mesh: &MeshState,
    s: &RefractionSettings,
    min_cos: f64,
    eye: &Point3<f64>,
    dir: &V3,
    prims: &[u32],
    interfaces: &mut Vec<Interface>,
) -> Result<Forward, DropReason> {
    if prims.len() > MAX_TRAIL {
        return Err(DropReason::RefractionCount);
    }
    let mut f = Forward {
        chain: ArrayVec::new(),
        o: *eye,
        d: *dir,
    };
    for &prim in prims {
        let it = refract_at(mesh, s, min_cos, &f.o, &f.d, prim)?;
        f.pass(it, interfaces);
    }
    Ok(f)
}

impl Forward {
    /// Continues the path through interface `it`, appended to `interfaces`.
    fn pass(&mut self, it: Interface, interfaces: &mut Vec<Interface>) {
        (self.o, self.d) = (it.hit.point, it.snell.out);
        self.chain.push(interfaces.len() as u32);
        interfaces.push(it);
    }
}

/// Traces the rays from `eye` along unit `dirs` through `surface` (which holds `mesh`) one
/// interface at a time for them all (each interface one batch for Embree, the first in
/// packets): Embree finds the triangle, and the hit and the refraction there are computed in
/// f64 on it ([`refract_at`]), once, for the trace and for the gradient. Ray `i` is dropped
/// where it meets an interface with cos θi or cos θt below `min_cos(i)`, and where its path
/// leaves with a refraction count the settings exclude. The interfaces are appended to
/// `interfaces` and the paths, one per ray, written to `paths`.
fn trace_forward(
    surface: &dyn Surface,
    mesh: &MeshState,
    s: &RefractionSettings,
    (eye, dirs): (&Point3<f64>, &[V3]),
    min_cos: impl Fn(usize) -> f64,
    (b, paths, interfaces): (
        &mut TraceBuffers,
        &mut Vec<Result<Forward, DropReason>>,
        &mut Vec<Interface>,
    ),
) -> Result<(), TraceError> {
    let max = (s.max_refractions as usize).min(MAX_TRAIL);
    let offset = surface.offset();
    // Component by component: copied whole, each ray and path was assembled on the stack from
    // partial stores and read back, a stall per ray (`bench gradient`, CHANGELOG 0.28.1).
    let (ex, ey, ez) = (eye.x, eye.y, eye.z);
    paths.clear();
    paths.extend(dirs.iter().map(|d| {
        Ok(Forward {
            chain: ArrayVec::new(),
            o: Point3::new(ex, ey, ez),
            d: V3::new(d.x, d.y, d.z),
        })
    }));
    let TraceBuffers {
        active,
        batch,
        next_batch,
        prims,
    } = b;
    active.clear();
    active.extend(0..dirs.len());
    batch.clear();
    batch.extend(
        dirs.iter()
            .map(|d| Ray::new(Point3::new(ex, ey, ez), V3::new(d.x, d.y, d.z))),
    );
    prims.clear();
    prims.resize(batch.len(), None);
    let mut first = true;
    while !active.is_empty() {
        let prims = &mut prims[..batch.len()];
        surface.first_elements(batch, prims, first)?;
        first = false;
        next_batch.clear();
        let mut kept = 0;
        for (k, prim) in prims.iter().enumerate() {
            if let Some(&Some(ahead)) = prims.get(k + PREFETCH_AHEAD) {
                mesh.prefetch_face(ahead);
            }
            let i = active[k];
            let Ok(f) = &mut paths[i] else {
                unreachable!("only live paths are active")
            };
            let step = match *prim {
                None if f.chain.is_empty() => Err(DropReason::NoHit),
                None if f.chain.len() % 2 == 1 => Err(DropReason::RefractionCount),
                None => continue,
                Some(_) if f.chain.len() == max => Err(DropReason::RefractionCount),
                Some(p) => refract_at(mesh, s, min_cos(i), &f.o, &f.d, p),
            };
            match step {
                Err(r) => paths[i] = Err(r),
                Ok(it) => {
                    // The geometric normal; with face normals, `it.n` is it, up to its sign.
                    let normal = match mesh.vertex_normals {
                        None => it.n,
                        Some(_) => it.hit.n / it.n_len,
                    };
                    f.pass(it, interfaces);
                    next_batch.push(Ray::new(restart_origin(&f.o, &f.d, &normal, offset), f.d));
                    active[kept] = i;
                    kept += 1;
                }
            }
        }
        active.truncate(kept);
        std::mem::swap(batch, next_batch);
    }
    Ok(())
}

/// How many rays ahead of the one it refracts [`trace_forward`] asks for the hit triangle's
/// data ([`MeshState::prefetch_face`]): enough for it to arrive from memory meanwhile.
const PREFETCH_AHEAD: usize = 8;

/// The rays [`trace_forward`] sends to Embree at each interface, and which paths they continue.
#[derive(Default)]
struct TraceBuffers {
    active: Vec<usize>,
    batch: Vec<Ray>,
    next_batch: Vec<Ray>,
    prims: Vec<Option<u32>>,
}

/// Forward through one interface: the ray (o, d) meets triangle `prim`'s plane and refracts
/// (face or interpolated vertex normal); everything the backward pass needs, or why the ray is
/// dropped (cos θi or cos θt below `min_cos`).
// Inlined into the trace loop, so that the interface is built where it is stored rather than
// returned and copied (`bench gradient`, CHANGELOG 0.27.1).
#[inline(always)]
fn refract_at(
    mesh: &MeshState,
    s: &RefractionSettings,
    min_cos: f64,
    o: &Point3<f64>,
    d: &V3,
    prim: u32,
) -> Result<Interface, DropReason> {
    let verts = mesh.faces[prim as usize];
    let plane = &mesh.planes[prim as usize];
    let hit = plane_hit_on(o, d, &plane.a, &plane.n).ok_or(DropReason::Grazing)?;
    let entering = hit.den < 0.0;
    let (eta, sign) = if entering {
        (s.ior_air / s.ior, 1.0)
    } else {
        (s.ior / s.ior_air, -1.0)
    };
    let n_len = plane.n_len;
    let (mut bary, mut interp_norm) = ((0.0, 0.0), 0.0);
    let outward = match mesh.vertex_normals {
        None => plane.unit,
        Some(vn) => {
            let tri = verts.map(|v| mesh.positions[v as usize]);
            bary = barycentric(&hit.point, &tri, &hit.n);
            let vnormals = verts.map(|v| vn[v as usize]);
            let m =
                vnormals[0] * (1.0 - bary.0 - bary.1) + vnormals[1] * bary.0 + vnormals[2] * bary.1;
            interp_norm = m.norm();
            m / interp_norm
        }
    };
    let n = outward * sign;
    let sn = snell(d, &n, eta).map_err(|e| match e {
        SnellFailure::Grazing => DropReason::Grazing,
        SnellFailure::Total => DropReason::TotalInternalReflection,
        SnellFailure::Critical => DropReason::NearCritical,
    })?;
    if sn.cos_i < min_cos {
        return Err(DropReason::Grazing);
    }
    if sn.cos_t < min_cos {
        return Err(DropReason::NearCritical);
    }
    Ok(Interface {
        verts,
        dir_in: *d,
        hit,
        n_len,
        entering,
        bary,
        interp_norm,
        n,
        snell: sn,
    })
}

/// The residual of an exit ray against a decoded point, and what its adjoint needs.
struct Exit {
    /// Screen form: Q′ − Q (mm, world frame); direction form: d − normalize(Q − o).
    r: V3,
    /// Screen form: distance along the exit ray to the monitor (mm) and d·ν.
    sdist: f64,
    dn: f64,
}

/// The residual of the exit ray (o, d) against `target` (world frame, mm).
fn exit_residual(
    s: &RefractionSettings,
    view: &ViewTargets,
    target: &Point3<f64>,
    o: &Point3<f64>,
    d: &V3,
) -> Result<Exit, DropReason> {
    match s.form {
        ResidualForm::Screen => {
            let (sdist, dn) = screen_hit(view, o, d).ok_or(DropReason::MissedMonitor)?;
            let r = o + d * sdist - target;
            Ok(Exit { r, sdist, dn })
        }
        ResidualForm::Direction => Ok(Exit {
            r: d - (target - o).normalize(),
            sdist: 0.0,
            dn: 0.0,
        }),
    }
}

/// From the gradient `gr` with respect to an exit residual to the gradients with respect to the
/// exit ray's origin and direction `d`.
fn exit_adjoint(s: &RefractionSettings, view: &ViewTargets, e: &Exit, d: &V3, gr: &V3) -> (V3, V3) {
    match s.form {
        ResidualForm::Screen => screen_adjoint(view, e.sdist, e.dn, d, gr),
        // The exit point is held fixed (DRT's code).
        ResidualForm::Direction => (V3::zeros(), *gr),
    }
}

/// Backward through one interface: from the gradients with respect to the outgoing ray (its
/// origin `gp`, the hit point, and its direction `gd`) to the triangle's vertices (and, with
/// vertex normals, the normals), added to `out` (and, given the object's `index`, to the
/// derivative with respect to it); returns the gradients with respect to the incoming ray's
/// origin and direction.
fn interface_adjoint(
    (mesh, index): (&MeshState, Option<f64>),
    it: &Interface,
    gp: &V3,
    gd: &V3,
    out: &mut PixelGradient,
) -> (V3, V3) {
    let (mut gdin, mut gn) = (V3::zeros(), V3::zeros());
    snell_adjoint(&it.snell, &it.dir_in, &it.n, gd, &mut gdin, &mut gn);
    if let Some(ior) = index {
        // ∂η/∂(object's index): η = n_air / n entering, n / n_air leaving.
        let deta_dior = if it.entering { -1.0 } else { 1.0 } * it.snell.eta / ior;
        out.ior += snell_eta_adjoint(&it.snell, &it.dir_in, &it.n, gd) * deta_dior;
    }
    // The unit normal, outward: the face's or the interpolated one.
    let (outward, g_outward) = if it.entering {
        (it.n, gn)
    } else {
        (-it.n, -gn)
    };
    let tri = it.verts.map(|v| mesh.positions[v as usize]);
    let mut gtri = [V3::zeros(); 3];
    let mut gnormal = V3::zeros();
    let mut gpoint = *gp;
    match mesh.vertex_normals {
        None => {
            gnormal += normalize_adjoint(&outward, it.n_len, &g_outward);
        }
        Some(vn) => {
            let (w1, w2) = it.bary;
            let w = [1.0 - w1 - w2, w1, w2];
            let gm = normalize_adjoint(&outward, it.interp_norm, &g_outward);
            out.ngrad
                .extend(it.verts.iter().zip(w).map(|(&v, wk)| (v, gm * wk)));
            let gw = it.verts.map(|v| gm.dot(&vn[v as usize]));
            barycentric_adjoint(
                &it.hit.point,
                &tri,
                &it.hit.n,
                (w1, w2),
                (gw[1] - gw[0], gw[2] - gw[0]),
                &mut gpoint,
                &mut gtri,
                &mut gnormal,
            );
        }
    }
    let mut go = V3::zeros();
    plane_hit_adjoint(
        &it.hit, &it.dir_in, &tri, &gpoint, &gnormal, &mut go, &mut gdin, &mut gtri,
    );
    // Component by component: copying each vector whole, the compiler assembled it on the
    // stack from partial stores and read it back, a stall behind every pending store
    // (`bench gradient`, CHANGELOG 0.27.2).
    for (&v, g) in it.verts.iter().zip(&gtri) {
        out.grad.push((v, V3::new(g.x, g.y, g.z)));
    }
    (go, gdin)
}

/// Traces one view through `surface` (holding `mesh`; with `vertex_normals` of `mesh` for the
/// vertex-normal model) and adds its refraction loss and gradient to `acc` (and, to a counting
/// one, each compared pixel's penalty at the vertices it touches: [`Contributions::penalties`]).
pub fn add_view(
    surface: &dyn Surface,
    mesh: &MeshState,
    s: &RefractionSettings,
    view: &ViewTargets,
    acc: &mut Accumulator,
) -> Result<(), TraceError> {
    let offsets = view_offsets(s, view);
    // Trace and differentiate chunk by chunk (about LOSS_CHUNK rays), each on one thread, so
    // the chunk's paths stay in cache between the two, and its entries until they are added.
    let counting = !acc.penalty.is_empty();
    let chunks: Vec<&[PixelTarget]> = view.pixels.chunks(pixels_per_chunk(&offsets)).collect();
    acc.add_in_order(chunks.len(), |k, spare| {
        ChunkBuffers::with(|buffers| {
            let pixels = (chunks[k], offsets.as_slice());
            chunk_contributions(surface, mesh, s, view, pixels, (counting, spare), buffers)
        })
    })
}

/// The forward pass of [`add_view`] alone: the view's rays traced through `surface` as the term
/// traces them (Embree's queries, and the hits and refractions in f64), nothing differentiated or
/// summed; how many rays' paths were traced to their end (none of the drops of the trace). For
/// `bench gradient`.
pub fn trace_view(
    surface: &dyn Surface,
    mesh: &MeshState,
    s: &RefractionSettings,
    view: &ViewTargets,
) -> Result<usize, TraceError> {
    let offsets = view_offsets(s, view);
    view.pixels
        .par_chunks(pixels_per_chunk(&offsets))
        .map(|chunk| {
            ChunkBuffers::with(|b| {
                trace_chunk_forward(surface, mesh, s, view, (chunk, &offsets), b)?;
                Ok(b.paths.iter().filter(|p| p.is_ok()).count())
            })
        })
        .sum()
}

/// The offsets (camera pixels) of the rays of a pixel's footprint in `view`: the pixel's centre
/// alone where the view has no pixel axes.
fn view_offsets(s: &RefractionSettings, view: &ViewTargets) -> Vec<(f64, f64)> {
    match view.pixel_axes {
        Some(_) => footprint_offsets(s.footprint.clamp(1, MAX_FOOTPRINT)),
        None => vec![(0.0, 0.0)],
    }
}

/// Pixels a chunk holds: about [`LOSS_CHUNK`] rays of footprints of `offsets`.
fn pixels_per_chunk(offsets: &[(f64, f64)]) -> usize {
    (LOSS_CHUNK / offsets.len()).max(1)
}

/// Rays a chunk of the term traces and then differentiates on one thread: half of
/// [`TRACE_CHUNK`], so that the chunk's paths, interfaces and gradient entries (about 0.8 MB
/// through the pig in `bench gradient`) stay in a core's L2 cache (1 MB on a current server
/// core) from the forward pass to the backward one.
const LOSS_CHUNK: usize = TRACE_CHUNK / 2;

/// What a thread reuses from chunk to chunk (and view to view, iteration to iteration), so
/// that tracing and differentiating a chunk neither allocates nor touches fresh memory.
#[derive(Default)]
struct ChunkBuffers {
    dirs: Vec<V3>,
    trace: TraceBuffers,
    paths: Vec<Result<Forward, DropReason>>,
    interfaces: Vec<Interface>,
}

thread_local! {
    static CHUNK_BUFFERS: std::cell::RefCell<ChunkBuffers> = Default::default();
}

impl ChunkBuffers {
    /// Runs `f` with this thread's buffers (fresh ones if they are in use further up this
    /// thread's stack).
    fn with<R>(f: impl FnOnce(&mut ChunkBuffers) -> R) -> R {
        CHUNK_BUFFERS.with(|b| match b.try_borrow_mut() {
            Ok(mut b) => f(&mut b),
            Err(_) => f(&mut ChunkBuffers::default()),
        })
    }
}

/// Traces and differentiates one chunk of a view's `pixels` (each by the rays at `offsets` from
/// its centre), on the calling thread: the chunk's loss, counts and gradient entries, and if
/// `counting`, each compared pixel's penalty at the vertices it touches; in lists taken from
/// `spare` where it has some.
fn chunk_contributions(
    surface: &dyn Surface,
    mesh: &MeshState,
    s: &RefractionSettings,
    view: &ViewTargets,
    (pixels, offsets): (&[PixelTarget], &[(f64, f64)]),
    (counting, spare): (bool, &Mutex<Vec<Contributions>>),
    b: &mut ChunkBuffers,
) -> Result<Contributions, TraceError> {
    let per_pixel = offsets.len();
    trace_chunk_forward(surface, mesh, s, view, (pixels, offsets), b)?;
    // Three vertices per refraction, each with a normal entry for vertex normals; the pixels
    // append theirs straight to the chunk's lists.
    let entries = 3 * s.max_refractions as usize * b.dirs.len();
    let normal_entries = if mesh.vertex_normals.is_some() {
        entries
    } else {
        0
    };
    let mut c = Contributions::reusing(spare, entries, normal_entries);
    let mut g = PixelGradient {
        grad: std::mem::take(&mut c.grad),
        ngrad: std::mem::take(&mut c.ngrad),
        ..PixelGradient::default()
    };
    for (px, part) in pixels.iter().zip(b.paths.chunks(per_pixel)) {
        let start = g.grad.len();
        match pixel_from_paths(mesh, s, view, px, (part, &b.interfaces), &mut g) {
            Ok(()) => {
                let ior = if px.index_evidence { g.ior } else { 0.0 };
                c.count_pixel(g.loss, px.weight, ior);
                if !counting {
                    continue;
                }
                let penalty = if px.weight > 0.0 {
                    g.loss / px.weight
                } else {
                    0.0
                };
                c.penalties
                    .extend(g.grad[start..].iter().map(|&(v, _)| (v, penalty)));
            }
            Err(r) => c.drops.count(r),
        }
    }
    (c.grad, c.ngrad) = (g.grad, g.ngrad);
    Ok(c)
}

/// Traces the footprint rays of one chunk of a view's `pixels` (each by the rays at `offsets`
/// from its centre) on the calling thread: their paths and interfaces into `b`.
fn trace_chunk_forward(
    surface: &dyn Surface,
    mesh: &MeshState,
    s: &RefractionSettings,
    view: &ViewTargets,
    (pixels, offsets): (&[PixelTarget], &[(f64, f64)]),
    b: &mut ChunkBuffers,
) -> Result<(), TraceError> {
    let per_pixel = offsets.len();
    footprint_dirs(view, pixels, offsets, &mut b.dirs);
    b.interfaces.clear();
    let min_cos = |i: usize| match per_pixel {
        1 => pixels[i].min_cos(s),
        n => pixels[i / n].min_cos(s),
    };
    let trace = (&mut b.trace, &mut b.paths, &mut b.interfaces);
    trace_forward(surface, mesh, s, (&view.eye, &b.dirs), min_cos, trace)
}

/// The directions of the footprint rays of `pixels`, pixel by pixel (the pixel's own ray for
/// the single offset (0, 0)), into `dirs`.
fn footprint_dirs(
    view: &ViewTargets,
    pixels: &[PixelTarget],
    offsets: &[(f64, f64)],
    dirs: &mut Vec<V3>,
) {
    dirs.clear();
    match view.pixel_axes {
        Some(axes) if offsets.len() > 1 => dirs.extend(
            pixels
                .iter()
                .flat_map(|p| offsets.iter().map(move |&o| axes.offset(&p.dir, o))),
        ),
        _ => dirs.extend(pixels.iter().map(|p| p.dir)),
    }
}

impl Drops {
    pub fn count(&mut self, r: DropReason) {
        match r {
            DropReason::NoHit => self.no_hit += 1,
            DropReason::TotalInternalReflection => self.total_internal_reflection += 1,
            DropReason::RefractionCount => self.refraction_count += 1,
            DropReason::MissedMonitor => self.missed_monitor += 1,
            DropReason::Grazing => self.grazing += 1,
            DropReason::NearCritical => self.near_critical += 1,
            DropReason::NonFinite => self.non_finite += 1,
        }
    }
}

/// A view from a camera on the +z axis `distance` mm from the origin, looking along −z, with
/// focal lengths `fx`, `fy` (px), a monitor plane 300 mm behind the origin and no pixels.
#[cfg(test)]
pub(crate) fn view_down_z(distance: f64, (fx, fy): (f64, f64)) -> ViewTargets {
    ViewTargets {
        view: 0,
        eye: Point3::new(0.0, 0.0, distance),
        monitor_point: Point3::new(0.0, 0.0, -300.0),
        monitor_normal: V3::z(),
        monitor_axes: None,
        pixel_axes: Some(PixelAxes {
            right: V3::new(1.0 / fx, 0.0, 0.0),
            down: V3::new(0.0, -1.0 / fy, 0.0),
            forward: -V3::z(),
        }),
        pixels: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pixel_spans_its_depth_over_the_focal_length() {
        let view = view_down_z(500.0, (1000.0, 800.0));
        // Depth along the optical axis, not the distance: an off-axis point at the same depth.
        for p in [Point3::origin(), Point3::new(80.0, -40.0, 0.0)] {
            let mm = view.pixel_mm_at(&p).unwrap();
            assert!((mm - 500.0 * 1.125e-3).abs() < 1e-12, "{mm}");
        }
        assert_eq!(view.pixel_mm_at(&Point3::new(0.0, 0.0, 600.0)), None);
        let blind = ViewTargets {
            pixel_axes: None,
            ..view.clone_empty()
        };
        assert_eq!(blind.pixel_mm_at(&Point3::origin()), None);
    }
}
