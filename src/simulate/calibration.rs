//! Calibration image sets with known truth (`simulate --calibration-images`):
//!
//! - `calibration/camera/board_NN.png`: a chessboard at distances from 0.45 to 1.2 × the camera's
//!   distance to the axis, tilted up to ±55°, at varied places in the image, seen through the
//!   camera's lens model (its distortion included);
//! - `calibration/turntable/board_NN.png`: a board standing on the turntable, beside the axis,
//!   turned to each angle of `calibration/setup.json`;
//! - the background capture (`captures/background/`) for the monitor pose;
//! - `calibration/setup.json`: the boards (inner corners, square sizes) and the turntable angles,
//!   with the commands that calibrate from them (into the scan's own rig files);
//! - `calibration/truth/`: the rig's true camera, screen and turntable files, kept there.
//!
//! Images are area-sampled (6 × 6 per pixel), with the scan's sensor noise and blur.

use std::path::Path;

use anyhow::{bail, Context, Result};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{write_sensor_image, SimulateOptions};
use crate::calibrate::board::Board;
use crate::rig::{calib_io, Camera};
use crate::scan::Scan;
use crate::util::scatter_seed;

/// The boards of the calibration sets, as a user prints them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibrationBoards {
    /// Inner corners per row and per column.
    pub cols: u32,
    pub rows: u32,
    /// Square side of the camera's board, mm; `None`: sized with the rig (the board with its
    /// margins spans 0.6 of the image width at the axis).
    pub camera_square_mm: Option<f64>,
    /// Square side of the board standing on the turntable, mm; `None`: the camera's board when
    /// that is given, else sized with the rig (0.5 of the image width).
    pub turntable_square_mm: Option<f64>,
    /// Images of the camera's board.
    pub camera_images: usize,
}

impl Default for CalibrationBoards {
    fn default() -> Self {
        Self {
            cols: 9,
            rows: 6,
            camera_square_mm: None,
            turntable_square_mm: None,
            camera_images: 60,
        }
    }
}

/// The most images of the camera's board a simulation renders.
pub const MAX_CAMERA_IMAGES: usize = 500;
/// Turntable angles of the board standing on it, degrees.
pub const TURNTABLE_ANGLES: [f64; 9] = [-40.0, -30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0, 40.0];
/// Grey levels of the board's black and white squares and of what lies behind it.
const BLACK: f32 = 25.0;
const WHITE: f32 = 225.0;
const BEHIND: f32 = 90.0;

/// What `calibration/setup.json` records.
#[derive(Serialize, Deserialize)]
pub struct Setup {
    /// Inner corners of both boards, COLSxROWS.
    pub board: String,
    /// Square sizes of the camera's and the turntable's boards, mm.
    pub camera_square_mm: f64,
    pub turntable_square_mm: f64,
    /// Turntable angle of each turntable image, in name order, degrees.
    pub turntable_angles_deg: Vec<f64>,
    /// The `glasscan calibrate` commands that calibrate from the images.
    pub commands: Vec<String>,
}

/// Renders the calibration sets of `scan` (its camera, turntable and background) into
/// `scan.dir/calibration`; the commands in `setup.json` name the scan's final folder `out`.
pub fn write_calibration_images(scan: &Scan, out: &Path, o: &SimulateOptions) -> Result<()> {
    let cam = &scan.camera;
    let (board, small) = boards(cam, o);
    let dir = scan.dir.join("calibration");
    let seed = scatter_seed(o.seed);
    let poses = camera_board_poses(cam, &board, o, seed ^ 0xca1b)?;
    let turned = turntable_board_poses(scan, &small, o)?;
    render_set(&dir.join("camera"), &poses, &board, cam, o, seed ^ 0x5eed)?;
    render_set(
        &dir.join("turntable"),
        &turned,
        &small,
        cam,
        o,
        seed ^ 0x7a61,
    )?;
    write_true_rig(scan, &dir.join("truth"))?;
    write_setup(&dir, out, &board, &small)
}

/// The rig the images were rendered with, as `calibrate` writes it, into `dir`: `setup.json`'s
/// commands overwrite the scan's own files, and these stay to compare the calibration with.
fn write_true_rig(scan: &Scan, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let t = &scan.turntable;
    calib_io::write_camera(&dir.join("camera.yml"), &scan.camera, 0.0, None)?;
    calib_io::write_screen(&dir.join("screen.yml"), &scan.screen)?;
    calib_io::write_turntable_axis(&dir.join("turntable.yml"), &t.axis_point, &t.axis_dir)?;
    Ok(())
}

