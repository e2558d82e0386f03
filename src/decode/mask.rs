//! The silhouette of the object in one view, from its decoded captures and a background
//! reference, cleaned with OpenCV.
//!
//! A pixel is "object" when (rules, each with its threshold in [`MaskOptions`]):
//! 1. its decoded monitor point differs from the background's by more than `shift_px` monitor
//!    pixels beyond the two cells' half widths (light bent by the glass);
//! 2. it decodes to nothing (no reliable bit on an axis, or unlit by OpenCV's shadow test) where
//!    the background decodes (light lost: total internal reflection, missed monitor);
//! 3. its white-image intensity is below `1 − white_drop` of the background's (absorption and
//!    Fresnel losses; only with a captured background). Every path through the object loses at
//!    least what two interfaces reflect at normal incidence (Fresnel transmittance is highest
//!    there), so by default `white_drop` is half that loss for the scan's refractive index, or
//!    five times the white ratio's noise in this view if that is larger ([`auto_white_drop`]).
//!    This catches rays that cross the glass nearly undeflected, which rule 1 cannot see.
//!
//! Then the edge is made sub-pixel honest ([`trim_mixed_edge`]): an undecoded edge pixel (a
//! mixture of what the object and the background show) is object only if it is more than half
//! covered, judged from how much of the background's fine code it still shows
//! ([`super::coherence`]), or from its white ratio where the background has no reliable fine
//! bits there. Last, small connected object regions (specks) are dropped and small or thin holes
//! (or, with a captured background, holes showing glass: [`shows_glass`]) filled with
//! [`MASK_FILLED`], which the hull counts as object and the losses as background. "Small" and
//! "thin" are shares of the image ([`MaskOptions`]), so that a scene framed alike cleans alike
//! at any camera resolution.
//!
//! Without a captured background, the background point is predicted from the calibrated screen
//! pose (the camera ray of each pixel meets the monitor plane), and rule 3 and the edge trim are
//! not used.

use anyhow::Result;
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, CV_32S};

use super::graycode::PixelDecode;
use crate::scan::decoded::{is_object, MASK_FILLED, MASK_OBJECT};
use crate::scan::outline::encode_coverage;

/// Thresholds of the silhouette rules. The cleaning sizes are shares of the image, so that a
/// scene framed alike cleans alike at any camera resolution.
#[derive(Clone, Copy, Debug)]
pub struct MaskOptions {
    /// Rule 1's threshold, monitor pixels.
    pub shift_px: f32,
    /// Rule 3's threshold; `None`: [`auto_white_drop`].
    pub white_drop: Option<f32>,
    /// Object regions smaller than this share of the image's area are dropped.
    pub min_component: f64,
    /// Holes smaller than this share of the image's area are filled.
    pub max_hole: f64,
    /// The object has flat faces through which the background's code shows barely shifted (a
    /// block, a slab): the outline's pixels are judged by their coverage after the share of the
    /// code the glass beside them shows is taken out
    /// ([`super::coherence::shares_beside_flat_glass`]).
    pub flat_faces: bool,
}

impl Default for MaskOptions {
    /// 1.6e-4 of the image: 49 pixels of a 640 × 480 image, 802 of a 2448 × 2048 one.
    fn default() -> Self {
        Self {
            shift_px: 2.0,
            white_drop: None,
            min_component: 1.6e-4,
            max_hole: 1.6e-4,
            flat_faces: false,
        }
    }
}

/// A hole at most this share of the image's size (the square root of its area) wide on average
/// is filled: the line where a ray through a lens-like part's centre decodes like the
/// background (2 pixels of a 640 × 480 image).
const THIN_HOLE_WIDTH: f64 = 0.00361;

/// What the background shows at a pixel.
#[derive(Clone, Copy, Debug)]
pub struct BackgroundPixel {
    /// Decoded (or predicted) monitor point and cell sizes; `None` where the monitor is not seen.
    pub point: Option<(f32, f32, f32, f32)>,
    /// White-image intensity, if a background was captured.
    pub white: Option<u8>,
}

/// A background white level below this (grey levels) gives no usable ratio.
const MIN_BACKGROUND_WHITE: u8 = 20;

impl BackgroundPixel {
    /// A pixel's white-image intensity `white` over this background's, where the background was
    /// captured bright enough.
    fn white_ratio(&self, white: u8) -> Option<f32> {
        self.white
            .filter(|&bw| bw >= MIN_BACKGROUND_WHITE)
            .map(|bw| white as f32 / bw as f32)
    }
}

