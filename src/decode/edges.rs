//! Sub-pixel stripe edges: where, between two neighbouring camera pixels, a Gray bit's stripes
//! change from one monitor cell to the next.
//!
//! A pixel's decoded cell says only that the monitor point it sees lies somewhere in the cell,
//! which on a rig whose camera pixel covers many monitor pixels is a block of 8–64 of them.
//! The boundaries between cells are known exactly on the monitor, and the camera sees each one
//! where a bit's pattern − inverse difference Δ changes sign: between two neighbouring pixels A
//! and B that agree on every coarser bit, at the fraction Δ_A / (Δ_A − Δ_B) of the way from A to
//! B (the blur spreads the step evenly on both sides). Each such crossing is a camera point that
//! sees a known monitor line (a column boundary u = const, or a row boundary v = const), far
//! more precisely than the cells around it.

use rayon::prelude::*;

use super::graycode::BitTest;
use super::DirectView;
use crate::patterns::GrayCode;
use crate::util::hash_share;

/// A cell boundary seen between two neighbouring camera pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StripeEdge {
    /// Where the camera sees it: image coordinates, camera pixels (pixel centres at integers).
    pub pixel: (f64, f64),
    /// A boundary between columns (`true`: the monitor line u = `coord`) or between rows (v).
    pub column: bool,
    /// The boundary's monitor coordinate, monitor pixels (pixel centres at integers, so a
    /// boundary lies half-way between two).
    pub coord: f64,
}

/// The stripe edges between horizontally or vertically neighbouring lit pixels, in pixel
/// order: a bit counts where its difference swings across the pair by at least twice the
/// contrast a reliable bit needs there (`test`). At most about `most` of them: beyond `most` / 2
/// lit pixels (each pair of pixels gives at most one edge per axis, about two per pixel) a
/// deterministic share of the pairs is looked at, so that a fine camera's edges do not outweigh
/// its images in memory.
pub fn stripe_edges(
    c: &DirectView,
    code: &GrayCode,
    test: BitTest,
    most: usize,
) -> Vec<StripeEdge> {
    let height = c.height;
    let lit = c.lit.iter().filter(|&&l| l).count();
    let share = (most as f64 / (2.0 * lit.max(1) as f64)).min(1.0);
    (0..height)
        .into_par_iter()
        .flat_map_iter(|y| {
            (0..c.width).flat_map(move |x| {
                let a = y * c.width + x;
                let right = (x + 1 < c.width).then_some(a + 1);
                let below = (y + 1 < height).then_some(a + c.width);
                [right, below]
                    .into_iter()
                    .flatten()
                    .filter(move |&b| {
                        share >= 1.0 || hash_share((a as u64) << 32 | b as u64) < share
                    })
                    .flat_map(move |b| {
                        [true, false].map(|column| edge(c, code, test, (a, b), column))
                    })
                    .flatten()
            })
        })
        .collect()
}

