//! `calibrate camera`: intrinsics and lens distortion from chessboard images, through OpenCV's
//! `calibrateCamera` with the flags of OpenCV's calibration sample, so that its results and its
//! YAML keys match the sample's. Corners are found as [`Board::find_corners`] says: every board
//! OpenCV finds in a still, refined in a window sized from the board's squares.

use std::path::PathBuf;

use anyhow::{bail, Result};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Point2f, Point3f, Size, Vector};

use super::board::{square_side_px, Board, BoardImage};
use crate::rig::calib_io::CameraRecord;
use crate::rig::Camera;

/// Options of `calibrateCamera`.
#[derive(Clone, Copy, Debug, Default)]
pub struct CameraOptions {
    /// fx/fy held at 1 (OpenCV's `CALIB_FIX_ASPECT_RATIO` with aspect ratio 1).
    pub fix_aspect_ratio: bool,
    /// p1 = p2 = 0 (`CALIB_ZERO_TANGENT_DIST`).
    pub zero_tangent: bool,
    /// k3 = 0 (`CALIB_FIX_K3`): for narrow lenses, whose image corners reach too small a radius
    /// for the sixth-order term to be told apart from k1 and k2.
    pub fix_k3: bool,
}

impl CameraOptions {
    /// OpenCV's `flags` value for these options.
    pub fn flags(&self) -> i32 {
        let mut f = 0;
        if self.fix_aspect_ratio {
            f |= opencv::calib3d::CALIB_FIX_ASPECT_RATIO;
        }
        if self.zero_tangent {
            f |= opencv::calib3d::CALIB_ZERO_TANGENT_DIST;
        }
        if self.fix_k3 {
            f |= opencv::calib3d::CALIB_FIX_K3;
        }
        f
    }
}

/// One image's share of a calibration.
#[derive(Clone, Debug)]
pub struct ViewResult {
    pub path: PathBuf,
    /// RMS reprojection error of its corners, pixels.
    pub error_px: f64,
    /// Flagged: its error exceeds 2.5 × the median view's.
    pub outlier: bool,
}

/// A camera calibration: the camera, how well it fits, and the images used and skipped.
#[derive(Clone, Debug)]
pub struct CameraCalibration {
    pub camera: Camera,
    /// RMS reprojection error over every corner, pixels (OpenCV's `avg_reprojection_error`).
    pub rms_px: f64,
    pub views: Vec<ViewResult>,
    /// Images in which the whole board was not found.
    pub skipped: Vec<PathBuf>,
    /// What the YAML file records beyond the camera.
    pub record: CameraRecord,
    /// Median over the used images of the board's smallest square side, pixels.
    pub square_px: f64,
}

impl CameraCalibration {
    /// Why the fit is not to be trusted (reprojection error over
    /// [`super::MAX_RMS_SQUARE_SHARE`] of a square), with the likely cause and the fix; `None`
    /// when it is within the limit.
    pub fn problem(&self) -> Option<String> {
        super::rms_problem(
            self.rms_px,
            self.square_px,
            "squares too small or blurred for the corners, a board that is not flat, or a lens the model does not fit (try without --fix-k3 or --zero-tangent)",
        )
    }
}

/// The smallest number of usable board images.
pub const MIN_IMAGES: usize = 3;

/// Calibrates from `images` (grey, all `size` = (width, height)).
pub fn calibrate_camera(
    images: &[BoardImage],
    size: (u32, u32),
    board: &Board,
    o: &CameraOptions,
    progress: impl FnMut(usize),
) -> Result<CameraCalibration> {
    let found = find_boards(images, board, progress)?;
    let solved = solve(&found, size, o)?;
    let median = crate::util::median(solved.errors.clone());
    let views = found
        .used
        .iter()
        .zip(&solved.errors)
        .map(|(p, &e)| ViewResult {
            path: p.clone(),
            error_px: e,
            outlier: e > 2.5 * median,
        })
        .collect();
    Ok(CameraCalibration {
        camera: solved.camera,
        rms_px: solved.rms,
        views,
        skipped: found.skipped,
        square_px: crate::util::median(found.square_px.clone()),
        record: CameraRecord {
            nframes: found.used.len(),
            board_width: board.cols,
            board_height: board.rows,
            square_size: board.square_mm,
            aspect_ratio: o.fix_aspect_ratio.then_some(1.0),
            flags: o.flags(),
            per_view_errors: solved.errors,
            extrinsics: solved.extrinsics,
        },
    })
}

