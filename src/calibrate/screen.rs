//! `calibrate screen`: the monitor's pose from the background capture (the patterns without the
//! object). Every camera pixel whose Gray code decodes completely sees the centre of a known
//! monitor pixel, a 2D–3D correspondence; a well-spread grid of them gives the pose by RANSAC
//! PnP, and a Levenberg–Marquardt refinement on every inlier pixel refines it (OpenCV).

use anyhow::{bail, Result};
use nalgebra::{Isometry3, Point3, Vector3};
use opencv::core::{Mat, MatTraitConst, Point2d, Point3d, Vector};
use rayon::prelude::*;

use super::{camera_mats, pose_from_vectors, reprojection_rms};
use crate::decode::DecodedCapture;
use crate::patterns::GrayCode;
use crate::rig::{Camera, Screen};

/// Correspondences RANSAC draws from (a grid over the decoded pixels).
pub const TARGET_POINTS: usize = 4000;
/// Correspondences the pose is refined on.
pub const REFINE_POINTS: usize = 60_000;
/// Reprojection error of an inlier, camera pixels.
pub const INLIER_PX: f64 = 2.0;
/// The smallest share of the image in which the monitor must decode.
pub const MIN_DECODED_SHARE: f64 = 0.05;

/// A monitor pose and how well it fits.
#[derive(Clone, Debug)]
pub struct ScreenCalibration {
    pub screen: Screen,
    /// RMS reprojection error of the inlier correspondences, camera pixels.
    pub rms_px: f64,
    /// Share of the image whose every Gray bit decodes.
    pub decoded_share: f64,
    /// Decoded pixels, and the inliers the pose is refined on (a sample of them).
    pub points: usize,
    pub inliers: usize,
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
    let complete: Vec<usize> = (0..cap.pixels.len())
        .filter(|&i| cap.lit[i] && cap.pixels[i].complete(code))
        .collect();
    let share = complete.len() as f64 / cap.pixels.len() as f64;
    if share < MIN_DECODED_SHARE {
        bail!(
            "the monitor decodes in {:.2} % of the background capture (at least {:.0} % needed): check that the monitor fills much of the camera view, the exposure, and that the patterns match the monitor ({}×{})",
            100.0 * share,
            100.0 * MIN_DECODED_SHARE,
            code.width,
            code.height
        );
    }
    let point = |i: usize| {
        let d = &cap.pixels[i];
        (
            Point3d::new(
                d.u.coord as f64 * pitch_mm,
                d.v.coord as f64 * pitch_mm,
                0.0,
            ),
            Point2d::new((i % cap.width) as f64, (i / cap.width) as f64),
        )
    };
    // RANSAC on a grid of them…
    let stride = ((complete.len() as f64 / TARGET_POINTS as f64)
        .sqrt()
        .floor() as usize)
        .max(1);
    let (object, image): (Vector<Point3d>, Vector<Point2d>) = complete
        .iter()
        .filter(|&&i| {
            (i % cap.width).is_multiple_of(stride) && (i / cap.width).is_multiple_of(stride)
        })
        .map(|&i| point(i))
        .unzip();
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
        INLIER_PX as f32,
        0.999,
        &mut inliers,
        opencv::calib3d::SOLVEPNP_ITERATIVE,
    )?;
    let ransac_inliers = if inliers.empty() { 0 } else { inliers.total() };
    if !found || ransac_inliers < 6 {
        bail!("no monitor pose fits the decoded background (RANSAC found {ransac_inliers} consistent points): check the camera calibration and the monitor pitch");
    }
    // …then the pose is refined on an irregular sample of the decoded pixels it explains (a
    // regular grid would alias with the monitor's pixel grid): every pixel whose index hashes
    // into a share of REFINE_POINTS / decoded.
    let guess = pose_from_vectors(&rvec, &tvec)?;
    let keep = (REFINE_POINTS as f64 / complete.len() as f64).min(1.0);
    let (obj_in, img_in): (Vector<Point3d>, Vector<Point2d>) = complete
        .par_iter()
        .filter(|&&i| {
            ((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11) as f64 / (1u64 << 53) as f64
                <= keep
        })
        .map(|&i| point(i))
        .filter(|(o, m)| {
            camera
                .project(&(guess * Point3::new(o.x, o.y, o.z)))
                .is_some_and(|p| (p.x - m.x).hypot(p.y - m.y) < INLIER_PX)
        })
        .collect::<Vec<_>>()
        .into_iter()
        .unzip();
    let criteria = super::criteria(100, 1e-12)?;
    opencv::calib3d::solve_pnp_refine_lm(
        &obj_in, &img_in, &k, &dist, &mut rvec, &mut tvec, criteria,
    )?;
    let pose: Isometry3<f64> = pose_from_vectors(&rvec, &tvec)?;
    let rms_px = reprojection_rms(&obj_in, &img_in, &rvec, &tvec, &k, &dist)?;
    // The monitor faces the camera: its z axis points away from it.
    if (pose.rotation * Vector3::z()).dot(&(pose * Point3::origin()).coords) <= 0.0 {
        bail!("the solved monitor faces away from the camera: the decoded rows or columns are mirrored (check the patterns' order)");
    }
    Ok(ScreenCalibration {
        screen: Screen {
            width_px: code.width,
            height_px: code.height,
            pitch_mm,
            pose,
        },
        rms_px,
        decoded_share: share,
        points: complete.len(),
        inliers: obj_in.len(),
    })
}
