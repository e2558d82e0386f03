//! Sub-pixel points on a chessboard's grid lines, for fits that need more than its corners.
//!
//! A corner refined by `cornerSubPix` on squares of 6–12 pixels is off by about 0.08 px RMS even
//! in a noise-free image, by an amount that follows where the corner falls within its pixel, so
//! that a board's 54 corners average it out only in part: nine images of them put a turntable
//! axis 0.02–0.16 mm off (glasscan's simulator, 640×480, the true camera). The grid lines
//! between the squares hold many more measurements: at points along each line (away from the
//! corners), the grey profile across it is summed between the grey levels of the two squares it
//! separates. For a step blurred by any symmetric spread and integrated over the pixels, the sum
//! locates the step wherever it falls within a pixel (the *area* rule): exactly across a pixel
//! row or column, nearly so along other directions, where bilinear samples stand in for pixels.
//!
//! Frames: board frame (mm, the corners at (j·square, i·square, 0) as
//! [`super::board::Board::object_points`]), camera frame (OpenCV), pixel coordinates with
//! integer values at pixel centres.

use anyhow::{ensure, Result};
use nalgebra::{Isometry3, Point2, Point3, Vector2, Vector3};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, CV_8UC1};

use super::board::Board;
use crate::rig::Camera;

/// The least grey-level difference (0–255) between the two squares beside a point for the point
/// to count: below it the profile's noise dominates the sum.
const MIN_CONTRAST: f64 = 30.0;
/// Points are taken along the middle of each square's side, from this share of the side to one
/// minus it: nearer a corner the profile crosses the neighbouring squares.
const END_SHARE: f64 = 0.25;
/// The furthest a step may lie from where the board's pose (PnP on its corners, within a few
/// hundredths of a square) puts it, as a share of the square's side: further, something else
/// than the two squares (glare, a mark, a shadow) shapes the profile.
const MAX_OFFSET_SHARE: f64 = 0.1;
/// Points along a side, at most one per this many pixels of its image.
const STEP_PX: f64 = 1.0;

/// A point of the board's grid found in an image.
#[derive(Clone, Copy, Debug)]
pub struct GridEdge {
    /// Where the step between the two squares lies, pixels.
    pub image: Point2<f64>,
    /// A point of the grid line (board frame, mm) and the line's direction (unit).
    pub on_board: Point3<f64>,
    pub along: Vector3<f64>,
}

impl GridEdge {
    /// The signed distance (pixels) from [`Self::image`] to the grid line's image through
    /// `camera` with the board at `pose` (board → camera), measured near `on_board` (the line's
    /// image is curved by the lens; a straight piece 0.5 mm long is used); `None` behind the
    /// camera.
    pub fn residual(&self, camera: &Camera, pose: &Isometry3<f64>) -> Option<f64> {
        let a = camera.project(&(pose * self.on_board))?;
        let b = camera.project(&(pose * (self.on_board + self.along * 0.5)))?;
        let t = (b - a).try_normalize(1e-12)?;
        Some((self.image - a).perp(&t))
    }
}

/// The grid points of `board` in the 8-bit grey `image`, with the board at `pose` (board →
/// camera, good to a fraction of a pixel, e.g. PnP on the corners) seen through `camera`.
pub fn grid_edges(
    image: &Mat,
    board: &Board,
    camera: &Camera,
    pose: &Isometry3<f64>,
) -> Result<Vec<GridEdge>> {
    let grey = Grey::new(image)?;
    let mut edges = Vec::new();
    for side in sides(board) {
        edges.extend(side_edges(&grey, camera, pose, &side, board.square_mm));
    }
    Ok(edges)
}

/// One square's side on a grid line: its start (board frame, mm), its direction (unit) and the
/// in-plane direction across it (unit).
struct Side {
    start: Point3<f64>,
    along: Vector3<f64>,
    across: Vector3<f64>,
}

