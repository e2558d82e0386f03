//! Uniform random sampling of a mesh surface by area, seeded and reproducible.

use nalgebra::Point3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::TriMesh;

/// `n` points distributed uniformly by area over the surface of `mesh` (mm), with the face each
/// lies on. The same `seed` gives the same points. Returns nothing for a mesh of zero area.
pub fn sample_surface(mesh: &TriMesh, n: usize, seed: u64) -> Vec<(Point3<f64>, u32)> {
    let mut cdf = Vec::with_capacity(mesh.faces.len());
    let mut total = 0.0;
    for f in 0..mesh.faces.len() {
        total += mesh.face_area(f);
        cdf.push(total);
    }
    if total.is_nan() || total <= 0.0 {
        return Vec::new();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let x = rng.random::<f64>() * total;
            let f = cdf.partition_point(|&c| c <= x).min(cdf.len() - 1);
            // Uniform point in a triangle (Osada et al. 2002).
            let (r1, r2) = (rng.random::<f64>().sqrt(), rng.random::<f64>());
            let [a, b, c] = mesh.corners(f);
            let p = a.coords * (1.0 - r1) + b.coords * (r1 * (1.0 - r2)) + c.coords * (r1 * r2);
            (Point3::from(p), f as u32)
        })
        .collect()
}
