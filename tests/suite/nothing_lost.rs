//! Nothing a user had is lost, and nothing silently wrong is written: partial decodes, outputs
//! over inputs, resuming from other inputs, two runs at once, kills at any instant, values out
//! of range, 16-bit captures, pattern folders written again. Each test names the row of the
//! reproducer it answers; every input is checked byte-identical afterwards.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use crate::common::{
    glasscan, glasscan_cmd, killed_then_rerun, ok, refused, refused_with, s, snapshot, spawn,
    stderr,
};
use glasscan::mesh::shapes::icosphere;
use glasscan::simulate::{simulate, SimulateOptions};
use opencv::core::{Mat, MatTraitConst, Vector, CV_16U};

/// A 4-view 160×120 scan of a 25 mm sphere with its captures (no decode), made once; tests
/// copy it before changing anything.
fn captured() -> &'static Path {
    static SCAN: OnceLock<PathBuf> = OnceLock::new();
    SCAN.get_or_init(|| {
        let path = crate::common::shared_dir().join("S");
        let o = captured_options();
        simulate(&icosphere(25.0, 3), &path, &o, |_| ()).unwrap();
        path
    })
}

/// The simulation of [`captured`].
fn captured_options() -> SimulateOptions {
    SimulateOptions {
        views: 4,
        width: 160,
        height: 120,
        spp: 1,
        ..Default::default()
    }
}

/// A copy of [`captured`] in `dir`, decoded when `decode`.
fn scan_copy(dir: &Path, decode: bool) -> PathBuf {
    let to = dir.join("S");
    copy_tree(captured(), &to);
    if decode {
        ok(&glasscan(&["decode", s(&to)]));
    }
    to
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), dst).unwrap();
        }
    }
}

/// Row 1: a decode of some views keeps the other views and the user's own files.
#[test]
fn a_partial_decode_keeps_the_other_views_and_foreign_files() {
    let dir = tempfile::tempdir().unwrap();
    let scan = scan_copy(dir.path(), true);
    let decoded = scan.join("decoded");
    std::fs::write(decoded.join("notes.txt"), "mine").unwrap();
    let before = snapshot(&decoded);
    ok(&glasscan(&["decode", s(&scan), "--views", "0-1"]));
    let after = snapshot(&decoded);
    for (name, bytes) in &before {
        let n = name.to_string_lossy();
        if n.contains("view_002") || n.contains("view_003") || n == "notes.txt" {
            assert_eq!(after.get(name), Some(bytes), "{n} changed or went");
        }
    }
    let summary: serde_json::Value =
        serde_json::from_slice(&after[Path::new("summary.json")]).unwrap();
    let views: Vec<u64> = summary["views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["view"].as_u64().unwrap())
        .collect();
    assert_eq!(views, [0, 1, 2, 3]);
    ok(&glasscan(&[
        "hull",
        s(&scan),
        "-o",
        s(&dir.path().join("h.ply")),
    ]));
}

/// Rows 2 and 2b: an output that is an input, or lies in an input folder, is refused and the
/// input left as it was; an output's extension names its format.
#[test]
fn outputs_over_inputs_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scan = scan_copy(dir.path(), true);
    let before = snapshot(&scan);
    let h = dir.path().join("h.ply");
    let summary = scan.join("decoded/summary.json");
    refused(
        &glasscan(&["hull", s(&scan), "-o", s(&h), "--report", s(&summary)]),
        "would overwrite the input",
    );
    refused(
        &glasscan(&["hull", s(&scan), "-o", s(&scan.join("scan.toml"))]),
        "would overwrite the input",
    );
    let run = dir.path().join("R");
    refused(
        &glasscan(&["reconstruct", s(&scan), "-o", s(&scan.join("decoded"))]),
        "would overwrite the input",
    );
    // Calibration: an input image, the camera file, a wrong extension.
    let images = scan.join("captures/view_000/*.png");
    let image = scan.join("captures/view_000/00.png");
    let camera = scan.join("camera.yml");
    let calibrate = |step: &str, out: &Path, extra: &[&str]| {
        let mut args = vec![
            "calibrate",
            step,
            "--images",
            s(&images),
            "--board",
            "9x6",
            "--square-mm",
            "25",
            "-o",
            s(out),
        ];
        args.extend_from_slice(extra);
        glasscan(&args)
    };
    refused(&calibrate("camera", &image, &[]), "give it that extension");
    refused(
        &calibrate("camera", &dir.path().join("x.txt"), &[]),
        "give it that extension",
    );
    let o = calibrate(
        "turntable",
        &camera,
        &["--angles=0", "--camera", s(&camera)],
    );
    refused(&o, "would overwrite the input");
    // Benchmarks: a JSON report over the mesh, a work folder over the meshes.
    let mesh = dir.path().join("m.ply");
    glasscan::mesh::io::write_mesh(&mesh, &icosphere(10.0, 1)).unwrap();
    let mesh_bytes = std::fs::read(&mesh).unwrap();
    refused(
        &glasscan(&["bench", "trace", "--mesh", s(&mesh), "--json", s(&mesh)]),
        "give it that extension",
    );
    refused(
        &glasscan(&[
            "bench",
            "calibrated",
            "--meshes",
            s(dir.path()),
            "--work",
            s(dir.path()),
        ]),
        "would overwrite the input",
    );
    assert_eq!(std::fs::read(&mesh).unwrap(), mesh_bytes);
    assert!(before == snapshot(&scan), "an input changed");
    assert!(!run.exists() && !h.exists());
}

