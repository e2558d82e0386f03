//! Visual hull: marching cubes' guarantees, convergence on a sphere, containment of the true
//! shape on simulated scans, and bad input.

use crate::common::{decoded_scan, glasscan};

use glasscan::hull::{visual_hull, HullOptions, HullRemesh, VoxelSize};
use glasscan::mesh::marching_cubes::{marching_cubes, FieldBlock, Grid};
use glasscan::mesh::sample::sample_surface;
use glasscan::mesh::shapes::{ellipsoid, figurine, torus};
use glasscan::mesh::validate::{ensure_valid, validate, Defect};
use glasscan::mesh::TriMesh;
use glasscan::rig::{Camera, Turntable};
use glasscan::scan::decoded::MASK_FILLED;
use glasscan::scan::silhouette::Silhouette;
use glasscan::scan::Scan;
use glasscan::simulate::{simulate, SimulateOptions, Transport};
use glasscan::trace::{BuildMode, Device, Ray, Scene};
use glasscan::util::progress::Silent;
use nalgebra::{Point3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[test]
fn marching_cubes_is_closed_manifold_and_outward_on_random_fields() {
    // Random values make every case, the ambiguous ones included, appear many times; blocks
    // meet at faces, edges and corners.
    for seed in 0..20u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (b, nb) = (4usize, 3usize);
        let n = nb * b;
        let value = |g: [usize; 3], r: f32| {
            if g.iter().any(|&x| x == 0 || x == n) {
                -1.0
            } else {
                r
            }
        };
        let noise: Vec<f32> = (0..(n + 1).pow(3))
            .map(|_| rng.random_range(-1.0f32..1.0) + 0.3)
            .collect();
        let mut blocks = Vec::new();
        for bz in 0..nb {
            for by in 0..nb {
                for bx in 0..nb {
                    let corner = [bx * b, by * b, bz * b];
                    let mut values = Vec::new();
                    for k in 0..=b {
                        for j in 0..=b {
                            for i in 0..=b {
                                let g = [corner[0] + i, corner[1] + j, corner[2] + k];
                                values.push(value(
                                    g,
                                    noise[g[0] + (n + 1) * (g[1] + (n + 1) * g[2])],
                                ));
                            }
                        }
                    }
                    blocks.push(FieldBlock { corner, values });
                }
            }
        }
        let grid = Grid {
            origin: Point3::new(-3.0, 1.0, 2.0),
            step: 0.7,
            block: b,
        };
        let mesh = marching_cubes(&grid, &blocks);
        assert!(!mesh.faces.is_empty());
        // Closed, manifold, consistently oriented; random fields enclose outside bubbles, whose
        // surfaces rightly face into them (negative volume), so orientation is checked overall:
        // the enclosed volume is that of the inside samples.
        let report = validate(&mesh);
        let defects: Vec<String> = report
            .defects
            .iter()
            .filter(|d| !matches!(d, Defect::InsideOut { .. }))
            .map(|d| d.to_string())
            .collect();
        assert!(defects.is_empty(), "seed {seed}: {defects:?}");
        let inside = noise
            .iter()
            .enumerate()
            .filter(|&(i, &r)| {
                value(
                    [i % (n + 1), (i / (n + 1)) % (n + 1), i / (n + 1).pow(2)],
                    r,
                ) > 0.0
            })
            .count() as f64;
        let expected = inside * grid.step.powi(3);
        let v = mesh.signed_volume();
        assert!(
            (v - expected).abs() < 0.25 * expected,
            "seed {seed}: volume {v} vs {expected}"
        );
    }
}

/// A camera ring like `simulate`'s: image `w`×`h`, the sphere filling 60 % of the height.
fn ring(views: usize, w: u32, h: u32, radius: f64) -> (Camera, Vec<nalgebra::Isometry3<f64>>) {
    let d = 550.0;
    let f = 0.6 * h as f64 * d / (2.0 * radius);
    let camera = Camera {
        width: w,
        height: h,
        fx: f,
        fy: f,
        cx: (w as f64 - 1.0) / 2.0,
        cy: (h as f64 - 1.0) / 2.0,
        dist: [0.0; 5],
    };
    let tt = Turntable {
        axis_point: Point3::new(0.0, 0.0, d),
        axis_dir: -Vector3::y_axis(),
        angles_deg: Turntable::even_angles(views),
    };
    (camera, tt.view_poses().unwrap())
}