/// What one pixel tells about the object, before thresholding the white ratio.
#[derive(Clone, Copy, Debug)]
struct Evidence {
    /// Something decoded (a reliable bit on both axes, lit).
    decoded: bool,
    /// Rules 1 or 2: the decoded point moved, or the light was lost.
    bent_or_lost: bool,
    /// How far the decoded point lies from the background's, over rule 1's threshold (the larger
    /// axis; > 1 where rule 1 holds); NaN where nothing decoded or the background shows no
    /// monitor.
    shift: f32,
    /// White intensity over the background's, where the background was captured bright enough.
    ratio: Option<f32>,
}

fn evidence(
    d: &PixelDecode,
    lit: bool,
    white: u8,
    bg: &BackgroundPixel,
    o: &MaskOptions,
) -> Evidence {
    let decoded = lit && d.u.bits > 0 && d.v.bits > 0;
    let over = |coord: f32, b: f32, cell: u32, cb: f32| {
        (coord - b).abs() / (o.shift_px + (cell as f32 + cb) / 2.0)
    };
    let shift = match (decoded, bg.point) {
        (true, Some((bu, bv, cu, cv))) => {
            over(d.u.coord, bu, d.u.cell, cu).max(over(d.v.coord, bv, d.v.cell, cv))
        }
        _ => f32::NAN,
    };
    let bent_or_lost = shift > 1.0 || (!decoded && bg.point.is_some());
    let ratio = bg.white_ratio(white);
    Evidence {
        decoded,
        bent_or_lost,
        shift,
        ratio,
    }
}

/// Rule 3's default threshold: half the share of light two air–glass interfaces reflect at normal
/// incidence for refractive index `ior` ([`normal_incidence_loss`]), or five times `noise` (the
/// robust standard deviation of the white ratio on background pixels) if that is larger.
pub fn auto_white_drop(ior: f64, noise: f32) -> f32 {
    (0.5 * normal_incidence_loss(ior)).max(5.0 * noise)
}

/// The share of light two air–glass interfaces of refractive index `ior` reflect at normal
/// incidence, where Fresnel transmittance is highest (R = ((n − 1)/(n + 1))², loss
/// 1 − (1 − R)²; 7.1 % for n = 1.4723).
fn normal_incidence_loss(ior: f64) -> f32 {
    let r = ((ior - 1.0) / (ior + 1.0)).powi(2);
    (1.0 - (1.0 - r) * (1.0 - r)) as f32
}

/// The object pixels whose decoded point is no refracted path's (`true`), with a captured
/// background: those whose white image shows less than `min_light` of the most light a path
/// through the object passes, what two air–glass interfaces of index `ior` transmit at normal
/// incidence (1 − [`normal_incidence_loss`]), relative to the background's white. Where the
/// light split on its way (total internal reflection, a ghost, a path that misses the monitor)
/// the code still decodes, to a point no refracted path reaches. `None` without a captured
/// background or with `min_light` 0.
pub fn dim_points(
    mask: &[u8],
    white: &[u8],
    background: &[BackgroundPixel],
    ior: f64,
    min_light: f32,
) -> Option<Vec<bool>> {
    let captured = background.iter().any(|b| b.white.is_some());
    if !captured || min_light <= 0.0 {
        return None;
    }
    let least = min_light * (1.0 - normal_incidence_loss(ior));
    let dim = mask
        .iter()
        .zip(white)
        .zip(background)
        .map(|((&m, &w), bg)| is_object(m) && bg.white_ratio(w).is_some_and(|r| r < least));
    Some(dim.collect())
}

/// The white ratio over the pixels rules 1 and 2 call background: its median and robust
/// standard deviation (1.4826 × median absolute deviation); `None` with fewer than 100 such
/// pixels (or without a captured background).
fn background_ratio(ev: &[Evidence]) -> Option<(f32, f32)> {
    let mut r: Vec<f32> = ev
        .iter()
        .filter(|e| e.decoded && !e.bent_or_lost)
        .filter_map(|e| e.ratio)
        .collect();
    if r.len() < 100 {
        return None;
    }
    let median = median_of(&mut r);
    let mut dev: Vec<f32> = r.iter().map(|x| (x - median).abs()).collect();
    Some((median, 1.4826 * median_of(&mut dev)))
}

