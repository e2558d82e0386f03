//! The camera's blur, measured on the background captures (the monitor seen directly, without
//! the object): across a stripe edge of a coarse Gray-code bit, the pattern − inverse difference
//! rises from one plateau to the other over as many camera pixels as the camera spreads a sharp
//! edge. For a step spread by a symmetric kernel K (the camera's Gaussian blur of σ and the
//! pixel's own square), the normalised profile f = 2F − 1 (F: K's distribution) gives
//! ∫ (1 − f²) = 4 ∫ F (1 − F) = 2 E|K − K'| across the edge (K, K' independent draws of K):
//! summed over the camera pixels of a line that crosses the edge at cos θ to its normal,
//! (1 − f²) sums to 2 E|K − K'| / cos θ. The summand is smooth where the profile crosses zero,
//! so the sum over whole pixels does not depend on where between two pixels the edge lies (with
//! 1 − |f|, whose kink at the crossing the pixels sample, an edge halfway between two pixels
//! reads 20 % narrower than one on a pixel's centre at σ 0.7 px, and a monitor square to the
//! camera puts every edge of a bit at the same place between its pixels). The sensor noise adds
//! its variance to every f², which the plateaus measure and the sum gets back; no edge position
//! is fitted. σ is the value whose model E|K − K'| (the square projected at θ) matches the
//! edges' mean (docs/architecture.md §4, measuring the blur).
//!
//! The estimate needs a linear camera response (raw or linear captures), since a tone curve bends
//! the profile; captures whose pattern and inverse do not add up to white and black between the
//! stripes are named instead ([`Unmeasured::Nonlinear`]).

use super::DirectView;
use crate::patterns::GrayCode;
use crate::scan::decoded::MeasuredBlur;
use crate::util::mean;

/// Edges measured along a line are those whose normal is within this cosine of the line.
const MIN_COS: f64 = 0.7;
/// Fewest edges an estimate needs.
const MIN_EDGES: usize = 100;
/// Half-width of the first window around an edge crossing, camera pixels along the line; it
/// doubles (to at most [`MAX_REACH`]) while the blur found is too wide for it.
const FIRST_REACH: usize = 12;
const MAX_REACH: usize = 48;
/// Share of the edges left out at either end of the sorted measurements (stray edges).
const TRIM: f64 = 0.1;
/// Bins of the edges' cos θ over [`MIN_COS`], 1 in the fit (the model changes by about 0.2 %
/// across one).
const COS_BINS: usize = 30;

/// Why the blur was not measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Unmeasured {
    /// Fewer clean stripe edges than [`MIN_EDGES`] (a monitor small in the frame, few lit
    /// pixels); how many there were.
    TooFewEdges(usize),
    /// Across the edges pattern + inverse exceed white + black by this share of white − black
    /// on average (more than [`MAX_EXCESS`]): the captures went through a tone curve, which
    /// bends the profile.
    Nonlinear(f64),
}

impl std::fmt::Display for Unmeasured {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Unmeasured::TooFewEdges(n) => write!(
                f,
                "{n} clean stripe edges in the background captures, {MIN_EDGES} needed"
            ),
            Unmeasured::Nonlinear(x) => write!(
                f,
                "the captures' response is not linear (between the stripes pattern + inverse exceed white + black by {:.0} % of white − black: a tone curve); capture linear or raw images, or set blur_px in scan.toml",
                100.0 * x
            ),
        }
    }
}

/// The largest mean excess of pattern + inverse over white + black between the stripes (a
/// share of white − black) of a linear camera: complementary patterns add up to white, but a
/// gamma of 1/2.2 makes the middle of an edge 46 % too bright.
const MAX_EXCESS: f64 = 0.15;

/// The camera's blur measured on `view`, or why it cannot be.
pub fn estimate(view: &DirectView, code: &GrayCode) -> Result<MeasuredBlur, Unmeasured> {
    let mut reach = FIRST_REACH;
    loop {
        let edges = measure_edges(view, code, reach);
        check_edges(&edges)?;
        let est = fit_sigma(&edges);
        // The window's outer quarters, its plateaus, must lie beyond the edge's spread along
        // the line (3 (σ + ½) from the crossing at the widest tilt).
        let wide_enough = 6.0 * (est.sigma_px + 0.5) / MIN_COS <= reach as f64;
        if wide_enough || reach >= MAX_REACH {
            return Ok(est);
        }
        reach *= 2;
    }
}

