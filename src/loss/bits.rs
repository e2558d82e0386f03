//! The per-bit term (docs/architecture.md §4): what share of a pixel's footprint each Gray-code
//! pattern lights, against what the camera measured.
//!
//! Through glass a camera pixel averages a footprint of many monitor pixels, and the decoder keeps
//! only the bits whose stripes the footprint still resolves: the decoded point is the centre of a
//! cell, known to ± half its width. The bits around the cell's size still say more: a bit's
//! measured contrast c = (pattern − inverse)/(white − black) is 2s − 1 for the share s of the
//! footprint its stripes light. Here the footprint is modelled by its traced rays, each standing
//! for a box of monitor pixels (its share of the footprint's extent) whose lit share has a closed
//! form ([`box_share`]), so the modelled contrast is differentiable in the rays' monitor points.
//!
//! Monitor coordinates are continuous monitor pixels: column x spans [x − ½, x + ½) (the decoder's
//! and the simulator's convention). Bits are numbered from the least significant (bit i has
//! stripes 2^(i+1) pixels wide).

use nalgebra::Vector2;

/// A measured bit of one axis: its index from the least significant and its contrast in [−1, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BitContrast {
    pub bit: u8,
    pub contrast: f32,
}

/// The measured bits of one pixel per axis (u: columns, v: rows): the last reliable bit of the
/// decoded cell and the first unreliable one, where present; the cell's centre and widths
/// (monitor pixels; the widths are the footprint's size where its rays do not give it).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelBits {
    pub u: [Option<BitContrast>; 2],
    pub v: [Option<BitContrast>; 2],
    pub centre: [f32; 2],
    pub cell: [f32; 2],
}

impl PixelBits {
    /// Whether any bit was measured.
    pub fn any(&self) -> bool {
        self.u.iter().chain(&self.v).any(Option::is_some)
    }

    /// The bits a decoded cell of width `cell` (a power of two, monitor pixels) leaves to
    /// measure, from a pixel's two stored contrasts (the last reliable bit's, the first
    /// unreliable one's; NaN for none).
    pub fn axis(cell: f64, contrasts: [f32; 2]) -> [Option<BitContrast>; 2] {
        let Some(last) = cell_bit(cell) else {
            return [None, None];
        };
        let first_unreliable = last.checked_sub(1);
        let at = |bit: Option<u8>, c: f32| {
            bit.filter(|_| c.is_finite())
                .map(|bit| BitContrast { bit, contrast: c })
        };
        [
            at(Some(last), contrasts[0]),
            at(first_unreliable, contrasts[1]),
        ]
    }
}

/// The index of the last reliable bit of a cell `cell` monitor pixels wide (a power of two up to
/// 2¹⁵); `None` for anything else.
fn cell_bit(cell: f64) -> Option<u8> {
    let b = cell.log2();
    ((0.0..=15.0).contains(&b) && b == b.round()).then_some(b as u8)
}

/// The lit share of a box of monitor pixels [u − w/2, u + w/2] in the pattern of Gray bit `bit`
/// (pixels where the bit is 1 are lit), with its derivatives with respect to u and w.
/// `w` > 0, monitor pixels.
pub fn box_share(u: f64, w: f64, bit: u8) -> (f64, f64, f64) {
    let stripe = (1u64 << (bit as u32 + 1)) as f64;
    let period = 2.0 * stripe;
    // x: the coordinate along which the bit is 1 on the upper half of each period.
    let x = u + 0.5 + stripe / 2.0;
    let lit = |x: f64| (x.rem_euclid(period) >= stripe) as u8 as f64;
    let integral =
        |x: f64| (x / period).floor() * stripe + (x.rem_euclid(period) - stripe).max(0.0);
    let (hi, lo) = (x + w / 2.0, x - w / 2.0);
    let share = (integral(hi) - integral(lo)) / w;
    let d_u = (lit(hi) - lit(lo)) / w;
    let d_w = ((lit(hi) + lit(lo)) / 2.0 - share) / w;
    (share, d_u, d_w)
}

/// Whether the mean of the rays' monitor points lies inside the decoded cell on both axes: a
/// bit's stripes repeat, so outside its cell a pixel's bits would pull towards the nearest
/// stripe of the right colour rather than towards the cell; there the decoded point alone
/// guides it.
pub fn within_cell(bits: &PixelBits, points: &[Vector2<f64>]) -> bool {
    if points.is_empty() {
        return false;
    }
    let mean = points.iter().sum::<Vector2<f64>>() / points.len() as f64;
    (0..2).all(|a| (mean[a] - bits.centre[a] as f64).abs() <= bits.cell[a] as f64 / 2.0)
}

