//! The decoded form of a scan on disk (`SCAN/decoded/`, documented in the README), written by
//! `glasscan decode` and by `glasscan simulate --decoded-only`, read by `hull` and the losses.
//!
//! - `view_NNN_mask.png`: 8-bit, 255 ([`MASK_OBJECT`]) for object pixels, 128 ([`MASK_FILLED`])
//!   for the pixels of a small or thin hole the decoder filled, 0 for the background (any other
//!   non-zero value counts as object);
//! - `view_NNN_monitor.png`: 16-bit, 4 channels: (u + 1)·s, (v + 1)·s of the decoded monitor
//!   point (monitor pixels) and the cell widths along u and v (monitor pixels); 65535 where
//!   nothing decodes;
//! - `view_NNN_bits.png` (optional; written by `glasscan decode`): 16-bit, 4 channels: the
//!   measured contrasts (pattern − inverse)/(white − black) of the last reliable and the first
//!   unreliable Gray bit along u, then along v, as (c + 1)·32767; 65535 where a bit is absent;
//! - `view_NNN_coverage.png` (optional; written by `glasscan decode` with a captured
//!   background): 8-bit, for the pixels on the outline the share c of the pixel the object
//!   covers, as 1..=254 (c·255); 255 and 0 elsewhere (object, background: not measured). The
//!   silhouette places its outline within those pixels ([`super::outline`]);
//! - `view_NNN_rays.bin` (imported scans, instead of the monitor image): per object pixel its
//!   camera ray and its 3D target, camera frame (see [`write_rays`]);
//! - `summary.json`: `fixed_point_scale` s and per-view figures, with the warning of any view that
//!   could not be decoded (such a view has no mask).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use nalgebra::{Point3, Vector3};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Vec4w};

use super::MAX_BLUR_PX;
use crate::util::fixed::{FixedPoint, NONE};
use crate::util::image::{png_size, read_image, write_pixels};
use serde::{Deserialize, Serialize};

/// Mask value of an object pixel.
pub const MASK_OBJECT: u8 = 255;

/// Mask value of a pixel in a hole the decoder's cleaning filled: the background decoded there,
/// but the hole is too small or thin to trust. The visual hull counts it as object (carving it
/// would cut glass away if the hole was a decoding gap); the silhouette term and the refraction
/// term count it as background, since a hole inside the object has no contour edge near it and
/// a gap between two parts of the object is what it shows.
pub const MASK_FILLED: u8 = 128;

/// Whether mask value `m` marks an object pixel (not a filled hole, not the background).
pub fn is_object(m: u8) -> bool {
    m != 0 && m != MASK_FILLED
}

/// Per-view figures of a decode.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewSummary {
    pub view: usize,
    pub object_pixels: usize,
    /// Share of the object pixels with a decoded monitor point.
    pub decoded_share: f64,
    /// Share of those whose every bit is reliable.
    pub complete_share: f64,
    /// Share of the object pixels whose point was dropped for too little light (`decode`'s
    /// `min_light`), where a background was captured and the rule was on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dim_share: Option<f64>,
    /// Mask rule 3's threshold used (relative white drop), where a background was captured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub white_drop: Option<f64>,
    /// Object pixels next to pixels where the background shows no monitor: the object reaches
    /// the edge of the monitor's image there; 0 where the monitor covers the object.
    #[serde(default)]
    pub monitor_edge_px: usize,
    pub warning: Option<String>,
    /// How much of the object's inside shows the monitor barely shifted, where a background was
    /// captured (`decode`'s flat-faces hint).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flat_glass: Option<FlatGlass>,
}

/// Interior object pixels (object with four object neighbours) whose share of the background's
/// fine code is known, and those of them that show at least the flat-glass share of it: through
/// flat, nearly parallel faces the monitor is seen barely shifted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FlatGlass {
    pub interior: usize,
    pub flat: usize,
}

/// The decoded monitor point of one camera pixel: coordinates and cell widths, monitor pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MonitorTarget {
    pub u: f64,
    pub v: f64,
    pub cell_u: f64,
    pub cell_v: f64,
}

/// One decoded view: row-major per camera pixel.
#[derive(Clone, Debug)]
pub struct DecodedView {
    pub view: usize,
    pub width: u32,
    pub height: u32,
    /// Object pixels (the silhouette without the holes the decoder filled).
    pub mask: Vec<bool>,
    /// The decoded monitor point, where one decoded.
    pub targets: Vec<Option<MonitorTarget>>,
    /// Imported scans: per pixel a ray and a 3D target, in place of `targets` (all `None`).
    pub rays: Option<Vec<PixelRay>>,
    /// Per pixel the measured Gray-bit contrasts (`view_NNN_bits.png`, NaN where absent), if the
    /// decode wrote them.
    pub contrasts: Option<Vec<[f32; 4]>>,
}