/// Enough edges, from a camera whose response is linear.
fn check_edges(edges: &[Edge]) -> Result<(), Unmeasured> {
    if edges.len() < MIN_EDGES {
        return Err(Unmeasured::TooFewEdges(edges.len()));
    }
    let excesses: Vec<f64> = edges.iter().filter_map(|e| e.excess).collect();
    let excess = excesses.iter().sum::<f64>() / excesses.len().max(1) as f64;
    if excess > MAX_EXCESS {
        return Err(Unmeasured::Nonlinear(excess));
    }
    Ok(())
}

/// A direction of stripes: the column bits' edges are crossed along rows, the row bits' along
/// columns.
#[derive(Clone, Copy)]
enum Axis {
    U,
    V,
}

/// One measured edge.
struct Edge {
    /// E|K − K'|, camera pixels along the edge's normal.
    spread: f64,
    /// The cosine between the line and that normal.
    cos: f64,
    /// The mean of (pattern + inverse − white − black) / (white − black) over the window's
    /// pixels between the plateaus (|f| < ½); `None` for an edge with none.
    excess: Option<f64>,
}

/// Every measurable edge of both axes' coarse bits, windows of ±`reach` pixels.
fn measure_edges(view: &DirectView, code: &GrayCode, reach: usize) -> Vec<Edge> {
    let mut edges = Vec::new();
    for axis in [Axis::U, Axis::V] {
        if let Some(image) = coarse_bit(view, code, axis, reach) {
            edges_of_bit(view, axis, image, reach, &mut edges);
        }
    }
    edges
}

/// (step along the line, step across it, lines, pixels per line) in the row-major image.
fn line_layout(view: &DirectView, axis: Axis) -> (usize, usize, usize, usize) {
    match axis {
        Axis::U => (1, view.width, view.height, view.width),
        Axis::V => (view.width, 1, view.width, view.height),
    }
}

/// The decoded monitor coordinate of `axis` at pixel `p`, where its cell is at most
/// [`MAX_CELL`] monitor pixels wide.
fn coord(view: &DirectView, axis: Axis, p: usize) -> Option<f64> {
    let d = view.pixels.get(p)?;
    let a = match axis {
        Axis::U => d.u,
        Axis::V => d.v,
    };
    (view.lit[p] && a.bits > 0 && a.cell <= MAX_CELL).then_some(a.coord as f64)
}

/// The widest decoded cell [`coord_gradient`] reads, monitor pixels: where a camera pixel spans
/// several monitor pixels the finest bits blur away, and the cells' centres, 2·`H` camera pixels
/// apart, still give the slope to a few per cent.
const MAX_CELL: u32 = 64;

/// How the decoded coordinate of `axis` changes at pixel `p` (line `l`, position `i`), monitor
/// pixels per camera pixel: (along the line, across it), from the pixels 8 away.
fn coord_gradient(view: &DirectView, axis: Axis, (l, i): (usize, usize)) -> Option<(f64, f64)> {
    const H: usize = 8;
    let (along, across, lines, len) = line_layout(view, axis);
    if i < H || i + H >= len || l < H || l + H >= lines {
        return None;
    }
    let p = l * across + i * along;
    let diff = |step: usize| {
        Some((coord(view, axis, p + H * step)? - coord(view, axis, p - H * step)?) / (2 * H) as f64)
    };
    Some((diff(along)?, diff(across)?))
}

