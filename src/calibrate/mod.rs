//! Calibration of a rig (`glasscan calibrate …`): the camera from chessboard images, the
//! monitor's pose from a decoded background capture, the turntable axis from a board turned on
//! it. Frames and units as in [`crate::rig`]: camera frame (OpenCV), mm, pixels.

pub mod board;
pub mod camera;
pub mod grid_edges;
pub mod screen;
pub mod turntable;

use anyhow::Result;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, CV_64F};

use crate::rig::{Camera, Screen};

/// The largest RMS reprojection error a board fit may have before it is refused, as a share of
/// the board's square side in the image. Corners of a sharp, well-lit board fit to about 1 % of
/// a square; a window wider than the squares, a blurred or moving board, a wrong corner count or
/// wrong turntable angles give 10–60 %. A share, not pixels, so that it holds at any camera
/// resolution.
pub const MAX_RMS_SQUARE_SHARE: f64 = 0.05;

/// The largest difference (degrees) between a turntable image's measured turn and its given
/// angle before the fit is refused.
pub const MAX_ANGLE_RESIDUAL_DEG: f64 = 1.0;

/// Why a board fit with RMS error `rms_px` over squares `square_px` wide is not to be trusted,
/// or `None` within [`MAX_RMS_SQUARE_SHARE`]; `causes` lists the likely ones for the message.
pub fn rms_problem(rms_px: f64, square_px: f64, causes: &str) -> Option<String> {
    let share = rms_px / square_px;
    (share.is_nan() || share > MAX_RMS_SQUARE_SHARE).then(|| {
        format!(
            "the corners fit to {rms_px:.2} px RMS, {:.0} % of a square ({square_px:.1} px; at most {:.0} % is trusted): likely {causes}",
            100.0 * share,
            100.0 * MAX_RMS_SQUARE_SHARE
        )
    })
}

/// Why a turntable axis through `axis_point` (camera frame, mm) does not fit between the camera
/// and `screen`, or `None`. The board's square size sets the scale of every pose, and a wrong
/// `--square-mm` moves the axis along the camera's rays by the same factor; the monitor, placed
/// by its own pitch, shows it.
pub fn axis_beyond_monitor(axis_point: &nalgebra::Point3<f64>, screen: &Screen) -> Option<String> {
    let n = screen.pose.rotation * Vector3::z();
    let origin = screen.pose.translation.vector;
    // Signed distances to the monitor's plane, positive on the camera's side.
    let side = -n.dot(&origin).signum();
    let axis = side * n.dot(&(axis_point.coords - origin));
    (axis.is_nan() || axis <= 0.0).then(|| {
        format!(
            "the axis lies {:.0} mm behind the monitor: the board's square size sets every distance, so --square-mm is likely not the printed square's side (measure it across several squares)",
            -axis
        )
    })
}

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
