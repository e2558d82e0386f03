//! `glasscan calibrate camera|screen|turntable`.

use std::path::PathBuf;

use super::common::bar;
use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};

use glasscan::calibrate::board::{read_images, Board};
use glasscan::calibrate::camera::{calibrate_camera, CameraOptions, OUTLIER_FACTOR};
use glasscan::calibrate::screen;
use glasscan::calibrate::turntable::{calibrate_turntable, Fitted};
use glasscan::rig::calib_io;
use glasscan::scan::ScanConfig;
use glasscan::util::paths::{ensure_extension, ensure_output_spares_inputs};

#[derive(Subcommand, Debug)]
pub enum CalibrateCommand {
    /// Intrinsics and distortion from chessboard images (OpenCV calibrateCamera).
    Camera(CameraArgs),
    /// The monitor's pose from the scan's background capture (decoded Gray code, PnP).
    Screen(ScreenArgs),
    /// The turntable axis from a chessboard turned on it to known angles.
    Turntable(TurntableArgs),
}

/// The chessboard, shared by the camera and turntable steps.
#[derive(Args, Debug)]
pub struct BoardArgs {
    /// Images of the board: a glob pattern (quote it), e.g. 'calib/left*.jpg'.
    #[arg(long)]
    pub images: String,
    /// Inner corners of the board, COLSxROWS (9x6 for a board of 10×7 squares).
    #[arg(long, value_parser = Board::parse_size)]
    pub board: (u32, u32),
    /// Size of a board square, mm.
    #[arg(long = "square-mm", value_parser = super::common::positive)]
    pub square_mm: f64,
}

impl BoardArgs {
    fn board(&self) -> Result<Board> {
        if !(self.square_mm > 0.0 && self.square_mm.is_finite()) {
            bail!("--square-mm {}: a square size is positive", self.square_mm);
        }
        Ok(Board {
            cols: self.board.0,
            rows: self.board.1,
            square_mm: self.square_mm,
        })
    }
}

#[derive(Args, Debug)]
pub struct CameraArgs {
    #[command(flatten)]
    pub board: BoardArgs,
    /// Hold fx/fy at 1 (square pixels).
    #[arg(long = "fix-aspect-ratio")]
    pub fix_aspect_ratio: bool,
    /// Assume no tangential distortion (p1 = p2 = 0).
    #[arg(long = "zero-tangent")]
    pub zero_tangent: bool,
    /// Hold k3 at 0 (advised for narrow lenses: the fit reports k3 in the hundreds otherwise).
    #[arg(long = "fix-k3")]
    pub fix_k3: bool,
    /// Keep every image in the fit: without it, the images a first fit finds outliers (error
    /// above 2.5 × the median image's) are left out and the camera fitted again, when they are
    /// at most a quarter of the boards found.
    #[arg(long = "keep-outliers")]
    pub keep_outliers: bool,
    /// Write the camera file even when the fit is outside the trusted limits (a warning then).
    #[arg(long)]
    pub force: bool,
    /// The camera file to write (OpenCV FileStorage YAML, the keys of OpenCV's sample).
    #[arg(short, long, visible_alias = "out", default_value = "camera.yml")]
    pub output: PathBuf,
}