/// The median of a non-empty `values` (the upper one of an even count), reordering them.
fn median_of(values: &mut [f32]) -> f32 {
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// What a view's captures tell about its holes, with a captured background: each pixel's white
/// ratio (NaN where the background was too dark for one) and decoded point's shift
/// ([`Evidence::shift`]), the background's median ratio, and [`normal_incidence_loss`] for the
/// scan's index.
pub struct HoleEvidence {
    pub ratio: Vec<f32>,
    pub shift: Vec<f32>,
    pub background: f32,
    pub loss: f32,
}

/// The pixels with a white ratio (away from the rim) or a shift [`clean`] needs to judge a hole
/// by either.
const MIN_HOLE_SAMPLES: usize = 10;

/// A hole whose pixels' median shift ([`Evidence::shift`]) exceeds this shows glass (measured:
/// true holes 0.00–0.14, bands of glass 0.72–0.80).
const GLASS_MEDIAN_SHIFT: f32 = 0.35;

/// What a view's captures show per pixel (row-major), for its silhouette.
pub struct ViewPixels<'a> {
    pub width: usize,
    pub decoded: &'a [PixelDecode],
    /// OpenCV's shadow test passed (white − black above the black threshold).
    pub lit: &'a [bool],
    pub white: &'a [u8],
    /// The share of the background's fine code each pixel shows
    /// ([`super::coherence::background_share`]), with a captured background.
    pub background_share: Option<&'a [f32]>,
}

/// A view's raw silhouette (rules 1–3 and the edge trim, before clean-up): 255 for object
/// pixels, and with a captured background what its white image shows (for [`clean`]).
pub struct RawMask {
    pub mask: Vec<u8>,
    /// Rule 3's threshold (`None` without a captured background).
    pub white_drop: Option<f32>,
    pub holes: Option<HoleEvidence>,
}

/// The raw silhouette of a view. `ior`: the object's refractive index (for [`auto_white_drop`]).
pub fn raw_mask(
    view: &ViewPixels,
    background: &[BackgroundPixel],
    ior: f64,
    o: &MaskOptions,
) -> RawMask {
    let ViewPixels {
        width,
        decoded,
        lit,
        white,
        background_share,
    } = *view;
    let ev: Vec<Evidence> = decoded
        .iter()
        .zip(lit)
        .zip(white)
        .zip(background)
        .map(|(((d, &lit), &w), bg)| evidence(d, lit, w, bg, o))
        .collect();
    let captured = background.iter().any(|b| b.white.is_some());
    let stats = background_ratio(&ev);
    let drop = captured.then(|| {
        o.white_drop
            .unwrap_or_else(|| auto_white_drop(ior, stats.map_or(0.0, |(_, noise)| noise)))
    });
    let mut mask: Vec<u8> = ev
        .iter()
        .map(|e| {
            let darker = drop.is_some_and(|t| e.ratio.is_some_and(|r| r < 1.0 - t));
            if e.bent_or_lost || darker {
                255
            } else {
                0
            }
        })
        .collect();
    if captured {
        trim_mixed_edge(&mut mask, &ev, width, background_share);
    }
    let holes = stats
        .filter(|_| captured)
        .map(|(background, _)| HoleEvidence {
            ratio: ev.iter().map(|e| e.ratio.unwrap_or(f32::NAN)).collect(),
            shift: ev.iter().map(|e| e.shift).collect(),
            background,
            loss: normal_incidence_loss(ior),
        });
    RawMask {
        mask,
        white_drop: drop,
        holes,
    }
}

/// Rule 1: decoded, to a point away from the background's.
fn clearly_bent(e: &Evidence) -> bool {
    e.decoded && e.bent_or_lost
}

/// Passes of [`trim_mixed_edge`]: enough for a blur of about a pixel.
const TRIM_PASSES: usize = 2;

