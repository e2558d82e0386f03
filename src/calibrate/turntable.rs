//! `calibrate turntable`: the rotation axis from a chessboard turned on the turntable, one image
//! per known angle. Each image's board pose (OpenCV PnP) starts a joint least-squares fit
//! (Levenberg–Marquardt, in-house): one axis (direction and point), one board pose at angle 0,
//! and every corner of every image reprojected through the lens model — with, unless asked not
//! to, the sub-pixel points along the board's grid lines ([`super::grid_edges`]) beside them.
//!
//! Convention (as [`crate::rig::Turntable`]): at angle θ the board is turned by θ right-handed
//! about the axis direction. The reported axis point is the one nearest the board's origin at
//! angle 0 (for a board lying on the platter: the platter's centre at the board's height).

use std::path::PathBuf;

use anyhow::{bail, Result};
use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix3, Point2, Point3, Translation3, Unit, UnitQuaternion,
    Vector3,
};
use opencv::core::{Mat, Point2d, Point3d, Vector};

use super::board::{square_side_px, Board, BoardImage};
use super::grid_edges::{grid_edges, GridEdge};
use super::{camera_mats, pose_from_vectors};
use crate::rig::Camera;

/// One image's share of the fit.
#[derive(Clone, Debug)]
pub struct TurntableView {
    pub path: PathBuf,
    /// The angle given for it, degrees.
    pub angle_deg: f64,
    /// The angle about the fitted axis that best fits its corners (the fitted board turned
    /// alone) minus the given angle, degrees.
    pub angle_residual_deg: f64,
    /// RMS reprojection error of its corners under the joint fit, pixels.
    pub rms_px: f64,
}

/// A fitted turntable axis.
#[derive(Clone, Debug)]
pub struct TurntableCalibration {
    /// Camera frame, mm.
    pub axis_point: Point3<f64>,
    pub axis_dir: Unit<Vector3<f64>>,
    /// RMS reprojection error over every corner, pixels.
    pub rms_px: f64,
    /// Grid-line points fitted beside the corners, and their RMS distance from the fitted
    /// lines, pixels (NaN without them).
    pub edges: usize,
    pub edge_rms_px: f64,
    pub views: Vec<TurntableView>,
    /// Images in which the board was not found.
    pub skipped: Vec<PathBuf>,
    /// Median over the used images of the board's smallest square side, pixels.
    pub square_px: f64,
}

impl TurntableCalibration {
    /// Why the fit is not to be trusted (reprojection error over [`super::MAX_RMS_SQUARE_SHARE`]
    /// of a square, or an image's angle off by more than [`super::MAX_ANGLE_RESIDUAL_DEG`]), with
    /// the likely cause and the fix; `None` when it is within both limits.
    pub fn problem(&self) -> Option<String> {
        let worst = self.views.iter().max_by(|a, b| {
            a.angle_residual_deg
                .abs()
                .total_cmp(&b.angle_residual_deg.abs())
        })?;
        if worst.angle_residual_deg.abs() > super::MAX_ANGLE_RESIDUAL_DEG {
            return Some(format!(
                "{} turned {:+.2}° from its given angle {}° (at most {}° is trusted): the angles likely do not match the images — give one per image in the images' name order, with the turntable's sense of rotation",
                worst.path.display(),
                worst.angle_residual_deg,
                worst.angle_deg,
                super::MAX_ANGLE_RESIDUAL_DEG
            ));
        }
        super::rms_problem(
            self.rms_px,
            self.square_px,
            "squares too small or blurred for the corners, a board that moved on the platter, or wrong angles",
        )
    }
}

/// Observed corners of one image.
struct Observation {
    theta: f64,
    corners: Vec<Point2<f64>>,
    /// The board's smallest square side in the image, pixels.
    square_px: f64,
    pose: Isometry3<f64>,
    /// Points on the board's grid lines (empty when the fit uses the corners alone).
    edges: Vec<GridEdge>,
}

/// Rotation by `theta` about the axis through `c` along `d`.
fn about_axis(d: &Unit<Vector3<f64>>, c: &Point3<f64>, theta: f64) -> Isometry3<f64> {
    let r = UnitQuaternion::from_axis_angle(d, theta);
    Isometry3::from_parts(Translation3::from(c.coords - r * c.coords), r)
}

/// Which image measurements the axis is fitted to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fitted {
    /// The corners and the points along the grid lines (the default).
    CornersAndEdges,
    /// The corners alone (`--corners-only`: for a board whose squares are not plain black and
    /// white, or to compare).
    Corners,
}

