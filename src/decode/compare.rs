//! `glasscan decode --compare-ground-truth`: a decoded view against `simulate`'s ground truth.

use std::path::Path;

use anyhow::{bail, Result};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Vec3w, Vec4w};
use serde::Serialize;

use crate::util::fixed::{FixedPoint, NONE};
use crate::util::median;

/// How a decoded view compares with the truth.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Comparison {
    pub view: usize,
    /// Intersection over union of the decoded and the true silhouette.
    pub mask_iou: f64,
    /// Object pixels (in both silhouettes) whose true pixel-centre ray reaches the monitor.
    pub valid: usize,
    /// Share of those that were decoded (not rejected).
    pub decoded_share: f64,
    /// Valid object pixels compared (decoded, and true monitor points exist).
    pub compared: usize,
    pub median_error_footprint_px: f64,
    pub median_error_centre_px: f64,
    pub within_1px_footprint: f64,
    pub within_uncertainty_footprint: f64,
    /// Pixels the decoded silhouette has and the true one lacks, and the reverse.
    pub mask_extra: usize,
    pub mask_missing: usize,
    /// Pixels of the true silhouette with a 4-neighbour outside it (its outline's length, px).
    pub outline: usize,
}

impl Comparison {
    /// Mean signed offset of the decoded outline from the true one, camera pixels (> 0: the
    /// decoded silhouette is larger): (extra − missing) / outline length.
    pub fn edge_offset_px(&self) -> f64 {
        Self::overall_edge_offset_px(std::slice::from_ref(self))
    }

    /// [`Self::edge_offset_px`] over several views together.
    pub fn overall_edge_offset_px(rows: &[Comparison]) -> f64 {
        let signed: f64 = rows
            .iter()
            .map(|c| c.mask_extra as f64 - c.mask_missing as f64)
            .sum();
        signed / rows.iter().map(|c| c.outline).sum::<usize>().max(1) as f64
    }
}

fn load(path: &Path) -> Result<Mat> {
    if !path.is_file() {
        bail!(
            "{}: missing (is this a scan made by `glasscan simulate`?)",
            path.display()
        );
    }
    Ok(opencv::imgcodecs::imread(
        path,
        opencv::imgcodecs::IMREAD_UNCHANGED,
    )?)
}

/// Compares view `k` of the scan in `scan_dir` (decoded already) with its truth, both stored with
/// `fixed`.
pub fn compare_view(scan_dir: &Path, k: usize, fixed: &FixedPoint) -> Result<Comparison> {
    let dec = scan_dir.join("decoded");
    let truth = scan_dir.join("truth");
    let (m, tm) = (
        load(&dec.join(format!("view_{k:03}_mask.png")))?,
        load(&truth.join(format!("view_{k:03}_mask.png")))?,
    );
    let mon = load(&dec.join(format!("view_{k:03}_monitor.png")))?;
    let (centre, foot) = (
        load(&truth.join(format!("view_{k:03}_centre.png")))?,
        load(&truth.join(format!("view_{k:03}_footprint.png")))?,
    );
    let unfix = |x: u16| fixed.decode(x).unwrap_or(f64::NAN);
    let (mut inter, mut union, mut valid) = (0usize, 0usize, 0usize);
    let (mut extra, mut missing) = (0usize, 0usize);
    let (mut e_foot, mut e_centre, mut within1, mut within_u) =
        (Vec::new(), Vec::new(), 0usize, 0usize);
    for y in 0..m.rows() {
        for x in 0..m.cols() {
            let (a, b) = (*m.at_2d::<u8>(y, x)? == 255, *tm.at_2d::<u8>(y, x)? == 255);
            inter += (a && b) as usize;
            union += (a || b) as usize;
            extra += (a && !b) as usize;
            missing += (!a && b) as usize;
            let d = *mon.at_2d::<Vec4w>(y, x)?;
            let (f, c) = (*foot.at_2d::<Vec4w>(y, x)?, *centre.at_2d::<Vec3w>(y, x)?);
            let truth_valid = a && b && c[0] != NONE;
            valid += truth_valid as usize;
            if !truth_valid || d[0] == NONE || f[0] == NONE {
                continue;
            }
            let (du, dv) = (unfix(d[0]), unfix(d[1]));
            let (fu, fv) = (unfix(f[0]) - du, unfix(f[1]) - dv);
            let ef = fu.hypot(fv);
            e_foot.push(ef);
            e_centre.push((unfix(c[0]) - du).hypot(unfix(c[1]) - dv));
            within1 += (ef <= 1.0) as usize;
            within_u += (fu.abs() <= d[2] as f64 / 2.0 + 0.5 && fv.abs() <= d[3] as f64 / 2.0 + 0.5)
                as usize;
        }
    }
    let n = e_foot.len();
    Ok(Comparison {
        view: k,
        mask_iou: inter as f64 / union.max(1) as f64,
        valid,
        decoded_share: n as f64 / valid.max(1) as f64,
        compared: n,
        median_error_footprint_px: median(e_foot),
        median_error_centre_px: median(e_centre),
        within_1px_footprint: within1 as f64 / n.max(1) as f64,
        within_uncertainty_footprint: within_u as f64 / n.max(1) as f64,
        mask_extra: extra,
        mask_missing: missing,
        outline: outline_length(tm.data_bytes()?, tm.cols() as usize),
    })
}

/// Pixels of the `width`-wide mask `m` (row-major, 255 inside) with a 4-neighbour outside it or
/// on the image border.
fn outline_length(m: &[u8], width: usize) -> usize {
    let height = m.len() / width;
    let inside = |x: usize, y: usize| m[y * width + x] == 255;
    (0..m.len())
        .map(|i| (i % width, i / width))
        .filter(|&(x, y)| inside(x, y))
        .filter(|&(x, y)| {
            x == 0
                || y == 0
                || x + 1 == width
                || y + 1 == height
                || !(inside(x - 1, y) && inside(x + 1, y) && inside(x, y - 1) && inside(x, y + 1))
        })
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outline_of_a_square_is_its_border_ring() {
        let mut data = vec![0u8; 20 * 30];
        for y in 5..15 {
            for x in 10..20 {
                data[y * 30 + x] = 255;
            }
        }
        assert_eq!(outline_length(&data, 30), 36);
        // A mask one pixel larger all round: (12² − 10²) extra pixels over the 36-pixel outline.
        let c = Comparison {
            mask_extra: 44,
            outline: 36,
            ..Default::default()
        };
        assert!((c.edge_offset_px() - 44.0 / 36.0).abs() < 1e-12);
    }
}
