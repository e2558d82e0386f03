//! Indexed triangle meshes: the data type, file I/O, validation, statistics, sampling and the
//! analytic test shapes.
//!
//! Positions are in millimetres (f64) in whatever frame the file uses (glasscan: the object /
//! turntable frame, y up). Faces are counter-clockwise seen from outside, so that the right-hand
//! normal points out of the object.

pub mod components;
pub mod halfedge;
pub mod io;
pub mod marching_cubes;
pub mod sample;
pub mod shapes;
pub mod stats;
pub mod validate;

use nalgebra::{Point3, Vector3};

/// An indexed triangle mesh with f64 positions (mm).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    /// Vertex positions, mm.
    pub positions: Vec<Point3<f64>>,
    /// Triangles as indices into `positions`, counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
}

/// An edge shared by two faces: its vertices and the faces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InteriorEdge {
    pub verts: [u32; 2],
    pub faces: [u32; 2],
}

impl TriMesh {
    /// Every edge with exactly two faces (all edges of a closed manifold mesh), sorted by vertices.
    pub fn interior_edges(&self) -> Vec<InteriorEdge> {
        let mut half: Vec<(u32, u32, u32)> = Vec::with_capacity(3 * self.faces.len());
        for (f, t) in self.faces.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                half.push((a.min(b), a.max(b), f as u32));
            }
        }
        half.sort_unstable();
        let same = |a: Option<&(u32, u32, u32)>, b: &(u32, u32, u32)| {
            a.is_some_and(|a| (a.0, a.1) == (b.0, b.1))
        };
        (0..half.len().saturating_sub(1))
            .filter(|&i| {
                same(Some(&half[i]), &half[i + 1])
                    && (i == 0 || !same(Some(&half[i - 1]), &half[i]))
                    && !same(half.get(i + 2), &half[i])
            })
            .map(|i| InteriorEdge {
                verts: [half[i].0, half[i].1],
                faces: [half[i].2, half[i + 1].2],
            })
            .collect()
    }

    /// A mesh from positions and faces; the caller guarantees that indices are in range
    /// (file readers check it and report the offending face).
    pub fn new(positions: Vec<Point3<f64>>, faces: Vec<[u32; 3]>) -> Self {
        Self { positions, faces }
    }

    /// The three corner positions of face `f`.
    pub fn corners(&self, f: usize) -> [Point3<f64>; 3] {
        let [a, b, c] = self.faces[f];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// Area-weighted normal of face `f`: [`triangle_cross`] of its corners.
    pub fn face_cross(&self, f: usize) -> Vector3<f64> {
        triangle_cross(&self.corners(f))
    }

    /// Area of face `f`, mm².
    pub fn face_area(&self, f: usize) -> f64 {
        0.5 * self.face_cross(f).norm()
    }

    /// Axis-aligned bounding box (min, max) of the vertices, mm; `None` for an empty mesh.
    pub fn bbox(&self) -> Option<(Point3<f64>, Point3<f64>)> {
        let first = *self.positions.first()?;
        Some(
            self.positions
                .iter()
                .fold((first, first), |(lo, hi), p| (lo.inf(p), hi.sup(p))),
        )
    }

    /// Length of the bounding-box diagonal, mm (0 for an empty mesh).
    pub fn bbox_diagonal(&self) -> f64 {
        self.bbox().map_or(0.0, |(lo, hi)| (hi - lo).norm())
    }

    /// Mean length of the faces' edges, mm (each edge of a closed mesh counted once per face, so
    /// as often as any other; 0 for a mesh without faces). On a closed mesh it equals
    /// [`stats::edge_lengths`]'s mean without listing the unique edges, cheap enough for every
    /// iteration.
    pub fn mean_edge_length(&self) -> f64 {
        let total: f64 = (0..self.faces.len())
            .map(|f| {
                let [a, b, c] = self.corners(f);
                (b - a).norm() + (c - b).norm() + (a - c).norm()
            })
            .sum();
        if self.faces.is_empty() {
            0.0
        } else {
            total / (3 * self.faces.len()) as f64
        }
    }

    /// Per vertex, a third of its faces' area, mm² (they sum to the mesh's area).
    pub fn vertex_areas(&self) -> Vec<f64> {
        let mut area = vec![0.0; self.positions.len()];
        for (f, face) in self.faces.iter().enumerate() {
            let third = self.face_area(f) / 3.0;
            for &v in face {
                area[v as usize] += third;
            }
        }
        area
    }

    /// Total surface area, mm².
    pub fn area(&self) -> f64 {
        (0..self.faces.len()).map(|f| self.face_area(f)).sum()
    }

    /// Signed enclosed volume, mm³ (divergence theorem); positive for a closed, outward-oriented
    /// mesh.
    pub fn signed_volume(&self) -> f64 {
        (0..self.faces.len())
            .map(|f| {
                let [a, b, c] = self.corners(f);
                a.coords.dot(&b.coords.cross(&c.coords)) / 6.0
            })
            .sum()
    }

    /// Area-weighted vertex normals (unit; zero for a vertex whose faces all have zero area, or
    /// that no face uses).
    pub fn vertex_normals(&self) -> Vec<Vector3<f64>> {
        let mut n = vec![Vector3::zeros(); self.positions.len()];
        for (f, t) in self.faces.iter().enumerate() {
            let c = self.face_cross(f);
            for &v in t {
                n[v as usize] += c;
            }
        }
        n.into_iter()
            .map(|v| v.try_normalize(0.0).unwrap_or_else(Vector3::zeros))
            .collect()
    }

    /// Per vertex, the largest angle between its normal ([`Self::vertex_normals`]) and the
    /// normals of its faces, radians: about half the bend of a crease through the vertex, and a
    /// fraction of (edge length / radius) on a smooth surface. 0 for a vertex that no face of
    /// non-zero area uses.
    pub fn normal_spread(&self) -> Vec<f64> {
        let normals = self.vertex_normals();
        let mut spread = vec![0.0f64; self.positions.len()];
        for (f, t) in self.faces.iter().enumerate() {
            let Some(n) = self.face_cross(f).try_normalize(0.0) else {
                continue;
            };
            for &v in t {
                let angle = n.dot(&normals[v as usize]).clamp(-1.0, 1.0).acos();
                spread[v as usize] = spread[v as usize].max(angle);
            }
        }
        spread
    }

    /// Vertex positions as packed f32 triples (Embree's vertex buffer format).
    pub fn positions_f32(&self) -> Vec<f32> {
        self.positions
            .iter()
            .flat_map(|p| [p.x as f32, p.y as f32, p.z as f32])
            .collect()
    }

    /// Applies `x ↦ s·x + t` to every vertex (mm).
    pub fn scale_translate(&mut self, s: f64, t: Vector3<f64>) {
        for p in &mut self.positions {
            *p = Point3::from(p.coords * s + t);
        }
    }
}