#[derive(Args, Debug)]
pub struct ScreenArgs {
    /// The scan folder: scan.toml, the camera file, captures/background/.
    pub scan: PathBuf,
    /// Monitor pixel pitch, mm (default: the scan's current screen file's).
    #[arg(long = "pitch-mm", value_parser = super::common::positive)]
    pub pitch_mm: Option<f64>,
    /// The screen file to write (default: the one scan.toml names).
    #[arg(short, long, visible_alias = "out")]
    pub output: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct TurntableArgs {
    #[command(flatten)]
    pub board: BoardArgs,
    /// Turntable angle of each image (degrees, comma-separated, in the images' name order).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub angles: Vec<f64>,
    /// The camera's calibration file.
    #[arg(long)]
    pub camera: PathBuf,
    /// The monitor's pose (screen.yml from `calibrate screen`): an axis that lands behind it
    /// shows a wrong --square-mm.
    #[arg(long)]
    pub screen: Option<PathBuf>,
    /// Fit the corners alone, without the points along the board's grid lines (for a board
    /// whose squares are not plain black and white, e.g. printed over).
    #[arg(long)]
    pub corners_only: bool,
    /// Write the turntable file even when the fit is outside the trusted limits (a warning then).
    #[arg(long)]
    pub force: bool,
    /// The turntable file to write.
    #[arg(short, long, visible_alias = "out", default_value = "turntable.yml")]
    pub output: PathBuf,
}

pub fn run(c: &CalibrateCommand) -> Result<()> {
    match c {
        CalibrateCommand::Camera(a) => camera(a),
        CalibrateCommand::Screen(a) => screen(a),
        CalibrateCommand::Turntable(a) => turntable(a),
    }
}

/// Refuses a fit outside the trusted limits (`problem`), or with `force` only warns.
fn check_fit(problem: Option<String>, force: bool, what: &str) -> Result<()> {
    match problem {
        None => Ok(()),
        Some(p) if force => {
            eprintln!("warning: {p}; written anyway (--force)");
            Ok(())
        }
        Some(p) => bail!("{p}; the {what} file is not written (--force writes it anyway)"),
    }
}

/// The image files of a board set: inputs that no output may overwrite.
fn image_paths(images: &[glasscan::calibrate::board::BoardImage]) -> Vec<&std::path::Path> {
    images.iter().map(|i| i.path.as_path()).collect()
}

fn camera(a: &CameraArgs) -> Result<()> {
    let board = a.board.board()?;
    ensure_extension(&a.output, "--output", &["yml", "yaml"])?;
    let (images, size) = read_images(&a.board.images)?;
    ensure_output_spares_inputs(&a.output, "--output", &image_paths(&images))?;
    let o = CameraOptions {
        fix_aspect_ratio: a.fix_aspect_ratio,
        zero_tangent: a.zero_tangent,
        fix_k3: a.fix_k3,
        keep_outliers: a.keep_outliers,
    };
    let b = bar("corners", images.len());
    let cal = calibrate_camera(&images, size, &board, &o, |_| b.inc(1))?;
    b.finish_and_clear();
    for p in &cal.skipped {
        eprintln!("warning: {}: board not found, image skipped", p.display());
    }
    for v in &cal.views {
        let flag = if v.outlier {
            format!("  <- outlier (error > {OUTLIER_FACTOR} × the median): check the image, or leave it out")
        } else {
            String::new()
        };
        outln!("{:>8.3} px  {}{flag}", v.error_px, v.path.display());
    }
    for v in &cal.left_out {
        outln!(
            "{:>8.3} px  {}  <- left out: error > {OUTLIER_FACTOR} × the median in a first fit (--keep-outliers keeps it)",
            v.error_px,
            v.path.display()
        );
    }
    let c = &cal.camera;
    check_fit(cal.problem(), a.force, "camera")?;
    calib_io::write_camera(&a.output, c, cal.rms_px, Some(&cal.record))?;
    outln!(
        "{} of {} images used{}; fx {:.3} fy {:.3} cx {:.3} cy {:.3} px; k1 {:.5} k2 {:.5} p1 {:.6} p2 {:.6} k3 {:.5}; RMS reprojection error {:.4} px",
        cal.views.len(),
        images.len(),
        match cal.left_out.len() {
            0 => String::new(),
            n => format!(" ({n} left out as outliers)"),
        },
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        c.dist[0],
        c.dist[1],
        c.dist[2],
        c.dist[3],
        c.dist[4],
        cal.rms_px
    );
    outln!("wrote {}", a.output.display());
    Ok(())
}

fn screen(a: &ScreenArgs) -> Result<()> {
    let config = ScanConfig::load(&a.scan)?;
    let camera = calib_io::read_camera(&a.scan.join(&config.calibration.camera))?;
    let screen_file = a.scan.join(&config.calibration.screen);
    let pitch_mm = match a.pitch_mm {
        Some(p) if p > 0.0 && p.is_finite() => p,
        Some(p) => bail!("--pitch-mm {p}: a pixel pitch is positive"),
        None => calib_io::read_screen(&screen_file)
            .map(|s| s.pitch_mm)
            .with_context(|| {
                "give the monitor's pixel pitch with --pitch-mm (no screen file to take it from)"
            })?,
    };
    let out = a.output.clone().unwrap_or(screen_file);
    ensure_extension(&out, "--output", &["yml", "yaml"])?;
    let inputs = [
        a.scan.join("scan.toml"),
        a.scan.join(&config.calibration.camera),
        glasscan::scan::background_dir(&a.scan),
    ];
    ensure_output_spares_inputs(&out, "--output", &inputs)?;
    let cal = screen::from_background(&a.scan, &config, &camera, pitch_mm)?;
    calib_io::write_screen(&out, &cal.screen)?;
    let t = cal.screen.pose.translation.vector;
    let n = cal.screen.pose.rotation * nalgebra::Vector3::z();
    outln!(
        "monitor decoded in {:.1} % of the image ({:.1} % to every bit; median cell {:.0} monitor px); pose fitted on {} of its {} pixels and {} stripe edges",
        100.0 * cal.decoded_share,
        100.0 * cal.complete_share,
        cal.median_cell_px,
        cal.fitted,
        cal.points,
        cal.edges
    );
    let edges = if cal.edges > 0 {
        format!(
            "; across the stripe edges median {:.3} monitor px",
            cal.edge_median_residual_px
        )
    } else {
        String::new()
    };
    outln!(
        "residuals: median {:.3}, 95 % {:.3} monitor px; RMS {:.2} cell standard deviations{edges}",
        cal.median_residual_px,
        cal.p95_residual_px,
        cal.rms_normalised
    );
    if let Some(w) = &cal.warning {
        eprintln!("warning: {w}");
    }
    outln!(
        "pixel (0, 0) at ({:.2}, {:.2}, {:.2}) mm, normal ({:.4}, {:.4}, {:.4}) (camera frame)",
        t.x,
        t.y,
        t.z,
        n.x,
        n.y,
        n.z
    );
    outln!("wrote {}", out.display());
    Ok(())
}

fn turntable(a: &TurntableArgs) -> Result<()> {
    let board = a.board.board()?;
    ensure_extension(&a.output, "--output", &["yml", "yaml"])?;
    let camera = calib_io::read_camera(&a.camera)?;
    let screen = a.screen.as_deref().map(calib_io::read_screen).transpose()?;
    let (images, size) = read_images(&a.board.images)?;
    let mut inputs = image_paths(&images);
    inputs.push(&a.camera);
    inputs.extend(a.screen.as_deref());
    ensure_output_spares_inputs(&a.output, "--output", &inputs)?;
    if size != (camera.width, camera.height) {
        bail!(
            "the images are {}×{} but the camera ({}) takes {}×{}",
            size.0,
            size.1,
            a.camera.display(),
            camera.width,
            camera.height
        );
    }
    let fitted = if a.corners_only {
        Fitted::Corners
    } else {
        Fitted::CornersAndEdges
    };
    let cal = calibrate_turntable(&images, &a.angles, &board, &camera, fitted)?;
    for p in &cal.skipped {
        eprintln!("warning: {}: board not found, image skipped", p.display());
    }
    for v in &cal.views {
        outln!(
            "{:>8.2}°  angle residual {:+.4}°  {:.3} px  {}",
            v.angle_deg,
            v.angle_residual_deg,
            v.rms_px,
            v.path.display()
        );
    }
    let behind = screen.and_then(|s| glasscan::calibrate::axis_beyond_monitor(&cal.axis_point, &s));
    check_fit(cal.problem().or(behind), a.force, "turntable")?;
    calib_io::write_turntable_axis(&a.output, &cal.axis_point, &cal.axis_dir)?;
    let (p, d) = (cal.axis_point, cal.axis_dir);
    outln!(
        "axis through ({:.2}, {:.2}, {:.2}) mm along ({:.5}, {:.5}, {:.5}) (camera frame); RMS reprojection error {:.3} px over {} images",
        p.x,
        p.y,
        p.z,
        d.x,
        d.y,
        d.z,
        cal.rms_px,
        cal.views.len()
    );
    if cal.edges > 0 {
        outln!(
            "{} points along the grid lines, {:.3} px RMS from them",
            cal.edges,
            cal.edge_rms_px
        );
    }
    outln!("wrote {}", a.output.display());
    Ok(())
}