/// The boards found in the images: OpenCV's point lists and the images used and skipped.
struct FoundBoards {
    object_points: Vector<Vector<Point3f>>,
    image_points: Vector<Vector<Point2f>>,
    used: Vec<PathBuf>,
    skipped: Vec<PathBuf>,
    /// Per used image, the board's smallest square side, pixels.
    square_px: Vec<f64>,
}

/// Finds the board's corners in every image; an error when fewer than [`MIN_IMAGES`] show it.
fn find_boards(
    images: &[BoardImage],
    board: &Board,
    mut progress: impl FnMut(usize),
) -> Result<FoundBoards> {
    let object: Vector<Point3f> = board
        .object_points()
        .iter()
        .map(|p| Point3f::new(p.x as f32, p.y as f32, p.z as f32))
        .collect();
    let mut f = FoundBoards {
        object_points: Vector::new(),
        image_points: Vector::new(),
        used: Vec::new(),
        skipped: Vec::new(),
        square_px: Vec::new(),
    };
    for (i, im) in images.iter().enumerate() {
        match board.find_corners(&im.image)? {
            Some(c) => {
                f.square_px.push(square_side_px(&c, board.cols as usize));
                let corners = c.iter().map(|p| Point2f::new(p.x as f32, p.y as f32));
                f.image_points.push(corners.collect());
                f.object_points.push(object.clone());
                f.used.push(im.path.clone());
            }
            None => f.skipped.push(im.path.clone()),
        }
        progress(i);
    }
    if f.used.len() < MIN_IMAGES {
        bail!(
            "the {}×{} board was found in {} of {} images; calibration needs at least {MIN_IMAGES} (check --board: it counts inner corners, e.g. 9x6 for a board of 10×7 squares)",
            board.cols,
            board.rows,
            f.used.len(),
            images.len()
        );
    }
    Ok(f)
}

/// What `calibrateCamera` found.
struct Solved {
    camera: Camera,
    rms: f64,
    /// Per used image: RMS reprojection error (px) and board pose (rotation vector, translation).
    errors: Vec<f64>,
    extrinsics: Vec<[f64; 6]>,
}

/// OpenCV's `calibrateCamera` on the found boards, checked to be finite.
fn solve(found: &FoundBoards, size: (u32, u32), o: &CameraOptions) -> Result<Solved> {
    // fx/fy = 1 when the aspect ratio is fixed (OpenCV reads only that ratio from it).
    let mut k = Mat::from_slice_2d(&[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])?;
    let mut dist = Mat::from_slice(&[0.0f64; 5])?.reshape(1, 5)?.try_clone()?;
    let (mut rvecs, mut tvecs) = (Vector::<Mat>::new(), Vector::<Mat>::new());
    let (mut sd_in, mut sd_ex, mut per_view) = (Mat::default(), Mat::default(), Mat::default());
    let criteria = super::criteria(30, f64::EPSILON)?;
    let rms = opencv::calib3d::calibrate_camera_extended(
        &found.object_points,
        &found.image_points,
        Size::new(size.0 as i32, size.1 as i32),
        &mut k,
        &mut dist,
        &mut rvecs,
        &mut tvecs,
        &mut sd_in,
        &mut sd_ex,
        &mut per_view,
        o.flags(),
        criteria,
    )?;
    let kk: Vec<f64> = k.data_typed::<f64>()?.to_vec();
    let dd: Vec<f64> = dist.data_typed::<f64>()?.to_vec();
    if !rms.is_finite() || kk.iter().chain(&dd).any(|v| !v.is_finite()) {
        bail!("calibration diverged (non-finite result): the board poses may be too similar; vary the tilt between images");
    }
    let mut d5 = [0.0; 5];
    for (d, v) in d5.iter_mut().zip(&dd) {
        *d = *v;
    }
    let extrinsics = rvecs
        .iter()
        .zip(tvecs.iter())
        .map(|(r, t)| -> Result<[f64; 6]> {
            let (r, t) = (r.data_typed::<f64>()?, t.data_typed::<f64>()?);
            Ok([r[0], r[1], r[2], t[0], t[1], t[2]])
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Solved {
        camera: Camera {
            width: size.0,
            height: size.1,
            fx: kk[0],
            fy: kk[4],
            cx: kk[2],
            cy: kk[5],
            dist: d5,
        },
        rms,
        errors: per_view.data_typed::<f64>()?.to_vec(),
        extrinsics,
    })
}
