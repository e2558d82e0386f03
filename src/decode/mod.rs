//! `glasscan decode`: captures → per view the silhouette and, per object pixel, the monitor point
//! it sees, with the uncertainty its reliable bits leave. The decoded form is documented in the
//! README (`decoded/` of the scan folder).

pub mod blur;
mod carry;
pub mod coherence;
pub mod compare;
pub mod edges;
pub mod graycode;
pub mod mask;
pub mod phase;

use std::path::Path;

use anyhow::{bail, Context, Result};
use nalgebra::Point3;
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Vec3b, Vec4w, CV_16U, CV_8U};
use rayon::prelude::*;

use crate::patterns::{GrayCode, PhaseShift};
use crate::scan::decoded::{self as form, ViewSummary};
use crate::scan::Scan;
use crate::util::fixed::{FixedPoint, NONE};
use crate::util::folder::StagedFolder;
use crate::util::image::{read_image, write_pixels};
use coherence::{
    background_share, fine_bits, flat_glass_pixels, flat_glass_share, interior_object_pixels,
    shares_beside_flat_glass, FineDiffs, FLAT_FACED_SCAN_SHARE,
};
use edges::StripeEdge;
use graycode::{bit_contrasts, decode_view, BitTest, PixelDecode};
use mask::{
    clean, dim_points, outline_coverage, pixels_at_monitor_edge, raw_mask, BackgroundPixel,
    MaskOptions, RawMask, ViewPixels,
};

/// Thresholds of decoding.
#[derive(Clone, Copy, Debug)]
pub struct DecodeOptions {
    /// A bit is reliable where pattern and inverse differ by at least this (grey levels; OpenCV's
    /// `whiteThreshold`, default 5).
    pub white_threshold: u8,
    /// A pixel is lit where white − black exceeds this (OpenCV's `blackThreshold`, default 40).
    pub black_threshold: u8,
    /// Smallest bit contrast as a share of the pixel's white − black range (0: OpenCV's test).
    pub min_contrast: f32,
    /// Refine with the phase-shift images, where the scan has them.
    pub use_phase: bool,
    /// Smallest phase modulation (B/A) a refined pixel needs.
    pub min_modulation: f64,
    pub mask: MaskOptions,
    /// Bits per sample of 16-bit captures (a 12-bit camera stores values up to 4095);
    /// `None`: the smallest of 10, 12, 14 and 16 that holds each view's white image.
    pub bit_depth: Option<u32>,
    /// Object pixels whose white image shows less than this share of the most light a path
    /// through the object passes get no monitor point (0: all keep theirs;
    /// [`mask::dim_points`], docs/decisions.md#points-from-light-that-split).
    pub min_light: f32,
}

impl Default for DecodeOptions {
    fn default() -> Self {
        Self {
            white_threshold: 5,
            black_threshold: 40,
            min_contrast: 0.3,
            use_phase: true,
            min_modulation: 0.3,
            mask: MaskOptions::default(),
            bit_depth: None,
            min_light: 0.0,
        }
    }
}

/// The captures of one view (or of the background), decoded.
pub struct DecodedCapture {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<PixelDecode>,
    pub lit: Vec<bool>,
    pub white: Vec<u8>,
    /// The fine bits' pattern − inverse differences (the mask's edge rule), when asked for.
    pub fine: Option<FineDiffs>,
    /// The contrasts of the bits around each pixel's cell ([`graycode::bit_contrasts`]).
    pub contrasts: Vec<[f32; 4]>,
    /// The camera's blur measured on the stripes, or why it could not be; `None` when not
    /// asked for.
    pub blur: Option<Result<form::MeasuredBlur, blur::Unmeasured>>,
    /// The sub-pixel stripe edges ([`edges`]), when asked for.
    pub edges: Option<Vec<StripeEdge>>,
}

/// A decoded capture of the monitor seen directly: its pattern images (OpenCV's order), white
/// and black images, decoded pixels and lit flags, row-major, `width` × `height`.
pub struct DirectView<'a> {
    pub images: &'a [&'a [u8]],
    pub white: &'a [u8],
    pub black: &'a [u8],
    pub pixels: &'a [PixelDecode],
    pub lit: &'a [bool],
    pub width: usize,
    pub height: usize,
}