/// The pattern image of the finest bit of `axis` whose stripes are at least 2·`reach` + 6 camera
/// pixels wide along the lines (the median scale of the decoded coordinate); `None` when no bit
/// below the most significant is that coarse.
fn coarse_bit(view: &DirectView, code: &GrayCode, axis: Axis, reach: usize) -> Option<usize> {
    let (_, _, lines, len) = line_layout(view, axis);
    let scales: Vec<f64> = (0..lines)
        .step_by(8)
        .flat_map(|l| (0..len).step_by(8).map(move |i| (l, i)))
        .filter_map(|li| coord_gradient(view, axis, li).map(|(a, _)| a.abs()))
        .filter(|a| *a > 0.0)
        .collect();
    if scales.is_empty() {
        return None;
    }
    let scale = crate::util::median(scales);
    let (bits, first) = match axis {
        Axis::U => (code.column_bits() as usize, 0),
        Axis::V => (code.row_bits() as usize, 2 * code.column_bits() as usize),
    };
    // Bit k (most significant first) has stripes 2^(bits − k) monitor pixels wide.
    (1..bits)
        .rev()
        .find(|&k| (1u64 << (bits - k)) as f64 / scale >= (2 * reach + 6) as f64)
        .map(|k| first + 2 * k)
}

/// Measures the edges of the pattern `image` (its inverse follows it) along every line of
/// `axis`, each in a window of ±`reach` pixels around its crossing, into `edges`.
fn edges_of_bit(view: &DirectView, axis: Axis, image: usize, reach: usize, edges: &mut Vec<Edge>) {
    let (along, across, lines, len) = line_layout(view, axis);
    let pair = (view.images[image], view.images[image + 1]);
    let diff = |p: usize| pair.0[p] as f64 - pair.1[p] as f64;
    for l in 0..lines {
        let at = |i: usize| l * across + i * along;
        let mut i = reach;
        while i + reach < len {
            let (a, b) = (diff(at(i - 1)), diff(at(i)));
            if (a < 0.0) == (b < 0.0) {
                i += 1;
                continue;
            }
            // The crossing lies between i − 1 and i: a window of 2·reach samples around it.
            let window: Vec<usize> = (i - reach..i + reach).map(at).collect();
            if let Some(edge) = measure_edge(view, axis, (l, i), &window, pair) {
                edges.push(edge);
            }
            i += reach;
        }
    }
}

/// The edge whose crossing lies just before pixel `(l, i)`, from the samples of `window`; `None`
/// when the window is not one clean edge between two plateaus in lit pixels.
fn measure_edge(
    view: &DirectView,
    axis: Axis,
    (l, i): (usize, usize),
    window: &[usize],
    (pattern, inverse): (&[u8], &[u8]),
) -> Option<Edge> {
    if !window.iter().all(|&p| view.lit[p]) {
        return None;
    }
    let n = window.len();
    let values: Vec<f64> = window
        .iter()
        .map(|&p| pattern[p] as f64 - inverse[p] as f64)
        .collect();
    // Plateaus: the window's outer quarters, each side's level their mean.
    let quarter = n / 4;
    let (low, high) = (&values[..quarter], &values[n - quarter..]);
    let (lo, hi) = (mean(low), mean(high));
    let (mid, swing) = ((hi + lo) / 2.0, (hi - lo) / 2.0);
    let p = window[n / 2];
    let range = view.white[p] as f64 - view.black[p] as f64;
    if swing.abs() < 0.25 * range || swing.abs() < 4.0 {
        return None;
    }
    let f: Vec<f64> = values.iter().map(|v| (v - mid) / swing).collect();
    // Each plateau stays on its side (no second edge).
    let clean = f[..quarter].iter().all(|&x| x < -0.5) && f[n - quarter..].iter().all(|&x| x > 0.5);
    if !clean {
        return None;
    }
    let (a_along, a_across) = coord_gradient(view, axis, (l, i))?;
    let cos = a_along.abs() / a_along.hypot(a_across);
    if cos.is_nan() || cos < MIN_COS {
        return None;
    }
    // The noise's variance in f, from the plateaus' scatter about their levels; every sample's
    // f² carries it.
    let noise = (sum_sq(low, lo) + sum_sq(high, hi)) / (2 * quarter - 2) as f64 / (swing * swing);
    let sum: f64 = f.iter().map(|x| 1.0 - x * x).sum::<f64>() + n as f64 * noise;
    Some(Edge {
        spread: cos * sum / 2.0,
        cos,
        excess: excess(view, window, &f, (pattern, inverse)),
    })
}

