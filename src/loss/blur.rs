//! What a blurred camera decodes (docs/architecture.md §4, "a blurred camera").
//!
//! A capture is the scene seen through the camera's point-spread function, here a Gaussian of
//! σ camera pixels (focus, optics, the sensor's own spread). Each Gray bit of a pixel is then
//! decided by the weighted vote of the monitor points its neighbourhood sees, and a Gray code
//! decoded bit by bit lands near the per-axis weighted median of those points — not where the
//! pixel's centre ray meets the monitor. Through glass that magnifies a neighbourhood unevenly
//! (near a rim, across a fold, partly outside the object) the two differ by many monitor
//! pixels, and a centre-ray model fitted to such points bends the surface and lowers the index.
//!
//! [`correct_targets`] traces each pixel's neighbourhood through a mesh and moves its decoded
//! point by the centre ray's point minus the neighbourhood's median, so that the centre-ray
//! model (and its exact gradient) compares like with like. The correction is a fixed shift per
//! pixel: it is recomputed on each stage's start mesh, not differentiated.
//!
//! The shift models the blur only in part (a 5 × 5 vote, the fixed shift): where it is large
//! the pixel's point stays skewed, and skewed the same way — towards the less bent rays — so
//! that an index fitted to them comes out low. [`correct_targets`] therefore also marks every
//! pixel whose shift exceeds [`SKEW_MM`] (or that has none) as no evidence of the index: its
//! derivative with respect to the index is left out, its pull on the shape kept.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::refraction::{screen_hit, ViewTargets};
use crate::trace::path::{trace_chunk, PathEnd, PathSettings, Surface, TRACE_CHUNK};
use crate::trace::{Ray, TraceError};
use crate::util::interpolated_median;

type V3 = Vector3<f64>;

/// Rays per side of a neighbourhood: 5 × 5 rays over ±3 σ.
const SIDE: usize = 5;
/// A neighbourhood spans this many σ on each side of the pixel centre.
const REACH_SIGMAS: f64 = 3.0;
/// The largest shift (mm on the monitor) of a pixel whose derivative with respect to the index
/// counts: on the horse's blurred scans (glasscan's simulator, 32-inch monitor, 640×480, the
/// true mesh) the index the kept pixels fit rises from 1.488 to 1.497 (truth 1.50) and from
/// 1.586 to 1.598 (1.60), about a third of the pixels kept
/// (docs/decisions.md#the-index-from-the-pixels-the-blur-leaves-alone).
pub const SKEW_MM: f64 = 1.0;
/// Most refractions a neighbourhood ray is followed through (it may meet other faces than the
/// centre ray's: that is what the vote sees).
const MAX_REFRACTIONS: u32 = 8;

/// The rays of a pixel's neighbourhood: offsets from its centre (camera pixels) and weights.
#[derive(Clone, Debug, PartialEq)]
pub struct BlurKernel {
    offsets: Vec<((f64, f64), f64)>,
}

impl BlurKernel {
    /// The kernel of a Gaussian blur of `sigma_px` camera pixels, widened by the pixel's own
    /// area (a box of one pixel: variance 1/12); `None` for no blur.
    pub fn gaussian(sigma_px: f64) -> Option<Self> {
        if !(sigma_px > 0.0 && sigma_px.is_finite()) {
            return None;
        }
        let sigma = (sigma_px * sigma_px + 1.0 / 12.0).sqrt();
        let step = 2.0 * REACH_SIGMAS * sigma / (SIDE - 1) as f64;
        let at = |i: usize| (i as f64 - (SIDE - 1) as f64 / 2.0) * step;
        let offsets = (0..SIDE * SIDE)
            .map(|k| {
                let (x, y) = (at(k % SIDE), at(k / SIDE));
                ((x, y), (-(x * x + y * y) / (2.0 * sigma * sigma)).exp())
            })
            .collect();
        Some(Self { offsets })
    }
}

/// How far [`correct_targets`] moved the decoded points, and how many it marked.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CorrectionSummary {
    /// Pixels whose point moved (their centre ray and some neighbourhood ray reach the monitor;
    /// none when the points are only marked).
    pub corrected: usize,
    /// Pixels left as decoded.
    pub kept: usize,
    /// The median shift on the monitor, mm (measured whether or not the points moved).
    pub median_shift_mm: f64,
    /// Pixels marked as no evidence of the index (a shift beyond [`SKEW_MM`], or none).
    #[serde(default)]
    pub skewed: usize,
}

/// `targets` with each pixel's decoded point moved (when `shift`) by what the blur `kernel`
/// shifts it, traced through `surface` at refractive index `ior`, and (when `mark`) each pixel
/// marked as evidence of the index or not (the module's doc); views without pixel or monitor
/// axes (imported rays) are returned as they are, and a pixel whose shift is not finite keeps
/// its decoded point (counted as kept) and is no evidence of the index.
pub fn correct_targets(
    surface: &dyn Surface,
    ior: f64,
    kernel: &BlurKernel,
    targets: &[&ViewTargets],
    (shift, mark): (bool, bool),
) -> Result<(Vec<ViewTargets>, CorrectionSummary), TraceError> {
    let settings = PathSettings::new(ior, MAX_REFRACTIONS);
    let views: Vec<(ViewTargets, Vec<f64>)> = targets
        .iter()
        .map(|t| correct_view(surface, &settings, kernel, t, (shift, mark)))
        .collect::<Result<_, _>>()?;
    let mut summary = CorrectionSummary::default();
    let mut shifts = Vec::new();
    let corrected = views
        .into_iter()
        .map(|(view, s)| {
            summary.kept += view.pixels.len() - s.len();
            summary.skewed += view.pixels.iter().filter(|p| !p.index_evidence).count();
            shifts.extend(s);
            view
        })
        .collect();
    if shift {
        summary.corrected = shifts.len();
    } else {
        summary.kept += shifts.len();
    }
    if !shifts.is_empty() {
        summary.median_shift_mm = crate::util::median(shifts);
    }
    Ok((corrected, summary))
}

