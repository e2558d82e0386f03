//! The silhouette of the object in one view, from its decoded captures and a background
//! reference, cleaned with OpenCV.
//!
//! A pixel is "object" when (rules, each with its threshold in [`MaskOptions`]):
//! 1. its decoded monitor point differs from the background's by more than `shift_px` monitor
//!    pixels beyond the two cells' half widths (light bent by the glass);
//! 2. it decodes to nothing (no reliable bit on an axis, or unlit by OpenCV's shadow test) where
//!    the background decodes (light lost: total internal reflection, missed monitor);
//! 3. its white-image intensity is below `1 − white_drop` of the background's (absorption and
//!    Fresnel losses; only with a captured background).
//!
//! Without a captured background, the background point is predicted from the calibrated screen
//! pose (the camera ray of each pixel meets the monitor plane) and rule 3 is not used. Then
//! connected object regions smaller than `min_component_px` are dropped and holes smaller than
//! `max_hole_px` filled.

use anyhow::Result;
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, CV_32S};

use super::graycode::PixelDecode;

/// Thresholds of the silhouette rules.
#[derive(Clone, Copy, Debug)]
pub struct MaskOptions {
    pub shift_px: f32,
    pub white_drop: f32,
    pub min_component_px: i32,
    pub max_hole_px: i32,
}

impl Default for MaskOptions {
    fn default() -> Self {
        Self {
            shift_px: 2.0,
            white_drop: 0.15,
            min_component_px: 50,
            max_hole_px: 50,
        }
    }
}

/// What the background shows at a pixel.
#[derive(Clone, Copy, Debug)]
pub struct BackgroundPixel {
    /// Decoded (or predicted) monitor point and cell sizes; `None` where the monitor is not seen.
    pub point: Option<(f32, f32, f32, f32)>,
    /// White-image intensity, if a background was captured.
    pub white: Option<u8>,
}

/// The raw silhouette (before clean-up): 255 for object pixels.
pub fn raw_mask(
    decoded: &[PixelDecode],
    lit: &[bool],
    white: &[u8],
    background: &[BackgroundPixel],
    o: &MaskOptions,
) -> Vec<u8> {
    decoded
        .iter()
        .zip(lit)
        .zip(white)
        .zip(background)
        .map(|(((d, &lit), &w), bg)| {
            let valid = lit && d.u.bits > 0 && d.v.bits > 0;
            let object = match (valid, bg.point) {
                (true, Some((bu, bv, cu, cv))) => {
                    (d.u.coord - bu).abs() > o.shift_px + (d.u.cell as f32 + cu) / 2.0
                        || (d.v.coord - bv).abs() > o.shift_px + (d.v.cell as f32 + cv) / 2.0
                }
                (false, Some(_)) => true,
                (_, None) => false,
            } || bg
                .white
                .is_some_and(|bw| (w as f32) < (1.0 - o.white_drop) * bw as f32);
            if object {
                255
            } else {
                0
            }
        })
        .collect()
}

/// Drops small object regions and fills holes that are small or thin (at most 2 pixels wide on
/// average, such as the line where a ray through the lens centre decodes like the background),
/// in place; 8-connected regions; a background region touching the image border is no hole.
pub fn clean(mask: &mut [u8], width: i32, height: i32, o: &MaskOptions) -> Result<()> {
    remove_regions(mask, width, height, 255, |area, _, _, _| {
        area < o.min_component_px
    })?;
    remove_regions(mask, width, height, 0, |area, w, h, border| {
        !border && (area < o.max_hole_px || area <= 2 * w.max(h))
    })?;
    Ok(())
}

/// Sets the regions of value `value` for which `drop(area, width, height, touches_border)`
/// (pixels) holds to the other value.
fn remove_regions(
    mask: &mut [u8],
    width: i32,
    height: i32,
    value: u8,
    drop: impl Fn(i32, i32, i32, bool) -> bool,
) -> Result<()> {
    let sel: Vec<u8> = mask
        .iter()
        .map(|&m| if m == value { 255 } else { 0 })
        .collect();
    let img = Mat::new_rows_cols_with_data(height, width, &sel)?;
    let (mut labels, mut stats, mut centroids) = (Mat::default(), Mat::default(), Mat::default());
    let n = opencv::imgproc::connected_components_with_stats(
        &img,
        &mut labels,
        &mut stats,
        &mut centroids,
        8,
        CV_32S,
    )?;
    use opencv::imgproc::{CC_STAT_AREA, CC_STAT_HEIGHT, CC_STAT_LEFT, CC_STAT_TOP, CC_STAT_WIDTH};
    let small: Vec<bool> = (0..n)
        .map(|l| -> Result<bool> {
            let st = |k| stats.at_2d::<i32>(l, k).copied();
            let (x, y, w, h) = (
                st(CC_STAT_LEFT)?,
                st(CC_STAT_TOP)?,
                st(CC_STAT_WIDTH)?,
                st(CC_STAT_HEIGHT)?,
            );
            let border = x == 0 || y == 0 || x + w == width || y + h == height;
            Ok(l > 0 && drop(st(CC_STAT_AREA)?, w, h, border))
        })
        .collect::<Result<_>>()?;
    let labels = labels.data_typed::<i32>()?;
    let other = if value == 255 { 0 } else { 255 };
    for (m, &l) in mask.iter_mut().zip(labels) {
        if small[l as usize] {
            *m = other;
        }
    }
    Ok(())
}
