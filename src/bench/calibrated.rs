//! `glasscan bench calibrated`: what calibrating the rig from images costs a reconstruction.
//!
//! For each object it simulates a noisy 72-view scan with a distorting lens and the calibration
//! image sets (`simulate --calibration-images`), decodes it, and calibrates camera, monitor and
//! turntable from the images alone, as a user does (`glasscan calibrate …`; the simulator's true
//! calibration files are read only to report the calibration's errors). The calibrated rig
//! becomes a scan folder of its own beside the true one (`WORK/scans/{object}_calibrated`: the
//! calibrated files, the same decoded data, and the true shape expressed in the calibrated
//! rig's world frame, through the camera frame both share at view 0). Both folders are then
//! reconstructed with the same preset through the pipeline's entry point and evaluated against
//! their own `ground_truth.ply`.
//!
//! Results go to `WORK/calibrated.json` and `WORK/calibrated.md`; a rerun skips the objects the
//! JSON already holds.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{Context, Result};
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use super::reconstruct::{Rig, ScanKind};
use super::ObjectMesh;
use crate::calibrate::board::{read_images, Board};
use crate::calibrate::camera::{calibrate_camera, CameraOptions};
use crate::calibrate::screen;
use crate::calibrate::turntable::{calibrate_turntable, Fitted};
use crate::eval::EvalReport;
use crate::hull::HullOptions;
use crate::mesh::io::{read_mesh, write_mesh};
use crate::reconstruct::config::{Preset, Settings};
use crate::reconstruct::pipeline::{reconstruct_scan, Job};
use crate::reconstruct::{Existing, Progress, Start};
use crate::rig::{calib_io, Camera, Screen};
use crate::scan::Scan;
use crate::simulate::calibration::{CalibrationBoards, Setup};
use crate::simulate::simulated_scan;

/// The lens of the simulated camera, OpenCV's k1 k2 p1 p2 k3: barrel distortion of about 2 % at
/// the image corners of the default 1280×960 camera.
pub const LENS: [f64; 5] = [-0.1, 0.05, 0.0, 0.0, 0.0];

/// What to run.
#[derive(Clone, Debug)]
pub struct CalibratedBenchOptions {
    /// Folder with `{object}_scan.ply`.
    pub meshes: PathBuf,
    /// Scans, runs and results go here.
    pub work: PathBuf,
    pub objects: Vec<String>,
    pub preset: Preset,
    /// The camera and fill of the scans.
    pub rig: Rig,
    /// The printed boards (default: sized with the rig).
    pub boards: CalibrationBoards,
}

/// How far the calibration from images is from the simulator's truth.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CalibrationErrors {
    /// Focal length, relative (%), and principal point, px.
    pub focal_percent: f64,
    pub principal_point_px: f64,
    /// RMS reprojection error of the camera calibration, px.
    pub camera_rms_px: f64,
    /// RMS reprojection error of the turntable fit, px, and its largest angle residual, degrees.
    #[serde(default)]
    pub turntable_rms_px: f64,
    #[serde(default)]
    pub turntable_angle_deg: f64,
    /// Square sides of the camera's and the turntable's boards, mm, and the turntable board's
    /// smallest square side in the images, px.
    #[serde(default)]
    pub camera_square_mm: f64,
    #[serde(default)]
    pub turntable_square_mm: f64,
    #[serde(default)]
    pub turntable_square_px: f64,
    /// The largest distance of a monitor corner from its true place, mm.
    pub monitor_corner_mm: f64,
    /// Angle between the calibrated and the true monitor normals, degrees.
    pub monitor_normal_deg: f64,
    /// Angle between the axes, degrees, and the largest distance of the calibrated axis from
    /// the true one over the object's height (±100 mm about the true axis point), mm.
    pub axis_direction_deg: f64,
    pub axis_offset_mm: f64,
}

/// One object: the calibration's errors and both reconstructions.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CalibratedRun {
    pub object: String,
    pub preset: Preset,
    #[serde(default)]
    pub rig: Rig,
    pub calibration: CalibrationErrors,
    /// Accuracy and completeness (mm) with the true calibration files.
    pub true_accuracy_mm: f64,
    pub true_completeness_mm: f64,
    /// The same with the calibration from images.
    pub calibrated_accuracy_mm: f64,
    pub calibrated_completeness_mm: f64,
    /// Seconds of the whole reconstruction (hull, stages, evaluation) of each.
    pub true_seconds: f64,
    pub calibrated_seconds: f64,
}

