//! Careless and hostile input, one test per kind of mistake: nothing a user had is lost, nothing
//! wrong is written silently, and every refusal is a one-line error in glasscan's words with the
//! documented exit code (1 for errors, 2 for arguments clap rejects).

use std::path::{Path, PathBuf};

use glasscan::mesh::io::{read_mesh, write_mesh};
use glasscan::mesh::shapes::{figurine, icosphere};
use glasscan::mesh::TriMesh;
use nalgebra::Point3;

use crate::common::{decoded_scan, glasscan, ok, refused_with, s};

fn write(dir: &Path, name: &str, mesh: &TriMesh) -> PathBuf {
    let p = dir.join(name);
    write_mesh(&p, mesh).unwrap();
    p
}

/// Remeshing at edges too long for the shape is refused with the largest usable edge; a
/// collapsed mesh is not valid for `info`.
#[test]
fn a_remesh_that_loses_the_shape_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let input = write(dir.path(), "fig.ply", &figurine(2.0));
    let out = dir.path().join("out.ply");
    let o = glasscan(&["remesh", s(&input), "-o", s(&out), "--edge-mm", "30"]);
    refused_with(&o, 1, "the largest usable edge is about");
    assert!(!out.exists(), "a refused remesh wrote its output");
    // A flat, closed surface: two triangles back to back.
    let flat = TriMesh::new(
        vec![
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(10.0, 0.0, 0.0),
            Point3::new(0.0, 10.0, 0.0),
        ],
        vec![[0, 1, 2], [0, 2, 1]],
    );
    let flat = write(dir.path(), "flat.ply", &flat);
    let o = glasscan(&["info", s(&flat)]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stdout).contains("collapsed"));
}

/// A larger allowed chord error never gives a finer adaptive remesh.
#[test]
fn adaptive_sizing_grows_with_the_allowed_error() {
    let dir = tempfile::tempdir().unwrap();
    let input = write(dir.path(), "fig.ply", &figurine(2.0));
    let faces = |err: &str| {
        let out = dir.path().join(format!("a{err}.ply"));
        let args = [
            "remesh",
            s(&input),
            "-o",
            s(&out),
            "--edge-mm",
            "6",
            "--adaptive",
            "--max-error-mm",
            err,
        ];
        ok(&glasscan(&args));
        read_mesh(&out).unwrap().faces.len()
    };
    let (fine, coarse) = (faces("0.05"), faces("100"));
    assert!(
        coarse <= fine,
        "ε 100 mm: {coarse} faces, ε 0.05 mm: {fine}"
    );
    let x = dir.path().join("x.ply");
    for (extra, needle) in [
        (
            &["--edge-mm", "6", "--adaptive", "--min-edge-mm", "0"][..],
            "adaptive sizing needs 0 < min edge",
        ),
        (&["--edge-mm", "1e-300"][..], "use at least 0."),
        (
            &["--edge-mm", "3", "--iterations", "1000000000"][..],
            "at most 1000",
        ),
    ] {
        let args = [&["remesh", s(&input), "-o", s(&x)][..], extra].concat();
        refused_with(&glasscan(&args), 1, needle);
    }
}

/// `simulate` never mixes two scans: a non-empty folder needs --force, which replaces it whole.
#[test]
fn simulate_replaces_a_scan_whole_or_not_at_all() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let mesh = write(dir.path(), "ball.ply", &icosphere(20.0, 3));
    let base = [
        "simulate",
        "--mesh",
        s(&mesh),
        "--out",
        s(&scan),
        "--size",
        "160x120",
    ];
    let o = glasscan(&[&base[..], &["--views", "2", "--decoded-only"]].concat());
    refused_with(&o, 1, "exists and is not empty");
    assert!(scan.join("decoded/view_003_mask.png").is_file());
    ok(&glasscan(
        &[&base[..], &["--views", "2", "--decoded-only", "--force"]].concat(),
    ));
    assert!(
        !scan.join("decoded/view_003_mask.png").exists(),
        "a stale view was kept"
    );
    assert!(scan.join("decoded/view_001_mask.png").is_file());
    // The mesh the command reads is never inside the folder it replaces.
    let inside = write(&scan, "inside.ply", &icosphere(20.0, 2));
    let o = glasscan(&[
        "simulate",
        "--mesh",
        s(&inside),
        "--out",
        s(&scan),
        "--force",
        "--views",
        "2",
    ]);
    refused_with(&o, 1, "would overwrite the input");
    assert!(inside.is_file());
}

