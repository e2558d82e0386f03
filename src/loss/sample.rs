//! Rays that follow the scene: each iteration traces a sample of a view's decoded pixels sized
//! so that its rays lie a given distance apart at the object, whatever the camera's pixel count
//! (docs/decisions.md#rays-that-follow-the-scene).
//!
//! The sample is systematic: for a share p of n pixels, step σ = 1/p and an offset o drawn
//! uniformly from [0, σ), pixel j is taken when some i has ⌊o + i·σ⌋ = j. The points o + i·σ lie
//! σ ≥ 1 apart, so at most one falls in [j, j + 1), with probability exactly 1/σ = p: every
//! pixel is drawn with the same probability, and weighting each drawn pixel by 1/p makes the
//! sample's sums of losses, weights and gradients unbiased estimates of the whole view's.
//! The pixels are in scan order, so the sample is also spread evenly over the image.

use nalgebra::Point3;

use super::refraction::ViewTargets;

/// The share of a view's pixels that puts rays `spacing_mm` apart at the object when its
/// pixels lie `pixel_mm` apart there: (pixel / spacing)², at most 1 (all pixels, when the
/// pixels are coarser than the spacing). 1 when either length is not a positive number.
pub fn pixel_share(pixel_mm: f64, spacing_mm: f64) -> f64 {
    let share = (pixel_mm / spacing_mm).powi(2);
    if share.is_finite() && share > 0.0 {
        share.min(1.0)
    } else {
        1.0
    }
}

/// The indices of a systematic sample of share `share` (in (0, 1]) of `n` items from the
/// offset `u` ∈ [0, 1) (a share of the step).
pub fn systematic(n: usize, share: f64, u: f64) -> impl Iterator<Item = usize> {
    let step = 1.0 / share.clamp(f64::MIN_POSITIVE, 1.0);
    let start = u.clamp(0.0, 1.0) * step;
    (0..)
        .map(move |i| (start + i as f64 * step).floor())
        .take_while(move |&x| x < n as f64)
        .map(|x| x as usize)
}

impl ViewTargets {
    /// This view's share of pixels that puts its rays `spacing_mm` apart at `centre` (world
    /// frame, mm; all pixels for views without pixel axes, such as imported rays).
    pub fn share_for_spacing(&self, centre: &Point3<f64>, spacing_mm: f64) -> f64 {
        self.pixel_mm_at(centre)
            .map_or(1.0, |p| pixel_share(p, spacing_mm))
    }

    /// A systematic sample of share `share` of this view's pixels from offset `u` ∈ [0, 1),
    /// each weight divided by the share (unbiased sums; [`systematic`]).
    pub fn sampled(&self, share: f64, u: f64) -> ViewTargets {
        let share = share.clamp(f64::MIN_POSITIVE, 1.0);
        let pixels = if share >= 1.0 {
            self.pixels.clone()
        } else {
            systematic(self.pixels.len(), share, u)
                .map(|j| {
                    let mut px = self.pixels[j];
                    px.weight /= share;
                    px
                })
                .collect()
        };
        ViewTargets {
            pixels,
            ..self.clone_empty()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_item_is_drawn_with_the_share_as_its_probability() {
        // Over a fine uniform grid of offsets, each index's frequency is the share.
        let (n, share, offsets) = (37, 0.3, 10_000);
        let mut counts = vec![0usize; n];
        for k in 0..offsets {
            for j in systematic(n, share, (k as f64 + 0.5) / offsets as f64) {
                counts[j] += 1;
            }
        }
        for (j, &c) in counts.iter().enumerate() {
            let freq = c as f64 / offsets as f64;
            assert!((freq - share).abs() < 1e-3, "index {j}: drawn {freq}");
        }
    }

    #[test]
    fn the_share_follows_the_spacing_and_never_exceeds_all_pixels() {
        assert!((pixel_share(0.5, 1.0) - 0.25).abs() < 1e-12);
        assert_eq!(pixel_share(2.0, 1.0), 1.0);
        assert_eq!(pixel_share(f64::NAN, 1.0), 1.0);
        assert_eq!(
            systematic(10, 1.0, 0.7).collect::<Vec<_>>(),
            (0..10).collect::<Vec<_>>()
        );
        assert_eq!(systematic(0, 0.5, 0.2).count(), 0);
    }
}
