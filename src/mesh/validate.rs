//! Topological and geometric validation of a triangle mesh: is it a closed, edge- and
//! vertex-manifold, consistently and outward-oriented surface without degenerate faces? Also the
//! connected components and the genus.
//!
//! Every defect is reported with a count and a first example (vertex or face ids), so a user can
//! find it in a mesh viewer. Self-intersections are not checked.

use std::fmt;

use super::components::UnionFind;
use super::TriMesh;

/// One kind of defect, with how often it occurs and a first example.
#[derive(Clone, Debug, PartialEq)]
pub enum Defect {
    /// Edges used by only one face: the surface has holes.
    Open { count: usize, example: (u32, u32) },
    /// Edges shared by more than two faces.
    NonManifoldEdge {
        count: usize,
        example: (u32, u32),
        faces: usize,
    },
    /// Vertices whose incident faces form more than one fan (surfaces touching at a point).
    NonManifoldVertex { count: usize, example: u32 },
    /// Edges traversed in the same direction by both of their faces: a flipped face.
    InconsistentOrientation {
        count: usize,
        example: (u32, u32),
        faces: (usize, usize),
    },
    /// Closed components with negative enclosed volume: the normals point inwards.
    InsideOut { components: usize, volume_mm3: f64 },
    /// Faces that repeat a vertex or have (numerically) zero area.
    Degenerate { count: usize, example: usize },
}

impl fmt::Display for Defect {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Defect::Open { count, example: (a, b) } => write!(
                f,
                "not watertight: {count} boundary edge(s) used by only one face, e.g. vertices {a}-{b} \
                 (close the holes, e.g. with a hole-filling tool)"
            ),
            Defect::NonManifoldEdge { count, example: (a, b), faces } => write!(
                f,
                "not edge-manifold: {count} edge(s) shared by more than two faces, e.g. vertices \
                 {a}-{b} ({faces} faces)"
            ),
            Defect::NonManifoldVertex { count, example } => write!(
                f,
                "not vertex-manifold: {count} vertex/vertices where separate surface sheets touch, \
                 e.g. vertex {example}"
            ),
            Defect::InconsistentOrientation { count, example: (a, b), faces: (f1, f2) } => write!(
                f,
                "inconsistently oriented: {count} edge(s) traversed the same way by both faces, \
                 e.g. vertices {a}->{b} in faces {f1} and {f2} (one of them is flipped)"
            ),
            Defect::InsideOut { components, volume_mm3 } => write!(
                f,
                "oriented inwards: {components} closed component(s) with negative volume \
                 ({volume_mm3:.6} mm³); flip every face"
            ),
            Defect::Degenerate { count, example } => write!(
                f,
                "{count} degenerate face(s) (repeated vertex, or zero area: below 1e-14 of the squared bbox diagonal), e.g. face {example}"
            ),
        }
    }
}

/// The result of [`validate`].
#[derive(Clone, Debug)]
pub struct Report {
    /// Defects found; empty for a valid mesh.
    pub defects: Vec<Defect>,
    /// Number of edges (unordered vertex pairs).
    pub edges: usize,
    /// Connected components (through shared edges).
    pub components: usize,
    /// Vertices not used by any face (harmless; not a defect).
    pub unreferenced_vertices: usize,
    /// Sum of the genera of the components; `None` unless the mesh is closed and manifold.
    pub genus: Option<i64>,
}

impl Report {
    /// True when no defect was found.
    pub fn is_valid(&self) -> bool {
        self.defects.is_empty()
    }
}

/// A mesh that failed validation: the defects, as one error.
#[derive(Clone, Debug, thiserror::Error)]
#[error("{}", .0.iter().map(|d| d.to_string()).collect::<Vec<_>>().join("; "))]
pub struct InvalidMesh(pub Vec<Defect>);

