//! Mesh files: round trips, foreign PLY variants, and bad input.

use std::fs;
use std::path::{Path, PathBuf};

use glasscan::mesh::io::{read_mesh, write_mesh, write_mesh_as, MeshFormat, MeshIoError};
use glasscan::mesh::shapes::{icosphere, perturb_radially};

#[test]
fn round_trips_are_exact() {
    let dir = tempfile::tempdir().unwrap();
    let mut m = icosphere(12.5, 2);
    perturb_radially(&mut m, 0.05, 3);
    for (name, format) in [
        ("a.ply", MeshFormat::PlyBinary),
        ("b.ply", MeshFormat::PlyAscii),
        ("c.obj", MeshFormat::Obj),
    ] {
        let path = dir.path().join(name);
        write_mesh_as(&path, &m, format).unwrap();
        let back = read_mesh(&path).unwrap();
        assert_eq!(back, m, "{name}");
    }
    write_mesh(&dir.path().join("d.ply"), &m).unwrap();
    assert_eq!(read_mesh(&dir.path().join("d.ply")).unwrap(), m);
    // No temporary files are left behind.
    let left: Vec<_> = fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left.len(), 4, "{left:?}");
}

const QUAD_PLY: &str = "ply
format ascii 1.0
comment a unit square pyramid with colours and a quality property
element vertex 5
property float x
property float y
property float z
property float quality
property uchar red
property uchar green
property uchar blue
element face 5
property list uchar int vertex_indices
property uchar flags
end_header
0 0 0 0.5 255 0 0
1 0 0 0.5 255 0 0
1 0 1 0.5 255 0 0
0 0 1 0.5 255 0 0
0.5 1 0.5 1.0 0 255 0
4 0 1 2 3 7
3 0 4 1 0
3 1 4 2 0
3 2 4 3 0
3 3 4 0 0
";

#[test]
fn extra_properties_are_ignored_and_polygons_triangulated() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pyramid.ply");
    fs::write(&path, QUAD_PLY).unwrap();
    let m = read_mesh(&path).unwrap();
    assert_eq!(m.positions.len(), 5);
    assert_eq!(m.faces.len(), 6);
    assert_eq!(m.faces[0], [0, 1, 2]);
    assert_eq!(m.faces[1], [0, 2, 3]);
    assert_eq!(m.positions[4].y, 1.0);
}

#[test]
fn big_endian_int16_ply_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("be.ply");
    let mut bytes = b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty short x\nproperty short y\nproperty short z\nelement face 1\nproperty list uchar ushort vertex_index\nend_header\n".to_vec();
    for v in [[0i16, 0, 0], [2, 0, 0], [0, 3, 0]] {
        for c in v {
            bytes.extend(c.to_be_bytes());
        }
    }
    bytes.push(3);
    for i in [0u16, 1, 2] {
        bytes.extend(i.to_be_bytes());
    }
    fs::write(&path, bytes).unwrap();
    let m = read_mesh(&path).unwrap();
    assert_eq!(m.faces, vec![[0, 1, 2]]);
    assert_eq!(m.positions[2].y, 3.0);
}

fn read_err(path: &Path) -> MeshIoError {
    read_mesh(path).expect_err("this input must be rejected")
}

#[test]
fn bad_input_gives_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();

    let missing = read_err(&d.join("nope.ply"));
    assert!(
        matches!(missing, MeshIoError::Open { .. }) && missing.to_string().contains("nope.ply"),
        "{missing}"
    );

    let mut files = truncated_files_are_parse_errors(d);
    files.extend(out_of_range_indices_name_the_face(d));
    files.extend(non_finite_coordinates_name_the_vertex(d));
    files.extend(unknown_formats_and_empty_meshes_are_named(d));
    // Every message is one line.
    for p in &files {
        assert!(!read_err(p).to_string().contains('\n'), "{}", read_err(p));
    }
}

