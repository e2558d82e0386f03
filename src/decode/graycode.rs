//! Whole-image Gray-code decoding with per-bit reliability.
//!
//! OpenCV's semantics per bit (`GrayCodePattern::getProjPixel`): the bit is 1 where the pattern
//! image is brighter than its inverse, and it is unreliable where the two differ by less than
//! the white threshold. OpenCV rejects a pixel if any bit is unreliable. Seen through solid glass,
//! a camera pixel averages tens of monitor pixels, so the finest stripes blur to grey while the
//! coarse bits stay clear: here the bits are kept from the most significant down to the first
//! unreliable one, and the pixel gets the centre of the cell those bits pin down, with the cell's
//! size as its uncertainty. Where every bit is reliable the result is OpenCV's exactly.

use rayon::prelude::*;

use crate::patterns::GrayCode;

/// One decoded axis of a pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisDecode {
    /// Monitor coordinate, pixels: the centre of the cell the reliable bits select.
    pub coord: f32,
    /// Width of that cell, monitor pixels (1 when every bit is reliable).
    pub cell: u32,
    /// Reliable bits, most significant first.
    pub bits: u8,
}

/// A decoded pixel: columns (u) and rows (v).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelDecode {
    pub u: AxisDecode,
    pub v: AxisDecode,
}

impl PixelDecode {
    /// Every bit reliable and inside the monitor: what OpenCV's `getProjPixel` accepts.
    pub fn complete(&self, code: &GrayCode) -> bool {
        self.u.bits as u32 == code.column_bits()
            && self.v.bits as u32 == code.row_bits()
            && (self.u.coord as u32) < code.width
            && (self.v.coord as u32) < code.height
    }
}

/// How sure a bit must be.
#[derive(Clone, Copy, Debug)]
pub struct BitTest {
    /// Smallest pattern–inverse difference, grey levels (OpenCV's `whiteThreshold`).
    pub white_threshold: u8,
    /// Smallest pattern–inverse difference as a share of the pixel's white − black range: a
    /// bit whose stripes split the pixel's footprint nearly evenly is not trusted. 0 gives
    /// OpenCV's test exactly.
    pub min_contrast: f32,
}

impl BitTest {
    /// The smallest pattern–inverse difference of a reliable bit at a pixel with these white
    /// and black levels, grey levels.
    pub fn need(&self, white: u8, black: u8) -> f32 {
        let range = (white as f32 - black as f32).max(0.0);
        (self.white_threshold as f32).max(self.min_contrast * range)
    }
}

/// Decodes every pixel of a view from its pattern images (`code.pattern_count()` 8-bit images of
/// one size, pixels in the same order, images in OpenCV's order) and its white and black images.
pub fn decode_view(
    images: &[&[u8]],
    white: &[u8],
    black: &[u8],
    code: &GrayCode,
    test: BitTest,
) -> Vec<PixelDecode> {
    assert_eq!(images.len(), code.pattern_count(), "one image per pattern");
    let n = images[0].len();
    assert!(images.iter().all(|i| i.len() == n), "images of one size");
    let (nc, nr) = (code.column_bits() as usize, code.row_bits() as usize);
    (0..n)
        .into_par_iter()
        .map(|p| {
            let need = test.need(white[p], black[p]);
            let axis = |first: usize, bits: usize| {
                let mut gray = 0u32;
                let mut kept = 0usize;
                for k in 0..bits {
                    let (a, b) = (
                        images[first + 2 * k][p] as i32,
                        images[first + 2 * k + 1][p] as i32,
                    );
                    if ((a - b).abs() as f32) < need {
                        break;
                    }
                    gray = (gray << 1) | (a > b) as u32;
                    kept += 1;
                }
                // Gray prefix → binary prefix (the prefix of the binary code is the binary of the
                // Gray prefix), then the centre of the cell of 2^(bits − kept) values.
                let mut bin = gray;
                let mut shift = gray >> 1;
                while shift != 0 {
                    bin ^= shift;
                    shift >>= 1;
                }
                let free = (bits - kept) as u32;
                let cell = 1u32 << free;
                let start = bin << free;
                AxisDecode {
                    coord: start as f32 + (cell as f32 - 1.0) / 2.0,
                    cell,
                    bits: kept as u8,
                }
            };
            PixelDecode {
                u: axis(0, nc),
                v: axis(2 * nc, nr),
            }
        })
        .collect()
}

