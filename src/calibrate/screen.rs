//! `calibrate screen`: the monitor's pose from the background capture (the patterns without the
//! object), at any footprint of a camera pixel on the monitor.
//!
//! Every camera pixel whose leading Gray bits decode reliably sees a known *cell* of the monitor
//! (the monitor pixel itself when every bit decodes; a block of 2ᵏ pixels when the camera does not
//! resolve the finer stripes, as on a rig whose pixel covers several monitor pixels): a 2D–3D
//! correspondence whose uncertainty is the cell's size.
//!
//! 1. A first pose: RANSAC PnP (OpenCV) on a grid over the most precise quarter of the
//!    correspondences, its threshold scaled to their cells as the camera sees them.
//! 2. A weighted fit in monitor pixels: each camera pixel's ray meets the monitor plane of the
//!    pose at (u′, v′); the residual against the cell centre (u, v), divided by the cell's standard
//!    deviation (width/√12, plus a floor for the decoder's own noise), is minimised by
//!    Gauss–Newton over the 6 degrees of freedom of the pose with Huber weights, on an irregular
//!    sample of the pixels (a regular grid would alias with the monitor's pixel grid). Beside the
//!    cells, the sub-pixel stripe edges ([`crate::decode::edges`]): each is a camera point whose
//!    ray meets a known monitor column (or row) boundary, its residual in u (or v) divided by
//!    [`EDGE_SIGMA_CAMERA_PX`] seen on the monitor, with the same floor.
//! 3. The residuals are reported in monitor pixels; a pose whose residuals exceed the cells
//!    (median normalised residual above 1) is flagged.

use std::path::Path;

