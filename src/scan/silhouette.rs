//! One view's silhouette as a signed distance: how far inside (> 0) or outside (< 0) the mask a
//! world point projects, in pixels and converted to mm at the point's depth.
//!
//! Holes the decoder filled ([`MASK_FILLED`]) are outside the silhouette (the losses' view: a
//! gap between two parts of the object shows there) and kept apart, so that the visual hull can
//! count them inside ([`Silhouette::with_holes_filled`]).
//!
//! Where the decoder measured how much of each pixel on the outline the object covers, the
//! distances near the outline are refined to a fraction of a pixel ([`Silhouette::with_coverage`],
//! [`super::outline`]).

use std::borrow::Cow;

use anyhow::{bail, Result};
use nalgebra::{Isometry3, Point3};
use opencv::core::{Mat, MatTraitConstManual, CV_32F};
use opencv::imgproc::{distance_transform, DIST_L2, DIST_MASK_PRECISE};

use super::decoded::{is_object, MASK_FILLED};
use crate::rig::Camera;

/// A view's mask as a signed distance image with the view's camera and pose.
#[derive(Clone, Debug)]
pub struct Silhouette {
    pub view: usize,
    pub camera: Camera,
    /// World → camera transform of the view (mm).
    pub pose: Isometry3<f64>,
    /// The part of the image the distances are kept for ([`Window`]).
    window: Window,
    /// Per pixel of the window (row-major): distance to the silhouette's outline, pixels, > 0
    /// inside. The outline runs between pixel centres, so a boundary pixel has ±0.5.
    sd: Vec<f32>,
    /// Object pixels.
    pub area_px: usize,
    /// Pixels (row-major indices in the window) of the holes the decoder filled, outside in `sd`.
    filled: Vec<u32>,
    /// The mask reaches the image border (the object may be cut off).
    pub touches_border: bool,
    /// The measured coverage of the window's outline pixels the distances were refined with, if
    /// any (`view_NNN_coverage.png`'s values).
    coverage: Option<Vec<u8>>,
}

/// The rectangle of the image a silhouette keeps its distances for (pixels, columns `x0..x0 +
/// w`, rows `y0..y0 + h`): the bounding box of the mask's pixels grown by [`WINDOW_MARGIN`] of its
/// longer side, and at least 2 pixels, on every side, clipped to the image. The memory then
/// follows the object's size in the image, not the camera's pixel count; distances inside the
/// window are those of the whole image (the nearest pixel of the other kind is always inside it).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Window {
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    /// Pixels between the mask's bounding box and every side of the window not on the image's
    /// border: a point beyond such a side is at least this much more outside.
    margin: f64,
}

/// How far a silhouette's window reaches beyond the mask's bounding box, a share of its longer
/// side: the contour and the hull's voxels near the outline stay inside it.
pub const WINDOW_MARGIN: f64 = 0.25;