/// A small reconstruction: one warm-up and one Large Steps stage of a few iterations.
const CONFIG: &str = "warmup_stages = 1\nstages = 2\nstart_edge = 0.2\nfinal_edge = 0.1\niterations = 30\nrefraction_views = 2\n";

fn reconstruct_args<'a>(scan: &'a Path, config: &'a Path, out: &'a Path) -> Vec<&'a str> {
    vec!["reconstruct", s(scan), "-o", s(out), "--config", s(config)]
}

/// Row 3: `--resume` from another scan (or the same scan decoded again) is refused, naming what
/// changed.
#[test]
fn resuming_from_other_inputs_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let a = scan_copy(&dir.path().join("a"), true);
    let config = dir.path().join("c.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let out = dir.path().join("R");
    ok(&glasscan(&reconstruct_args(&a, &config, &out)));
    let before = snapshot(&out);
    // Another scan: the same object, another ior.
    let b = scan_copy(&dir.path().join("b"), true);
    let toml = std::fs::read_to_string(b.join("scan.toml")).unwrap();
    let ior = toml.lines().find(|l| l.starts_with("ior")).unwrap();
    std::fs::write(b.join("scan.toml"), toml.replace(ior, "ior = 1.5")).unwrap();
    let mut args = reconstruct_args(&b, &config, &out);
    args.push("--resume");
    refused(&glasscan(&args), "(scan.toml changed since)");
    // The same rig captured again (with sensor noise) and decoded again.
    let noisy = dir.path().join("noisy");
    let o = SimulateOptions {
        noise: 3.0,
        ..captured_options()
    };
    simulate(&icosphere(25.0, 3), &noisy, &o, |_| ()).unwrap();
    std::fs::remove_dir_all(a.join("captures")).unwrap();
    copy_tree(&noisy.join("captures"), &a.join("captures"));
    ok(&glasscan(&["decode", s(&a)]));
    let mut args = reconstruct_args(&a, &config, &out);
    args.push("--resume");
    refused(&glasscan(&args), "(decoded changed since)");
    assert!(
        before == snapshot(&out),
        "the refused runs changed the output"
    );
}