/// Removes edge pixels that are less than half object. An object pixel with a background
/// 4-neighbour that is object only by rules 2 or 3 (it decodes to nothing, or to the background's
/// point but darker) mixes the object's light and the background's. Its centre lies outside the
/// object (coverage c < ½) when it shows more than half of the background's fine code
/// (`background_share`, see [`super::coherence`]). Where that share is unknown, the white ratio
/// decides: it is about c·r_in + (1 − c), r_in the object's own (the smallest ratio among the
/// object pixels within two pixels), so c < ½ when the ratio exceeds (1 + r_in)/2 — a rule that
/// trims too much where the glass near the outline is brighter than r_in (light reflected at
/// grazing incidence:
/// docs/decisions.md#grazing-rays-dropped-and-the-outline-placed-by-coverage).
/// Pixels whose decoded point moved (rule 1) are never
/// trimmed.
fn trim_mixed_edge(
    mask: &mut [u8],
    ev: &[Evidence],
    width: usize,
    background_share: Option<&[f32]>,
) {
    let height = mask.len() / width;
    for _ in 0..TRIM_PASSES {
        let is_edge = |m: &[u8], i: usize| any_4_neighbour(i, width, height, |j| m[j] == 0);
        let inner_ratio = |m: &[u8], i: usize| {
            let (x, y) = (i % width, i / width);
            let mut lowest: Option<f32> = None;
            for yy in y.saturating_sub(2)..(y + 3).min(height) {
                for xx in x.saturating_sub(2)..(x + 3).min(width) {
                    let j = yy * width + xx;
                    if m[j] == 255 {
                        if let Some(r) = ev[j].ratio {
                            lowest = Some(lowest.map_or(r, |l: f32| l.min(r)));
                        }
                    }
                }
            }
            lowest
        };
        let trim: Vec<usize> = (0..mask.len())
            .filter(|&i| mask[i] == 255 && !clearly_bent(&ev[i]) && is_edge(mask, i))
            .filter(|&i| {
                if let Some(share) = background_share.map(|s| s[i]).filter(|s| !s.is_nan()) {
                    return share > 0.5;
                }
                let (Some(r), Some(r_in)) = (ev[i].ratio, inner_ratio(mask, i)) else {
                    return false;
                };
                r > 0.5 * (1.0 + r_in)
            })
            .collect();
        if trim.is_empty() {
            break;
        }
        for i in trim {
            mask[i] = 0;
        }
    }
}

/// Object pixels (255 in `mask`) next to a pixel where the background shows no monitor (nothing
/// decoded there, and dark if a background was captured): there the silhouette reaches the edge
/// of the monitor's image, and whatever of the object lies beyond it shows nothing the decoder
/// could tell from the background, so it is cut off the silhouette.
pub fn pixels_at_monitor_edge(mask: &[u8], background: &[BackgroundPixel], width: usize) -> usize {
    let unseen = |j: usize| {
        let b = &background[j];
        b.point.is_none() && b.white.is_none_or(|w| w < MIN_BACKGROUND_WHITE)
    };
    let height = mask.len() / width.max(1);
    (0..mask.len())
        .filter(|&i| mask[i] == 255)
        .filter(|&i| any_4_neighbour(i, width, height, unseen))
        .count()
}

/// The outline coverage of a cleaned `mask` (the decoded form's `view_NNN_coverage.png`): for
/// each pixel on the outline (an object pixel with a 4-neighbour that is not, or the reverse;
/// filled holes count as background) where `background_share` is known, the share of it the
/// object covers, 1 − share, kept on the pixel's side of ½ and stored as 1..=254 (c·255);
/// elsewhere 255 for object and 0 for other pixels.
pub fn outline_coverage(mask: &[u8], background_share: &[f32], width: usize) -> Vec<u8> {
    let height = mask.len() / width.max(1);
    let object = |i: usize| is_object(mask[i]);
    (0..mask.len())
        .map(|i| {
            let side = object(i);
            let on_outline = any_4_neighbour(i, width, height, |j| object(j) != side);
            let share = background_share[i];
            if !on_outline || share.is_nan() {
                return if side { 255 } else { 0 };
            }
            encode_coverage(1.0 - share, side)
        })
        .collect()
}

/// Whether pixel `i` of a `width` × `height` image (row-major) has a 4-neighbour `j` with
/// `pred(j)`.
fn any_4_neighbour(i: usize, width: usize, height: usize, pred: impl Fn(usize) -> bool) -> bool {
    let (x, y) = (i % width, i / width);
    (x > 0 && pred(i - 1))
        || (x + 1 < width && pred(i + 1))
        || (y > 0 && pred(i - width))
        || (y + 1 < height && pred(i + width))
}

