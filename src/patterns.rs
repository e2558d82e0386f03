//! Gray-code patterns in exactly the order of OpenCV's `structured_light::GrayCodePattern`
//! (DESIGN §2): for each column bit, most significant first, the pattern then its inverse; then
//! the same for the row bits; then the white and the black image of
//! `getImagesForShadowMasks()`. A pattern pixel is white where the bit of the Gray code
//! `g = c ^ (c >> 1)` of its column (or row) is set.

/// The Gray-code pattern set of a `width` × `height` monitor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GrayCode {
    pub width: u32,
    pub height: u32,
}

impl GrayCode {
    /// Bits needed for the columns: ⌈log2 width⌉ (as OpenCV computes it).
    pub fn column_bits(&self) -> u32 {
        bits_for(self.width)
    }

    /// Bits needed for the rows: ⌈log2 height⌉.
    pub fn row_bits(&self) -> u32 {
        bits_for(self.height)
    }

    /// Number of pattern images (patterns and inverses, without white and black): 44 for
    /// 1920×1080.
    pub fn pattern_count(&self) -> usize {
        2 * (self.column_bits() + self.row_bits()) as usize
    }

    /// Is monitor pixel (u, v) white in pattern image `i` (< [`Self::pattern_count`])?
    pub fn is_white(&self, i: usize, u: u32, v: u32) -> bool {
        let nc = self.column_bits() as usize;
        let (bits, value, j) = if i < 2 * nc {
            (nc, u, i)
        } else {
            (self.row_bits() as usize, v, i - 2 * nc)
        };
        let k = bits - 1 - j / 2;
        let gray = value ^ (value >> 1);
        ((gray >> k) & 1 == 1) != (j % 2 == 1)
    }

    /// File names of the captures, in order: `00.png` … (two digits at least), `white.png`,
    /// `black.png`.
    pub fn file_names(&self) -> Vec<String> {
        let n = self.pattern_count();
        let digits = n.saturating_sub(1).to_string().len().max(2);
        let mut names: Vec<String> = (0..n).map(|i| format!("{i:0digits$}.png")).collect();
        names.push("white.png".into());
        names.push("black.png".into());
        names
    }
}

fn bits_for(n: u32) -> u32 {
    (n as f64).log2().ceil() as u32
}
