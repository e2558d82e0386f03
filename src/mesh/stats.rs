//! Mesh statistics: unique edges, edge-length and angle statistics.

use super::TriMesh;

/// Summary of a list of lengths (mm).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct LengthStats {
    pub count: usize,
    pub min_mm: f64,
    pub max_mm: f64,
    pub mean_mm: f64,
    /// Coefficient of variation: standard deviation / mean.
    pub cv: f64,
}

impl LengthStats {
    /// Statistics of `lengths` (mm); all zeros for an empty list.
    pub fn of(lengths: &[f64]) -> Self {
        if lengths.is_empty() {
            return Self::default();
        }
        let n = lengths.len() as f64;
        let mean = lengths.iter().sum::<f64>() / n;
        let var = lengths.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / n;
        Self {
            count: lengths.len(),
            min_mm: lengths.iter().copied().fold(f64::INFINITY, f64::min),
            max_mm: lengths.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            mean_mm: mean,
            cv: if mean > 0.0 { var.sqrt() / mean } else { 0.0 },
        }
    }
}

/// Triangle-shape statistics.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct AngleStats {
    /// Smallest interior angle of any triangle, degrees.
    pub min_deg: f64,
    /// Share of triangles with an interior angle below 30° (0..1).
    pub below_30_share: f64,
}

/// The unique undirected edges of `mesh`, each as (smaller id, larger id), sorted.
pub fn unique_edges(mesh: &TriMesh) -> Vec<[u32; 2]> {
    let mut e: Vec<[u32; 2]> = mesh
        .faces
        .iter()
        .flat_map(|t| (0..3).map(move |k| [t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3])]))
        .collect();
    e.sort_unstable();
    e.dedup();
    e
}

/// Edge-length statistics over the unique edges of `mesh` (mm).
pub fn edge_lengths(mesh: &TriMesh) -> LengthStats {
    let lengths: Vec<f64> = unique_edges(mesh)
        .iter()
        .map(|&[a, b]| (mesh.positions[a as usize] - mesh.positions[b as usize]).norm())
        .collect();
    LengthStats::of(&lengths)
}

/// Interior-angle statistics over the faces of `mesh`.
pub fn angles(mesh: &TriMesh) -> AngleStats {
    let mut min_deg = f64::INFINITY;
    let mut below = 0usize;
    for f in 0..mesh.faces.len() {
        let p = mesh.corners(f);
        let mut smallest = f64::INFINITY;
        for k in 0..3 {
            let (u, v) = (p[(k + 1) % 3] - p[k], p[(k + 2) % 3] - p[k]);
            smallest = smallest.min(u.angle(&v).to_degrees());
        }
        min_deg = min_deg.min(smallest);
        below += (smallest < 30.0) as usize;
    }
    AngleStats {
        min_deg: if mesh.faces.is_empty() { 0.0 } else { min_deg },
        below_30_share: below as f64 / mesh.faces.len().max(1) as f64,
    }
}

/// Share of the referenced vertices with exactly six incident edges (0..1).
pub fn valence6_share(mesh: &TriMesh) -> f64 {
    let mut valence = vec![0u32; mesh.positions.len()];
    for [a, b] in unique_edges(mesh) {
        valence[a as usize] += 1;
        valence[b as usize] += 1;
    }
    let used: Vec<u32> = valence.into_iter().filter(|&v| v > 0).collect();
    used.iter().filter(|&&v| v == 6).count() as f64 / used.len().max(1) as f64
}

/// The triangle-quality figures remeshing is judged by.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct MeshQuality {
    pub faces: usize,
    pub edges: LengthStats,
    pub angles: AngleStats,
    /// Share of vertices of valence 6 (0..1).
    pub valence6_share: f64,
}

/// Faces, edge lengths, angles and valences of `mesh`.
pub fn quality(mesh: &TriMesh) -> MeshQuality {
    MeshQuality {
        faces: mesh.faces.len(),
        edges: edge_lengths(mesh),
        angles: angles(mesh),
        valence6_share: valence6_share(mesh),
    }
}
