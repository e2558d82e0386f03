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
    /// Closed components that enclose (numerically) no volume: a collapsed, flat surface.
    Flat { components: usize },
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
            Defect::Flat { components } => write!(
                f,
                "collapsed: {components} closed component(s) enclose no volume (below 1e-9 of the \
                 bbox diagonal cubed): a flat surface, not a solid"
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

/// A half-edge of the sorted list [`validate`] works on: (smaller vertex, larger vertex, face,
/// runs from the smaller to the larger vertex).
type HalfEdge = (u32, u32, u32, bool);

/// Validates `mesh`; see [`Defect`] for what is checked.
pub fn validate(mesh: &TriMesh) -> Report {
    let mut defects = Vec::new();
    defects.extend(degenerate_faces(mesh));
    let half = sorted_half_edges(mesh);
    let edges = classify_edges(mesh.faces.len(), &half);
    defects.extend(edges.defects());
    let nonmanifold_vertices = count_fans(mesh, &half);
    if let Some(&example) = nonmanifold_vertices.first() {
        defects.push(Defect::NonManifoldVertex {
            count: nonmanifold_vertices.len(),
            example,
        });
    }
    let (comp_of_face, components) = components(mesh.faces.len(), edges.joined);
    let closed_manifold =
        edges.open.is_empty() && edges.nonmanifold.is_empty() && nonmanifold_vertices.is_empty();
    let genus = closed_manifold.then(|| {
        let per = per_component(mesh, &comp_of_face, components);
        if edges.flipped.is_empty() {
            defects.extend(volume_defects(&per.volume, mesh.bbox_diagonal()));
        }
        per.genus
    });
    Report {
        defects,
        edges: edges.count,
        components,
        unreferenced_vertices: unreferenced_vertices(mesh),
        genus,
    }
}

/// Faces that repeat a vertex or whose area is below 1e-14 of the squared bbox diagonal.
fn degenerate_faces(mesh: &TriMesh) -> Option<Defect> {
    let diag2 = mesh.bbox_diagonal().powi(2);
    let degenerate: Vec<usize> = (0..mesh.faces.len())
        .filter(|&f| {
            let [a, b, c] = mesh.faces[f];
            a == b || b == c || a == c || mesh.face_cross(f).norm() <= 1e-14 * diag2
        })
        .collect();
    degenerate.first().map(|&example| Defect::Degenerate {
        count: degenerate.len(),
        example,
    })
}

/// Every face's three half-edges, sorted by their undirected edge.
fn sorted_half_edges(mesh: &TriMesh) -> Vec<HalfEdge> {
    let mut half: Vec<HalfEdge> = Vec::with_capacity(3 * mesh.faces.len());
    for (f, t) in mesh.faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            half.push((a.min(b), a.max(b), f as u32, a < b));
        }
    }
    half.sort_unstable();
    half
}

/// The edges by how many faces use them, and the faces they join.
struct EdgeClasses {
    count: usize,
    open: Vec<(u32, u32)>,
    /// Edges with more than two faces, and their face count.
    nonmanifold: Vec<((u32, u32), usize)>,
    /// Edges both faces traverse the same way (directed as the first face does), and the faces.
    flipped: Vec<((u32, u32), (usize, usize))>,
    /// Faces joined through edges.
    joined: UnionFind,
}

impl EdgeClasses {
    fn defects(&self) -> Vec<Defect> {
        let mut d = Vec::new();
        if let Some(&example) = self.open.first() {
            d.push(Defect::Open {
                count: self.open.len(),
                example,
            });
        }
        if let Some(&(example, faces)) = self.nonmanifold.first() {
            d.push(Defect::NonManifoldEdge {
                count: self.nonmanifold.len(),
                example,
                faces,
            });
        }
        if let Some(&(example, faces)) = self.flipped.first() {
            d.push(Defect::InconsistentOrientation {
                count: self.flipped.len(),
                example,
                faces,
            });
        }
        d
    }
}