/// Runs every object `WORK/calibrated.json` does not hold yet.
pub fn run_calibrated_bench(
    o: &CalibratedBenchOptions,
    progress: &dyn Progress,
    log: &dyn Fn(&str),
) -> Result<Vec<CalibratedRun>> {
    std::fs::create_dir_all(&o.work)
        .with_context(|| format!("cannot create {}", o.work.display()))?;
    let mut results: Vec<CalibratedRun> = super::read_runs(&o.work.join("calibrated.json"))?;
    for object in &o.objects {
        if results
            .iter()
            .any(|r| r.object == *object && r.preset == o.preset && r.rig == o.rig)
        {
            continue;
        }
        let mesh = ObjectMesh::locate(&o.meshes, object)?;
        let r = run_object(o, object, &mesh, progress, log)?;
        results.push(r);
        write_results(&o.work, &results)?;
    }
    write_results(&o.work, &results)?;
    Ok(results)
}

/// The scan, its calibration from images, and both reconstructions of one object.
fn run_object(
    o: &CalibratedBenchOptions,
    object: &str,
    mesh: &ObjectMesh,
    progress: &dyn Progress,
    log: &dyn Fn(&str),
) -> Result<CalibratedRun> {
    let scans = o.work.join("scans");
    let suffix = o.rig.folder_suffix();
    let true_dir = scans.join(format!("{object}_true{suffix}"));
    ensure_scan(mesh, &true_dir, o, log)?;
    let truth_scan = Scan::open(&true_dir)?;
    log(&format!("{object}: calibrating from the images"));
    let calibrated_dir = scans.join(format!("{object}_calibrated{suffix}"));
    let calibration = calibrated_scan(&truth_scan, &calibrated_dir)?;
    let calibrated_scan = Scan::open(&calibrated_dir)?;
    log(&format!("{object}: {}", describe(&calibration)));
    let runs = o.work.join("runs");
    let (t, t_s) = reconstruct(
        &truth_scan,
        o.preset,
        &runs.join(format!("{object}_true{suffix}")),
        progress,
    )?;
    log(&format!(
        "{object}, true calibration: accuracy {:.3} mm, completeness {:.3} mm, {t_s:.0} s",
        t.accuracy_mm, t.completeness_mm
    ));
    let (c, c_s) = reconstruct(
        &calibrated_scan,
        o.preset,
        &runs.join(format!("{object}_calibrated{suffix}")),
        progress,
    )?;
    log(&format!(
        "{object}, calibrated from images: accuracy {:.3} mm, completeness {:.3} mm, {c_s:.0} s",
        c.accuracy_mm, c.completeness_mm
    ));
    Ok(CalibratedRun {
        object: object.into(),
        preset: o.preset,
        rig: o.rig,
        calibration,
        true_accuracy_mm: t.accuracy_mm,
        true_completeness_mm: t.completeness_mm,
        calibrated_accuracy_mm: c.accuracy_mm,
        calibrated_completeness_mm: c.completeness_mm,
        true_seconds: t_s,
        calibrated_seconds: c_s,
    })
}

/// Simulates the noisy scan with a distorting lens and the calibration images, and decodes it,
/// unless `dir` already holds it.
fn ensure_scan(
    object: &ObjectMesh,
    dir: &Path,
    o: &CalibratedBenchOptions,
    log: &dyn Fn(&str),
) -> Result<()> {
    if dir.join("decoded").join("summary.json").is_file() {
        return Ok(());
    }
    let mesh = object.read()?;
    let options = crate::simulate::SimulateOptions {
        distortion: LENS,
        calibration_images: true,
        boards: o.boards,
        normals: object.normals(),
        ..ScanKind::Noisy.simulate_options(&o.rig.for_object(&mesh)?)
    };
    log(&format!(
        "simulating {} with calibration images into {}",
        object.describe(),
        dir.display()
    ));
    let t0 = Instant::now();
    simulated_scan(&mesh, dir, &options, |_| ())?;
    log(&format!("  {:.1} s", t0.elapsed().as_secs_f64()));
    Ok(())
}

