//! The hand-written gradients against central finite differences (f64), on random
//! configurations and at the extremes docs/architecture.md §5 lists; exclusion of non-differentiable rays; and
//! the consistency of the refraction loss with the simulator on the true shape.

#![allow(clippy::needless_range_loop)]

use glasscan::loss::bits::PixelBits;
use glasscan::loss::membrane::{add_membrane, along_normals};
use glasscan::loss::refraction::{
    add_view, footprint_gradient_into, footprint_offsets, pixel_gradient, MeshState, PixelAxes,
    PixelGradient, PixelTarget, RefractionSettings, ResidualForm, ViewTargets,
};
use glasscan::loss::silhouette::{
    contour_edges, edge_gradient, outline_disagreement, pixels_per_unit, ContourMesh,
    SilhouetteForm,
};
use glasscan::loss::smoothness::{add_smoothness, Smoothness};
use glasscan::loss::{Accumulator, Contributions, DropReason, Robust};
use glasscan::mesh::shapes::{ellipsoid, icosphere, perturb_radially};
use glasscan::mesh::{InteriorEdge, TriMesh};
use glasscan::rig::{Camera, Turntable};
use glasscan::scan::decoded::{MASK_FILLED, MASK_OBJECT};
use glasscan::scan::silhouette::Silhouette;
use glasscan::trace::path::{trace_chunk, MeshSurface, NormalModel, PathEnd, PathSettings, Trail};
use glasscan::trace::refract::IOR_AIR;
use glasscan::trace::{BuildMode, Device, Ray, Scene};
use nalgebra::{Isometry3, Point3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

type V3 = Vector3<f64>;

/// A slab of two triangulated patches: the top one (outward +z) at z ≈ 0, the bottom one
/// (outward −z) at z ≈ −thickness, cells `sx` × `sy`, heights from `top` and `bottom`.
fn slab(
    n: usize,
    (sx, sy): (f64, f64),
    top: impl Fn(f64, f64) -> f64,
    bottom: impl Fn(f64, f64) -> f64,
) -> TriMesh {
    let mut positions = Vec::new();
    let mut faces = Vec::new();
    for (surface, up) in [(&top as &dyn Fn(f64, f64) -> f64, true), (&bottom, false)] {
        let base = positions.len() as u32;
        for j in 0..n {
            for i in 0..n {
                let (x, y) = (
                    (i as f64 - (n - 1) as f64 / 2.0) * sx,
                    (j as f64 - (n - 1) as f64 / 2.0) * sy,
                );
                positions.push(Point3::new(x, y, surface(x, y)));
            }
        }
        let v = |i: usize, j: usize| base + (j * n + i) as u32;
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let (a, b, c, d) = (v(i, j), v(i + 1, j), v(i + 1, j + 1), v(i, j + 1));
                if up {
                    faces.extend([[a, b, c], [a, c, d]]);
                } else {
                    faces.extend([[a, c, b], [a, d, c]]);
                }
            }
        }
    }
    TriMesh::new(positions, faces)
}

struct Case {
    mesh: TriMesh,
    s: RefractionSettings,
    view: ViewTargets,
    px: PixelTarget,
    /// The pixel's rays (one: its centre ray) and the triangles each refracts at.
    rays: Vec<(V3, Vec<u32>)>,
    /// Where the centre ray meets the plane z = `monitor_z`.
    landing: Point3<f64>,
}

fn settings(
    ior: f64,
    normals: NormalModel,
    form: ResidualForm,
    robust: Robust,
) -> RefractionSettings {
    RefractionSettings {
        ior,
        ior_air: IOR_AIR,
        max_refractions: 8,
        normals,
        form,
        robust,
        min_cos: 0.0,
        grazing_cell_footprints: 0.0,
        footprint: 1,
        bit_weight: 0.0,
        index_gradient: true,
    }
}

/// Traces the ray (eye, dir) through `mesh` and builds a case with a target near where it lands
/// on the plane z = `monitor_z` (screen form), or far along a direction near its exit direction
/// (direction form: the target's direction from the exit point is then fixed to 1e-12).
fn case(
    mesh: TriMesh,
    s: RefractionSettings,
    eye: Point3<f64>,
    dir: V3,
    monitor_z: f64,
    seed: u64,
) -> Case {
    let surface = MeshSurface::new(&mesh, s.normals).unwrap();
    let ps = PathSettings {
        ior: s.ior,
        ior_air: s.ior_air,
        max_refractions: 8,
    };
    let mut trails = [Trail::default()];
    let paths = trace_chunk(&surface, &[Ray::new(eye, dir)], &ps, Some(&mut trails)).unwrap();
    assert_eq!(
        paths[0].end,
        PathEnd::Left,
        "the test ray must pass: {:?}",
        paths[0]
    );
    assert!(paths[0].refractions >= 1);
    let (o, d) = (paths[0].origin, paths[0].dir);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let scale = mesh.bbox_diagonal();
    let jitter = V3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    );
    let target = match s.form {
        ResidualForm::Screen => {
            let t = (monitor_z - o.z) / d.z;
            let q = o + d * t + jitter * 0.05 * scale;
            Point3::new(q.x, q.y, monitor_z)
        }
        ResidualForm::Direction => o + (d + jitter * 0.05).normalize() * 1e9 * scale.max(1.0),
    };
    Case {
        s,
        view: ViewTargets {
            view: 0,
            eye,
            monitor_point: Point3::new(0.0, 0.0, monitor_z),
            monitor_normal: V3::z(),
            monitor_axes: None,
            pixel_axes: None,
            pixels: vec![],
        },
        px: PixelTarget {
            dir,
            target,
            weight: 0.7,
            bits: Default::default(),
            cell_px: 1.0,
            direct_px: 1.0,
            index_evidence: true,
        },
        rays: vec![(dir, trails[0].prims().to_vec())],
        landing: o + d * ((monitor_z - o.z) / d.z),
        mesh,
    }
}

fn state<'a>(mesh: &'a TriMesh, normals: &'a Option<Vec<V3>>) -> MeshState<'a> {
    MeshState::new(mesh, normals.as_deref())
}

/// The pixel's loss and gradient on `mesh` from its rays.
fn gradient(c: &Case, mesh: &TriMesh) -> Result<PixelGradient, DropReason> {
    let vn = (c.s.normals == NormalModel::Vertex).then(|| mesh.vertex_normals());
    let rays: Vec<_> = c.rays.iter().map(|(d, p)| (*d, Ok(&p[..]))).collect();
    let mut g = PixelGradient::default();
    footprint_gradient_into(&state(mesh, &vn), &c.s, &c.view, &c.px, &rays, &mut g).map(|()| g)
}

fn loss(c: &Case, mesh: &TriMesh) -> Result<f64, DropReason> {
    gradient(c, mesh).map(|g| g.loss)
}

fn analytic(c: &Case) -> Vec<V3> {
    let vn = (c.s.normals == NormalModel::Vertex).then(|| c.mesh.vertex_normals());
    let g = gradient(c, &c.mesh).unwrap();
    let mut acc = Accumulator::new(c.mesh.positions.len(), vn.is_some());
    let mut contributions = Contributions::default();
    contributions.push_pixel(&g, c.px.weight);
    acc.add(&[contributions]);
    acc.finish(&c.mesh)
}

/// Central differences with step `h` (mm) on every coordinate of every vertex; the largest
/// deviation relative to the gradient's largest component.
fn fd_check(c: &Case, h: f64, label: &str) {
    let g = analytic(c);
    let gmax = g.iter().map(|v| v.amax()).fold(0.0, f64::max);
    assert!(gmax > 0.0 && gmax.is_finite(), "{label}: gradient {gmax}");
    let mut worst = 0.0f64;
    for v in 0..c.mesh.positions.len() {
        for a in 0..3 {
            let mut m = c.mesh.clone();
            m.positions[v][a] += h;
            let lp = loss(c, &m).unwrap();
            m.positions[v][a] -= 2.0 * h;
            let lm = loss(c, &m).unwrap();
            let fd = (lp - lm) / (2.0 * h);
            let err = (fd - g[v][a]).abs();
            if err > 1e-9 {
                worst = worst.max(err / gmax);
            }
        }
    }
    assert!(
        worst <= 1e-5,
        "{label}: finite differences deviate by {worst:.2e} of the largest component ({gmax:.3e})"
    );
    ior_fd_check(c, (10.0 * h).min(1e-5), label);
}

