//! A blurred camera's decoded points against the centre-ray model, with and without the blur
//! correction (`glasscan::loss::blur`).

use crate::common::{fine_monitor_ellipsoid, glasscan};
use glasscan::loss::blur::{correct_targets, BlurKernel};
use glasscan::loss::refraction::ViewTargets;
use glasscan::loss::targets::scan_targets;
use glasscan::mesh::shapes::ellipsoid;
use glasscan::mesh::TriMesh;
use glasscan::scan::decoded::DecodedScan;
use glasscan::scan::Scan;
use glasscan::simulate::SimulateOptions;
use glasscan::trace::path::{trace_paths, MeshSurface, NormalModel, PathEnd, PathSettings};
use glasscan::trace::Ray;
use nalgebra::Vector3;

const IOR: f64 = 1.5;

/// Per decoded pixel whose centre ray refracts twice through `mesh`: the distance (mm, on the
/// monitor) from its decoded point to where that ray meets the monitor.
fn centre_ray_misses_mm(mesh: &TriMesh, targets: &[ViewTargets]) -> Vec<f64> {
    let surface = MeshSurface::new(mesh, NormalModel::Vertex).unwrap();
    let mut misses = Vec::new();
    for t in targets {
        let rays: Vec<Ray> = t.pixels.iter().map(|p| Ray::new(t.eye, p.dir)).collect();
        let paths = trace_paths(&surface, &rays, &PathSettings::new(IOR, 2)).unwrap();
        for (p, path) in t.pixels.iter().zip(paths) {
            if path.end != PathEnd::Left || path.refractions != 2 {
                continue;
            }
            let n = t.monitor_normal;
            let s = (t.monitor_point - path.origin).dot(&n) / path.dir.dot(&n);
            if s > 0.0 {
                misses.push((path.origin + path.dir * s - p.target).norm());
            }
        }
    }
    misses
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn a_blurred_cameras_decoded_points_corrected_for_the_blur_meet_the_centre_rays() {
    // A glass ellipsoid through a camera blurred by 1 px, its pixel spanning ~4 monitor pixels:
    // where the glass magnifies a pixel's neighbourhood unevenly its blurred Gray bits decode
    // off the point its centre ray reaches, even on the true shape at the true index.
    // Corrected on the true shape, the decoded points lie nearer the centre rays' points.
    let dir = tempfile::tempdir().unwrap();
    let opts = SimulateOptions {
        views: 3,
        spp: 4,
        blur_px: 1.0,
        ior: IOR,
        ..Default::default()
    };
    let scan_dir = fine_monitor_ellipsoid(dir.path(), opts);
    let shape = ellipsoid(Vector3::new(30.0, 22.0, 18.0), 4);
    let o = glasscan(&["decode", scan_dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scan = Scan::open(&scan_dir).unwrap();
    // simulate records the captures' blur in scan.toml, and decode measures it on the
    // background captures (low: the simulator blurs on the pixel grid and takes 4 area samples,
    // narrower than a pixel's square: docs/architecture.md §4).
    assert_eq!(scan.config.blur_px, Some(1.0));
    let size = (scan.camera.width, scan.camera.height);
    let measured = DecodedScan::open(&scan_dir, size).unwrap().blur.unwrap();
    eprintln!("blur 1 px, measured {measured:?}");
    assert!((measured.sigma_px - 1.0).abs() < 0.2, "{measured:?}");
    let views: Vec<usize> = (0..3).collect();
    let (targets, _) = scan_targets(&scan, &views, Default::default()).unwrap();

    let kernel = BlurKernel::gaussian(1.0).unwrap();
    let surface = MeshSurface::new(&shape, NormalModel::Vertex).unwrap();
    let picked: Vec<&_> = targets.iter().collect();
    let (corrected, summary) =
        correct_targets(&surface, IOR, &kernel, &picked, (true, true)).unwrap();
    let before = centre_ray_misses_mm(&shape, &targets);
    let after = centre_ray_misses_mm(&shape, &corrected);
    let (b, a) = (mean(&before), mean(&after));
    eprintln!(
        "{} pixels: mean miss {b:.3} mm as decoded, {a:.3} mm corrected ({summary:?})",
        before.len()
    );
    assert!(
        before.len() > 10_000 && summary.corrected > 10_000,
        "{summary:?}"
    );
    assert!(a < 0.7 * b, "{a} against {b}");

    // Marked only: the points as decoded, the same pixels marked as no evidence of the index;
    // those are the pixels whose decoded points the blur skews most.
    let (marked, only) = correct_targets(&surface, IOR, &kernel, &picked, (false, true)).unwrap();
    assert_eq!(
        (only.corrected, only.skewed),
        (0, summary.skewed),
        "{only:?}"
    );
    for ((m, c), t) in marked.iter().zip(&corrected).zip(&targets) {
        for ((m, c), t) in m.pixels.iter().zip(&c.pixels).zip(&t.pixels) {
            assert_eq!((m.target, m.index_evidence), (t.target, c.index_evidence));
        }
    }
    let evidence = |flag: bool| -> Vec<ViewTargets> {
        let pick = |(t, m): (&ViewTargets, &ViewTargets)| ViewTargets {
            pixels: (t.pixels.iter().zip(&m.pixels))
                .filter(|(_, m)| m.index_evidence == flag)
                .map(|(p, _)| *p)
                .collect(),
            ..t.clone()
        };
        targets.iter().zip(&marked).map(pick).collect()
    };
    let skewed = mean(&centre_ray_misses_mm(&shape, &evidence(false)));
    let kept = mean(&centre_ray_misses_mm(&shape, &evidence(true)));
    eprintln!(
        "{} pixels marked: mean miss {skewed:.3} mm, the others {kept:.3} mm",
        only.skewed
    );
    assert!(
        only.skewed > 100 && skewed > 3.0 * kept,
        "{only:?}: {skewed} against {kept}"
    );
}
