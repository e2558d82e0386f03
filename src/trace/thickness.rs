//! Local thickness of a closed mesh: at each face, the distance from its centroid along the
//! inward normal to the opposite side (the shape diameter along one ray), mm. A tail or a leg
//! a few millimetres across shows up as the thin end of the area-weighted distribution.

use super::embree::{BuildMode, Device, Ray, Scene, TraceError};
use crate::mesh::TriMesh;

/// The thickness below which `share` of the surface area lies (mm): e.g. `share = 0.02` is the
/// thickness of the thinnest 2 % of the surface. `None` when no inward ray meets the far side
/// (an open or inside-out mesh). `mesh` must be closed and outward-oriented.
pub fn thickness_quantile(mesh: &TriMesh, share: f64) -> Result<Option<f64>, TraceError> {
    Ok(thickness_quantiles(mesh, &[share])?[0])
}

/// [`thickness_quantile`] for each of `shares`, from one set of rays.
pub fn thickness_quantiles(mesh: &TriMesh, shares: &[f64]) -> Result<Vec<Option<f64>>, TraceError> {
    let mut samples = face_thicknesses(mesh)?;
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = samples.iter().map(|s| s.1).sum();
    let quantile = |share: f64| {
        let mut below = 0.0;
        samples
            .iter()
            .find(|(_, area)| {
                below += area;
                below >= share * total
            })
            .or(samples.last())
            .map(|s| s.0)
    };
    Ok(shares.iter().map(|&share| quantile(share)).collect())
}

/// (thickness mm, face area mm²) of every face whose inward ray meets the mesh again.
fn face_thicknesses(mesh: &TriMesh) -> Result<Vec<(f64, f64)>, TraceError> {
    let scene = Scene::new(&Device::new()?, mesh, BuildMode::Static)?;
    // Starts each ray just inside its face: clear of the face itself at Embree's f32 precision.
    let start = 1e-5 * mesh.bbox_diagonal().max(f64::MIN_POSITIVE);
    let (rays, areas): (Vec<Ray>, Vec<f64>) = (0..mesh.faces.len())
        .filter_map(|f| {
            let cross = mesh.face_cross(f);
            let norm = cross.norm();
            (norm > 0.0).then(|| {
                let inward = -cross / norm;
                let [a, b, c] = mesh.corners(f);
                let centroid = (a.coords + b.coords + c.coords) / 3.0;
                (
                    Ray::new((centroid + inward * start).into(), inward),
                    0.5 * norm,
                )
            })
        })
        .unzip();
    let hits = scene.intersect(&rays, false)?;
    Ok(hits
        .iter()
        .zip(areas)
        .filter_map(|(h, area)| h.map(|h| (h.t + start, area)))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::shapes::{cuboid, icosphere};
    use nalgebra::Vector3;

    #[test]
    fn a_sphere_is_its_diameter_thick() {
        let sphere = icosphere(10.0, 4);
        let thin = thickness_quantile(&sphere, 0.02).unwrap().unwrap();
        let median = thickness_quantile(&sphere, 0.5).unwrap().unwrap();
        // Face centroids lie slightly inside the sphere and face normals point at its centre.
        assert!((19.5..=20.0).contains(&thin), "{thin}");
        assert!((19.5..=20.0).contains(&median), "{median}");
    }

    #[test]
    fn a_slab_is_thin_where_its_faces_are_large() {
        // 40 × 40 × 2 mm: the two large faces hold 2 · 1600 of 3520 mm², so 0.8 of the area is
        // 2 mm thick and the 40 mm sides are the rest.
        let slab = cuboid(Vector3::new(40.0, 40.0, 2.0), 8);
        let thin = thickness_quantile(&slab, 0.5).unwrap().unwrap();
        let thick = thickness_quantile(&slab, 0.99).unwrap().unwrap();
        assert!((thin - 2.0).abs() < 1e-6, "{thin}");
        assert!((thick - 40.0).abs() < 1e-6, "{thick}");
    }
}
