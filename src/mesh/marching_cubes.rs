//! Marching cubes over a block-sparse scalar field, watertight, manifold and outward-oriented by
//! construction.
//!
//! The case table is not typed in: it is derived once from one rule per cube face. A face whose
//! corners change sign twice gets one segment between its two crossing edges; a face with two
//! diagonal inside corners (the ambiguous case) gets two segments, each cutting off one inside
//! corner (inside corners touching only diagonally stay apart). Because two cubes sharing a face
//! apply the same rule to it, their surface boundaries on that face coincide. Each cube's
//! segments, oriented so the inside lies behind the surface, chain into closed loops; a loop is
//! triangulated as a fan when no fan diagonal lies on a cube face (so every mesh edge is either a
//! face segment, shared by exactly two cubes, or interior to one cube), else around an extra
//! centre vertex. Vertices sit on grid edges and are shared through a cache keyed by the edge.

use std::collections::HashMap;
use std::sync::OnceLock;

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::TriMesh;

/// A block of samples of a scalar field on a regular grid: `(b + 1)³` values (x fastest) for the
/// `b³` cells starting at grid point `corner`. A point is inside where its value is > 0.
#[derive(Clone, Debug)]
pub struct FieldBlock {
    pub corner: [usize; 3],
    pub values: Vec<f32>,
}

/// The regular grid: point (i, j, k) sits at `origin + step·(i, j, k)` (mm).
#[derive(Clone, Copy, Debug)]
pub struct Grid {
    pub origin: Point3<f64>,
    pub step: f64,
    /// Cells per block side.
    pub block: usize,
}

/// How one of the 256 sign cases is triangulated: vertex ids below 12 are cube edges, id
/// `12 + i` the centre of `centre_loops[i]` (cube edges).
#[derive(Clone, Debug, Default)]
struct Case {
    tris: Vec<[u8; 3]>,
    centre_loops: Vec<Vec<u8>>,
}

/// Corner `c` of the unit cube: bit 0 = x, bit 1 = y, bit 2 = z.
fn corner(c: usize) -> [usize; 3] {
    [c & 1, (c >> 1) & 1, (c >> 2) & 1]
}

/// Edge `e` = 4·axis + j runs along `axis` from the corner whose other two coordinates (in
/// increasing axis order) are the bits of j; returns its two corners (low, high along the axis).
fn edge_corners(e: usize) -> [usize; 2] {
    let axis = e / 4;
    let others: Vec<usize> = (0..3).filter(|&a| a != axis).collect();
    let low = ((e & 1) << others[0]) | (((e >> 1) & 1) << others[1]);
    [low, low | (1 << axis)]
}

fn edge_between(a: usize, b: usize) -> usize {
    (0..12)
        .find(|&e| {
            let [p, q] = edge_corners(e);
            (p, q) == (a, b) || (p, q) == (b, a)
        })
        .expect("corners of a face side are joined by an edge")
}

/// Face `f` = 2·axis + side: its corners in cyclic order.
fn face_corners(f: usize) -> [usize; 4] {
    let (axis, side) = (f / 2, f % 2);
    let o: Vec<usize> = (0..3).filter(|&a| a != axis).collect();
    let at = |u: usize, v: usize| (side << axis) | (u << o[0]) | (v << o[1]);
    [at(0, 0), at(1, 0), at(1, 1), at(0, 1)]
}

/// The two faces containing edge `e`.
fn edge_faces(e: usize) -> [usize; 2] {
    let [p, _] = edge_corners(e);
    let c = corner(p);
    let mut faces = (0..3).filter(|&a| a != e / 4).map(|a| 2 * a + c[a]);
    [faces.next().unwrap(), faces.next().unwrap()]
}

fn mid(e: usize) -> Vector3<f64> {
    let [p, q] = edge_corners(e);
    let (a, b) = (corner(p), corner(q));
    Vector3::from_fn(|i, _| (a[i] + b[i]) as f64 / 2.0)
}

fn pos(c: usize) -> Vector3<f64> {
    let a = corner(c);
    Vector3::new(a[0] as f64, a[1] as f64, a[2] as f64)
}