/// ∂L/∂(refractive index) against five-point central differences of the index (step `h`); and
/// without it (`index_gradient` off), none, and the same loss and position gradient.
fn ior_fd_check(c: &Case, h: f64, label: &str) {
    let with = |s: RefractionSettings| Case {
        s,
        view: c.view.clone(),
        px: c.px,
        rays: c.rays.clone(),
        landing: c.landing,
        mesh: c.mesh.clone(),
    };
    let full = gradient(c, &c.mesh).unwrap();
    let off = with(RefractionSettings {
        index_gradient: false,
        ..c.s
    });
    let without = gradient(&off, &c.mesh).unwrap();
    assert_eq!(without.ior, 0.0, "{label}");
    assert_eq!(
        (without.loss, &without.grad, &without.ngrad),
        (full.loss, &full.grad, &full.ngrad),
        "{label}"
    );
    let g = full.ior;
    let at = |ior: f64| loss(&with(RefractionSettings { ior, ..c.s }), &c.mesh).unwrap();
    let n = c.s.ior;
    let fd = (8.0 * (at(n + h) - at(n - h)) - (at(n + 2.0 * h) - at(n - 2.0 * h))) / (12.0 * h);
    assert!(g.abs() > 0.0 && g.is_finite(), "{label}: ∂L/∂ior = {g}");
    assert!(
        (fd - g).abs() <= 1e-5 * g.abs().max(1e-9),
        "{label}: ∂L/∂ior {g:.6e} against finite differences {fd:.6e}"
    );
}

fn bumpy(amplitude: f64, seed: u64) -> impl Fn(f64, f64) -> f64 {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (a, b, c) = (
        rng.random_range(0.5..1.5),
        rng.random_range(0.5..1.5),
        rng.random_range(0.0..6.0),
    );
    move |x: f64, y: f64| amplitude * ((a * x + c).sin() + (b * y).cos())
}

#[test]
fn refraction_gradient_matches_finite_differences_on_random_slabs() {
    for seed in 0..6u64 {
        for normals in [NormalModel::Face, NormalModel::Vertex] {
            for (form, robust) in [
                (ResidualForm::Screen, Robust::L2),
                (ResidualForm::Screen, Robust::Huber(0.01)),
                (ResidualForm::Screen, Robust::Cauchy(0.05)),
                (ResidualForm::Direction, Robust::L2),
            ] {
                let mesh = slab(5, (1.0, 1.0), bumpy(0.15, seed), {
                    let b = bumpy(0.15, seed + 100);
                    move |x, y| -1.5 + b(x, y)
                });
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                let dir = V3::new(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    -1.0,
                )
                .normalize();
                let eye = Point3::new(
                    rng.random_range(-0.4..0.4),
                    rng.random_range(-0.4..0.4),
                    0.0,
                ) - dir * 5.0;
                let c = case(
                    mesh,
                    settings(1.5, normals, form, robust),
                    eye,
                    dir,
                    -10.0,
                    seed,
                );
                assert_eq!(c.rays[0].1.len(), 2);
                fd_check(
                    &c,
                    1e-6,
                    &format!("seed {seed} {normals:?} {form:?} {robust:?}"),
                );
            }
        }
    }
}

/// The case of one pixel seen from `eye` looking down −z, its footprint `n`×`n` rays over a
/// pixel 0.2 rad wide.
fn footprint_case(mesh: TriMesh, s: RefractionSettings, eye: Point3<f64>, n: u32) -> Case {
    let pixel_rad = 0.2;
    let axes = PixelAxes {
        right: V3::x() * pixel_rad,
        down: V3::y() * pixel_rad,
        forward: -V3::z(),
    };
    let dir = -V3::z();
    let mut c = case(mesh, s, eye, dir, -10.0, 3);
    let surface = MeshSurface::new(&c.mesh, c.s.normals).unwrap();
    let ps = PathSettings {
        ior: c.s.ior,
        ior_air: c.s.ior_air,
        max_refractions: 8,
    };
    c.rays = footprint_offsets(n)
        .into_iter()
        .map(|o| {
            let d = axes.offset(&dir, o);
            let mut trails = [Trail::default()];
            let paths = trace_chunk(&surface, &[Ray::new(eye, d)], &ps, Some(&mut trails)).unwrap();
            assert_eq!(paths[0].end, PathEnd::Left);
            (d, trails[0].prims().to_vec())
        })
        .collect();
    c.view.pixel_axes = Some(axes);
    c
}

#[test]
fn footprint_gradient_matches_finite_differences() {
    for seed in 0..3u64 {
        for normals in [NormalModel::Face, NormalModel::Vertex] {
            for (form, robust) in [
                (ResidualForm::Screen, Robust::L2),
                (ResidualForm::Screen, Robust::Cauchy(0.05)),
                (ResidualForm::Direction, Robust::L2),
            ] {
                let mesh = slab(6, (0.8, 0.8), bumpy(0.15, seed), {
                    let b = bumpy(0.15, seed + 100);
                    move |x, y| -1.5 + b(x, y)
                });
                let s = settings(1.5, normals, form, robust);
                let c = footprint_case(mesh, s, Point3::new(0.11, -0.07, 5.0), 2);
                // The rays cross different triangles: a footprint, not four copies of a ray.
                let distinct: std::collections::BTreeSet<_> =
                    c.rays.iter().map(|(_, p)| p.clone()).collect();
                assert!(
                    distinct.len() > 1,
                    "seed {seed}: the rays share their triangles"
                );
                fd_check(
                    &c,
                    1e-6,
                    &format!("footprint seed {seed} {normals:?} {form:?}"),
                );
            }
        }
    }
}

/// `c` with the per-bit term on: monitor pixels of 0.1 mm, the monitor turned 0.3 rad about z
/// (so that no two rays of a footprint share a monitor coordinate: the extent's end rays would
/// tie), and measured bits of a 16 × 8 pixel cell centred 2 pixels from where the centre ray
/// lands (inside it: the term acts within the cell).
fn with_bits(mut c: Case) -> Case {
    c.s.bit_weight = 0.5;
    let (sin, cos) = 0.3f64.sin_cos();
    let axes = [V3::new(cos, sin, 0.0) * 0.1, V3::new(-sin, cos, 0.0) * 0.1];
    let x = c.landing - c.view.monitor_point;
    let at = |a: usize| (x.dot(&axes[a]) / axes[a].norm_squared()) as f32;
    c.view.monitor_axes = Some(axes);
    c.px.bits = PixelBits {
        u: PixelBits::axis(16.0, [0.3, -0.1]),
        v: PixelBits::axis(8.0, [-0.5, 0.2]),
        centre: [at(0) + 2.0, at(1) - 1.0],
        cell: [16.0, 8.0],
    };
    c
}