use anyhow::{bail, Result};
use nalgebra::{Isometry3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use opencv::core::{Mat, MatTraitConst, Point2d, Point3d, Vector};
use rayon::prelude::*;

use super::{camera_mats, pose_from_vectors};
use crate::decode::edges::StripeEdge;
use crate::decode::{decode_captures, DecodeOptions, DecodedCapture, Keep};
use crate::patterns::GrayCode;
use crate::rig::{Camera, Screen};
use crate::scan::{background_dir, ScanConfig};
use crate::util::hash_share;

/// Correspondences RANSAC draws from (a grid over the most precise pixels).
pub const TARGET_POINTS: usize = 4000;
/// Correspondences the pose is fitted on.
pub const REFINE_POINTS: usize = 60_000;
/// The smallest share of the image in which the monitor must decode (at any cell size).
pub const MIN_DECODED_SHARE: f64 = 0.05;
/// The largest cell a correspondence may have, monitor pixels.
pub const MAX_CELL_PX: u32 = 64;
/// Standard deviation of a fully decoded pixel's position besides its cell, monitor pixels.
const NOISE_FLOOR_PX: f64 = 0.3;
/// Standard deviation of a stripe edge's position in the image, camera pixels: the zero crossing
/// between two pixels that each average the stripes over their area lands within 0.09 px of the
/// boundary's image (`decode::edges`' test); the rest is the captures' noise.
pub const EDGE_SIGMA_CAMERA_PX: f64 = 0.1;

/// A monitor pose and how well it fits.
#[derive(Clone, Debug)]
pub struct ScreenCalibration {
    pub screen: Screen,
    /// RMS of the residuals divided by their cells' standard deviations (about 1 when the pose
    /// explains the decodes as well as their cells allow).
    pub rms_normalised: f64,
    /// Median and 95th percentile of the residuals, monitor pixels.
    pub median_residual_px: f64,
    pub p95_residual_px: f64,
    /// Median cell width of the correspondences, monitor pixels (1: every bit decodes).
    pub median_cell_px: f64,
    /// Share of the image with a correspondence.
    pub decoded_share: f64,
    /// Share of the image whose every Gray bit decodes.
    pub complete_share: f64,
    /// Correspondences, and those the pose was fitted on.
    pub points: usize,
    pub fitted: usize,
    /// Stripe edges the pose was fitted on, and the median of their residuals across their
    /// boundaries, monitor pixels (NaN without edges).
    pub edges: usize,
    pub edge_median_residual_px: f64,
    /// Set when the residuals exceed the cells: the pose does not explain the decodes.
    pub warning: Option<String>,
}

/// A stripe edge as the fit uses it: a ray (camera frame, unit) that meets the monitor on the
/// column boundary u = `coord` (or the row boundary v = `coord`), within `sigma` monitor pixels.
#[derive(Clone, Copy, Debug)]
struct EdgeLine {
    ray: Vector3<f64>,
    column: bool,
    coord: f64,
    sigma: f64,
}

/// What the pose is fitted to: a pixel's cell, or a stripe edge.
#[derive(Clone, Copy, Debug)]
enum Constraint {
    Cell(Correspondence),
    Edge(EdgeLine),
}

impl Constraint {
    /// The normalised residuals at `pose` (an edge's second is 0), or `None` where the ray
    /// misses the plane.
    fn residual(&self, pose: &Isometry3<f64>, pitch_mm: f64) -> Option<[f64; 2]> {
        match self {
            Constraint::Cell(c) => normalised_residual(c, pose, pitch_mm),
            Constraint::Edge(e) => {
                let (u, v) = monitor_hit(&e.ray, pose, pitch_mm)?;
                let at = if e.column { u } else { v };
                Some([(at - e.coord) / e.sigma, 0.0])
            }
        }
    }
}

/// One correspondence: a camera pixel's ray (camera frame, unit) and the monitor cell it sees.
#[derive(Clone, Copy, Debug)]
struct Correspondence {
    pixel: (f64, f64),
    ray: Vector3<f64>,
    /// Cell centre and width, monitor pixels.
    u: f64,
    v: f64,
    cell_u: f64,
    cell_v: f64,
}

impl Correspondence {
    /// Standard deviations of u and v, monitor pixels.
    fn sigma(&self) -> (f64, f64) {
        let s = |c: f64| (c * c / 12.0 + NOISE_FLOOR_PX * NOISE_FLOOR_PX).sqrt();
        (s(self.cell_u), s(self.cell_v))
    }
}

/// Decodes the background capture of the scan folder `dir` (`captures/background/`, the
/// patterns of `config`) and solves the monitor pose from it.
pub fn from_background(
    dir: &Path,
    config: &ScanConfig,
    camera: &Camera,
    pitch_mm: f64,
) -> Result<ScreenCalibration> {
    let background = background_dir(dir);
    if !background.is_dir() {
        bail!(
            "{}: no background capture; capture the patterns without the object there (see the README: scan folder)",
            background.display()
        );
    }
    let code = config.graycode();
    let cap = decode_captures(
        &background,
        &code,
        config.patterns.phase_shift.as_ref(),
        (camera.width, camera.height),
        &DecodeOptions::default(),
        Keep {
            edges: true,
            ..Keep::default()
        },
    )?;
    calibrate_screen(&cap, &code, camera, pitch_mm)
}

/// Solves the monitor pose (monitor frame → camera frame) from a decoded background capture.
pub fn calibrate_screen(
    cap: &DecodedCapture,
    code: &GrayCode,
    camera: &Camera,
    pitch_mm: f64,
) -> Result<ScreenCalibration> {
    if (cap.width, cap.height) != (camera.width as usize, camera.height as usize) {
        bail!(
            "the background captures are {}×{} but the camera takes {}×{}",
            cap.width,
            cap.height,
            camera.width,
            camera.height
        );
    }
    let all = correspondences(cap, code, camera);
    let share = all.len() as f64 / cap.pixels.len() as f64;
    if share < MIN_DECODED_SHARE {
        bail!(
            "the monitor decodes in {:.2} % of the background capture, even to cells of {MAX_CELL_PX} monitor pixels (at least {:.0} % needed): check that the monitor fills much of the camera view, the exposure, and that the patterns match the monitor ({}×{})",
            100.0 * share,
            100.0 * MIN_DECODED_SHARE,
            code.width,
            code.height
        );
    }
    let guess = ransac_pose(&all, camera, pitch_mm)?;
    let sample = irregular_sample(&all, REFINE_POINTS, |c| pixel_key(c.pixel));
    let scale = monitor_px_per_camera_px(&all);
    let edges = edge_lines(cap.edges.as_deref().unwrap_or(&[]), camera, scale);
    let edges = irregular_sample(&edges, REFINE_POINTS, |e| e.0);
    let constraints: Vec<Constraint> = (sample.iter().map(|&c| Constraint::Cell(c)))
        .chain(edges.iter().map(|&(_, e)| Constraint::Edge(e)))
        .collect();
    let pose = fit_pose(&constraints, guess, pitch_mm);
    if (pose.rotation * Vector3::z()).dot(&(pose * Point3::origin()).coords) <= 0.0 {
        bail!("the solved monitor faces away from the camera: the decoded rows or columns are mirrored (check the patterns' order)");
    }
    let complete = (0..cap.pixels.len())
        .filter(|&i| cap.lit[i] && cap.pixels[i].complete(code))
        .count();
    let edges: Vec<EdgeLine> = edges.into_iter().map(|(_, e)| e).collect();
    Ok(summarise(
        (&sample, &edges),
        pose,
        code,
        pitch_mm,
        share,
        complete as f64 / cap.pixels.len() as f64,
        all.len(),
    ))
}

/// Every lit pixel whose cells are at most [`MAX_CELL_PX`] wide and inside the monitor.
fn correspondences(cap: &DecodedCapture, code: &GrayCode, camera: &Camera) -> Vec<Correspondence> {
    (0..cap.pixels.len())
        .into_par_iter()
        .filter_map(|i| {
            let d = &cap.pixels[i];
            let usable = cap.lit[i]
                && d.u.bits > 0
                && d.v.bits > 0
                && d.u.cell <= MAX_CELL_PX
                && d.v.cell <= MAX_CELL_PX
                && (d.u.coord as f64) < code.width as f64
                && (d.v.coord as f64) < code.height as f64;
            if !usable {
                return None;
            }
            let pixel = ((i % cap.width) as f64, (i / cap.width) as f64);
            Some(Correspondence {
                pixel,
                ray: camera.pixel_ray(pixel.0, pixel.1)?,
                u: d.u.coord as f64,
                v: d.v.coord as f64,
                cell_u: d.u.cell as f64,
                cell_v: d.v.cell as f64,
            })
        })
        .collect()
}

/// Step 1: RANSAC PnP on a grid over the correspondences with the smallest cells.
fn ransac_pose(all: &[Correspondence], camera: &Camera, pitch_mm: f64) -> Result<Isometry3<f64>> {
    let cell = |c: &Correspondence| c.cell_u.max(c.cell_v);
    let mut cells: Vec<f64> = all.iter().map(cell).collect();
    cells.sort_by(f64::total_cmp);
    let best_cell = cells[cells.len() / 4];
    let precise: Vec<&Correspondence> = all.iter().filter(|c| cell(c) <= best_cell).collect();
    let stride = ((precise.len() as f64 / TARGET_POINTS as f64).sqrt().floor() as usize).max(1);
    let on_grid = |c: &&&Correspondence| {
        (c.pixel.0 as usize).is_multiple_of(stride) && (c.pixel.1 as usize).is_multiple_of(stride)
    };
    let (object, image): (Vector<Point3d>, Vector<Point2d>) = precise
        .iter()
        .filter(on_grid)
        .map(|c| {
            (
                Point3d::new(c.u * pitch_mm, c.v * pitch_mm, 0.0),
                Point2d::new(c.pixel.0, c.pixel.1),
            )
        })
        .unzip();
    // The cells as the camera sees them: monitor pixels per camera pixel from an affine fit.
    let threshold_px =
        2.0 + best_cell / monitor_px_per_camera_px(precise.iter().copied()).max(1e-3);
    let (k, dist) = camera_mats(camera)?;
    let (mut rvec, mut tvec, mut inliers) = (Mat::default(), Mat::default(), Mat::default());
    let found = opencv::calib3d::solve_pnp_ransac(
        &object,
        &image,
        &k,
        &dist,
        &mut rvec,
        &mut tvec,
        false,
        500,
        threshold_px as f32,
        0.999,
        &mut inliers,
        opencv::calib3d::SOLVEPNP_ITERATIVE,
    )?;
    let n = if inliers.empty() { 0 } else { inliers.total() };
    if !found || n < 6 {
        bail!("no monitor pose fits the decoded background (RANSAC found {n} consistent points): check the camera calibration and the monitor pitch");
    }
    pose_from_vectors(&rvec, &tvec)
}

/// The scale of the decoded coordinates against the pixel coordinates: √|det A| of the
/// least-squares affine map (x, y) → (u, v).
fn monitor_px_per_camera_px<'a>(cs: impl IntoIterator<Item = &'a Correspondence>) -> f64 {
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let (mut atu, mut atv) = (Vector3::zeros(), Vector3::zeros());
    for c in cs {
        let a = Vector3::new(c.pixel.0, c.pixel.1, 1.0);
        ata += a * a.transpose();
        atu += a * c.u;
        atv += a * c.v;
    }
    let Some(inv) = ata.try_inverse() else {
        return 1.0;
    };
    let (pu, pv) = (inv * atu, inv * atv);
    (pu.x * pv.y - pu.y * pv.x).abs().sqrt()
}