/// The measured contrasts (pattern − inverse)/(white − black) of the two Gray bits around each
/// pixel's decoded cell, per axis: the bit whose stripes are twice the cell wide (the last one
/// the cell keeps) and the one whose stripes are the cell's width (the first one it drops); NaN
/// where a bit does not exist or the pixel has no white − black range. Pixels in the order of
/// `decoded` (`images`, `white`, `black` as in [`decode_view`]).
pub fn bit_contrasts(
    images: &[&[u8]],
    white: &[u8],
    black: &[u8],
    code: &GrayCode,
    decoded: &[PixelDecode],
) -> Vec<[f32; 4]> {
    let (nc, nr) = (code.column_bits(), code.row_bits());
    decoded
        .par_iter()
        .enumerate()
        .map(|(p, d)| {
            let range = white[p] as f32 - black[p] as f32;
            // Bit `bit` (from the least significant) of the axis whose images start at `first`.
            let contrast = |first: usize, bits: u32, bit: Option<u32>| match bit {
                Some(b) if b < bits && range > 0.0 => {
                    let i = first + 2 * (bits - 1 - b) as usize;
                    (images[i][p] as f32 - images[i + 1][p] as f32) / range
                }
                _ => f32::NAN,
            };
            let axis = |a: &AxisDecode, first: usize, bits: u32| {
                let last = a.cell.trailing_zeros();
                [
                    contrast(first, bits, Some(last)),
                    contrast(first, bits, last.checked_sub(1)),
                ]
            };
            let (u, v) = (axis(&d.u, 0, nc), axis(&d.v, 2 * nc as usize, nr));
            [u[0], u[1], v[0], v[1]]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bit_contrasts_read_the_bits_around_the_cell() {
        // An 8×2 monitor: 3 column bits, 1 row bit. One pixel whose column bits 2 and 1 (from
        // the least significant) are clear and bit 0 is grey, white 200, black 0.
        let code = GrayCode {
            width: 8,
            height: 2,
        };
        let images: Vec<Vec<u8>> = vec![
            vec![180], // column bit 2: pattern
            vec![20],  // inverse
            vec![40],  // column bit 1
            vec![160],
            vec![110], // column bit 0: (110 − 90)/200 = 0.1, below 0.3 → unreliable
            vec![90],
            vec![200], // row bit 0
            vec![0],
        ];
        let refs: Vec<&[u8]> = images.iter().map(|v| &v[..]).collect();
        let test = BitTest {
            white_threshold: 5,
            min_contrast: 0.3,
        };
        let d = decode_view(&refs, &[200], &[0], &code, test);
        assert_eq!((d[0].u.cell, d[0].v.cell), (2, 1));
        let c = bit_contrasts(&refs, &[200], &[0], &code, &d)[0];
        // u: the cell keeps bits 2 and 1 (last: bit 1, −0.6), drops bit 0 (0.1); v: every bit
        // kept (bit 0, 1.0), none dropped.
        assert!(
            (c[0] + 0.6).abs() < 1e-6 && (c[1] - 0.1).abs() < 1e-6,
            "{c:?}"
        );
        assert!((c[2] - 1.0).abs() < 1e-6 && c[3].is_nan(), "{c:?}");
        // No white − black range: nothing to measure.
        assert!(bit_contrasts(&refs, &[0], &[0], &code, &d)[0]
            .iter()
            .all(|x| x.is_nan()));
    }
}