/// Fits the axis to `images` taken at `angles_deg` (one per image, same order).
pub fn calibrate_turntable(
    images: &[BoardImage],
    angles_deg: &[f64],
    board: &Board,
    camera: &Camera,
    fitted: Fitted,
) -> Result<TurntableCalibration> {
    if angles_deg.len() != images.len() {
        bail!(
            "{} angles for {} images: give one angle per image, in the images' name order",
            angles_deg.len(),
            images.len()
        );
    }
    let object = board.object_points();
    let Observed { obs, used, skipped } =
        observe(images, angles_deg, (board, &object), camera, fitted)?;
    if obs.len() < 3 {
        bail!(
            "the board was found in {} of {} images; the axis needs at least 3",
            obs.len(),
            images.len()
        );
    }
    let poses: Vec<Isometry3<f64>> = obs.iter().map(|o| o.pose).collect();
    let thetas: Vec<f64> = obs.iter().map(|o| o.theta).collect();
    let (d0, c0) = axis_of_motions(&poses, Some(&thetas))?;
    let base0 = about_axis(&d0, &c0, -obs[0].theta) * obs[0].pose;
    let fit = Fit {
        obs: &obs,
        object: &object,
        camera,
        d0,
        c0,
        base0,
    };
    let x = fit.solve()?;
    let (d, c, base) = fit.params(&x);
    // The axis point nearest the board's origin at angle 0.
    let o = base.translation.vector;
    let c = c + d.into_inner() * d.dot(&(o - c.coords));
    let residuals = fit.residuals(&x);
    let views = fit.view_reports(&x, (&d, &base), used, &residuals);
    let corners = obs.len() * object.len();
    let squares = |r: &[f64]| r.iter().map(|e| e * e).sum::<f64>();
    // Two residuals (x, y) a corner, one a grid point.
    let (at_corners, at_edges) = residuals.as_slice().split_at(2 * corners);
    Ok(TurntableCalibration {
        axis_point: c,
        axis_dir: d,
        rms_px: (squares(at_corners) / corners as f64).sqrt(),
        edges: at_edges.len(),
        edge_rms_px: (squares(at_edges) / at_edges.len() as f64).sqrt(),
        views,
        skipped,
        square_px: crate::util::median(obs.iter().map(|o| o.square_px).collect()),
    })
}

/// The board as [`observe`] found it in a turntable's images.
struct Observed {
    obs: Vec<Observation>,
    /// The images the board was found in, with their given angles (degrees), in `obs`' order.
    used: Vec<(PathBuf, f64)>,
    /// The images it was not found in.
    skipped: Vec<PathBuf>,
}

/// The board in each of `images` (taken at `angles_deg`): its corners and its pose by PnP with
/// the calibrated `camera` (`object`: the board's corners in its own frame, mm), and the points
/// along its grid lines when they are `fitted`.
fn observe(
    images: &[BoardImage],
    angles_deg: &[f64],
    (board, object): (&Board, &[Point3<f64>]),
    camera: &Camera,
    fitted: Fitted,
) -> Result<Observed> {
    let object_cv: Vector<Point3d> = object.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect();
    let (k, dist) = camera_mats(camera)?;
    let (mut obs, mut used, mut skipped) = (Vec::new(), Vec::new(), Vec::new());
    for (im, &a) in images.iter().zip(angles_deg) {
        let Some(corners) = board.find_corners(&im.image)? else {
            skipped.push(im.path.clone());
            continue;
        };
        let image_cv: Vector<Point2d> = corners.iter().map(|p| Point2d::new(p.x, p.y)).collect();
        let (mut rvec, mut tvec) = (Mat::default(), Mat::default());
        opencv::calib3d::solve_pnp(
            &object_cv,
            &image_cv,
            &k,
            &dist,
            &mut rvec,
            &mut tvec,
            false,
            opencv::calib3d::SOLVEPNP_ITERATIVE,
        )?;
        let pose = pose_from_vectors(&rvec, &tvec)?;
        let edges = match fitted {
            Fitted::CornersAndEdges => grid_edges(&im.image, board, camera, &pose)?,
            Fitted::Corners => Vec::new(),
        };
        obs.push(Observation {
            theta: a.to_radians(),
            square_px: square_side_px(&corners, board.cols as usize),
            corners,
            pose,
            edges,
        });
        used.push((im.path.clone(), a));
    }
    Ok(Observed { obs, used, skipped })
}