/// Sizes that would allocate beyond the memory limit, or take forever, are refused up front.
/// Two area samples cannot be centred on the pixel with its centre among them: `simulate`
/// refuses them before writing anything.
#[test]
fn two_area_samples_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let ball = write(dir.path(), "ball.ply", &icosphere(20.0, 2));
    let out = dir.path().join("never");
    let o = glasscan(&[
        "simulate",
        "--mesh",
        s(&ball),
        "--out",
        s(&out),
        "--spp",
        "2",
    ]);
    refused_with(&o, 1, "--spp 2");
    assert!(!out.exists());
}

#[test]
fn sizes_beyond_the_budget_are_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let ball = write(dir.path(), "ball.ply", &icosphere(20.0, 2));
    let o = glasscan(&[
        "eval",
        s(&ball),
        "--reference",
        s(&ball),
        "--samples",
        "1000000000",
        "--max-memory-gb",
        "1",
    ]);
    refused_with(&o, 1, "more than the limit of 1.0 GiB");
    let scan = small_scan(dir.path());
    let o = glasscan(&["decode", s(&scan), "--max-memory-gb", "0.001"]);
    refused_with(&o, 1, "decoding 160×120 captures");
    let o = glasscan(&[
        "hull",
        s(&scan),
        "-o",
        s(&dir.path().join("h.ply")),
        "--voxel-mm",
        "0.001",
    ]);
    refused_with(&o, 1, "--voxel-mm 0.001 is too fine");
    for (args, needle) in [
        (vec!["--views", "100000000"], "--views"),
        (vec!["--spp", "1000000"], "--spp"),
        (vec!["--screen", "100000x100000"], "between 1 and 16384"),
        (vec!["--ior", "nan"], "--ior"),
        (vec!["--fill", "0"], "(0, 1]"),
    ] {
        let mut a = vec!["simulate", "--mesh", s(&ball), "--out", "never"];
        a.extend(args);
        refused_with(&glasscan(&a), 2, needle);
        assert!(!Path::new("never").exists());
    }
    // A PLY header promising more vertices than memory holds.
    let ply = dir.path().join("huge.ply");
    std::fs::write(
        &ply,
        "ply\nformat binary_little_endian 1.0\nelement vertex 99999999999999\nproperty float x\n\
         property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n\
         end_header\n",
    )
    .unwrap();
    refused_with(&glasscan(&["info", s(&ply)]), 1, "more than the limit");
}

/// A 4-view 160×120 decoded scan of a 25 mm sphere in `dir/scan`.
fn small_scan(dir: &Path) -> PathBuf {
    decoded_scan(&dir.join("scan"), &icosphere(25.0, 3), 4, (160, 120))
}

/// A monitor behind the camera, or showing its back, is refused when the scan is opened.
#[test]
fn an_implausible_rig_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let screen = std::fs::read_to_string(scan.join("screen.yml")).unwrap();
    // Negate the z of translation_mm: the monitor moves behind the camera.
    let t = screen.find("translation_mm").unwrap();
    let open = t + screen[t..].find('[').unwrap();
    let close = open + screen[open..].find(']').unwrap();
    let xyz: Vec<f64> = screen[open + 1..close]
        .split(',')
        .map(|w| w.trim().parse().unwrap())
        .collect();
    let moved = format!(
        "{}[ {:e}, {:e}, {:e} ]{}",
        &screen[..open],
        xyz[0],
        xyz[1],
        -xyz[2],
        &screen[close + 1..]
    );
    std::fs::write(scan.join("screen.yml"), moved).unwrap();
    let o = glasscan(&["hull", s(&scan), "-o", s(&dir.path().join("h.ply"))]);
    refused_with(&o, 1, "the monitor lies behind the camera");
}

/// A decode summary whose measured blur is out of range is refused when the scan is read, naming
/// the file and what to do.
#[test]
fn a_measured_blur_out_of_range_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let path = scan.join("decoded/summary.json");
    let mut summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    for sigma in [-1.0, 80.0] {
        summary["blur"] = serde_json::json!({ "sigma_px": sigma, "edges": 500 });
        std::fs::write(&path, serde_json::to_vec(&summary).unwrap()).unwrap();
        let o = glasscan(&["hull", s(&scan), "-o", s(&dir.path().join("h.ply"))]);
        refused_with(&o, 1, "blur.sigma_px");
        refused_with(&o, 1, "decode the scan again");
    }
}

/// Decoder thresholds out of range are rejected when parsed; `auto` is accepted in any case.
#[test]
fn decoder_options_are_range_checked() {
    for (flag, value) in [
        ("--white-drop", "-0.5"),
        ("--min-contrast", "2"),
        ("--shift-px", "nan"),
        ("--min-modulation", "-1"),
        ("--max-hole", "-3"),
        ("--min-component", "1.5"),
    ] {
        let arg = format!("{flag}={value}");
        refused_with(&glasscan(&["decode", "nowhere", &arg]), 2, flag);
    }
    let o = glasscan(&["decode", "nowhere", "--white-drop", "AUTO"]);
    refused_with(&o, 1, "nowhere");
}

