//! A silhouette's outline to a fraction of a pixel, from how much of each pixel along it the
//! object covers.
//!
//! A binary mask puts the outline on the lines between pixel centres: a staircase up to half a
//! pixel off the true curve. Where the decoder measured the coverage c of the pixels on the
//! outline (the share of each pixel the object covers, `view_NNN_coverage.png`), the outline is
//! placed where c, interpolated linearly between two neighbouring pixel centres on either side of
//! the mask's edge, crosses ½ — marching squares on the coverage image, with the mask deciding
//! each pixel's side. A camera's blur spreads the coverage over a pixel or two on either side
//! but, being symmetric, leaves its ½ crossing where the edge is; reading a pixel's coverage as
//! the share of a sharp square cut by a straight edge would not (a blurred edge pixel reads near
//! ½ on both sides, and the outline would be placed at both pixels' centres at once). The signed
//! distance of every pixel near the outline then becomes its distance to the nearest piece of
//! that contour.

use nalgebra::Vector2;

type V2 = Vector2<f64>;

/// Stored coverage values that say "not measured": the pixel is wholly object (255) or wholly
/// background (0) as far as the decoder knows. Measured values are 1..=254 (c·255, rounded).
pub const UNMEASURED: [u8; 2] = [0, 255];

/// The stored value of a measured coverage `c` of a pixel on the `inside` (object) or outside
/// side of the outline: c kept on that side of ½, as 1..=254 (c·255).
pub fn encode_coverage(c: f32, inside: bool) -> u8 {
    let c = if inside { c.max(0.5) } else { c.min(0.5) };
    (c * 255.0).round().clamp(1.0, 254.0) as u8
}

/// The coverage stored value `v` of a pixel on the `inside` or outside side of the outline
/// stands for, kept on that side of ½; unmeasured: 1 inside, 0 outside.
pub fn decode_coverage(v: u8, inside: bool) -> f64 {
    let c = if UNMEASURED.contains(&v) {
        f64::from(u8::from(inside))
    } else {
        f64::from(v) / 255.0
    };
    if inside {
        c.max(0.5)
    } else {
        c.min(0.5)
    }
}

/// Pixels nearer the binary outline than this (pixels) get their distance from the refined
/// contour; farther ones keep the binary distance.
const BAND_PX: f32 = 3.0;

/// A straight piece of the contour, pixel coordinates.
#[derive(Clone, Copy, Debug)]
struct Piece {
    a: V2,
    b: V2,
}