/// Validates `mesh`; see [`Defect`] for what is checked.
pub fn validate(mesh: &TriMesh) -> Report {
    let nf = mesh.faces.len();
    let nv = mesh.positions.len();
    let mut defects = Vec::new();

    // Degenerate faces: repeated index, or area below 1e-14 of the squared bbox diagonal.
    let diag2 = mesh.bbox_diagonal().powi(2);
    let degenerate: Vec<usize> = (0..nf)
        .filter(|&f| {
            let [a, b, c] = mesh.faces[f];
            a == b || b == c || a == c || mesh.face_cross(f).norm() <= 1e-14 * diag2
        })
        .collect();
    if let Some(&example) = degenerate.first() {
        defects.push(Defect::Degenerate {
            count: degenerate.len(),
            example,
        });
    }

    // Half-edges sorted by their undirected edge: (min, max, face, forward?).
    let mut half: Vec<(u32, u32, u32, bool)> = Vec::with_capacity(3 * nf);
    for (f, t) in mesh.faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            half.push((a.min(b), a.max(b), f as u32, a < b));
        }
    }
    half.sort_unstable();

    let mut uf = UnionFind::new(nf);
    let (mut open, mut nonmanifold, mut flipped) = (Vec::new(), Vec::new(), Vec::new());
    let mut edges = 0;
    let mut i = 0;
    while i < half.len() {
        let mut j = i + 1;
        while j < half.len() && half[j].0 == half[i].0 && half[j].1 == half[i].1 {
            j += 1;
        }
        edges += 1;
        let e = (half[i].0, half[i].1);
        match j - i {
            1 => open.push(e),
            2 => {
                uf.union(half[i].2 as usize, half[i + 1].2 as usize);
                if half[i].3 == half[i + 1].3 {
                    let (a, b) = if half[i].3 { e } else { (e.1, e.0) };
                    flipped.push(((a, b), (half[i].2 as usize, half[i + 1].2 as usize)));
                }
            }
            n => {
                for k in i + 1..j {
                    uf.union(half[i].2 as usize, half[k].2 as usize);
                }
                nonmanifold.push((e, n));
            }
        }
        i = j;
    }
    if let Some(&example) = open.first() {
        defects.push(Defect::Open {
            count: open.len(),
            example,
        });
    }
    if let Some(&(example, faces)) = nonmanifold.first() {
        defects.push(Defect::NonManifoldEdge {
            count: nonmanifold.len(),
            example,
            faces,
        });
    }
    if let Some(&(example, faces)) = flipped.first() {
        defects.push(Defect::InconsistentOrientation {
            count: flipped.len(),
            example,
            faces,
        });
    }

    let nonmanifold_vertices = count_fans(mesh, &half);
    if let Some(&example) = nonmanifold_vertices.first() {
        defects.push(Defect::NonManifoldVertex {
            count: nonmanifold_vertices.len(),
            example,
        });
    }

    // Components: faces joined through edges.
    let mut comp_of_face = vec![usize::MAX; nf];
    let mut roots = std::collections::HashMap::new();
    for (f, c) in comp_of_face.iter_mut().enumerate() {
        let r = uf.find(f);
        let next = roots.len();
        *c = *roots.entry(r).or_insert(next);
    }
    let components = roots.len();

    let mut used = vec![false; nv];
    for t in &mesh.faces {
        for &v in t {
            used[v as usize] = true;
        }
    }
    let unreferenced_vertices = used.iter().filter(|u| !**u).count();

    let closed_manifold =
        open.is_empty() && nonmanifold.is_empty() && nonmanifold_vertices.is_empty();
    let mut genus = None;
    if closed_manifold {
        // Per component: volume sign and Euler characteristic V - E + F = 2 - 2g.
        let mut volume = vec![0.0; components];
        let mut faces_in = vec![0i64; components];
        let mut verts_in = vec![0i64; components];
        for (f, &c) in comp_of_face.iter().enumerate() {
            let [a, b, cc] = mesh.corners(f);
            volume[c] += a.coords.dot(&b.coords.cross(&cc.coords)) / 6.0;
            faces_in[c] += 1;
        }
        let mut comp_of_vertex = vec![usize::MAX; nv];
        for (f, t) in mesh.faces.iter().enumerate() {
            for &v in t {
                comp_of_vertex[v as usize] = comp_of_face[f];
            }
        }
        for &c in comp_of_vertex.iter().filter(|&&c| c != usize::MAX) {
            verts_in[c] += 1;
        }
        // Closed manifold: every edge has two faces, so E = 3F/2 per component.
        let g: i64 = (0..components)
            .map(|c| (2 - (verts_in[c] - 3 * faces_in[c] / 2 + faces_in[c])) / 2)
            .sum();
        genus = Some(g);
        if flipped.is_empty() {
            let inverted: Vec<f64> = volume.iter().copied().filter(|&v| v < 0.0).collect();
            if !inverted.is_empty() {
                defects.push(Defect::InsideOut {
                    components: inverted.len(),
                    volume_mm3: inverted.iter().sum(),
                });
            }
        }
    }

    Report {
        defects,
        edges,
        components,
        unreferenced_vertices,
        genus,
    }
}

/// Checks `mesh` and returns the defects as an error if there are any.
pub fn ensure_valid(mesh: &TriMesh) -> Result<Report, InvalidMesh> {
    let report = validate(mesh);
    if report.is_valid() {
        Ok(report)
    } else {
        Err(InvalidMesh(report.defects))
    }
}

/// Vertices around which the incident faces form more than one fan (connected through edges
/// that contain the vertex). `half` is the sorted half-edge list of [`validate`].
fn count_fans(mesh: &TriMesh, half: &[(u32, u32, u32, bool)]) -> Vec<u32> {
    let nv = mesh.positions.len();
    // Incident faces per vertex (CSR).
    let mut start = vec![0usize; nv + 1];
    for t in &mesh.faces {
        for &v in t {
            start[v as usize + 1] += 1;
        }
    }
    for v in 0..nv {
        start[v + 1] += start[v];
    }
    let mut fill = start.clone();
    let mut incident = vec![0u32; start[nv]];
    for (f, t) in mesh.faces.iter().enumerate() {
        for &v in t {
            incident[fill[v as usize]] = f as u32;
            fill[v as usize] += 1;
        }
    }
    // Face pairs adjacent across each edge, to join fans at both edge ends.
    let mut links: Vec<Vec<(u32, u32)>> = vec![Vec::new(); nv];
    let mut i = 0;
    while i < half.len() {
        let mut j = i + 1;
        while j < half.len() && half[j].0 == half[i].0 && half[j].1 == half[i].1 {
            j += 1;
        }
        for k in i + 1..j {
            let pair = (half[i].2, half[k].2);
            links[half[i].0 as usize].push(pair);
            links[half[i].1 as usize].push(pair);
        }
        i = j;
    }
    let mut bad = Vec::new();
    for v in 0..nv {
        let faces = &incident[start[v]..start[v + 1]];
        if faces.len() < 2 {
            continue;
        }
        let local = |f: u32| faces.iter().position(|&g| g == f).expect("incident face");
        let mut uf = UnionFind::new(faces.len());
        for &(a, b) in &links[v] {
            uf.union(local(a), local(b));
        }
        let root = uf.find(0);
        if (1..faces.len()).any(|k| uf.find(k) != root) {
            bad.push(v as u32);
        }
    }
    bad
}
