//! Chessboard images: listing them, finding the board's inner corners (OpenCV, refined to
//! sub-pixel), and the corners' positions on the board.
//!
//! Board frame: origin at the first inner corner OpenCV reports, x along the `cols` corners of a
//! row, y along the rows, z = x × y (into the board as the camera sees it), mm.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use nalgebra::{Point2, Point3};
use opencv::core::{Mat, MatTraitConst, Point2f, Size, Vector};

/// A chessboard: inner corners per row (`cols`) and per column (`rows`), square size in mm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Board {
    pub cols: u32,
    pub rows: u32,
    pub square_mm: f64,
}

impl Board {
    /// Parses `COLSxROWS` (inner corners, each at least 2).
    pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
        let (a, b) = s
            .split_once(['x', 'X'])
            .ok_or_else(|| format!("'{s}': expected COLSxROWS inner corners, e.g. 9x6"))?;
        let parse = |t: &str| {
            t.trim()
                .parse::<u32>()
                .ok()
                .filter(|&n| n >= 2)
                .ok_or_else(|| format!("'{s}': each count must be a whole number ≥ 2"))
        };
        Ok((parse(a)?, parse(b)?))
    }

    /// The inner corners on the board, in OpenCV's order (row by row), board frame, mm.
    pub fn object_points(&self) -> Vec<Point3<f64>> {
        (0..self.rows)
            .flat_map(|i| {
                (0..self.cols).map(move |j| {
                    Point3::new(j as f64 * self.square_mm, i as f64 * self.square_mm, 0.0)
                })
            })
            .collect()
    }

    /// The inner corners of `image` (8-bit grey), sub-pixel refined as OpenCV's calibration
    /// sample does (adaptive threshold, normalised image, fast check; 11×11 window); `None` if
    /// the whole board is not found.
    pub fn find_corners(&self, image: &Mat) -> Result<Option<Vec<Point2<f64>>>> {
        let size = Size::new(self.cols as i32, self.rows as i32);
        let mut corners = Vector::<Point2f>::new();
        let flags = opencv::calib3d::CALIB_CB_ADAPTIVE_THRESH
            | opencv::calib3d::CALIB_CB_NORMALIZE_IMAGE
            | opencv::calib3d::CALIB_CB_FAST_CHECK;
        if !opencv::calib3d::find_chessboard_corners(image, size, &mut corners, flags)? {
            return Ok(None);
        }
        let criteria = super::criteria(30, 1e-4)?;
        opencv::imgproc::corner_sub_pix(
            image,
            &mut corners,
            Size::new(11, 11),
            Size::new(-1, -1),
            criteria,
        )?;
        Ok(Some(
            corners
                .iter()
                .map(|p| Point2::new(p.x as f64, p.y as f64))
                .collect(),
        ))
    }
}

/// An image of a calibration set, read as 8-bit grey.
pub struct BoardImage {
    pub path: PathBuf,
    pub image: Mat,
}

/// The files matching `pattern` (a glob such as `calib/left*.jpg`), sorted by name, read as grey
/// images of one size; errors name the pattern, the unreadable file or the odd size out.
pub fn read_images(pattern: &str) -> Result<(Vec<BoardImage>, (u32, u32))> {
    let paths: Vec<PathBuf> = glob::glob(pattern)
        .with_context(|| format!("'{pattern}' is not a valid file pattern"))?
        .filter_map(|p| p.ok())
        .filter(|p| p.is_file())
        .collect();
    if paths.is_empty() {
        bail!("no file matches '{pattern}' (quote the pattern so the shell passes it as is)");
    }
    let mut images = Vec::with_capacity(paths.len());
    let mut size = None;
    for path in paths {
        let image = read_grey(&path)?;
        let s = (image.cols() as u32, image.rows() as u32);
        match size {
            None => size = Some((s, path.clone())),
            Some((first, ref first_path)) if first != s => bail!(
                "{}: {}×{} pixels, but {} is {}×{}: a calibration set comes from one camera at one resolution",
                path.display(),
                s.0,
                s.1,
                Path::display(first_path),
                first.0,
                first.1
            ),
            _ => {}
        }
        images.push(BoardImage { path, image });
    }
    Ok((images, size.expect("at least one image").0))
}

/// Reads an image file as 8-bit grey; names the file if it cannot.
pub fn read_grey(path: &Path) -> Result<Mat> {
    let m = opencv::imgcodecs::imread(path, opencv::imgcodecs::IMREAD_GRAYSCALE)
        .with_context(|| format!("cannot read {}", path.display()))?;
    if m.empty() {
        bail!("{}: not a readable image", path.display());
    }
    Ok(m)
}