/// Config keys out of range are refused before any work, naming the key.
#[test]
fn config_values_are_range_checked() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let config = dir.path().join("c.toml");
    let out = dir.path().join("out");
    for (text, needle) in [
        ("robust = { huber = -1.0 }", "setting robust"),
        ("robust = { cauchy = 0.0 }", "setting robust"),
        ("max_refractions = 3", "setting max_refractions"),
        (
            "optimizer = { large_steps = { lambda = -20.0, lr_edge = 0.3, beta1 = 0.9, beta2 = 0.999 } }",
            "lambda and lr_edge must be positive",
        ),
        (
            "optimizer = { large_steps = { lambda = 20.0, lr_edge = 0.3, beta1 = 1.0, beta2 = 0.999 } }",
            "beta1 and beta2",
        ),
        (
            "optimizer = { large_steps = { lambda = 20.0, lr_edge = 0.3, beta1 = 0.9, beta2 = 0.999, clip = -1.0 } }",
            "clip must be 0 (off) or positive",
        ),
        (
            "optimizer = { large_steps = { lambda = 20.0, lr_edge = 0.3, beta1 = 0.9, beta2 = 0.999, lr_end_share = 0.0 } }",
            "lr_end_share must lie in (0, 1]",
        ),
        (
            "optimizer = { sgd = { lr_start = -0.1, lr_end = 0.05, momentum = 0.9 } }",
            "lr_start and lr_end",
        ),
        (
            "optimizer = { sgd = { lr_start = 0.1, lr_end = 0.05, momentum = 1.0 } }",
            "momentum",
        ),
        ("smoothness = { tolerant = { tau = 0.0 } }", "setting smoothness"),
        ("smoothness = { annealed = { tau = 0.1 } }", "annealed"),
        ("iterations = 1000000000", "setting iterations"),
        ("average_share = 1.0", "setting average_share"),
        ("average_share = -0.5", "setting average_share"),
    ] {
        std::fs::write(&config, text).unwrap();
        let o = glasscan(&["reconstruct", s(&scan), "-o", s(&out), "--config", s(&config)]);
        refused_with(&o, 1, needle);
        assert!(!out.exists(), "{text}: the run started");
    }
    let o = glasscan(&[
        "reconstruct",
        s(&scan),
        "-o",
        s(&out),
        "--hull-voxel-mm",
        "0",
    ]);
    refused_with(&o, 2, "--hull-voxel-mm");
    // An output that is a file is named before any work.
    let file = dir.path().join("file");
    std::fs::write(&file, "x").unwrap();
    let o = glasscan(&["reconstruct", s(&scan), "-o", s(&file)]);
    refused_with(&o, 1, &format!("{} is a file", file.display()));
}

/// `eval` refuses meshes without area, ignores stray vertices, and never writes over an input
/// or under a misleading extension.
#[test]
fn eval_refuses_empty_meshes_and_protects_its_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let ball = icosphere(20.0, 3);
    let a = write(dir.path(), "a.ply", &ball);
    let mut stray = ball.clone();
    stray.positions.push(Point3::new(500.0, 0.0, 0.0));
    let b = write(dir.path(), "b.ply", &stray);
    let out = ok(&glasscan(&["eval", s(&b), "--reference", s(&a)]));
    let hausdorff: f64 = out
        .lines()
        .find(|l| l.starts_with("Hausdorff"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{out}"));
    assert!(hausdorff < 1e-6, "{out}");
    let empty = TriMesh::new(vec![Point3::origin(); 3], vec![[0, 1, 2]]);
    let e = dir.path().join("e.ply");
    write_mesh(&e, &empty).unwrap();
    refused_with(
        &glasscan(&["eval", s(&e), "--reference", s(&a)]),
        1,
        "has no area",
    );
    let before = std::fs::read(&a).unwrap();
    refused_with(
        &glasscan(&["eval", s(&b), "--reference", s(&a), "--json", s(&a)]),
        1,
        "--json",
    );
    refused_with(
        &glasscan(&["eval", s(&b), "--reference", s(&a), "--error-map", s(&a)]),
        1,
        "--error-map",
    );
    assert_eq!(before, std::fs::read(&a).unwrap());
    refused_with(
        &glasscan(&[
            "eval",
            s(&b),
            "--reference",
            s(&a),
            "--error-map",
            s(&dir.path().join("m.jpg")),
        ]),
        1,
        ".png",
    );
    let scan = small_scan(dir.path());
    let x = dir.path().join("x.ply");
    refused_with(
        &glasscan(&["hull", s(&scan), "-o", s(&x), "--report", s(&x)]),
        1,
        "--report",
    );
}

/// Broken calibration files get glasscan's messages, never OpenCV's assertions.
#[test]
fn broken_calibration_files_are_explained() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let camera = std::fs::read_to_string(scan.join("camera.yml")).unwrap();
    let width_line = camera
        .lines()
        .find(|l| l.starts_with("image_width"))
        .unwrap()
        .to_string();
    let k_start = camera.find("camera_matrix").unwrap();
    let k_end = k_start + camera[k_start..].find("distortion_coefficients").unwrap();
    for (text, needle) in [
        (String::new(), "must start with %YAML"),
        (
            "%YAML:1.0\n---\nimage_width: [\n".to_string(),
            "cannot be parsed",
        ),
        (
            camera.replace(&width_line, "image_width: \"abc\""),
            "'image_width' must be a number",
        ),
        (
            format!(
                "{}camera_matrix: 5\n{}",
                &camera[..k_start],
                &camera[k_end..]
            ),
            "'camera_matrix' must be an !!opencv-matrix",
        ),
        (
            camera.replacen("rows: 3", "rows: 4", 1),
            "declares 4×3 but its data holds 9",
        ),
    ] {
        std::fs::write(scan.join("camera.yml"), &text).unwrap();
        let o = glasscan(&["hull", s(&scan), "-o", s(&dir.path().join("h.ply"))]);
        refused_with(&o, 1, needle);
        assert!(
            o.status.code() == Some(1) && String::from_utf8_lossy(&o.stderr).contains("camera.yml")
        );
    }
}