/// The camera's and the turntable's boards of `o.boards`. A board sized with the rig has a
/// width with margins (cols + 3 squares) that is a share of the image width at the axis
/// distance: a large one for the camera (strong perspective when tilted), a smaller one that
/// stays in view on the turntable; sides rounded to 0.1 mm.
fn boards(cam: &Camera, o: &SimulateOptions) -> (Board, Board) {
    let b = &o.boards;
    let camera_square = b
        .camera_square_mm
        .unwrap_or_else(|| square_with_rig(cam, o, CAMERA_BOARD_SHARE));
    let turntable_square = b
        .turntable_square_mm
        .or(b.camera_square_mm)
        .unwrap_or_else(|| square_with_rig(cam, o, TURNTABLE_BOARD_SHARE));
    let board = |square_mm| Board {
        cols: b.cols,
        rows: b.rows,
        square_mm,
    };
    (board(camera_square), board(turntable_square))
}

/// Shares of the image width at the axis that a board sized with the rig spans with its
/// margins: the camera's board, the turntable's.
const CAMERA_BOARD_SHARE: f64 = 0.6;
const TURNTABLE_BOARD_SHARE: f64 = 0.5;

/// The square side (mm, rounded to 0.1) of a board of `o.boards`' corners whose width with
/// margins (cols + 3 squares) spans `share` of the image width at the axis distance.
fn square_with_rig(cam: &Camera, o: &SimulateOptions, share: f64) -> f64 {
    let squares = (o.boards.cols + 3) as f64;
    (share * cam.width as f64 * o.camera_distance_mm / cam.fx / squares * 10.0).round() / 10.0
}

/// `o.boards.camera_images` random poses (board → camera) of `board` held in front of the
/// camera 0.45–1.2 × `o.camera_distance_mm` away, tilted up to 55°, each wholly in view.
fn camera_board_poses(
    cam: &Camera,
    board: &Board,
    o: &SimulateOptions,
    seed: u64,
) -> Result<Vec<Isometry3<f64>>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut poses = Vec::new();
    let wanted = o.boards.camera_images;
    for _ in 0..100_000 {
        if poses.len() == wanted {
            break;
        }
        let rot = UnitQuaternion::from_euler_angles(
            rng.random_range(-55f64..55.0).to_radians(),
            rng.random_range(-55f64..55.0).to_radians(),
            rng.random_range(-15f64..15.0).to_radians(),
        );
        let z = o.camera_distance_mm * rng.random_range(0.45..1.2);
        let centre = Vector3::new(
            rng.random_range(-0.35..0.35) * cam.width as f64 * z / cam.fx,
            rng.random_range(-0.35..0.35) * cam.height as f64 * z / cam.fy,
            z,
        );
        let half = Vector3::new(board.cols as f64, board.rows as f64, 0.0) * board.square_mm / 2.0;
        let pose = Isometry3::from_parts(Translation3::from(centre - rot * half), rot);
        if in_view(cam, &pose, board) {
            poses.push(pose);
        }
    }
    if poses.len() < wanted {
        bail!(
            "cannot place the {} mm board in the camera's view at 0.45–1.2 × {} mm: leave out --square-mm (the board is then sized with the rig: {} mm here), give a smaller one or a larger --camera-distance-mm",
            board.square_mm,
            o.camera_distance_mm,
            square_with_rig(cam, o, CAMERA_BOARD_SHARE)
        );
    }
    Ok(poses)
}

/// The poses (board → camera) of `small` standing on the turntable, facing the camera at 0°,
/// 10 mm beside the axis and 30 mm in front of it, at each of [`TURNTABLE_ANGLES`]; an error
/// when it leaves the camera's view.
fn turntable_board_poses(
    scan: &Scan,
    small: &Board,
    o: &SimulateOptions,
) -> Result<Vec<Isometry3<f64>>> {
    let s = small.square_mm;
    let upright = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let in_world = Isometry3::from_parts(
        Translation3::new(
            -(small.cols as f64) * s / 2.0 + 10.0,
            small.rows as f64 * s / 2.0,
            30.0,
        ),
        upright,
    );
    let base = scan
        .turntable
        .base_pose()
        .context("the camera lies on the turntable axis")?;
    let turned: Vec<Isometry3<f64>> = TURNTABLE_ANGLES
        .iter()
        .map(|a| {
            base * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), a.to_radians()) * in_world
        })
        .collect();
    if let Some(k) = turned.iter().position(|p| !in_view(&scan.camera, p, small)) {
        bail!(
            "the turntable's {} mm board leaves the camera's view at {}°: give a smaller --turntable-square-mm (sized with the rig: {} mm here) or a larger --camera-distance-mm",
            small.square_mm,
            TURNTABLE_ANGLES[k],
            square_with_rig(&scan.camera, o, TURNTABLE_BOARD_SHARE)
        );
    }
    Ok(turned)
}

