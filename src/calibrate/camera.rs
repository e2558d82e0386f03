//! `calibrate camera`: intrinsics and lens distortion from chessboard images, through OpenCV's
//! `calibrateCamera` with the flags of OpenCV's calibration sample, so that its results and its
//! YAML keys match the sample's. Corners are found as [`Board::find_corners`] says: every board
//! OpenCV finds in a still, refined in a window sized from the spacing of its corners. Unlike
//! the sample, a first fit's outlier images are left out of a second ([`calibrate_camera`]).

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
    /// Keep every image in the fit; otherwise the outliers of a first fit are left out of the
    /// second ([`calibrate_camera`]).
    pub keep_outliers: bool,
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
    /// Flagged: its error exceeds [`OUTLIER_FACTOR`] × the median view's.
    pub outlier: bool,
}

/// An image whose reprojection error exceeds this many times the median image's is an outlier.
pub const OUTLIER_FACTOR: f64 = 2.5;

/// A camera calibration: the camera, how well it fits, and the images used and skipped.
#[derive(Clone, Debug)]
pub struct CameraCalibration {
    pub camera: Camera,
    /// RMS reprojection error over every corner, pixels (OpenCV's `avg_reprojection_error`).
    pub rms_px: f64,
    pub views: Vec<ViewResult>,
    /// Images the first fit found outliers, left out of this one (with that fit's errors).
    pub left_out: Vec<ViewResult>,
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

/// Calibrates from `images` (grey, all `size` = (width, height)). Unless `o.keep_outliers`, a
/// first fit's outliers are left out and the camera fitted again without them, when they are at
/// most a quarter of the boards found (more is a set that disagrees throughout, not a few bad
/// images) and at least [`MIN_IMAGES`] remain: one round, so that a fit is never pared down.
pub fn calibrate_camera(
    images: &[BoardImage],
    size: (u32, u32),
    board: &Board,
    o: &CameraOptions,
    progress: impl FnMut(usize),
) -> Result<CameraCalibration> {
    let mut found = find_boards(images, board, progress)?;
    let mut solved = solve(&found, size, o)?;
    let mut left_out = Vec::new();
    if !o.keep_outliers {
        left_out = leave_out_outliers(&mut found, &solved.errors);
        if !left_out.is_empty() {
            solved = solve(&found, size, o)?;
        }
    }
    Ok(CameraCalibration {
        camera: solved.camera,
        rms_px: solved.rms,
        views: view_results(&found.used, &solved.errors),
        left_out,
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

/// Each used image's error, flagged above [`OUTLIER_FACTOR`] × the median.
fn view_results(used: &[PathBuf], errors: &[f64]) -> Vec<ViewResult> {
    let median = crate::util::median(errors.to_vec());
    used.iter()
        .zip(errors)
        .map(|(p, &e)| ViewResult {
            path: p.clone(),
            error_px: e,
            outlier: e > OUTLIER_FACTOR * median,
        })
        .collect()
}

/// Removes the outliers among `found`'s boards (by `errors`, a fit's per-image errors) when
/// they are at most a quarter of them and at least [`MIN_IMAGES`] remain; returns them.
fn leave_out_outliers(found: &mut FoundBoards, errors: &[f64]) -> Vec<ViewResult> {
    let views = view_results(&found.used, errors);
    let outliers = views.iter().filter(|v| v.outlier).count();
    if outliers == 0 || 4 * outliers > views.len() || views.len() - outliers < MIN_IMAGES {
        return Vec::new();
    }
    let keep: Vec<bool> = views.iter().map(|v| !v.outlier).collect();
    found.object_points = kept(found.object_points.iter(), &keep);
    found.image_points = kept(found.image_points.iter(), &keep);
    found.used = kept(std::mem::take(&mut found.used), &keep);
    found.square_px = kept(found.square_px.iter().copied(), &keep);
    views.into_iter().filter(|v| v.outlier).collect()
}

/// The `items` whose entry in `keep` is true, in order.
fn kept<T, C: FromIterator<T>>(items: impl IntoIterator<Item = T>, keep: &[bool]) -> C {
    items
        .into_iter()
        .zip(keep)
        .filter(|&(_, &k)| k)
        .map(|(x, _)| x)
        .collect()
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

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` found boards (without corners), named by their index.
    fn boards(n: usize) -> FoundBoards {
        FoundBoards {
            object_points: (0..n).map(|_| Vector::new()).collect(),
            image_points: (0..n).map(|_| Vector::new()).collect(),
            used: (0..n).map(|k| PathBuf::from(k.to_string())).collect(),
            skipped: Vec::new(),
            square_px: (0..n).map(|k| k as f64).collect(),
        }
    }

    #[test]
    fn outliers_are_left_out_only_when_few() {
        let mut found = boards(8);
        let errors = [0.1, 0.1, 0.12, 0.09, 0.1, 0.5, 0.11, 0.1];
        let left = leave_out_outliers(&mut found, &errors);
        assert_eq!(left.len(), 1);
        assert_eq!(left[0].path, PathBuf::from("5"));
        assert_eq!(found.used.len(), 7);
        assert_eq!(
            (found.object_points.len(), found.image_points.len()),
            (7, 7)
        );
        assert_eq!(found.square_px, [0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 7.0]);
        // Three of eight are more than a quarter: a set that disagrees, kept whole.
        let mut found = boards(8);
        let errors = [0.1, 0.5, 0.12, 0.09, 0.6, 0.5, 0.11, 0.1];
        assert!(leave_out_outliers(&mut found, &errors).is_empty());
        assert_eq!(found.used.len(), 8);
        // No outlier, nothing left out.
        let mut found = boards(4);
        assert!(leave_out_outliers(&mut found, &[0.1, 0.2, 0.15, 0.12]).is_empty());
    }
}
