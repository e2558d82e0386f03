//! Calibration of a rig (`glasscan calibrate …`): the camera from chessboard images, the
//! monitor's pose from a decoded background capture, the turntable axis from a board turned on
//! it. Frames and units as in [`crate::rig`]: camera frame (OpenCV), mm, pixels.

pub mod board;
pub mod camera;
pub mod screen;
pub mod turntable;

use anyhow::Result;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Point2d, Point3d, Vector, CV_64F};

use crate::rig::Camera;

/// OpenCV's stopping rule: at most `iterations`, or a change below `eps`.
pub fn criteria(iterations: i32, eps: f64) -> Result<opencv::core::TermCriteria> {
    use opencv::core::{TermCriteria, TermCriteria_Type};
    Ok(TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        iterations,
        eps,
    )?)
}

/// OpenCV's camera matrix and distortion vector (5 × 1) of `c`.
pub fn camera_mats(c: &Camera) -> Result<(Mat, Mat)> {
    let k = Mat::from_slice_2d(&[[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])?;
    let d = Mat::from_slice(&c.dist)?.reshape(1, 5)?.try_clone()?;
    Ok((k, d))
}

/// The rigid transform of OpenCV's rotation vector and translation (`x_cam = R·x + t`).
pub fn pose_from_vectors(rvec: &Mat, tvec: &Mat) -> Result<Isometry3<f64>> {
    let as_f64 = |m: &Mat| -> Result<Vec<f64>> {
        let mut f = Mat::default();
        m.convert_to(&mut f, CV_64F, 1.0, 0.0)?;
        Ok(f.data_typed::<f64>()?.to_vec())
    };
    let (r, t) = (as_f64(rvec)?, as_f64(tvec)?);
    Ok(Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_scaled_axis(Vector3::new(r[0], r[1], r[2])),
    ))
}

/// RMS distance (pixels) between `image` and `object` projected with the pose and camera.
pub fn reprojection_rms(
    object: &Vector<Point3d>,
    image: &Vector<Point2d>,
    rvec: &Mat,
    tvec: &Mat,
    k: &Mat,
    dist: &Mat,
) -> Result<f64> {
    let mut projected = Vector::<Point2d>::new();
    opencv::calib3d::project_points(
        object,
        rvec,
        tvec,
        k,
        dist,
        &mut projected,
        &mut opencv::core::no_array(),
        0.0,
    )?;
    let sum: f64 = projected
        .iter()
        .zip(image.iter())
        .map(|(p, q)| (p.x - q.x).powi(2) + (p.y - q.y).powi(2))
        .sum();
    Ok((sum / image.len().max(1) as f64).sqrt())
}