/// Writes `dir/setup.json`: the boards and the commands that calibrate the scan `out` from the
/// images.
fn write_setup(dir: &Path, out: &Path, board: &Board, small: &Board) -> Result<()> {
    let board_arg = format!("{}x{}", board.cols, board.rows);
    let screen = format!("{}/screen.yml", out.display());
    let scan_dir = out.display();
    let angles: Vec<String> = TURNTABLE_ANGLES.iter().map(|a| a.to_string()).collect();
    let setup = Setup {
        board: board_arg.clone(),
        camera_square_mm: board.square_mm,
        turntable_square_mm: small.square_mm,
        turntable_angles_deg: TURNTABLE_ANGLES.to_vec(),
        commands: vec![
            format!("glasscan calibrate camera --images '{scan_dir}/calibration/camera/*.png' --board {board_arg} --square-mm {} -o {scan_dir}/camera.yml", board.square_mm),
            format!("glasscan calibrate screen {scan_dir}"),
            format!("glasscan calibrate turntable --images '{scan_dir}/calibration/turntable/*.png' --board {board_arg} --square-mm {} --angles={} --camera {scan_dir}/camera.yml --screen {screen} -o {scan_dir}/turntable.yml", small.square_mm, angles.join(",")),
        ],
    };
    crate::util::atomic::write_atomic(&dir.join("setup.json"), |w| {
        serde_json::to_writer_pretty(&mut *w, &setup)?;
        Ok(())
    })
    .with_context(|| format!("cannot write {}", dir.join("setup.json").display()))
}

/// True when the whole board with its margin projects inside the image (10 px inset).
fn in_view(cam: &Camera, pose: &Isometry3<f64>, b: &Board) -> bool {
    let s = b.square_mm;
    let (x0, y0, x1, y1) = (
        -2.0 * s,
        -2.0 * s,
        (b.cols + 1) as f64 * s,
        (b.rows + 1) as f64 * s,
    );
    [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
        .iter()
        .all(|&(x, y)| {
            cam.project(&(pose * Point3::new(x, y, 0.0)))
                .is_some_and(|p| {
                    p.x > 10.0
                        && p.y > 10.0
                        && p.x < cam.width as f64 - 11.0
                        && p.y < cam.height as f64 - 11.0
                })
        })
}

/// Renders one image per pose into `dir/board_NN.png`.
fn render_set(
    dir: &Path,
    poses: &[Isometry3<f64>],
    b: &Board,
    cam: &Camera,
    o: &SimulateOptions,
    seed: u64,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    poses.par_iter().enumerate().try_for_each(|(k, pose)| {
        let mut img = render_board(cam, pose, b, seed.wrapping_add(k as u64));
        write_sensor_image(
            &dir.join(format!("board_{k:02}.png")),
            &mut img,
            (cam.width, cam.height),
            o,
            seed.wrapping_add(k as u64),
        )
    })
}

/// The grey image of the board at `pose` (board → camera), 6 × 6 samples per pixel, each at a
/// random place within its cell of the pixel (drawn from `seed`, row by row): on a regular grid
/// of samples every pixel an edge crosses would see it at a multiple of 1/6 pixel, and the
/// error, the same all along a straight edge, would move the corners and lines found by up to
/// 1/12 pixel. Each pixel's sample rays come from its centre ray and the ray's derivatives
/// across the pixel.
fn render_board(cam: &Camera, pose: &Isometry3<f64>, b: &Board, seed: u64) -> Vec<f32> {
    let inv = pose.inverse();
    let (o, n) = (inv * Point3::origin(), 6usize);
    let s = b.square_mm;
    let shade = |x: f64, y: f64| -> f32 {
        let (i, j) = ((x / s).floor(), (y / s).floor());
        if i < -2.0 || j < -2.0 || i > b.cols as f64 || j > b.rows as f64 {
            BEHIND
        } else if i < -1.0 || j < -1.0 || i >= b.cols as f64 || j >= b.rows as f64 {
            WHITE
        } else if (i + j) as i64 % 2 == 0 {
            BLACK
        } else {
            WHITE
        }
    };
    let w = cam.width as usize;
    let mut img = vec![0.0f32; w * cam.height as usize];
    img.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
        let mut rng = ChaCha8Rng::seed_from_u64(scatter_seed(seed) ^ ((v as u64) << 32));
        for (u, px) in row.iter_mut().enumerate() {
            let (uf, vf) = (u as f64, v as f64);
            let ray = |du: f64, dv: f64| cam.pixel_ray(uf + du, vf + dv).map(|r| inv * r);
            let (Some(r0), Some(ru), Some(rv)) = (ray(0.0, 0.0), ray(0.5, 0.0), ray(0.0, 0.5))
            else {
                *px = BEHIND;
                continue;
            };
            let (du, dv) = ((ru - r0) * 2.0, (rv - r0) * 2.0);
            let mut sum = 0.0;
            for a in 0..n {
                for c in 0..n {
                    let (fu, fv) = (
                        (a as f64 + rng.random::<f64>()) / n as f64 - 0.5,
                        (c as f64 + rng.random::<f64>()) / n as f64 - 0.5,
                    );
                    let r: Vector3<f64> = r0 + du * fu + dv * fv;
                    let t = -o.z / r.z;
                    sum += if r.z.abs() > 1e-12 && t > 0.0 {
                        shade(o.x + t * r.x, o.y + t * r.y)
                    } else {
                        BEHIND
                    };
                }
            }
            *px = sum / (n * n) as f32;
        }
    });
    img
}