/// The mask of a sphere of radius `r` at the world origin: pixels whose ray meets it.
fn sphere_mask(camera: &Camera, pose: &nalgebra::Isometry3<f64>, r: f64) -> Vec<u8> {
    let c = pose * Point3::origin();
    let w = camera.width;
    (0..camera.height * w)
        .map(|i| {
            let d = camera.pixel_ray((i % w) as f64, (i / w) as f64).unwrap();
            let along = c.coords.dot(&d);
            (along > 0.0 && (c.coords - along * d).norm() < r) as u8 * 255
        })
        .collect()
}

fn sphere_silhouettes(views: usize, w: u32, h: u32, r: f64) -> Vec<Silhouette> {
    let (camera, poses) = ring(views, w, h, r);
    poses
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            Silhouette::from_mask(k, &sphere_mask(&camera, pose, r), &camera, *pose).unwrap()
        })
        .collect()
}

/// Points of `truth` that are neither inside `hull` nor within `tol` of its surface.
fn outside_points(hull: &TriMesh, points: &[Point3<f64>], tol: f64) -> usize {
    let scene = Scene::new(&Device::new().unwrap(), hull, BuildMode::Static).unwrap();
    let near = scene.closest_points(points).unwrap();
    let far: Vec<Point3<f64>> = points
        .iter()
        .zip(&near)
        .filter(|(_, c)| c.dist > tol)
        .map(|(p, _)| *p)
        .collect();
    // A point is inside when the first surface a ray from it meets faces away from it.
    let dir = Vector3::new(0.3, 0.8, 0.52).normalize();
    let rays: Vec<Ray> = far.iter().map(|p| Ray::new(*p, dir)).collect();
    let hits = scene.intersect(&rays, false).unwrap();
    hits.iter()
        .filter(|h| match h {
            None => true,
            Some(h) => hull.face_cross(h.prim as usize).dot(&dir) <= 0.0,
        })
        .count()
}

#[test]
fn the_hull_of_a_sphere_converges_to_it() {
    let r = 40.0;
    let mut errors = Vec::new();
    for (views, w, h, voxel) in [(6, 160, 120, 4.0), (18, 320, 240, 2.0), (72, 640, 480, 1.0)] {
        let sils = sphere_silhouettes(views, w, h, r);
        let o = HullOptions {
            voxel: VoxelSize::Mm(voxel),
            remesh: HullRemesh::Raw,
            ..HullOptions::default()
        };
        let (mesh, report) = visual_hull(&sils, &o, &Silent).unwrap();
        assert_eq!(report.genus, 0);
        let radial: Vec<f64> = mesh.positions.iter().map(|p| p.coords.norm() - r).collect();
        let mean = radial.iter().map(|e| e.abs()).sum::<f64>() / radial.len() as f64;
        let sphere: Vec<Point3<f64>> = sample_surface(&ellipsoid(Vector3::repeat(r), 5), 20_000, 1)
            .into_iter()
            .map(|(p, _)| p)
            .collect();
        assert_eq!(outside_points(&mesh, &sphere, voxel), 0, "{views} views");
        errors.push(mean);
    }
    assert!(
        errors.windows(2).all(|e| e[1] < 0.7 * e[0]) && errors[2] < 0.5,
        "mean radial errors {errors:?} mm"
    );
}

#[test]
fn tolerance_keeps_what_one_bad_mask_cuts_away() {
    let r = 30.0;
    let mut sils = sphere_silhouettes(24, 240, 180, r);
    // View 5 loses the left half of its silhouette.
    let (camera, poses) = ring(24, 240, 180, r);
    let w = camera.width as usize;
    let mut mask = sphere_mask(&camera, &poses[5], r);
    for (i, m) in mask.iter_mut().enumerate() {
        if i % w <= w / 2 {
            *m = 0;
        }
    }
    sils[5] = Silhouette::from_mask(5, &mask, &camera, poses[5]).unwrap();
    let volume = |tolerance| {
        let o = HullOptions {
            voxel: VoxelSize::Mm(1.5),
            tolerance,
            remesh: HullRemesh::Raw,
            ..HullOptions::default()
        };
        visual_hull(&sils, &o, &Silent).unwrap().1.volume_mm3
    };
    let ball = 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
    let (strict, tolerant) = (volume(0), volume(1));
    assert!(strict < 0.7 * ball, "strict {strict} vs ball {ball}");
    assert!(
        tolerant > ball && tolerant < 1.15 * ball,
        "tolerant {tolerant} vs ball {ball}"
    );
}

