//! `glasscan capture`: shows each pattern full-screen on the rig's monitor (OpenCV highgui),
//! grabs it with the camera (OpenCV videoio), and writes the scan folder's captures: every view
//! of `scan.toml` into `captures/view_NNN/`, turning the turntable between views (a command, or
//! a prompt), or the background set (`captures/background/`, the object removed).
//!
//! Each image is written atomically as it is grabbed, so an interrupted capture resumes at the
//! first missing image. Within a view, white and black are shown first: their contrast is the
//! exposure check, made on the first view a run captures, before the patterns.
//!
//! The camera is a device index, or a file pattern or video whose frame k is the k-th image of
//! the capture (views in order, each in [`capture_order`]): a recorded capture replays exactly,
//! which is how the tests drive this module.

mod camera;
mod exposure;
mod window;

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};

pub use camera::CameraSource;
pub use exposure::Exposure;

use crate::patterns::capture_names;
use crate::scan::{background_dir, ScanConfig};
use crate::util::image::write_png;

/// How to capture.
#[derive(Clone, Debug)]
pub struct CaptureOptions {
    pub camera: CameraSource,
    /// Top-left corner of the rig's monitor on the desktop, pixels (the window goes there).
    pub monitor_origin: (i32, i32),
    /// Wait after showing a pattern before grabbing, milliseconds.
    pub settle_ms: u64,
    /// Frames grabbed and dropped after the wait (a device camera's buffered frames).
    pub flush_frames: u32,
    /// Run between views (`sh -c`), with `{angle}` (degrees) and `{view}` replaced; without
    /// it the user is asked to turn the object and press Enter.
    pub turn_cmd: Option<String>,
    /// Capture the background set instead of the views.
    pub background: bool,
    /// The camera's image size, pixels (from the scan's camera file), when known.
    pub expect_size: Option<(u32, u32)>,
}

/// What a capture did.
#[derive(Clone, Debug, Default)]
pub struct CaptureReport {
    /// Images grabbed by this run, and those already there.
    pub grabbed: usize,
    pub kept: usize,
    /// Where this run began: (folder, image name), when anything was missing.
    pub resumed_at: Option<(PathBuf, String)>,
    /// The exposure check of the first set this run captured.
    pub exposure: Option<Exposure>,
}

/// One folder of captures to fill: a view (with its turntable angle) or the background.
struct Set {
    dir: PathBuf,
    view: Option<(usize, f64)>,
}

/// The order images are shown and grabbed in: white and black first (the exposure check),
/// then the Gray code, then the phase shift; names as in [`capture_names`].
pub fn capture_order(config: &ScanConfig) -> Vec<String> {
    let mut names = capture_names(&config.graycode(), config.patterns.phase_shift.as_ref());
    let white = names
        .iter()
        .position(|n| n == "white.png")
        .expect("the Gray code has a white image");
    let shadow: Vec<String> = names.drain(white..white + 2).collect();
    shadow.into_iter().chain(names).collect()
}

/// Captures the scan in `dir` (described by `config`), resuming where an earlier run stopped;
/// `progress` gets (images done, images in all), `warn` advice as soon as it arises.
pub fn capture_scan(
    dir: &Path,
    config: &ScanConfig,
    o: &CaptureOptions,
    progress: &dyn Fn(usize, usize),
    warn: &dyn Fn(&str),
) -> Result<CaptureReport> {
    let names = capture_order(config);
    let sets = sets(dir, config, o.background);
    let total = sets.len() * names.len();
    let mut report = CaptureReport::default();
    let missing = first_missing(&sets, &names);
    report.kept = sets
        .iter()
        .flat_map(|set| names.iter().map(move |n| set.dir.join(n)))
        .filter(|p| p.is_file())
        .count();
    let Some((first_set, first_image)) = missing else {
        return Ok(report);
    };
    report.resumed_at = Some((sets[first_set].dir.clone(), names[first_image].clone()));
    let images = monitor_images(config, &names)?;
    let mut window = window::PatternWindow::open(
        o.monitor_origin,
        (config.patterns.width, config.patterns.height),
    )?;
    let mut camera = camera::Camera::open(&o.camera, o.flush_frames, o.expect_size)?;
    if let Some(w) = window.size_warning() {
        warn(&w);
    }
    for (s, set) in sets.iter().enumerate().skip(first_set) {
        let todo: Vec<usize> = (0..names.len())
            .filter(|&i| !set.dir.join(&names[i]).is_file())
            .collect();
        if todo.is_empty() {
            continue;
        }
        turn_to(set, o)?;
        std::fs::create_dir_all(&set.dir)
            .with_context(|| format!("cannot create {}", set.dir.display()))?;
        for i in todo {
            let frame = s * names.len() + i;
            window.show(&images[i], Duration::from_millis(o.settle_ms))?;
            let img = camera.grab(frame).with_context(|| {
                format!(
                    "{}: no image from the camera (frame {frame}); rerun the same command to resume here",
                    set.dir.join(&names[i]).display()
                )
            })?;
            write_png(&set.dir.join(&names[i]), &img)?;
            report.grabbed += 1;
            progress(report.kept + report.grabbed, total);
            if report.exposure.is_none() && names[i] == "black.png" {
                report.exposure = Some(check_exposure(set, warn)?);
            }
        }
    }
    Ok(report)
}