impl<'a> DirectView<'a> {
    /// From a capture's `n` pattern images followed by its white and black ones, its decoded
    /// `pixels` and `lit` flags, `size` = (width, height).
    fn new(
        data: &'a [&'a [u8]],
        n: usize,
        (pixels, lit): (&'a [PixelDecode], &'a [bool]),
        size: (u32, u32),
    ) -> Self {
        Self {
            images: &data[..n],
            white: data[n],
            black: data[n + 1],
            pixels,
            lit,
            width: size.0 as usize,
            height: size.1 as usize,
        }
    }
}

/// The most stripe edges [`decode_captures`] keeps ([`edges::stripe_edges`]), about 32 MB: every
/// edge of a 640×480 camera, those of a tenth of the pixel pairs of a 5 MP one.
pub const MOST_EDGES: usize = 1_000_000;

/// What [`decode_captures`] keeps beyond the decoded pixels.
#[derive(Clone, Copy, Debug, Default)]
pub struct Keep {
    /// The fine bits' pattern − inverse differences (the mask's edge rule).
    pub fine: bool,
    /// The camera's blur, measured on the stripes ([`blur`]; captures of the monitor alone).
    pub blur: bool,
    /// The sub-pixel stripe edges ([`edges`]; captures of the monitor alone).
    pub edges: bool,
}

/// The bit contrasts of the object pixels with a decoded monitor point, encoded for
/// `view_NNN_bits.png` (absent elsewhere).
fn object_contrasts(cap: &DecodedCapture, mask: &[u8], monitor: &[Vec4w]) -> Vec<Vec4w> {
    cap.contrasts
        .iter()
        .zip(mask.iter().zip(monitor))
        .map(|(c, (&m, t))| {
            if m == 255 && t[0] != NONE {
                Vec4w::from(c.map(form::encode_contrast))
            } else {
                Vec4w::from([NONE; 4])
            }
        })
        .collect()
}

/// Reads one capture as grey at its own depth (8 or 16 bits), checked to be `size`.
fn read_capture(path: &Path, size: (u32, u32)) -> Result<Mat> {
    use opencv::imgcodecs::{IMREAD_ANYDEPTH, IMREAD_GRAYSCALE};
    let m = read_image(path, IMREAD_GRAYSCALE | IMREAD_ANYDEPTH)?;
    if (m.cols() as u32, m.rows() as u32) != size {
        bail!(
            "{}: {}×{} pixels, but the camera (camera.yml) takes {}×{}",
            path.display(),
            m.cols(),
            m.rows(),
            size.0,
            size.1
        );
    }
    if !matches!(m.depth(), CV_8U | CV_16U) {
        bail!(
            "{}: captures are 8- or 16-bit grey or colour images",
            path.display()
        );
    }
    Ok(m)
}

/// The bits per sample of a view whose white capture is `white`: 8 for 8-bit images, else the
/// smallest of 10, 12, 14 and 16 bits that holds its brightest pixel.
fn bit_depth_of(white: &Mat) -> Result<u32> {
    if white.depth() == CV_8U {
        return Ok(8);
    }
    let max = white
        .data_typed::<u16>()?
        .iter()
        .copied()
        .max()
        .unwrap_or(0);
    Ok([10, 12, 14, 16]
        .into_iter()
        .find(|&b| u32::from(max) < 1 << b)
        .unwrap_or(16))
}

/// `m` as 8-bit grey levels, a 16-bit image scaled from `bits` bits per sample.
fn to_8bit(m: Mat, bits: u32) -> Result<Mat> {
    let m = if m.depth() == CV_8U {
        m
    } else {
        let mut out = Mat::default();
        let scale = 255.0 / ((1u64 << bits.clamp(8, 16)) - 1) as f64;
        m.convert_to(&mut out, CV_8U, scale, 0.0)?;
        out
    };
    Ok(if m.is_continuous() { m } else { m.try_clone()? })
}

/// Whether each pixel is lit: white − black above `black_threshold` grey levels.
fn lit_pixels(white: &[u8], black: &[u8], black_threshold: u8) -> Vec<bool> {
    (white.iter().zip(black))
        .map(|(&w, &b)| w as i32 - b as i32 > black_threshold as i32)
        .collect()
}

