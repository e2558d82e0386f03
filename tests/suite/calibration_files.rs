//! Calibration files in OpenCV's FileStorage format, both ways; the camera model; the turntable
//! frames; the scan folder.
#![allow(clippy::excessive_precision)] // the literals are the exact text of OpenCV's sample file

use std::fs;

use glasscan::rig::calib_io::{
    read_camera, read_screen, read_turntable_axis, write_camera, write_screen, write_turntable_axis,
};
use glasscan::rig::{Camera, Screen, Turntable};
use glasscan::scan::Scan;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{
    FileNodeTraitConst, FileStorage, FileStorageTraitConst, MatTraitConst, MatTraitConstManual,
};

/// The head of OpenCV's sample `samples/data/left_intrinsics.yml` (shipped by Debian's
/// opencv-doc package under /usr/share/doc/opencv-doc/examples/data/), as OpenCV's calibration
/// sample writes it.
const OPENCV_SAMPLE: &str = "%YAML:1.0
---
nframes: 13
image_width: 640
image_height: 480
board_width: 9
board_height: 6
square_size: 2.5000000372529030e-02
aspectRatio: 1.
flags: 2
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 5.3591573396163199e+02, 0., 3.4228315473308373e+02, 0.,
       5.3591573396163199e+02, 2.3557082909788173e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -2.6637260909660682e-01, -3.8588898922304653e-02,
       1.7831947042852964e-03, -2.8122100441115472e-04,
       2.3839153080878486e-01 ]
avg_reprojection_error: 3.9259098975581364e-01
per_view_reprojection_errors: !!opencv-matrix
   rows: 13
   cols: 1
   dt: f
   data: [ 1.92965463e-01, 1.18204820e+00, 1.73180386e-01,
       1.93417311e-01, 1.59574091e-01, 1.79683909e-01, 2.30989486e-01,
       2.41952404e-01, 2.96267658e-01, 1.67184874e-01, 2.02002615e-01,
       3.81039530e-01, 1.74401343e-01 ]
";

fn opencv_sample_camera() -> Camera {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("left_intrinsics.yml");
    fs::write(&p, OPENCV_SAMPLE).unwrap();
    read_camera(&p).unwrap()
}

#[test]
fn opencv_sample_calibration_loads() {
    let c = opencv_sample_camera();
    assert_eq!((c.width, c.height), (640, 480));
    assert_eq!(
        (c.fx, c.fy, c.cx, c.cy),
        (
            5.3591573396163199e+02,
            5.3591573396163199e+02,
            3.4228315473308373e+02,
            2.3557082909788173e+02
        )
    );
    assert_eq!(
        c.dist,
        [
            -2.6637260909660682e-01,
            -3.8588898922304653e-02,
            1.7831947042852964e-03,
            -2.8122100441115472e-04,
            2.3839153080878486e-01
        ]
    );
}

#[test]
fn files_written_here_load_in_opencv_and_back() {
    let dir = tempfile::tempdir().unwrap();
    let cam = opencv_sample_camera();
    let p = dir.path().join("camera.yml");
    write_camera(&p, &cam, 0.25, None).unwrap();
    assert!(fs::read_to_string(&p).unwrap().starts_with("%YAML:1.0"));
    // OpenCV reads what we wrote.
    let fs_cv = FileStorage::new(&p, opencv::core::FileStorage_READ, "").unwrap();
    let k = fs_cv.get("camera_matrix").unwrap().mat().unwrap();
    assert_eq!((k.rows(), k.cols()), (3, 3));
    assert_eq!(*k.at_2d::<f64>(0, 2).unwrap(), cam.cx);
    let d = fs_cv.get("distortion_coefficients").unwrap().mat().unwrap();
    assert_eq!(d.data_typed::<f64>().unwrap(), &cam.dist);
    assert_eq!(fs_cv.get("image_width").unwrap().to_i32().unwrap(), 640);
    assert_eq!(
        fs_cv.get("avg_reprojection_error").unwrap().real().unwrap(),
        0.25
    );
    // And we read it back exactly.
    assert_eq!(read_camera(&p).unwrap(), cam);

    let screen = Screen {
        width_px: 1920,
        height_px: 1080,
        pitch_mm: 0.2715,
        pose: Isometry3::from_parts(
            Translation3::new(-260.0, -146.0, 800.0),
            UnitQuaternion::from_euler_angles(0.01, -0.02, 0.03),
        ),
    };
    let sp = dir.path().join("screen.yml");
    write_screen(&sp, &screen).unwrap();
    let back = read_screen(&sp).unwrap();
    assert_eq!(
        (back.width_px, back.height_px, back.pitch_mm),
        (1920, 1080, 0.2715)
    );
    assert!((back.point(100.0, 50.0) - screen.point(100.0, 50.0)).norm() < 1e-9);
    let r = FileStorage::new(&sp, opencv::core::FileStorage_READ, "")
        .unwrap()
        .get("rotation")
        .unwrap()
        .mat()
        .unwrap();
    assert_eq!((r.rows(), r.cols()), (3, 3));

    let tp = dir.path().join("turntable.yml");
    let dir3 = -Vector3::y_axis();
    write_turntable_axis(&tp, &Point3::new(1.0, 2.0, 550.0), &dir3).unwrap();
    assert_eq!(
        read_turntable_axis(&tp).unwrap(),
        (Point3::new(1.0, 2.0, 550.0), dir3)
    );
}

