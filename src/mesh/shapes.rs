//! Analytic test shapes (closed, manifold, outward-oriented), centred on the origin, in mm, with
//! +y as the turntable axis. Tests, benchmarks and the demo build their objects from these.

use std::collections::HashMap;

use nalgebra::{Point3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::TriMesh;

/// A sphere of `radius` mm: an icosahedron subdivided `subdivisions` times (20·4^s faces).
pub fn icosphere(radius: f64, subdivisions: u32) -> TriMesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut pos: Vec<Vector3<f64>> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|p| Vector3::from(*p).normalize())
    .collect();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut midpoint = |a: u32, b: u32, pos: &mut Vec<Vector3<f64>>| {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                pos.push((pos[a as usize] + pos[b as usize]).normalize());
                pos.len() as u32 - 1
            })
        };
        let mut next = Vec::with_capacity(faces.len() * 4);
        for [a, b, c] in faces {
            let ab = midpoint(a, b, &mut pos);
            let bc = midpoint(b, c, &mut pos);
            let ca = midpoint(c, a, &mut pos);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        faces = next;
    }
    TriMesh::new(
        pos.into_iter().map(|p| Point3::from(p * radius)).collect(),
        faces,
    )
}

/// An ellipsoid with semi-axes `radii` (mm) along x, y, z, tessellated like [`icosphere`].
pub fn ellipsoid(radii: Vector3<f64>, subdivisions: u32) -> TriMesh {
    let mut m = icosphere(1.0, subdivisions);
    for p in &mut m.positions {
        *p = Point3::from(p.coords.component_mul(&radii));
    }
    m
}

/// A torus around the y axis: tube centre-line radius `major` mm, tube radius `minor` mm,
/// `n_major` × `n_minor` quads split into triangles. Genus 1.
pub fn torus(major: f64, minor: f64, n_major: u32, n_minor: u32) -> TriMesh {
    let mut positions = Vec::with_capacity((n_major * n_minor) as usize);
    for i in 0..n_major {
        let u = std::f64::consts::TAU * i as f64 / n_major as f64;
        for j in 0..n_minor {
            let v = std::f64::consts::TAU * j as f64 / n_minor as f64;
            let r = major + minor * v.cos();
            positions.push(Point3::new(r * u.cos(), minor * v.sin(), r * u.sin()));
        }
    }
    let id = |i: u32, j: u32| (i % n_major) * n_minor + (j % n_minor);
    let mut faces = Vec::with_capacity(2 * positions.len());
    for i in 0..n_major {
        for j in 0..n_minor {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            faces.push([a, c, b]);
            faces.push([a, d, c]);
        }
    }
    TriMesh::new(positions, faces)
}

/// An axis-aligned box of edge lengths `size` (mm), each side split into `n` × `n` quads.
pub fn cuboid(size: Vector3<f64>, n: u32) -> TriMesh {
    let mut index: HashMap<[u32; 3], u32> = HashMap::new();
    let mut positions = Vec::new();
    let mut faces = Vec::new();
    let mut vertex = |g: [u32; 3], positions: &mut Vec<Point3<f64>>| {
        *index.entry(g).or_insert_with(|| {
            let p = Vector3::from(g.map(|c| c as f64 / n as f64 - 0.5));
            positions.push(Point3::from(p.component_mul(&size)));
            positions.len() as u32 - 1
        })
    };
    // Each side: the fixed axis, its grid coordinate, and the two in-plane axes ordered so that
    // (a × b) points outward.
    for axis in 0..3 {
        for &(fixed, outward) in &[(0u32, false), (n, true)] {
            let (mut a, mut b) = ((axis + 1) % 3, (axis + 2) % 3);
            if !outward {
                std::mem::swap(&mut a, &mut b);
            }
            for i in 0..n {
                for j in 0..n {
                    let corner = |di: u32, dj: u32| {
                        let mut g = [0u32; 3];
                        g[axis] = fixed;
                        g[a] = i + di;
                        g[b] = j + dj;
                        g
                    };
                    let v00 = vertex(corner(0, 0), &mut positions);
                    let v10 = vertex(corner(1, 0), &mut positions);
                    let v11 = vertex(corner(1, 1), &mut positions);
                    let v01 = vertex(corner(0, 1), &mut positions);
                    faces.push([v00, v10, v11]);
                    faces.push([v00, v11, v01]);
                }
            }
        }
    }
    TriMesh::new(positions, faces)
}

/// Moves every vertex radially (from the origin) by a uniform random factor in
/// [1 − amplitude, 1 + amplitude]; seeded.
pub fn perturb_radially(mesh: &mut TriMesh, amplitude: f64, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for p in &mut mesh.positions {
        let s = 1.0 + amplitude * (2.0 * rng.random::<f64>() - 1.0);
        *p = Point3::from(p.coords * s);
    }
}

