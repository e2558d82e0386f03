//! What a run reads from the scan, loaded once: refraction targets, silhouettes, and the
//! fingerprint of the files they came from.
//!
//! A view's targets are kept as a fixed sample that puts its rays half `ray_spacing` apart at
//! the object ([`Settings::kept_spacing_share`]), so that memory, like the rays, follows the
//! object and not the camera's pixel count (docs/decisions.md#rays-that-follow-the-scene).

use std::sync::Arc;

use super::config::Settings;
use crate::decode::coherence::{flat_glass_share, FLAT_FACED_SCAN_SHARE};
use crate::loss::blur::{correct_targets, BlurKernel, CorrectionSummary};
use crate::loss::refraction::ViewTargets;
use crate::scan::decoded::{DecodedScan, MeasuredBlur};
use crate::scan::silhouette::Silhouette;
use crate::trace::path::Surface;
use anyhow::{bail, Result};
use nalgebra::Point3;

/// What the optimisation reads from the scan, loaded once.
pub struct Inputs {
    /// The object's refractive index, known or to estimate.
    pub ior: crate::scan::Ior,
    /// Where an unknown index starts (the index pass's estimate; `None`: the range's middle).
    pub ior_start: Option<f64>,
    pub targets: Vec<ViewTargets>,
    /// Per view of `targets`, the share of its decoded pixels kept (their weights carry its
    /// inverse).
    pub kept_shares: Vec<f64>,
    /// Shared with the inputs [`Inputs::deblurred`] makes.
    pub silhouettes: Arc<Vec<Silhouette>>,
    /// The camera's blur ([`CameraBlur`]), which a run whose settings have `blur_correction`
    /// corrects the decoded points for.
    pub blur: Option<BlurKernel>,
    /// Where the blur comes from, with what decode measured.
    pub blur_source: CameraBlur,
    /// Whether the blur's skew marks pixels as no evidence of the index
    /// ([`crate::loss::blur`]): a blur is known, and the glass is not flat-faced by decode's
    /// measure (less than [`FLAT_FACED_SCAN_SHARE`] of its inside shows the monitor barely
    /// shifted, or not measured). Through flat faces the marks took the rays that settle the
    /// index: the block at 1.60 estimated 1.557 with them, 1.581 without.
    pub skew_marks: bool,
    /// Whether the decoded points were measured from captures (they carry Gray bits; exact
    /// correspondences do not) through glass that is not flat-faced by decode's measure (as for
    /// [`Self::skew_marks`]): a run that estimates the index models each such pixel by a
    /// footprint of rays ([`super::index::estimating_settings`]).
    pub curved_captures: bool,
    /// What the inputs were read from ([`fingerprint`]); a run resumes only from the same.
    pub fingerprint: super::fingerprint::Fingerprint,
}

/// Loads the decoded targets of `views` (weighted by `settings.target_weights`), each view's
/// kept as a sample for an object of bounding-box diagonal `diagonal_mm` (the start mesh's), with
/// `silhouettes` and warnings: views without refraction data, a per-bit term without contrasts
/// to read.
pub fn load_inputs(
    scan: &crate::scan::Scan,
    views: &[usize],
    settings: &Settings,
    (silhouettes, mut warnings): (Vec<Silhouette>, Vec<String>),
    diagonal_mm: f64,
) -> Result<(Inputs, Vec<String>)> {
    let weights = settings.target_weights;
    let spacing_mm = settings.kept_spacing_share() * diagonal_mm;
    let keep = |t: ViewTargets| {
        // At the camera's height on the turntable axis (the world frame's y axis).
        let share = t.share_for_spacing(&Point3::new(0.0, t.eye.y, 0.0), spacing_mm);
        if share < 1.0 {
            (t.sampled(share, 0.5), share)
        } else {
            (t, 1.0)
        }
    };
    let decoded = DecodedScan::open(&scan.dir, (scan.camera.width, scan.camera.height))?;
    let (targets, skipped) =
        crate::loss::targets::scan_targets_with(scan, &decoded, views, weights, keep)?;
    let blur_source = CameraBlur {
        given_px: scan.config.blur_px,
        measured: decoded.blur,
    };
    let (targets, kept_shares): (Vec<ViewTargets>, Vec<f64>) = targets.into_iter().unzip();
    if targets.is_empty() {
        bail!("no decoded view to reconstruct from");
    }
    let pixels: usize = targets.iter().map(|t| t.pixels.len()).sum();
    if pixels == 0 {
        bail!("no object pixel has a decoded monitor point: check the decode (decoded/preview/)");
    }
    warnings.extend(
        skipped
            .iter()
            .map(|k| format!("view {k}: no refraction data (decode skipped it)")),
    );
    let has_bits = targets.iter().any(ViewTargets::has_measured_bits);
    if settings.weight_bits > 0.0 && !has_bits && scan.dir.join("captures").is_dir() {
        warnings.push(format!(
            "the decoded data has no Gray-bit contrasts (decoded by an earlier glasscan): the per-bit term is idle; run `glasscan decode {}` again to use it",
            scan.dir.display()
        ));
    }
    let curved = flat_glass_share(decoded.summaries()).is_none_or(|s| s < FLAT_FACED_SCAN_SHARE);
    Ok((
        Inputs {
            ior: scan.config.ior,
            ior_start: None,
            targets,
            kept_shares,
            silhouettes: Arc::new(silhouettes),
            blur: blur_source.sigma_px().and_then(BlurKernel::gaussian),
            blur_source,
            skew_marks: blur_source.sigma_px().is_some() && curved,
            curved_captures: has_bits && curved,
            fingerprint: super::fingerprint::of_scan(scan, views)?,
        },
        warnings,
    ))
}

