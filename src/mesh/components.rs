//! Connected components of a triangle mesh (faces joined through shared edges).

use super::TriMesh;

/// The component of every face (numbered from 0 in order of first appearance) and their count;
/// faces are joined when they share an edge, given as vertex pairs.
pub fn face_components(mesh: &TriMesh) -> (Vec<usize>, usize) {
    let mut edges: Vec<(u32, u32, u32)> = Vec::with_capacity(3 * mesh.faces.len());
    for (f, t) in mesh.faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            edges.push((a.min(b), a.max(b), f as u32));
        }
    }
    edges.sort_unstable();
    let mut uf = UnionFind::new(mesh.faces.len());
    for w in edges.windows(2) {
        if (w[0].0, w[0].1) == (w[1].0, w[1].1) {
            uf.union(w[0].2 as usize, w[1].2 as usize);
        }
    }
    let mut label = vec![usize::MAX; uf.parent.len()];
    let mut count = 0;
    let comp = (0..mesh.faces.len())
        .map(|f| {
            let r = uf.find(f);
            if label[r] == usize::MAX {
                label[r] = count;
                count += 1;
            }
            label[r]
        })
        .collect();
    (comp, count)
}

/// Keeps the components of a closed mesh whose enclosed volume (mm³) is at least `share` of the
/// largest one's; returns the mesh (unused vertices removed) and how many components were dropped.
pub fn keep_large_components(mesh: &TriMesh, share: f64) -> (TriMesh, usize) {
    let (comp, count) = face_components(mesh);
    let mut volume = vec![0.0; count];
    for (f, &c) in comp.iter().enumerate() {
        let [a, b, cc] = mesh.corners(f);
        volume[c] += a.coords.dot(&b.coords.cross(&cc.coords)) / 6.0;
    }
    let largest = volume.iter().copied().fold(0.0, f64::max);
    let keep: Vec<bool> = volume.iter().map(|&v| v >= share * largest).collect();
    let mut index = vec![u32::MAX; mesh.positions.len()];
    let mut positions = Vec::new();
    let mut faces = Vec::new();
    for (f, t) in mesh.faces.iter().enumerate() {
        if !keep[comp[f]] {
            continue;
        }
        faces.push(t.map(|v| {
            if index[v as usize] == u32::MAX {
                index[v as usize] = positions.len() as u32;
                positions.push(mesh.positions[v as usize]);
            }
            index[v as usize]
        }));
    }
    let dropped = keep.iter().filter(|k| !**k).count();
    (TriMesh::new(positions, faces), dropped)
}

/// Disjoint sets with path halving and union by size.
pub(crate) struct UnionFind {
    parent: Vec<usize>,
    size: Vec<usize>,
}

impl UnionFind {
    pub(crate) fn new(n: usize) -> Self {
        Self {
            parent: (0..n).collect(),
            size: vec![1; n],
        }
    }
    pub(crate) fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }
    pub(crate) fn union(&mut self, a: usize, b: usize) {
        let (mut a, mut b) = (self.find(a), self.find(b));
        if a == b {
            return;
        }
        if self.size[a] < self.size[b] {
            std::mem::swap(&mut a, &mut b);
        }
        self.parent[b] = a;
        self.size[a] += self.size[b];
    }
}