/// A bit's contrast in [−1, 1] (clamped; NaN: absent) as stored in `view_NNN_bits.png`.
pub fn encode_contrast(c: f32) -> u16 {
    if c.is_nan() {
        NONE
    } else {
        ((c.clamp(-1.0, 1.0) + 1.0) * 32767.0).round() as u16
    }
}

/// The inverse of [`encode_contrast`].
pub fn decode_contrast(c: u16) -> f32 {
    if c == NONE {
        f32::NAN
    } else {
        c as f32 / 32767.0 - 1.0
    }
}

/// A camera pixel's ray and the 3D point it sees on the monitor, camera frame, mm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelRay {
    /// Row-major pixel index.
    pub pixel: u32,
    /// Unit direction.
    pub dir: Vector3<f64>,
    pub target: Point3<f64>,
}

/// Path of view `k`'s rays in the decoded folder `dir`.
pub fn rays_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("view_{k:03}_rays.bin"))
}

const RAYS_MAGIC: &[u8; 8] = b"GSRAYS01";

/// Writes view `k`'s rays: the 8 bytes `GSRAYS01`, the count (u64), then per ray the pixel index
/// (u32) and direction and target (3 + 3 f32), all little-endian.
pub fn write_rays(dir: &Path, k: usize, rays: &[PixelRay]) -> Result<()> {
    let mut bytes = Vec::with_capacity(16 + rays.len() * 28);
    bytes.extend_from_slice(RAYS_MAGIC);
    bytes.extend_from_slice(&(rays.len() as u64).to_le_bytes());
    for r in rays {
        bytes.extend_from_slice(&r.pixel.to_le_bytes());
        for v in r.dir.iter().chain(r.target.coords.iter()) {
            bytes.extend_from_slice(&(*v as f32).to_le_bytes());
        }
    }
    let path = rays_path(dir, k);
    crate::util::atomic::write_atomic(&path, |w| w.write_all(&bytes))
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Reads a rays file of a view with `pixels` pixels.
pub fn read_rays(path: &Path, pixels: usize) -> Result<Vec<PixelRay>> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let bad = || {
        anyhow::anyhow!(
            "{}: not a glasscan rays file (truncated or corrupt)",
            path.display()
        )
    };
    if bytes.len() < 16 || &bytes[..8] != RAYS_MAGIC {
        return Err(bad());
    }
    let n = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes"));
    if n.checked_mul(28).and_then(|b| b.checked_add(16)) != Some(bytes.len() as u64) {
        return Err(bad());
    }
    let f = |b: &[u8]| f32::from_le_bytes(b.try_into().expect("4 bytes")) as f64;
    bytes[16..]
        .chunks_exact(28)
        .map(|c| {
            let pixel = u32::from_le_bytes(c[..4].try_into().expect("4 bytes"));
            let v: Vec<f64> = c[4..].chunks_exact(4).map(f).collect();
            if pixel as usize >= pixels || v.iter().any(|x| !x.is_finite()) {
                return Err(bad());
            }
            Ok(PixelRay {
                pixel,
                dir: Vector3::new(v[0], v[1], v[2]),
                target: Point3::new(v[3], v[4], v[5]),
            })
        })
        .collect()
}

/// Path of view `k`'s mask in the decoded folder `dir`.
pub fn mask_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("view_{k:03}_mask.png"))
}

/// Path of view `k`'s monitor points in the decoded folder `dir`.
pub fn monitor_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("view_{k:03}_monitor.png"))
}

/// Path of view `k`'s measured bit contrasts in the decoded folder `dir`.
pub fn contrasts_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("view_{k:03}_bits.png"))
}

/// Path of view `k`'s outline coverage in the decoded folder `dir`.
pub fn coverage_path(dir: &Path, k: usize) -> PathBuf {
    dir.join(format!("view_{k:03}_coverage.png"))
}

/// What one view's decoded form holds besides its mask and monitor points (each optional).
#[derive(Clone, Copy, Default)]
pub struct ViewExtras<'a> {
    pub contrasts: Option<&'a [Vec4w]>,
    pub coverage: Option<&'a [u8]>,
}