fn build_case(inside: u8) -> Case {
    let is_in = |c: usize| inside >> c & 1 == 1;
    // Oriented segments (from edge, to edge) on every face.
    let mut next = [usize::MAX; 12];
    for f in 0..6 {
        let cs = face_corners(f);
        let normal = {
            let mut n = Vector3::zeros();
            n[f / 2] = if f % 2 == 1 { 1.0 } else { -1.0 };
            n
        };
        let centre = cs.iter().map(|&c| pos(c)).sum::<Vector3<f64>>() / 4.0;
        let crossing: Vec<usize> = (0..4)
            .filter(|&i| is_in(cs[i]) != is_in(cs[(i + 1) % 4]))
            .collect();
        // Each segment: its two edges and the in-face direction from inside to outside.
        let segments: Vec<(usize, usize, Vector3<f64>)> = match crossing.len() {
            0 => vec![],
            2 => {
                let side = |want: bool| {
                    let pts: Vec<Vector3<f64>> = cs
                        .iter()
                        .filter(|&&c| is_in(c) == want)
                        .map(|&c| pos(c))
                        .collect();
                    pts.iter().sum::<Vector3<f64>>() / pts.len() as f64
                };
                let e = |i: usize| edge_between(cs[i], cs[(i + 1) % 4]);
                vec![(e(crossing[0]), e(crossing[1]), side(false) - side(true))]
            }
            _ => (0..4)
                .filter(|&i| is_in(cs[i]))
                .map(|i| {
                    let before = edge_between(cs[(i + 3) % 4], cs[i]);
                    let after = edge_between(cs[i], cs[(i + 1) % 4]);
                    (before, after, centre - pos(cs[i]))
                })
                .collect(),
        };
        for (a, b, m) in segments {
            let t = m.cross(&normal);
            let (from, to) = if (mid(b) - mid(a)).dot(&t) >= 0.0 {
                (a, b)
            } else {
                (b, a)
            };
            debug_assert_eq!(next[from], usize::MAX);
            next[from] = to;
        }
    }
    // Chain the segments into loops.
    let mut case = Case::default();
    let mut used = [false; 12];
    for start in 0..12 {
        if next[start] == usize::MAX || used[start] {
            continue;
        }
        let mut lp = vec![];
        let mut e = start;
        while !used[e] {
            used[e] = true;
            lp.push(e as u8);
            e = next[e];
        }
        triangulate(&lp, &mut case);
    }
    case
}

fn triangulate(lp: &[u8], case: &mut Case) {
    let n = lp.len();
    let share_face = |a: u8, b: u8| {
        let (fa, fb) = (edge_faces(a as usize), edge_faces(b as usize));
        fa.iter().any(|f| fb.contains(f))
    };
    let fan = (0..n).find(|&s| (2..n - 1).all(|i| !share_face(lp[s], lp[(s + i) % n])));
    match fan {
        Some(s) => {
            for i in 1..n - 1 {
                case.tris
                    .push([lp[s], lp[(s + i) % n], lp[(s + i + 1) % n]]);
            }
        }
        None => {
            let c = 12 + case.centre_loops.len() as u8;
            for i in 0..n {
                case.tris.push([c, lp[i], lp[(i + 1) % n]]);
            }
            case.centre_loops.push(lp.to_vec());
        }
    }
}

fn cases() -> &'static [Case] {
    static CASES: OnceLock<Vec<Case>> = OnceLock::new();
    CASES.get_or_init(|| (0..=255u8).map(build_case).collect())
}

/// A vertex of one block's output before merging: on a grid edge (global key) or a loop centre.
enum LocalVertex {
    Edge(u64, Point3<f64>),
    Centre(Point3<f64>),
}

/// Extracts the surface {value = 0} of the field given by `blocks` (points outside every block
/// are taken to agree with their block's neighbours: the caller must give every cell that
/// changes sign). Normals point to where the field is ≤ 0.
pub fn marching_cubes(grid: &Grid, blocks: &[FieldBlock]) -> TriMesh {
    let table = cases();
    let per_block: Vec<(Vec<LocalVertex>, Vec<[u32; 3]>)> = blocks
        .par_iter()
        .map(|blk| {
            let mut m = BlockMesher {
                grid,
                blk,
                verts: Vec::new(),
                tris: Vec::new(),
                edge_ids: HashMap::new(),
            };
            for k in 0..grid.block {
                for j in 0..grid.block {
                    for i in 0..grid.block {
                        m.cube([i, j, k], table);
                    }
                }
            }
            (m.verts, m.tris)
        })
        .collect();
    merge_blocks(per_block)
}

/// The surface of one block, with block-local vertex ids.
struct BlockMesher<'a> {
    grid: &'a Grid,
    blk: &'a FieldBlock,
    verts: Vec<LocalVertex>,
    tris: Vec<[u32; 3]>,
    /// Local id of the vertex on each grid edge (keyed as in [`LocalVertex::Edge`]).
    edge_ids: HashMap<u64, u32>,
}