impl Window {
    /// The window of a `width`×`height` mask whose pixels with `set(i)` are the object (or a
    /// filled hole); the whole image when there are none.
    fn around(width: usize, height: usize, set: impl Fn(usize) -> bool) -> Self {
        let (mut lo, mut hi) = ([usize::MAX; 2], [0usize; 2]);
        for i in (0..width * height).filter(|&i| set(i)) {
            let (x, y) = (i % width, i / width);
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
        if lo[0] > hi[0] {
            return Window {
                x0: 0,
                y0: 0,
                w: width,
                h: height,
                margin: 0.0,
            };
        }
        let side = (hi[0] - lo[0]).max(hi[1] - lo[1]) + 1;
        let m = ((WINDOW_MARGIN * side as f64).ceil() as usize).max(2);
        let (x0, y0) = (lo[0].saturating_sub(m), lo[1].saturating_sub(m));
        let (x1, y1) = ((hi[0] + m).min(width - 1), (hi[1] + m).min(height - 1));
        Window {
            x0,
            y0,
            w: x1 - x0 + 1,
            h: y1 - y0 + 1,
            margin: m as f64,
        }
    }

    /// The window's part of a row-major image of width `width`.
    fn crop<T: Copy>(&self, image: &[T], width: usize) -> Vec<T> {
        (self.y0..self.y0 + self.h)
            .flat_map(|y| {
                image[y * width + self.x0..y * width + self.x0 + self.w]
                    .iter()
                    .copied()
            })
            .collect()
    }

    /// The image pixel of the window's first pixel.
    fn origin(&self) -> [usize; 2] {
        [self.x0, self.y0]
    }

    /// Image pixel (x, y) as an index into the window, if it lies in it.
    fn index(&self, x: usize, y: usize) -> Option<usize> {
        let (i, j) = (x.checked_sub(self.x0)?, y.checked_sub(self.y0)?);
        (i < self.w && j < self.h).then_some(j * self.w + i)
    }
}

impl Silhouette {
    /// From a mask of the camera's size (`scan::decoded`'s values: [`MASK_FILLED`] a filled hole,
    /// any other non-zero value object).
    pub fn from_mask(
        view: usize,
        mask: &[u8],
        camera: &Camera,
        pose: Isometry3<f64>,
    ) -> Result<Self> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        if mask.len() != w * h {
            bail!(
                "view {view}: the mask has {} pixels, the camera {w}×{h}",
                mask.len()
            );
        }
        let object = |i: usize| is_object(mask[i]);
        let touches_border = (0..w).any(|x| object(x) || object((h - 1) * w + x))
            || (0..h).any(|y| object(y * w) || object(y * w + w - 1));
        let window = Window::around(w, h, |i| mask[i] != 0);
        let mask = window.crop(mask, w);
        let inside: Vec<u8> = mask
            .iter()
            .map(|&m| if is_object(m) { 255 } else { 0 })
            .collect();
        let filled = (0..mask.len() as u32)
            .filter(|&i| mask[i as usize] == MASK_FILLED)
            .collect();
        let base = Silhouette {
            view,
            camera: camera.clone(),
            pose,
            window,
            sd: Vec::new(),
            area_px: 0,
            filled,
            touches_border,
            coverage: None,
        };
        base.with_inside(&inside)
    }

    /// This silhouette's distances made from `inside` (the window's pixels, non-zero for the
    /// object).
    fn with_inside(mut self, inside: &[u8]) -> Result<Self> {
        let (w, h) = (self.window.w, self.window.h);
        let outside: Vec<u8> = inside
            .iter()
            .map(|&m| if m != 0 { 0 } else { 255 })
            .collect();
        let dist = |src: &[u8]| -> Result<Vec<f32>> {
            let m = Mat::new_rows_cols_with_data(h as i32, w as i32, src)?;
            let mut d = Mat::default();
            distance_transform(&m, &mut d, DIST_L2, DIST_MASK_PRECISE, CV_32F)?;
            Ok(d.data_typed::<f32>()?.to_vec())
        };
        self.area_px = inside.iter().filter(|&&m| m != 0).count();
        // With no pixel of one kind OpenCV returns a huge distance; the caller rejects empty
        // masks, and a full mask is simply "inside everywhere on the image".
        let (din, dout) = (dist(inside)?, dist(&outside)?);
        self.sd = inside
            .iter()
            .zip(din.iter().zip(&dout))
            .map(|(&m, (&a, &b))| if m != 0 { a - 0.5 } else { 0.5 - b })
            .collect();
        Ok(self)
    }

    /// This silhouette with its distances near the outline refined by the measured `coverage`
    /// of the outline's pixels (row-major, the camera's size; see [`super::outline::UNMEASURED`]).
    pub fn with_coverage(self, coverage: Vec<u8>) -> Result<Self> {
        let width = self.camera.width as usize;
        if coverage.len() != width * self.camera.height as usize {
            bail!(
                "view {}: the coverage image has {} pixels, the camera {}×{}",
                self.view,
                coverage.len(),
                self.camera.width,
                self.camera.height
            );
        }
        let coverage = self.window.crop(&coverage, width);
        Ok(self.refined(coverage))
    }

    /// This silhouette with its distances refined by `coverage`, the window's part of the
    /// coverage image.
    fn refined(mut self, coverage: Vec<u8>) -> Self {
        let inside: Vec<bool> = self.sd.iter().map(|&d| d > 0.0).collect();
        let (w, origin) = (self.window.w, self.window.origin());
        super::outline::refine(&mut self.sd, &inside, &coverage, w, origin);
        self.coverage = Some(coverage);
        self
    }

