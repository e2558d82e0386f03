//! One view of a simulated scan: trace every pixel's area samples once (camera → object →
//! monitor), then shade all pattern images from those paths, and keep the ground truth.

use std::ops::Range;

use nalgebra::{Isometry3, Point2, Point3, Vector3};
use rayon::prelude::*;

use super::light::Light;
use crate::patterns::{GrayCode, PhaseShift};
use crate::rig::{Camera, Screen};
use crate::trace::path::{trace_paths, MeshSurface, PathEnd, PathSettings};
use crate::trace::{Ray, TraceError};

/// What happened to a ray from the camera (the `status` channel of the ground truth).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Outcome {
    /// Reached the monitor after this many refractions (0: it missed the object).
    Monitor(u32),
    TotalInternalReflection,
    TooManyInterfaces,
    /// Left the object but missed the monitor (or missed both).
    MissedMonitor {
        refractions: u32,
    },
    GrazingNormal,
}

impl Outcome {
    /// The value stored in the `status` channel: refractions (≥ 0) when the monitor was reached,
    /// −1 TIR, −2 too many interfaces, −3 missed the monitor, −4 grazing shading normal.
    pub fn code(&self) -> f32 {
        match *self {
            Outcome::Monitor(k) => k as f32,
            Outcome::TotalInternalReflection => -1.0,
            Outcome::TooManyInterfaces => -2.0,
            Outcome::MissedMonitor { .. } => -3.0,
            Outcome::GrazingNormal => -4.0,
        }
    }

    /// Did the ray meet the object?
    pub fn hit_object(&self) -> bool {
        !matches!(
            self,
            Outcome::Monitor(0) | Outcome::MissedMonitor { refractions: 0 }
        )
    }
}

/// One area sample of a pixel.
#[derive(Clone, Copy, Debug)]
pub struct Sample {
    pub outcome: Outcome,
    /// Monitor pixel coordinates where the ray landed (valid for `Outcome::Monitor`).
    pub monitor: Point2<f64>,
    /// Light carried (Fresnel transmittance, or 1).
    pub weight: f64,
}

/// Sub-pixel offsets of `spp` area samples, camera pixels: sample 0 is the pixel centre, the
/// others the R2 low-discrepancy sequence, moved together so that the centroid of all `spp` is
/// the centre, then drawn in towards it if that moved any outside the pixel (which keeps the
/// centroid). A camera pixel gathers light evenly about its centre; the bare sequence's 4
/// samples average (−0.118, −0.145) px, which shifted every simulated capture against the
/// calibrated camera (docs/decisions.md#area-samples-centred-on-the-pixel). Two samples cannot
/// be centred with the centre among them: `spp` 2 is refused by the options' check.
pub fn sample_offsets(spp: u32) -> Vec<(f64, f64)> {
    const A1: f64 = 0.754_877_666_246_692_7;
    const A2: f64 = 0.569_840_290_998_053_2;
    let mut offsets: Vec<(f64, f64)> = (0..spp)
        .map(|j| {
            (
                (0.5 + j as f64 * A1).fract() - 0.5,
                (0.5 + j as f64 * A2).fract() - 0.5,
            )
        })
        .collect();
    if spp < 3 {
        return offsets;
    }
    let rest = (spp - 1) as f64;
    let (mx, my) = offsets[1..]
        .iter()
        .fold((0.0, 0.0), |(a, b), (x, y)| (a + x / rest, b + y / rest));
    offsets[1..].iter_mut().for_each(|(x, y)| {
        *x -= mx;
        *y -= my;
    });
    let reach = offsets
        .iter()
        .fold(0.5f64, |r, (x, y)| r.max(x.abs()).max(y.abs()));
    offsets
        .into_iter()
        .map(|(x, y)| (x * 0.5 / reach, y * 0.5 / reach))
        .collect()
}

/// Everything a view needs, in the world frame.
pub struct ViewSetup<'a> {
    pub camera: &'a Camera,
    /// World → camera.
    pub pose: Isometry3<f64>,
    pub screen: &'a Screen,
    pub surface: Option<&'a MeshSurface>,
    /// Bounding sphere of the object (world frame): rays that miss it skip the tracer.
    pub bound_centre: Point3<f64>,
    pub bound_radius: f64,
    pub settings: PathSettings,
    pub fresnel: bool,
}

/// Area samples in one band of image rows (see [`row_bands`]): a view is traced band by band,
/// so its rays, paths and light branches are held for one band at a time, whatever the camera's
/// pixel count.
pub const BAND_SAMPLES: usize = 1 << 20;

/// The image rows of a camera, `height` of them, cut into consecutive bands of about
/// `band_samples` area samples each (at least one row).
pub fn row_bands(
    camera: &Camera,
    spp: u32,
    band_samples: usize,
) -> impl Iterator<Item = Range<u32>> {
    let per_row = (camera.width as usize * spp as usize).max(1);
    let rows = (band_samples / per_row).clamp(1, u32::MAX as usize) as u32;
    let height = camera.height;
    (0..height.div_ceil(rows)).map(move |b| b * rows..((b + 1) * rows).min(height))
}

/// The camera rays of `spp` area samples of every pixel in image rows `rows`, world frame
/// (row-major; samples of a pixel together; `None` where the lens model has no ray).
pub fn camera_rays(v: &ViewSetup, spp: u32, rows: Range<u32>) -> Vec<Option<Ray>> {
    let w = v.camera.width as usize;
    let to_world = v.pose.inverse();
    let eye = to_world * Point3::origin();
    let offsets = sample_offsets(spp);
    (rows.start as usize * w..rows.end as usize * w)
        .into_par_iter()
        .flat_map_iter(|p| {
            let (x, y) = ((p % w) as f64, (p / w) as f64);
            offsets.iter().map(move |(dx, dy)| {
                v.camera
                    .pixel_ray(x + dx, y + dy)
                    .map(|d| Ray::new(eye, to_world * d))
            })
        })
        .collect()
}

