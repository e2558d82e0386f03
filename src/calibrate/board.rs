//! Chessboard images: listing them, finding the board's inner corners (OpenCV, refined to
//! sub-pixel), and the corners' positions on the board. Why the steps are what they are:
//! docs/decisions.md#board-corners-and-the-fits-limits.
//!
//! Board frame: origin at the first inner corner, x along the `cols` corners of a row, y along
//! the rows, z = x × y (into the board as the camera sees it), mm. The first corner is the one
//! whose square (between the first two rows' first two corners) is dark, so the frame does not
//! flip between images of a board with `cols + rows` odd (a 9×6 board: 10×7 squares).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use nalgebra::{Point2, Point3};
use opencv::core::{Mat, MatTraitConst, Point2f, Size, Vector};

use crate::util::image::read_image;

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

    /// The inner corners of `image` (8-bit grey), sub-pixel refined, in a consistent order;
    /// `None` if the whole board is not found. The steps:
    ///
    /// 1. OpenCV's classic detector (adaptive threshold, normalised image) without its fast
    ///    check, which is meant for skipping video frames and rejects small boards in stills;
    ///    failing that, OpenCV's sector-based detector (`findChessboardCornersSB`); either's
    ///    corners are taken only if they lie on a grid ([`off_grid_share`] at most
    ///    [`MAX_OFF_GRID_SHARE`]);
    /// 2. the corners (either detector's) refined by `cornerSubPix` in a window sized from the
    ///    spacing of the board's own corners ([`corner_spacing_px`], [`subpixel_half_window`]),
    ///    so that it never reaches a neighbouring corner;
    /// 3. the order turned by 180° where needed so that the square spanned by the first two
    ///    rows' first two corners is the darker one ([`orient_dark_first`]): the board frame
    ///    does not flip between images.
    pub fn find_corners(&self, image: &Mat) -> Result<Option<Vec<Point2<f64>>>> {
        let Some(corners) = self.detect(image)? else {
            return Ok(None);
        };
        let corners: Vec<Point2<f64>> = corners
            .iter()
            .map(|p| Point2::new(p.x as f64, p.y as f64))
            .collect();
        let mut corners = refine_corners(image, &corners, self.cols as usize)?;
        orient_dark_first(image, &mut corners, self.cols as usize, self.rows as usize)?;
        Ok(Some(corners))
    }

    /// Step 1 of [`find_corners`](Self::find_corners): the raw corners. (The sector-based
    /// detector's come refined, but on small, oblique boards about ten times less precisely
    /// than `cornerSubPix` refines them.)
    fn detect(&self, image: &Mat) -> Result<Option<Vector<Point2f>>> {
        use opencv::calib3d as c3;
        let size = Size::new(self.cols as i32, self.rows as i32);
        let mut corners = Vector::<Point2f>::new();
        let flags = c3::CALIB_CB_ADAPTIVE_THRESH | c3::CALIB_CB_NORMALIZE_IMAGE;
        if c3::find_chessboard_corners(image, size, &mut corners, flags)?
            && self.on_grid(&corners)?
        {
            return Ok(Some(corners));
        }
        let mut corners = Vector::<Point2f>::new();
        let flags = c3::CALIB_CB_NORMALIZE_IMAGE | c3::CALIB_CB_EXHAUSTIVE | c3::CALIB_CB_ACCURACY;
        if c3::find_chessboard_corners_sb(image, size, &mut corners, flags)?
            && self.on_grid(&corners)?
        {
            return Ok(Some(corners));
        }
        Ok(None)
    }

    /// Whether a detector's `corners` lie on a grid ([`off_grid_share`] within
    /// [`MAX_OFF_GRID_SHARE`]).
    fn on_grid(&self, corners: &Vector<Point2f>) -> Result<bool> {
        let corners: Vec<Point2<f64>> = corners
            .iter()
            .map(|p| Point2::new(p.x as f64, p.y as f64))
            .collect();
        Ok(off_grid_share(self, &corners)? <= MAX_OFF_GRID_SHARE)
    }
}

