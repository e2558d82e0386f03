//! `glasscan capture` under Xvfb with a file-backed camera: a recorded 2-view capture replays
//! into a scan that `decode` accepts, and an interrupted capture resumes at the first missing
//! image.

use std::path::Path;

use glasscan::capture::capture_order;
use glasscan::mesh::shapes::ellipsoid;
use glasscan::scan::ScanConfig;
use glasscan::simulate::{simulate, SimulateOptions};
use nalgebra::Vector3;

use crate::common::{ok, refused, run, s};

/// Runs `glasscan ARGS` in a virtual X server (package xvfb; `make test` installs it). The X
/// authority file lives in a folder of the test's own: left to make and remove its own,
/// `xvfb-run` once failed to remove it under load and exited 5 in place of glasscan's status.
fn glasscan_in_xvfb(args: &[&str]) -> std::process::Output {
    let xvfb = Path::new("/usr/bin/xvfb-run");
    assert!(
        xvfb.is_file(),
        "xvfb-run is missing: `sudo apt-get install xvfb` (make test installs it)"
    );
    let auth = tempfile::tempdir().unwrap();
    let auth_file = auth.path().join("Xauthority");
    std::fs::File::create(&auth_file).unwrap();
    run(std::process::Command::new(xvfb)
        .arg("-a")
        .arg("--auth-file")
        .arg(&auth_file)
        .arg(env!("CARGO_BIN_EXE_glasscan"))
        .args(args))
}

/// The recorded frames: every view's captures in capture order, numbered from 0.
fn record_frames(scan: &Path, views: usize, frames: &Path, keep: usize) {
    std::fs::create_dir_all(frames).unwrap();
    let names = capture_order(&ScanConfig::load(scan).unwrap());
    let all = (0..views).flat_map(|v| names.iter().map(move |n| (v, n)));
    for (k, (v, name)) in all.take(keep).enumerate() {
        let from = scan
            .join("captures")
            .join(format!("view_{v:03}"))
            .join(name);
        std::fs::copy(from, frames.join(format!("{k:04}.png"))).unwrap();
    }
}

/// A scan folder with the rig's files and no captures.
fn empty_scan(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for f in ["scan.toml", "camera.yml", "screen.yml", "turntable.yml"] {
        std::fs::copy(from.join(f), to.join(f)).unwrap();
    }
}

/// Every image of `scan`'s two views is the one in `recorded`, to the bit.
fn assert_same_images(recorded: &Path, scan: &Path) {
    for v in ["view_000", "view_001"] {
        for name in capture_order(&ScanConfig::load(scan).unwrap()) {
            let a = opencv::imgcodecs::imread(s(&recorded.join("captures").join(v).join(&name)), 0)
                .unwrap();
            let b = opencv::imgcodecs::imread(s(&scan.join("captures").join(v).join(&name)), 0)
                .unwrap();
            let same =
                opencv::core::norm2(&a, &b, opencv::core::NORM_INF, &opencv::core::no_array())
                    .unwrap();
            assert_eq!(same, 0.0, "{v}/{name}");
        }
    }
}

#[test]
fn a_replayed_capture_decodes_and_an_interrupted_one_resumes_at_the_first_missing_image() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let recorded = d.join("recorded");
    let o = SimulateOptions {
        views: 2,
        width: 160,
        height: 120,
        spp: 1,
        ..Default::default()
    };
    simulate(
        &ellipsoid(Vector3::new(30.0, 24.0, 20.0), 4),
        &recorded,
        &o,
        |_| (),
    )
    .unwrap();
    let per_view = capture_order(&ScanConfig::load(&recorded).unwrap()).len();
    let cut = per_view + 12;
    record_frames(&recorded, 2, &d.join("all"), 2 * per_view);
    record_frames(&recorded, 2, &d.join("cut"), cut);
    let scan = d.join("scan");
    empty_scan(&recorded, &scan);
    let turns = d.join("turns.txt");
    let turn_cmd = format!("echo {{view}} {{angle}} >> {}", s(&turns));
    let capture = |frames: &str| {
        let camera = d.join(frames).join("%04d.png");
        glasscan_in_xvfb(&[
            "capture",
            s(&scan),
            "--camera",
            s(&camera),
            "--settle-ms",
            "1",
            "--turn-cmd",
            &turn_cmd,
        ])
    };

    // The camera runs out of frames in view 1: a clean error naming the image to resume at.
    let missing = scan
        .join("captures/view_001")
        .join(&capture_order(&ScanConfig::load(&scan).unwrap())[12]);
    refused(
        &capture("cut"),
        &format!("{}: no image from the camera", missing.display()),
    );
    assert!(!missing.exists());
    // The rerun starts there: it grabs only what is missing and turns to view 1 again.
    let out = ok(&capture("all"));
    assert!(
        out.contains(&format!("resumed at {}", missing.display())),
        "{out}"
    );
    assert!(
        out.contains(&format!(
            "captured {} images ({cut} already there)",
            2 * per_view - cut
        )),
        "{out}"
    );
    assert_eq!(
        std::fs::read_to_string(&turns).unwrap(),
        "0 0\n1 180\n1 180\n"
    );
    // Every image is the recorded one, and the scan decodes.
    assert_same_images(&recorded, &scan);
    let decoded = ok(&crate::common::glasscan(&["decode", s(&scan)]));
    assert!(decoded.contains("decoded 2 views"), "{decoded}");
    // A complete capture is left as it is.
    let again = ok(&capture("all"));
    assert!(
        again.contains(&format!(
            "captured 0 images ({} already there)",
            2 * per_view
        )),
        "{again}"
    );
}

#[test]
fn capture_refuses_a_camera_it_cannot_open_and_a_missing_display() {
    let dir = tempfile::tempdir().unwrap();
    let recorded = dir.path().join("recorded");
    let sphere = ellipsoid(Vector3::new(30.0, 24.0, 20.0), 3);
    crate::common::decoded_scan(&recorded, &sphere, 1, (64, 48));
    let nowhere = dir.path().join("nowhere/%04d.png");
    let o = glasscan_in_xvfb(&[
        "capture",
        s(&recorded),
        "--camera",
        s(&nowhere),
        "--turn-cmd",
        "true",
    ]);
    refused(&o, "cannot open the camera");
    let o = run(crate::common::glasscan_cmd()
        .args([
            "capture",
            s(&recorded),
            "--camera",
            s(&nowhere),
            "--turn-cmd",
            "true",
        ])
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY"));
    refused(&o, "no display");
}