#[test]
fn a_hole_the_decoder_filled_is_inside_for_the_hull_and_outside_for_the_silhouette_term() {
    let r = 30.0;
    let (camera, poses) = ring(24, 240, 180, r);
    let w = camera.width as usize;
    let centre = (w / 2 + w * camera.height as usize / 2) as i64;
    // An 11×11 patch in the middle of view 3's silhouette: marked filled, or truly background.
    let with_patch = |value: u8| {
        let mut mask = sphere_mask(&camera, &poses[3], r);
        for dy in -5..=5i64 {
            for dx in -5..=5i64 {
                mask[(centre + dy * w as i64 + dx) as usize] = value;
            }
        }
        Silhouette::from_mask(3, &mask, &camera, poses[3]).unwrap()
    };
    let (filled, open) = (with_patch(MASK_FILLED), with_patch(0));
    let (cx, cy) = ((w / 2) as f64, (camera.height / 2) as f64);
    assert!(filled.sd_px(cx, cy) < -2.0, "{}", filled.sd_px(cx, cy));
    assert_eq!(filled.sd_px(cx, cy), open.sd_px(cx, cy));
    let as_hull_sees_it = filled.with_holes_filled().unwrap();
    assert!(as_hull_sees_it.sd_px(cx, cy) > 10.0);
    let volume = |sil: Silhouette| {
        let mut sils = sphere_silhouettes(24, 240, 180, r);
        sils[3] = sil;
        let o = HullOptions {
            voxel: VoxelSize::Mm(1.5),
            remesh: HullRemesh::Raw,
            ..HullOptions::default()
        };
        visual_hull(&sils, &o, &Silent).unwrap().1.volume_mm3
    };
    let whole = volume(sphere_silhouettes(24, 240, 180, r).swap_remove(3));
    assert_eq!(volume(filled), whole);
    // A hole that is truly background carves a tunnel through the hull.
    let tunnelled = volume(open);
    assert!(tunnelled < 0.995 * whole, "{tunnelled} vs {whole}");
}

#[test]
fn hull_of_a_simulated_torus_contains_it_and_keeps_its_hole() {
    let dir = tempfile::tempdir().unwrap();
    decoded_scan(dir.path(), &standing_torus(40.0, 14.0), 36, (320, 240));
    let out = dir.path().join("hull.ply");
    let text = hull_at_1_5_mm(dir.path(), &out);
    assert!(text.contains("genus 1"), "{text}");
    let hull = glasscan::mesh::io::read_mesh(&out).unwrap();
    ensure_valid(&hull).unwrap();
    let truth = glasscan::mesh::io::read_mesh(&dir.path().join("ground_truth.ply")).unwrap();
    let samples: Vec<Point3<f64>> = sample_surface(&truth, 20_000, 3)
        .into_iter()
        .map(|(p, _)| p)
        .collect();
    assert_eq!(outside_points(&hull, &samples, 1.5), 0);
}