/// Groups the sorted half-edges by undirected edge and classifies each edge.
fn classify_edges(faces: usize, half: &[HalfEdge]) -> EdgeClasses {
    let mut c = EdgeClasses {
        count: 0,
        open: Vec::new(),
        nonmanifold: Vec::new(),
        flipped: Vec::new(),
        joined: UnionFind::new(faces),
    };
    for run in half.chunk_by(|x, y| (x.0, x.1) == (y.0, y.1)) {
        c.count += 1;
        let e = (run[0].0, run[0].1);
        for h in &run[1..] {
            c.joined.union(run[0].2 as usize, h.2 as usize);
        }
        match run {
            [_] => c.open.push(e),
            [h1, h2] if h1.3 == h2.3 => {
                let directed = if h1.3 { e } else { (e.1, e.0) };
                c.flipped.push((directed, (h1.2 as usize, h2.2 as usize)));
            }
            [_, _] => {}
            _ => c.nonmanifold.push((e, run.len())),
        }
    }
    c
}

/// Each face's component index (0-based, in order of first face) and the component count.
fn components(faces: usize, mut joined: UnionFind) -> (Vec<usize>, usize) {
    let mut roots = std::collections::HashMap::new();
    let comp_of_face: Vec<usize> = (0..faces)
        .map(|f| {
            let next = roots.len();
            *roots.entry(joined.find(f)).or_insert(next)
        })
        .collect();
    (comp_of_face, roots.len())
}

/// Vertices no face uses.
fn unreferenced_vertices(mesh: &TriMesh) -> usize {
    let mut used = vec![false; mesh.positions.len()];
    for t in &mesh.faces {
        for &v in t {
            used[v as usize] = true;
        }
    }
    used.iter().filter(|u| !**u).count()
}

/// Enclosed volume (mm³) of each component, and the genus summed over them.
struct PerComponent {
    volume: Vec<f64>,
    genus: i64,
}

/// Volumes and genus of the components of a closed manifold mesh (Euler characteristic
/// V − E + F = 2 − 2g per component, with E = 3F/2).
fn per_component(mesh: &TriMesh, comp_of_face: &[usize], components: usize) -> PerComponent {
    let mut volume = vec![0.0; components];
    let mut faces_in = vec![0i64; components];
    let mut verts_in = vec![0i64; components];
    for (f, &c) in comp_of_face.iter().enumerate() {
        let [a, b, cc] = mesh.corners(f);
        volume[c] += a.coords.dot(&b.coords.cross(&cc.coords)) / 6.0;
        faces_in[c] += 1;
    }
    let mut comp_of_vertex = vec![usize::MAX; mesh.positions.len()];
    for (f, t) in mesh.faces.iter().enumerate() {
        for &v in t {
            comp_of_vertex[v as usize] = comp_of_face[f];
        }
    }
    for &c in comp_of_vertex.iter().filter(|&&c| c != usize::MAX) {
        verts_in[c] += 1;
    }
    let genus = (0..components)
        .map(|c| (2 - (verts_in[c] - 3 * faces_in[c] / 2 + faces_in[c])) / 2)
        .sum();
    PerComponent { volume, genus }
}

/// Components oriented inwards (negative volume), or enclosing no volume (a flat, collapsed
/// surface: below 1e-9 of the bbox diagonal cubed).
fn volume_defects(volume: &[f64], diagonal: f64) -> Vec<Defect> {
    let flat_below = 1e-9 * diagonal.powi(3);
    let mut d = Vec::new();
    let flat = volume.iter().filter(|v| v.abs() <= flat_below).count();
    if flat > 0 {
        d.push(Defect::Flat { components: flat });
    }
    let inverted: Vec<f64> = volume
        .iter()
        .copied()
        .filter(|&v| v < -flat_below)
        .collect();
    if !inverted.is_empty() {
        d.push(Defect::InsideOut {
            components: inverted.len(),
            volume_mm3: inverted.iter().sum(),
        });
    }
    d
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
fn count_fans(mesh: &TriMesh, half: &[HalfEdge]) -> Vec<u32> {
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