/// The surface {field > 0} of a scalar field over the box [`lo`, `hi`] (mm), sampled every
/// `step` mm and extracted by marching cubes (closed, manifold, outward): an organic mesh with
/// the irregular triangles of a scanned or carved surface. The field must be ≤ 0 on the box's
/// boundary.
pub fn implicit_surface<F>(field: F, lo: Point3<f64>, hi: Point3<f64>, step: f64) -> TriMesh
where
    F: Fn(Point3<f64>) -> f64 + Sync,
{
    use super::marching_cubes::{marching_cubes, FieldBlock, Grid};
    use rayon::prelude::*;
    let cells = ((hi - lo) / step).map(|c| c.ceil().max(1.0) as usize).max();
    let n1 = cells + 1;
    let grid = Grid {
        origin: lo,
        step,
        block: cells,
    };
    let values: Vec<f32> = (0..n1 * n1 * n1)
        .into_par_iter()
        .map(|i| {
            let g = Vector3::new(i % n1, (i / n1) % n1, i / (n1 * n1)).map(|c| c as f64);
            // f32 can round a tiny positive value to 0, which reads as outside: harmless.
            field(lo + g * step) as f32
        })
        .collect();
    marching_cubes(
        &grid,
        &[FieldBlock {
            corner: [0, 0, 0],
            values,
        }],
    )
}

/// Signed "inside" value of an ellipsoid centred at `c` with semi-axes `r` (mm): positive inside,
/// about the distance to the surface near it.
fn ellipsoid_field(p: Point3<f64>, c: Point3<f64>, r: Vector3<f64>) -> f64 {
    let q = (p - c).component_div(&r);
    (1.0 - q.norm()) * r.min()
}

/// Smooth union of two inside values (polynomial smooth maximum over a blend width `k` mm).
fn smooth_union(a: f64, b: f64, k: f64) -> f64 {
    let h = (0.5 + 0.5 * (a - b) / k).clamp(0.0, 1.0);
    b + (a - b) * h + k * h * (1.0 - h)
}

/// A glass figurine of genus 1, about 110 × 90 × 55 mm, standing on the turntable (+y up,
/// centred on the axis): an ellipsoid body, a head, four legs with gaps between them (concave
/// regions no silhouette shows), and a looped tail (the handle). Built by
/// [`implicit_surface`] every `step` mm, so its triangles look like a scanned mesh's; tests use
/// it where a real scan would stand.
pub fn figurine(step: f64) -> TriMesh {
    let field = |p: Point3<f64>| {
        let mut v = ellipsoid_field(
            p,
            Point3::new(0.0, 5.0, 0.0),
            Vector3::new(40.0, 22.0, 22.0),
        );
        v = smooth_union(
            v,
            ellipsoid_field(
                p,
                Point3::new(40.0, 18.0, 0.0),
                Vector3::new(15.0, 14.0, 13.0),
            ),
            4.0,
        );
        for (x, z) in [(-24.0, -11.0), (-24.0, 11.0), (24.0, -11.0), (24.0, 11.0)] {
            let leg = ellipsoid_field(p, Point3::new(x, -22.0, z), Vector3::new(6.5, 22.0, 6.5));
            v = smooth_union(v, leg, 3.0);
        }
        // The tail: a ring in the xy-plane, half inside the body.
        let c = Point3::new(-44.0, 12.0, 0.0);
        let d = p - c;
        let ring = (Vector3::new(d.x, d.y, 0.0).norm() - 9.0).hypot(d.z);
        smooth_union(v, 3.0 - ring, 1.5)
    };
    implicit_surface(
        field,
        Point3::new(-60.0, -48.0, -30.0),
        Point3::new(60.0, 40.0, 30.0),
        step,
    )
}

/// The built-in object: an ellipsoid with three smooth lobes around the vertical axis and a
/// dimple in its front face (which no silhouette shows), mm.
pub fn pebble() -> TriMesh {
    let mut object = ellipsoid(Vector3::new(40.0, 30.0, 25.0), 5);
    for p in &mut object.positions {
        // Smooth lobes around the vertical axis, fading towards the poles.
        let lobe = 1.0 + 0.08 * (3.0 * p.z.atan2(p.x)).sin() * (1.0 - (p.y / 30.0).powi(2));
        p.x *= lobe;
        p.z *= lobe;
        // A dimple in the front face.
        if p.z > 0.0 {
            p.z *= 1.0 - 0.3 * (-(p.x * p.x + p.y * p.y) / 225.0).exp();
        }
    }
    object
}

/// Signed "inside" value of a box centred at `c` with half-sizes `half` (mm), its edges and
/// corners rounded with radius `r`: positive inside, the distance to the surface (exact).
fn rounded_box_field(p: Point3<f64>, c: Point3<f64>, half: Vector3<f64>, r: f64) -> f64 {
    let q = (p - c).abs() - half.add_scalar(-r);
    let outside = q.map(|x| x.max(0.0)).norm();
    r - outside - q.max().min(0.0)
}