/// Traces `rays` (from [`camera_rays`]) along one refracted path each.
pub fn trace_view(v: &ViewSetup, rays: &[Option<Ray>]) -> Result<Vec<Sample>, TraceError> {
    let screen = v.screen.transformed(&v.pose.inverse());
    // Rays that can meet the object go through the tracer; the others fly straight.
    let r2 = v.bound_radius * v.bound_radius;
    let may_hit = |r: &Ray| {
        let oc = r.origin - v.bound_centre;
        let b = oc.dot(&r.dir);
        oc.norm_squared() - b * b <= r2 && (b < 0.0 || oc.norm_squared() <= r2)
    };
    let candidates: Vec<usize> = match v.surface {
        Some(_) => (0..rays.len())
            .filter(|&i| rays[i].as_ref().is_some_and(may_hit))
            .collect(),
        None => Vec::new(),
    };
    let traced = match v.surface {
        Some(s) => {
            let batch: Vec<Ray> = candidates
                .iter()
                .map(|&i| rays[i].expect("filtered"))
                .collect();
            trace_paths(s, &batch, &v.settings)?
        }
        None => Vec::new(),
    };
    let mut samples: Vec<Sample> = rays
        .par_iter()
        .map(|r| match r {
            None => Sample {
                outcome: Outcome::MissedMonitor { refractions: 0 },
                monitor: Point2::origin(),
                weight: 0.0,
            },
            Some(r) => land(&screen, &r.origin, &r.dir, 0, 1.0),
        })
        .collect();
    for (&i, p) in candidates.iter().zip(&traced) {
        let weight = if v.fresnel { p.transmittance } else { 1.0 };
        samples[i] = match p.end {
            PathEnd::Left => land(&screen, &p.origin, &p.dir, p.refractions, weight),
            PathEnd::TotalInternalReflection => dark(Outcome::TotalInternalReflection),
            PathEnd::TooManyInterfaces => dark(Outcome::TooManyInterfaces),
            PathEnd::GrazingNormal => dark(Outcome::GrazingNormal),
        };
    }
    Ok(samples)
}

fn dark(outcome: Outcome) -> Sample {
    Sample {
        outcome,
        monitor: Point2::origin(),
        weight: 0.0,
    }
}

fn land(
    screen: &Screen,
    o: &Point3<f64>,
    d: &Vector3<f64>,
    refractions: u32,
    weight: f64,
) -> Sample {
    match screen.intersect(o, d) {
        Some((_, px)) => Sample {
            outcome: Outcome::Monitor(refractions),
            monitor: px,
            weight,
        },
        None => dark(Outcome::MissedMonitor { refractions }),
    }
}

/// Shades one image as 0..255 intensities (before noise): each pixel sums, over the light it
/// gathers, the weight times the monitor's brightness (0..1) there, given by `brightness(u, v)`
/// at the monitor pixel, divided by its area samples.
fn shade_with(light: &Light, spp: u32, brightness: impl Fn(f64, f64) -> f64 + Sync) -> Vec<f32> {
    light
        .offsets
        .par_windows(2)
        .map(|r| {
            let lit: f64 = (r[0]..r[1])
                .map(|k| {
                    let p = light.points[k];
                    light.weights[k] * brightness(p.x.round(), p.y.round())
                })
                .sum();
            (255.0 * lit / spp as f64) as f32
        })
        .collect()
}

/// Shades image `i` of the capture sequence (patterns, then white, then black).
pub fn shade(light: &Light, spp: u32, code: &GrayCode, i: usize) -> Vec<f32> {
    let n = code.pattern_count();
    shade_with(light, spp, |u, v| {
        let on = match i {
            i if i < n => code.is_white(i, u as u32, v as u32),
            i => i == n, // white image; the black image shows nothing
        };
        on as u8 as f64
    })
}

/// Shades phase-shift image `j` (the first `steps` along u, then along v).
pub fn shade_phase(light: &Light, spp: u32, phase: &PhaseShift, j: u32) -> Vec<f32> {
    let (k, along_u) = (j % phase.steps, j < phase.steps);
    shade_with(light, spp, |u, v| {
        phase.value(if along_u { u } else { v }, k)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The area samples lie in the pixel, the first at its centre, and their centroid is the
    /// centre (the bare R2 sequence's 4 samples averaged (−0.118, −0.145) px); they stay apart.
    #[test]
    fn area_samples_are_centred_on_the_pixel() {
        for spp in (1..=crate::simulate::MAX_SPP).filter(|&s| s != 2) {
            let o = sample_offsets(spp);
            assert_eq!(o.len(), spp as usize);
            assert_eq!(o[0], (0.0, 0.0), "spp {spp}");
            let n = spp as f64;
            let (mx, my) = o
                .iter()
                .fold((0.0, 0.0), |(a, b), (x, y)| (a + x / n, b + y / n));
            assert!(
                mx.abs() < 1e-12 && my.abs() < 1e-12,
                "spp {spp}: ({mx}, {my})"
            );
            assert!(
                o.iter().all(|(x, y)| x.abs() <= 0.5 && y.abs() <= 0.5),
                "spp {spp}"
            );
        }
        let o = sample_offsets(4);
        let closest = (0..4)
            .flat_map(|i| (0..i).map(move |j| (i, j)))
            .map(|(i, j)| (o[i].0 - o[j].0).hypot(o[i].1 - o[j].1))
            .fold(f64::INFINITY, f64::min);
        assert!(closest > 0.2, "{o:?}");
    }
}
