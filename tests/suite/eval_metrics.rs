//! The reconstruction metrics against closed forms.

use glasscan::eval::{evaluate, EvalOptions};
use glasscan::mesh::shapes::{icosphere, torus};

#[test]
fn a_mesh_against_itself_scores_zero() {
    for mesh in [icosphere(50.0, 5), torus(40.0, 10.0, 128, 48)] {
        let opts = EvalOptions {
            samples: 100_000,
            ..Default::default()
        };
        let r = evaluate(&mesh, &mesh, &opts).unwrap();
        let tol = 1e-6 * mesh.bbox_diagonal();
        assert!(r.accuracy_mm < tol && r.completeness_mm < tol, "{r:?}");
        assert!(r.signed_accuracy_mm.abs() < tol, "{r:?}");
        assert!(r.drt_mean_mm < tol && r.hausdorff_mm < tol, "{r:?}");
        assert!(r.fscores.iter().all(|f| f.fscore == 1.0), "{r:?}");
    }
}

#[test]
fn concentric_spheres_half_a_millimetre_apart() {
    // Level 7: 327,680 faces, edges ≈ 0.2 mm: the chord error (< 0.001 mm) is far below 1 % of 0.5 mm.
    let inner = icosphere(50.0, 7);
    let outer = icosphere(50.5, 7);
    let opts = EvalOptions {
        samples: 200_000,
        thresholds_mm: vec![0.25, 1.0],
        seed: 4,
    };
    let r = evaluate(&outer, &inner, &opts).unwrap();
    // The larger sphere lies wholly outside the smaller one, and the smaller inside the larger.
    assert!((r.signed_accuracy_mm - 0.5).abs() <= 0.005, "{r:?}");
    assert_eq!(r.outside_share, 1.0);
    let back = evaluate(&inner, &outer, &opts).unwrap();
    assert!((back.signed_accuracy_mm + 0.5).abs() <= 0.005, "{back:?}");
    assert_eq!(back.outside_share, 0.0);
    for (name, v) in [
        ("accuracy", r.accuracy_mm),
        ("completeness", r.completeness_mm),
        ("DRT", r.drt_mean_mm),
    ] {
        assert!((v - 0.5).abs() <= 0.005, "{name} = {v}");
    }
    assert!(
        (r.hausdorff_mm - 0.5).abs() < 0.01,
        "Hausdorff {}",
        r.hausdorff_mm
    );
    let f = |t: f64| {
        r.fscores
            .iter()
            .find(|f| f.threshold_mm == t)
            .unwrap()
            .fscore
    };
    assert_eq!(f(1.0), 1.0);
    assert_eq!(f(0.25), 0.0);
}

#[test]
fn same_seed_same_figures_other_seed_other_samples() {
    let a = icosphere(10.0, 3);
    let b = icosphere(10.2, 4);
    let opts = EvalOptions {
        samples: 20_000,
        seed: 9,
        ..Default::default()
    };
    let r1 = evaluate(&a, &b, &opts).unwrap();
    let r2 = evaluate(&a, &b, &opts).unwrap();
    assert_eq!(r1, r2);
    let r3 = evaluate(&a, &b, &EvalOptions { seed: 10, ..opts }).unwrap();
    assert_ne!(r1.accuracy_mm, r3.accuracy_mm);
}