/// Drops small object regions (to 0) and marks as [`MASK_FILLED`] the holes that are small,
/// thin ([`THIN_HOLE_WIDTH`]) or, with a captured background's `evidence`, showing glass the
/// rays cross nearly undeflected ([`shows_glass`]), in place; 8-connected regions, sizes
/// relative to the image ([`MaskOptions`]); a background region touching the image border is
/// no hole.
pub fn clean(
    mask: &mut [u8],
    width: i32,
    height: i32,
    o: &MaskOptions,
    evidence: Option<&HoleEvidence>,
) -> Result<()> {
    let image = width as f64 * height as f64;
    let smaller_than = |share: f64, r: &Region| (r.area as f64) < share * image;
    let specks = Regions::of(mask, width, height, MASK_OBJECT)?;
    let chosen: Vec<bool> = (specks.stats.iter())
        .map(|r| smaller_than(o.min_component, r))
        .collect();
    specks.relabel(mask, &chosen, 0);
    let holes = Regions::of(mask, width, height, 0)?;
    let thin =
        |r: &Region| r.area as f64 <= THIN_HOLE_WIDTH * image.sqrt() * r.width.max(r.height) as f64;
    let mut chosen: Vec<bool> = (holes.stats.iter())
        .map(|r| !r.border && (smaller_than(o.max_hole, r) || thin(r)))
        .collect();
    if let Some(e) = evidence {
        // Only the holes the sizes left open are judged by what they show.
        let open: Vec<bool> = (holes.stats.iter().zip(&chosen))
            .map(|(r, &c)| !r.border && !c)
            .collect();
        let glass = holes.showing_glass(mask, width as usize, e, &open);
        for (c, g) in chosen.iter_mut().zip(glass) {
            *c |= g;
        }
    }
    holes.relabel(mask, &chosen, MASK_FILLED);
    Ok(())
}

/// The 8-connected regions of one value in a mask.
struct Regions {
    /// Each pixel's region; 0 for pixels of other values.
    labels: Vec<i32>,
    /// Per region (index = label; label 0 is the other pixels and never chosen).
    stats: Vec<Region>,
}

/// A region's size in pixels and whether it touches the image border.
struct Region {
    area: i32,
    width: i32,
    height: i32,
    border: bool,
}

impl Regions {
    /// The regions of value `value` in `mask` (`width` × `height`, row-major).
    fn of(mask: &[u8], width: i32, height: i32, value: u8) -> Result<Self> {
        let sel: Vec<u8> = mask
            .iter()
            .map(|&m| if m == value { 255 } else { 0 })
            .collect();
        let img = Mat::new_rows_cols_with_data(height, width, &sel)?;
        let (mut labels, mut stats, mut centroids) =
            (Mat::default(), Mat::default(), Mat::default());
        let n = opencv::imgproc::connected_components_with_stats(
            &img,
            &mut labels,
            &mut stats,
            &mut centroids,
            8,
            CV_32S,
        )?;
        use opencv::imgproc::{
            CC_STAT_AREA, CC_STAT_HEIGHT, CC_STAT_LEFT, CC_STAT_TOP, CC_STAT_WIDTH,
        };
        let stats = (0..n)
            .map(|l| -> Result<Region> {
                let st = |k| stats.at_2d::<i32>(l, k).copied();
                let (x, y, w, h) = (
                    st(CC_STAT_LEFT)?,
                    st(CC_STAT_TOP)?,
                    st(CC_STAT_WIDTH)?,
                    st(CC_STAT_HEIGHT)?,
                );
                Ok(Region {
                    area: st(CC_STAT_AREA)?,
                    width: w,
                    height: h,
                    border: x == 0 || y == 0 || x + w == width || y + h == height,
                })
            })
            .collect::<Result<_>>()?;
        let labels = labels.data_typed::<i32>()?.to_vec();
        Ok(Self { labels, stats })
    }

    /// Sets the pixels of the `chosen` regions (by label; label 0 never) to `to`.
    fn relabel(&self, mask: &mut [u8], chosen: &[bool], to: u8) {
        for (m, &l) in mask.iter_mut().zip(&self.labels) {
            if l > 0 && chosen[l as usize] {
                *m = to;
            }
        }
    }