/// Calibrates the rig of `truth` from its images into the scan folder `dir` (recreated): the
/// calibrated files, `scan.toml`, a link to the decoded data, and the true shape in the
/// calibrated world frame. Returns the calibration's errors against the truth.
fn calibrated_scan(truth: &Scan, dir: &Path) -> Result<CalibrationErrors> {
    let setup: Setup = serde_json::from_str(
        &std::fs::read_to_string(truth.dir.join("calibration").join("setup.json"))
            .context("the scan has no calibration/setup.json (simulate --calibration-images)")?,
    )?;
    let (cols, rows) = Board::parse_size(&setup.board).map_err(anyhow::Error::msg)?;
    let board = |square_mm| Board {
        cols,
        rows,
        square_mm,
    };
    let images =
        |set: &str| read_images(&format!("{}/calibration/{set}/*.png", truth.dir.display()));
    let (camera_images, size) = images("camera")?;
    let camera_options = CameraOptions {
        zero_tangent: true,
        ..Default::default()
    };
    let cam = calibrate_camera(
        &camera_images,
        size,
        &board(setup.camera_square_mm),
        &camera_options,
        |_| (),
    )?;
    let monitor = screen::from_background(
        &truth.dir,
        &truth.config,
        &cam.camera,
        truth.screen.pitch_mm,
    )?;
    let (turntable_images, _) = images("turntable")?;
    let axis = calibrate_turntable(
        &turntable_images,
        &setup.turntable_angles_deg,
        &board(setup.turntable_square_mm),
        &cam.camera,
        Fitted::CornersAndEdges,
    )?;
    if let Some(p) = cam.problem().or(axis.problem()) {
        anyhow::bail!("{}: {p}", truth.dir.display());
    }
    write_scan_folder(
        truth,
        dir,
        &cam.camera,
        cam.rms_px,
        &monitor.screen,
        (&axis.axis_point, &axis.axis_dir),
    )?;
    let calibrated = Scan::open(dir)?;
    write_truth_in_frame(truth, &calibrated)?;
    let worst_angle = axis
        .views
        .iter()
        .map(|v| v.angle_residual_deg.abs())
        .fold(0.0, f64::max);
    Ok(CalibrationErrors {
        turntable_rms_px: axis.rms_px,
        turntable_angle_deg: worst_angle,
        camera_square_mm: setup.camera_square_mm,
        turntable_square_mm: setup.turntable_square_mm,
        turntable_square_px: axis.square_px,
        ..errors(truth, &calibrated, cam.rms_px)
    })
}

/// A scan folder with the calibrated files beside a link to `truth`'s decoded data.
fn write_scan_folder(
    truth: &Scan,
    dir: &Path,
    camera: &Camera,
    camera_rms_px: f64,
    monitor: &Screen,
    (axis_point, axis_dir): (&Point3<f64>, &nalgebra::Unit<nalgebra::Vector3<f64>>),
) -> Result<()> {
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("cannot clear {}", dir.display()))?;
    }
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let toml = truth.dir.join("scan.toml");
    std::fs::copy(&toml, dir.join("scan.toml"))
        .with_context(|| format!("cannot copy {} into {}", toml.display(), dir.display()))?;
    let c = &truth.config.calibration;
    calib_io::write_camera(&dir.join(&c.camera), camera, camera_rms_px, None)?;
    calib_io::write_screen(&dir.join(&c.screen), monitor)?;
    calib_io::write_turntable_axis(&dir.join(&c.turntable), axis_point, axis_dir)?;
    let decoded = std::fs::canonicalize(truth.dir.join("decoded"))?;
    std::os::unix::fs::symlink(decoded, dir.join("decoded"))
        .with_context(|| format!("cannot link the decoded data into {}", dir.display()))
}

/// The world → world map from `truth`'s frame to `calibrated`'s, through the camera frame at
/// view 0 (the one frame both rigs share).
fn world_to_world(truth: &Scan, calibrated: &Scan) -> Isometry3<f64> {
    calibrated.view_poses()[0].inverse() * truth.view_poses()[0]
}

/// `calibrated/ground_truth.ply`: the true shape in the calibrated rig's world frame.
fn write_truth_in_frame(truth: &Scan, calibrated: &Scan) -> Result<()> {
    let map = world_to_world(truth, calibrated);
    let mut mesh = read_mesh(&truth.dir.join("ground_truth.ply"))?;
    for v in &mut mesh.positions {
        *v = map * *v;
    }
    write_mesh(&calibrated.dir.join("ground_truth.ply"), &mesh)?;
    Ok(())
}