/// Reads and decodes the captures in `dir` (with the phase-shift images if `phase` is given),
/// keeping what `keep` asks for; names the missing or misfit image.
pub fn decode_captures(
    dir: &Path,
    code: &GrayCode,
    phase: Option<&PhaseShift>,
    size: (u32, u32),
    o: &DecodeOptions,
    keep: Keep,
) -> Result<DecodedCapture> {
    let names = crate::patterns::capture_names(code, phase);
    let n = code.pattern_count();
    let paths: Vec<_> = names.iter().map(|name| dir.join(name)).collect();
    if let Some(path) = paths.iter().find(|p| !p.is_file()) {
        bail!(
            "{}: missing capture (expected {} images named as in `glasscan patterns`)",
            path.display(),
            names.len()
        );
    }
    let depth = match o.bit_depth {
        Some(bits) => bits,
        None => bit_depth_of(&read_capture(&paths[n], size)?)?,
    };
    // PNG decompression is most of a decode's time: the images are read in parallel.
    let mats = paths
        .par_iter()
        .map(|path| to_8bit(read_capture(path, size)?, depth))
        .collect::<Result<Vec<_>>>()?;
    let data: Vec<&[u8]> = mats
        .iter()
        .map(|m| m.data_typed::<u8>())
        .collect::<Result<_, _>>()?;
    let (white, black) = (data[n], data[n + 1]);
    let test = BitTest {
        white_threshold: o.white_threshold,
        min_contrast: o.min_contrast,
    };
    let mut pixels = decode_view(&data[..n], white, black, code, test);
    let lit = lit_pixels(white, black, o.black_threshold);
    let edges = keep.edges.then(|| {
        let view = DirectView::new(&data, n, (&pixels, &lit), size);
        edges::stripe_edges(&view, code, test, MOST_EDGES)
    });
    let fine = keep
        .fine
        .then(|| FineDiffs::new(&data[..n], white, black, &fine_bits(code), test));
    if let Some(p) = phase {
        phase::refine(&mut pixels, &data[n + 2..], p, o.min_modulation);
    }
    let contrasts = bit_contrasts(&data[..n], white, black, code, &pixels);
    let blur = keep
        .blur
        .then(|| blur::estimate(&DirectView::new(&data, n, (&pixels, &lit), size), code));
    Ok(DecodedCapture {
        width: size.0 as usize,
        height: size.1 as usize,
        pixels,
        lit,
        white: white.to_vec(),
        fine,
        contrasts,
        blur,
        edges,
    })
}

/// Decodes views `views` of `scan` into `scan/decoded/` (replaced whole once the decode is
/// complete; a failure leaves the previous decode as it was). The other views' decoded files and
/// any file the user put there are kept ([`carry::carry_over`]). The background captures, where
/// taken, also give the camera's blur ([`blur`]).
pub fn decode_scan(
    scan: &Scan,
    views: &[usize],
    o: &DecodeOptions,
    mut progress: impl FnMut(&ViewSummary),
) -> Result<DecodeOutcome> {
    let code = scan.graycode();
    let phase_shift = scan.config.patterns.phase_shift.filter(|_| o.use_phase);
    let phase = phase_shift.as_ref();
    let size = (scan.camera.width, scan.camera.height);
    check_memory(size, &code, phase)?;
    // The new decode replaces `decoded/` whole once it is complete; until then the old one stays.
    // It starts from what it does not decode again of the old one.
    let target = scan.dir.join("decoded");
    let staged = StagedFolder::new(&target, true, "")?;
    let out = staged.path().to_path_buf();
    let fixed = FixedPoint::for_screen(code.width, code.height);
    let kept = carry::carry_over(&target, &out, views, &fixed)?;
    std::fs::create_dir_all(out.join("preview"))
        .with_context(|| format!("cannot create {}", out.display()))?;
    let (background, background_capture) = background_reference(scan, &code, phase, size, o)?;
    let blur = background_capture.as_ref().and_then(|c| c.blur);
    let measured = blur.and_then(Result::ok);
    let writer = ViewWriter {
        out: &out,
        background: &background,
        background_capture: background_capture.as_ref(),
        code: &code,
        ior: scan.config.ior.nominal(),
        o,
        fixed: &fixed,
    };
    let mut summaries = Vec::new();
    for &k in views {
        let keep = Keep {
            fine: background_capture.is_some(),
            ..Keep::default()
        };
        let cap = decode_captures(&scan.view_dir(k), &code, phase, size, o, keep)?;
        let summary = match view_problem(&cap) {
            Some(why) => ViewSummary {
                view: k,
                object_pixels: 0,
                decoded_share: 0.0,
                complete_share: 0.0,
                dim_share: None,
                white_drop: None,
                monitor_edge_px: 0,
                warning: Some(why),
                flat_glass: None,
            },
            None => writer.write(k, &cap)?,
        };
        progress(&summary);
        summaries.push(summary);
    }
    let mut all: Vec<ViewSummary> = kept.into_iter().chain(summaries.iter().cloned()).collect();
    all.sort_by_key(|s| s.view);
    form::write_summary(&out, &fixed, &all, measured.as_ref())?;
    staged.commit()?;
    Ok(DecodeOutcome {
        views: summaries,
        blur,
    })
}