/// Row 4: a second run on a folder a run is writing, or `--force` on it, is refused while the
/// first lives; once it is killed, `--resume` finishes it.
#[test]
fn two_runs_on_one_folder_are_not_let_in_together() {
    let dir = tempfile::tempdir().unwrap();
    let scan = scan_copy(dir.path(), true);
    let config = dir.path().join("c.toml");
    std::fs::write(
        &config,
        CONFIG.replace("iterations = 30", "iterations = 400"),
    )
    .unwrap();
    let out = dir.path().join("R");
    let args = reconstruct_args(&scan, &config, &out);
    let mut first = spawn(
        glasscan_cmd()
            .args(&args)
            .stdout(Stdio::null())
            .stderr(Stdio::null()),
    );
    let t0 = Instant::now();
    while !out.join("checkpoint.json").is_file() {
        assert!(t0.elapsed() < Duration::from_secs(120), "no checkpoint");
        std::thread::sleep(Duration::from_millis(10));
    }
    for extra in [None, Some("--force"), Some("--resume")] {
        let mut a = args.clone();
        a.extend(extra);
        refused(&glasscan(&a), "another glasscan process is writing");
    }
    assert!(
        first.try_wait().unwrap().is_none(),
        "the first run ended before it could be raced"
    );
    first.kill().unwrap();
    first.wait().unwrap();
    assert!(
        out.join("checkpoint.json").is_file(),
        "the run's files are intact"
    );
    let mut a = args.clone();
    a.push("--resume");
    ok(&glasscan(&a));
    assert!(out.join("result.ply").is_file());
}

/// Rows 5 and 6: `decode` and `simulate --force` killed at seeded random instants, then run
/// again: the rerun succeeds and leaves no temporary behind; a kill between the two renames of
/// a folder replacement (the old folder only set aside) is put right by the next run.
#[test]
fn commands_killed_anywhere_are_put_right_by_the_next_run() {
    let dir = tempfile::tempdir().unwrap();
    let scan = scan_copy(dir.path(), true);
    let decode = ["decode", s(&scan)];
    let t0 = Instant::now();
    ok(&glasscan(&decode));
    killed_then_rerun(&decode, &scan.join("decoded"), 6, t0.elapsed(), 1);

    let mesh = dir.path().join("ball.ply");
    glasscan::mesh::io::write_mesh(&mesh, &icosphere(25.0, 2)).unwrap();
    let out = dir.path().join("sim");
    let sim = [
        "simulate",
        "--mesh",
        s(&mesh),
        "--out",
        s(&out),
        "--views",
        "3",
        "--size",
        "120x90",
        "--spp",
        "1",
        "--force",
    ];
    let t0 = Instant::now();
    ok(&glasscan(&sim));
    killed_then_rerun(&sim, &out, 6, t0.elapsed(), 2);

    // Killed between the renames: decoded/ only aside, with the new decode's temporary.
    let decoded = scan.join("decoded");
    let before = snapshot(&decoded);
    let aside = scan.join(".decoded.glasscan-killed.old");
    std::fs::rename(&decoded, &aside).unwrap();
    std::fs::create_dir(scan.join(".decoded.glasscan-killed")).unwrap();
    ok(&glasscan(&["decode", s(&scan), "--views", "0"]));
    let after = snapshot(&decoded);
    for (name, bytes) in &before {
        if !name.to_string_lossy().contains("view_000") && name != Path::new("summary.json") {
            assert_eq!(after.get(name), Some(bytes), "{} lost", name.display());
        }
    }
    let left: Vec<_> = std::fs::read_dir(&scan)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .filter(|n| n.to_string_lossy().starts_with(".decoded"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

/// Rows 8 and 9: an index out of (1, 4], a camera blur out of 0–5 px, angles that are not
/// turntable angles, and capture folders without an angle are refused where the scan is opened,
/// in short words.
#[test]
fn scan_values_out_of_range_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scan = scan_copy(dir.path(), false);
    let toml_path = scan.join("scan.toml");
    let toml = std::fs::read_to_string(&toml_path).unwrap();
    let ior = toml.lines().find(|l| l.starts_with("ior")).unwrap();
    let start = toml.find("angles_deg").unwrap();
    let angles = &toml[start..start + toml[start..].find(']').unwrap() + 1];
    let decode = || glasscan(&["decode", s(&scan)]);
    let blur = |v: &str| format!("{ior}\nblur_px = {v}");
    for (line, want) in [
        ("ior = 100.0".to_string(), "refractive index lies in (1, 4]"),
        ("ior = 1e300".to_string(), "ior = 1e300: a solid"),
        (blur("-1"), "blur_px = -1: the camera's blur"),
        (blur("nan"), "blur_px = NaN: the camera's blur"),
        (blur("80"), "0 to 5 (leave it out"),
    ] {
        std::fs::write(&toml_path, toml.replace(ior, &line)).unwrap();
        refused(&decode(), want);
    }
    std::fs::write(
        &toml_path,
        toml.replace(angles, "angles_deg = [0.0, 90.0, 180.0, 1e300]"),
    )
    .unwrap();
    refused(&decode(), "views.angles_deg holds 1e300");
    std::fs::write(
        &toml_path,
        toml.replace(angles, "angles_deg = [0.0, 90.0, 180.0]"),
    )
    .unwrap();
    refused(&decode(), "view_003 exists");
    let o = glasscan(&[
        "simulate", "--mesh", "m.ply", "--out", "x", "--ior", "1e300",
    ]);
    refused_with(&o, 2, "1e300");
    assert!(stderr(&o).len() < 400, "{}", stderr(&o));
}

/// Row 10: 12-bit data in 16-bit PNGs decode as the same captures in 8 bits do.
#[test]
fn sixteen_bit_captures_decode_by_their_depth() {
    let dir = tempfile::tempdir().unwrap();
    let scan = scan_copy(dir.path(), true);
    let pixels = |scan: &Path| -> u64 {
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(scan.join("decoded/summary.json")).unwrap())
                .unwrap();
        v["views"][0]["object_pixels"].as_u64().unwrap()
    };
    let eight = pixels(&scan);
    assert!(eight > 100, "{eight}");
    for dir in [
        scan.join("captures/view_000"),
        scan.join("captures/background"),
    ] {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            let m = opencv::imgcodecs::imread(s(&p), opencv::imgcodecs::IMREAD_GRAYSCALE).unwrap();
            let mut wide = Mat::default();
            m.convert_to(&mut wide, CV_16U, 4095.0 / 255.0, 0.0)
                .unwrap();
            opencv::imgcodecs::imwrite(s(&p), &wide, &Vector::new()).unwrap();
        }
    }
    ok(&glasscan(&["decode", s(&scan), "--views", "0"]));
    let twelve = pixels(&scan);
    assert!(
        (twelve as f64 - eight as f64).abs() <= 0.02 * eight as f64,
        "8-bit {eight} object pixels, 12-bit {twelve}"
    );
}