/// One view's targets corrected (when `shift`) and marked (when `mark`), and the shift (mm) of
/// each pixel that has one.
fn correct_view(
    surface: &dyn Surface,
    settings: &PathSettings,
    kernel: &BlurKernel,
    view: &ViewTargets,
    (shift, mark): (bool, bool),
) -> Result<(ViewTargets, Vec<f64>), TraceError> {
    let (Some(axes), Some(monitor)) = (view.pixel_axes, view.monitor_axes) else {
        return Ok((view.clone(), Vec::new()));
    };
    let per_pixel = kernel.offsets.len() + 1;
    let chunk_pixels = (TRACE_CHUNK / per_pixel).max(1);
    let moved: Vec<Vec<(usize, V3)>> = view
        .pixels
        .par_chunks(chunk_pixels)
        .enumerate()
        .map(|(c, pixels)| {
            let rays: Vec<Ray> = pixels
                .iter()
                .flat_map(|p| {
                    let centre = std::iter::once(Ray::new(view.eye, p.dir));
                    centre.chain(
                        (kernel.offsets.iter())
                            .map(|&(o, _)| Ray::new(view.eye, axes.offset(&p.dir, o))),
                    )
                })
                .collect();
            let paths = trace_chunk(surface, &rays, settings, None)?;
            let shifts = paths.chunks(per_pixel).enumerate().filter_map(|(i, p)| {
                let exits = p.iter().map(|p| {
                    (p.end == PathEnd::Left)
                        .then(|| monitor_uv(view, monitor, &p.origin, &p.dir))
                        .flatten()
                        .map(|uv| (uv, p.transmittance))
                });
                let shift =
                    blur_shift(exits, kernel).filter(|s| s.0.is_finite() && s.1.is_finite())?;
                Some((
                    c * chunk_pixels + i,
                    monitor[0] * shift.0 + monitor[1] * shift.1,
                ))
            });
            Ok(shifts.collect())
        })
        .collect::<Result<_, TraceError>>()?;
    let mut out = view.clone();
    if mark {
        // No evidence until a shift within SKEW_MM says otherwise.
        out.pixels.iter_mut().for_each(|p| p.index_evidence = false);
    }
    let mut sizes = Vec::new();
    for (i, by) in moved.into_iter().flatten() {
        let (p, size) = (&mut out.pixels[i], by.norm());
        if shift {
            p.target -= by;
        }
        if mark {
            p.index_evidence = size <= SKEW_MM;
        }
        sizes.push(size);
    }
    Ok((out, sizes))
}

/// The shift (monitor pixels, u and v) from a pixel's centre-ray point to the weighted median
/// of its neighbourhood's points: `exits` = the centre ray's monitor point, then each kernel
/// ray's (`None` where it does not reach the monitor), each with its path's transmittance.
/// `None` when the centre ray or every neighbourhood ray misses the monitor.
fn blur_shift(
    mut exits: impl Iterator<Item = Option<((f64, f64), f64)>>,
    kernel: &BlurKernel,
) -> Option<(f64, f64)> {
    let ((cu, cv), _) = exits.next()??;
    let (mut us, mut vs) = (Vec::new(), Vec::new());
    for (exit, &(_, w)) in exits.zip(&kernel.offsets) {
        if let Some(((u, v), t)) = exit {
            us.push((u, w * t));
            vs.push((v, w * t));
        }
    }
    Some((interpolated_median(us)? - cu, interpolated_median(vs)? - cv))
}

/// Where the ray (o, d) meets the monitor plane, in monitor pixels along its `axes` from
/// `view.monitor_point`; `None` when it runs parallel to the plane or away from it.
fn monitor_uv(view: &ViewTargets, axes: [V3; 2], o: &Point3<f64>, d: &V3) -> Option<(f64, f64)> {
    let (s, _) = screen_hit(view, o, d)?;
    let x = o + d * s - view.monitor_point;
    let [au, av] = axes;
    Some((
        x.dot(&au) / au.norm_squared(),
        x.dot(&av) / av.norm_squared(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kernel_is_symmetric_and_spans_three_sigmas() {
        assert!(BlurKernel::gaussian(0.0).is_none());
        let k = BlurKernel::gaussian(0.7).unwrap();
        assert_eq!(k.offsets.len(), SIDE * SIDE);
        let sigma = (0.49f64 + 1.0 / 12.0).sqrt();
        let far = k
            .offsets
            .iter()
            .map(|((x, _), _)| x.abs())
            .fold(0.0, f64::max);
        assert!((far - 3.0 * sigma).abs() < 1e-12, "{far}");
        let sum = |f: fn(&((f64, f64), f64)) -> f64| k.offsets.iter().map(f).sum::<f64>();
        assert!(sum(|((x, _), w)| x * w).abs() < 1e-12);
        assert!(sum(|((_, y), w)| y * w).abs() < 1e-12);
    }
}