#[test]
fn the_per_bit_term_gradient_matches_finite_differences() {
    for seed in 0..3u64 {
        for n in [1u32, 2] {
            for form in [ResidualForm::Screen, ResidualForm::Direction] {
                let mesh = slab(6, (0.8, 0.8), bumpy(0.15, seed), {
                    let b = bumpy(0.15, seed + 100);
                    move |x, y| -1.5 + b(x, y)
                });
                let mut s = settings(1.5, NormalModel::Face, form, Robust::Cauchy(0.05));
                s.footprint = n;
                let plain = footprint_case(mesh, s, Point3::new(0.11, -0.07, 5.0), n);
                let c = with_bits(footprint_case(
                    plain.mesh.clone(),
                    s,
                    Point3::new(0.11, -0.07, 5.0),
                    n,
                ));
                let (gb, g0) = (analytic(&c), analytic(&plain));
                let moved = gb
                    .iter()
                    .zip(&g0)
                    .map(|(a, b)| (a - b).amax())
                    .fold(0.0, f64::max);
                assert!(
                    moved > 1e-6,
                    "seed {seed} n {n}: the bits do not change the gradient"
                );
                assert!(loss(&c, &c.mesh).unwrap() > loss(&plain, &c.mesh).unwrap());
                fd_check(&c, 1e-6, &format!("bits seed {seed} n {n} {form:?}"));
            }
        }
    }
}

#[test]
fn a_symmetric_footprint_on_a_flat_slab_lands_where_its_centre_ray_does() {
    // At normal incidence through parallel faces the four rays land symmetrically about the
    // centre ray's point: the footprint's mean residual equals the centre ray's for any target,
    // while each ray's own residual differs.
    let mesh = slab(4, (1.0, 1.0), |_, _| 0.0, |_, _| -1.0);
    let s = settings(1.5, NormalModel::Face, ResidualForm::Screen, Robust::L2);
    let c = footprint_case(mesh, s, Point3::new(0.1, 0.2, 5.0), 2);
    let centre = Case {
        rays: vec![(-V3::z(), c.rays[0].1.clone())],
        ..footprint_case(c.mesh.clone(), c.s, Point3::new(0.1, 0.2, 5.0), 1)
    };
    let (lf, lc) = (loss(&c, &c.mesh).unwrap(), loss(&centre, &c.mesh).unwrap());
    assert!((lf - lc).abs() <= 1e-12 * lc.max(1e-300), "{lf} vs {lc}");
    let one = Case {
        rays: vec![c.rays[0].clone()],
        ..footprint_case(c.mesh.clone(), c.s, Point3::new(0.1, 0.2, 5.0), 1)
    };
    assert!((loss(&one, &c.mesh).unwrap() - lc).abs() > 1e-6 * lc);
}

/// A flat slab (faces parallel), scaled by `scale`, crossed by a ray at incidence `incidence_deg`.
fn flat_case(
    scale: f64,
    ior: f64,
    incidence_deg: f64,
    normals: NormalModel,
    cells: (f64, f64),
    offset: (f64, f64),
) -> Case {
    let mesh = slab(
        4,
        (cells.0 * scale, cells.1 * scale),
        |_, _| 0.0,
        move |_, _| -scale,
    );
    let th = incidence_deg.to_radians();
    let dir = V3::new(th.sin() * 0.6, th.sin() * 0.8, -th.cos());
    let hit = Point3::new(offset.0 * scale, offset.1 * scale, 0.0);
    let eye = hit - dir * (0.5 * scale);
    case(
        mesh,
        settings(ior, normals, ResidualForm::Screen, Robust::L2),
        eye,
        dir,
        -20.0 * scale,
        7,
    )
}

#[test]
fn refraction_gradient_at_the_extremes() {
    for normals in [NormalModel::Face, NormalModel::Vertex] {
        // Object scales 1 mm and 10 m.
        for scale in [1.0, 1e4] {
            let c = flat_case(scale / 3.0, 1.5, 30.0, normals, (1.0, 1.0), (0.13, 0.21));
            fd_check(&c, 1e-6 * scale, &format!("scale {scale} mm {normals:?}"));
        }
        // Refractive indices barely above air, and diamond's.
        for ior in [1.0001, 2.42] {
            let c = flat_case(1.0, ior, 40.0, normals, (1.0, 1.0), (0.13, 0.21));
            fd_check(&c, 1e-6, &format!("ior {ior} {normals:?}"));
        }
        // Grazing incidence: 86° in, and (parallel faces) 86° out.
        let c = flat_case(1.0, 1.5, 86.0, normals, (1.0, 1.0), (0.13, 0.21));
        fd_check(&c, 1e-7, &format!("grazing {normals:?}"));
        // Sliver triangles (aspect ratio 1e3).
        let c = flat_case(1.0, 1.5, 25.0, normals, (1e-3, 1.0), (1.3e-4, 0.21));
        fd_check(&c, 1e-9, &format!("sliver {normals:?}"));
        // A ray passing 1e-7 mm from the diagonal edge of a cell (x = y in cell coordinates,
        // cells centred at 0.5 + k).
        let c = flat_case(1.0, 1.5, 20.0, normals, (1.0, 1.0), (0.1, 0.1 + 1e-7));
        fd_check(&c, 1e-9, &format!("near an edge {normals:?}"));
    }
}

/// A ray inside the object meets a face tilted so that its incidence is `theta` (radians).
fn exit_case(theta: f64, ior: f64) -> (TriMesh, RefractionSettings, Point3<f64>, V3) {
    let (s, c) = theta.sin_cos();
    // Bottom surface tilted about x by theta: outward normal (0, sin θ, −cos θ).
    let mesh = slab(4, (1.0, 1.0), |_, _| 1.0, move |_, y| -1.0 - y * s / c);
    let st = settings(ior, NormalModel::Face, ResidualForm::Screen, Robust::L2);
    (mesh, st, Point3::new(0.1, 0.1, 0.0), -V3::z())
}

#[test]
fn near_the_critical_angle_the_gradient_holds_and_beyond_it_the_ray_is_dropped() {
    let ior = 1.5;
    let critical = (IOR_AIR / ior).asin();
    // Valid side, 1e-6 rad from the critical angle: steps small enough to stay there.
    let (mesh, s, eye, dir) = exit_case(critical - 1e-6, ior);
    let c = case(mesh, s, eye, dir, -3.0, 1);
    assert_eq!(c.rays[0].1.len(), 1);
    fd_check(&c, 1e-10, "1e-6 from critical");
    // Beyond it: not differentiable (TIR); the tracer ends the path and the gradient refuses it.
    let (mesh, s, eye, dir) = exit_case(critical + 1e-9, ior);
    let surface = MeshSurface::new(&mesh, NormalModel::Face).unwrap();
    let mut trails = [Trail::default()];
    let paths = trace_chunk(
        &surface,
        &[Ray::new(eye, dir)],
        &PathSettings::new(ior, 8),
        Some(&mut trails),
    )
    .unwrap();
    assert_eq!(paths[0].end, PathEnd::TotalInternalReflection);
    let view = ViewTargets {
        view: 0,
        eye,
        monitor_point: Point3::new(0.0, 0.0, -3.0),
        monitor_normal: V3::z(),
        monitor_axes: None,
        pixel_axes: None,
        pixels: vec![],
    };
    let px = PixelTarget {
        dir,
        target: Point3::new(0.0, 0.0, -3.0),
        weight: 1.0,
        bits: Default::default(),
        cell_px: 1.0,
        direct_px: 1.0,
        index_evidence: true,
    };
    assert!(trails[0].prims().is_empty());
    // The face the ray reflects at, given explicitly.
    let bottom = (0..mesh.faces.len() as u32)
        .find(|&f| {
            mesh.face_cross(f as usize).z < 0.0 && {
                let [a, b, cc] = mesh.corners(f as usize);
                let (lo, hi) = (a.x.min(b.x).min(cc.x), a.x.max(b.x).max(cc.x));
                (lo..=hi).contains(&0.1)
            }
        })
        .unwrap();
    let none = None;
    let r = pixel_gradient(&state(&mesh, &none), &s, &view, &px, &[bottom]);
    assert_eq!(r.err(), Some(DropReason::TotalInternalReflection));
}