/// Writes view `k`'s mask (0, [`MASK_FILLED`], [`MASK_OBJECT`]), monitor points, and its bit
/// contrasts and outline coverage if any (encoded as above), into `dir`.
pub fn write_view(
    dir: &Path,
    k: usize,
    (width, height): (u32, u32),
    mask: &[u8],
    monitor: &[Vec4w],
    extras: ViewExtras,
) -> Result<()> {
    write_pixels(&mask_path(dir, k), width, height, mask)?;
    write_pixels(&monitor_path(dir, k), width, height, monitor)?;
    if let Some(c) = extras.contrasts {
        write_pixels(&contrasts_path(dir, k), width, height, c)?;
    }
    if let Some(c) = extras.coverage {
        write_pixels(&coverage_path(dir, k), width, height, c)?;
    }
    Ok(())
}

/// Writes `summary.json`.
pub fn write_summary(
    dir: &Path,
    fixed: &FixedPoint,
    views: &[ViewSummary],
    blur: Option<&MeasuredBlur>,
) -> Result<()> {
    crate::util::atomic::write_atomic(&dir.join("summary.json"), |w| {
        serde_json::to_writer_pretty(
            &mut *w,
            &serde_json::json!({ "fixed_point_scale": fixed.scale, "views": views, "blur": blur }),
        )?;
        Ok(())
    })
    .with_context(|| format!("cannot write {}", dir.join("summary.json").display()))
}

/// The camera's blur as decode measured it on the background captures.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeasuredBlur {
    /// σ of the camera's Gaussian blur beyond the pixel's own area, camera pixels.
    pub sigma_px: f64,
    /// Stripe edges measured.
    pub edges: usize,
}

/// What `summary.json` holds.
#[derive(Clone, Debug)]
pub struct Summary {
    pub fixed: FixedPoint,
    pub views: Vec<ViewSummary>,
    /// Absent without background captures (or too few stripe edges in them).
    pub blur: Option<MeasuredBlur>,
}