/// The camera's blur a run knows: scan.toml's `blur_px` if given, else what decode measured on
/// the background captures.
#[derive(Clone, Copy, Debug, Default)]
pub struct CameraBlur {
    /// scan.toml's `blur_px`, camera pixels.
    pub given_px: Option<f64>,
    pub measured: Option<MeasuredBlur>,
}

impl CameraBlur {
    /// σ of the blur, camera pixels: the given one, else the measured one.
    pub fn sigma_px(&self) -> Option<f64> {
        self.given_px.or(self.measured.map(|m| m.sigma_px))
    }

    /// Where σ comes from, for the run's notes.
    pub fn describe(&self) -> String {
        match (self.given_px, self.measured) {
            (Some(g), Some(m)) => format!(
                "σ {g} px, scan.toml; decode measured {:.2} px on the background captures",
                m.sigma_px
            ),
            (Some(g), None) => format!("σ {g} px, scan.toml"),
            (None, Some(m)) => format!(
                "σ {:.2} px, measured by decode on the background captures over {} stripe edges",
                m.sigma_px, m.edges
            ),
            (None, None) => "none known".into(),
        }
    }
}

impl Inputs {
    /// These inputs with the decoded points of the targets `views` (indices into `targets`;
    /// `None`: all) corrected for the camera's blur (when `shift`) through the mesh `surface`
    /// holds at refractive index `ior`, and those the blur skews marked as no evidence of the
    /// index where [`Self::skew_marks`] ([`crate::loss::blur`]), and how far they moved; `None`
    /// without a blur known.
    pub fn deblurred(
        &self,
        surface: &dyn Surface,
        ior: f64,
        views: Option<&[usize]>,
        shift: bool,
    ) -> Result<Option<(Inputs, CorrectionSummary)>> {
        let Some(kernel) = &self.blur else {
            return Ok(None);
        };
        let chosen = |t: usize| views.is_none_or(|v| v.contains(&t));
        let picked: Vec<&ViewTargets> = (self.targets.iter().enumerate())
            .filter(|&(t, _)| chosen(t))
            .map(|(_, view)| view)
            .collect();
        let (corrected, summary) =
            correct_targets(surface, ior, kernel, &picked, (shift, self.skew_marks))?;
        // Each view copied once: the chosen ones corrected, in order, the others as they are.
        let mut corrected = corrected.into_iter();
        let targets = (self.targets.iter().enumerate())
            .map(
                |(t, view)| match chosen(t).then(|| corrected.next()).flatten() {
                    Some(c) => c,
                    None => view.clone(),
                },
            )
            .collect();
        let inputs = Inputs {
            ior: self.ior,
            ior_start: self.ior_start,
            targets,
            kept_shares: self.kept_shares.clone(),
            silhouettes: Arc::clone(&self.silhouettes),
            blur: self.blur.clone(),
            blur_source: self.blur_source,
            skew_marks: self.skew_marks,
            curved_captures: self.curved_captures,
            fingerprint: self.fingerprint.clone(),
        };
        Ok(Some((inputs, summary)))
    }
}