#[test]
fn degenerate_triangles_drop_rays_and_never_reach_a_gradient() {
    // A zero-area (collinear) face in the path: dropped as grazing, nothing accumulated.
    let mut mesh = slab(3, (1.0, 1.0), |_, _| 0.0, |_, _| -1.0);
    mesh.positions.push(Point3::new(0.0, 0.0, 0.0));
    mesh.positions.push(Point3::new(1.0, 1.0, 0.0));
    mesh.positions.push(Point3::new(2.0, 2.0, 0.0));
    let n = mesh.positions.len() as u32;
    mesh.faces.push([n - 3, n - 2, n - 1]);
    let degenerate = mesh.faces.len() as u32 - 1;
    for normals in [NormalModel::Face, NormalModel::Vertex] {
        let s = settings(1.5, normals, ResidualForm::Screen, Robust::L2);
        let vn = (normals == NormalModel::Vertex).then(|| mesh.vertex_normals());
        let view = ViewTargets {
            view: 0,
            eye: Point3::new(0.3, 0.2, 2.0),
            monitor_point: Point3::new(0.0, 0.0, -5.0),
            monitor_normal: V3::z(),
            monitor_axes: None,
            pixel_axes: None,
            pixels: vec![],
        };
        let px = PixelTarget {
            dir: -V3::z(),
            target: Point3::new(0.0, 0.0, -5.0),
            weight: 1.0,
            bits: Default::default(),
            cell_px: 1.0,
            direct_px: 1.0,
            index_evidence: true,
        };
        let r = pixel_gradient(&state(&mesh, &vn), &s, &view, &px, &[degenerate, 0]);
        assert_eq!(r.err(), Some(DropReason::Grazing), "{normals:?}");
        // The zero-area face's vertices have zero normals; the normal adjoint stays finite.
        let mut acc = Accumulator::new(mesh.positions.len(), true);
        acc.normal_grad[n as usize - 1] = V3::new(1.0, 2.0, 3.0);
        assert!(acc
            .finish(&mesh)
            .iter()
            .all(|g| g.iter().all(|x| x.is_finite())));
    }
    // Smoothness over a mesh with a zero-area face: those edges are dropped and counted.
    let mut sphere = icosphere(5.0, 1);
    let f0 = sphere.faces[0];
    sphere.positions[f0[1] as usize] = sphere.positions[f0[0] as usize];
    let mut acc = Accumulator::new(sphere.positions.len(), false);
    add_smoothness(
        &sphere,
        &sphere.interior_edges(),
        Smoothness::NegLogOnePlusCos,
        &mut acc,
    );
    assert!(acc.drops.non_finite > 0);
    assert!(acc.grad.iter().all(|g| g.iter().all(|x| x.is_finite())) && acc.loss.is_finite());
}

#[test]
fn smoothness_gradients_match_finite_differences() {
    let mut mesh = icosphere(3.0, 1);
    perturb_radially(&mut mesh, 0.4, 5);
    let edges = mesh.interior_edges();
    assert_eq!(edges.len(), 3 * mesh.faces.len() / 2);
    for kind in [
        Smoothness::NegLogOnePlusCos,
        Smoothness::LogTwoMinusCos,
        Smoothness::Tolerant { tau: 0.1 },
    ] {
        let total = |m: &TriMesh| {
            let mut acc = Accumulator::new(m.positions.len(), false);
            add_smoothness(m, &edges, kind, &mut acc);
            acc
        };
        let label = format!("{kind:?}");
        assert_mesh_gradient(&mesh, 0..mesh.positions.len(), total, 1e-5, &label);
    }
}

/// Checks the gradient of the term `total` computes on `mesh` against central differences
/// (step 1e-6 mm) at `vertices`: within `rel` of the largest component, or 1e-9.
fn assert_mesh_gradient(
    mesh: &TriMesh,
    vertices: impl Iterator<Item = usize>,
    total: impl Fn(&TriMesh) -> Accumulator,
    rel: f64,
    label: &str,
) {
    let g = total(mesh).grad;
    let gmax = g.iter().map(|v| v.amax()).fold(0.0, f64::max);
    assert!(gmax > 0.0, "{label}: no gradient");
    let h = 1e-6;
    for v in vertices {
        for a in 0..3 {
            let mut m = mesh.clone();
            m.positions[v][a] += h;
            let lp = total(&m).loss;
            m.positions[v][a] -= 2.0 * h;
            let fd = (lp - total(&m).loss) / (2.0 * h);
            assert!(
                (fd - g[v][a]).abs() <= rel * gmax + 1e-9,
                "{label} vertex {v}: {fd} vs {}",
                g[v][a]
            );
        }
    }
}

#[test]
fn membrane_gradients_match_finite_differences() {
    let mut mesh = icosphere(3.0, 1);
    perturb_radially(&mut mesh, 0.4, 8);
    let edges = mesh.interior_edges();
    // Every other vertex selected: unselected vertices still feel their selected neighbours'.
    let selected: Vec<bool> = (0..mesh.positions.len()).map(|v| v % 2 == 0).collect();
    let total = |m: &TriMesh| {
        let mut acc = Accumulator::new(m.positions.len(), false);
        add_membrane(m, &edges, &selected, 1.3, &mut acc);
        acc
    };
    let acc = total(&mesh);
    assert_eq!(
        acc.weight,
        mesh.positions.len() as f64,
        "a mean over every vertex"
    );
    let touching = (edges.iter()).filter(|e| e.verts.iter().any(|&v| selected[v as usize]));
    assert_eq!(acc.used, touching.count());
    // The unselected vertices are the term's constants: no gradient on them.
    assert!((0..mesh.positions.len()).all(|v| selected[v] || acc.grad[v] == Vector3::zeros()));
    let moved = (0..mesh.positions.len()).filter(|&v| selected[v]);
    assert_mesh_gradient(&mesh, moved, total, 1e-6, "membrane");
}

/// A 10 × 10 × 1 mm box whose top's inner vertices (the membrane's patch; its rim held) are
/// lifted by a paraboloid (uniform curvature) and, if `graded`, crowded towards x = 5; with its
/// interior edges and which vertices are the patch.
fn bulged_box_top(graded: bool) -> (TriMesh, Vec<InteriorEdge>, Vec<bool>) {
    let mut grid = glasscan::mesh::shapes::cuboid(Vector3::new(10.0, 10.0, 1.0), 10);
    let edges = grid.interior_edges();
    let inner = |p: &Point3<f64>| p.z > 0.49 && p.x.abs() < 4.9 && p.y.abs() < 4.9;
    let top: Vec<bool> = grid.positions.iter().map(inner).collect();
    for (p, t) in grid.positions.iter_mut().zip(&top) {
        if *t {
            if graded {
                p.x = 5.0 - 10.0 * ((5.0 - p.x) / 10.0).powf(1.5);
            }
            p.z += 0.02 * (25.0 - p.x * p.x - p.y * p.y);
        }
    }
    (grid, edges, top)
}

#[test]
fn the_membrane_pulls_every_vertex_of_a_uniformly_bulged_patch_down() {
    // The top of a box bulged by a paraboloid (uniform curvature) with its rim held: every
    // interior vertex's gradient points up (descent lowers it), the centre's as much as those
    // near the rim — the patch flattens as a whole.
    let (grid, edges, top) = bulged_box_top(false);
    let mut acc = Accumulator::new(grid.positions.len(), false);
    add_membrane(&grid, &edges, &top, 1.0, &mut acc);
    let ups: Vec<f64> = (0..grid.positions.len())
        .filter(|&v| top[v] && grid.positions[v].x.abs() < 3.5 && grid.positions[v].y.abs() < 3.5)
        .map(|v| acc.grad[v].z)
        .collect();
    assert!(ups.len() >= 25);
    let (lo, hi) = ups
        .iter()
        .fold((f64::MAX, 0.0f64), |(l, h), &g| (l.min(g), h.max(g)));
    assert!(lo > 0.0 && hi < 1.01 * lo, "uniform pull down: {lo} … {hi}");
}

