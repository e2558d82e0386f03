//! `glasscan capture SCAN`: the patterns on the monitor, grabbed by the camera, into the scan
//! folder's captures.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use super::common::bar;
use glasscan::capture::{capture_scan, CameraSource, CaptureOptions};
use glasscan::rig::calib_io;
use glasscan::scan::ScanConfig;

#[derive(Args, Debug)]
pub struct CaptureArgs {
    /// The scan folder: scan.toml (views, patterns) and the camera file; the captures go into
    /// its captures/ folder.
    pub scan: PathBuf,
    /// The camera: a device index (0 is the first), or a recorded image sequence or video
    /// (frames/%04d.png) whose frame k is the capture's k-th image.
    #[arg(long, value_parser = CameraSource::parse)]
    pub camera: CameraSource,
    /// Top-left corner of the rig's monitor on the desktop, X,Y pixels (`xrandr` lists them).
    #[arg(long = "monitor-origin", value_parser = parse_origin, default_value = "0,0")]
    pub monitor_origin: (i32, i32),
    /// Wait after showing each pattern before grabbing, milliseconds (the monitor's response
    /// and the camera's exposure).
    #[arg(long = "settle-ms", default_value_t = 300)]
    pub settle_ms: u64,
    /// Frames a device camera grabs and drops after the wait (its buffer holds older frames).
    #[arg(long = "flush-frames", default_value_t = 2)]
    pub flush_frames: u32,
    /// Command that turns the turntable, run with `sh -c` before each view, `{angle}` replaced
    /// by the view's angle in degrees and `{view}` by its index; without it you are asked to
    /// turn the object and press Enter.
    #[arg(long = "turn-cmd")]
    pub turn_cmd: Option<String>,
    /// Capture the background set (captures/background/, object removed) instead of the views.
    #[arg(long)]
    pub background: bool,
}

fn parse_origin(s: &str) -> Result<(i32, i32), String> {
    let bad = || format!("'{s}': expected X,Y in pixels, e.g. 1920,0");
    let (x, y) = s.split_once(',').ok_or_else(bad)?;
    Ok((
        x.trim().parse().map_err(|_| bad())?,
        y.trim().parse().map_err(|_| bad())?,
    ))
}

pub fn run(a: &CaptureArgs) -> Result<()> {
    let config = ScanConfig::load(&a.scan)?;
    let camera_file = a.scan.join(&config.calibration.camera);
    let expect_size = camera_file
        .is_file()
        .then(|| calib_io::read_camera(&camera_file))
        .transpose()?
        .map(|c| (c.width, c.height));
    let o = CaptureOptions {
        camera: a.camera.clone(),
        monitor_origin: a.monitor_origin,
        settle_ms: a.settle_ms,
        flush_frames: a.flush_frames,
        turn_cmd: a.turn_cmd.clone(),
        background: a.background,
        expect_size,
    };
    let b = bar("capture", 0);
    let progress = |done: usize, total: usize| {
        b.set_length(total as u64);
        b.set_position(done as u64);
    };
    let warn = |w: &str| b.suspend(|| eprintln!("warning: {w}"));
    let report = capture_scan(&a.scan, &config, &o, &progress, &warn)?;
    b.finish_and_clear();
    if let Some((dir, name)) = &report.resumed_at {
        if report.kept > 0 {
            outln!(
                "resumed at {} ({} images were there)",
                dir.join(name).display(),
                report.kept
            );
        }
    }
    if let Some(e) = &report.exposure {
        outln!(
            "exposure: white − black {:.0} grey levels, {:.2} % saturated",
            e.contrast,
            100.0 * e.saturated
        );
    }
    outln!(
        "captured {} images ({} already there) into {}",
        report.grabbed,
        report.kept,
        a.scan.join("captures").display()
    );
    Ok(())
}