/// What [`decode_scan`] found.
pub struct DecodeOutcome {
    /// The views decoded, in the order asked for.
    pub views: Vec<ViewSummary>,
    /// The camera's blur measured on the background captures, or why it could not be; `None`
    /// without them.
    pub blur: Option<Result<form::MeasuredBlur, blur::Unmeasured>>,
}

impl DecodeOutcome {
    /// The share of the object's inside through which the monitor shows barely shifted, when it
    /// marks the object flat-faced ([`FLAT_FACED_SCAN_SHARE`]) and the decode did not already
    /// judge the outlines for flat faces (`flat_faces`): such outlines lie closer to the truth
    /// with [`MaskOptions::flat_faces`], unless the object has sharp edges.
    pub fn flat_faces_suggested(&self, flat_faces: bool) -> Option<f64> {
        let share = flat_glass_share(&self.views)?;
        (!flat_faces && share >= FLAT_FACED_SCAN_SHARE).then_some(share)
    }

    /// Whether a decode without a light rule (`min_light` 0) of a scan whose index is to be
    /// estimated (`ior_auto`) should have one ([`DecodeOptions::min_light`]): the object is curved,
    /// its inside showing the monitor barely shifted through less than
    /// [`FLAT_FACED_SCAN_SHARE`] (which, like the rule, needs the background captures). Points
    /// from light that split bias the estimate low there; on flat faces seen edge-on the rule
    /// would take the only rays that hold them.
    pub fn min_light_suggested(&self, min_light: f32, ior_auto: bool) -> bool {
        ior_auto
            && min_light == 0.0
            && flat_glass_share(&self.views).is_some_and(|s| s < FLAT_FACED_SCAN_SHARE)
    }
}

/// Refuses a decode whose images would not fit the memory budget: per camera pixel it holds the
/// background's and one view's captures (8-bit) with their decoded data at a time.
fn check_memory(size: (u32, u32), code: &GrayCode, phase: Option<&PhaseShift>) -> Result<()> {
    let images = crate::patterns::capture_names(code, phase).len() as u128;
    let decoded = (std::mem::size_of::<PixelDecode>() + 6 + 2 * fine_bits(code).len()) as u128;
    let outputs = 32; // mask, monitor point, preview, the mask's evidence
    crate::util::budget::check(
        &format!("decoding {}×{} captures", size.0, size.1),
        u128::from(size.0) * u128::from(size.1),
        2 * (images + decoded) + outputs,
        "decode on a machine with more memory",
    )?;
    Ok(())
}

/// The warning of a decoded view with `object` object pixels, `edge` of them at the edge of the
/// monitor's image.
fn view_warning(object: usize, edge: usize) -> Option<String> {
    if object == 0 {
        return Some(
            "no object pixel found: is the object in view, and the background right?".into(),
        );
    }
    (edge > 0).then(|| {
        format!(
            "the object reaches the edge of the monitor's image ({edge} outline pixels): what lies \
             beyond shows no pattern, is cut off the silhouette and carved off the hull; move the \
             monitor closer to the object or use a larger one, so that it covers the object in \
             every view"
        )
    })
}