/// Area-weighted normal of the triangle (a, b, c): (b − a) × (c − a), length = 2 × area (mm²).
pub fn triangle_cross([a, b, c]: &[Point3<f64>; 3]) -> Vector3<f64> {
    (b - a).cross(&(c - a))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mean_edge_counts_every_edge_of_a_closed_mesh_alike() {
        // A corner tetrahedron: three edges of 1 mm and three of √2 mm, each in two faces.
        let p = |x, y, z| Point3::new(x, y, z);
        let tetra = TriMesh::new(
            vec![p(0., 0., 0.), p(1., 0., 0.), p(0., 1., 0.), p(0., 0., 1.)],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        );
        let expected = (3.0 + 3.0 * 2f64.sqrt()) / 6.0;
        assert!((tetra.mean_edge_length() - expected).abs() < 1e-15);
        // On any closed mesh it is the mean over the unique edges.
        let sphere = shapes::icosphere(10.0, 3);
        let unique = stats::edge_lengths(&sphere).mean_mm;
        assert!((sphere.mean_edge_length() - unique).abs() < 1e-12 * unique);
        assert_eq!(TriMesh::new(vec![], vec![]).mean_edge_length(), 0.0);
    }

    /// A box's vertices on its edges and corners spread by about half a right angle or more, the
    /// ones inside its sides not at all; a 10 mm sphere's (edges of about 1.3 mm) by less than
    /// 15°.
    #[test]
    fn the_normal_spread_tells_a_box_s_edges_from_its_sides_and_from_a_sphere() {
        let cube = shapes::cuboid(Vector3::new(10.0, 10.0, 10.0), 4);
        let spread = cube.normal_spread();
        for (p, s) in cube.positions.iter().zip(&spread) {
            let on_edge = p.iter().filter(|c| (c.abs() - 5.0).abs() < 1e-9).count() >= 2;
            if on_edge {
                assert!(*s > 40f64.to_radians(), "{p}: {}°", s.to_degrees());
            } else {
                assert!(*s < 1e-9, "{p}: {}°", s.to_degrees());
            }
        }
        let sphere = shapes::icosphere(10.0, 3);
        let widest = sphere.normal_spread().into_iter().fold(0.0, f64::max);
        assert!(widest < 15f64.to_radians(), "{}°", widest.to_degrees());
    }
}