/// The most a detector's corners may stray from a grid ([`off_grid_share`]) for the board to
/// count as found. Unrefined corners of a good detection lie within 6 % of a square of the best
/// plane-to-image map, refined ones within 1.5 % (either detector, 52 boards of a test's 60
/// found, 640×480, barrel distortion, noise and blur); on a board seen obliquely, with squares
/// of 6 px on its far side, the sector-based detector has returned a grid 42 % off (fitted
/// 2.5 px off by the camera calibration).
pub const MAX_OFF_GRID_SHARE: f64 = 0.2;

/// How far `corners` (row-major, pixels) stray from the best plane-to-image map (homography,
/// least squares) of the board's corners: their RMS distance from it over the board's smallest
/// square side in the image ([`square_side_px`]).
pub fn off_grid_share(board: &Board, corners: &[Point2<f64>]) -> Result<f64> {
    let to_cv = |x: f64, y: f64| Point2f::new(x as f32, y as f32);
    let on_board: Vector<Point2f> = (board.object_points().iter())
        .map(|p| to_cv(p.x, p.y))
        .collect();
    let seen: Vector<Point2f> = corners.iter().map(|p| to_cv(p.x, p.y)).collect();
    let h = opencv::calib3d::find_homography(&on_board, &seen, &mut Mat::default(), 0, 3.0)?;
    if h.empty() {
        return Ok(f64::INFINITY);
    }
    let mut mapped = Vector::<Point2f>::new();
    opencv::core::perspective_transform(&on_board, &mut mapped, &h)?;
    let squares: f64 = (mapped.iter().zip(corners))
        .map(|(m, c)| (m.x as f64 - c.x).powi(2) + (m.y as f64 - c.y).powi(2))
        .sum();
    let rms = (squares / corners.len() as f64).sqrt();
    Ok(rms / square_side_px(corners, board.cols as usize))
}

/// Half-width w (pixels) of the `cornerSubPix` search window for a board whose corners lie
/// `spacing_px` pixels apart at the closest ([`corner_spacing_px`]): half that, rounded down, so
/// that the window spans at most one square and never reaches half-way to the neighbouring
/// corners (a wider one lets their edges pull the refined corner between them); at least 2 and
/// at most OpenCV's sample's 11 (reached from 22 px squares on, so that large boards are refined
/// as OpenCV's sample refines them).
pub fn subpixel_half_window(spacing_px: f64) -> i32 {
    ((spacing_px / 2.0).floor() as i32).clamp(2, 11)
}

/// The board's smallest square side in the image, pixels: the shortest distance between
/// neighbouring corners of a row-major grid of `cols` corners a row (a tilted board's squares
/// are foreshortened along one direction).
pub fn square_side_px(corners: &[Point2<f64>], cols: usize) -> f64 {
    let mut side = f64::INFINITY;
    for (k, p) in corners.iter().enumerate() {
        if (k + 1) % cols != 0 && k + 1 < corners.len() {
            side = side.min((corners[k + 1] - p).norm());
        }
        if let Some(q) = corners.get(k + cols) {
            side = side.min((q - p).norm());
        }
    }
    side
}

/// The shortest distance (pixels) between neighbouring corners of a row-major grid of `cols`
/// corners a row, diagonal neighbours included: [`square_side_px`], or less on a board seen so
/// obliquely that its squares are sheared and a square's short diagonal is shorter than its
/// sides.
pub fn corner_spacing_px(corners: &[Point2<f64>], cols: usize) -> f64 {
    let rows = corners.len() / cols;
    let mut spacing = square_side_px(corners, cols);
    for r in 0..rows.saturating_sub(1) {
        for c in 0..cols - 1 {
            let (a, b) = (r * cols + c, r * cols + c + 1);
            let (below_a, below_b) = (a + cols, b + cols);
            spacing = spacing
                .min((corners[below_b] - corners[a]).norm())
                .min((corners[below_a] - corners[b]).norm());
        }
    }
    spacing
}