/// The edge of one axis between pixels `a` and `b`, if their difference crosses one there.
fn edge(
    c: &DirectView,
    code: &GrayCode,
    test: BitTest,
    (a, b): (usize, usize),
    column: bool,
) -> Option<StripeEdge> {
    if !(c.lit[a] && c.lit[b]) {
        return None;
    }
    let (total, first, extent) = if column {
        (code.column_bits(), 0, code.width)
    } else {
        (
            code.row_bits(),
            2 * code.column_bits() as usize,
            code.height,
        )
    };
    let axis = |p: usize| if column { c.pixels[p].u } else { c.pixels[p].v };
    let (da, db) = (axis(a), axis(b));
    let shared = u32::from(da.bits.min(db.bits));
    let start = |d: super::graycode::AxisDecode| (d.coord - (d.cell as f32 - 1.0) / 2.0) as u32;
    // The bits both decode and agree on: any bit they decode differently, or the first one
    // either leaves undecided, is where the boundary may lie.
    let differ = if shared == 0 {
        0
    } else {
        (start(da) ^ start(db)) >> (total - shared)
    };
    let k = shared - (32 - differ.leading_zeros());
    if k >= total {
        return None;
    }
    let diff = |p: usize| {
        let i = first + 2 * k as usize;
        c.images[i][p] as f64 - c.images[i + 1][p] as f64
    };
    let (fa, fb) = (diff(a), diff(b));
    let need = test
        .need(c.white[a], c.black[a])
        .max(test.need(c.white[b], c.black[b]));
    if fa * fb >= 0.0 || (fa - fb).abs() < 2.0 * need as f64 {
        return None;
    }
    // The level-k cell both lie in; bit k splits it in the middle.
    let half = 1u32 << (total - k - 1);
    let boundary = ((start(da) >> (total - k)) << (total - k)) + half;
    if boundary >= extent {
        return None;
    }
    let t = fa / (fa - fb);
    let at = |p: usize| ((p % c.width) as f64, (p / c.width) as f64);
    let (pa, pb) = (at(a), at(b));
    Some(StripeEdge {
        pixel: (pa.0 + t * (pb.0 - pa.0), pa.1 + t * (pb.1 - pa.1)),
        column,
        coord: boundary as f64 - 0.5,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decode::graycode::decode_view;

    /// A camera looking straight at the monitor, one camera pixel over `scale` monitor
    /// pixels, the stripes blurred by a box of one camera pixel: every edge lands within a
    /// tenth of a camera pixel of where the boundary it names projects (a cell is 3–12 camera
    /// pixels wide here).
    #[test]
    fn edges_land_where_their_boundaries_project() {
        let code = GrayCode {
            width: 256,
            height: 64,
        };
        let (w, h, scale, offset) = (40usize, 8usize, 5.3, 7.9);
        // Camera pixel x sees monitor u = offset + scale·x (its centre), averaged over its width.
        let sample = |i: usize, x: usize| {
            let n = 64;
            (0..n)
                .map(|s| {
                    let u = offset + scale * (x as f64 - 0.5 + (s as f64 + 0.5) / n as f64);
                    // Monitor pixel u covers [u − 0.5, u + 0.5).
                    code.is_white(i, (u + 0.5).floor() as u32, 3) as u32 as f64
                })
                .sum::<f64>()
                / n as f64
        };
        let images: Vec<Vec<u8>> = (0..code.pattern_count())
            .map(|i| {
                (0..w * h)
                    .map(|p| (20.0 + 200.0 * sample(i, p % w)).round() as u8)
                    .collect()
            })
            .collect();
        let refs: Vec<&[u8]> = images.iter().map(|v| v.as_slice()).collect();
        let (white, black) = (vec![220u8; w * h], vec![20u8; w * h]);
        let test = BitTest {
            white_threshold: 5,
            min_contrast: 0.3,
        };
        let pixels = decode_view(&refs, &white, &black, &code, test);
        let lit = vec![true; w * h];
        let data: Vec<&[u8]> = refs
            .iter()
            .copied()
            .chain([&white[..], &black[..]])
            .collect();
        let capture = DirectView::new(&data, refs.len(), (&pixels, &lit), (w as u32, h as u32));
        let edges = stripe_edges(&capture, &code, test, usize::MAX);
        let columns: Vec<_> = edges.iter().filter(|e| e.column).collect();
        // The boundaries of the stripes the camera resolves: about one per 16 monitor pixels.
        assert!(columns.len() >= h * 10, "{} edges", columns.len());
        for e in &columns {
            let seen = offset + scale * e.pixel.0;
            assert!(
                (seen - e.coord).abs() < 0.1 * scale,
                "edge at x {} sees u {seen}, names {}",
                e.pixel.0,
                e.coord
            );
        }
        // Rows: the camera sees one monitor row, so no row boundary.
        assert!(edges.iter().all(|e| e.column));
        // A cap on the edges looks at a share of the pairs (here a quarter: a cap of 160 over
        // 320 lit pixels), the same ones on every call.
        let few = stripe_edges(&capture, &code, test, 160);
        assert!(
            few.len() < edges.len() / 2 && few.len() > edges.len() / 10,
            "{}",
            few.len()
        );
        assert!(few.iter().all(|e| edges.contains(e)));
        assert_eq!(few, stripe_edges(&capture, &code, test, 160));
    }
}