impl BlockMesher<'_> {
    /// The field at local grid point `l`.
    fn value(&self, l: [usize; 3]) -> f32 {
        let n1 = self.grid.block + 1;
        self.blk.values[l[0] + n1 * (l[1] + n1 * l[2])]
    }

    /// Triangulates the cube whose low corner is local point `c`.
    fn cube(&mut self, c: [usize; 3], table: &[Case]) {
        let mut config = 0u8;
        for k in 0..8 {
            let o = corner(k);
            if self.value([c[0] + o[0], c[1] + o[1], c[2] + o[2]]) > 0.0 {
                config |= 1 << k;
            }
        }
        let case = &table[config as usize];
        if case.tris.is_empty() {
            return;
        }
        let mut ids = [u32::MAX; 16];
        for t in &case.tris {
            for &v in t {
                if v < 12 && ids[v as usize] == u32::MAX {
                    ids[v as usize] = self.edge_vertex(c, v as usize);
                }
            }
        }
        for (l, lp) in case.centre_loops.iter().enumerate() {
            let mut sum = Vector3::zeros();
            for &e in lp {
                let id = self.edge_vertex(c, e as usize);
                sum += match &self.verts[id as usize] {
                    LocalVertex::Edge(_, p) | LocalVertex::Centre(p) => p.coords,
                };
            }
            self.verts
                .push(LocalVertex::Centre(Point3::from(sum / lp.len() as f64)));
            ids[12 + l] = self.verts.len() as u32 - 1;
        }
        for t in &case.tris {
            self.tris.push(t.map(|v| ids[v as usize]));
        }
    }

    /// The vertex on edge `e` of the cube at local point `c` (made once per grid edge): where
    /// the field crosses zero along it, kept 1 % away from the edge's ends.
    fn edge_vertex(&mut self, c: [usize; 3], e: usize) -> u32 {
        let [p, q] = edge_corners(e);
        let (a, b) = (corner(p), corner(q));
        let la = [c[0] + a[0], c[1] + a[1], c[2] + a[2]];
        let lb = [c[0] + b[0], c[1] + b[1], c[2] + b[2]];
        let g = std::array::from_fn::<usize, 3, _>(|x| self.blk.corner[x] + la[x]);
        let key = ((((g[0] as u64) << 21 | g[1] as u64) << 21) | g[2] as u64) << 2 | (e / 4) as u64;
        if let Some(&id) = self.edge_ids.get(&key) {
            return id;
        }
        let (va, vb) = (self.value(la) as f64, self.value(lb) as f64);
        let t = (va / (va - vb)).clamp(0.01, 0.99);
        let step = self.grid.step;
        let mut pos = self.grid.origin + step * Vector3::from(g.map(|x| x as f64));
        pos[e / 4] += t * step;
        self.verts.push(LocalVertex::Edge(key, pos));
        let id = self.verts.len() as u32 - 1;
        self.edge_ids.insert(key, id);
        id
    }
}

/// One mesh from the blocks' surfaces: edge vertices shared between blocks through their keys.
fn merge_blocks(per_block: Vec<(Vec<LocalVertex>, Vec<[u32; 3]>)>) -> TriMesh {
    let mut positions = Vec::new();
    let mut faces = Vec::new();
    let mut global: HashMap<u64, u32> = HashMap::new();
    for (verts, tris) in per_block {
        let map: Vec<u32> = verts
            .into_iter()
            .map(|v| match v {
                LocalVertex::Edge(key, p) => *global.entry(key).or_insert_with(|| {
                    positions.push(p);
                    positions.len() as u32 - 1
                }),
                LocalVertex::Centre(p) => {
                    positions.push(p);
                    positions.len() as u32 - 1
                }
            })
            .collect();
        faces.extend(tris.into_iter().map(|t| t.map(|v| map[v as usize])));
    }
    TriMesh::new(positions, faces)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_case_closes_its_loops_and_faces_outward() {
        for config in 0..=255u8 {
            let case = &cases()[config as usize];
            let inside: Vec<Vector3<f64>> =
                (0..8).filter(|c| config >> c & 1 == 1).map(pos).collect();
            let outside: Vec<Vector3<f64>> =
                (0..8).filter(|c| config >> c & 1 == 0).map(pos).collect();
            assert_eq!(
                case.tris.is_empty(),
                inside.is_empty() || outside.is_empty()
            );
            if case.tris.is_empty() {
                continue;
            }
            // The summed area vector points from the inside corners to the outside ones.
            let at = |v: u8| {
                if v < 12 {
                    mid(v as usize)
                } else {
                    let lp = &case.centre_loops[v as usize - 12];
                    lp.iter().map(|&e| mid(e as usize)).sum::<Vector3<f64>>() / lp.len() as f64
                }
            };
            let area: Vector3<f64> = case
                .tris
                .iter()
                .map(|t| (at(t[1]) - at(t[0])).cross(&(at(t[2]) - at(t[0]))))
                .sum();
            let ci = inside.iter().sum::<Vector3<f64>>() / inside.len() as f64;
            let co = outside.iter().sum::<Vector3<f64>>() / outside.len() as f64;
            if (co - ci).norm() > 1e-9 {
                assert!(area.dot(&(co - ci)) > 0.0, "case {config:08b}");
            }
        }
    }
}
