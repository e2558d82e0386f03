//! `glasscan import-drt`: HDF5 files written here in DRT's layout (both cameras, invalid rows,
//! 0/1 and 0/255 masks) import to the same reconstruction inputs as the scan they were exported
//! from; bad files are clear errors; hull and reconstruct run on an import.

use crate::common::{glasscan, hdf5_open, killed_then_rerun, refused, snapshot};
use std::path::Path;
use std::process::Output;
use std::sync::OnceLock;

use glasscan::loss::refraction::ViewTargets;
use glasscan::loss::targets::{scan_targets, TargetWeights};
use glasscan::mesh::shapes::ellipsoid;
use glasscan::scan::decoded::DecodedScan;
use glasscan::scan::Scan;
use nalgebra::{Point3, Vector3};
use ndarray::{Array2, Array3, Array4};

const VIEWS: usize = 72;

/// A simulated 72-view scan (decoded-only, 64×48), made once.
fn source() -> &'static Scan {
    static SRC: OnceLock<Scan> = OnceLock::new();
    SRC.get_or_init(|| {
        let dir = crate::common::shared_dir();
        let sphere = ellipsoid(Vector3::new(30.0, 24.0, 20.0), 3);
        crate::common::decoded_scan(&dir, &sphere, VIEWS, (64, 48));
        Scan::open(&dir).unwrap()
    })
}

/// How to lay the file out.
#[derive(Clone, Copy)]
struct Layout {
    /// Point Grey (per-pixel rays, [72, H·W, 3]) or Redmi (no rays, [72, H, W, 3]).
    point_grey: bool,
    /// Masks as 0/255 (else 0/1).
    mask_255: bool,
    /// Views written (DRT: 72).
    views: usize,
    /// Leave out this key.
    without: Option<&'static str>,
    /// Zero the monitor point of every 7th object pixel (invalid rows).
    invalid_rows: bool,
}

const POINT_GREY: Layout = Layout {
    point_grey: true,
    mask_255: true,
    views: VIEWS,
    without: None,
    invalid_rows: false,
};

/// Writes `scan` in DRT's layout; returns the number of rows zeroed.
fn export_drt(scan: &Scan, path: &Path, l: Layout) -> usize {
    let _open = hdf5_open();
    let (arrays, zeroed) = drt_arrays(scan, l);
    write_drt_file(path, l, arrays);
    zeroed
}

/// The datasets of a DRT file, as DRT names them.
struct DrtArrays {
    cam_proj: Array3<f64>,
    cam_k: Array2<f64>,
    mask: Array3<u8>,
    screen_position: Array3<f32>,
    ray_origin: Array3<f32>,
    ray_dir: Array3<f32>,
    /// The image size, pixels.
    size: (usize, usize),
}