#[test]
fn the_membrane_moves_vertices_of_a_graded_face_only_along_their_normals() {
    // A box's top, graded (its vertices crowded towards x = 5) and bulged, its rim held: the
    // energy's gradient has a part along the face (towards the neighbours' centroid, which
    // grading moves); taken along the normals, none is left, and what is left is the energy's
    // derivative along each normal.
    let (grid, edges, top) = bulged_box_top(true);
    let energy = |m: &TriMesh| {
        let mut acc = Accumulator::new(m.positions.len(), false);
        add_membrane(m, &edges, &top, 1.0, &mut acc);
        acc
    };
    let raw = energy(&grid).grad;
    let normals = grid.vertex_normals();
    let mut force = raw.clone();
    along_normals(&mut force, &normals);
    let moved: Vec<usize> = (0..grid.positions.len()).filter(|&v| top[v]).collect();
    let tangential = |v: usize| (raw[v] - normals[v] * normals[v].dot(&raw[v])).norm();
    let most = moved.iter().map(|&v| tangential(v)).fold(0.0, f64::max);
    let largest = moved.iter().map(|&v| raw[v].norm()).fold(0.0, f64::max);
    assert!(
        most > 0.1 * largest,
        "the graded face pulls along itself: {most} of {largest}"
    );
    for &v in &moved {
        let n = normals[v];
        assert!(
            (force[v] - n * n.dot(&force[v])).norm() < 1e-12,
            "vertex {v}: {}",
            force[v]
        );
        let h = 1e-6;
        let at = |t: f64| {
            let mut m = grid.clone();
            m.positions[v] += n * t;
            energy(&m).loss
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        assert!(
            (fd - n.dot(&force[v])).abs() < 1e-6 * (1.0 + fd.abs()),
            "vertex {v}: {fd} against {}",
            n.dot(&force[v])
        );
    }
}

fn ring_camera(w: u32, h: u32, f: f64, dist: [f64; 5]) -> Camera {
    Camera {
        width: w,
        height: h,
        fx: f,
        fy: f * 1.01,
        cx: w as f64 / 2.0 - 0.3,
        cy: h as f64 / 2.0 + 0.2,
        dist,
    }
}

/// The world → camera pose of one turntable view at `angle_deg`, the axis `distance` mm in front
/// of the camera (the turntable's frame: +y up the axis).
fn ring_pose(distance: f64, angle_deg: f64) -> Isometry3<f64> {
    Turntable {
        axis_point: Point3::new(0.0, 0.0, distance),
        axis_dir: -V3::y_axis(),
        angles_deg: vec![angle_deg],
    }
    .view_poses()
    .unwrap()[0]
}

#[test]
fn projection_jacobian_matches_finite_differences_with_distortion() {
    let cam = ring_camera(640, 480, 800.0, [-0.2, 0.1, 0.001, -0.002, 0.01]);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..50 {
        let p = Point3::new(
            rng.random_range(-60.0..60.0),
            rng.random_range(-40.0..40.0),
            rng.random_range(300.0..700.0),
        );
        let (_, j) = cam.project_jacobian(&p).unwrap();
        for a in 0..3 {
            let h = 1e-5;
            let (mut pp, mut pm) = (p, p);
            pp[a] += h;
            pm[a] -= h;
            let d = (cam.project(&pp).unwrap() - cam.project(&pm).unwrap()) / (2.0 * h);
            assert!(
                (d - j.column(a)).norm() <= 1e-6 * j.norm(),
                "{d} vs {}",
                j.column(a)
            );
        }
    }
}

/// A sphere mesh of radius `r` at the origin seen by one ring view, and the silhouette of a
/// sphere of radius `r_mask`.
fn silhouette_setup(r: f64, r_mask: f64) -> (TriMesh, Silhouette) {
    let mut mesh = ellipsoid(V3::repeat(r), 3);
    perturb_radially(&mut mesh, 0.02 * r, 2);
    let cam = ring_camera(320, 240, 700.0, [-0.05, 0.01, 0.0, 0.0, 0.0]);
    let pose = ring_pose(400.0, 20.0);
    let centre = pose * Point3::origin();
    let mask: Vec<u8> = (0..cam.width * cam.height)
        .map(|i| {
            let d = cam
                .pixel_ray((i % cam.width) as f64, (i / cam.width) as f64)
                .unwrap();
            let along = centre.coords.dot(&d);
            ((centre.coords - along * d).norm() < r_mask) as u8 * 255
        })
        .collect();
    (mesh, Silhouette::from_mask(0, &mask, &cam, pose).unwrap())
}

#[test]
fn silhouette_gradient_matches_finite_differences_and_drt_points_the_same_way() {
    let (mesh, sil) = silhouette_setup(30.0, 32.0);
    let scene = Scene::new(&Device::new().unwrap(), &mesh, BuildMode::Static).unwrap();
    let edges = mesh.interior_edges();
    let contour = contour_edges(&ContourMesh::new(&mesh, &edges), &sil, &scene, 1.0).unwrap();
    assert!(contour.len() > 30, "{} contour edges", contour.len());
    // Half a millimetre as the outline unit (k ≈ 0.9 px here), held fixed as the mesh moves.
    let unit_px = pixels_per_unit(&mesh, &sil, 0.5);
    assert!((unit_px - 1.0).abs() > 0.05, "{unit_px} px");
    let (mut agree, mut compared) = (0, 0);
    for e in &contour {
        let (_, g) = edge_gradient(&mesh, &sil, e, SilhouetteForm::Distance, unit_px).unwrap();
        let gmax = g.iter().map(|v| v.amax()).fold(0.0, f64::max);
        let h = 1e-6;
        for (k, &v) in e.verts.iter().enumerate() {
            for a in 0..3 {
                let mut m = mesh.clone();
                m.positions[v as usize][a] += h;
                let lp = edge_gradient(&m, &sil, e, SilhouetteForm::Distance, unit_px)
                    .unwrap()
                    .0;
                m.positions[v as usize][a] -= 2.0 * h;
                let lm = edge_gradient(&m, &sil, e, SilhouetteForm::Distance, unit_px)
                    .unwrap()
                    .0;
                let fd = (lp - lm) / (2.0 * h);
                assert!(
                    (fd - g[k][a]).abs() <= 1e-5 * gmax + 1e-9,
                    "edge {:?}: {fd} vs {}",
                    e.verts,
                    g[k][a]
                );
            }
        }
        let (_, d) = edge_gradient(&mesh, &sil, e, SilhouetteForm::Drt, unit_px).unwrap();
        if gmax > 0.0 {
            compared += 1;
            agree += ((d[0] + d[1]).dot(&(g[0] + g[1])) > 0.0) as usize;
        }
    }
    // The mesh is 2 mm inside the mask: every contour edge should move outwards.
    assert!(
        compared > 30 && agree as f64 >= 0.95 * compared as f64,
        "{agree}/{compared}"
    );
}

/// The mask of the mesh in `scene` as `cam` at `pose` (world → camera) sees it: the pixels whose
/// centre ray hits it.
fn own_mask(scene: &Scene, cam: &Camera, pose: &Isometry3<f64>) -> Vec<u8> {
    let eye = pose.inverse() * Point3::origin();
    let w = cam.width as usize;
    let rays: Vec<Ray> = (0..w * cam.height as usize)
        .map(|i| {
            let d = cam.pixel_ray((i % w) as f64, (i / w) as f64).unwrap();
            Ray::new(eye, pose.inverse() * d)
        })
        .collect();
    (scene.intersect(&rays, false).unwrap())
        .iter()
        .map(|h| h.is_some() as u8 * MASK_OBJECT)
        .collect()
}

#[test]
fn only_contour_edges_on_the_meshs_own_outline_pull_with_a_short_probe() {
    // The mask is the mesh's own (pixel-centre rays that hit it), so at this shape the term
    // should not pull either way. A bumpy mesh's contour zigzags: with DRT's 1 px probes the
    // edges hidden just inside the outline count too, sit inside the mask and pull outward.
    let mut mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    perturb_radially(&mut mesh, 0.2, 3);
    let cam = ring_camera(320, 240, 700.0, [0.0; 5]);
    let tt = Turntable {
        axis_point: Point3::new(0.0, 0.0, 400.0),
        axis_dir: -V3::y_axis(),
        angles_deg: Turntable::even_angles(8),
    };
    let scene = Scene::new(&Device::new().unwrap(), &mesh, BuildMode::Static).unwrap();
    let edges = mesh.interior_edges();
    let mean_sd = |probe: f64| {
        let (mut sum, mut n) = (0.0, 0usize);
        for (k, pose) in tt.view_poses().unwrap().into_iter().enumerate() {
            let mask = own_mask(&scene, &cam, &pose);
            let sil = Silhouette::from_mask(k, &mask, &cam, pose).unwrap();
            for e in contour_edges(&ContourMesh::new(&mesh, &edges), &sil, &scene, probe).unwrap() {
                let [a, b] = e
                    .verts
                    .map(|v| cam.project(&(pose * mesh.positions[v as usize])).unwrap());
                let m = nalgebra::center(&a, &b);
                sum += sil.sd_px(m.x, m.y);
                n += 1;
            }
        }
        sum / n as f64
    };
    let (drt, short) = (mean_sd(1.0), mean_sd(0.03));
    eprintln!(
        "mean signed distance at the contour edges: probe 1 px {drt:+.4}, 0.03 px {short:+.4}"
    );
    // Measured: +0.151 and +0.029 px (+0.14…+0.18 and +0.03…+0.04 over seeds 1–6).
    assert!(drt > 0.08, "probe 1 px: {drt}");
    assert!(
        short.abs() < 0.4 * drt,
        "probe 0.03 px: {short} against {drt}"
    );
}

#[test]
fn the_outline_disagreement_counts_the_pixels_where_mesh_and_mask_differ() {
    let mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 3);
    let cam = ring_camera(320, 240, 700.0, [-0.05, 0.01, 0.0, 0.0, 0.0]);
    let pose = ring_pose(400.0, 30.0);
    let scene = Scene::new(&Device::new().unwrap(), &mesh, BuildMode::Static).unwrap();
    let own = own_mask(&scene, &cam, &pose);
    let w = cam.width as usize;
    let strided = |mask: &[u8], stride: usize| {
        let sil = Silhouette::from_mask(0, mask, &cam, pose).unwrap();
        outline_disagreement(&mesh, &sil, &scene, stride).unwrap()
    };
    let count = |mask: &[u8]| strided(mask, 1);
    assert_eq!(count(&own), 0);
    assert_eq!(strided(&own, 3), 0);
    // The mask moved 3 pixels right: every third pixel of every third row, each counted 9
    // times, estimates the exact count.
    let moved: Vec<u8> = (0..own.len())
        .map(|i| if i % w >= 3 { own[i - 3] } else { 0 })
        .collect();
    let (exact, estimate) = (count(&moved) as f64, strided(&moved, 3) as f64);
    assert!(exact > 200.0, "{exact}");
    assert!(
        (estimate - exact).abs() < 0.15 * exact,
        "{estimate} against {exact}"
    );
    let (cx, cy) = (w / 2, cam.height as usize / 2);
    assert_eq!(
        own[cy * w + cx],
        MASK_OBJECT,
        "the object covers the image centre"
    );
    // A 5×5 speck in a corner (beyond the mesh's projected box), a 3×3 hole in the object and
    // the same hole marked filled by the decoder (background for the terms).
    let mut speck = own.clone();
    let mut hole = own.clone();
    let mut filled = own.clone();
    for d in 0..25 {
        speck[(2 + d / 5) * w + 2 + d % 5] = MASK_OBJECT;
    }
    for d in 0..9 {
        hole[(cy - 1 + d / 3) * w + cx - 1 + d % 3] = 0;
        filled[(cy - 1 + d / 3) * w + cx - 1 + d % 3] = MASK_FILLED;
    }
    assert_eq!(count(&speck), 25);
    assert_eq!(
        strided(&speck, 3),
        25,
        "object pixels beyond the box count as they are"
    );
    assert_eq!(count(&hole), 9);
    assert_eq!(count(&filled), 9);
}

