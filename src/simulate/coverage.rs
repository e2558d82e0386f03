//! The true coverage of each camera pixel: the share of its area whose camera rays meet the
//! object, measured on a grid of sub-pixel rays where the silhouette's outline crosses the pixel.
//! The centre-ray mask puts a straight outline on the lines between pixel centres, up to half a
//! pixel off; an edge that keeps its place in the image from view to view (the top of an
//! object on a turntable) keeps that error in every view, so the decoded outline's sub-pixel
//! offset is measured against this instead (`decode --compare-ground-truth`).

use rayon::prelude::*;

use super::render::ViewSetup;
use crate::trace::path::Surface;
use crate::trace::{Ray, TraceError};

/// Sub-pixel rays per side of a pixel whose coverage is measured: its share is known to
/// 1/`COVERAGE_SIDE`² (the rays at the centres of a `COVERAGE_SIDE` × `COVERAGE_SIDE` grid).
pub const COVERAGE_SIDE: u32 = 8;

/// Pixels measured per batch of rays (`COVERAGE_SIDE`² rays each), on one thread.
const BATCH_PIXELS: usize = 256;

/// Per pixel of the view (row-major), the share of its area whose camera rays meet the object:
/// measured on the sub-pixel grid for the pixels whose centre ray's outcome (`centre_hit`) differs
/// from one of its 8 neighbours' — every pixel an outline crosses, but for features thinner than
/// a pixel that no centre ray meets — and 0 or 1 from the centre ray elsewhere (everywhere
/// without a surface: no centre ray then meets an object).
pub fn true_coverage(v: &ViewSetup, centre_hit: &[bool]) -> Result<Vec<f32>, TraceError> {
    let (w, h) = (v.camera.width as usize, v.camera.height as usize);
    let mut coverage: Vec<f32> = centre_hit.iter().map(|&c| f32::from(u8::from(c))).collect();
    let Some(surface) = v.surface else {
        return Ok(coverage);
    };
    let outline: Vec<usize> = (0..w * h)
        .filter(|&i| crosses_outline(i, w, h, centre_hit))
        .collect();
    let shares = outline
        .par_chunks(BATCH_PIXELS)
        .map(|pixels| measured_shares(v, surface, pixels, w))
        .collect::<Result<Vec<Vec<f32>>, TraceError>>()?;
    for (&i, share) in outline.iter().zip(shares.into_iter().flatten()) {
        coverage[i] = share;
    }
    Ok(coverage)
}

/// Whether pixel `i` of a `w` × `h` image has an 8-neighbour whose centre ray's outcome differs.
fn crosses_outline(i: usize, w: usize, h: usize, hit: &[bool]) -> bool {
    let (x, y) = ((i % w) as i64, (i / w) as i64);
    (-1..=1).any(|dy| {
        (-1..=1).any(|dx| {
            let (nx, ny) = (x + dx, y + dy);
            (0..w as i64).contains(&nx)
                && (0..h as i64).contains(&ny)
                && hit[ny as usize * w + nx as usize] != hit[i]
        })
    })
}

/// The measured shares of `pixels` (row-major indices, image `w` wide), in order.
fn measured_shares(
    v: &ViewSetup,
    surface: &dyn Surface,
    pixels: &[usize],
    w: usize,
) -> Result<Vec<f32>, TraceError> {
    let per_pixel = (COVERAGE_SIDE * COVERAGE_SIDE) as usize;
    let to_world = v.pose.inverse();
    let eye = to_world * nalgebra::Point3::origin();
    let grid = |k: u32| (f64::from(k) + 0.5) / f64::from(COVERAGE_SIDE) - 0.5;
    // Sub-pixel rays the lens model has none for count as missing the object.
    let rays: Vec<Option<Ray>> = pixels
        .iter()
        .flat_map(|&i| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            (0..COVERAGE_SIDE * COVERAGE_SIDE).map(move |k| {
                let (dx, dy) = (grid(k % COVERAGE_SIDE), grid(k / COVERAGE_SIDE));
                v.camera
                    .pixel_ray(x + dx, y + dy)
                    .map(|d| Ray::new(eye, to_world * d))
            })
        })
        .collect();
    let traced: Vec<Ray> = rays.iter().flatten().copied().collect();
    let mut first = vec![None; traced.len()];
    surface.first_elements(&traced, &mut first, false)?;
    let mut hits = first.iter();
    let met: Vec<bool> = rays
        .iter()
        .map(|r| r.is_some() && hits.next().is_some_and(|p| p.is_some()))
        .collect();
    Ok(met
        .chunks(per_pixel)
        .map(|c| c.iter().filter(|&&m| m).count() as f32 / per_pixel as f32)
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_outline_is_where_a_neighbour_differs() {
        // A 4×3 image with one object pixel at (1, 1): it and its 8 neighbours cross the
        // outline; the last column does not.
        let mut hit = vec![false; 12];
        hit[5] = true;
        let crossing: Vec<usize> = (0..12)
            .filter(|&i| crosses_outline(i, 4, 3, &hit))
            .collect();
        assert_eq!(crossing, [0, 1, 2, 4, 5, 6, 8, 9, 10]);
    }
}
