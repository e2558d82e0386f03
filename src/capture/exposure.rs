//! The exposure check: what the camera makes of the monitor's white and black.

use std::path::Path;

use anyhow::{bail, Result};
use opencv::core::MatTraitConstManual;

use crate::util::image::read_image;

/// Contrast below which the camera does not see the monitor's light (grey levels).
const FATAL_CONTRAST: f64 = 10.0;
/// Contrast below which decoding loses bits to noise (grey levels).
const LOW_CONTRAST: f64 = 60.0;
/// Share of saturated pixels in the white image above which exposure is too long.
const SATURATED_SHARE: f64 = 0.01;
/// Share of pixels brighter than this in the black image above which the room is too bright.
const BRIGHT_BLACK: u8 = 60;
const BRIGHT_BLACK_SHARE: f64 = 0.2;

/// Figures of one white/black pair.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Exposure {
    /// White − black in the brightest tenth of the image (where the monitor is), grey levels.
    pub contrast: f64,
    /// Share of the white image at 255.
    pub saturated: f64,
    /// Share of the black image brighter than 60 grey levels.
    pub bright_black: f64,
}

impl Exposure {
    /// Measures the pair of 8-bit grey images.
    pub fn measure(white: &Path, black: &Path) -> Result<Self> {
        let (w, b) = (read_grey(white)?, read_grey(black)?);
        if w.len() != b.len() || w.is_empty() {
            bail!("{} and {} differ in size", white.display(), black.display());
        }
        let mut diff: Vec<i32> = w
            .iter()
            .zip(&b)
            .map(|(&w, &b)| w as i32 - b as i32)
            .collect();
        let top = diff.len() - diff.len() / 10 - 1;
        let (_, &mut p90, _) = diff.select_nth_unstable(top);
        let share = |n: usize| n as f64 / w.len() as f64;
        Ok(Exposure {
            contrast: p90 as f64,
            saturated: share(w.iter().filter(|&&v| v == 255).count()),
            bright_black: share(b.iter().filter(|&&v| v > BRIGHT_BLACK).count()),
        })
    }

    /// Why the capture cannot go on, if it cannot.
    pub fn fatal(&self) -> Option<String> {
        (self.contrast < FATAL_CONTRAST).then(|| {
            format!(
                "the monitor's white and black differ by only {:.0} grey levels where the image is brightest: check that the camera sees the monitor, then raise the exposure or gain",
                self.contrast
            )
        })
    }

    /// Advice on an exposure that works but loses accuracy.
    pub fn advice(&self) -> Vec<String> {
        let mut advice = Vec::new();
        if self.contrast < LOW_CONTRAST {
            advice.push(format!(
                "low contrast ({:.0} grey levels between white and black): raise the exposure or the monitor's brightness; the finest Gray bits will drown in noise",
                self.contrast
            ));
        }
        if self.saturated > SATURATED_SHARE {
            advice.push(format!(
                "{:.1} % of the white image is saturated: shorten the exposure (saturation blurs the stripes' edges)",
                100.0 * self.saturated
            ));
        }
        if self.bright_black > BRIGHT_BLACK_SHARE {
            advice.push(format!(
                "{:.0} % of the black image is brighter than {BRIGHT_BLACK} grey levels: darken the room",
                100.0 * self.bright_black
            ));
        }
        advice
    }
}

fn read_grey(path: &Path) -> Result<Vec<u8>> {
    let m = read_image(path, opencv::imgcodecs::IMREAD_GRAYSCALE)?;
    Ok(m.data_bytes()?.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair(dir: &Path, white: u8, black: u8) -> Exposure {
        let (w, b) = (dir.join("white.png"), dir.join("black.png"));
        crate::util::image::write_pixels(&w, 40, 30, &[white; 1200]).unwrap();
        crate::util::image::write_pixels(&b, 40, 30, &[black; 1200]).unwrap();
        Exposure::measure(&w, &b).unwrap()
    }

    #[test]
    fn good_dark_and_saturated_exposures_are_told_apart() {
        let dir = tempfile::tempdir().unwrap();
        let good = pair(dir.path(), 200, 10);
        assert_eq!(good.contrast, 190.0);
        assert!(
            good.fatal().is_none() && good.advice().is_empty(),
            "{good:?}"
        );
        let dark = pair(dir.path(), 15, 10);
        assert!(dark.fatal().is_some(), "{dark:?}");
        let dim = pair(dir.path(), 50, 10);
        assert!(dim.fatal().is_none() && dim.advice().len() == 1, "{dim:?}");
        let burnt = pair(dir.path(), 255, 100);
        assert!(burnt.advice().len() == 2, "{burnt:?}");
    }
}