/// Σ (x − `m`)² over `xs`.
fn sum_sq(xs: &[f64], m: f64) -> f64 {
    xs.iter().map(|x| (x - m) * (x - m)).sum()
}

/// The mean of (pattern + inverse − white − black) / (white − black) over the window's pixels
/// between the plateaus (|f| < ½); `None` for a window with none.
fn excess(
    view: &DirectView,
    window: &[usize],
    f: &[f64],
    (pattern, inverse): (&[u8], &[u8]),
) -> Option<f64> {
    let excesses: Vec<f64> = (window.iter().zip(f))
        .filter(|(_, x)| x.abs() < 0.5)
        .map(|(&p, _)| {
            let (w, b) = (view.white[p] as f64, view.black[p] as f64);
            (pattern[p] as f64 + inverse[p] as f64 - w - b) / (w - b)
        })
        .collect();
    (!excesses.is_empty()).then(|| mean(&excesses))
}

/// σ whose model matches the edges' trimmed mean E|K − K'| (edges checked by [`check_edges`]).
fn fit_sigma(edges: &[Edge]) -> MeasuredBlur {
    let mut spreads: Vec<f64> = edges.iter().map(|e| e.spread).collect();
    spreads.sort_by(f64::total_cmp);
    let cut = (TRIM * spreads.len() as f64) as usize;
    let kept = &spreads[cut..spreads.len() - cut];
    let measured = mean(kept);
    // The edges' tilts, counted in COS_BINS bins over [MIN_COS, 1]: the model is evaluated once
    // per bin, not once per edge.
    let mut counts = [0usize; COS_BINS];
    for e in edges {
        let b = ((e.cos - MIN_COS) / (1.0 - MIN_COS) * COS_BINS as f64) as usize;
        counts[b.min(COS_BINS - 1)] += 1;
    }
    let bin_cos = |b: usize| MIN_COS + (1.0 - MIN_COS) * (b as f64 + 0.5) / COS_BINS as f64;
    let model = |sigma: f64| {
        (counts.iter().enumerate())
            .filter(|(_, &n)| n > 0)
            .map(|(b, &n)| n as f64 * mean_abs_difference(sigma, bin_cos(b)))
            .sum::<f64>()
            / edges.len() as f64
    };
    let (mut lo, mut hi) = (0.0, 2.0 * crate::scan::MAX_BLUR_PX);
    if model(lo) >= measured {
        hi = 0.0;
    }
    for _ in 0..40 {
        let m = 0.5 * (lo + hi);
        if model(m) < measured {
            lo = m;
        } else {
            hi = m;
        }
    }
    MeasuredBlur {
        sigma_px: 0.5 * (lo + hi),
        edges: edges.len(),
    }
}