/// Two views of `mesh` (an ellipsoid about 60 mm wide, 300 mm from a 160×120 camera) with exact
/// correspondences: the simulator's own pixel-centre paths through `surface` (up to 4
/// refractions) and where they meet the monitor.
fn exact_views(surface: &MeshSurface) -> Vec<ViewTargets> {
    use glasscan::simulate::render::{camera_rays, trace_view, Outcome, ViewSetup};
    let cam = ring_camera(160, 120, 300.0, [0.0; 5]);
    let tt = Turntable {
        axis_point: Point3::new(0.0, 0.0, 300.0),
        axis_dir: -V3::y_axis(),
        angles_deg: vec![0.0, 70.0],
    };
    let screen = glasscan::rig::Screen {
        width_px: 800,
        height_px: 600,
        pitch_mm: 0.5,
        pose: nalgebra::Isometry3::translation(-200.0, -150.0, 500.0),
    };
    tt.view_poses()
        .unwrap()
        .into_iter()
        .enumerate()
        .map(|(k, pose)| {
            let setup = ViewSetup {
                camera: &cam,
                pose,
                screen: &screen,
                surface: Some(surface),
                bound_centre: Point3::origin(),
                bound_radius: 31.0,
                settings: PathSettings::new(1.5, 4),
                fresnel: false,
            };
            let samples =
                trace_view(&setup, &camera_rays(&setup, 1, 0..setup.camera.height)).unwrap();
            let to_world = pose.inverse();
            let world_screen = screen.transformed(&to_world);
            ViewTargets {
                view: k,
                eye: to_world * Point3::origin(),
                monitor_point: world_screen.point(0.0, 0.0),
                monitor_normal: world_screen.pose * V3::z(),
                monitor_axes: None,
                pixel_axes: None,
                pixels: samples
                    .iter()
                    .enumerate()
                    .filter(|(_, s)| matches!(s.outcome, Outcome::Monitor(k) if k >= 2))
                    .map(|(i, smp)| PixelTarget {
                        dir: to_world * cam.pixel_ray((i % 160) as f64, (i / 160) as f64).unwrap(),
                        target: world_screen.point(smp.monitor.x, smp.monitor.y),
                        weight: 1.0,
                        bits: Default::default(),
                        cell_px: 1.0,
                        direct_px: 1.0,
                        index_evidence: true,
                    })
                    .collect(),
            }
        })
        .collect()
}

/// The refraction term of `views` on `surface`'s mesh: loss, rays used, drops and the gradient's
/// norm.
fn evaluate_views(
    surface: &MeshSurface,
    views: &[ViewTargets],
    s: &RefractionSettings,
) -> (f64, usize, glasscan::loss::Drops, f64) {
    let vn = (s.normals == NormalModel::Vertex).then(|| surface.mesh().vertex_normals());
    let mut acc = Accumulator::new(surface.mesh().positions.len(), vn.is_some());
    let state = MeshState::new(surface.mesh(), vn.as_deref());
    for v in views {
        add_view(surface, &state, s, v, &mut acc).unwrap();
    }
    let (loss, used, drops) = (acc.loss, acc.used, acc.drops);
    let g = acc.finish(surface.mesh());
    let gnorm = g.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt();
    (loss, used, drops, gnorm)
}

/// The refraction term of `views` on `surface`'s mesh at index `ior`: loss, rays used,
/// ∂L/∂index and the gradient per vertex.
fn term_and_index_slope(
    surface: &MeshSurface,
    views: &[ViewTargets],
    ior: f64,
) -> (f64, usize, f64, Vec<V3>) {
    let s = RefractionSettings {
        max_refractions: 4,
        ..settings(
            ior,
            NormalModel::Vertex,
            ResidualForm::Direction,
            Robust::L2,
        )
    };
    let vn = surface.mesh().vertex_normals();
    let mut acc = Accumulator::new(surface.mesh().positions.len(), true);
    let state = MeshState::new(surface.mesh(), Some(&vn));
    for v in views {
        add_view(surface, &state, &s, v, &mut acc).unwrap();
    }
    let (loss, used, ior) = (acc.loss, acc.used, acc.ior);
    (loss, used, ior, acc.finish(surface.mesh()))
}

