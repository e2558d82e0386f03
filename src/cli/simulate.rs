//! `glasscan simulate --mesh M --out SCAN`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use super::common::{bar, ior, non_negative, parse_size, positive, positive_share};
use glasscan::calibrate::board::Board;
use glasscan::mesh::io::read_mesh;
use glasscan::patterns::PhaseShift;
use glasscan::simulate::calibration::{CalibrationBoards, MAX_CAMERA_IMAGES};
use glasscan::simulate::Transport;
use glasscan::simulate::{simulate, SimulateOptions, SimulateReport};
use glasscan::simulate::{MAX_SPP, MAX_VIEWS};
use glasscan::trace::path::NormalModel;
use glasscan::util::paths::ensure_output_spares_inputs;

#[derive(Args, Debug)]
pub struct SimulateArgs {
    /// The object (.ply or .obj; closed, manifold, outward), mm.
    #[arg(long)]
    pub mesh: PathBuf,
    /// The scan folder to write.
    #[arg(short = 'o', long, visible_alias = "output")]
    pub out: PathBuf,
    /// Turntable views, evenly spaced over 360°.
    #[arg(long, default_value_t = 72, value_parser = clap::value_parser!(u32).range(1..=MAX_VIEWS as i64))]
    pub views: u32,
    /// Camera image size, WIDTHxHEIGHT pixels.
    #[arg(long, default_value = "1280x960", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Refractive index of the object.
    #[arg(long, default_value_t = 1.4723, value_parser = ior)]
    pub ior: f64,
    /// Monitor resolution, WIDTHxHEIGHT pixels.
    #[arg(long, default_value = "1920x1080", value_parser = parse_size)]
    pub screen: (u32, u32),
    /// Monitor pixel pitch, mm.
    #[arg(long = "pitch-mm", default_value_t = 0.2715, value_parser = positive)]
    pub pitch_mm: f64,
    /// Area samples per camera pixel (1: pixel centres only).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..=MAX_SPP as i64))]
    pub spp: u32,
    /// Sensor noise, standard deviation in grey levels.
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    pub noise: f64,
    /// Gaussian blur of the captures, sigma in pixels (at most 5; recorded in scan.toml as
    /// `blur_px`, which `reconstruct` corrects for).
    #[arg(long = "blur", default_value_t = 0.0, value_parser = non_negative)]
    pub blur_px: f64,
    /// Refractions traced before a path is given up.
    #[arg(long = "max-refractions", default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub max_refractions: u32,
    /// Write calibration and ground truth only, no capture images.
    #[arg(long = "decoded-only")]
    pub decoded_only: bool,
    /// Seed of the sensor noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Camera centre to turntable axis, mm.
    #[arg(long = "camera-distance-mm", default_value_t = 550.0, value_parser = positive)]
    pub camera_distance_mm: f64,
    /// Turntable axis to monitor, mm.
    #[arg(long = "screen-distance-mm", default_value_t = 250.0, value_parser = positive)]
    pub screen_distance_mm: f64,
    /// Share of the image height the object fills.
    #[arg(long, default_value_t = 0.6, value_parser = positive_share)]
    pub fill: f64,
    /// Normals the object refracts with: vertex (interpolated, a smooth object) or face (flat
    /// facets).
    #[arg(long, value_enum, default_value_t = NormalModel::Vertex)]
    pub normals: NormalModel,
    /// No Fresnel transmission losses (simple transport).
    #[arg(long = "no-fresnel", conflicts_with = "transport")]
    pub no_fresnel: bool,
    /// Light transport of the captures: simple (one refracted path per area sample, the model
    /// the reconstruction inverts) or physical (Fresnel reflection and refraction at every
    /// interface, internal reflections and their ghosts).
    #[arg(long, value_enum, default_value_t = Transport::Simple)]
    pub transport: Transport,
    /// Also render N-step phase-shift images after the Gray code.
    #[arg(long = "phase-shift", value_parser = clap::value_parser!(u32).range(3..=64))]
    pub phase_steps: Option<u32>,
    /// Lens distortion of the camera, OpenCV's k1,k2,p1,p2,k3.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_values_t = [0.0; 5])]
    pub distortion: Vec<f64>,
    /// Also render calibration images with known truth (chessboards for the camera and the
    /// turntable, the background capture for the monitor) under SCAN/calibration/.
    #[arg(long = "calibration-images")]
    pub calibration_images: bool,
    /// Inner corners of the calibration boards, COLSxROWS (with --calibration-images).
    #[arg(long, default_value = "9x6", value_parser = Board::parse_size, requires = "calibration_images")]
    pub board: (u32, u32),
    /// Square side of the printed board, mm, for both calibration sets (default: sized with
    /// the rig, a large board for the camera and a smaller one for the turntable).
    #[arg(long = "square-mm", value_parser = positive, requires = "calibration_images")]
    pub square_mm: Option<f64>,
    /// Square side of the board standing on the turntable, mm, when it is a second, smaller
    /// print (default: --square-mm).
    #[arg(long = "turntable-square-mm", value_parser = positive, requires = "calibration_images")]
    pub turntable_square_mm: Option<f64>,
    /// Images of the camera's board.
    #[arg(long = "board-images", default_value_t = 60, value_parser = clap::value_parser!(u32).range(3..=MAX_CAMERA_IMAGES as i64), requires = "calibration_images")]
    pub board_images: u32,
    /// Replace a non-empty output folder (whole, once the new scan is written).
    #[arg(long)]
    pub force: bool,
    /// Period of the phase-shift sinusoid, monitor pixels.
    #[arg(long = "period-px", default_value_t = 64, requires = "phase_steps", value_parser = clap::value_parser!(u32).range(4..=65_536))]
    pub period_px: u32,
}

