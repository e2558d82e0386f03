//! How well a result's confidence (its per-vertex `quality`, as `reconstruct` writes it: refraction
//! rays per mm² over their mean penalty) predicts its error: the mean distance to the reference of the vertices in each
//! quarter of the result's area, from the least to the most confident.

use serde::Serialize;

use crate::mesh::TriMesh;
use crate::trace::{Scene, TraceError};

/// The mean error (mm; each vertex's distance to the reference, weighted by its area) in each
/// quarter of the area, ordered by confidence: `quartiles_mm[0]` the least confident.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ErrorByConfidence {
    pub quartiles_mm: [f64; 4],
    /// The least confident quarter's mean error over the most confident one's; `None` (JSON
    /// null) when the most confident quarter has no error to divide by.
    pub least_over_most: Option<f64>,
}

/// The error of `result`'s vertices against `reference` (its scene) by quarters of the area
/// ordered by `quality` (one value per vertex; vertices of equal quality as one group).
pub fn error_by_confidence(
    result: &TriMesh,
    quality: &[f64],
    reference: &Scene,
) -> Result<ErrorByConfidence, TraceError> {
    let errors: Vec<f64> = reference
        .closest_points(&result.positions)?
        .iter()
        .map(|c| c.dist)
        .collect();
    Ok(by_quarters(quality, &result.vertex_areas(), &errors))
}

/// The area-weighted mean of `errors` in each quarter of the total of `areas`, vertices taken
/// in increasing `quality`. Vertices of equal quality cannot be told apart, so they count as
/// one group at the group's mean error, spread over the quarters it spans by area (as a vertex
/// that straddles a boundary is); the result does not depend on the vertices' order.
fn by_quarters(quality: &[f64], areas: &[f64], errors: &[f64]) -> ErrorByConfidence {
    let mut order: Vec<usize> = (0..quality.len()).collect();
    order.sort_by(|&a, &b| quality[a].total_cmp(&quality[b]));
    let total: f64 = areas.iter().sum::<f64>().max(f64::MIN_POSITIVE);
    let (mut sum, mut weight) = ([0.0; 4], [0.0; 4]);
    let mut seen = 0.0;
    for group in order.chunk_by(|&a, &b| quality[a] == quality[b]) {
        let area: f64 = group.iter().map(|&v| areas[v]).sum();
        if area <= 0.0 {
            continue;
        }
        let mean = group.iter().map(|&v| errors[v] * areas[v]).sum::<f64>() / area;
        for q in 0..4 {
            let (lo, hi) = (q as f64 * total / 4.0, (q + 1) as f64 * total / 4.0);
            let hi = if q == 3 { f64::INFINITY } else { hi };
            let part = (seen + area).min(hi) - seen.max(lo);
            if part > 0.0 {
                sum[q] += mean * part;
                weight[q] += part;
            }
        }
        seen += area;
    }
    let quartiles_mm: [f64; 4] = std::array::from_fn(|q| {
        if weight[q] > 0.0 {
            sum[q] / weight[q]
        } else {
            0.0
        }
    });
    ErrorByConfidence {
        quartiles_mm,
        least_over_most: (quartiles_mm[3] > 0.0).then(|| quartiles_mm[0] / quartiles_mm[3]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quarters_follow_the_area_in_order_of_confidence() {
        // Eight vertices of equal area; the error falls as the confidence rises.
        let quality = [7.0, 0.0, 6.0, 1.0, 5.0, 2.0, 4.0, 3.0];
        let errors = quality.map(|q| 1.0 / (1.0 + q));
        let r = by_quarters(&quality, &[1.0; 8], &errors);
        let want = [
            (1.0 + 0.5) / 2.0,
            (1.0 / 3.0 + 0.25) / 2.0,
            (0.2 + 1.0 / 6.0) / 2.0,
            (1.0 / 7.0 + 0.125) / 2.0,
        ];
        for (got, want) in r.quartiles_mm.iter().zip(want) {
            assert!((got - want).abs() < 1e-12, "{:?}", r.quartiles_mm);
        }
        assert!((r.least_over_most.unwrap() - want[0] / want[3]).abs() < 1e-12);
        // One vertex holding most of the area fills the quarters it spans.
        let r = by_quarters(&[0.0, 1.0], &[3.0, 1.0], &[2.0, 1.0]);
        assert_eq!(r.quartiles_mm, [2.0, 2.0, 2.0, 1.0]);
        // Vertices of equal quality count at their mean error, in whatever order they come.
        let (quality, areas) = ([0.0, 0.0, 0.0, 1.0], [1.0; 4]);
        for errors in [[3.0, 0.0, 0.0, 1.0], [0.0, 0.0, 3.0, 1.0]] {
            let r = by_quarters(&quality, &areas, &errors);
            assert_eq!(r.quartiles_mm, [1.0, 1.0, 1.0, 1.0], "{errors:?}");
        }
        // No error at all: no ratio.
        let r = by_quarters(&[0.0, 1.0], &[1.0, 1.0], &[0.0, 0.0]);
        assert_eq!(r.least_over_most, None);
    }
}