/// E|K − K'| for independent K, K' = σZ + the unit square pixel projected on a direction at
/// cos θ = `cos` to a side (Z standard normal), camera pixels: K − K' = σ√2 Z + cos θ (u − u') +
/// sin θ (v − v'), the differences of the square's coordinates triangular over [−1, 1]; by
/// quadrature (32 × 32 points over the two differences, 121 over Z).
fn mean_abs_difference(sigma: f64, cos: f64) -> f64 {
    const TRI: usize = 32;
    const Z: usize = 121;
    let sin = (1.0 - cos * cos).max(0.0).sqrt();
    let tri: Vec<(f64, f64)> = (0..TRI)
        .map(|i| {
            let t = -1.0 + 2.0 * (i as f64 + 0.5) / TRI as f64;
            (t, 1.0 - t.abs())
        })
        .collect();
    let (mut sum, mut weight) = (0.0, 0.0);
    for k in 0..Z {
        let z = -6.0 + 12.0 * k as f64 / (Z - 1) as f64;
        let wz = (-0.5 * z * z).exp();
        for &(a, wa) in &tri {
            for &(b, wb) in &tri {
                let w = wz * wa * wb;
                sum += w * (cos * a + sin * b + sigma * std::f64::consts::SQRT_2 * z).abs();
                weight += w;
            }
        }
    }
    sum / weight
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decode::graycode::{AxisDecode, PixelDecode};
    use rayon::prelude::*;

    #[test]
    fn the_spread_of_a_pixel_alone_and_of_a_wide_gaussian() {
        // Two draws over a unit square seen along a side: E|U − U'| = 1/3; a wide Gaussian:
        // E|σ√2 Z| = 2σ/√π.
        assert!((mean_abs_difference(0.0, 1.0) - 1.0 / 3.0).abs() < 2e-3);
        let wide = mean_abs_difference(4.0, 1.0);
        let gauss = 8.0 / std::f64::consts::PI.sqrt();
        assert!(
            (wide - gauss).abs() < 0.01 * gauss,
            "{wide} against {gauss}"
        );
        assert!(mean_abs_difference(0.5, 0.8) > mean_abs_difference(0.4, 0.8));
    }

    /// How the test's camera sees the monitor and makes its images.
    struct Camera {
        /// Monitor (column, row) seen at camera pixel (x, y), monitor pixels.
        uv: Box<dyn Fn(f64, f64) -> (f64, f64) + Sync>,
        /// The blur, camera pixels.
        sigma: f64,
        /// The response: grey = 255·(linear/255)^gamma.
        gamma: f64,
        /// The sensor noise after the blur, grey levels.
        noise: f64,
    }

    impl Camera {
        /// A linear, noise-free camera with a monitor tilted in the frame, so that a bit's edges
        /// fall anywhere between pixels.
        fn tilted(sigma: f64) -> Camera {
            Camera {
                uv: Box::new(|x, y| (1.3 * x + 0.4 * y + 20.0, -0.3 * x + 1.2 * y + 120.0)),
                sigma,
                gamma: 1.0,
                noise: 0.0,
            }
        }
    }

    /// The test camera's image size, pixels.
    const SIZE: (usize, usize) = (320, 240);
    /// Monitor samples per camera pixel side, blurred there (as optics blur before the sensor),
    /// then averaged over each pixel's square.
    const SUB: usize = 6;

    impl Camera {
        /// Grey level of a linear intensity through the response, rounded to 8 bits.
        fn tone(&self, v: f64) -> u8 {
            (255.0 * (v.clamp(0.0, 255.0) / 255.0).powf(self.gamma)).round() as u8
        }

        /// The monitor at 6 × 6 samples a camera pixel, lit by pattern `i` of `code` (all white
        /// for `usize::MAX`): 20 grey levels dark, 220 lit.
        fn monitor_samples(&self, code: &GrayCode, i: usize) -> Vec<f32> {
            let (sw, sh) = (SIZE.0 * SUB, SIZE.1 * SUB);
            (0..sw * sh)
                .map(|q| {
                    let (x, y) = ((q % sw) as f64 + 0.5, (q / sw) as f64 + 0.5);
                    let (u, v) = (self.uv)(x / SUB as f64 - 0.5, y / SUB as f64 - 0.5);
                    let lit =
                        i == usize::MAX || code.is_white(i, u.floor() as u32, v.floor() as u32);
                    20.0 + 200.0 * lit as u8 as f32
                })
                .collect()
        }

        /// Pattern `i`'s image (see [`Self::monitor_samples`]): blurred, area-integrated, noisy
        /// (seeded by `i`), through the response.
        fn image(&self, code: &GrayCode, i: usize) -> Vec<u8> {
            use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Size, BORDER_REPLICATE};
            use opencv::imgproc::INTER_AREA;
            use rand::SeedableRng;
            use rand_distr::Distribution;
            let fine = self.monitor_samples(code, i);
            let (sw, sh) = (SIZE.0 * SUB, SIZE.1 * SUB);
            let fine = Mat::new_rows_cols_with_data(sh as i32, sw as i32, &fine).unwrap();
            let mut blurred = fine.try_clone().unwrap();
            if self.sigma > 0.0 {
                let s = self.sigma * SUB as f64;
                let zero = Size::new(0, 0);
                opencv::imgproc::gaussian_blur(&fine, &mut blurred, zero, s, s, BORDER_REPLICATE)
                    .unwrap();
            }
            let mut out = Mat::default();
            let size = Size::new(SIZE.0 as i32, SIZE.1 as i32);
            opencv::imgproc::resize(&blurred, &mut out, size, 0.0, 0.0, INTER_AREA).unwrap();
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(i as u64);
            let normal = rand_distr::Normal::new(0.0, self.noise).unwrap();
            let mut noise = || {
                if self.noise > 0.0 {
                    normal.sample(&mut rng)
                } else {
                    0.0
                }
            };
            out.data_typed::<f32>()
                .unwrap()
                .iter()
                .map(|&v| self.tone(v as f64 + noise()))
                .collect()
        }

        /// Every pixel decoded to the monitor cell its centre sees.
        fn true_decodes(&self) -> Vec<PixelDecode> {
            let (w, h) = SIZE;
            let axis = |c: f64| AxisDecode {
                coord: c.floor() as f32,
                cell: 1,
                bits: 10,
            };
            (0..w * h)
                .map(|p| {
                    let (u, v) = (self.uv)((p % w) as f64, (p / w) as f64);
                    PixelDecode {
                        u: axis(u),
                        v: axis(v),
                    }
                })
                .collect()
        }
    }

    /// Stripes of `code`'s bits seen by `cam` (blurred, area-integrated, noisy, through its
    /// response, rounded to 8 bits): the blur found.
    fn measured(cam: &Camera) -> Result<MeasuredBlur, Unmeasured> {
        let code = GrayCode {
            width: 640,
            height: 512,
        };
        let images: Vec<Vec<u8>> = (0..code.pattern_count())
            .into_par_iter()
            .map(|i| cam.image(&code, i))
            .collect();
        let (w, h) = SIZE;
        let white = cam.image(&code, usize::MAX);
        let black = vec![cam.tone(20.0); w * h];
        let pixels = cam.true_decodes();
        let lit = vec![true; w * h];
        let refs: Vec<&[u8]> = images.iter().map(|i| i.as_slice()).collect();
        let view = DirectView {
            images: &refs,
            white: &white,
            black: &black,
            pixels: &pixels,
            lit: &lit,
            width: w,
            height: h,
        };
        estimate(&view, &code)
    }

    #[test]
    fn a_known_blur_is_found_on_tilted_stripes() {
        for sigma in [0.0, 0.7, 1.5, 3.0] {
            let e = measured(&Camera::tilted(sigma)).expect("a linear camera's edges measure");
            eprintln!(
                "blur {sigma} px: found {:.3} px over {} edges",
                e.sigma_px, e.edges
            );
            assert!(e.edges >= MIN_EDGES);
            assert!(
                (e.sigma_px - sigma).abs() <= 0.05 + 0.02 * sigma,
                "{sigma}: {e:?}"
            );
        }
    }

    #[test]
    fn the_blur_does_not_depend_on_where_the_edges_fall_between_pixels() {
        // A monitor square to a noisy camera, 2 monitor pixels a camera pixel: every edge of a
        // coarse bit lies at the same place between two pixels, from a pixel's centre (offset
        // 0) to halfway (1).
        for offset in [0.0, 0.5, 1.0, 1.5] {
            let cam = Camera {
                uv: Box::new(move |x, y| (2.0 * x + 20.0 + offset, 2.0 * y + 120.0 + offset)),
                sigma: 0.7,
                gamma: 1.0,
                noise: 3.0,
            };
            let e = measured(&cam).expect("a linear camera's edges measure");
            eprintln!("offset {offset}: found {:.3} px", e.sigma_px);
            assert!((e.sigma_px - 0.7).abs() <= 0.03, "{offset}: {e:?}");
        }
    }

    #[test]
    fn a_tone_curve_is_named_not_measured() {
        // sRGB-like captures: between the stripes pattern + inverse exceed white + black.
        let cam = Camera {
            gamma: 1.0 / 2.2,
            ..Camera::tilted(0.7)
        };
        match measured(&cam) {
            Err(Unmeasured::Nonlinear(x)) => assert!(x > MAX_EXCESS, "{x}"),
            other => panic!("{other:?}"),
        }
    }
}