pub fn run(a: &SimulateArgs) -> Result<()> {
    ensure_output_spares_inputs(&a.out, "--out", &[&a.mesh])?;
    let mesh = read_mesh(&a.mesh)?;
    let o = options(a)?;
    let bar = bar("simulate", a.views as usize);
    let r = simulate(&mesh, &a.out, &o, |_| bar.inc(1))?;
    bar.finish_and_clear();
    print_report(a, &r)
}

/// The simulator's options from the command line's.
fn options(a: &SimulateArgs) -> Result<SimulateOptions> {
    Ok(SimulateOptions {
        views: a.views as usize,
        width: a.size.0,
        height: a.size.1,
        ior: a.ior,
        screen_width: a.screen.0,
        screen_height: a.screen.1,
        pitch_mm: a.pitch_mm,
        spp: a.spp,
        noise: a.noise,
        blur_px: a.blur_px,
        max_refractions: a.max_refractions,
        decoded_only: a.decoded_only,
        seed: a.seed,
        camera_distance_mm: a.camera_distance_mm,
        screen_distance_mm: a.screen_distance_mm,
        fill: a.fill,
        normals: a.normals,
        fresnel: !a.no_fresnel,
        transport: a.transport,
        phase_shift: a.phase_steps.map(|steps| PhaseShift {
            steps,
            period_px: a.period_px,
        }),
        distortion: a
            .distortion
            .clone()
            .try_into()
            .map_err(|_| anyhow::anyhow!("--distortion takes 5 coefficients: k1,k2,p1,p2,k3"))?,
        calibration_images: a.calibration_images,
        boards: CalibrationBoards {
            cols: a.board.0,
            rows: a.board.1,
            camera_square_mm: a.square_mm,
            turntable_square_mm: a.turntable_square_mm,
            camera_images: a.board_images as usize,
        },
        force: a.force,
    })
}

/// The run's summary: where the scan went, and what the camera rays met.
fn print_report(a: &SimulateArgs, r: &SimulateReport) -> Result<()> {
    outln!(
        "simulated {} views of {} into {} in {:.1} s",
        r.views,
        a.mesh.display(),
        a.out.display(),
        r.seconds
    );
    outln!(
        "object pixels (pixel-centre rays meeting the object): {}",
        r.object_pixels
    );
    if !r.monitor_covers_object {
        eprintln!(
            "warning: the monitor does not cover the object in every view: parts of it show no \
             pattern and decode cuts them off the silhouettes; use a larger --screen (or \
             --pitch-mm) or a smaller --screen-distance-mm"
        );
    }
    for (what, share) in [
        (
            "exactly 2 refractions, reach the monitor",
            r.two_refractions,
        ),
        (
            "4 or more refractions, reach the monitor",
            r.more_refractions,
        ),
        (
            "an odd number of refractions (grazing)",
            r.one_or_odd_refractions,
        ),
        ("total internal reflection", r.total_internal_reflection),
        ("leave the object but miss the monitor", r.missed_monitor),
        (
            "more interfaces than --max-refractions",
            r.too_many_interfaces,
        ),
        ("grazing shading normal", r.grazing_normal),
    ] {
        outln!("  {:>6.2} %  {what}", 100.0 * share);
    }
    if a.calibration_images {
        outln!(
            "calibration images and the commands that use them: {}",
            a.out.join("calibration").join("setup.json").display()
        );
    }
    if a.spp < 2 {
        outln!("median footprint of a camera pixel on the monitor: not measured (it needs --spp 2 or more)");
    } else {
        outln!(
            "median footprint of a camera pixel on the monitor: {:.1} monitor pixels through the glass (2 refractions), {:.2} directly",
            r.median_footprint_px,
            r.direct_footprint_px
        );
    }
    if a.transport == Transport::Physical {
        outln!(
            "ghosts: {:.2} % of the light the object pixels receive came through a reflection ({:.2} % more was dropped: trapped or fainter than 1e-4)",
            100.0 * r.ghost_share,
            100.0 * r.dropped_share
        );
    }
    Ok(())
}