/// The smallest box a ray stands for, monitor pixels.
pub const MIN_BOX_PX: f64 = 1.0;

/// The per-bit loss of one pixel, Σ over its bits of (modelled − measured contrast)², and its
/// gradient with respect to each ray's monitor point (u, v), into `grad` (overwritten; as many
/// entries as `points`).
/// `points`: the rays' monitor points; `side`: rays per footprint side (1: a single ray whose
/// box is the decoded cell; n > 1: each ray's box spans the footprint's extent / (n − 1) along
/// each axis, at least [`MIN_BOX_PX`], and the extent's own dependence on the extreme rays is
/// differentiated).
pub fn pixel_loss(
    bits: &PixelBits,
    points: &[Vector2<f64>],
    side: u32,
    grad: &mut [Vector2<f64>],
) -> f64 {
    grad.fill(Vector2::zeros());
    let mut loss = 0.0;
    for (a, axis_bits) in [bits.u, bits.v].iter().enumerate() {
        if axis_bits.iter().all(Option::is_none) || points.is_empty() {
            continue;
        }
        let coord = |j: usize| points[j][a];
        let extent = ray_extent(points.len(), coord, side);
        let w = match extent {
            Some((e, _, _)) => e.max(MIN_BOX_PX),
            None => (bits.cell[a] as f64).max(MIN_BOX_PX),
        };
        let m = points.len() as f64;
        let mut g_w = 0.0;
        for b in axis_bits.iter().flatten() {
            let model: f64 = (0..points.len())
                .map(|j| 2.0 * box_share(coord(j), w, b.bit).0 - 1.0)
                .sum::<f64>()
                / m;
            let r = model - b.contrast as f64;
            loss += r * r;
            // d(r²)/d(share_j) = 2r · 2/m.
            let k = 4.0 * r / m;
            for (j, g) in grad.iter_mut().enumerate() {
                let (_, d_u, d_w) = box_share(coord(j), w, b.bit);
                g[a] += k * d_u;
                g_w += k * d_w;
            }
        }
        if let Some((e, hi, lo)) = extent {
            if e > MIN_BOX_PX {
                let k = g_w / (side - 1) as f64;
                grad[hi][a] += k;
                grad[lo][a] -= k;
            }
        }
    }
    loss
}