/// Reads `dir/summary.json`.
pub fn read_summary(dir: &Path) -> Result<Summary> {
    let path = dir.join("summary.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    #[derive(serde::Deserialize)]
    struct Stored {
        fixed_point_scale: f64,
        views: Vec<ViewSummary>,
        #[serde(default)]
        blur: Option<MeasuredBlur>,
    }
    let s: Stored = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a decode summary", path.display()))?;
    if s.fixed_point_scale.is_nan() || s.fixed_point_scale <= 0.0 {
        bail!("{}: fixed_point_scale must be positive", path.display());
    }
    if let Some(b) = s
        .blur
        .filter(|b| !(0.0..=MAX_BLUR_PX).contains(&b.sigma_px))
    {
        bail!(
            "{}: blur.sigma_px = {}: a Gaussian's σ in camera pixels, 0 to {MAX_BLUR_PX}; decode the scan again",
            path.display(),
            b.sigma_px
        );
    }
    Ok(Summary {
        fixed: FixedPoint {
            scale: s.fixed_point_scale,
        },
        views: s.views,
        blur: s.blur,
    })
}

/// True when `name` is a file of view `k` in the decoded folder or its previews
/// (`view_NNN_….png`, `view_NNN.png`).
pub fn is_view_file(name: &str, k: usize) -> bool {
    name.strip_prefix(&format!("view_{k:03}"))
        .is_some_and(|rest| rest.starts_with('_') || rest.starts_with('.'))
}

/// The decoded folder of a scan, opened for reading.
#[derive(Clone, Debug)]
pub struct DecodedScan {
    pub dir: PathBuf,
    pub fixed: FixedPoint,
    /// Image size every view must have (the camera's), pixels.
    pub size: (u32, u32),
    summaries: Vec<ViewSummary>,
    /// The camera's blur measured on the background captures, where decode could.
    pub blur: Option<MeasuredBlur>,
}

impl DecodedScan {
    /// Opens `scan_dir/decoded` for images of `size`; a clear error when it was never decoded.
    pub fn open(scan_dir: &Path, size: (u32, u32)) -> Result<Self> {
        let dir = scan_dir.join("decoded");
        let path = dir.join("summary.json");
        if !path.is_file() {
            bail!(
                "{}: the scan has no decoded data; run `glasscan decode {}` first (or simulate with --decoded-only)",
                path.display(),
                scan_dir.display()
            );
        }
        let summary = read_summary(&dir)?;
        Ok(Self {
            dir,
            fixed: summary.fixed,
            size,
            summaries: summary.views,
            blur: summary.blur,
        })
    }

    /// What decode recorded of each view.
    pub fn summaries(&self) -> &[ViewSummary] {
        &self.summaries
    }

    /// The warning decode recorded for view `k`, if any.
    pub fn warning(&self, k: usize) -> Option<&str> {
        self.summaries
            .iter()
            .find(|s| s.view == k)
            .and_then(|s| s.warning.as_deref())
    }

    /// View `k`'s mask as stored (see [`MASK_OBJECT`], [`MASK_FILLED`]); `Ok(None)` for a view decode skipped with a warning.
    pub fn mask(&self, k: usize) -> Result<Option<Vec<u8>>> {
        let path = mask_path(&self.dir, k);
        if !path.is_file() {
            if self.warning(k).is_some() {
                return Ok(None);
            }
            bail!(
                "{}: view {k} is not decoded; run `glasscan decode` on all views",
                path.display()
            );
        }
        let m = self.load(&path, opencv::core::CV_8UC1)?;
        Ok(Some(m.data_typed::<u8>()?.to_vec()))
    }

    /// View `k` decoded; `Ok(None)` for a view decode skipped with a warning.
    pub fn view(&self, k: usize) -> Result<Option<DecodedView>> {
        let Some(mask) = self.mask(k)? else {
            return Ok(None);
        };
        let n = (self.size.0 * self.size.1) as usize;
        let rays = rays_path(&self.dir, k);
        if !monitor_path(&self.dir, k).is_file() && rays.is_file() {
            return Ok(Some(DecodedView {
                view: k,
                width: self.size.0,
                height: self.size.1,
                mask: mask.iter().map(|&b| is_object(b)).collect(),
                targets: vec![None; n],
                rays: Some(read_rays(&rays, n)?),
                contrasts: None,
            }));
        }
        let path = monitor_path(&self.dir, k);
        let m = self.load(&path, opencv::core::CV_16UC4)?;
        let targets = m
            .data_typed::<Vec4w>()?
            .iter()
            .map(|p| {
                Some(MonitorTarget {
                    u: self.fixed.decode(p[0])?,
                    v: self.fixed.decode(p[1])?,
                    cell_u: p[2] as f64,
                    cell_v: p[3] as f64,
                })
            })
            .collect();
        Ok(Some(DecodedView {
            view: k,
            width: self.size.0,
            height: self.size.1,
            mask: mask.iter().map(|&b| is_object(b)).collect(),
            targets,
            rays: None,
            contrasts: self.contrasts(k)?,
        }))
    }

    /// View `k`'s outline coverage (see [`coverage_path`]), if the decode wrote it.
    pub fn coverage(&self, k: usize) -> Result<Option<Vec<u8>>> {
        let path = coverage_path(&self.dir, k);
        if !path.is_file() {
            return Ok(None);
        }
        let m = self.load(&path, opencv::core::CV_8UC1)?;
        Ok(Some(m.data_typed::<u8>()?.to_vec()))
    }

    /// View `k`'s measured bit contrasts, if the decode wrote them.
    fn contrasts(&self, k: usize) -> Result<Option<Vec<[f32; 4]>>> {
        let path = contrasts_path(&self.dir, k);
        if !path.is_file() {
            return Ok(None);
        }
        let m = self.load(&path, opencv::core::CV_16UC4)?;
        let c = m.data_typed::<Vec4w>()?;
        Ok(Some(c.iter().map(|p| p.0.map(decode_contrast)).collect()))
    }

    fn load(&self, path: &Path, typ: i32) -> Result<Mat> {
        if !path.is_file() {
            bail!("{}: missing from the decoded data", path.display());
        }
        // The size a PNG declares is checked before OpenCV allocates it.
        if let Some((w, h)) = png_size(path) {
            if (w, h) != self.size {
                bail!(
                    "{}: {w}×{h} pixels, but the camera (camera.yml) takes {}×{}; decode again",
                    path.display(),
                    self.size.0,
                    self.size.1
                );
            }
        }
        let m = read_image(path, opencv::imgcodecs::IMREAD_UNCHANGED)?;
        if (m.cols() as u32, m.rows() as u32) != self.size {
            bail!(
                "{}: {}×{} pixels, but the camera (camera.yml) takes {}×{}; decode again",
                path.display(),
                m.cols(),
                m.rows(),
                self.size.0,
                self.size.1
            );
        }
        if m.typ() != typ {
            bail!(
                "{}: unexpected pixel type (see the README's decoded form)",
                path.display()
            );
        }
        Ok(if m.is_continuous() { m } else { m.try_clone()? })
    }
}