/// Step 2 of [`Board::find_corners`]: `cornerSubPix` with [`subpixel_half_window`] of the
/// corners' spacing ([`corner_spacing_px`]).
fn refine_corners(image: &Mat, corners: &[Point2<f64>], cols: usize) -> Result<Vec<Point2<f64>>> {
    let w = subpixel_half_window(corner_spacing_px(corners, cols));
    let mut cv: Vector<Point2f> = corners
        .iter()
        .map(|p| Point2f::new(p.x as f32, p.y as f32))
        .collect();
    opencv::imgproc::corner_sub_pix(
        image,
        &mut cv,
        Size::new(w, w),
        Size::new(-1, -1),
        super::criteria(30, 1e-4)?,
    )?;
    Ok(cv
        .iter()
        .map(|p| Point2::new(p.x as f64, p.y as f64))
        .collect())
}

/// Step 3 of [`Board::find_corners`]: reverses the row-major `corners` (a turn by 180° in the
/// board's plane) when the square they start with is lighter than its neighbour. A board with
/// `cols + rows` even looks the same turned, and is left in OpenCV's order.
fn orient_dark_first(
    image: &Mat,
    corners: &mut [Point2<f64>],
    cols: usize,
    rows: usize,
) -> Result<()> {
    if (cols + rows).is_multiple_of(2) {
        return Ok(());
    }
    // The first square (corners 0, 1, cols, cols + 1) against the next one along the row, or
    // along the column when a row has only two corners.
    let step = if cols >= 3 { 1 } else { cols };
    let first = square_grey(image, corners, 0, cols)?;
    let next = square_grey(image, corners, step, cols)?;
    if first > next {
        corners.reverse();
    }
    Ok(())
}

/// Mean grey level (0–255) of the pixels around the centre of the square whose top-left corner
/// is `corners[k]` (row-major grid of `cols` a row), within a quarter of its diagonal.
fn square_grey(image: &Mat, corners: &[Point2<f64>], k: usize, cols: usize) -> Result<f64> {
    let quad = [
        corners[k],
        corners[k + 1],
        corners[k + cols + 1],
        corners[k + cols],
    ];
    let centre = quad
        .iter()
        .fold(nalgebra::Vector2::zeros(), |s, p| s + p.coords)
        / 4.0;
    let r = ((quad[2] - quad[0]).norm().min((quad[3] - quad[1]).norm()) / 4.0).max(0.5);
    let (mut sum, mut n) = (0.0, 0usize);
    let (w, h) = (image.cols(), image.rows());
    let ri = r.ceil() as i32;
    for dy in -ri..=ri {
        for dx in -ri..=ri {
            if ((dx * dx + dy * dy) as f64) > r * r {
                continue;
            }
            let (x, y) = (centre.x.round() as i32 + dx, centre.y.round() as i32 + dy);
            if x >= 0 && y >= 0 && x < w && y < h {
                sum += *image.at_2d::<u8>(y, x)? as f64;
                n += 1;
            }
        }
    }
    Ok(if n == 0 { 0.0 } else { sum / n as f64 })
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
    read_image(path, opencv::imgcodecs::IMREAD_GRAYSCALE)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grid of 3 × 2 corners, each row shifted by `shear` px along it, rows 10 px apart.
    fn sheared_grid(shear: f64) -> Vec<Point2<f64>> {
        (0..2)
            .flat_map(|r| {
                (0..3)
                    .map(move |c| Point2::new(12.0 * c as f64 + shear * r as f64, 10.0 * r as f64))
            })
            .collect()
    }

    #[test]
    fn the_spacing_of_a_sheared_board_is_its_short_diagonal() {
        // Unsheared: the rows' 10 px; the diagonals are longer.
        assert_eq!(corner_spacing_px(&sheared_grid(0.0), 3), 10.0);
        // Sheared by 11 px: the sides are 12 and √221 ≈ 14.9 px, the short diagonal from a
        // row's second corner to the next row's first (−1, 10): √101 ≈ 10.05 px.
        let grid = sheared_grid(11.0);
        assert!((square_side_px(&grid, 3) - 12.0).abs() < 1e-12);
        assert!((corner_spacing_px(&grid, 3) - 101f64.sqrt()).abs() < 1e-12);
        // By 18 px the short diagonal (6, 10) is √136 ≈ 11.7 px, still under the 12 px side.
        let grid = sheared_grid(18.0);
        assert!((corner_spacing_px(&grid, 3) - (36.0f64 + 100.0).sqrt()).abs() < 1e-12);
    }
}