/// The box width the footprint's rays give along one axis, (max − min)/(side − 1), with the
/// indices of the extreme rays; `None` when the rays do not span the footprint (one ray, or a
/// single-ray footprint).
fn ray_extent(n: usize, coord: impl Fn(usize) -> f64, side: u32) -> Option<(f64, usize, usize)> {
    if side < 2 || n < 2 {
        return None;
    }
    let (mut hi, mut lo) = (0, 0);
    for j in 1..n {
        if coord(j) > coord(hi) {
            hi = j;
        }
        if coord(j) < coord(lo) {
            lo = j;
        }
    }
    Some(((coord(hi) - coord(lo)) / (side - 1) as f64, hi, lo))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::patterns::GrayCode;

    /// The lit share of a box by brute force from the pattern generator: column x is lit in
    /// pattern image 2·(bits − 1 − bit).
    fn brute_share(u: f64, w: f64, bit: u8) -> f64 {
        let code = GrayCode {
            width: 1024,
            height: 8,
        };
        let image = 2 * (code.column_bits() as usize - 1 - bit as usize);
        let n = 200_000;
        let lit = (0..n)
            .filter(|&k| {
                let x = u - w / 2.0 + w * (k as f64 + 0.5) / n as f64;
                code.is_white(image, x.round() as u32, 0)
            })
            .count();
        lit as f64 / n as f64
    }

    #[test]
    fn box_share_agrees_with_the_patterns() {
        for bit in [0u8, 1, 3, 5] {
            for &(u, w) in &[
                (100.3, 1.5),
                (200.0, 7.0),
                (333.7, 40.0),
                (512.2, 3.3),
                (64.0, 100.0),
            ] {
                let (s, _, _) = box_share(u, w, bit);
                let b = brute_share(u, w, bit);
                assert!((s - b).abs() < 1e-4, "bit {bit} u {u} w {w}: {s} vs {b}");
            }
        }
    }

    #[test]
    fn box_share_derivatives_match_finite_differences() {
        let h = 1e-6;
        for bit in [0u8, 2, 4] {
            for &(u, w) in &[(100.37, 1.7), (210.1, 9.3), (333.71, 45.2)] {
                let (_, du, dw) = box_share(u, w, bit);
                let fu = (box_share(u + h, w, bit).0 - box_share(u - h, w, bit).0) / (2.0 * h);
                let fw = (box_share(u, w + h, bit).0 - box_share(u, w - h, bit).0) / (2.0 * h);
                assert!((du - fu).abs() < 1e-6, "d/du bit {bit}: {du} vs {fu}");
                assert!((dw - fw).abs() < 1e-6, "d/dw bit {bit}: {dw} vs {fw}");
            }
        }
    }

    fn some_bits() -> PixelBits {
        PixelBits {
            u: PixelBits::axis(16.0, [0.4, -0.2]),
            v: PixelBits::axis(8.0, [-0.7, f32::NAN]),
            centre: [103.0, 52.0],
            cell: [16.0, 8.0],
        }
    }

    #[test]
    fn cells_name_their_bits() {
        let b = some_bits();
        assert_eq!(b.u[0].map(|c| c.bit), Some(4));
        assert_eq!(b.u[1].map(|c| c.bit), Some(3));
        assert_eq!(b.v[0].map(|c| c.bit), Some(3));
        assert_eq!(b.v[1], None);
        assert_eq!(PixelBits::axis(1.0, [0.9, 0.1])[1], None);
        assert_eq!(PixelBits::axis(12.0, [0.9, 0.1]), [None, None]);
        assert!(!PixelBits::default().any());
    }

    #[test]
    fn pixel_loss_gradient_matches_finite_differences() {
        let bits = some_bits();
        let h = 1e-6;
        for side in [1u32, 2] {
            let points: Vec<Vector2<f64>> =
                [(100.3, 50.2), (104.9, 51.1), (101.2, 55.7), (106.4, 57.3)]
                    .iter()
                    .take((side * side) as usize)
                    .map(|&(u, v)| Vector2::new(u, v))
                    .collect();
            let mut g = vec![Vector2::zeros(); points.len()];
            pixel_loss(&bits, &points, side, &mut g);
            assert!(
                g.iter().any(|v| v.amax() > 1e-3),
                "side {side}: no gradient"
            );
            for j in 0..points.len() {
                for a in 0..2 {
                    let mut p = points.clone();
                    p[j][a] += h;
                    let lp = pixel_loss(&bits, &p, side, &mut g.clone());
                    p[j][a] -= 2.0 * h;
                    let lm = pixel_loss(&bits, &p, side, &mut g.clone());
                    let fd = (lp - lm) / (2.0 * h);
                    assert!(
                        (fd - g[j][a]).abs() < 1e-8,
                        "side {side} ray {j} axis {a}: {} vs {fd}",
                        g[j][a]
                    );
                }
            }
        }
    }

    #[test]
    fn the_measured_contrasts_are_matched_at_the_true_position() {
        // A 12-pixel box at u = 70.4 measured exactly: the loss is 0 there and larger 3 px away.
        let (s4, _, _) = box_share(70.4, 12.0, 4);
        let (s3, _, _) = box_share(70.4, 12.0, 3);
        let bits = PixelBits {
            u: PixelBits::axis(16.0, [2.0 * s4 as f32 - 1.0, 2.0 * s3 as f32 - 1.0]),
            v: [None, None],
            centre: [72.0, 0.0],
            cell: [12.0, 1.0],
        };
        let at = |u: f64| pixel_loss(&bits, &[Vector2::new(u, 0.0)], 1, &mut [Vector2::zeros()]);
        assert!(at(70.4) < 1e-12);
        assert!(at(67.4) > 1e-3 && at(73.4) > 1e-3);
    }

    #[test]
    fn the_term_acts_within_the_cell() {
        let b = some_bits();
        let at = |u: f64, v: f64| within_cell(&b, &[Vector2::new(u, v)]);
        assert!(at(103.0, 52.0) && at(110.9, 48.1));
        assert!(!at(111.1, 52.0) && !at(103.0, 47.9));
        assert!(!within_cell(&b, &[]));
    }
}