    /// Per region: whether it shows glass ([`shows_glass`]), judged for the regions `judged`
    /// (by label; false for the others) from its pixels' shifts and from the white ratios of
    /// those with no object 4-neighbour in `mask` (a rim pixel may mix the object's light in).
    fn showing_glass(
        &self,
        mask: &[u8],
        width: usize,
        evidence: &HoleEvidence,
        judged: &[bool],
    ) -> Vec<bool> {
        let height = mask.len() / width.max(1);
        let mut ratios: Vec<Vec<f32>> = vec![Vec::new(); self.stats.len()];
        let mut shifts: Vec<Vec<f32>> = vec![Vec::new(); self.stats.len()];
        for (i, &l) in self.labels.iter().enumerate() {
            if l == 0 || !judged[l as usize] {
                continue;
            }
            let (r, shift) = (evidence.ratio[i], evidence.shift[i]);
            if !shift.is_nan() {
                shifts[l as usize].push(shift);
            }
            if !r.is_nan() && !any_4_neighbour(i, width, height, |j| mask[j] != 0) {
                ratios[l as usize].push(r);
            }
        }
        (ratios.iter_mut().zip(&mut shifts))
            .map(|(r, s)| shows_glass(r, s, evidence))
            .collect()
    }
}

/// A hole shows glass — rays that cross it nearly undeflected, so that rule 1 cannot see them,
/// and not dark enough for rule 3 pixel by pixel (light the glass reflects inside adds to
/// theirs) — when (with at least [`MIN_HOLE_SAMPLES`] values) either
/// - even the brightest tenth of its `ratios` lies below the background's median ratio by more
///   than a quarter of [`normal_incidence_loss`]: air passes the monitor's light whole, so a
///   true hole's brightest pixels match the background, even where the blur darkens the rest
///   of it next to its rim; or
/// - the median of its `shifts` exceeds [`GLASS_MEDIAN_SHIFT`]: through air the decoded points
///   are the background's, while across a band of glass they move from one side's bend to the
///   other's (and decode to coarser cells).
///
/// docs/decisions.md#holes-in-a-silhouette-that-show-glass gives the measurements.
fn shows_glass(ratios: &mut [f32], shifts: &mut [f32], evidence: &HoleEvidence) -> bool {
    let dark = ratios.len() >= MIN_HOLE_SAMPLES && {
        let bright = ratios.len() * 9 / 10;
        let p90 = *ratios.select_nth_unstable_by(bright, f32::total_cmp).1;
        p90 < evidence.background - 0.25 * evidence.loss
    };
    let moved = shifts.len() >= MIN_HOLE_SAMPLES && median_of(shifts) > GLASS_MEDIAN_SHIFT;
    dark || moved
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn object_points_with_too_little_light_are_marked_and_nothing_else_is() {
        // Index 1.5: two interfaces pass at most 92.2 % of the light; 0.8 of that is 73.7 %.
        let bg = |white| BackgroundPixel {
            point: Some((0.0, 0.0, 1.0, 1.0)),
            white,
        };
        let mask = [
            MASK_OBJECT,
            MASK_OBJECT,
            MASK_OBJECT,
            0,
            MASK_FILLED,
            MASK_OBJECT,
        ];
        let white = [200u8, 180, 120, 40, 40, 15];
        let background = [
            bg(Some(240)), // 0.83: a refracted path's light
            bg(Some(240)), // 0.75: still above
            bg(Some(240)), // 0.50: the light split
            bg(Some(240)), // background pixel: never marked
            bg(Some(240)), // a filled hole counts as background here
            bg(Some(10)),  // the background too dark to judge
        ];
        let dim = dim_points(&mask, &white, &background, 1.5, 0.8).unwrap();
        assert_eq!(dim, [false, false, true, false, false, false]);
        let stricter = dim_points(&mask, &white, &background, 1.5, 0.9).unwrap();
        assert_eq!(stricter, [false, true, true, false, false, false]);
        assert_eq!(dim_points(&mask, &white, &background, 1.5, 0.0), None);
        let predicted = background.map(|b| BackgroundPixel { white: None, ..b });
        assert_eq!(dim_points(&mask, &white, &predicted, 1.5, 0.8), None);
    }

    /// The same scene at two camera resolutions cleans alike. In a 640 × 480 image an object 125
    /// pixels across with holes 6 × 6 (filled: under 49 pixels), 10 × 10 (kept), a line 2 wide
    /// (filled: thin) and one 4 wide (kept), each 100 tall; beside it a 5 × 5 speck (dropped)
    /// and a 10 × 10 part (kept). At 1280 × 960 every length doubles.
    #[test]
    fn cleaning_fills_small_and_thin_holes_and_drops_specks_at_any_resolution() {
        for scale in [1usize, 2] {
            let s = |v: usize| v * scale;
            let (w, h) = (s(640), s(480));
            let square = |x0: usize, y0: usize, side: usize| {
                move |x: usize, y: usize| {
                    (s(x0)..s(x0 + side)).contains(&x) && (s(y0)..s(y0 + side)).contains(&y)
                }
            };
            let line = |x0: usize, wide: usize| {
                move |x: usize, y: usize| {
                    (s(x0)..s(x0 + wide)).contains(&x) && (s(20)..s(120)).contains(&y)
                }
            };
            let (object, small, large) =
                (square(10, 10, 125), square(20, 20, 6), square(40, 40, 10));
            let (thin, wide) = (line(70, 2), line(90, 4));
            let (speck, part) = (square(145, 20, 5), square(140, 60, 10));
            let mut mask = vec![0u8; w * h];
            for (i, m) in mask.iter_mut().enumerate() {
                let (x, y) = (i % w, i / w);
                let hole = small(x, y) || large(x, y) || thin(x, y) || wide(x, y);
                if (object(x, y) && !hole) || speck(x, y) || part(x, y) {
                    *m = MASK_OBJECT;
                }
            }
            let before = mask.clone();
            clean(&mut mask, w as i32, h as i32, &MaskOptions::default(), None).unwrap();
            for (i, (&b, &a)) in before.iter().zip(&mask).enumerate() {
                let (x, y) = (i % w, i / w);
                let expected = if small(x, y) || thin(x, y) {
                    MASK_FILLED
                } else if speck(x, y) {
                    0
                } else {
                    b
                };
                assert_eq!(a, expected, "scale {scale}: pixel ({x}, {y})");
            }
        }
    }

    /// Three holes of 4 × 20 pixels in an object: one shows the background through air (its rim
    /// columns darkened by the blur, its middle ones as bright as the background, its decoded
    /// points the background's within a fifth of rule 1's threshold); one glass 5 % darker
    /// throughout (rule 3 needing 5.2 % at 1.60) whose points barely moved; one glass as bright
    /// as the air whose points moved by 0.7 of rule 1's threshold.
    #[test]
    fn a_hole_that_shows_glass_is_filled_and_one_of_air_is_kept() {
        let (w, h) = (70usize, 40usize);
        let at = |x: usize, y: usize| y * w + x;
        let mut mask = vec![0u8; w * h];
        let (mut ratio, mut shift) = (vec![1.0f32; w * h], vec![0.0f32; w * h]);
        for y in 5..35 {
            for x in 5..65 {
                mask[at(x, y)] = MASK_OBJECT;
                (ratio[at(x, y)], shift[at(x, y)]) = (0.9, 3.0);
            }
        }
        let (air, dark, moved) = (15..19, 30..34, 45..49);
        for y in 10..30 {
            for (k, x) in air.clone().enumerate() {
                mask[at(x, y)] = 0;
                ratio[at(x, y)] = [0.90, 0.97, 0.995, 0.90][k];
                shift[at(x, y)] = if (x + y) % 3 == 0 { 0.2 } else { 0.0 };
            }
            for x in dark.clone() {
                mask[at(x, y)] = 0;
                ratio[at(x, y)] = if (x + y) % 2 == 0 { 0.95 } else { 0.96 };
                shift[at(x, y)] = 0.1;
            }
            for x in moved.clone() {
                mask[at(x, y)] = 0;
                ratio[at(x, y)] = 0.995;
                shift[at(x, y)] = 0.7;
            }
        }
        let holes = HoleEvidence {
            ratio,
            shift,
            background: 1.0,
            loss: normal_incidence_loss(1.6),
        };
        let o = MaskOptions::default();
        let mut without = mask.clone();
        clean(&mut without, w as i32, h as i32, &o, None).unwrap();
        clean(&mut mask, w as i32, h as i32, &o, Some(&holes)).unwrap();
        for y in 10..30 {
            for x in air.clone().chain(dark.clone()).chain(moved.clone()) {
                assert_eq!(
                    without[at(x, y)],
                    0,
                    "pixel ({x}, {y}) without the evidence"
                );
                let expected = if air.contains(&x) { 0 } else { MASK_FILLED };
                assert_eq!(mask[at(x, y)], expected, "pixel ({x}, {y})");
            }
        }
    }
}