/// The rotation axis of rigid motions (`poses[k]` = the rotation about the axis by
/// θk − θ0 after `poses[0]`): its direction from the relative rotations to the first pose,
/// oriented by `thetas` when given (else along the first clear rotation), and its point by
/// least squares on the relative motions' fixed points, at the height of `poses[0]`'s origin.
pub fn axis_of_motions(
    poses: &[Isometry3<f64>],
    thetas: Option<&[f64]>,
) -> Result<(Unit<Vector3<f64>>, Point3<f64>)> {
    let first = &poses[0];
    let mut sum = Vector3::zeros();
    for (k, p) in poses.iter().enumerate().skip(1) {
        let v = (p.rotation * first.rotation.inverse()).scaled_axis();
        let weight = match thetas {
            Some(t) if (t[k] - t[0]).abs() > 1f64.to_radians() => t[k] - t[0],
            Some(_) => continue,
            None if sum.norm() > 0.0 => v.norm() * v.dot(&sum).signum(),
            None => v.norm(),
        };
        if v.norm() > 1e-3 {
            sum += v.normalize() * weight;
        }
    }
    let Some(d) = Unit::try_new(sum, 1e-9) else {
        bail!("the poses do not turn: give views at angles at least a few degrees apart");
    };
    let n = poses.len() - 1;
    let mut a = DMatrix::zeros(3 * n + 1, 3);
    let mut b = DVector::zeros(3 * n + 1);
    for (i, p) in poses[1..].iter().enumerate() {
        let rel = p * first.inverse();
        let m = Matrix3::identity() - rel.rotation.to_rotation_matrix().into_inner();
        a.view_mut((3 * i, 0), (3, 3)).copy_from(&m);
        b.rows_mut(3 * i, 3).copy_from(&rel.translation.vector);
    }
    a.row_mut(3 * n).copy_from(&d.transpose());
    b[3 * n] = d.dot(&first.translation.vector);
    let c = a
        .svd(true, true)
        .solve(&b, 1e-12)
        .map_err(|e| anyhow::anyhow!("axis point: {e}"))?;
    Ok((d, Point3::new(c[0], c[1], c[2])))
}

/// The joint fit: parameters are small changes of the axis direction (2, radians), the axis
/// point across the axis (2, mm), and the board pose at angle 0 (rotation vector 3, translation
/// 3 mm), all about the initial guess.
struct Fit<'a> {
    obs: &'a [Observation],
    object: &'a [Point3<f64>],
    camera: &'a Camera,
    d0: Unit<Vector3<f64>>,
    c0: Point3<f64>,
    base0: Isometry3<f64>,
}