/// About `n` of `all` drawn by a hash of each one's `key` (irregular, deterministic).
fn irregular_sample<T: Copy>(all: &[T], n: usize, key: impl Fn(&T) -> u64) -> Vec<T> {
    let keep = (n as f64 / all.len() as f64).min(1.0);
    all.iter()
        .filter(|c| hash_share(key(c)) <= keep)
        .copied()
        .collect()
}

/// A key of a position in the image (camera pixels, to a 1/1024 of a pixel) for
/// [`irregular_sample`].
fn pixel_key((x, y): (f64, f64)) -> u64 {
    let q = |a: f64| (a * 1024.0).round() as u64 & 0xFFFF_FFFF;
    q(y) << 32 | q(x)
}

/// The stripe edges as the fit uses them, each with its key for [`irregular_sample`] (its
/// position and axis); `scale`: monitor pixels per camera pixel.
fn edge_lines(edges: &[StripeEdge], camera: &Camera, scale: f64) -> Vec<(u64, EdgeLine)> {
    let sigma = (EDGE_SIGMA_CAMERA_PX * scale).hypot(NOISE_FLOOR_PX);
    edges
        .iter()
        .filter_map(|e| {
            let line = EdgeLine {
                ray: camera.pixel_ray(e.pixel.0, e.pixel.1)?,
                column: e.column,
                coord: e.coord,
                sigma,
            };
            Some((pixel_key(e.pixel) ^ u64::from(e.column) << 63, line))
        })
        .collect()
}

