//! The settings of a simulated scan and their bounds.

use anyhow::{bail, Result};

use super::calibration;
use super::light::Transport;
use super::render::Sample;
use crate::patterns::PhaseShift;
use crate::trace::path::NormalModel;
use crate::util::fixed::MAX_SIDE_PX;

/// Settings of a simulated scan (defaults: DRT's rig at 1280×960).
#[derive(Clone, Debug)]
pub struct SimulateOptions {
    pub views: usize,
    pub width: u32,
    pub height: u32,
    pub ior: f64,
    pub screen_width: u32,
    pub screen_height: u32,
    pub pitch_mm: f64,
    /// Area samples per pixel (1: pixel centres only).
    pub spp: u32,
    /// Standard deviation of the sensor noise, grey levels (0..255).
    pub noise: f64,
    /// Gaussian blur of the captures, sigma in pixels (0: none).
    pub blur_px: f64,
    pub max_refractions: u32,
    pub decoded_only: bool,
    pub seed: u64,
    /// Camera centre to turntable axis, mm.
    pub camera_distance_mm: f64,
    /// Turntable axis to monitor, mm.
    pub screen_distance_mm: f64,
    /// Share of the image height the object fills.
    pub fill: f64,
    /// Normals the simulated object refracts with: interpolated by default (a real glass object
    /// is smooth; flat facets would add facet-edge artefacts a real capture does not have).
    pub normals: NormalModel,
    /// Fresnel transmission losses (simple transport; the physical one always has them).
    pub fresnel: bool,
    /// The light transport of the captures.
    pub transport: Transport,
    /// Phase-shift images after the Gray code.
    pub phase_shift: Option<PhaseShift>,
    /// The camera's lens distortion, OpenCV's k1 k2 p1 p2 k3.
    pub distortion: [f64; 5],
    /// Also render calibration image sets (see [`calibration`]) and the background capture.
    pub calibration_images: bool,
    /// The chessboards of the calibration sets.
    pub boards: calibration::CalibrationBoards,
    /// Replace a non-empty output folder (whole, once the new scan is written).
    pub force: bool,
}

impl Default for SimulateOptions {
    fn default() -> Self {
        Self {
            views: 72,
            width: 1280,
            height: 960,
            ior: 1.4723,
            screen_width: 1920,
            screen_height: 1080,
            pitch_mm: 0.2715,
            spp: 4,
            noise: 0.0,
            blur_px: 0.0,
            max_refractions: 8,
            decoded_only: false,
            seed: 0,
            camera_distance_mm: 550.0,
            screen_distance_mm: 250.0,
            fill: 0.6,
            normals: NormalModel::Vertex,
            fresnel: true,
            transport: Transport::Simple,
            phase_shift: None,
            distortion: [0.0; 5],
            calibration_images: false,
            boards: calibration::CalibrationBoards::default(),
            force: false,
        }
    }
}

pub use crate::scan::MAX_VIEWS;
/// The most area samples per pixel.
pub const MAX_SPP: u32 = 1024;

pub(super) fn check_options(o: &SimulateOptions) -> Result<()> {
    use crate::util::budget;
    if o.views > MAX_VIEWS || o.spp > MAX_SPP {
        bail!(
            "{} views and {} samples per pixel: at most {MAX_VIEWS} views and {MAX_SPP} samples",
            o.views,
            o.spp
        );
    }
    if o.width.max(o.height) > MAX_SIDE_PX || o.screen_width.max(o.screen_height) > MAX_SIDE_PX {
        bail!("image and monitor sides must be at most {MAX_SIDE_PX} pixels");
    }
    // One view's samples are held at a time, plus its images.
    let pixels = u128::from(o.width) * u128::from(o.height);
    budget::check(
        &format!(
            "{}×{} pixels at {} samples per pixel",
            o.width, o.height, o.spp
        ),
        pixels * u128::from(o.spp),
        std::mem::size_of::<Sample>() as u128 + 16,
        "use a smaller --size or --spp",
    )?;
    if o.width == 0 || o.height == 0 {
        bail!(
            "image size {}x{}: both must be at least 1 pixel",
            o.width,
            o.height
        );
    }
    if o.screen_width < 2 || o.screen_height < 2 {
        bail!(
            "screen size {}x{}: both must be at least 2 pixels",
            o.screen_width,
            o.screen_height
        );
    }
    check_optics(o)?;
    check_boards(&o.boards)
}

/// The optics' and the capture's bounds: index, distances, fill, phase shift, samples, noise,
/// blur and distortion.
fn check_optics(o: &SimulateOptions) -> Result<()> {
    if !(o.ior > 1.0 && o.ior.is_finite()) {
        bail!(
            "--ior {}: a solid object's refractive index is above 1",
            o.ior
        );
    }
    if !(o.pitch_mm > 0.0 && o.camera_distance_mm > 0.0 && o.screen_distance_mm > 0.0) {
        bail!("pitch and distances must be positive");
    }
    if !(o.fill > 0.0 && o.fill <= 1.0) {
        bail!("--fill {}: it must lie in (0, 1]", o.fill);
    }
    if let Some(p) = o.phase_shift {
        if p.steps < 3 || p.period_px < 4 {
            bail!("phase shift needs at least 3 steps and a period of at least 4 pixels");
        }
    }
    if o.transport == Transport::Physical && o.decoded_only {
        bail!("the physical transport shows in captures: drop --decoded-only (decode the captures instead)");
    }
    if o.views == 0 || o.spp == 0 || o.max_refractions == 0 {
        bail!("views, spp and max refractions must be at least 1");
    }
    if o.spp == 2 {
        bail!(
            "--spp 2: a pixel's area samples include its centre and are centred on it, which two \
             samples cannot be; use --spp 1 (centres only) or 3 or more"
        );
    }
    if !(o.noise >= 0.0 && o.blur_px >= 0.0) {
        bail!("noise and blur must not be negative");
    }
    if o.blur_px > crate::scan::MAX_BLUR_PX {
        bail!(
            "--blur {}: at most {} camera pixels",
            o.blur_px,
            crate::scan::MAX_BLUR_PX
        );
    }
    if o.distortion.iter().any(|d| d.is_nan() || d.abs() >= 1.0) {
        bail!("distortion coefficients must be finite and below 1 in size");
    }
    Ok(())
}

/// The calibration boards' bounds: 2–64 inner corners a side, squares of 0.1–1000 mm, 3 to
/// [`calibration::MAX_CAMERA_IMAGES`] images of the camera's board.
fn check_boards(b: &calibration::CalibrationBoards) -> Result<()> {
    if !(2..=64).contains(&b.cols) || !(2..=64).contains(&b.rows) {
        bail!(
            "--board {}x{}: 2 to 64 inner corners a side",
            b.cols,
            b.rows
        );
    }
    for s in [b.camera_square_mm, b.turntable_square_mm]
        .into_iter()
        .flatten()
    {
        if !(0.1..=1000.0).contains(&s) {
            bail!("a board square of {s} mm: give 0.1 to 1000 mm");
        }
    }
    let n = b.camera_images;
    if !(3..=calibration::MAX_CAMERA_IMAGES).contains(&n) {
        bail!(
            "{n} camera board images: give 3 to {}",
            calibration::MAX_CAMERA_IMAGES
        );
    }
    Ok(())
}