impl Fit<'_> {
    const N: usize = 10;

    /// Per image `used` (its path and given angle, in the observations' order), the angle the
    /// fitted parameters `x` (the axis direction `d` and the board's pose at angle 0 `base`
    /// among them) put it at against the given one, and its reprojection RMS from the fit's
    /// `residuals` (pixels).
    fn view_reports(
        &self,
        x: &DVector<f64>,
        (d, base): (&Unit<Vector3<f64>>, &Isometry3<f64>),
        used: Vec<(PathBuf, f64)>,
        residuals: &DVector<f64>,
    ) -> Vec<TurntableView> {
        let per_image = 2 * self.object.len();
        used.into_iter()
            .zip(self.obs)
            .zip(residuals.as_slice().chunks(per_image))
            .map(|(((path, angle_deg), ob), r)| {
                let rel = ob.pose.rotation * base.rotation.inverse();
                let v = rel.scaled_axis();
                let from_pnp = v.norm() * v.dot(d).signum();
                let measured = self.image_angle(x, ob, from_pnp);
                let diff = (measured.to_degrees() - angle_deg + 180.0).rem_euclid(360.0) - 180.0;
                let squares = r.iter().map(|e| e * e).sum::<f64>();
                TurntableView {
                    path,
                    angle_deg,
                    angle_residual_deg: diff,
                    rms_px: (squares / self.object.len() as f64).sqrt(),
                }
            })
            .collect()
    }

    fn basis(&self) -> (Vector3<f64>, Vector3<f64>) {
        let d = self.d0.into_inner();
        let e1 = if d.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let e1 = (e1 - d * d.dot(&e1)).normalize();
        (e1, d.cross(&e1))
    }

    fn params(&self, x: &DVector<f64>) -> (Unit<Vector3<f64>>, Point3<f64>, Isometry3<f64>) {
        let (e1, e2) = self.basis();
        let d = Unit::new_normalize(self.d0.into_inner() + e1 * x[0] + e2 * x[1]);
        let c = self.c0 + e1 * x[2] + e2 * x[3];
        let rot =
            UnitQuaternion::from_scaled_axis(Vector3::new(x[4], x[5], x[6])) * self.base0.rotation;
        let t = self.base0.translation.vector + Vector3::new(x[7], x[8], x[9]);
        (d, c, Isometry3::from_parts(Translation3::from(t), rot))
    }

    /// Reprojection residuals (pixels): image by image, corner by corner, x then y; then image
    /// by image each grid-line point's distance from its line. A point behind the camera
    /// counts as 1e6 px.
    fn residuals(&self, x: &DVector<f64>) -> DVector<f64> {
        let (d, c, base) = self.params(x);
        let poses: Vec<Isometry3<f64>> = (self.obs.iter())
            .map(|o| about_axis(&d, &c, o.theta) * base)
            .collect();
        let mut r = Vec::with_capacity(2 * self.obs.len() * self.object.len());
        for (o, pose) in self.obs.iter().zip(&poses) {
            for (p, q) in self.object.iter().zip(&o.corners) {
                let e = self.camera.project(&(pose * p)).map(|u| u - q);
                r.extend(e.map_or([1e6, 1e6], |e| [e.x, e.y]));
            }
        }
        for (o, pose) in self.obs.iter().zip(&poses) {
            r.extend(
                o.edges
                    .iter()
                    .map(|e| e.residual(self.camera, pose).unwrap_or(1e6)),
            );
        }
        DVector::from_vec(r)
    }

    /// The angle (radians) about the fitted axis at which the fitted board (parameters `x`)
    /// best fits `o`'s corners: Newton's method on the reprojection error from `start` (the
    /// image's own PnP pose's angle), with central differences.
    fn image_angle(&self, x: &DVector<f64>, o: &Observation, start: f64) -> f64 {
        let (d, c, base) = self.params(x);
        let cost = |theta: f64| -> f64 {
            let pose = about_axis(&d, &c, theta) * base;
            self.object
                .iter()
                .zip(&o.corners)
                .map(|(p, q)| match self.camera.project(&(pose * p)) {
                    Some(u) => (u - q).norm_squared(),
                    None => 1e12,
                })
                .sum()
        };
        let (mut theta, h) = (start, 1e-5);
        for _ in 0..20 {
            let (lo, mid, hi) = (cost(theta - h), cost(theta), cost(theta + h));
            let (g, curv) = ((hi - lo) / (2.0 * h), (hi - 2.0 * mid + lo) / (h * h));
            if curv.is_nan() || curv <= 0.0 {
                break;
            }
            let step = (-g / curv).clamp(-0.05, 0.05);
            theta += step;
            if step.abs() < 1e-9 {
                break;
            }
        }
        theta
    }

    /// Levenberg–Marquardt with central-difference Jacobians.
    fn solve(&self) -> Result<DVector<f64>> {
        let steps = [1e-7, 1e-7, 1e-5, 1e-5, 1e-7, 1e-7, 1e-7, 1e-5, 1e-5, 1e-5];
        let mut x = DVector::zeros(Self::N);
        let mut r = self.residuals(&x);
        let mut cost = r.norm_squared();
        let mut mu = 1e-3;
        for _ in 0..200 {
            let mut j = DMatrix::zeros(r.len(), Self::N);
            for (p, h) in steps.iter().enumerate() {
                let (mut a, mut b) = (x.clone(), x.clone());
                a[p] += h;
                b[p] -= h;
                j.set_column(p, &((self.residuals(&a) - self.residuals(&b)) / (2.0 * h)));
            }
            let jtj = j.transpose() * &j;
            let g = j.transpose() * &r;
            let mut improved = false;
            for _ in 0..20 {
                let mut m = jtj.clone();
                for p in 0..Self::N {
                    m[(p, p)] += mu * jtj[(p, p)].max(1e-12);
                }
                let Some(step) = m.cholesky().map(|ch| ch.solve(&(-&g))) else {
                    mu *= 10.0;
                    continue;
                };
                let xn = &x + &step;
                let rn = self.residuals(&xn);
                let cn = rn.norm_squared();
                if cn.is_finite() && cn < cost {
                    let done = cost - cn < 1e-14 * cost.max(1e-300);
                    (x, r, cost) = (xn, rn, cn);
                    mu = (mu / 3.0).max(1e-12);
                    improved = !done;
                    break;
                }
                mu *= 4.0;
            }
            if !improved {
                break;
            }
        }
        if !cost.is_finite() {
            bail!("the axis fit diverged");
        }
        Ok(x)
    }
}