/// Row 11: `patterns` writes its folder whole: a non-empty one is refused without --force and
/// replaced whole with it, so no image of an earlier set is left.
#[test]
fn patterns_replace_their_folder_whole() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("P");
    ok(&glasscan(&[
        "patterns",
        "--screen",
        "256x128",
        "--out",
        s(&p),
        "--phase-shift",
        "4",
    ]));
    let many = std::fs::read_dir(&p).unwrap().count();
    refused(
        &glasscan(&["patterns", "--screen", "8x4", "--out", s(&p)]),
        "exists and is not empty",
    );
    ok(&glasscan(&[
        "patterns",
        "--screen",
        "8x4",
        "--out",
        s(&p),
        "--force",
    ]));
    let names: Vec<String> = std::fs::read_dir(&p)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.len() < many, "{names:?}");
    assert!(
        !names
            .iter()
            .any(|n| n.starts_with("phase_") || n == "20.png"),
        "{names:?}"
    );
}

/// Row 12: calibration files are read whatever characters their path holds.
#[test]
fn odd_path_characters_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let odd = dir.path().join("a?b [c]");
    let scan = scan_copy(&odd, true);
    ok(&glasscan(&[
        "hull",
        s(&scan),
        "-o",
        s(&dir.path().join("h.ply")),
    ]));
}