/// Where `ray` (camera frame) meets the monitor plane of `pose`, monitor pixels; `None` if it
/// runs parallel to it or meets it behind the camera.
fn monitor_hit(ray: &Vector3<f64>, pose: &Isometry3<f64>, pitch_mm: f64) -> Option<(f64, f64)> {
    let inv = pose.inverse();
    let o = inv * Point3::origin();
    let d = inv.rotation * ray;
    let t = -o.z / d.z;
    if !(t > 0.0 && t.is_finite()) {
        return None;
    }
    let p = o + d * t;
    Some((p.x / pitch_mm, p.y / pitch_mm))
}

/// `c`'s residual divided by its standard deviations, or `None` where its ray misses the plane.
fn normalised_residual(
    c: &Correspondence,
    pose: &Isometry3<f64>,
    pitch_mm: f64,
) -> Option<[f64; 2]> {
    let (u, v) = monitor_hit(&c.ray, pose, pitch_mm)?;
    let (su, sv) = c.sigma();
    Some([(u - c.u) / su, (v - c.v) / sv])
}

/// `pose` moved by the 6-vector `x` (rotation vector, rad; translation, mm; camera frame).
fn moved(pose: &Isometry3<f64>, x: &Vector6<f64>) -> Isometry3<f64> {
    let delta = Isometry3::from_parts(
        Translation3::new(x[3], x[4], x[5]),
        UnitQuaternion::from_scaled_axis(Vector3::new(x[0], x[1], x[2])),
    );
    delta * pose
}

