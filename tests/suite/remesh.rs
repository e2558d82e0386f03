//! Isotropic remeshing: the local operators, and the remesher's output on analytic shapes,
//! sliver-ridden inputs and marching-cubes surfaces.

use glasscan::eval::sampled_distances;
use glasscan::mesh::halfedge::HalfEdgeMesh;
use glasscan::mesh::shapes::{cuboid, ellipsoid, figurine, icosphere, perturb_radially, torus};
use glasscan::mesh::stats::unique_edges;
use glasscan::mesh::validate::validate;
use glasscan::mesh::TriMesh;
use glasscan::remesh::{remesh, RemeshError, RemeshOptions};
use glasscan::trace::{BuildMode, Device, Scene};
use nalgebra::{Point3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A latitude–longitude sphere: triangle fans at the poles and thin triangles near them.
fn uv_sphere(radius: f64, n_lat: u32, n_lon: u32) -> TriMesh {
    let mut positions = vec![Point3::new(0.0, radius, 0.0)];
    for i in 1..n_lat {
        let theta = std::f64::consts::PI * i as f64 / n_lat as f64;
        for j in 0..n_lon {
            let phi = std::f64::consts::TAU * j as f64 / n_lon as f64;
            positions.push(Point3::new(
                radius * theta.sin() * phi.cos(),
                radius * theta.cos(),
                radius * theta.sin() * phi.sin(),
            ));
        }
    }
    positions.push(Point3::new(0.0, -radius, 0.0));
    let south = positions.len() as u32 - 1;
    let ring = |i: u32, j: u32| 1 + (i - 1) * n_lon + j % n_lon;
    let mut faces = Vec::new();
    for j in 0..n_lon {
        faces.push([0, ring(1, j + 1), ring(1, j)]);
        faces.push([south, ring(n_lat - 1, j), ring(n_lat - 1, j + 1)]);
    }
    for i in 1..n_lat - 1 {
        for j in 0..n_lon {
            let (a, b, c, d) = (
                ring(i, j),
                ring(i, j + 1),
                ring(i + 1, j + 1),
                ring(i + 1, j),
            );
            faces.push([a, b, c]);
            faces.push([a, c, d]);
        }
    }
    TriMesh::new(positions, faces)
}

/// Splits random edges very close to one end: a marching-cubes-like input full of slivers.
fn with_slivers(mesh: &TriMesh, count: usize, seed: u64) -> TriMesh {
    let mut h = HalfEdgeMesh::from_trimesh(mesh);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for _ in 0..count {
        let e = rng.random_range(0..h.edge_slots() as u32);
        let [a, b] = h.edge_vertices(e);
        let (pa, pb) = (h.pos[a as usize], h.pos[b as usize]);
        h.split(e, pa + (pb - pa) * 0.01);
    }
    h.to_trimesh()
}

/// The remesher's contract on `input` at edge length `h`.
fn check_remesh(name: &str, input: &TriMesh, h: f64) -> TriMesh {
    let before = validate(input);
    let out = remesh(input, &RemeshOptions::uniform(h)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let after = validate(&out);
    assert!(after.is_valid(), "{name}: {:?}", after.defects);
    assert_eq!(after.genus, before.genus, "{name}: genus changed");
    assert_eq!(
        after.components, before.components,
        "{name}: components changed"
    );

    let device = Device::new().unwrap();
    let scene = Scene::new(&device, input, BuildMode::Static).unwrap();
    let d = sampled_distances(&out, &scene, 50_000, 1).unwrap();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    assert!(
        mean <= 0.05 * h,
        "{name}: mean distance to the input {mean} mm > 0.05·h"
    );

    let edges = unique_edges(&out);
    let within = edges
        .iter()
        .filter(|&&[a, b]| {
            let l = (out.positions[a as usize] - out.positions[b as usize]).norm();
            (0.7 * h..=1.4 * h).contains(&l)
        })
        .count();
    let share = within as f64 / edges.len() as f64;
    assert!(
        share >= 0.95,
        "{name}: only {:.1} % of edges in [0.7h, 1.4h]",
        100.0 * share
    );
    out
}

#[test]
fn remeshing_analytic_shapes_keeps_topology_and_surface() {
    let mut bumpy = icosphere(20.0, 4);
    perturb_radially(&mut bumpy, 0.02, 5);
    check_remesh("sphere, coarse to fine", &icosphere(20.0, 2), 1.0);
    check_remesh("sphere, fine to coarse", &icosphere(20.0, 5), 2.5);
    check_remesh("bumpy sphere", &bumpy, 1.0);
    check_remesh(
        "ellipsoid",
        &ellipsoid(Vector3::new(30.0, 15.0, 8.0), 4),
        1.5,
    );
    check_remesh("torus (genus 1)", &torus(20.0, 6.0, 48, 24), 1.0);
    check_remesh("box", &cuboid(Vector3::new(20.0, 10.0, 15.0), 4), 1.0);
}

#[test]
fn remeshing_sliver_inputs() {
    let poles = uv_sphere(15.0, 24, 96);
    let a = validate(&poles);
    assert!(a.is_valid(), "{:?}", a.defects);
    check_remesh("uv sphere (fans and needles)", &poles, 1.0);
    let slivers = with_slivers(&icosphere(15.0, 3), 400, 2);
    assert!(
        glasscan::mesh::stats::angles(&slivers).min_deg < 1.0,
        "the input should hold slivers"
    );
    check_remesh("sphere with 400 slivers", &slivers, 1.0);
    let torus_slivers = with_slivers(&torus(20.0, 6.0, 32, 16), 300, 3);
    check_remesh("torus with 300 slivers", &torus_slivers, 1.2);
}

/// Marching-cubes surfaces like a visual hull's (slivers, needles, a handle): a genus-1
/// figurine at two sampling steps.
#[test]
fn remeshing_marching_cubes_surfaces() {
    for step in [0.8, 1.7] {
        check_remesh(&format!("figurine at {step} mm"), &figurine(step), 2.0);
    }
}

#[test]
fn remeshing_is_deterministic() {
    let input = with_slivers(&icosphere(10.0, 3), 100, 9);
    let opts = RemeshOptions::uniform(0.8);
    assert_eq!(
        remesh(&input, &opts).unwrap(),
        remesh(&input, &opts).unwrap()
    );
}

#[test]
fn random_operator_sequences_keep_the_mesh_valid() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut m = HalfEdgeMesh::from_trimesh(&torus(10.0, 4.0, 16, 8));
    let mut stamp = Vec::new();
    let (mut splits, mut collapses, mut flips) = (0, 0, 0);
    for step in 0..3000 {
        let e = rng.random_range(0..m.edge_slots() as u32);
        if m.edge_removed(e) {
            continue;
        }
        match step % 3 {
            0 => {
                let [a, b] = m.edge_vertices(e);
                let p = Point3::from((m.pos[a as usize].coords + m.pos[b as usize].coords) / 2.0);
                m.split(e, p);
                splits += 1;
            }
            1 => {
                if m.is_collapse_ok(2 * e, &mut stamp) {
                    m.collapse(2 * e);
                    collapses += 1;
                }
            }
            _ => {
                if m.is_flip_ok(e) {
                    m.flip(e);
                    flips += 1;
                }
            }
        }
        if step % 100 == 0 {
            m.garbage_collect();
            let r = validate(&m.to_trimesh());
            let topological: Vec<_> = r
                .defects
                .iter()
                .filter(|d| {
                    !matches!(
                        d,
                        glasscan::mesh::validate::Defect::Degenerate { .. }
                            | glasscan::mesh::validate::Defect::InsideOut { .. }
                    )
                })
                .collect();
            assert!(topological.is_empty(), "step {step}: {topological:?}");
            assert_eq!(r.genus, Some(1), "step {step}");
        }
    }
    assert!(
        splits > 500 && collapses > 300 && flips > 300,
        "{splits} splits, {collapses} collapses, {flips} flips"
    );
}

#[test]
fn bad_input_is_refused() {
    let mut open = icosphere(10.0, 2);
    open.faces.pop();
    let e = remesh(&open, &RemeshOptions::uniform(1.0)).unwrap_err();
    assert!(
        matches!(e, RemeshError::Invalid(_)) && e.to_string().contains("not watertight"),
        "{e}"
    );

    let sphere = icosphere(10.0, 2);
    for h in [0.0, -1.0, f64::NAN, 100.0] {
        let e = remesh(&sphere, &RemeshOptions::uniform(h)).unwrap_err();
        assert!(matches!(e, RemeshError::BadSetting(_)), "h = {h}: {e}");
    }
    let e = remesh(&sphere, &RemeshOptions::uniform(1e-5)).unwrap_err();
    assert!(e.to_string().contains("faces"), "{e}");
    // Per-vertex edge bounds: one per input vertex, each a positive length; a tiny one counts
    // against the face limit like a tiny edge.
    let n = sphere.positions.len();
    for bound in [
        vec![1.0; n - 1],
        vec![0.0; n],
        vec![f64::NAN; n],
        vec![1e-5; n],
    ] {
        let opts = RemeshOptions {
            edge_bound_mm: Some(bound),
            ..RemeshOptions::uniform(1.0)
        };
        let e = remesh(&sphere, &opts).unwrap_err();
        assert!(matches!(e, RemeshError::BadSetting(_)), "{e}");
    }
}

#[test]
fn feature_lines_keep_a_box_sharp() {
    let size = Vector3::new(20.0, 10.0, 15.0);
    let input = cuboid(size, 3);
    let device = Device::new().unwrap();
    let scene = Scene::new(&device, &input, BuildMode::Static).unwrap();
    let max_distance = |m: &TriMesh| {
        sampled_distances(m, &scene, 50_000, 2)
            .unwrap()
            .into_iter()
            .fold(0.0, f64::max)
    };

    let plain = remesh(&input, &RemeshOptions::uniform(1.0)).unwrap();
    let opts = RemeshOptions {
        feature_angle_deg: Some(45.0),
        ..RemeshOptions::uniform(1.0)
    };
    let sharp = remesh(&input, &opts).unwrap();
    let r = validate(&sharp);
    assert!(r.is_valid(), "{:?}", r.defects);
    for k in 0..8 {
        let corner = Point3::from(
            Vector3::from_fn(|i, _| if k >> i & 1 == 1 { 0.5 } else { -0.5 }).component_mul(&size),
        );
        assert!(
            sharp.positions.iter().any(|p| (p - corner).norm() < 1e-9),
            "corner {corner:?} lost"
        );
    }
    let (d_plain, d_sharp) = (max_distance(&plain), max_distance(&sharp));
    assert!(
        d_sharp < 1e-6 && d_plain > 0.05,
        "max distance to the box: {d_sharp} with features, {d_plain} without"
    );
    let e = glasscan::mesh::stats::edge_lengths(&sharp);
    assert!((0.8..1.2).contains(&e.mean_mm), "{e:?}");
}

/// `balanced`'s sizing field (`sizing_error`, `sizing_max_edge`) gives the glass block's flat
/// faces fewer than half the triangles per mm² of its 3 mm rounded edges (measured: a third, with
/// a quarter of the uniform stage's faces); a uniform stage gives both alike.
#[test]
fn the_sizing_field_spends_triangles_on_the_rounded_edges_not_the_flat_faces() {
    use glasscan::reconstruct::config::{Preset, Settings};
    let block = glasscan::mesh::shapes::glass_block(1.0);
    let edge = 1.5;
    // Faces per mm² on the flat faces (normal within 5° of an axis) and on the rounded edges
    // (more than 20° from every axis).
    let densities = |settings: &Settings| {
        let opts = glasscan::reconstruct::remesh_options(settings, edge);
        let mesh = remesh(&block, &opts).unwrap();
        assert!(validate(&mesh).is_valid());
        let (mut flat, mut rounded) = ((0usize, 0.0), (0usize, 0.0));
        for f in 0..mesh.faces.len() {
            let n = mesh.face_cross(f).normalize();
            let axis = n.abs().max();
            let class = if axis > 5f64.to_radians().cos() {
                &mut flat
            } else if axis < 20f64.to_radians().cos() {
                &mut rounded
            } else {
                continue;
            };
            class.0 += 1;
            class.1 += mesh.face_area(f);
        }
        let d = |(n, a): (usize, f64)| n as f64 / a;
        (d(flat), d(rounded), mesh.faces.len())
    };
    let adaptive = Settings::preset(Preset::Balanced);
    let uniform = Settings {
        sizing_error: 0.0,
        sizing_max_edge: 1.0,
        ..adaptive.clone()
    };
    let (uf, ur, un) = densities(&uniform);
    let (af, ar, an) = densities(&adaptive);
    eprintln!("faces per mm², flat / rounded: uniform {uf:.3} / {ur:.3} ({un} faces), sizing field {af:.3} / {ar:.3} ({an} faces)");
    assert!(uf > 0.6 * ur, "uniform: {uf} against {ur}");
    assert!(af < 0.5 * ar, "sizing field: {af} against {ar}");
    assert!(an < un / 2, "{an} faces against {un} uniform");
}