/// OBJ errors quote indices as written (1-based) with their line.
#[test]
fn obj_errors_quote_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("bad.obj");
    std::fs::write(&obj, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n").unwrap();
    refused_with(&glasscan(&["info", s(&obj)]), 1, "line 4");
    refused_with(&glasscan(&["info", s(&obj)]), 1, "vertex index 7");
    std::fs::write(&obj, "v 0 0 0\nf 1 -5 1\n").unwrap();
    refused_with(&glasscan(&["info", s(&obj)]), 1, "vertex index -5");
}

/// A folder that is not a scan is named as such, and a file output's missing folder is made
/// (as a folder output's is) rather than failing after the work.
#[test]
fn a_folder_without_scan_toml_and_a_missing_output_folder() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    for command in ["decode", "hull"] {
        let mut args = vec![command, s(&empty)];
        let out = dir.path().join("h.ply");
        if command == "hull" {
            args.extend(["-o", s(&out)]);
        }
        refused_with(
            &glasscan(&args),
            1,
            "is not a scan folder: it has no scan.toml",
        );
    }
    let input = write(dir.path(), "ball.ply", &icosphere(20.0, 3));
    let out = dir.path().join("new").join("deeper").join("ball.ply");
    ok(&glasscan(&[
        "remesh",
        s(&input),
        "--out",
        s(&out),
        "--edge-mm",
        "4",
    ]));
    assert!(read_mesh(&out).unwrap().faces.len() > 20);
    // A file where the output's folder should be.
    let file = dir.path().join("a-file");
    std::fs::write(&file, "").unwrap();
    let o = glasscan(&[
        "remesh",
        s(&input),
        "-o",
        s(&file.join("x.ply")),
        "--edge-mm",
        "4",
    ]);
    refused_with(&o, 1, "a file stands where a folder is needed");
}

/// A file that is not PLY is refused with the reader's one sentence, not its debug dump.
#[test]
fn a_broken_ply_gets_one_sentence() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.ply");
    std::fs::write(&bad, "garbage\n").unwrap();
    let o = glasscan(&["info", s(&bad)]);
    refused_with(
        &o,
        1,
        "not a readable PLY file: Line 1: Expected magic number 'ply'.",
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !err.contains("ParseError") && !err.contains("String:"),
        "{err}"
    );
}

/// A PNG cut short (a copy interrupted) is named as such before OpenCV reads it, without
/// libpng's own line; a missing or empty image is named too.
#[test]
fn a_png_cut_short_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("board.png");
    let grey = vec![128u8; 64 * 48];
    glasscan::util::image::write_pixels(&png, 64, 48, &grey).unwrap();
    let bytes = std::fs::read(&png).unwrap();
    std::fs::write(&png, &bytes[..bytes.len() - 20]).unwrap();
    let camera = dir.path().join("camera.yml");
    let run = |images: &Path| {
        glasscan(&[
            "calibrate",
            "camera",
            "--images",
            s(images),
            "--board",
            "9x6",
            "--square-mm",
            "25",
            "-o",
            s(&camera),
        ])
    };
    let o = run(&png);
    refused_with(&o, 1, "a PNG cut short");
    assert!(!String::from_utf8_lossy(&o.stderr).contains("libpng"));
    std::fs::write(&png, b"").unwrap();
    refused_with(&run(&png), 1, "not a readable image");
}