    /// This silhouette with the holes the decoder filled counted inside (the visual hull's
    /// view: carving a hole that was a decoding gap would cut glass away); itself if it has none.
    pub fn with_holes_filled(&self) -> Result<Cow<'_, Self>> {
        if self.filled.is_empty() {
            return Ok(Cow::Borrowed(self));
        }
        let mut inside: Vec<u8> = self.sd.iter().map(|&d| u8::from(d > 0.0) * 255).collect();
        for &i in &self.filled {
            inside[i as usize] = 255;
        }
        let filled = self.clone_without_images().with_inside(&inside)?;
        let Some(coverage) = &self.coverage else {
            return Ok(Cow::Owned(filled));
        };
        let mut coverage = coverage.clone();
        for &i in &self.filled {
            coverage[i as usize] = 255;
        }
        Ok(Cow::Owned(filled.refined(coverage)))
    }

    /// This silhouette's view, camera, pose and window, without its images.
    fn clone_without_images(&self) -> Self {
        Silhouette {
            view: self.view,
            camera: self.camera.clone(),
            pose: self.pose,
            window: self.window,
            sd: Vec::new(),
            area_px: self.area_px,
            filled: Vec::new(),
            touches_border: self.touches_border,
            coverage: None,
        }
    }

    /// The four window pixels around window point (x, y) (clamped to the window) and the
    /// position between them.
    fn cell(&self, x: f64, y: f64) -> ([f64; 4], f64, f64) {
        let (w, h) = (self.window.w, self.window.h);
        let (x, y) = (x.clamp(0.0, (w - 1) as f64), y.clamp(0.0, (h - 1) as f64));
        let (x0, y0) = (
            (x as usize).min(w.max(2) - 2),
            (y as usize).min(h.max(2) - 2),
        );
        let at = |i: usize, j: usize| self.sd[j.min(h - 1) * w + i.min(w - 1)] as f64;
        (
            [
                at(x0, y0),
                at(x0 + 1, y0),
                at(x0, y0 + 1),
                at(x0 + 1, y0 + 1),
            ],
            x - x0 as f64,
            y - y0 as f64,
        )
    }

    /// Whether pixel (x, y) (column, row; inside the image) is an object pixel of the mask (a
    /// hole the decoder filled is not).
    pub fn is_object_px(&self, x: usize, y: usize) -> bool {
        self.window.index(x, y).is_some_and(|i| self.sd[i] > 0.0)
    }

    /// The signed distance image at pixel coordinates (x, y), bilinear between pixel centres
    /// (clamped to the image).
    pub fn sd_px(&self, x: f64, y: f64) -> f64 {
        self.sample_px(x, y).0
    }

    /// [`Self::sd_px`] and its gradient (per pixel). Beyond the window (a point at least its
    /// margin from every object pixel) the distance grows from the margin by the distance to
    /// the window, pointing away from it: never more outside than the whole image says.
    pub fn sample_px(&self, x: f64, y: f64) -> (f64, f64, f64) {
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        let (x, y) = (x.clamp(0.0, w - 1.0), y.clamp(0.0, h - 1.0));
        let wn = &self.window;
        let (lx, ly) = (x - wn.x0 as f64, y - wn.y0 as f64);
        let (cx, cy) = (
            lx.clamp(0.0, (wn.w - 1) as f64),
            ly.clamp(0.0, (wn.h - 1) as f64),
        );
        let (v, fx, fy) = self.cell(cx, cy);
        let [a, b, c, d] = v;
        let beyond = (lx - cx).hypot(ly - cy);
        if beyond == 0.0 {
            return (
                bilinear(&v, fx, fy),
                (1.0 - fy) * (b - a) + fy * (d - c),
                (1.0 - fx) * (c - a) + fx * (d - b),
            );
        }
        (
            0.5 - wn.margin - beyond,
            -(lx - cx) / beyond,
            -(ly - cy) / beyond,
        )
    }

    /// Signed distance (mm, > 0 inside the silhouette cone) of world point `p` (mm): the image
    /// distance of its projection to the outline, bilinear between pixel centres, scaled by
    /// depth / focal length. Outside the image, the distance to the image adds to the outside.
    pub fn signed_distance_mm(&self, p: &Point3<f64>) -> f64 {
        let q = self.pose * p;
        let Some(px) = self.camera.project(&q) else {
            return -1e9;
        };
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        let beyond = (px.x - px.x.clamp(0.0, w - 1.0)).hypot(px.y - px.y.clamp(0.0, h - 1.0));
        let px_to_mm = q.z / (0.5 * (self.camera.fx + self.camera.fy));
        (self.sd_px(px.x, px.y) - beyond) * px_to_mm
    }
}