/// Step 2: Gauss–Newton on the normalised residuals with Huber weights (k = 2), Jacobians by
/// central differences.
fn fit_pose(cs: &[Constraint], mut pose: Isometry3<f64>, pitch_mm: f64) -> Isometry3<f64> {
    let scale = (pose.translation.vector.norm()).max(1.0);
    let steps = Vector6::new(1e-6, 1e-6, 1e-6, 1e-6 * scale, 1e-6 * scale, 1e-6 * scale);
    for _ in 0..30 {
        let (jtj, jtr) = cs
            .par_iter()
            .filter_map(|c| {
                let r = c.residual(&pose, pitch_mm)?;
                let mut j = [[0.0; 6]; 2];
                for k in 0..6 {
                    let mut e = Vector6::zeros();
                    e[k] = steps[k];
                    let p = c.residual(&moved(&pose, &e), pitch_mm)?;
                    let m = c.residual(&moved(&pose, &-e), pitch_mm)?;
                    for a in 0..2 {
                        j[a][k] = (p[a] - m[a]) / (2.0 * steps[k]);
                    }
                }
                let w = |x: f64| if x.abs() <= 2.0 { 1.0 } else { 2.0 / x.abs() };
                let mut jtj = Matrix6::zeros();
                let mut jtr = Vector6::zeros();
                for a in 0..2 {
                    let row = Vector6::from_row_slice(&j[a]);
                    jtj += w(r[a]) * row * row.transpose();
                    jtr += w(r[a]) * row * r[a];
                }
                Some((jtj, jtr))
            })
            .reduce(
                || (Matrix6::zeros(), Vector6::zeros()),
                |a, b| (a.0 + b.0, a.1 + b.1),
            );
        let Some(step) = jtj.cholesky().map(|ch| ch.solve(&-jtr)) else {
            break;
        };
        pose = moved(&pose, &step);
        if step.fixed_rows::<3>(0).norm() < 1e-10 && step.fixed_rows::<3>(3).norm() < 1e-7 * scale {
            break;
        }
    }
    pose
}

/// Step 3: the residuals of the fitted pose, in monitor pixels and normalised, and the flag.
fn summarise(
    (cs, edges): (&[Correspondence], &[EdgeLine]),
    pose: Isometry3<f64>,
    code: &GrayCode,
    pitch_mm: f64,
    decoded_share: f64,
    complete_share: f64,
    points: usize,
) -> ScreenCalibration {
    let mut px = Vec::with_capacity(cs.len());
    let mut norm = Vec::with_capacity(cs.len());
    for c in cs {
        if let (Some((u, v)), Some(r)) = (
            monitor_hit(&c.ray, &pose, pitch_mm),
            normalised_residual(c, &pose, pitch_mm),
        ) {
            px.push((u - c.u).hypot(v - c.v));
            norm.push(r[0].hypot(r[1]) / std::f64::consts::SQRT_2);
        }
    }
    let quantile = |v: &mut Vec<f64>, q: f64| {
        v.sort_by(f64::total_cmp);
        v.get(((v.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    let mut edge_px: Vec<f64> = edges
        .iter()
        .filter_map(|e| Some(Constraint::Edge(*e).residual(&pose, pitch_mm)?[0].abs() * e.sigma))
        .collect();
    let rms_normalised =
        (norm.iter().map(|x| x * x).sum::<f64>() / norm.len().max(1) as f64).sqrt();
    let median_normalised = quantile(&mut norm, 0.5);
    let mut cells: Vec<f64> = cs.iter().map(|c| c.cell_u.max(c.cell_v)).collect();
    let warning = (median_normalised > 1.0).then(|| {
        format!(
            "the monitor pose leaves residuals larger than the decoded cells (median {median_normalised:.2} cell standard deviations): check the camera calibration, the pitch, and reflections on the monitor"
        )
    });
    ScreenCalibration {
        screen: Screen {
            width_px: code.width,
            height_px: code.height,
            pitch_mm,
            pose,
        },
        rms_normalised,
        median_residual_px: quantile(&mut px, 0.5),
        p95_residual_px: quantile(&mut px, 0.95),
        median_cell_px: quantile(&mut cells, 0.5),
        decoded_share,
        complete_share,
        points,
        fitted: cs.len(),
        edges: edges.len(),
        edge_median_residual_px: quantile(&mut edge_px, 0.5),
        warning,
    }
}