/// A view that cannot be decoded: monitor off, or saturated.
fn view_problem(cap: &DecodedCapture) -> Option<String> {
    let n = cap.white.len() as f64;
    let bright = cap.white.iter().filter(|&&w| w > 30).count() as f64;
    let lit = cap.lit.iter().filter(|&&l| l).count() as f64;
    if bright < 0.01 * n {
        return Some("the white image is dark: was the monitor off?".into());
    }
    if lit < 0.01 * n {
        return Some(
            "white and black images look alike (saturated or monitor off): nothing decodes".into(),
        );
    }
    None
}

/// The background per pixel: decoded from `captures/background` if present (returned too), else
/// predicted from the screen pose.
fn background_reference(
    scan: &Scan,
    code: &GrayCode,
    phase: Option<&PhaseShift>,
    size: (u32, u32),
    o: &DecodeOptions,
) -> Result<(Vec<BackgroundPixel>, Option<DecodedCapture>)> {
    let dir = scan.background_dir();
    if dir.is_dir() {
        let keep = Keep {
            fine: true,
            blur: true,
            ..Keep::default()
        };
        let cap = decode_captures(&dir, code, phase, size, o, keep)?;
        let pixels = cap
            .pixels
            .iter()
            .zip(&cap.lit)
            .zip(&cap.white)
            .map(|((d, &lit), &w)| BackgroundPixel {
                point: (lit && d.u.bits > 0 && d.v.bits > 0).then_some((
                    d.u.coord,
                    d.v.coord,
                    d.u.cell as f32,
                    d.v.cell as f32,
                )),
                white: Some(w),
            })
            .collect();
        return Ok((pixels, Some(cap)));
    }
    let (w, h) = size;
    let pixels = (0..h * w)
        .map(|p| {
            let point = scan
                .camera
                .pixel_ray((p % w) as f64, (p / w) as f64)
                .and_then(|d| scan.screen.intersect(&Point3::origin(), &d))
                .map(|(_, px)| (px.x as f32, px.y as f32, 1.0, 1.0));
            BackgroundPixel { point, white: None }
        })
        .collect();
    Ok((pixels, None))
}

/// What every view's outputs depend on besides its captures.
struct ViewWriter<'a> {
    /// The `decoded/` folder.
    out: &'a Path,
    background: &'a [BackgroundPixel],
    /// The background's captures, decoded, where they were taken.
    background_capture: Option<&'a DecodedCapture>,
    code: &'a GrayCode,
    /// The object's refractive index (for the mask's white-drop rule).
    ior: f64,
    o: &'a DecodeOptions,
    fixed: &'a FixedPoint,
}