/// Truncated binary and ASCII PLY files (made in `d`, returned) are parse errors.
fn truncated_files_are_parse_errors(d: &Path) -> Vec<PathBuf> {
    // Truncated binary PLY: cut the file in the middle of the faces.
    let full = d.join("full.ply");
    write_mesh(&full, &icosphere(1.0, 2)).unwrap();
    let bytes = fs::read(&full).unwrap();
    let cut = d.join("cut.ply");
    fs::write(&cut, &bytes[..bytes.len() - 100]).unwrap();
    let e = read_err(&cut);
    assert!(matches!(e, MeshIoError::Parse { .. }), "{e}");

    // Truncated ASCII PLY: drop the last face line.
    let ascii = QUAD_PLY
        .lines()
        .take(QUAD_PLY.lines().count() - 1)
        .collect::<Vec<_>>()
        .join("\n")
        + "\n";
    let cut_ascii = d.join("cut_ascii.ply");
    fs::write(&cut_ascii, ascii).unwrap();
    let e = read_err(&cut_ascii);
    assert!(matches!(e, MeshIoError::Parse { .. }), "{e}");

    vec![cut, cut_ascii]
}

/// Out-of-range indices, in PLY and OBJ files (made in `d`, returned), are named.
fn out_of_range_indices_name_the_face(d: &Path) -> Vec<PathBuf> {
    let oob = d.join("oob.ply");
    fs::write(&oob, QUAD_PLY.replace("3 3 4 0 0", "3 3 4 9 0")).unwrap();
    let e = read_err(&oob);
    assert!(
        matches!(
            e,
            MeshIoError::IndexOutOfRange {
                face: 4,
                index: 9,
                nverts: 5,
                ..
            }
        ),
        "{e}"
    );
    let oob_obj = d.join("oob.obj");
    fs::write(&oob_obj, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n").unwrap();
    // OBJ errors quote the index as written (1-based) and its line.
    let e = read_err(&oob_obj).to_string();
    assert!(
        e.contains("line 4") && e.contains("vertex index 7") && e.contains("3 vertices"),
        "{e}"
    );
    let zero_obj = d.join("zero.obj");
    fs::write(&zero_obj, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n").unwrap();
    assert!(
        read_err(&zero_obj).to_string().contains("line 4"),
        "{}",
        read_err(&zero_obj)
    );

    vec![oob, oob_obj]
}

/// NaN coordinates, in PLY and OBJ files (made in `d`, returned), are refused.
fn non_finite_coordinates_name_the_vertex(d: &Path) -> Vec<PathBuf> {
    let nan = d.join("nan.ply");
    fs::write(&nan, QUAD_PLY.replace("0.5 1 0.5 1.0", "0.5 nan 0.5 1.0")).unwrap();
    let e = read_err(&nan);
    assert!(
        matches!(e, MeshIoError::NonFinite { vertex: 4, .. })
            || matches!(e, MeshIoError::Parse { .. }),
        "{e}"
    );
    let nan_obj = d.join("nan.obj");
    fs::write(&nan_obj, "v 0 0 0\nv 1 NaN 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    let e = read_err(&nan_obj);
    assert!(matches!(e, MeshIoError::NonFinite { vertex: 1, .. }), "{e}");

    vec![nan]
}

/// Not a mesh format, not a PLY, no faces: the files made in `d` (the PLY returned).
fn unknown_formats_and_empty_meshes_are_named(d: &Path) -> Vec<PathBuf> {
    assert!(matches!(
        read_err(&d.join("x.stl")),
        MeshIoError::UnknownFormat { .. }
    ));
    let junk = d.join("junk.ply");
    fs::write(&junk, "hello\n").unwrap();
    assert!(matches!(read_err(&junk), MeshIoError::Parse { .. }));
    let cloud = d.join("cloud.obj");
    fs::write(&cloud, "v 0 0 0\nv 1 0 0\n").unwrap();
    assert!(read_err(&cloud).to_string().contains("no faces"));

    vec![junk]
}

#[test]
fn obj_groups_and_relative_indices_share_one_vertex_list() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("groups.obj");
    // A tetrahedron split into two groups.
    fs::write(
        &path,
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\ng a\nf 1//1 3//1 2//1\nf 1/1 2/1 4/1\ng b\nf -4 -1 -2\nf 2 3 4\n",
    )
    .unwrap();
    let m = read_mesh(&path).unwrap();
    assert_eq!(m.positions.len(), 4);
    glasscan::mesh::validate::ensure_valid(&m).unwrap();
}