/// Every side between two squares of the board's inner grid lines: the lines through the
/// corners, each crossing the whole checkered area (one square beyond the corners at each end).
fn sides(board: &Board) -> Vec<Side> {
    let s = board.square_mm;
    let (cols, rows) = (board.cols as i32, board.rows as i32);
    // (column j, row i) of each side's start, and whether it runs along y (a line of constant
    // x through a column of corners) or along x.
    let along_y = (0..cols).flat_map(|j| (-1..rows).map(move |i| (j, i, true)));
    let along_x = (0..rows).flat_map(|i| (-1..cols).map(move |j| (j, i, false)));
    along_y
        .chain(along_x)
        .map(|(j, i, vertical)| {
            let (along, across) = if vertical {
                (Vector3::y(), Vector3::x())
            } else {
                (Vector3::x(), Vector3::y())
            };
            Side {
                start: Point3::new(j as f64 * s, i as f64 * s, 0.0),
                along,
                across,
            }
        })
        .collect()
}

/// The grid points found along one `side` of squares `square_mm` wide.
fn side_edges(
    grey: &Grey,
    camera: &Camera,
    pose: &Isometry3<f64>,
    side: &Side,
    square_mm: f64,
) -> Vec<GridEdge> {
    let project = |p: Point3<f64>| camera.project(&(pose * p));
    let (Some(a), Some(b)) = (
        project(side.start),
        project(side.start + side.along * square_mm),
    ) else {
        return Vec::new();
    };
    let n = (((b - a).norm() * (1.0 - 2.0 * END_SHARE)) / STEP_PX)
        .floor()
        .max(1.0) as usize;
    (0..n)
        .filter_map(|k| {
            let f = END_SHARE + (1.0 - 2.0 * END_SHARE) * (k as f64 + 0.5) / n as f64;
            let on_board = side.start + side.along * (f * square_mm);
            let half = side.across * (0.5 * square_mm);
            let centres = (project(on_board - half)?, project(on_board + half)?);
            let image = step_across(grey, project(on_board)?, centres)?;
            Some(GridEdge {
                image,
                on_board,
                along: side.along,
            })
        })
        .collect()
}

/// The step between the squares centred at `centres` (pixels) near `p` (pixels), by the area
/// rule along the line from one centre to the other: samples one pixel apart at p + k·n,
/// k = −w…w (n the unit direction from the first square to the second, w as wide as stays a
/// pixel and a half inside both squares), each as its share of the way from the first square's
/// grey to the second's; the step lies at w + ½ − (the shares' sum) along n. `None` where the
/// squares are too small or too alike, or the step lies further from `p` than
/// [`MAX_OFFSET_SHARE`] of the distance between the centres (a square's side).
fn step_across(
    grey: &Grey,
    p: Point2<f64>,
    centres: (Point2<f64>, Point2<f64>),
) -> Option<Point2<f64>> {
    let (c1, c2) = centres;
    let n: Vector2<f64> = (c2 - c1).try_normalize(1e-12)?;
    let reach = (p - c1).dot(&n).min((c2 - p).dot(&n));
    let w = (reach - 1.5).floor();
    if w < 1.0 {
        return None;
    }
    let (g1, g2) = (grey.at(c1)?, grey.at(c2)?);
    if (g2 - g1).abs() < MIN_CONTRAST {
        return None;
    }
    let w = w as i32;
    let mut sum = 0.0;
    for k in -w..=w {
        sum += (grey.at(p + n * k as f64)? - g1) / (g2 - g1);
    }
    let t = w as f64 + 0.5 - sum;
    (t.abs() <= MAX_OFFSET_SHARE * (c2 - c1).norm()).then(|| p + n * t)
}

/// An 8-bit grey image, sampled bilinearly.
struct Grey<'a> {
    data: &'a [u8],
    width: usize,
    height: usize,
}