#[test]
fn bad_calibration_files_are_named_errors() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("c.yml");
    let e = read_camera(&p).unwrap_err().to_string();
    assert!(e.contains("c.yml") && e.contains("no such file"), "{e}");
    fs::write(&p, OPENCV_SAMPLE.replace("camera_matrix", "camera_matrx")).unwrap();
    let e = read_camera(&p).unwrap_err().to_string();
    assert!(e.contains("missing key 'camera_matrix'"), "{e}");
    fs::write(
        &p,
        OPENCV_SAMPLE.replace("rows: 5", "rows: 1").replace(
            "cols: 1\n   dt: d\n   data: [ -2.66",
            "cols: 5\n   dt: d\n   data: [ -2.66",
        ),
    )
    .unwrap();
    assert!(read_camera(&p).is_ok(), "a 1×5 distortion row is fine");
    fs::write(&p, "not yaml at all: [").unwrap();
    assert!(read_camera(&p).is_err());
    let s = dir.path().join("s.yml");
    let screen = Screen {
        width_px: 10,
        height_px: 10,
        pitch_mm: 1.0,
        pose: Isometry3::identity(),
    };
    write_screen(&s, &screen).unwrap();
    let text = fs::read_to_string(&s).unwrap();
    assert!(text.contains("data: [ 1., 0., 0., 0., 1."), "{text}");
    fs::write(
        &s,
        text.replace("data: [ 1., 0., 0., 0., 1.", "data: [ 2., 0., 0., 0., 1."),
    )
    .unwrap();
    let e = read_screen(&s).unwrap_err().to_string();
    assert!(e.contains("rotation"), "{e}");
}

#[test]
fn the_lens_model_inverts_and_projects_consistently() {
    let c = opencv_sample_camera();
    for &(u, v) in &[(0.0, 0.0), (639.0, 479.0), (320.0, 240.0), (100.5, 400.25)] {
        let d = c.pixel_ray(u, v).unwrap();
        let p = c.project(&Point3::from(d * 123.0)).unwrap();
        assert!(
            (p.x - u).abs() < 1e-9 && (p.y - v).abs() < 1e-9,
            "({u}, {v}) -> {p:?}"
        );
    }
}

#[test]
fn turntable_views_rotate_the_object_about_the_axis() {
    let t = Turntable {
        axis_point: Point3::new(0.0, 0.0, 550.0),
        axis_dir: -Vector3::y_axis(),
        angles_deg: vec![0.0, 90.0],
    };
    let poses = t.view_poses().unwrap();
    // The world origin is on the axis; world +y is the axis direction; +z faces the camera.
    assert!((poses[0] * Point3::origin() - Point3::new(0.0, 0.0, 550.0)).norm() < 1e-12);
    assert!((poses[0] * Vector3::y() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    assert!((poses[0] * Vector3::z() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
    // A point on the axis is the same in every view; others turn by the angle.
    let on_axis = Point3::new(0.0, 10.0, 0.0);
    assert!((poses[0] * on_axis - poses[1] * on_axis).norm() < 1e-12);
    let p = Point3::new(10.0, 0.0, 0.0);
    let (a, b) = (poses[0] * p, poses[1] * p);
    assert!(((a - Point3::new(0.0, 0.0, 550.0)).norm() - 10.0).abs() < 1e-12);
    assert!(
        (a - Point3::new(0.0, 0.0, 550.0))
            .dot(&(b - Point3::new(0.0, 0.0, 550.0)))
            .abs()
            < 1e-9
    );
}

#[test]
fn scan_folder_round_trips_and_rejects_bad_configs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mesh = glasscan::mesh::shapes::icosphere(20.0, 3);
    let opts = glasscan::simulate::SimulateOptions {
        views: 3,
        width: 64,
        height: 48,
        screen_width: 128,
        screen_height: 72,
        decoded_only: true,
        ..Default::default()
    };
    glasscan::simulate::simulate(&mesh, d, &opts, |_| ()).unwrap();
    let scan = Scan::open(d).unwrap();
    assert_eq!(scan.config.views.angles_deg, vec![0.0, 120.0, 240.0]);
    assert_eq!((scan.screen.width_px, scan.camera.width), (128, 64));
    assert_eq!(scan.graycode().pattern_count(), 2 * (7 + 7));

    let toml_path = d.join("scan.toml");
    let good = fs::read_to_string(&toml_path).unwrap();
    for (edit, needle) in [
        (
            good.replace("ior = ", "colour = 1\nior = "),
            "unknown field `colour`",
        ),
        (
            good.replace("ior = 1.4723", "ior = 0.9"),
            "refractive index",
        ),
        (
            good.replace("width = 128", "width = 100"),
            "patterns are 100×72",
        ),
        (good.replace("camera.yml", "nowhere.yml"), "nowhere.yml"),
    ] {
        fs::write(&toml_path, edit).unwrap();
        let e = Scan::open(d).unwrap_err().to_string();
        assert!(e.contains(needle), "expected '{needle}' in: {e}");
    }
}
