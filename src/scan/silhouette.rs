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
    /// Per pixel (row-major): distance to the silhouette's outline, pixels, > 0 inside. The
    /// outline runs between pixel centres, so a boundary pixel has ±0.5.
    sd: Vec<f32>,
    /// Object pixels.
    pub area_px: usize,
    /// Pixels (row-major indices) of the holes the decoder filled, outside in `sd`.
    filled: Vec<u32>,
    /// The mask reaches the image border (the object may be cut off).
    pub touches_border: bool,
    /// The measured coverage of the outline's pixels the distances were refined with, if any
    /// (`view_NNN_coverage.png`'s values).
    coverage: Option<Vec<u8>>,
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
        let inside: Vec<u8> = mask
            .iter()
            .map(|&m| if is_object(m) { 255 } else { 0 })
            .collect();
        let filled = (0..mask.len() as u32)
            .filter(|&i| mask[i as usize] == MASK_FILLED)
            .collect();
        let outside: Vec<u8> = inside.iter().map(|&m| 255 - m).collect();
        let dist = |src: &[u8]| -> Result<Vec<f32>> {
            let m = Mat::new_rows_cols_with_data(h as i32, w as i32, src)?;
            let mut d = Mat::default();
            distance_transform(&m, &mut d, DIST_L2, DIST_MASK_PRECISE, CV_32F)?;
            Ok(d.data_typed::<f32>()?.to_vec())
        };
        let area_px = inside.iter().filter(|&&m| m != 0).count();
        // With no pixel of one kind OpenCV returns a huge distance; the caller rejects empty
        // masks, and a full mask is simply "inside everywhere on the image".
        let (din, dout) = (dist(&inside)?, dist(&outside)?);
        let sd = inside
            .iter()
            .zip(din.iter().zip(&dout))
            .map(|(&m, (&a, &b))| if m != 0 { a - 0.5 } else { 0.5 - b })
            .collect();
        let touches_border = (0..w).any(|x| inside[x] != 0 || inside[(h - 1) * w + x] != 0)
            || (0..h).any(|y| inside[y * w] != 0 || inside[y * w + w - 1] != 0);
        Ok(Self {
            view,
            camera: camera.clone(),
            pose,
            sd,
            area_px,
            filled,
            touches_border,
            coverage: None,
        })
    }

    /// This silhouette with its distances near the outline refined by the measured `coverage`
    /// of the outline's pixels (row-major, the camera's size; see [`super::outline::UNMEASURED`]).
    pub fn with_coverage(mut self, coverage: Vec<u8>) -> Result<Self> {
        if coverage.len() != self.sd.len() {
            bail!(
                "view {}: the coverage image has {} pixels, the camera {}",
                self.view,
                coverage.len(),
                self.sd.len()
            );
        }
        let inside: Vec<bool> = self.sd.iter().map(|&d| d > 0.0).collect();
        super::outline::refine(&mut self.sd, &inside, &coverage, self.camera.width as usize);
        self.coverage = Some(coverage);
        Ok(self)
    }

    /// This silhouette with the holes the decoder filled counted inside (the visual hull's
    /// view: carving a hole that was a decoding gap would cut glass away); itself if it has none.
    pub fn with_holes_filled(&self) -> Result<Cow<'_, Self>> {
        if self.filled.is_empty() {
            return Ok(Cow::Borrowed(self));
        }
        let mut mask: Vec<u8> = self.sd.iter().map(|&d| u8::from(d > 0.0) * 255).collect();
        for &i in &self.filled {
            mask[i as usize] = 255;
        }
        let filled = Self::from_mask(self.view, &mask, &self.camera, self.pose)?;
        let Some(coverage) = &self.coverage else {
            return Ok(Cow::Owned(filled));
        };
        let mut coverage = coverage.clone();
        for &i in &self.filled {
            coverage[i as usize] = 255;
        }
        filled.with_coverage(coverage).map(Cow::Owned)
    }

    /// The four pixels around (x, y) (clamped to the image) and the position between them.
    fn cell(&self, x: f64, y: f64) -> ([f64; 4], f64, f64) {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let (x, y) = (x.clamp(0.0, (w - 1) as f64), y.clamp(0.0, (h - 1) as f64));
        let (x0, y0) = ((x as usize).min(w - 2), (y as usize).min(h - 2));
        let at = |i: usize, j: usize| self.sd[j * w + i] as f64;
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
        self.sd[y * self.camera.width as usize + x] > 0.0
    }

    /// The signed distance image at pixel coordinates (x, y), bilinear between pixel centres
    /// (clamped to the image).
    pub fn sd_px(&self, x: f64, y: f64) -> f64 {
        let (v, fx, fy) = self.cell(x, y);
        bilinear(&v, fx, fy)
    }

    /// [`Self::sd_px`] and its gradient (per pixel).
    pub fn sample_px(&self, x: f64, y: f64) -> (f64, f64, f64) {
        let (v, fx, fy) = self.cell(x, y);
        let [a, b, c, d] = v;
        (
            bilinear(&v, fx, fy),
            (1.0 - fy) * (b - a) + fy * (d - c),
            (1.0 - fx) * (c - a) + fx * (d - b),
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