/// The calibration's errors against the simulator's truth.
fn errors(truth: &Scan, calibrated: &Scan, camera_rms_px: f64) -> CalibrationErrors {
    let (t, c) = (&truth.camera, &calibrated.camera);
    let (ts, cs) = (&truth.screen, &calibrated.screen);
    let corners = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)].map(|(a, b)| {
        let (u, v) = (a * ts.width_px as f64, b * ts.height_px as f64);
        (ts.point(u, v) - cs.point(u, v)).norm()
    });
    let normal = |s: &Screen| s.pose.rotation * nalgebra::Vector3::z();
    let (ta, ca) = (&truth.turntable, &calibrated.turntable);
    let off_axis = |p: Point3<f64>| {
        let d = p - ca.axis_point;
        (d - ca.axis_dir.into_inner() * d.dot(&ca.axis_dir)).norm()
    };
    CalibrationErrors {
        focal_percent: 100.0 * (c.fx / t.fx - 1.0),
        principal_point_px: ((c.cx - t.cx).powi(2) + (c.cy - t.cy).powi(2)).sqrt(),
        camera_rms_px,
        monitor_corner_mm: corners.into_iter().fold(0.0, f64::max),
        monitor_normal_deg: normal(ts).angle(&normal(cs)).to_degrees(),
        axis_direction_deg: ta.axis_dir.angle(&ca.axis_dir).to_degrees(),
        axis_offset_mm: [-100.0, 100.0]
            .map(|h| off_axis(ta.axis_point + ta.axis_dir.into_inner() * h))
            .into_iter()
            .fold(0.0, f64::max),
        turntable_rms_px: 0.0,
        turntable_angle_deg: 0.0,
        camera_square_mm: 0.0,
        turntable_square_mm: 0.0,
        turntable_square_px: 0.0,
    }
}

fn describe(e: &CalibrationErrors) -> String {
    format!(
        "focal {:+.3} %, principal point {:.2} px, monitor corners ≤ {:.3} mm, normal {:.4}°, axis {:.4}° / {:.3} mm",
        e.focal_percent,
        e.principal_point_px,
        e.monitor_corner_mm,
        e.monitor_normal_deg,
        e.axis_direction_deg,
        e.axis_offset_mm
    )
}

/// A reconstruction of `scan` from its visual hull with `preset` into `dir` (recreated), and its
/// evaluation against the scan's `ground_truth.ply`; seconds of the whole.
fn reconstruct(
    scan: &Scan,
    preset: Preset,
    dir: &Path,
    progress: &dyn Progress,
) -> Result<(EvalReport, f64)> {
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("cannot clear {}", dir.display()))?;
    }
    let t0 = Instant::now();
    let job = Job {
        scan,
        views: (0..scan.config.views.angles_deg.len()).collect(),
        settings: Settings::preset(preset),
        start: Start::Hull(HullOptions::default()),
        out: dir,
        existing: Existing::Nothing,
    };
    let outcome = reconstruct_scan(job, progress, &AtomicBool::new(false))?;
    let e = outcome
        .evaluation
        .context("the scan has no ground_truth.ply to evaluate against")?;
    Ok((e, t0.elapsed().as_secs_f64()))
}

/// Writes calibrated.json and calibrated.md.
fn write_results(work: &Path, results: &[CalibratedRun]) -> Result<()> {
    let mut md = String::from(
        "| object | camera, fill | preset | boards mm (turntable px) | focal % | principal point px | monitor corner mm | monitor normal ° | axis ° | axis mm | turntable RMS px | true calibration acc./compl. mm | from images acc./compl. mm | difference mm |\n|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in results {
        let e = &r.calibration;
        md += &format!(
            "| {} | {}×{}, {} | {} | {} / {} ({:.1}) | {:+.3} | {:.2} | {:.3} | {:.4} | {:.4} | {:.3} | {:.3} | {:.3} / {:.3} | {:.3} / {:.3} | {:+.3} |\n",
            r.object,
            r.rig.width,
            r.rig.height,
            r.rig.fill,
            r.preset,
            e.camera_square_mm,
            e.turntable_square_mm,
            e.turntable_square_px,
            e.focal_percent,
            e.principal_point_px,
            e.monitor_corner_mm,
            e.monitor_normal_deg,
            e.axis_direction_deg,
            e.axis_offset_mm,
            e.turntable_rms_px,
            r.true_accuracy_mm,
            r.true_completeness_mm,
            r.calibrated_accuracy_mm,
            r.calibrated_completeness_mm,
            r.calibrated_accuracy_mm - r.true_accuracy_mm
        );
    }
    super::write_runs(
        &work.join("calibrated.json"),
        results,
        &work.join("calibrated.md"),
        &md,
    )
}