impl Piece {
    fn distance(&self, p: V2) -> f64 {
        let ab = self.b - self.a;
        let len2 = ab.norm_squared();
        let s = if len2 > 0.0 {
            ((p - self.a).dot(&ab) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (p - (self.a + ab * s)).norm()
    }
}

/// Refines the binary signed distance image `sd` (pixels, > 0 inside; row-major, `width`
/// wide) with the measured `coverage` (same layout, see [`UNMEASURED`]) of the pixels on the
/// outline, in place. `inside` is the mask the distances were made from; a pixel keeps its side
/// of the outline (its sign) whatever its coverage says, at least 0.01 px from it. The images
/// are a window of the camera's whose first pixel is the camera's `origin` (column, row):
/// positions are reckoned in the camera's pixels, so a window refines as its whole image would.
pub fn refine(sd: &mut [f32], inside: &[bool], coverage: &[u8], width: usize, origin: [usize; 2]) {
    let height = sd.len() / width.max(1);
    if width < 2 || height < 2 {
        return;
    }
    let cells = contour_pieces(inside, coverage, width, height, origin);
    let reach = BAND_PX.ceil() as usize + 1;
    let refined: Vec<(usize, f32)> = (0..sd.len())
        .filter(|&i| sd[i].abs() <= BAND_PX)
        .filter_map(|i| {
            let (x, y) = (i % width, i / width);
            let p = V2::new((x + origin[0]) as f64, (y + origin[1]) as f64);
            let mut best = f64::INFINITY;
            for cy in y.saturating_sub(reach)..(y + reach).min(height - 1) {
                for cx in x.saturating_sub(reach)..(x + reach).min(width - 1) {
                    for piece in &cells[cy * (width - 1) + cx] {
                        best = best.min(piece.distance(p));
                    }
                }
            }
            best.is_finite().then(|| {
                let d = best.max(0.01) as f32;
                (i, if inside[i] { d } else { -d })
            })
        })
        .collect();
    for (i, d) in refined {
        sd[i] = d;
    }
}

/// Per cell of four pixel centres ((x, y) to (x + 1, y + 1), row-major over the
/// (width − 1) × (height − 1) cells), the pieces of the contour crossing it: marching squares
/// with each corner's side from `inside` and each crossing of an edge between sides where the
/// coverage, interpolated linearly along it, is ½. A cell whose two object corners face each
/// other diagonally is split by its centre's coverage (the mean of its corners').
fn contour_pieces(
    inside: &[bool],
    coverage: &[u8],
    width: usize,
    height: usize,
    [ox, oy]: [usize; 2],
) -> Vec<Vec<Piece>> {
    let c = |i: usize| decode_coverage(coverage[i], inside[i]);
    (0..(width - 1) * (height - 1))
        .map(|k| {
            let (x, y) = (k % (width - 1), k / (width - 1));
            // Corners counter-clockwise: (x, y), (x + 1, y), (x + 1, y + 1), (x, y + 1).
            let idx = [
                y * width + x,
                y * width + x + 1,
                (y + 1) * width + x + 1,
                (y + 1) * width + x,
            ];
            let (px, py) = ((x + ox) as f64, (y + oy) as f64);
            let pos = [
                V2::new(px, py),
                V2::new(px + 1.0, py),
                V2::new(px + 1.0, py + 1.0),
                V2::new(px, py + 1.0),
            ];
            let side = idx.map(|i| inside[i]);
            if side.iter().all(|&s| s == side[0]) {
                return Vec::new();
            }
            let cov = idx.map(c);
            // The crossing on edge e (from corner e to corner e + 1), if the sides differ.
            let crossing = |e: usize| -> Option<V2> {
                let (a, b) = (e, (e + 1) % 4);
                (side[a] != side[b]).then(|| {
                    let den = cov[a] - cov[b];
                    let t = if den.abs() > 1e-12 {
                        ((cov[a] - 0.5) / den).clamp(0.0, 1.0)
                    } else {
                        0.5
                    };
                    pos[a] + (pos[b] - pos[a]) * t
                })
            };
            let cuts: Vec<(usize, V2)> =
                (0..4).filter_map(|e| crossing(e).map(|p| (e, p))).collect();
            match cuts.as_slice() {
                [(_, a), (_, b)] => vec![Piece { a: *a, b: *b }],
                [_, _, _, _] => {
                    // A saddle: cut off the two corners on the side the centre is not on,
                    // each by the piece joining the crossings on its two edges.
                    let centre_inside = cov.iter().sum::<f64>() / 4.0 >= 0.5;
                    (0..4)
                        .filter(|&v| side[v] != centre_inside)
                        .map(|v| Piece {
                            a: cuts[(v + 3) % 4].1,
                            b: cuts[v].1,
                        })
                        .collect()
                }
                _ => Vec::new(),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bilinear interpolation of `img` (row-major, `w` wide) at (x, y).
    fn bilinear(img: &[f32], w: usize, x: f64, y: f64) -> f64 {
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let at = |i: usize, j: usize| img[j * w + i] as f64;
        (1.0 - fy) * ((1.0 - fx) * at(x0, y0) + fx * at(x0 + 1, y0))
            + fy * ((1.0 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1))
    }

    /// A disk's mask (pixel centres inside), binary signed distance and coverage as a camera with
    /// a Gaussian blur of `blur` px would measure it (a 16 × 16 grid of samples per pixel and a
    /// blur kernel sampled at the same spacing), stored as the decoder stores it.
    fn disk(w: usize, centre: V2, r: f64, blur: f64) -> (Vec<bool>, Vec<f32>, Vec<u8>) {
        let n = w * w;
        let inside: Vec<bool> = (0..n)
            .map(|i| (V2::new((i % w) as f64, (i / w) as f64) - centre).norm() < r)
            .collect();
        let sd: Vec<f32> = (0..n)
            .map(|i| {
                let p = V2::new((i % w) as f64, (i / w) as f64);
                let d = (0..n)
                    .filter(|&j| inside[j] != inside[i])
                    .map(|j| (V2::new((j % w) as f64, (j / w) as f64) - p).norm())
                    .fold(f64::INFINITY, f64::min);
                (if inside[i] { d - 0.5 } else { 0.5 - d }) as f32
            })
            .collect();
        let k = 16;
        let reach = (3.0 * blur).ceil() as i64;
        let coverage = (0..n)
            .map(|i| {
                let p = V2::new((i % w) as f64, (i / w) as f64);
                let (mut lit, mut total) = (0.0, 0.0);
                for s in 0..(k * k) as i64 * (2 * reach + 1).pow(2) {
                    let (cell, sub) = (s / (k * k) as i64, s % (k * k) as i64);
                    let (dx, dy) = (
                        cell % (2 * reach + 1) - reach,
                        cell / (2 * reach + 1) - reach,
                    );
                    let o = V2::new(
                        dx as f64 + ((sub % k as i64) as f64 + 0.5) / k as f64 - 0.5,
                        dy as f64 + ((sub / k as i64) as f64 + 0.5) / k as f64 - 0.5,
                    );
                    let g = if blur > 0.0 {
                        (-o.norm_squared() / (2.0 * blur * blur)).exp()
                    } else {
                        f64::from(u8::from(dx == 0 && dy == 0))
                    };
                    total += g;
                    if (p + o - centre).norm() < r {
                        lit += g;
                    }
                }
                let c = ((lit / total) * 255.0).round();
                match c as u8 {
                    0 => 0,
                    255 => 255,
                    v => v,
                }
            })
            .collect();
        (inside, sd, coverage)
    }

    /// The largest |signed distance| of `img` on the circle (`centre`, `r`), 360 points.
    fn worst_on_circle(img: &[f32], w: usize, centre: V2, r: f64) -> f64 {
        (0..360)
            .map(|a| {
                let t = (a as f64).to_radians();
                let p = centre + V2::new(t.cos(), t.sin()) * r;
                bilinear(img, w, p.x, p.y).abs()
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn measured_coverage_puts_a_circle_s_outline_within_a_tenth_of_a_pixel() {
        let (w, centre, r) = (40usize, V2::new(19.3, 20.6), 11.7);
        for blur in [0.0, 0.7] {
            let (inside, sd, coverage) = disk(w, centre, r, blur);
            let mut refined = sd.clone();
            refine(&mut refined, &inside, &coverage, w, [0, 0]);
            let (binary, sub) = (
                worst_on_circle(&sd, w, centre, r),
                worst_on_circle(&refined, w, centre, r),
            );
            eprintln!("blur {blur} px: outline off by up to {binary:.3} px (binary), {sub:.3} px (refined)");
            assert!(
                binary > 0.3,
                "blur {blur}: binary outline off by at most {binary} px"
            );
            assert!(
                sub < 0.1,
                "blur {blur}: refined outline off by up to {sub} px"
            );
            // Every pixel keeps its side, and the distance grows by about a pixel per pixel
            // across the outline (a weaker slope would weaken the silhouette term's pull).
            assert!(refined.iter().zip(&inside).all(|(&d, &i)| (d > 0.0) == i));
            for a in 0..360 {
                let t = (a as f64).to_radians();
                let p = centre + V2::new(t.cos(), t.sin()) * r;
                let n = V2::new(t.cos(), t.sin()) * 0.25;
                let slope = (bilinear(&refined, w, p.x - n.x, p.y - n.y)
                    - bilinear(&refined, w, p.x + n.x, p.y + n.y))
                    / 0.5;
                assert!(slope > 0.7, "blur {blur}, angle {a}°: slope {slope}");
            }
        }
    }

    #[test]
    fn unmeasured_coverage_leaves_the_binary_outline() {
        let (w, centre, r) = (24usize, V2::new(11.4, 12.2), 6.3);
        let (inside, sd, _) = disk(w, centre, r, 0.0);
        let coverage: Vec<u8> = inside.iter().map(|&i| if i { 255 } else { 0 }).collect();
        let mut refined = sd.clone();
        refine(&mut refined, &inside, &coverage, w, [0, 0]);
        // The contour runs through the midpoints between the two sides' pixel centres: the
        // staircase's straight runs keep ±0.5, its corners are cut.
        for (i, (a, b)) in sd.iter().zip(&refined).enumerate() {
            assert!((a - b).abs() < 0.2, "pixel {i}: {a} → {b}");
            assert_eq!(*a > 0.0, *b > 0.0, "pixel {i}");
        }
    }
}
