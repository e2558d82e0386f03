//! Validation, genus and statistics on analytic shapes and on broken copies of them.

use glasscan::mesh::shapes::{cuboid, ellipsoid, icosphere, torus};
use glasscan::mesh::stats;
use glasscan::mesh::validate::{ensure_valid, validate, Defect};
use glasscan::mesh::TriMesh;
use nalgebra::{Point3, Vector3};

#[test]
fn analytic_shapes_are_valid_with_the_right_genus_and_volume() {
    let cases: Vec<(&str, TriMesh, i64, f64)> = vec![
        (
            "sphere",
            icosphere(10.0, 4),
            0,
            4.0 / 3.0 * std::f64::consts::PI * 1000.0,
        ),
        (
            "ellipsoid",
            ellipsoid(Vector3::new(3.0, 2.0, 1.0), 4),
            0,
            4.0 / 3.0 * std::f64::consts::PI * 6.0,
        ),
        (
            "torus",
            torus(20.0, 5.0, 96, 48),
            1,
            2.0 * std::f64::consts::PI.powi(2) * 20.0 * 25.0,
        ),
        ("box", cuboid(Vector3::new(1.0, 2.0, 3.0), 5), 0, 6.0),
    ];
    for (name, mesh, genus, volume) in cases {
        let report = ensure_valid(&mesh).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(report.genus, Some(genus), "{name}");
        assert_eq!(report.components, 1, "{name}");
        let v = mesh.signed_volume();
        assert!(
            (v - volume).abs() < 0.01 * volume,
            "{name}: volume {v} vs {volume}"
        );
    }
}

#[test]
fn two_disjoint_tori_have_genus_two() {
    let mut a = torus(20.0, 5.0, 32, 16);
    let mut b = a.clone();
    b.scale_translate(1.0, Vector3::new(100.0, 0.0, 0.0));
    let n = a.positions.len() as u32;
    a.positions.append(&mut b.positions);
    a.faces.extend(b.faces.iter().map(|f| f.map(|i| i + n)));
    let r = ensure_valid(&a).unwrap();
    assert_eq!((r.components, r.genus), (2, Some(2)));
}

#[test]
fn an_open_mesh_is_reported_with_a_boundary_edge() {
    let mut m = icosphere(1.0, 2);
    let removed = m.faces.remove(10);
    let r = validate(&m);
    assert_eq!(r.genus, None);
    match &r.defects[..] {
        [Defect::Open {
            count: 3,
            example: (a, b),
        }] => {
            assert!(
                removed.contains(a) && removed.contains(b),
                "example edge {a}-{b} not of face {removed:?}"
            );
        }
        other => panic!("expected exactly an open-mesh defect, got {other:?}"),
    }
    assert!(ensure_valid(&m)
        .unwrap_err()
        .to_string()
        .contains("not watertight"));
}

#[test]
fn a_flipped_face_is_reported_with_its_edge_and_faces() {
    let mut m = icosphere(1.0, 2);
    m.faces[5].swap(1, 2);
    let r = validate(&m);
    match &r.defects[..] {
        [Defect::InconsistentOrientation {
            count: 3,
            faces: (f1, f2),
            ..
        }] => {
            assert!(*f1 == 5 || *f2 == 5, "faces {f1}, {f2} should include 5");
        }
        other => panic!("expected exactly an orientation defect, got {other:?}"),
    }
}

#[test]
fn an_inside_out_mesh_is_reported() {
    let mut m = icosphere(1.0, 2);
    for f in &mut m.faces {
        f.swap(1, 2);
    }
    let r = validate(&m);
    assert!(
        matches!(&r.defects[..], [Defect::InsideOut { components: 1, volume_mm3 }] if *volume_mm3 < 0.0),
        "{:?}",
        r.defects
    );
    assert!(ensure_valid(&m)
        .unwrap_err()
        .to_string()
        .contains("oriented inwards"));
}

#[test]
fn a_non_manifold_edge_is_reported() {
    // A closed tetrahedron plus two extra faces on edge 0-1 (a second, closed "fin" tetrahedron
    // sharing that edge): edge 0-1 has four faces.
    let mut m = TriMesh::new(
        vec![
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(0.0, 1.0, 0.0),
            Point3::new(0.0, 0.0, 1.0),
            Point3::new(0.0, -1.0, 0.0),
            Point3::new(0.5, -0.5, -1.0),
        ],
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    );
    m.faces
        .extend([[0, 4, 1], [0, 1, 5], [0, 5, 4], [1, 4, 5]].map(|f| [f[0], f[2], f[1]]));
    let r = validate(&m);
    let d = r
        .defects
        .iter()
        .find(|d| matches!(d, Defect::NonManifoldEdge { .. }))
        .expect("non-manifold edge");
    assert_eq!(
        *d,
        Defect::NonManifoldEdge {
            count: 1,
            example: (0, 1),
            faces: 4
        }
    );
    assert!(d.to_string().contains("vertices 0-1"));
}

#[test]
fn a_pinched_vertex_is_reported() {
    // An icosahedron and its mirror image through its vertex 0 (faces flipped to stay outward),
    // sharing only that vertex.
    let mut m = icosphere(1.0, 0);
    let p0 = m.positions[0];
    let n = m.positions.len() as u32;
    let mirrored: Vec<Point3<f64>> = m.positions.iter().map(|p| p0 + (p0 - p)).collect();
    m.positions.extend(mirrored);
    let extra: Vec<[u32; 3]> = m
        .faces
        .iter()
        .map(|f| {
            let g = f.map(|i| if i == 0 { 0 } else { i + n });
            [g[0], g[2], g[1]]
        })
        .collect();
    m.faces.extend(extra);
    let r = validate(&m);
    assert_eq!(
        r.defects,
        vec![Defect::NonManifoldVertex {
            count: 1,
            example: 0
        }]
    );
}

#[test]
fn degenerate_faces_are_reported() {
    let mut m = icosphere(1.0, 1);
    let f = m.faces[0];
    m.faces.push([f[0], f[0], f[1]]);
    let r = validate(&m);
    assert!(
        r.defects.iter().any(|d| matches!(
            d,
            Defect::Degenerate {
                count: 1,
                example: 80
            }
        )),
        "{:?}",
        r.defects
    );
}

#[test]
fn edge_and_angle_statistics() {
    let m = cuboid(Vector3::new(2.0, 2.0, 2.0), 2);
    let e = stats::edge_lengths(&m);
    // Unit squares split along a diagonal: edges of length 1 and √2.
    assert!(
        (e.min_mm - 1.0).abs() < 1e-12 && (e.max_mm - 2f64.sqrt()).abs() < 1e-12,
        "{e:?}"
    );
    assert_eq!(e.count, stats::unique_edges(&m).len());
    let a = stats::angles(&m);
    assert!(
        (a.min_deg - 45.0).abs() < 1e-9 && a.below_30_share == 0.0,
        "{a:?}"
    );
}
