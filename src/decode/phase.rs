//! Phase-shift refinement of Gray-code decodes: inside the cell the reliable Gray bits select,
//! the sinusoid's phase gives the position to a fraction of a pixel.
//!
//! Through glass a camera pixel averages a footprint of monitor pixels: the measured phase is
//! then that of the footprint's light-weighted centroid (for a footprint small against the
//! period), which is what the optimisation wants. The refinement needs the Gray cell to be at
//! most half a period wide (so that the period is unambiguous) and the modulation (B/A) at least
//! `min_modulation` (a footprint wider than the period averages the sinusoid away).

use rayon::prelude::*;

use super::graycode::{AxisDecode, PixelDecode};
use crate::patterns::PhaseShift;

/// Refines `decoded` in place from the phase images (`2·steps` images, u then v, pixels in the
/// same order as `decoded`). Returns how many pixels were refined on both axes.
pub fn refine(
    decoded: &mut [PixelDecode],
    images: &[&[u8]],
    phase: &PhaseShift,
    min_modulation: f64,
) -> usize {
    let n = phase.steps as usize;
    assert_eq!(images.len(), 2 * n, "u and v phase images");
    decoded
        .par_iter_mut()
        .enumerate()
        .map(|(p, d)| {
            let (wu, mu) = phase.wrapped(images[..n].iter().map(|img| img[p] as f64));
            let (wv, mv) = phase.wrapped(images[n..].iter().map(|img| img[p] as f64));
            let ru = refine_axis(&mut d.u, wu, mu, phase.period_px, min_modulation);
            let rv = refine_axis(&mut d.v, wv, mv, phase.period_px, min_modulation);
            (ru && rv) as usize
        })
        .sum()
}

fn refine_axis(
    a: &mut AxisDecode,
    wrapped: f64,
    modulation: f64,
    period: u32,
    min_modulation: f64,
) -> bool {
    let p = period as f64;
    if a.bits == 0 || modulation < min_modulation || a.cell as f64 > p / 2.0 {
        return false;
    }
    let c = a.coord as f64;
    let x = wrapped + ((c - wrapped) / p).round() * p;
    if (x - c).abs() > a.cell as f64 / 2.0 + 1.0 {
        return false;
    }
    a.coord = x as f32;
    a.cell = 1;
    true
}