#[test]
fn pixels_that_are_no_evidence_of_the_index_pull_the_shape_but_not_the_index() {
    // Exact correspondences made at 1.5, the term taken at 1.52: every pixel pulls the index
    // down. Marked as no evidence of the index, a pixel keeps its loss and its pull on the
    // shape, and its ∂L/∂index leaves the sum: the marked and the unmarked halves add up.
    let mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    let surface = MeshSurface::new(&mesh, NormalModel::Vertex).unwrap();
    let views = exact_views(&surface);
    let mark = |keep: &dyn Fn(usize) -> bool| -> Vec<ViewTargets> {
        let mut marked = views.clone();
        for v in &mut marked {
            for (i, p) in v.pixels.iter_mut().enumerate() {
                p.index_evidence = keep(i);
            }
        }
        marked
    };
    let (loss, used, slope, grad) = term_and_index_slope(&surface, &views, 1.52);
    assert!(used > 2000 && slope > 0.0, "{used} rays, ∂L/∂index {slope}");
    assert!(grad.iter().any(|g| g.norm() > 0.0));
    let (loss_none, used_none, slope_none, grad_none) =
        term_and_index_slope(&surface, &mark(&|_| false), 1.52);
    assert_eq!((loss_none, used_none, slope_none), (loss, used, 0.0));
    assert_eq!(grad_none, grad, "the pull on the shape changed");
    let (_, _, even, _) = term_and_index_slope(&surface, &mark(&|i| i % 2 == 0), 1.52);
    let (_, _, odd, _) = term_and_index_slope(&surface, &mark(&|i| i % 2 == 1), 1.52);
    assert!(even > 0.0 && odd > 0.0, "{even} {odd}");
    assert!(
        (even + odd - slope).abs() <= 1e-9 * slope,
        "{even} + {odd} against {slope}"
    );
}

#[test]
fn on_the_true_shape_with_exact_correspondences_the_loss_vanishes() {
    let mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    for normals in [NormalModel::Vertex, NormalModel::Face] {
        let mut surface = MeshSurface::with_mode(&mesh, normals, BuildMode::Refit).unwrap();
        let s = RefractionSettings {
            max_refractions: 4,
            ..settings(1.5, normals, ResidualForm::Screen, Robust::L2)
        };
        let views = exact_views(&surface);
        let (loss, used, drops, gnorm) = evaluate_views(&surface, &views, &s);
        assert!(used > 2000, "{normals:?}: {used} rays");
        assert_eq!(drops.non_finite, 0);
        let per_ray = loss / used as f64;
        assert!(per_ray <= 1e-10, "{normals:?}: {per_ray:e} mm² per ray");
        // The gradient, against its size when the mesh is 0.1 % too large.
        let mut grown = mesh.clone();
        grown.scale_translate(1.001, V3::zeros());
        surface.update_positions(&grown.positions).unwrap();
        let (_, _, _, gnorm_grown) = evaluate_views(&surface, &views, &s);
        assert!(
            gnorm < 1e-4 * gnorm_grown,
            "{normals:?}: |gradient| {gnorm:e} on the truth, {gnorm_grown:e} 0.1 % off"
        );
    }
}

#[test]
fn the_term_traces_the_paths_the_path_tracer_finds() {
    // The refraction term traces its rays itself, computing each hit and refraction once in f64
    // on the triangle Embree found. Pixel by pixel, the path tracer's triangles recomputed by
    // `pixel_gradient` must give the same rays used, the same loss and the same gradient, on a
    // bumpy ellipsoid (so that the loss is far from 0) with up to 4 refractions. The term writes
    // each pixel's entries straight into its chunk's list, in buffers reused from chunk to
    // chunk and view to view; the pixels apart are added one by one, in the same order.
    let mut mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    let views = {
        let truth = MeshSurface::new(&mesh, NormalModel::Vertex).unwrap();
        exact_views(&truth)
    };
    perturb_radially(&mut mesh, 0.01, 3);
    for normals in [NormalModel::Face, NormalModel::Vertex] {
        let surface = MeshSurface::new(&mesh, normals).unwrap();
        let s = RefractionSettings {
            max_refractions: 4,
            ..settings(1.5, normals, ResidualForm::Screen, Robust::L2)
        };
        let vn = (normals == NormalModel::Vertex).then(|| mesh.vertex_normals());
        let mut acc = Accumulator::new(mesh.positions.len(), vn.is_some());
        let state = MeshState::new(&mesh, vn.as_deref());
        for v in &views {
            add_view(&surface, &state, &s, v, &mut acc).unwrap();
        }
        let (loss, used) = (acc.loss, acc.used);
        let grad = acc.finish(&mesh);
        let (mut loss_apart, mut used_apart) = (0.0, 0);
        let mut apart = Contributions::default();
        for v in &views {
            let rays: Vec<Ray> = v.pixels.iter().map(|p| Ray::new(v.eye, p.dir)).collect();
            let mut trails = vec![Trail::default(); rays.len()];
            let ps = PathSettings::new(s.ior, s.max_refractions);
            let paths = trace_chunk(&surface, &rays, &ps, Some(&mut trails)).unwrap();
            for ((px, path), trail) in v.pixels.iter().zip(&paths).zip(&trails) {
                let compared = path.end == PathEnd::Left && path.refractions % 2 == 0;
                if !compared || path.refractions == 0 {
                    continue;
                }
                if let Ok(g) = pixel_gradient(&state, &s, v, px, trail.prims()) {
                    loss_apart += g.loss;
                    used_apart += 1;
                    apart.push_pixel(&g, px.weight);
                }
            }
        }
        let mut acc_apart = Accumulator::new(mesh.positions.len(), vn.is_some());
        acc_apart.add(&[apart]);
        let grad_apart = acc_apart.finish(&mesh);
        let scale = grad.iter().map(|g| g.norm()).fold(0.0, f64::max);
        let worst = grad
            .iter()
            .zip(&grad_apart)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        assert!(
            scale > 0.0 && worst <= 1e-9 * scale,
            "{normals:?}: {worst} of {scale}"
        );
        assert!(used > 2000, "{normals:?}: {used} rays");
        assert_eq!(used, used_apart, "{normals:?}");
        assert!(loss > 1.0, "{normals:?}: loss {loss}");
        assert!(
            (loss - loss_apart).abs() <= 1e-9 * loss,
            "{normals:?}: {loss} traced by the term, {loss_apart} apart"
        );
    }
}

#[test]
fn grazing_rays_are_dropped_unless_their_decoded_cell_is_fine() {
    // Exact correspondences on the true ellipsoid: `min_cos` drops the rays that meet it near
    // grazing or near the critical angle, except those of pixels whose decoded cell is at most
    // `grazing_cell_footprints` direct footprints wide; the rays it keeps still fit exactly.
    let mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    let surface = MeshSurface::with_mode(&mesh, NormalModel::Vertex, BuildMode::Refit).unwrap();
    let with_cells = |cells: f32| {
        let mut views = exact_views(&surface);
        for p in views.iter_mut().flat_map(|v| v.pixels.iter_mut()) {
            p.cell_px = cells;
            p.direct_px = 1.0;
        }
        views
    };
    let term = |min_cos, grazing_cell_footprints| RefractionSettings {
        max_refractions: 4,
        min_cos,
        grazing_cell_footprints,
        ..settings(1.5, NormalModel::Vertex, ResidualForm::Screen, Robust::L2)
    };
    let count = |cells, s: &RefractionSettings| {
        let (loss, used, drops, _) = evaluate_views(&surface, &with_cells(cells), s);
        assert!(loss / used as f64 <= 1e-10, "{loss:e} over {used} rays");
        (used, drops.grazing + drops.near_critical)
    };
    let (all, none_dropped) = count(1.0, &term(0.0, 0.0));
    let (kept, dropped) = count(1.0, &term(0.3, 0.0));
    eprintln!("{all} rays; min_cos 0.3 drops {dropped}, keeps {kept}");
    assert!(dropped > 50 && kept + dropped <= all && none_dropped < dropped / 10);
    assert_eq!(count(1.0, &term(0.3, 3.0)), (all, none_dropped));
    assert_eq!(count(3.0, &term(0.3, 3.0)), (all, none_dropped));
    assert_eq!(count(6.0, &term(0.3, 3.0)), (kept, dropped));
}