impl<'a> Grey<'a> {
    fn new(image: &'a Mat) -> Result<Self> {
        ensure!(
            image.typ() == CV_8UC1 && image.is_continuous(),
            "a grid needs an 8-bit grey image"
        );
        Ok(Self {
            data: image.data_bytes()?,
            width: image.cols() as usize,
            height: image.rows() as usize,
        })
    }

    /// The grey level (0–255) at `p` (pixels), bilinear between the four nearest pixel centres;
    /// `None` outside the image.
    fn at(&self, p: Point2<f64>) -> Option<f64> {
        let (x0, y0) = (p.x.floor(), p.y.floor());
        if !(x0 >= 0.0 && y0 >= 0.0) {
            return None;
        }
        let (i, j) = (x0 as usize, y0 as usize);
        if i + 1 >= self.width || j + 1 >= self.height {
            return None;
        }
        let (fx, fy) = (p.x - x0, p.y - y0);
        let g = |x: usize, y: usize| self.data[y * self.width + x] as f64;
        let top = g(i, j) * (1.0 - fx) + g(i + 1, j) * fx;
        let bottom = g(i, j + 1) * (1.0 - fx) + g(i + 1, j + 1) * fx;
        Some(top * (1.0 - fy) + bottom * fy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{MatTrait, Scalar};

    /// An image of a vertical step from grey 50 to 200 at x = `edge` (pixels), each pixel the
    /// mean over its area, blurred across by a box of `spread` pixels either side.
    fn step_image(edge: f64, spread: f64) -> Mat {
        let mut m = Mat::new_rows_cols_with_default(40, 40, CV_8UC1, Scalar::all(0.0)).unwrap();
        for x in 0..40 {
            // The share of the pixel [x − ½, x + ½] beyond the edge, averaged over the blur.
            let beyond = |e: f64| (x as f64 + 0.5 - e).clamp(0.0, 1.0);
            let n = 64;
            let share = (0..n)
                .map(|k| beyond(edge + spread * (2.0 * (k as f64 + 0.5) / n as f64 - 1.0)))
                .sum::<f64>()
                / n as f64;
            for y in 0..40 {
                *m.at_2d_mut::<u8>(y, x).unwrap() = (50.0 + 150.0 * share).round() as u8;
            }
        }
        m
    }

    #[test]
    fn the_area_rule_places_a_step_wherever_it_falls_within_a_pixel() {
        for spread in [0.0, 1.0] {
            for k in 0..=10 {
                let edge = 19.5 + 0.1 * k as f64;
                let image = step_image(edge, spread);
                let grey = Grey::new(&image).unwrap();
                let p = Point2::new(20.0, 20.0);
                let centres = (Point2::new(14.0, 20.0), Point2::new(26.0, 20.0));
                let found = step_across(&grey, p, centres).unwrap();
                // 8-bit grey levels over a contrast of 150 leave at most a few thousandths.
                assert!(
                    (found.x - edge).abs() < 0.01,
                    "{edge} (spread {spread}): {found}"
                );
                assert!((found.y - 20.0).abs() < 1e-12);
            }
        }
        // A step 2 px from where it was expected (a sixth of the 12 px square), squares too
        // small for a pixel and a half either side, or a point not between the squares, give
        // nothing.
        let far = step_image(22.0, 0.0);
        let centres = (Point2::new(14.0, 20.0), Point2::new(26.0, 20.0));
        let at = Point2::new(20.0, 20.0);
        assert!(step_across(&Grey::new(&far).unwrap(), at, centres).is_none());
        let image = step_image(20.0, 0.0);
        let grey = Grey::new(&image).unwrap();
        let p = Point2::new(20.0, 20.0);
        assert!(
            step_across(&grey, p, (Point2::new(17.6, 20.0), Point2::new(22.4, 20.0))).is_none()
        );
        assert!(step_across(&grey, p, (Point2::new(2.0, 20.0), Point2::new(10.0, 20.0))).is_none());
    }
}