/// The folders to fill, in order.
fn sets(dir: &Path, config: &ScanConfig, background: bool) -> Vec<Set> {
    if background {
        return vec![Set {
            dir: background_dir(dir),
            view: None,
        }];
    }
    config
        .views
        .angles_deg
        .iter()
        .enumerate()
        .map(|(k, &a)| Set {
            dir: dir.join("captures").join(format!("view_{k:03}")),
            view: Some((k, a)),
        })
        .collect()
}

/// (set, image) of the first image not on disk yet.
fn first_missing(sets: &[Set], names: &[String]) -> Option<(usize, usize)> {
    sets.iter().enumerate().find_map(|(s, set)| {
        names
            .iter()
            .position(|n| !set.dir.join(n).is_file())
            .map(|i| (s, i))
    })
}

/// The images to show, in `names`' order, 8-bit grey, the monitor's size.
fn monitor_images(config: &ScanConfig, names: &[String]) -> Result<Vec<opencv::core::Mat>> {
    let code = config.graycode();
    let mut by_name: std::collections::HashMap<String, opencv::core::Mat> =
        code.file_names().into_iter().zip(code.images()?).collect();
    if let Some(p) = &config.patterns.phase_shift {
        let (w, h) = (code.width, code.height);
        for (i, name) in p.file_names().into_iter().enumerate() {
            let pixels = p.image(i, w, h);
            let mat = opencv::core::Mat::new_rows_cols_with_data(h as i32, w as i32, &pixels)?
                .clone_pointee();
            by_name.insert(name, mat);
        }
    }
    names
        .iter()
        .map(|n| by_name.remove(n).context("a pattern without an image"))
        .collect()
}

/// Turns the turntable to the set's angle: the turn command, or a prompt.
fn turn_to(set: &Set, o: &CaptureOptions) -> Result<()> {
    let Some((view, angle)) = set.view else {
        return Ok(());
    };
    match &o.turn_cmd {
        Some(cmd) => run_turn_command(cmd, view, angle),
        None => prompt_turn(view, angle),
    }
}

fn run_turn_command(cmd: &str, view: usize, angle: f64) -> Result<()> {
    let line = cmd
        .replace("{angle}", &angle.to_string())
        .replace("{view}", &view.to_string());
    let status = std::process::Command::new("sh")
        .arg("-c")
        .arg(&line)
        .status()
        .with_context(|| format!("cannot run the turn command '{line}'"))?;
    if !status.success() {
        bail!(
            "the turn command '{line}' failed ({status}) before view {view}; fix it and rerun the same command to resume"
        );
    }
    Ok(())
}

fn prompt_turn(view: usize, angle: f64) -> Result<()> {
    eprintln!("turn the object to {angle}° (view {view}) and press Enter");
    let mut line = String::new();
    let n = std::io::stdin()
        .read_line(&mut line)
        .context("cannot read standard input")?;
    if n == 0 {
        bail!("standard input is closed: give --turn-cmd, or run the capture in a terminal");
    }
    Ok(())
}

/// The exposure check on the white and black images of `set`, with advice as warnings; an
/// error when the camera does not see the monitor's light at all.
fn check_exposure(set: &Set, warn: &dyn Fn(&str)) -> Result<Exposure> {
    let e = Exposure::measure(&set.dir.join("white.png"), &set.dir.join("black.png"))?;
    if let Some(problem) = e.fatal() {
        bail!("{}: {problem}", set.dir.display());
    }
    for advice in e.advice() {
        warn(&advice);
    }
    Ok(e)
}
