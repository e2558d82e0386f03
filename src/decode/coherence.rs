//! How much of the background's own fine code a pixel still shows: the share of its area through
//! which the monitor is seen as without the object. The mask's edge rule uses it to decide
//! whether a mixed edge pixel (part glass, part background) is more than half glass.
//!
//! At a mixed pixel every bit's pattern − inverse difference Δ is the sum of the two parts': the
//! background part's is its share (1 − c) of the background capture's own difference Δbg there,
//! while the light through the glass near the outline is bent strongly and comes from monitor
//! points far away, so on the fine stripes its sign agrees with the background's as often as not.
//! Hence (1 − c) ≈ Σ s_k·Δ_k / Σ |Δbg_k| over the fine bits k that the background decodes
//! reliably at that pixel, s_k the sign of Δbg_k. Unlike the white image's ratio, this does not
//! depend on how bright the glass part is: light reflected at grazing incidence near the outline
//! brightens a pixel's white image without showing the background's fine code.

use rayon::prelude::*;

use super::graycode::BitTest;
use crate::patterns::GrayCode;
use crate::scan::decoded::{FlatGlass, ViewSummary, MASK_OBJECT};

/// Stripes of at most this half-period (monitor pixels) count as fine.
pub const FINE_HALF_PERIOD_PX: u32 = 32;
/// Fewest fine bits the background must decode reliably at a pixel for a share.
pub const MIN_FINE_BITS: usize = 2;

/// The fine bits' pattern − inverse differences of one capture, grey levels: pixel `p`'s are
/// `diffs[p * bits .. (p + 1) * bits]`, in [`fine_bits`]' order; and per pixel the smallest
/// difference of a reliable bit there ([`BitTest::need`]).
pub struct FineDiffs {
    pub bits: usize,
    pub diffs: Vec<i16>,
    pub need: Vec<f32>,
}

/// Indices (into OpenCV's bit order: columns then rows, most significant first) of the bits
/// whose stripes have a half-period of at most [`FINE_HALF_PERIOD_PX`].
pub fn fine_bits(code: &GrayCode) -> Vec<usize> {
    let (nc, nr) = (code.column_bits(), code.row_bits());
    let fine = |bits: u32, k: u32| (1u32 << (bits - 1 - k)) <= FINE_HALF_PERIOD_PX;
    let columns = (0..nc).filter(|&k| fine(nc, k)).map(|k| k as usize);
    let rows = (0..nr).filter(|&k| fine(nr, k)).map(|k| (nc + k) as usize);
    columns.chain(rows).collect()
}

impl FineDiffs {
    /// From a capture's pattern images (OpenCV's order: pattern, inverse, per bit), white and
    /// black images (all of one size), keeping the bits `fine`.
    pub fn new(
        images: &[&[u8]],
        white: &[u8],
        black: &[u8],
        fine: &[usize],
        test: BitTest,
    ) -> Self {
        let bits = fine.len();
        let mut diffs = vec![0i16; white.len() * bits];
        diffs
            .par_chunks_mut(bits.max(1))
            .enumerate()
            .for_each(|(p, out)| {
                for (d, &k) in out.iter_mut().zip(fine) {
                    *d = images[2 * k][p] as i16 - images[2 * k + 1][p] as i16;
                }
            });
        let need = white
            .par_iter()
            .zip(black)
            .map(|(&w, &b)| test.need(w, b))
            .collect();
        Self { bits, diffs, need }
    }
}

/// Per pixel the share (0..=1) of the background's fine code that `view` shows: see the module
/// doc. `NaN` where the background decodes fewer than [`MIN_FINE_BITS`] fine bits reliably, that
/// is with a difference of at least its `need` there.
pub fn background_share(view: &FineDiffs, background: &FineDiffs) -> Vec<f32> {
    let b = view.bits;
    background
        .need
        .par_iter()
        .enumerate()
        .map(|(p, &need)| {
            let v = &view.diffs[p * b..(p + 1) * b];
            let g = &background.diffs[p * b..(p + 1) * b];
            let (mut agree, mut full, mut used) = (0.0f32, 0.0f32, 0usize);
            for (&vk, &gk) in v.iter().zip(g) {
                let gk = gk as f32;
                if gk.abs() >= need {
                    agree += gk.signum() * vk as f32;
                    full += gk.abs();
                    used += 1;
                }
            }
            if used < MIN_FINE_BITS {
                f32::NAN
            } else {
                (agree / full).clamp(0.0, 1.0)
            }
        })
        .collect()
}

