//! Half-edge topology of a closed, oriented, manifold triangle mesh, with the local operators
//! remeshing needs: edge split, edge collapse and edge flip, and their topological validity tests.
//!
//! Layout (as in pmp-library's `SurfaceMesh`, restricted to closed triangle meshes): edge `e` owns
//! the half-edges `2e` and `2e + 1`, so the opposite of `h` is `h ^ 1`; every half-edge stores its
//! target vertex, the next half-edge of its face and its face; the previous half-edge of a triangle
//! is `next(next(h))`. Removed elements are flagged, and [`HalfEdgeMesh::to_trimesh`] compacts.
//! Positions are in mm.

use std::collections::HashMap;

use nalgebra::{Point3, Vector3};

use super::TriMesh;

const NONE: u32 = u32::MAX;

/// New ids after [`HalfEdgeMesh::garbage_collect`], indexed by old id; `u32::MAX` for removed.
pub struct Compaction {
    pub vertices: Vec<u32>,
    pub edges: Vec<u32>,
}

impl Compaction {
    /// The entries of per-vertex `data` that survive, in their new order.
    pub fn vertex_data<T: Copy>(&self, data: &[T]) -> Vec<T> {
        keep_mapped(data, &self.vertices)
    }

    /// The entries of per-edge `data` that survive, in their new order.
    pub fn edge_data<T: Copy>(&self, data: &[T]) -> Vec<T> {
        keep_mapped(data, &self.edges)
    }
}

fn keep_mapped<T: Copy>(data: &[T], map: &[u32]) -> Vec<T> {
    data.iter()
        .zip(map)
        .filter(|(_, &m)| m != NONE)
        .map(|(d, _)| *d)
        .collect()
}

/// A closed triangle mesh in half-edge form.
#[derive(Clone, Debug)]
pub struct HalfEdgeMesh {
    /// Vertex positions, mm (also of removed vertices, whose entries are stale).
    pub pos: Vec<Point3<f64>>,
    v_out: Vec<u32>,
    h_to: Vec<u32>,
    h_next: Vec<u32>,
    h_face: Vec<u32>,
    f_h: Vec<u32>,
    v_removed: Vec<bool>,
    e_removed: Vec<bool>,
    f_removed: Vec<bool>,
}

