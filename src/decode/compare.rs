//! `glasscan decode --compare-ground-truth`: a decoded view against `simulate`'s ground truth.

use std::path::Path;

use anyhow::{bail, Result};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Vec3w, Vec4w};
use serde::Serialize;

use crate::scan::decoded::is_object;
use crate::scan::outline::decode_coverage;
use crate::util::fixed::{FixedPoint, NONE};
use crate::util::image::read_image;
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
    /// Pixels outside both silhouettes (the monitor seen without the object) with a decoded and
    /// a true point.
    pub direct_compared: usize,
    /// Their mean offset, decoded − true pixel-centre point, in camera pixels (x right, y down;
    /// the monitor offset mapped back through the view's mean monitor-per-camera-pixel
    /// Jacobian): a camera-side bias of the capture or the decoder, whatever the resolution.
    pub direct_offset_px: [f64; 2],
    /// The decoded silhouette's area, pixels: its outline pixels' measured coverage where the
    /// decode wrote it, 1 for its other object pixels.
    pub decoded_area_px: f64,
    /// The true silhouette's area from the simulator's true coverage (`None`: the truth has no
    /// `view_NNN_coverage.png`).
    pub true_area_px: Option<f64>,
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

    /// Mean signed offset of the decoded outline from the true one by area, camera pixels
    /// (> 0: the decoded silhouette is larger): (decoded − true area) / outline length, the
    /// areas to a fraction of a pixel ([`Self::decoded_area_px`], [`Self::true_area_px`]).
    pub fn coverage_offset_px(&self) -> Option<f64> {
        Self::overall_coverage_offset_px(std::slice::from_ref(self))
    }

    /// [`Self::coverage_offset_px`] over several views together (`None` if one lacks the true
    /// coverage).
    pub fn overall_coverage_offset_px(rows: &[Comparison]) -> Option<f64> {
        let signed = rows
            .iter()
            .map(|c| c.true_area_px.map(|t| c.decoded_area_px - t))
            .sum::<Option<f64>>()?;
        Some(signed / rows.iter().map(|c| c.outline).sum::<usize>().max(1) as f64)
    }

    /// [`Self::direct_offset_px`] over several views together (weighted by their pixels).
    pub fn overall_direct_offset_px(rows: &[Comparison]) -> [f64; 2] {
        let n = rows.iter().map(|c| c.direct_compared).sum::<usize>().max(1) as f64;
        [0, 1].map(|i| {
            rows.iter()
                .map(|c| c.direct_offset_px[i] * c.direct_compared as f64)
                .sum::<f64>()
                / n
        })
    }
}

/// The monitor seen without the object: sums of the decoded − true offsets (monitor pixels) and
/// of the true points' steps between neighbouring camera pixels (the Jacobian ∂(u, v)/∂(x, y)).
#[derive(Default)]
struct DirectView {
    offset: [f64; 2],
    count: usize,
    /// Σ ∂(u, v)/∂x over horizontal neighbours, and their count; the same for ∂/∂y.
    dx: ([f64; 2], usize),
    dy: ([f64; 2], usize),
}

impl DirectView {
    /// The mean offset in camera pixels: J⁻¹ · mean monitor offset (zero without pixels or with
    /// a degenerate Jacobian).
    fn offset_px(&self) -> [f64; 2] {
        let mean = |(s, n): ([f64; 2], usize)| s.map(|v| v / n.max(1) as f64);
        let (jx, jy) = (mean(self.dx), mean(self.dy));
        let det = jx[0] * jy[1] - jy[0] * jx[1];
        if self.count == 0 || !det.is_normal() {
            return [0.0; 2];
        }
        let o = self.offset.map(|v| v / self.count as f64);
        [
            (jy[1] * o[0] - jy[0] * o[1]) / det,
            (-jx[1] * o[0] + jx[0] * o[1]) / det,
        ]
    }
}

