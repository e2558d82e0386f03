//! Gray-code patterns in exactly the order of OpenCV's `structured_light::GrayCodePattern`
//! (docs/architecture.md §2): for each column bit, most significant first, the pattern then its inverse; then
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

    /// What image `i` of the sequence shows, for the order file: e.g. "column bit 10 (most
    /// significant), pattern".
    pub fn describe(&self, i: usize) -> String {
        let (nc, nr) = (self.column_bits() as usize, self.row_bits() as usize);
        let n = self.pattern_count();
        if i >= n {
            return if i == n {
                "white (shadow mask)".into()
            } else {
                "black (shadow mask)".into()
            };
        }
        let (axis, bits, j) = if i < 2 * nc {
            ("column", nc, i)
        } else {
            ("row", nr, i - 2 * nc)
        };
        let k = bits - 1 - j / 2;
        let rank = if k == bits - 1 {
            " (most significant)"
        } else if k == 0 {
            " (least significant)"
        } else {
            ""
        };
        format!(
            "{axis} bit {k}{rank}, {}",
            if j % 2 == 0 { "pattern" } else { "inverse" }
        )
    }

    /// The images to show on the monitor, in order, 8-bit grey: OpenCV's own
    /// `GrayCodePattern::generate`, then white and black.
    pub fn images(&self) -> anyhow::Result<Vec<opencv::core::Mat>> {
        use opencv::core::{Mat, Scalar, Vector, CV_8UC1};
        use opencv::prelude::*;
        use opencv::structured_light::{GrayCodePattern, GrayCodePattern_Params};

        let mut params = GrayCodePattern_Params::default()?;
        params.set_width(self.width as i32);
        params.set_height(self.height as i32);
        let mut generator = GrayCodePattern::create(&params)?;
        let mut images = Vector::<Mat>::new();
        generator.generate(&mut images)?;
        let (h, w) = (self.height as i32, self.width as i32);
        for level in [255.0, 0.0] {
            images.push(Mat::new_rows_cols_with_default(
                h,
                w,
                CV_8UC1,
                Scalar::all(level),
            )?);
        }
        if images.len() != self.file_names().len() {
            anyhow::bail!(
                "OpenCV generated {} images, expected {}",
                images.len(),
                self.file_names().len()
            );
        }
        Ok(images.to_vec())
    }

    /// Writes the images to show on the monitor into `dir` (named as the captures are), plus
    /// `ORDER.txt` saying what each one is.
    pub fn write_images(&self, dir: &std::path::Path) -> anyhow::Result<()> {
        use anyhow::Context;

        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let mut order = format!(
            "Gray-code patterns for a {}x{} monitor, in the order of OpenCV's structured_light::GrayCodePattern\n\
             (generate(), then getImagesForShadowMasks()). Show them in this order; name the captures the same.\n\n",
            self.width, self.height
        );
        for (i, (img, name)) in self.images()?.iter().zip(self.file_names()).enumerate() {
            crate::util::image::write_png(&dir.join(&name), img)?;
            order += &format!("{name}\t{}\n", self.describe(i));
        }
        let path = dir.join("ORDER.txt");
        crate::util::atomic::write_atomic(&path, |w| w.write_all(order.as_bytes()))
            .with_context(|| format!("cannot write {}", path.display()))
    }
}

/// File names of a view's captures: the Gray code's, then the phase shift's if there is one.
pub fn capture_names(code: &GrayCode, phase: Option<&PhaseShift>) -> Vec<String> {
    let mut names = code.file_names();
    if let Some(p) = phase {
        names.extend(p.file_names());
    }
    names
}

fn bits_for(n: u32) -> u32 {
    (n as f64).log2().ceil() as u32
}

/// Sinusoidal phase-shift patterns, shown after the Gray code for sub-pixel accuracy: for each
/// axis, `steps` images `0.5 + 0.5·cos(2π·x/period − 2π·k/steps)` (x the monitor column, then
/// row). The Gray code's reliable bits pick the period; the phase gives the position inside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhaseShift {
    /// Images per axis (≥ 3).
    pub steps: u32,
    /// Period of the sinusoid, monitor pixels (≥ 4).
    pub period_px: u32,
}

impl PhaseShift {
    /// File names: `phase_u_00.png` … then `phase_v_00.png` …
    pub fn file_names(&self) -> Vec<String> {
        ["u", "v"]
            .iter()
            .flat_map(|a| (0..self.steps).map(move |k| format!("phase_{a}_{k:02}.png")))
            .collect()
    }

    /// Brightness (0..1) of image `k` of an axis at monitor coordinate `x` (pixels).
    pub fn value(&self, x: f64, k: u32) -> f64 {
        let t = std::f64::consts::TAU;
        0.5 + 0.5 * (t * x / self.period_px as f64 - t * k as f64 / self.steps as f64).cos()
    }

    /// From the `steps` intensities of one axis: the coordinate modulo the period (monitor
    /// pixels) and the modulation B/A (1 for full contrast, 0 for none).
    pub fn wrapped(&self, intensities: impl Iterator<Item = f64>) -> (f64, f64) {
        let t = std::f64::consts::TAU;
        let (mut s, mut c, mut sum) = (0.0, 0.0, 0.0);
        for (k, i) in intensities.enumerate() {
            let d = t * k as f64 / self.steps as f64;
            s += i * d.sin();
            c += i * d.cos();
            sum += i;
        }
        let n = self.steps as f64;
        let (a, b) = (sum / n, 2.0 / n * s.hypot(c));
        let phase = s.atan2(c).rem_euclid(t);
        (
            phase / t * self.period_px as f64,
            if a > 0.0 { b / a } else { 0.0 },
        )
    }

    /// Image `i` (in [`Self::file_names`] order) for a `width` × `height` monitor: 8-bit grey,
    /// row-major.
    pub fn image(&self, i: usize, width: u32, height: u32) -> Vec<u8> {
        let (k, along_u) = ((i as u32) % self.steps, (i as u32) < self.steps);
        (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| (255.0 * self.value(if along_u { x } else { y } as f64, k)).round() as u8)
            .collect()
    }

    /// Writes the images for a `width` × `height` monitor into `dir`.
    pub fn write_images(
        &self,
        dir: &std::path::Path,
        width: u32,
        height: u32,
    ) -> anyhow::Result<()> {
        for (i, name) in self.file_names().iter().enumerate() {
            let img = self.image(i, width, height);
            crate::util::image::write_pixels(&dir.join(name), width, height, &img)?;
        }
        Ok(())
    }
}