impl ViewWriter<'_> {
    /// Masks view `k` and writes its decoded form and preview.
    fn write(&self, k: usize, cap: &DecodedCapture) -> Result<ViewSummary> {
        let background = self.background_capture.and_then(|b| b.fine.as_ref());
        let share = match (&cap.fine, background) {
            (Some(view), Some(background)) => Some(background_share(view, background)),
            _ => None,
        };
        let (mut mask, mut white_drop) = self.mask(cap, share.as_deref())?;
        let interior = share
            .as_ref()
            .map(|_| interior_object_pixels(&mask, cap.width));
        let flat_glass = share
            .as_deref()
            .zip(interior.as_deref())
            .map(|(s, inside)| flat_glass_pixels(s, inside));
        let share = match (share, interior) {
            (Some(s), Some(inside)) if self.o.mask.flat_faces => {
                let corrected = shares_beside_flat_glass(&s, &inside, cap.width);
                (mask, white_drop) = self.mask(cap, Some(&corrected))?;
                Some(corrected)
            }
            (share, _) => share,
        };
        let dim = dim_points(
            &mask,
            &cap.white,
            self.background,
            self.ior,
            self.o.min_light,
        );
        let images = ViewImages::of(cap, (&mask, dim.as_deref()), self.code, self.fixed);
        let contrasts = object_contrasts(cap, &mask, &images.monitor);
        let coverage = share
            .as_deref()
            .map(|s| outline_coverage(&mask, s, cap.width));
        let size = (cap.width as u32, cap.height as u32);
        let extras = form::ViewExtras {
            contrasts: Some(&contrasts),
            coverage: coverage.as_deref(),
        };
        form::write_view(self.out, k, size, &mask, &images.monitor, extras)?;
        let preview = self.out.join("preview").join(format!("view_{k:03}.png"));
        write_pixels(&preview, size.0, size.1, &images.preview)?;
        let edge = pixels_at_monitor_edge(&mask, self.background, cap.width);
        let (object, decoded) = (images.object, images.decoded);
        Ok(ViewSummary {
            view: k,
            object_pixels: object,
            decoded_share: decoded as f64 / object.max(1) as f64,
            complete_share: images.complete as f64 / decoded.max(1) as f64,
            dim_share: dim.map(|_| images.dim as f64 / object.max(1) as f64),
            white_drop: white_drop.map(f64::from),
            monitor_edge_px: edge,
            warning: view_warning(object, edge),
            flat_glass,
        })
    }

    /// The view's cleaned mask, and the white drop its rule used if any (`share`: each
    /// pixel's share of the background's fine code, where it was captured).
    fn mask(&self, cap: &DecodedCapture, share: Option<&[f32]>) -> Result<(Vec<u8>, Option<f32>)> {
        let view = ViewPixels {
            width: cap.width,
            decoded: &cap.pixels,
            lit: &cap.lit,
            white: &cap.white,
            background_share: share,
        };
        let RawMask {
            mut mask,
            white_drop,
            holes,
        } = raw_mask(&view, self.background, self.ior, &self.o.mask);
        let (w, h) = (cap.width as i32, cap.height as i32);
        clean(&mut mask, w, h, &self.o.mask, holes.as_ref())?;
        Ok((mask, white_drop))
    }
}

/// A view's decoded monitor points as stored (fixed point, cell widths) and its preview, with
/// the counts of its object pixels, those decoded, those decoded to the last bit, and those
/// whose point was dropped for too little light.
struct ViewImages {
    monitor: Vec<Vec4w>,
    preview: Vec<Vec3b>,
    object: usize,
    decoded: usize,
    complete: usize,
    dim: usize,
}

impl ViewImages {
    /// The images of capture `cap` under its cleaned `mask`, without the points of the object
    /// pixels `dim` marks ([`dim_points`]).
    fn of(
        cap: &DecodedCapture,
        (mask, dim): (&[u8], Option<&[bool]>),
        code: &GrayCode,
        fixed: &FixedPoint,
    ) -> Self {
        let mut im = ViewImages {
            monitor: Vec::with_capacity(mask.len()),
            preview: Vec::with_capacity(mask.len()),
            object: 0,
            decoded: 0,
            complete: 0,
            dim: 0,
        };
        for (i, ((d, (&m, &lit)), &white)) in cap
            .pixels
            .iter()
            .zip(mask.iter().zip(&cap.lit))
            .zip(&cap.white)
            .enumerate()
        {
            let decoded = lit && d.u.bits > 0 && d.v.bits > 0;
            let dimmed = decoded && dim.is_some_and(|dim| dim[i]);
            let valid = decoded && !dimmed;
            im.monitor.push(if valid {
                Vec4w::from([
                    fixed.encode(d.u.coord as f64),
                    fixed.encode(d.v.coord as f64),
                    d.u.cell.min(65534) as u16,
                    d.v.cell.min(65534) as u16,
                ])
            } else {
                Vec4w::from([NONE; 4])
            });
            if m != 255 {
                let g = white / 2;
                im.preview.push(Vec3b::from([g, g, g]));
                continue;
            }
            im.object += 1;
            im.decoded += valid as usize;
            im.dim += dimmed as usize;
            im.complete += (valid && d.complete(code)) as usize;
            // Object pixels: decoded coordinates as colours (blue: row, green: column), red
            // without a point (nothing decoded, or too little light).
            im.preview.push(if valid {
                Vec3b::from([
                    (255.0 * d.v.coord / code.height as f32) as u8,
                    (255.0 * d.u.coord / code.width as f32) as u8,
                    40,
                ])
            } else {
                Vec3b::from([0, 0, 255])
            });
        }
        im
    }
}