/// `scan`'s views in DRT's arrays (views repeated up to `l.views`; every seventh object pixel's
/// row zeroed with `l.invalid_rows`), and how many rows were zeroed.
fn drt_arrays(scan: &Scan, l: Layout) -> (DrtArrays, usize) {
    let (w, h) = (scan.camera.width as usize, scan.camera.height as usize);
    let decoded = DecodedScan::open(&scan.dir, (w as u32, h as u32)).unwrap();
    let poses = scan.view_poses();
    let mut cam_proj = Array3::<f64>::zeros((l.views, 4, 4));
    let mut mask = Array3::<u8>::zeros((l.views, h, w));
    let mut pos = Array3::<f32>::zeros((l.views, w * h, 3));
    let mut origin = Array3::<f32>::zeros((l.views, w * h, 3));
    let mut dir = Array3::<f32>::zeros((l.views, w * h, 3));
    let mut zeroed = 0;
    for v in 0..l.views {
        let k = v % VIEWS;
        let m = poses[k].to_homogeneous();
        for i in 0..4 {
            for j in 0..4 {
                cam_proj[[v, i, j]] = m[(i, j)];
            }
        }
        let to_world = poses[k].inverse();
        let screen = scan.screen.transformed(&to_world);
        let eye = to_world * Point3::origin();
        let dv = decoded.view(k).unwrap().unwrap();
        let mut object = 0;
        for p in 0..w * h {
            let (x, y) = (p % w, p / w);
            if dv.mask[p] {
                mask[[v, y, x]] = if l.mask_255 { 255 } else { 1 };
                object += 1;
            }
            let d = to_world * scan.camera.pixel_ray(x as f64, y as f64).unwrap();
            for c in 0..3 {
                origin[[v, p, c]] = eye[c] as f32;
                dir[[v, p, c]] = d[c] as f32;
            }
            if let Some(t) = dv.targets[p] {
                if l.invalid_rows && dv.mask[p] && object % 7 == 0 {
                    zeroed += 1;
                    continue;
                }
                let q = screen.point(t.u, t.v);
                for c in 0..3 {
                    pos[[v, p, c]] = q[c] as f32;
                }
            }
        }
    }
    let k = &scan.camera;
    let cam_k = Array2::from_shape_vec(
        (3, 3),
        vec![k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
    )
    .unwrap();
    let arrays = DrtArrays {
        cam_proj,
        cam_k,
        mask,
        screen_position: pos,
        ray_origin: origin,
        ray_dir: dir,
        size: (w, h),
    };
    (arrays, zeroed)
}

/// Writes `a` to a new HDF5 file at `path` in layout `l`.
fn write_drt_file(path: &Path, l: Layout, a: DrtArrays) {
    let (w, h) = a.size;
    let f = hdf5::File::create(path).unwrap();
    let put = |name: &str| l.without != Some(name);
    if put("cam_proj") {
        f.new_dataset_builder()
            .with_data(&a.cam_proj)
            .create("cam_proj")
            .unwrap();
    }
    if put("cam_k") {
        f.new_dataset_builder()
            .with_data(&a.cam_k)
            .create("cam_k")
            .unwrap();
    }
    if put("mask") {
        f.new_dataset_builder()
            .with_data(&a.mask)
            .create("mask")
            .unwrap();
    }
    if put("screen_position") {
        if l.point_grey {
            f.new_dataset_builder()
                .with_data(&a.screen_position)
                .create("screen_position")
                .unwrap();
        } else {
            let grid: Array4<f32> = a
                .screen_position
                .into_shape_with_order((l.views, h, w, 3))
                .unwrap();
            f.new_dataset_builder()
                .with_data(&grid)
                .create("screen_position")
                .unwrap();
        }
    }
    if l.point_grey && put("ray_origin") {
        f.new_dataset_builder()
            .with_data(&a.ray_origin)
            .create("ray_origin")
            .unwrap();
    }
    if l.point_grey && put("ray_dir") {
        f.new_dataset_builder()
            .with_data(&a.ray_dir)
            .create("ray_dir")
            .unwrap();
    }
    f.close().unwrap();
}

fn all_targets(scan: &Scan) -> Vec<ViewTargets> {
    let views: Vec<usize> = (0..VIEWS).collect();
    scan_targets(scan, &views, TargetWeights::Uniform)
        .unwrap()
        .0
}

/// The imported inputs equal the source's (f32 precision), pixel for pixel, minus `zeroed`.
fn assert_same_inputs(src: &Scan, imported: &Scan, zeroed: usize) {
    let (a, b) = (all_targets(src), all_targets(imported));
    let count = |t: &[ViewTargets]| t.iter().map(|v| v.pixels.len()).sum::<usize>();
    assert_eq!(count(&a), count(&b) + zeroed);
    if zeroed > 0 {
        return;
    }
    for (va, vb) in a.iter().zip(&b) {
        assert!((va.eye - vb.eye).norm() < 1e-3, "view {}: eye", va.view);
        for (pa, pb) in va.pixels.iter().zip(&vb.pixels) {
            assert!(
                (pa.target - pb.target).norm() < 1e-3,
                "view {}: target",
                va.view
            );
            assert!(
                (pa.dir - pb.dir).norm() < 1e-6,
                "view {}: direction",
                va.view
            );
        }
    }
    // The silhouettes are the same.
    let size = (src.camera.width, src.camera.height);
    let (da, db) = (
        DecodedScan::open(&src.dir, size).unwrap(),
        DecodedScan::open(&imported.dir, size).unwrap(),
    );
    for k in 0..VIEWS {
        assert_eq!(da.mask(k).unwrap(), db.mask(k).unwrap(), "mask of view {k}");
    }
    // The poses are the source's.
    for (p, q) in src.view_poses().iter().zip(imported.view_poses()) {
        assert!((p.to_homogeneous() - q.to_homogeneous()).amax() < 1e-9);
    }
}

fn import(file: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "import-drt",
        file.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    glasscan(&args)
}

#[test]
fn both_layouts_import_to_the_sources_inputs() {
    let src = source();
    let tmp = tempfile::tempdir().unwrap();
    for (name, layout) in [
        ("pointgrey", POINT_GREY),
        (
            "redmi",
            Layout {
                point_grey: false,
                mask_255: false,
                ..POINT_GREY
            },
        ),
    ] {
        let file = tmp.path().join(format!("{name}.h5"));
        export_drt(src, &file, layout);
        let out = tmp.path().join(name);
        let o = import(&file, &out, &[]);
        assert!(
            o.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let stdout = String::from_utf8_lossy(&o.stdout);
        let camera = if layout.point_grey {
            "PointGrey"
        } else {
            "Redmi"
        };
        assert!(stdout.contains(camera), "{stdout}");
        let imported = Scan::open(&out).unwrap();
        assert_same_inputs(src, &imported, 0);
    }
}

#[test]
fn invalid_rows_are_left_out_and_the_camera_can_be_forced() {
    let src = source();
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("f.h5");
    let zeroed = export_drt(
        src,
        &file,
        Layout {
            invalid_rows: true,
            ..POINT_GREY
        },
    );
    assert!(zeroed > 100, "{zeroed}");
    let out = tmp.path().join("s");
    let o = import(&file, &out, &["--camera", "redmi"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("Redmi"));
    assert_same_inputs(src, &Scan::open(&out).unwrap(), zeroed);
}

#[test]
fn hull_and_reconstruct_run_on_an_import() {
    let src = source();
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("f.h5");
    export_drt(src, &file, POINT_GREY);
    let scan = tmp.path().join("s");
    assert!(import(&file, &scan, &[]).status.success());
    let hull = tmp.path().join("hull.ply");
    let o = glasscan(&[
        "hull",
        scan.to_str().unwrap(),
        "-o",
        hull.to_str().unwrap(),
        "--voxel-mm",
        "2",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let config = tmp.path().join("c.toml");
    std::fs::write(
        &config,
        "stages = 2\nstart_edge = 0.1\nfinal_edge = 0.06\niterations = 5\n",
    )
    .unwrap();
    let out = tmp.path().join("out");
    let o = glasscan(&[
        "reconstruct",
        scan.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--hull-voxel-mm",
        "2",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.join("result.ply").is_file());
}

#[test]
fn bad_files_name_the_key_and_shape() {
    let src = source();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("s");
    for (layout, needle) in [
        (
            Layout {
                without: Some("cam_k"),
                ..POINT_GREY
            },
            "no dataset 'cam_k'",
        ),
        (
            Layout {
                without: Some("ray_dir"),
                ..POINT_GREY
            },
            "Redmi",
        ),
        (
            Layout {
                views: 71,
                ..POINT_GREY
            },
            "dataset 'cam_proj' has shape [71, 4, 4]: 71 views",
        ),
    ] {
        let file = tmp.path().join("bad.h5");
        let _ = std::fs::remove_file(&file);
        export_drt(src, &file, layout);
        let _ = std::fs::remove_dir_all(&out);
        let o = import(&file, &out, &[]);
        if needle == "Redmi" {
            // Without rays the file reads as a Redmi one; forcing Point Grey names the key.
            assert!(o.status.success());
            let o = import(&file, &tmp.path().join("s2"), &["--camera", "pointgrey"]);
            refused(&o, "no dataset 'ray_dir'");
        } else {
            refused(&o, needle);
        }
    }
    // A wrong shape.
    let file = tmp.path().join("shape.h5");
    export_drt(src, &file, POINT_GREY);
    {
        let _open = hdf5_open();
        let f = hdf5::File::open_rw(&file).unwrap();
        f.unlink("screen_position").unwrap();
        let a = Array3::<f32>::zeros((VIEWS, 10, 3));
        f.new_dataset_builder()
            .with_data(&a)
            .create("screen_position")
            .unwrap();
        f.close().unwrap();
    }
    refused(
        &import(&file, &out, &[]),
        "dataset 'screen_position' has shape [72, 10, 3]",
    );
    refused(
        &import(&tmp.path().join("none.h5"), &out, &[]),
        "no such file",
    );
}

/// A failed import over an earlier one (even with --force) leaves it byte-identical, and a
/// non-empty folder is refused without --force.
#[test]
fn a_failed_import_leaves_the_previous_scan_as_it_was() {
    let src = source();
    let tmp = tempfile::tempdir().unwrap();
    let good = tmp.path().join("good.h5");
    export_drt(src, &good, POINT_GREY);
    let out = tmp.path().join("G");
    let o = import(&good, &out, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let before = snapshot(&out);
    assert!(before.len() > 2 * VIEWS, "{} files", before.len());

    let bad = tmp.path().join("bad.h5");
    export_drt(src, &bad, POINT_GREY);
    {
        let _open = hdf5_open();
        let f = hdf5::File::open_rw(&bad).unwrap();
        f.unlink("screen_position").unwrap();
        let (w, h) = (src.camera.width as usize, src.camera.height as usize);
        let zeros = Array3::<f32>::zeros((VIEWS, w * h, 3));
        f.new_dataset_builder()
            .with_data(&zeros)
            .create("screen_position")
            .unwrap();
        f.close().unwrap();
    }
    refused(&import(&bad, &out, &[]), "not empty");
    refused(
        &import(&bad, &out, &["--force"]),
        "no object pixel has a monitor point",
    );
    assert!(
        before == snapshot(&out),
        "the failed import changed the scan"
    );
    let siblings = std::fs::read_dir(tmp.path()).unwrap().count();
    assert_eq!(siblings, 3, "a temporary folder was left behind");
    // The input is never the output.
    refused(
        &import(&good, tmp.path(), &["--force"]),
        "would overwrite the input",
    );
}

/// A small file declaring a huge mask is refused before anything is allocated.
#[test]
fn a_declared_size_beyond_the_memory_limit_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("huge.h5");
    {
        let _open = hdf5_open();
        let f = hdf5::File::create(&file).unwrap();
        let eye: Array3<f64> =
            Array3::from_shape_fn((VIEWS, 4, 4), |(_, i, j)| (i == j) as u8 as f64);
        f.new_dataset_builder()
            .with_data(&eye)
            .create("cam_proj")
            .unwrap();
        let k = Array2::from_shape_vec((3, 3), vec![1e3, 0.0, 5.0, 0.0, 1e3, 5.0, 0.0, 0.0, 1.0])
            .unwrap();
        f.new_dataset_builder()
            .with_data(&k)
            .create("cam_k")
            .unwrap();
        f.new_dataset::<u8>()
            .chunk((1, 1000, 1000))
            .shape((VIEWS, 100_000, 100_000))
            .create("mask")
            .unwrap();
        f.close().unwrap();
    }
    assert!(std::fs::metadata(&file).unwrap().len() < 1 << 20);
    let o = import(&file, &tmp.path().join("out"), &[]);
    refused(&o, "more than the limit");
}

/// `import-drt --force` killed at seeded random instants, then run again: the rerun succeeds
/// and no temporary folder or lock is left beside the scan.
#[test]
fn an_import_killed_anywhere_is_put_right_by_the_next() {
    let src = source();
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("drt.h5");
    export_drt(src, &file, POINT_GREY);
    let out = tmp.path().join("S");
    let args = [
        "import-drt",
        file.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--force",
    ];
    let t0 = std::time::Instant::now();
    assert!(glasscan(&args).status.success());
    killed_then_rerun(&args, &out, 6, t0.elapsed(), 43);
    assert!(Scan::open(&out).is_ok());
}
