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