/// A decoded or truth image of a simulated scan, as stored (`IMREAD_UNCHANGED`).
pub fn load(path: &Path) -> Result<Mat> {
    if !path.is_file() {
        bail!(
            "{}: missing (is this a scan made by `glasscan simulate`?)",
            path.display()
        );
    }
    read_image(path, opencv::imgcodecs::IMREAD_UNCHANGED)
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
    let direct = direct_view((&m, &tm), &mon, &centre, &unfix)?;
    let decoded_coverage = crate::scan::decoded::coverage_path(&dec, k);
    let decoded_area_px = decoded_area(
        &m,
        decoded_coverage
            .is_file()
            .then_some(decoded_coverage.as_path()),
    )?;
    let true_coverage = truth.join(format!("view_{k:03}_coverage.png"));
    let true_area_px = if true_coverage.is_file() {
        Some(true_area(&load(&true_coverage)?)?)
    } else {
        None
    };
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
        direct_compared: direct.count,
        direct_offset_px: direct.offset_px(),
        decoded_area_px,
        true_area_px,
    })
}

/// The decoded silhouette's area (pixels) from its `mask` and, where given, the coverage image
/// at `coverage` (the decoded form's values, [`decode_coverage`]).
fn decoded_area(mask: &Mat, coverage: Option<&Path>) -> Result<f64> {
    let inside: Vec<bool> = mask.data_bytes()?.iter().map(|&m| is_object(m)).collect();
    let Some(path) = coverage else {
        return Ok(inside.iter().filter(|&&i| i).count() as f64);
    };
    let c = load(path)?;
    let values = c.data_bytes()?;
    if values.len() != inside.len() {
        bail!(
            "{}: {} pixels, the mask {}",
            path.display(),
            values.len(),
            inside.len()
        );
    }
    Ok(values
        .iter()
        .zip(&inside)
        .map(|(&v, &i)| decode_coverage(v, i))
        .sum())
}

/// The true silhouette's area (pixels) from the simulator's 16-bit coverage image `c`.
fn true_area(c: &Mat) -> Result<f64> {
    Ok(c.data_typed::<u16>()?
        .iter()
        .map(|&v| f64::from(v) / 65535.0)
        .sum())
}

/// The monitor seen without the object in a view: pixels outside both `masks` (decoded, true)
/// whose true centre point exists, against the decoded points `mon` (fixed point, read with
/// `unfix`).
fn direct_view(
    (m, tm): (&Mat, &Mat),
    mon: &Mat,
    centre: &Mat,
    unfix: &impl Fn(u16) -> f64,
) -> Result<DirectView> {
    // The true point of pixel (x, y) where it shows the monitor directly.
    let truth = |x: i32, y: i32| -> Result<Option<[f64; 2]>> {
        let inside = *m.at_2d::<u8>(y, x)? == 255 || *tm.at_2d::<u8>(y, x)? == 255;
        let c = *centre.at_2d::<Vec3w>(y, x)?;
        Ok((!inside && c[0] != NONE).then(|| [unfix(c[0]), unfix(c[1])]))
    };
    // Each pixel's truth read once: a row, and the row above it for the vertical steps.
    let step = |(sum, n): &mut ([f64; 2], usize), from: [f64; 2], to: Option<[f64; 2]>| {
        if let Some(q) = to {
            (sum[0], sum[1], *n) = (sum[0] + q[0] - from[0], sum[1] + q[1] - from[1], *n + 1);
        }
    };
    let mut dv = DirectView::default();
    let mut above: Vec<Option<[f64; 2]>> = vec![None; m.cols().max(0) as usize];
    for y in 0..m.rows() {
        let row = (0..m.cols())
            .map(|x| truth(x, y))
            .collect::<Result<Vec<_>>>()?;
        for (x, t) in row.iter().enumerate() {
            let Some(t) = *t else { continue };
            let d = *mon.at_2d::<Vec4w>(y, x as i32)?;
            if d[0] != NONE {
                dv.offset[0] += unfix(d[0]) - t[0];
                dv.offset[1] += unfix(d[1]) - t[1];
                dv.count += 1;
            }
            step(&mut dv.dx, t, row.get(x + 1).copied().flatten());
            if let Some(a) = above[x] {
                step(&mut dv.dy, a, Some(t));
            }
        }
        above = row;
    }
    Ok(dv)
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
