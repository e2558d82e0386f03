//! The refraction term's inputs from a decoded scan: per view, the camera ray of every object
//! pixel with a decoded monitor point, that point in the world frame, and its weight
//! ([`TargetWeights`]; 1 for imported rays and 3D targets, which carry no uncertainty).

use anyhow::Result;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use nalgebra::Vector3;

use super::bits::PixelBits;
use super::refraction::{PixelAxes, PixelTarget, ViewTargets};
use crate::scan::decoded::{DecodedScan, MonitorTarget};
use crate::scan::Scan;

/// How decoded monitor points are weighted in the refraction term.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetWeights {
    /// Every decoded point weighs 1. The default: on captures through glass most points come
    /// from partly decoded cells (blurred, noisy footprints), and weighting by the cell puts the
    /// term on the few complete decodes (noisy 72-view pig scan, `balanced` without warm-up:
    /// 0.83 mm with cell weights, 0.28–0.44 mm with uniform ones over three seeds).
    #[default]
    Uniform,
    /// The inverse of the point's variance: a uniform spread over its cell
    /// ((c_u² + c_v²)/12 monitor px²), relative to a fully decoded 1×1 cell, so every bit
    /// reliable weighs 1 and a 4×4 cell 1/16.
    Cell,
}

impl TargetWeights {
    /// The weight of a decoded point.
    pub fn weight(self, t: &MonitorTarget) -> f64 {
        match self {
            TargetWeights::Uniform => 1.0,
            TargetWeights::Cell => 2.0 / (t.cell_u * t.cell_u + t.cell_v * t.cell_v).max(2.0),
        }
    }
}

/// The width of a camera pixel's footprint on the monitor seen directly, at decoded point `t`'s
/// distance (monitor pixels; the camera sits at the origin of the frame `scan.screen` is given
/// in).
fn direct_footprint_px(scan: &Scan, t: &MonitorTarget) -> f32 {
    let distance_mm = scan.screen.point(t.u, t.v).coords.norm();
    let pixel_rad = 2.0 / (scan.camera.fx + scan.camera.fy);
    (distance_mm * pixel_rad / scan.screen.pitch_mm) as f32
}

/// A decoded point's measured bits (none without contrasts).
fn pixel_bits(t: &MonitorTarget, contrasts: Option<[f32; 4]>) -> PixelBits {
    let Some(c) = contrasts else {
        return PixelBits::default();
    };
    PixelBits {
        u: PixelBits::axis(t.cell_u, [c[0], c[1]]),
        v: PixelBits::axis(t.cell_v, [c[2], c[3]]),
        centre: [t.u as f32, t.v as f32],
        cell: [t.cell_u as f32, t.cell_v as f32],
    }
}

/// The targets of `views` (skipping views decode left out, which are returned by index).
pub fn scan_targets(
    scan: &Scan,
    views: &[usize],
    weights: TargetWeights,
) -> Result<(Vec<ViewTargets>, Vec<usize>)> {
    let decoded = DecodedScan::open(&scan.dir, (scan.camera.width, scan.camera.height))?;
    scan_targets_with(scan, &decoded, views, weights, |t| t)
}

/// [`scan_targets`] from the scan's opened `decoded` folder, each view passed through `keep` as
/// soon as it is read (a sample of it: a view's whole targets are held only while it is read).
pub fn scan_targets_with<T: Send>(
    scan: &Scan,
    decoded: &DecodedScan,
    views: &[usize],
    weights: TargetWeights,
    keep: impl Fn(ViewTargets) -> T + Sync,
) -> Result<(Vec<T>, Vec<usize>)> {
    let poses = scan.view_poses();
    let loaded: Vec<Result<Option<T>>> = views
        .par_iter()
        .map(|&k| {
            let Some(dv) = decoded.view(k)? else {
                return Ok(None);
            };
            let to_world = poses[k].inverse();
            let screen = scan.screen.transformed(&to_world);
            let w = dv.width as usize;
            let pixels = if let Some(rays) = &dv.rays {
                rays.iter()
                    .filter(|r| dv.mask[r.pixel as usize])
                    .map(|r| PixelTarget {
                        dir: to_world * r.dir,
                        target: to_world * r.target,
                        weight: 1.0,
                        bits: PixelBits::default(),
                        cell_px: f32::INFINITY,
                        direct_px: f32::NAN,
                        index_evidence: true,
                    })
                    .collect()
            } else {
                dv.mask
                    .iter()
                    .zip(&dv.targets)
                    .enumerate()
                    .filter_map(|(i, (&m, t))| {
                        let t = t.as_ref().filter(|_| m)?;
                        let dir = scan.camera.pixel_ray((i % w) as f64, (i / w) as f64)?;
                        Some(PixelTarget {
                            dir: to_world * dir,
                            target: screen.point(t.u, t.v),
                            weight: weights.weight(t),
                            bits: pixel_bits(t, dv.contrasts.as_ref().map(|c| c[i])),
                            cell_px: t.cell_u.max(t.cell_v) as f32,
                            direct_px: direct_footprint_px(scan, t),
                            index_evidence: true,
                        })
                    })
                    .collect()
            };
            Ok(Some(keep(ViewTargets {
                view: k,
                eye: to_world * nalgebra::Point3::origin(),
                monitor_point: screen.point(0.0, 0.0),
                monitor_normal: screen.pose * Vector3::z(),
                monitor_axes: Some([
                    screen.point(1.0, 0.0) - screen.point(0.0, 0.0),
                    screen.point(0.0, 1.0) - screen.point(0.0, 0.0),
                ]),
                pixel_axes: Some(PixelAxes {
                    right: to_world * Vector3::new(1.0 / scan.camera.fx, 0.0, 0.0),
                    down: to_world * Vector3::new(0.0, 1.0 / scan.camera.fy, 0.0),
                    forward: to_world * Vector3::z(),
                }),
                pixels,
            })))
        })
        .collect();
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    for (&k, v) in views.iter().zip(loaded) {
        match v? {
            Some(v) => out.push(v),
            None => skipped.push(k),
        }
    }
    Ok((out, skipped))
}
