//! Embree (through the C shim and its safe wrapper) against brute-force f64 geometry.

use glasscan::mesh::shapes::{icosphere, perturb_radially};
use glasscan::mesh::TriMesh;
use glasscan::trace::{BuildMode, Device, Hit, Ray, Scene, TraceError};
use nalgebra::{Point3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Möller–Trumbore in f64: the closest hit (t, triangle) over all triangles.
fn brute_hit(mesh: &TriMesh, ray: &Ray) -> Option<(f64, u32)> {
    let mut best: Option<(f64, u32)> = None;
    for f in 0..mesh.faces.len() {
        let [a, b, c] = mesh.corners(f);
        let (e1, e2) = (b - a, c - a);
        let p = ray.dir.cross(&e2);
        let det = e1.dot(&p);
        if det == 0.0 {
            continue;
        }
        let s = ray.origin - a;
        let u = s.dot(&p) / det;
        let q = s.cross(&e1);
        let v = ray.dir.dot(&q) / det;
        let t = e2.dot(&q) / det;
        if u >= 0.0
            && v >= 0.0
            && u + v <= 1.0
            && t > ray.tnear
            && best.is_none_or(|(bt, _)| t < bt)
        {
            best = Some((t, f as u32));
        }
    }
    best
}

/// Distance from `p` to the nearest edge (segment) of triangle `f`.
fn edge_distance(mesh: &TriMesh, f: u32, p: Point3<f64>) -> f64 {
    let c = mesh.corners(f as usize);
    (0..3)
        .map(|k| {
            let (a, b) = (c[k], c[(k + 1) % 3]);
            let t = ((p - a).dot(&(b - a)) / (b - a).norm_squared()).clamp(0.0, 1.0);
            (p - (a + (b - a) * t)).norm()
        })
        .fold(f64::INFINITY, f64::min)
}

/// A perturbed unit sphere whose coordinates are exactly representable in f32, so that Embree
/// and the f64 reference see the same triangles.
fn test_sphere(seed: u64) -> TriMesh {
    let mut m = icosphere(1.0, 3);
    perturb_radially(&mut m, 0.1, seed);
    for p in &mut m.positions {
        *p = p.map(|c| c as f32 as f64);
    }
    m
}

fn random_rays(n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut unit = move || loop {
        let v = Vector3::from_fn(|_, _| 2.0 * rng.random::<f64>() - 1.0);
        if v.norm() <= 1.0 && v.norm() > 1e-3 {
            return v;
        }
    };
    (0..n)
        .map(|_| {
            let o = Point3::from(unit().normalize() * 3.0);
            let target = Point3::from(unit() * 1.1);
            let d = (target - o).normalize();
            Ray::new(o.map(|c| c as f32 as f64), d.map(|c| c as f32 as f64))
        })
        .collect()
}

/// Compares Embree's hits with brute force; returns (agreeing rays, mismatches far from edges).
fn compare(mesh: &TriMesh, rays: &[Ray], hits: &[Option<Hit>]) -> (usize, Vec<String>) {
    let mut agree = 0;
    let mut unexplained = Vec::new();
    for (i, (ray, hit)) in rays.iter().zip(hits).enumerate() {
        let brute = brute_hit(mesh, ray);
        let same = match (hit, brute) {
            (None, None) => true,
            (Some(h), Some((t, f))) => h.prim == f && ((h.t - t) / t).abs() <= 1e-5,
            _ => false,
        };
        if same {
            agree += 1;
            continue;
        }
        // A mismatch is acceptable only for a ray within 1e-6 (mm, on a unit sphere) of an edge.
        let near_edge = |f: u32, t: f64| edge_distance(mesh, f, ray.origin + ray.dir * t) < 1e-6;
        let explained = hit.is_none_or(|h| near_edge(h.prim, h.t))
            && brute.is_none_or(|(t, f)| near_edge(f, t));
        if !explained {
            unexplained.push(format!("ray {i}: embree {hit:?}, brute force {brute:?}"));
        }
    }
    (agree, unexplained)
}

#[test]
fn embree_hits_agree_with_brute_force_on_100k_rays() {
    let mesh = test_sphere(7);
    let device = Device::new().unwrap();
    let scene = Scene::new(&device, &mesh, BuildMode::Static).unwrap();
    let rays = random_rays(100_000, 11);
    for coherent in [false, true] {
        let hits = scene.intersect(&rays, coherent).unwrap();
        let misses = hits.iter().filter(|h| h.is_none()).count();
        assert!(
            misses > 1000 && misses < 90_000,
            "the ray set should both hit and miss: {misses} misses"
        );
        let (agree, unexplained) = compare(&mesh, &rays, &hits);
        assert!(
            agree as f64 >= 0.9999 * rays.len() as f64,
            "only {agree} of {} rays agree",
            rays.len()
        );
        assert!(
            unexplained.is_empty(),
            "mismatches away from edges: {unexplained:?}"
        );
    }
}

#[test]
fn any_hit_queries_answer_as_closest_hits_do() {
    let mesh = test_sphere(9);
    let device = Device::new().unwrap();
    // Rays from outside (hitting and missing, some grazing the rim) and from inside (every one
    // hits), and rays that stop short of the surface (tfar). Random rays pass no triangle edge
    // within float precision, the one place where the two queries may answer differently.
    let mut rays = random_rays(20_000, 13);
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    rays.extend((0..5_000).map(|_| {
        let d = Vector3::from_fn(|_, _| rng.random::<f64>() - 0.5).normalize();
        Ray::new(Point3::from(d * 0.3), d)
    }));
    let short: Vec<Ray> = rays[..5_000]
        .iter()
        .map(|r| Ray { tfar: 2.0, ..*r })
        .collect();
    rays.extend(short);
    for mode in [BuildMode::Static, BuildMode::Rebuild, BuildMode::Refit] {
        let scene = Scene::new(&device, &mesh, mode).unwrap();
        let closest = scene.intersect(&rays, false).unwrap();
        for coherent in [false, true] {
            let any = scene.hits_any(&rays, coherent).unwrap();
            let (hits, misses) = (
                any.iter().filter(|&&h| h).count(),
                any.iter().filter(|&&h| !h).count(),
            );
            assert!(
                hits > 5_000 && misses > 5_000,
                "{hits} hits, {misses} misses"
            );
            let differ: Vec<usize> = (0..rays.len())
                .filter(|&i| any[i] != closest[i].is_some())
                .collect();
            assert!(
                differ.is_empty(),
                "{mode:?}, coherent {coherent}: rays {differ:?} differ"
            );
        }
    }
}

#[test]
fn refit_and_rebuild_follow_moved_vertices() {
    let mesh = test_sphere(3);
    let moved = test_sphere(4);
    let rays = random_rays(5_000, 5);
    let device = Device::new().unwrap();
    for mode in [BuildMode::Rebuild, BuildMode::Refit] {
        let mut scene = Scene::new(&device, &mesh, mode).unwrap();
        scene.update_vertices(&moved.positions).unwrap();
        let hits = scene.intersect(&rays, false).unwrap();
        let (agree, unexplained) = compare(&moved, &rays, &hits);
        assert!(
            agree >= rays.len() - 1,
            "{mode:?}: {agree} of {} agree",
            rays.len()
        );
        assert!(unexplained.is_empty(), "{mode:?}: {unexplained:?}");
        // Closest points follow too.
        let q = [Point3::new(0.0, 0.0, 2.0)];
        let c = scene.closest_points(&q).unwrap()[0];
        let brute = brute_closest(&moved, q[0]);
        assert!(
            (c.dist - brute).abs() < 1e-12,
            "{mode:?}: {} vs {brute}",
            c.dist
        );
    }
}

/// Exact point–triangle distance by minimising over the triangle's interior, edges and corners.
fn point_triangle_distance(p: Point3<f64>, [a, b, c]: [Point3<f64>; 3]) -> f64 {
    let n = (b - a).cross(&(c - a));
    let mut best = f64::INFINITY;
    // Projection onto the plane, if inside.
    let q = p - n * ((p - a).dot(&n) / n.norm_squared());
    let inside = [(a, b), (b, c), (c, a)]
        .iter()
        .all(|(u, v)| (v - u).cross(&(q - u)).dot(&n) >= 0.0);
    if inside {
        best = (p - q).norm();
    }
    for (u, v) in [(a, b), (b, c), (c, a)] {
        let t = ((p - u).dot(&(v - u)) / (v - u).norm_squared()).clamp(0.0, 1.0);
        best = best.min((p - (u + (v - u) * t)).norm());
    }
    best
}

fn brute_closest(mesh: &TriMesh, p: Point3<f64>) -> f64 {
    (0..mesh.faces.len())
        .map(|f| point_triangle_distance(p, mesh.corners(f)))
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn closest_points_are_exact() {
    let mesh = test_sphere(9);
    let device = Device::new().unwrap();
    let scene = Scene::new(&device, &mesh, BuildMode::Static).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    // Points inside, near and far outside the surface.
    let pts: Vec<Point3<f64>> = (0..2000)
        .map(|i| {
            let r = [0.3, 0.95, 1.05, 5.0][i % 4];
            let v = Vector3::from_fn(|_, _| rng.random::<f64>() - 0.5).normalize();
            Point3::from(v * r)
        })
        .collect();
    let got = scene.closest_points(&pts).unwrap();
    for (p, c) in pts.iter().zip(&got) {
        let expected = brute_closest(&mesh, *p);
        assert!(
            (c.dist - expected).abs() <= 1e-12 * (1.0 + expected),
            "{p:?}: {} vs {expected}",
            c.dist
        );
        assert!(
            ((c.point - p).norm() - c.dist).abs() < 1e-12,
            "point and distance disagree"
        );
        let on_face = point_triangle_distance(c.point, mesh.corners(c.prim as usize));
        assert!(
            on_face < 1e-12,
            "closest point is not on its triangle: {on_face}"
        );
    }
}

#[test]
fn bad_vertex_updates_are_errors() {
    let mesh = test_sphere(1);
    let device = Device::new().unwrap();
    let mut scene = Scene::new(&device, &mesh, BuildMode::Refit).unwrap();
    let err = scene.update_vertices(&mesh.positions[1..]).unwrap_err();
    assert!(matches!(err, TraceError::VertexCount { .. }), "{err}");
    let mut bad = mesh.positions.clone();
    bad[17].y = f64::NAN;
    let err = scene.update_vertices(&bad).unwrap_err();
    assert!(matches!(err, TraceError::NonFinite(17)), "{err}");
    let mut bad_mesh = mesh.clone();
    bad_mesh.positions[3].x = f64::INFINITY;
    assert!(matches!(
        Scene::new(&device, &bad_mesh, BuildMode::Static),
        Err(TraceError::NonFinite(3))
    ));
}

/// Every build of the same mesh answers the same queries with the same triangles, bit for bit —
/// also for rays through vertices and points equidistant from several triangles (ties), which
/// the traversal order decides — so that a run, or a killed and resumed one, repeats itself.
#[test]
fn every_build_of_a_scene_answers_alike() {
    let mut mesh = icosphere(20.0, 5);
    perturb_radially(&mut mesh, 0.01, 4);
    let device = Device::new().unwrap();
    // Rays from outside straight at every vertex, and the vertices and edge midpoints pushed out.
    let rays: Vec<Ray> = (mesh.positions.iter())
        .map(|p| Ray::new(Point3::from(p.coords * 3.0), -p.coords.normalize()))
        .collect();
    let points: Vec<Point3<f64>> = (mesh.positions.iter())
        .map(|p| Point3::from(p.coords * 1.01))
        .chain(mesh.interior_edges().iter().map(|e| {
            let [a, b] = e.verts.map(|v| mesh.positions[v as usize]);
            Point3::from(nalgebra::center(&a, &b).coords * 1.01)
        }))
        .collect();
    let answers = |mode: BuildMode| {
        let scene = Scene::new(&device, &mesh, mode).unwrap();
        let hits: Vec<Option<u32>> = (scene.intersect(&rays, false).unwrap().iter())
            .map(|h| h.map(|h| h.prim))
            .collect();
        let near: Vec<u32> = (scene.closest_points(&points).unwrap().iter())
            .map(|c| c.prim)
            .collect();
        (hits, near)
    };
    for mode in [BuildMode::Static, BuildMode::Rebuild, BuildMode::Refit] {
        let first = answers(mode);
        for build in 1..12 {
            assert!(
                answers(mode) == first,
                "{mode:?}: build {build} answered otherwise"
            );
        }
    }
}