/// The decoder fills holes in a mask that show glass (darker than the background, or decoded
/// away from its points); a true hole, seen through air beside blurred glass rims in captures
/// with Fresnel and internal reflections, must stay open.
#[test]
fn a_torus_captured_with_physical_light_keeps_its_hole_through_decode() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    let opts = SimulateOptions {
        views: 12,
        width: 320,
        height: 240,
        spp: 4,
        noise: 2.0,
        blur_px: 0.7,
        ior: 1.6,
        transport: Transport::Physical,
        ..Default::default()
    };
    let t = standing_torus(30.0, 10.0);
    simulate(&t, &scan, &opts, |_| ()).expect("simulate the torus");
    let o = glasscan(&["decode", scan.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = hull_at_1_5_mm(&scan, &dir.path().join("hull.ply"));
    assert!(text.contains("genus 1"), "{text}");
}

/// A torus of radii `major` and `minor` (mm) standing up (axis horizontal), so its hole shows in
/// most views.
fn standing_torus(major: f64, minor: f64) -> TriMesh {
    let mut t = torus(major, minor, 64, 24);
    for p in &mut t.positions {
        *p = Point3::new(p.x, p.z, -p.y);
    }
    t
}

/// Runs `glasscan hull` on `scan` with 1.5 mm voxels into `out`; its standard output.
fn hull_at_1_5_mm(scan: &std::path::Path, out: &std::path::Path) -> String {
    let o = glasscan(&[
        "hull",
        scan.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--voxel-mm",
        "1.5",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A missing scan is an error, and a scan not decoded (a copy of `decoded`'s settings without
/// its decoded folder) says to decode it.
fn a_scan_not_decoded_is_named(decoded: &std::path::Path) {
    let err = |o: &std::process::Output| String::from_utf8_lossy(&o.stderr).into_owned();
    let raw = tempfile::tempdir().unwrap();
    let r = glasscan(&["hull", "/nonexistent-scan", "-o", "x.ply"]);
    assert_eq!(r.status.code(), Some(1));
    let scan = Scan::open(decoded).unwrap();
    let mut moved = scan.clone();
    moved.dir = raw.path().to_path_buf();
    moved.save().unwrap();
    let r = glasscan(&["hull", raw.path().to_str().unwrap(), "-o", "x.ply"]);
    assert!(err(&r).contains("glasscan decode"), "{}", err(&r));
}

#[test]
fn bad_masks_are_clear_errors_or_named_warnings() {
    let dir = tempfile::tempdir().unwrap();
    decoded_scan(
        dir.path(),
        &ellipsoid(Vector3::new(30.0, 25.0, 20.0), 4),
        8,
        (320, 240),
    );
    let scan_dir = dir.path().to_str().unwrap();
    let out = dir.path().join("hull.ply");
    let run = || {
        glasscan(&[
            "hull",
            scan_dir,
            "-o",
            out.to_str().unwrap(),
            "--voxel-mm",
            "2",
        ])
    };
    let err = |o: &std::process::Output| String::from_utf8_lossy(&o.stderr).into_owned();
    let mask = |k: usize| dir.path().join(format!("decoded/view_{k:03}_mask.png"));
    let write = |k: usize, w: i32, h: i32, fill: f64| {
        let m = opencv::core::Mat::new_rows_cols_with_default(
            h,
            w,
            opencv::core::CV_8UC1,
            opencv::core::Scalar::all(fill),
        )
        .unwrap();
        opencv::imgcodecs::imwrite(mask(k), &m, &opencv::core::Vector::new()).unwrap();
    };
    let ok = run();
    assert!(ok.status.success(), "{}", err(&ok));

    a_scan_not_decoded_is_named(dir.path());

    let original = std::fs::read(mask(3)).unwrap();
    // Wrong size.
    write(3, 100, 80, 255.0);
    let r = run();
    assert!(
        r.status.code() == Some(1)
            && err(&r).contains("view_003_mask.png")
            && err(&r).contains("100×80"),
        "{}",
        err(&r)
    );
    // Empty.
    write(3, 320, 240, 0.0);
    let r = run();
    assert!(
        r.status.code() == Some(1) && err(&r).contains("view 3: the mask is empty"),
        "{}",
        err(&r)
    );
    // Touching the border: a warning naming the view, and the hull still made.
    write(3, 320, 240, 255.0);
    let r = run();
    assert!(
        r.status.success()
            && err(&r).contains("warning: view 3: the mask touches the image border"),
        "{}",
        err(&r)
    );
    std::fs::write(mask(3), original).unwrap();
    // Every mask empty.
    for k in 0..8 {
        write(k, 320, 240, 0.0);
    }
    let r = run();
    assert!(
        r.status.code() == Some(1) && err(&r).contains("mask is empty"),
        "{}",
        err(&r)
    );
    assert!(!err(&r).contains("panicked"));
}

/// A genus-1 figurine with legs (concave gaps no silhouette shows), a torus and an elongated
/// ellipsoid, each scanned from 72 views: the hull holds every true surface point (to a voxel).
#[test]
fn hulls_of_procedural_objects_contain_the_true_shapes() {
    let objects = [
        ("figurine", figurine(1.5)),
        ("torus", torus(35.0, 12.0, 64, 24)),
        ("ellipsoid", ellipsoid(Vector3::new(50.0, 20.0, 30.0), 4)),
    ];
    for (name, mesh) in objects {
        let dir = tempfile::tempdir().unwrap();
        let opts = SimulateOptions {
            views: 72,
            width: 640,
            height: 480,
            spp: 1,
            decoded_only: true,
            ..Default::default()
        };
        simulate(&mesh, dir.path(), &opts, |_| ()).unwrap();
        let scan = Scan::open(dir.path()).unwrap();
        let (sils, warnings) =
            glasscan::hull::silhouettes(&scan, &(0..72).collect::<Vec<_>>()).unwrap();
        assert!(warnings.is_empty(), "{name}: {warnings:?}");
        let voxel = 1.5;
        let o = HullOptions {
            voxel: VoxelSize::Mm(voxel),
            remesh: HullRemesh::EdgeMm(1.0),
            ..HullOptions::default()
        };
        let (hull, _) = visual_hull(&sils, &o, &Silent).unwrap();
        ensure_valid(&hull).unwrap();
        let truth = glasscan::mesh::io::read_mesh(&dir.path().join("ground_truth.ply")).unwrap();
        let samples: Vec<Point3<f64>> = sample_surface(&truth, 100_000, 4)
            .into_iter()
            .map(|(p, _)| p)
            .collect();
        assert_eq!(outside_points(&hull, &samples, voxel), 0, "{name}");
    }
}