/// The glass's own share ρ below which [`shares_beside_flat_glass`] leaves a share as it is:
/// through curved glass the fine code comes from far-off monitor points and ρ is noise about 0.
pub const FLAT_GLASS_SHARE: f32 = 0.2;
/// The largest ρ a share is corrected for (the correction divides by 1 − ρ).
const MAX_GLASS_SHARE: f32 = 0.9;
/// How far (pixels, each way) the glass beside a pixel is looked for.
const BESIDE_PX: usize = 2;

/// Each pixel's `share` corrected for the share ρ of the background's fine code that the glass
/// beside it shows itself: glass seen through flat, nearly parallel faces shows the background's
/// code barely shifted, so an outline pixel part glass (coverage c) shows (1 − c) + c·ρ of it,
/// and 1 − c = 1 − (1 − share)/(1 − ρ). ρ is the median share of the `interior` object pixels
/// ([`interior_object_pixels`]; images `width` wide) within [`BESIDE_PX`] pixels; where it is
/// below [`FLAT_GLASS_SHARE`], or fewer than 3 such pixels have a share, the share stays as it is.
pub fn shares_beside_flat_glass(share: &[f32], interior: &[bool], width: usize) -> Vec<f32> {
    let height = share.len() / width.max(1);
    (0..share.len())
        .into_par_iter()
        .map(|i| {
            let s = share[i];
            if s.is_nan() {
                return s;
            }
            let (x, y) = (i % width, i / width);
            let mut beside = [0f32; (2 * BESIDE_PX + 1) * (2 * BESIDE_PX + 1)];
            let mut n = 0;
            for yy in y.saturating_sub(BESIDE_PX)..(y + BESIDE_PX + 1).min(height) {
                for xx in x.saturating_sub(BESIDE_PX)..(x + BESIDE_PX + 1).min(width) {
                    let j = yy * width + xx;
                    if interior[j] && !share[j].is_nan() {
                        beside[n] = share[j];
                        n += 1;
                    }
                }
            }
            if n < 3 {
                return s;
            }
            let beside = &mut beside[..n];
            beside.sort_by(f32::total_cmp);
            let rho = beside[n / 2].min(MAX_GLASS_SHARE);
            if rho < FLAT_GLASS_SHARE {
                return s;
            }
            (1.0 - (1.0 - s) / (1.0 - rho)).clamp(0.0, 1.0)
        })
        .collect()
}

/// From this share of the object's inside showing the monitor barely shifted ([`FlatGlass`]) a
/// scan is flat-faced: the bench's physical 640×480 scans (glasscan's simulator) measure 0.48 on
/// the block and 0.66 on the prism, 0.055–0.064 on the pig, the dog and the horse.
pub const FLAT_FACED_SCAN_SHARE: f64 = 0.25;

/// The share of the interior object pixels of `views` (those with a share of the background's
/// code) through which the monitor shows barely shifted; `None` where no view has any.
pub fn flat_glass_share(views: &[ViewSummary]) -> Option<f64> {
    let counts = views.iter().filter_map(|v| v.flat_glass);
    let total = counts.fold(FlatGlass::default(), |t, c| FlatGlass {
        interior: t.interior + c.interior,
        flat: t.flat + c.flat,
    });
    (total.interior > 0).then(|| total.flat as f64 / total.interior as f64)
}

/// Per pixel of `mask` (`width` wide), whether it and its four neighbours are object pixels.
pub fn interior_object_pixels(mask: &[u8], width: usize) -> Vec<bool> {
    let height = mask.len() / width.max(1);
    (0..mask.len())
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % width, i / width);
            let inside = x > 0 && y > 0 && x + 1 < width && y + 1 < height;
            inside
                && [i, i - 1, i + 1, i - width, i + width]
                    .iter()
                    .all(|&j| mask[j] == MASK_OBJECT)
        })
        .collect()
}