#[test]
fn a_robust_loss_leaves_ghost_points_without_pull_and_still_sees_a_wrong_shape() {
    // Exact correspondences on the true shape with every fifth decoded point a "ghost": 30 mm
    // away on the monitor, as where light that reflected inside the object lands. On the truth
    // the other points fit exactly, so all the pull is the ghosts'.
    let mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    let mut surface = MeshSurface::with_mode(&mesh, NormalModel::Vertex, BuildMode::Refit).unwrap();
    let mut views = exact_views(&surface);
    for v in &mut views {
        let along = v.monitor_normal.cross(&V3::y()).normalize() * 30.0;
        for p in v.pixels.iter_mut().step_by(5) {
            p.target += along;
        }
    }
    let term = |robust| RefractionSettings {
        max_refractions: 4,
        ..settings(1.5, NormalModel::Vertex, ResidualForm::Screen, robust)
    };
    let (l2, cauchy) = (term(Robust::L2), term(Robust::Cauchy(1.0)));
    let (_, used, _, pull_l2) = evaluate_views(&surface, &views, &l2);
    let (_, _, _, pull_cauchy) = evaluate_views(&surface, &views, &cauchy);
    assert!(used > 2000);
    assert!(
        pull_cauchy < 0.01 * pull_l2,
        "ghosts pull {pull_cauchy:e} under Cauchy, {pull_l2:e} under L2"
    );
    // The same ghosts with the mesh 0.5 % too large: the robust term's gradient is the misfit's.
    let mut grown = mesh.clone();
    grown.scale_translate(1.005, V3::zeros());
    surface.update_positions(&grown.positions).unwrap();
    let (_, _, _, misfit_cauchy) = evaluate_views(&surface, &views, &cauchy);
    assert!(
        misfit_cauchy > 10.0 * pull_cauchy,
        "a 0.5 % misfit gives {misfit_cauchy:e} against the ghosts' {pull_cauchy:e}"
    );
}

#[test]
fn gradients_are_bitwise_the_same_on_any_number_of_threads() {
    let mut mesh = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    perturb_radially(&mut mesh, 0.3, 9);
    let cam = ring_camera(200, 150, 300.0, [0.0; 5]);
    let pose = ring_pose(300.0, 30.0);
    let to_world = pose.inverse();
    let eye = to_world * Point3::origin();
    let view = ViewTargets {
        view: 0,
        eye,
        monitor_point: to_world * Point3::new(0.0, 0.0, 500.0),
        monitor_normal: to_world * V3::z(),
        monitor_axes: None,
        pixel_axes: None,
        pixels: (0..200 * 150)
            .map(|i| PixelTarget {
                dir: to_world * cam.pixel_ray((i % 200) as f64, (i / 200) as f64).unwrap(),
                target: to_world
                    * Point3::new(
                        ((i % 200) as f64 - 100.0) * 0.9,
                        ((i / 200) as f64 - 75.0) * 0.9,
                        500.0,
                    ),
                weight: 1.0,
                bits: Default::default(),
                cell_px: 1.0,
                direct_px: 1.0,
                index_evidence: true,
            })
            .collect(),
    };
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let surface = MeshSurface::new(&mesh, NormalModel::Vertex).unwrap();
                let s = settings(
                    1.5,
                    NormalModel::Vertex,
                    ResidualForm::Screen,
                    Robust::Huber(1.0),
                );
                let vn = mesh.vertex_normals();
                let mut acc = Accumulator::new(mesh.positions.len(), true);
                let state = MeshState::new(&mesh, Some(&vn));
                add_view(&surface, &state, &s, &view, &mut acc).unwrap();
                add_smoothness(
                    &mesh,
                    &mesh.interior_edges(),
                    Smoothness::LogTwoMinusCos,
                    &mut acc,
                );
                let loss = acc.loss;
                (loss, acc.finish(&mesh))
            })
    };
    let (l1, g1) = run(1);
    assert!(l1 > 0.0);
    for threads in [2, 3, 5] {
        let (l, g) = run(threads);
        assert_eq!(l.to_bits(), l1.to_bits(), "{threads} threads");
        assert!(
            g.iter().zip(&g1).all(|(a, b)| a
                .iter()
                .zip(b.iter())
                .all(|(x, y)| x.to_bits() == y.to_bits())),
            "{threads} threads"
        );
    }
}

#[test]
fn the_ray_sample_is_unbiased_its_mean_gradient_is_the_full_views() {
    // Exact correspondences of the true ellipsoid against a mesh 0.3 mm off: over 600 evenly
    // spread offsets, the mean of a 30 % sample's loss and gradient sums (each drawn pixel
    // weighted by 1/share) equals the whole views'; one sample alone does not.
    let truth = ellipsoid(V3::new(30.0, 24.0, 20.0), 4);
    let truth_surface = MeshSurface::with_mode(&truth, NormalModel::Vertex, BuildMode::Refit);
    let views = exact_views(&truth_surface.unwrap());
    let mut mesh = truth.clone();
    perturb_radially(&mut mesh, 0.3, 5);
    let surface = MeshSurface::with_mode(&mesh, NormalModel::Vertex, BuildMode::Refit).unwrap();
    let s = settings(
        1.5,
        NormalModel::Vertex,
        ResidualForm::Direction,
        Robust::Cauchy(0.2),
    );
    let vn = mesh.vertex_normals();
    let sums = |views: &[ViewTargets]| {
        let mut acc = Accumulator::new(mesh.positions.len(), true);
        let state = MeshState::new(&mesh, Some(&vn));
        for v in views {
            add_view(&surface, &state, &s, v, &mut acc).unwrap();
        }
        (acc.loss, acc.finish(&mesh))
    };
    let (full_loss, full) = sums(&views);
    let norm = |g: &[V3]| g.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt();
    let off = |g: &[V3]| norm(&g.iter().zip(&full).map(|(a, b)| a - b).collect::<Vec<_>>());
    let (share, offsets) = (0.3, 600);
    let (mut loss, mut mean) = (0.0, vec![V3::zeros(); full.len()]);
    let mut single = f64::NAN;
    for k in 0..offsets {
        let u = (k as f64 + 0.5) / offsets as f64;
        let sample: Vec<ViewTargets> = views.iter().map(|v| v.sampled(share, u)).collect();
        let (l, g) = sums(&sample);
        if k == 0 {
            single = off(&g) / norm(&full);
        }
        loss += l / offsets as f64;
        for (m, g) in mean.iter_mut().zip(&g) {
            *m += g / offsets as f64;
        }
    }
    let (gradient_error, loss_error) = (off(&mean) / norm(&full), (loss / full_loss - 1.0).abs());
    eprintln!("sample mean: gradient {gradient_error:.2e}, loss {loss_error:.2e} off; one sample {single:.2e}");
    assert!(full_loss > 0.0 && norm(&full) > 0.0);
    assert!(gradient_error < 0.01 && loss_error < 0.01);
    assert!(
        single > 0.05,
        "one sample is {single} off: the test cannot tell"
    );
}