/// Bilinear interpolation of the corner values [(0,0), (1,0), (0,1), (1,1)] at (fx, fy).
fn bilinear(&[a, b, c, d]: &[f64; 4], fx: f64, fy: f64) -> f64 {
    (1.0 - fy) * ((1.0 - fx) * a + fx * b) + fy * ((1.0 - fx) * c + fx * d)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The signed distance (camera pixels, positive inside) of the whole `w` × `h` image of
    /// `mask`, as the silhouette computed it before it had a window.
    fn whole_image_signed_distance(mask: &[u8], w: usize, h: usize) -> Vec<f32> {
        let full = |inside: bool| -> Vec<f32> {
            let src: Vec<u8> = mask
                .iter()
                .map(|&m| if is_object(m) == inside { 255 } else { 0 })
                .collect();
            let m = Mat::new_rows_cols_with_data(h as i32, w as i32, &src).unwrap();
            let mut d = Mat::default();
            distance_transform(&m, &mut d, DIST_L2, DIST_MASK_PRECISE, CV_32F).unwrap();
            d.data_typed::<f32>().unwrap().to_vec()
        };
        let (din, dout) = (full(true), full(false));
        (0..w * h)
            .map(|i| {
                if is_object(mask[i]) {
                    din[i] - 0.5
                } else {
                    0.5 - dout[i]
                }
            })
            .collect()
    }

    /// A silhouette keeps its distances for a window around the object: inside it they are the
    /// whole image's, bit for bit (also refined by a measured coverage), beyond it a point is
    /// never said to be further outside than the whole image says, and the window is a small
    /// part of a large image.
    #[test]
    fn distances_in_the_window_are_the_whole_images_and_beyond_it_never_further_out() {
        let (w, h) = (1600usize, 1200usize);
        let camera = Camera {
            width: w as u32,
            height: h as u32,
            fx: 1000.0,
            fy: 1000.0,
            cx: 800.0,
            cy: 600.0,
            dist: [0.0; 5],
        };
        // An L-shaped object with a filled hole and a round knob, off the image's centre.
        let mask: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let body = (900..1100).contains(&x) && (300..700).contains(&y);
                let foot = (1000..1250).contains(&x) && (600..700).contains(&y);
                let hole = (950..970).contains(&x) && (400..420).contains(&y);
                let knob = (x as f64 - 1180.3).hypot(y as f64 - 420.7) < 60.4;
                match (body || foot || knob, hole) {
                    (true, true) => MASK_FILLED,
                    (true, false) => 255,
                    _ => 0,
                }
            })
            .collect();
        let sil = Silhouette::from_mask(0, &mask, &camera, Isometry3::identity()).unwrap();
        assert!(sil.sd.len() * 3 < w * h, "window {:?}", sil.window);
        let mut whole = whole_image_signed_distance(&mask, w, h);
        // Coverage measured on the outline's pixels, uneven from pixel to pixel, so that the
        // refined contour's crossings fall at positions whose rounding depends on the frame
        // they are reckoned in.
        let coverage: Vec<u8> = (0..w * h)
            .map(|i| match (whole[i] > 0.0, whole[i].abs() < 1.0) {
                (true, true) => 160 + (i * 37 % 90) as u8,
                (false, true) => 10 + (i * 53 % 110) as u8,
                (true, false) => 255,
                (false, false) => 0,
            })
            .collect();
        let inside: Vec<bool> = whole.iter().map(|&d| d > 0.0).collect();
        super::super::outline::refine(&mut whole, &inside, &coverage, w, [0, 0]);
        let sil = sil.with_coverage(coverage).unwrap();
        let (mut inside_window, mut beyond) = (0, 0);
        for y in 0..h {
            for x in 0..w {
                let (got, want) = (sil.sd_px(x as f64, y as f64), whole[y * w + x] as f64);
                assert_eq!(sil.is_object_px(x, y), is_object(mask[y * w + x]));
                if sil.window.index(x, y).is_some() {
                    inside_window += 1;
                    assert_eq!(got, want, "({x}, {y})");
                } else {
                    beyond += 1;
                    assert!(got < 0.0 && got >= want, "({x}, {y}): {got} against {want}");
                }
            }
        }
        assert!(inside_window > 1000 && beyond > 1000);
        // The hull's view counts the filled hole inside, with the same window.
        let filled = sil.with_holes_filled().unwrap();
        assert!(sil.sd_px(960.0, 410.0) < 0.0 && filled.sd_px(960.0, 410.0) > 0.0);
        assert_eq!(filled.window, sil.window);
    }
}