/// The `interior` object pixels ([`interior_object_pixels`]) with a `share`, and those whose
/// share is at least [`FLAT_GLASS_SHARE`].
pub fn flat_glass_pixels(share: &[f32], interior: &[bool]) -> FlatGlass {
    let known = share
        .iter()
        .zip(interior)
        .filter(|(s, &inside)| inside && !s.is_nan());
    known.fold(FlatGlass::default(), |c, (&s, _)| FlatGlass {
        interior: c.interior + 1,
        flat: c.flat + usize::from(s >= FLAT_GLASS_SHARE),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pixel that sees the background through (1 − c) of its area and, through the rest,
    /// a monitor point whose fine bits disagree with the background's on half of them.
    fn mixed(background: &[i16], c: f64) -> Vec<i16> {
        background
            .iter()
            .enumerate()
            .map(|(k, &g)| {
                let glass = if k % 2 == 0 { g } else { -g };
                ((1.0 - c) * g as f64 + c * glass as f64).round() as i16
            })
            .collect()
    }

    /// One pixel's differences, whose reliable bits need 20 grey levels.
    fn diffs(d: Vec<i16>) -> FineDiffs {
        FineDiffs {
            bits: d.len(),
            diffs: d,
            need: vec![20.0],
        }
    }

    #[test]
    fn share_is_the_background_part_of_a_mixed_pixel() {
        let bg: Vec<i16> = vec![180, -170, 175, -190, 160, -185, 170, -180];
        for c in [0.0, 0.3, 0.6, 1.0] {
            let view = diffs(mixed(&bg, c));
            let background = diffs(bg.clone());
            let share = background_share(&view, &background)[0];
            assert!(
                (share as f64 - (1.0 - c)).abs() < 0.03,
                "glass share {c}: background share {share}"
            );
        }
    }

    /// A 7 × 5 image whose left four columns are glass showing `rho` of the background's code
    /// and whose column 4 is an outline pixel covered `c` by the glass, beside background.
    fn outline_beside_glass(rho: f32, c: f32) -> (Vec<f32>, Vec<u8>) {
        let (w, h) = (7, 5);
        let mut share = vec![1.0f32; w * h];
        let mut mask = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..5 {
                let i = y * w + x;
                mask[i] = MASK_OBJECT;
                share[i] = if x == 4 { (1.0 - c) + c * rho } else { rho };
            }
        }
        (share, mask)
    }

    #[test]
    fn an_outline_pixel_beside_flat_glass_is_judged_by_its_coverage() {
        let (w, c) = (7, 0.6);
        let (share, mask) = outline_beside_glass(0.5, c);
        let corrected = shares_beside_flat_glass(&share, &interior_object_pixels(&mask, w), w);
        let i = 2 * w + 4;
        // Uncorrected, the pixel shows 0.7 of the code and would be trimmed as background.
        assert!(share[i] > 0.5, "{}", share[i]);
        assert!((corrected[i] - (1.0 - c)).abs() < 1e-6, "{}", corrected[i]);
        // The background beside keeps its share.
        assert_eq!(corrected[2 * w + 6], 1.0);
    }

    #[test]
    fn shares_beside_curved_glass_stay() {
        let w = 7;
        let (share, mask) = outline_beside_glass(FLAT_GLASS_SHARE * 0.5, 0.6);
        let interior = interior_object_pixels(&mask, w);
        assert_eq!(shares_beside_flat_glass(&share, &interior, w), share);
    }

    #[test]
    fn flat_glass_counts_the_inside_that_shows_the_background_code() {
        // A 6 × 5 object in an 8 × 7 image: its 4 × 3 interior pixels count, the rim does not.
        let (w, h) = (8, 7);
        let mask: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if (1..7).contains(&x) && (1..6).contains(&y) {
                    MASK_OBJECT
                } else {
                    0
                }
            })
            .collect();
        // Interior shares by column x = 2..=5: two flat columns, one below the share, one
        // undecoded; the rim and the background show the code whole.
        let share: Vec<f32> = (0..w * h)
            .map(|i| match i % w {
                2 => FLAT_GLASS_SHARE,
                3 => 0.9,
                4 => FLAT_GLASS_SHARE * 0.5,
                5 => f32::NAN,
                _ => 1.0,
            })
            .collect();
        let counts = flat_glass_pixels(&share, &interior_object_pixels(&mask, w));
        assert_eq!(
            counts,
            FlatGlass {
                interior: 9,
                flat: 6
            }
        );
        let view = |flat_glass| ViewSummary {
            view: 0,
            object_pixels: 30,
            decoded_share: 1.0,
            complete_share: 1.0,
            dim_share: None,
            white_drop: None,
            monitor_edge_px: 0,
            warning: None,
            flat_glass,
        };
        let curved = FlatGlass {
            interior: 91,
            flat: 4,
        };
        let share = flat_glass_share(&[view(Some(counts)), view(None), view(Some(curved))]);
        assert_eq!(share, Some(0.1));
        assert_eq!(flat_glass_share(&[view(None)]), None);
    }

    #[test]
    fn no_share_where_the_background_is_not_decoded() {
        let (view, background) = (diffs(vec![100, -100, 100]), diffs(vec![150, 4, -3]));
        assert!(background_share(&view, &background)[0].is_nan());
    }

    #[test]
    fn fine_bits_are_the_last_six_of_each_axis_of_a_full_hd_code() {
        let code = GrayCode {
            width: 1920,
            height: 1080,
        };
        // 11 bits per axis; half-periods 1024 … 1: bits 5..=10 are at most 32 px.
        let expected: Vec<usize> = (5..11).chain(16..22).collect();
        assert_eq!(fine_bits(&code), expected);
    }
}