impl HalfEdgeMesh {
    /// Builds the half-edge form of `mesh`, which must be closed, edge- and vertex-manifold and
    /// consistently oriented (check with [`super::validate`]). Vertex ids are kept; unreferenced
    /// vertices are marked removed.
    pub fn from_trimesh(mesh: &TriMesh) -> Self {
        let nf = mesh.faces.len();
        let nv = mesh.positions.len();
        let mut m = Self {
            v_out: vec![NONE; nv],
            v_removed: vec![true; nv],
            pos: mesh.positions.clone(),
            h_to: vec![NONE; 3 * nf],
            h_next: vec![NONE; 3 * nf],
            h_face: vec![NONE; 3 * nf],
            f_h: vec![NONE; nf],
            e_removed: vec![false; 3 * nf / 2],
            f_removed: vec![false; nf],
        };
        let mut half: HashMap<(u32, u32), u32> = HashMap::with_capacity(3 * nf);
        let mut next_edge = 0u32;
        for (f, &t) in mesh.faces.iter().enumerate() {
            let mut hs = [0u32; 3];
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let h = match half.get(&(b, a)) {
                    Some(&o) => o ^ 1,
                    None => {
                        let h = 2 * next_edge;
                        next_edge += 1;
                        h
                    }
                };
                half.insert((a, b), h);
                m.h_to[h as usize] = b;
                m.h_face[h as usize] = f as u32;
                m.v_out[a as usize] = h;
                m.v_removed[a as usize] = false;
                hs[k] = h;
            }
            for k in 0..3 {
                m.h_next[hs[k] as usize] = hs[(k + 1) % 3];
            }
            m.f_h[f] = hs[0];
        }
        m
    }

    /// The live part as an indexed mesh (vertices renumbered in order, removed elements dropped).
    pub fn to_trimesh(&self) -> TriMesh {
        let mut remap = vec![NONE; self.pos.len()];
        let mut positions = Vec::new();
        for (v, slot) in remap.iter_mut().enumerate() {
            if !self.v_removed[v] {
                *slot = positions.len() as u32;
                positions.push(self.pos[v]);
            }
        }
        let faces = (0..self.f_h.len())
            .filter(|&f| !self.f_removed[f])
            .map(|f| self.face_vertices(f as u32).map(|v| remap[v as usize]))
            .collect();
        TriMesh::new(positions, faces)
    }

    /// Drops removed elements, renumbering the rest in order. Returns, per old vertex slot and
    /// per old edge slot, the new id (`u32::MAX` for a removed one), so that data can follow.
    pub fn garbage_collect(&mut self) -> Compaction {
        fn renumber(removed: &[bool]) -> (Vec<u32>, usize) {
            let mut map = vec![NONE; removed.len()];
            let mut n = 0;
            for (i, &r) in removed.iter().enumerate() {
                if !r {
                    map[i] = n as u32;
                    n += 1;
                }
            }
            (map, n)
        }
        let (vmap, nv) = renumber(&self.v_removed);
        let (emap, ne) = renumber(&self.e_removed);
        let (fmap, nf) = renumber(&self.f_removed);
        let hmap = |h: u32| 2 * emap[(h / 2) as usize] + (h & 1);

        let mut pos = Vec::with_capacity(nv);
        let mut v_out = Vec::with_capacity(nv);
        for v in (0..self.pos.len()).filter(|&v| !self.v_removed[v]) {
            pos.push(self.pos[v]);
            v_out.push(hmap(self.v_out[v]));
        }
        let (mut h_to, mut h_next, mut h_face) = (
            Vec::with_capacity(2 * ne),
            Vec::with_capacity(2 * ne),
            Vec::with_capacity(2 * ne),
        );
        for e in (0..self.e_removed.len()).filter(|&e| !self.e_removed[e]) {
            for h in [2 * e, 2 * e + 1] {
                h_to.push(vmap[self.h_to[h] as usize]);
                h_next.push(hmap(self.h_next[h]));
                h_face.push(fmap[self.h_face[h] as usize]);
            }
        }
        let f_h = (0..self.f_h.len())
            .filter(|&f| !self.f_removed[f])
            .map(|f| hmap(self.f_h[f]))
            .collect();
        *self = Self {
            pos,
            v_out,
            h_to,
            h_next,
            h_face,
            f_h,
            v_removed: vec![false; nv],
            e_removed: vec![false; ne],
            f_removed: vec![false; nf],
        };
        Compaction {
            vertices: vmap,
            edges: emap,
        }
    }

    /// Number of edge slots (live or removed).
    pub fn edge_slots(&self) -> usize {
        self.e_removed.len()
    }

    /// Number of vertex slots (live or removed).
    pub fn vertex_slots(&self) -> usize {
        self.pos.len()
    }

    /// Number of face slots (live or removed).
    pub fn face_slots(&self) -> usize {
        self.f_h.len()
    }

    pub fn edge_removed(&self, e: u32) -> bool {
        self.e_removed[e as usize]
    }

    pub fn vertex_removed(&self, v: u32) -> bool {
        self.v_removed[v as usize]
    }

    pub fn face_removed(&self, f: u32) -> bool {
        self.f_removed[f as usize]
    }

    /// Target vertex of half-edge `h`.
    pub fn to(&self, h: u32) -> u32 {
        self.h_to[h as usize]
    }

    /// Origin vertex of half-edge `h`.
    pub fn from(&self, h: u32) -> u32 {
        self.h_to[(h ^ 1) as usize]
    }

    /// The face of half-edge `h`.
    pub fn face(&self, h: u32) -> u32 {
        self.h_face[h as usize]
    }

    pub fn next(&self, h: u32) -> u32 {
        self.h_next[h as usize]
    }

    pub fn prev(&self, h: u32) -> u32 {
        self.next(self.next(h))
    }

    /// The two vertices of edge `e`.
    pub fn edge_vertices(&self, e: u32) -> [u32; 2] {
        [self.from(2 * e), self.to(2 * e)]
    }

    /// Length of edge `e`, mm.
    pub fn edge_length(&self, e: u32) -> f64 {
        let [a, b] = self.edge_vertices(e);
        (self.pos[a as usize] - self.pos[b as usize]).norm()
    }

    /// The three vertices of face `f`, counter-clockwise.
    pub fn face_vertices(&self, f: u32) -> [u32; 3] {
        let h = self.f_h[f as usize];
        [self.from(h), self.to(h), self.to(self.next(h))]
    }

    /// (b − a) × (c − a) of face `f` (twice its area times its unit normal), mm².
    pub fn face_cross(&self, f: u32) -> Vector3<f64> {
        super::triangle_cross(&self.face_vertices(f).map(|v| self.pos[v as usize]))
    }

    /// Calls `visit` with every half-edge leaving `v`.
    pub fn for_each_outgoing(&self, v: u32, mut visit: impl FnMut(u32)) {
        let start = self.v_out[v as usize];
        let mut h = start;
        loop {
            visit(h);
            h = self.prev(h) ^ 1;
            if h == start {
                break;
            }
        }
    }

    /// Number of edges at `v`.
    pub fn valence(&self, v: u32) -> u32 {
        let mut n = 0;
        self.for_each_outgoing(v, |_| n += 1);
        n
    }

    /// Splits edge `e` at `p` (mm): the edge's two triangles become four around a new vertex.
    /// Returns the new vertex and the edge that continues `e` beyond it (`e` keeps the first
    /// half). Always valid on a closed mesh.
    pub fn split(&mut self, e: u32, p: Point3<f64>) -> (u32, u32) {
        let (h0, h1) = (2 * e, 2 * e + 1);
        let (h0n, h1n) = (self.next(h0), self.next(h1));
        let (h0p, h1p) = (self.next(h0n), self.next(h1n));
        let (b, c, d) = (self.to(h0), self.to(h0n), self.to(h1n));
        let (f0, f1) = (self.h_face[h0 as usize], self.h_face[h1 as usize]);

        let m = self.new_vertex(p);
        let (hmb, hmc, hmd) = (
            self.new_edge(m, b),
            self.new_edge(m, c),
            self.new_edge(m, d),
        );
        let (hbm, hcm, hdm) = (hmb ^ 1, hmc ^ 1, hmd ^ 1);
        let (f2, f3) = (self.new_face(), self.new_face());

        self.h_to[h0 as usize] = m;
        self.link_face(f0, [h0, hmc, h0p]);
        self.link_face(f2, [hmb, h0n, hcm]);
        self.link_face(f1, [h1, h1n, hdm]);
        self.link_face(f3, [hbm, hmd, h1p]);
        self.v_out[m as usize] = hmb;
        if self.v_out[b as usize] == h1 {
            self.v_out[b as usize] = hbm;
        }
        (m, hmb / 2)
    }

    /// Can edge `e` be flipped without breaking the topology: its new end points are not yet
    /// connected and both old end points keep a valence of at least 3.
    pub fn is_flip_ok(&self, e: u32) -> bool {
        let (h0, h1) = (2 * e, 2 * e + 1);
        let (a, b) = (self.to(h1), self.to(h0));
        let (c, d) = (self.to(self.next(h0)), self.to(self.next(h1)));
        if c == d || self.valence(a) <= 3 || self.valence(b) <= 3 {
            return false;
        }
        let mut connected = false;
        self.for_each_outgoing(c, |h| connected |= self.to(h) == d);
        !connected
    }

    /// Flips edge `e` (a–b between triangles abc and bad) to c–d. Check [`Self::is_flip_ok`] first.
    pub fn flip(&mut self, e: u32) {
        let (h0, h1) = (2 * e, 2 * e + 1);
        let (h0n, h1n) = (self.next(h0), self.next(h1));
        let (h0p, h1p) = (self.next(h0n), self.next(h1n));
        let (a, b) = (self.to(h1), self.to(h0));
        let (c, d) = (self.to(h0n), self.to(h1n));
        let (f0, f1) = (self.h_face[h0 as usize], self.h_face[h1 as usize]);
        self.h_to[h0 as usize] = c;
        self.h_to[h1 as usize] = d;
        self.link_face(f0, [h0, h0p, h1n]);
        self.link_face(f1, [h1, h1p, h0n]);
        if self.v_out[a as usize] == h0 {
            self.v_out[a as usize] = h1n;
        }
        if self.v_out[b as usize] == h1 {
            self.v_out[b as usize] = h0n;
        }
    }

    /// Can half-edge `h` (v0 → v1) be collapsed (v0 merged into v1) without breaking the
    /// topology? The link condition: the one-rings of v0 and v1 share exactly the two vertices
    /// opposite the edge. `stamp` is scratch space of one entry per vertex slot (any content).
    pub fn is_collapse_ok(&self, h: u32, stamp: &mut Vec<u32>) -> bool {
        let (v0, v1) = (self.from(h), self.to(h));
        let vl = self.to(self.next(h));
        let vr = self.to(self.next(h ^ 1));
        if vl == vr {
            return false;
        }
        stamp.resize(self.pos.len(), NONE);
        self.for_each_outgoing(v0, |g| stamp[self.to(g) as usize] = v0);
        let mut shared = 0;
        self.for_each_outgoing(v1, |g| {
            let w = self.to(g);
            if stamp[w as usize] == v0 && w != vl && w != vr {
                shared += 1;
            }
        });
        // Reset the marks (so a stale mark never matches a later v0 of the same id).
        self.for_each_outgoing(v0, |g| stamp[self.to(g) as usize] = NONE);
        shared == 0
    }

    /// Collapses half-edge `h` (v0 → v1): v0 and the edge's two triangles disappear, v1 keeps its
    /// position. In each of the two triangles, two edges merge into one: returned as
    /// (removed edge, edge that replaces it) pairs. Check [`Self::is_collapse_ok`] first.
    pub fn collapse(&mut self, h: u32) -> [(u32, u32); 2] {
        let o = h ^ 1;
        let (v0, v1) = (self.from(h), self.to(h));
        let (hn, on) = (self.next(h), self.next(o));
        let (hp, op) = (self.next(hn), self.next(on));
        let (vl, vr) = (self.to(hn), self.to(on));
        let (f0, f1) = (self.h_face[h as usize], self.h_face[o as usize]);

        // Every half-edge that ended at v0 now ends at v1.
        let mut incoming = Vec::with_capacity(8);
        self.for_each_outgoing(v0, |g| incoming.push(g ^ 1));
        for g in incoming {
            self.h_to[g as usize] = v1;
        }
        // Triangle f0 (v0 v1 vl) degenerates: edge hp (vl→v1 now) replaces edge hn's twin.
        self.replace_in_face(hn ^ 1, hp);
        // Triangle f1 (v1 v0 vr) degenerates: edge on (v1→vr now) replaces edge op's twin.
        self.replace_in_face(op ^ 1, on);

        if self.v_out[vl as usize] == hn ^ 1 {
            self.v_out[vl as usize] = hp;
        }
        if self.v_out[vr as usize] == op {
            self.v_out[vr as usize] = on ^ 1;
        }
        self.v_out[v1 as usize] = on;
        self.v_removed[v0 as usize] = true;
        self.f_removed[f0 as usize] = true;
        self.f_removed[f1 as usize] = true;
        for g in [h, hn, op] {
            self.e_removed[(g / 2) as usize] = true;
        }
        [(hn / 2, hp / 2), (op / 2, on / 2)]
    }

    /// Puts half-edge `new` in the place of `old` in `old`'s face.
    fn replace_in_face(&mut self, old: u32, new: u32) {
        let f = self.h_face[old as usize];
        let prev = self.prev(old);
        self.h_next[prev as usize] = new;
        self.h_next[new as usize] = self.next(old);
        self.h_face[new as usize] = f;
        if self.f_h[f as usize] == old {
            self.f_h[f as usize] = new;
        }
    }

    fn link_face(&mut self, f: u32, hs: [u32; 3]) {
        for k in 0..3 {
            self.h_next[hs[k] as usize] = hs[(k + 1) % 3];
            self.h_face[hs[k] as usize] = f;
        }
        self.f_h[f as usize] = hs[0];
    }

    fn new_vertex(&mut self, p: Point3<f64>) -> u32 {
        self.pos.push(p);
        self.v_out.push(NONE);
        self.v_removed.push(false);
        self.pos.len() as u32 - 1
    }

    /// A new edge a–b; returns its half-edge a → b (the twin is b → a).
    fn new_edge(&mut self, a: u32, b: u32) -> u32 {
        let h = self.h_to.len() as u32;
        self.h_to.extend([b, a]);
        self.h_next.extend([NONE, NONE]);
        self.h_face.extend([NONE, NONE]);
        self.e_removed.push(false);
        h
    }

    fn new_face(&mut self) -> u32 {
        self.f_h.push(NONE);
        self.f_removed.push(false);
        self.f_h.len() as u32 - 1
    }
}