/// A glass block on a plinth, +y up and centred on the turntable axis, mm: a 100 × 50 × 40 mm
/// block with 3 mm rounded edges standing on a 120 × 15 × 60 mm plinth with 2 mm rounded
/// edges. Its large flat, parallel faces are where refraction constrains position least (a ray
/// through two parallel faces leaves parallel to itself whatever their distance). Built by
/// [`implicit_surface`] every `step` mm.
pub fn glass_block(step: f64) -> TriMesh {
    let field = |p: Point3<f64>| {
        let block = rounded_box_field(
            p,
            Point3::new(0.0, 10.0, 0.0),
            Vector3::new(50.0, 25.0, 20.0),
            3.0,
        );
        let plinth = rounded_box_field(
            p,
            Point3::new(0.0, -22.5, 0.0),
            Vector3::new(60.0, 7.5, 30.0),
            2.0,
        );
        block.max(plinth)
    };
    // The grid is offset from the faces' planes, so no sample lands on a face (marching cubes
    // then places every vertex of a flat part on its plane).
    let lo = Point3::new(-64.37, -34.37, -34.37);
    implicit_surface(field, lo, lo + Vector3::repeat(128.0), step)
}

/// A cut glass prism, +y up and centred on the turntable axis, mm: a 45 mm tall prism over a
/// 70 × 35 mm rectangle whose four vertical edges are cut by 6 mm chamfers (an octagon), every
/// edge sharp. Flat facets only (32 triangles): simulate it with face normals.
pub fn cut_prism() -> TriMesh {
    let (a, b, c, h) = (35.0, 17.5, 6.0, 22.5);
    // The octagon's corners in the (x, z) plane, by increasing angle from +x towards +z:
    // clockwise seen from +y, so the top's triangles take them in reverse.
    let outline = [
        (a, b - c),
        (a - c, b),
        (c - a, b),
        (-a, b - c),
        (-a, c - b),
        (c - a, -b),
        (a - c, -b),
        (a, c - b),
    ];
    let mut positions: Vec<Point3<f64>> = Vec::with_capacity(18);
    for y in [h, -h] {
        positions.extend(outline.iter().map(|&(x, z)| Point3::new(x, y, z)));
    }
    positions.push(Point3::new(0.0, h, 0.0));
    positions.push(Point3::new(0.0, -h, 0.0));
    let (n, top, bottom) = (8u32, 16u32, 17u32);
    let mut faces = Vec::with_capacity(32);
    for i in 0..n {
        let j = (i + 1) % n;
        faces.push([top, j, i]);
        faces.push([bottom, n + i, n + j]);
        faces.push([i, j, n + j]);
        faces.push([i, n + j, n + i]);
    }
    TriMesh::new(positions, faces)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Volume of a box of sides `s` with edges and corners rounded by `r`, mm³.
    fn rounded_box_volume(s: [f64; 3], r: f64) -> f64 {
        let [a, b, c] = s.map(|x| x - 2.0 * r);
        a * b * c
            + 2.0 * r * (a * b + b * c + a * c)
            + std::f64::consts::PI * r * r * (a + b + c)
            + 4.0 / 3.0 * std::f64::consts::PI * r.powi(3)
    }

    #[test]
    fn the_cut_prism_is_a_valid_solid_of_the_octagon_s_volume() {
        let mesh = cut_prism();
        crate::mesh::validate::ensure_valid(&mesh).unwrap();
        let octagon = 70.0 * 35.0 - 2.0 * 6.0 * 6.0;
        assert!((mesh.signed_volume() - 45.0 * octagon).abs() < 1e-9);
    }

    #[test]
    fn the_glass_block_is_a_valid_solid_with_flat_parallel_faces() {
        let mesh = glass_block(1.0);
        crate::mesh::validate::ensure_valid(&mesh).unwrap();
        let truth = rounded_box_volume([100.0, 50.0, 40.0], 3.0)
            + rounded_box_volume([120.0, 15.0, 60.0], 2.0);
        let v = mesh.signed_volume();
        assert!((v / truth - 1.0).abs() < 0.01, "volume {v} against {truth}");
        // The block's front and back faces: every vertex within their flat parts lies on the
        // planes z = ±20 mm.
        let flat = |p: &&Point3<f64>| p.x.abs() < 45.0 && p.y > -10.0 && p.y < 30.0;
        let mut on_faces = [0, 0];
        for p in mesh
            .positions
            .iter()
            .filter(flat)
            .filter(|p| p.z.abs() >= 19.0)
        {
            let off = (p.z.abs() - 20.0).abs();
            assert!(off < 1e-4, "vertex {p} is {off} mm off its face");
            on_faces[(p.z > 0.0) as usize] += 1;
        }
        assert!(on_faces.iter().all(|&n| n > 1000), "{on_faces:?}");
    }
}
