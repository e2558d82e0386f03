//! `glasscan reconstruct`: resuming after a crash gives the uninterrupted result; bad input.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use glasscan::mesh::shapes::ellipsoid;
use glasscan::simulate::{simulate, SimulateOptions};
use nalgebra::Vector3;

fn glasscan(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_glasscan"))
        .args(args)
        .output()
        .expect("run glasscan")
}

fn small_scan(dir: &Path) {
    let opts = SimulateOptions {
        views: 12,
        width: 240,
        height: 180,
        spp: 1,
        decoded_only: true,
        ..Default::default()
    };
    simulate(
        &ellipsoid(Vector3::new(30.0, 24.0, 20.0), 4),
        dir,
        &opts,
        |_| (),
    )
    .unwrap();
}

const CONFIG: &str =
    "stages = 3\nstart_edge = 0.1\nfinal_edge = 0.04\niterations = 8\nrefraction_views = 2\n";

#[test]
fn a_killed_run_resumes_to_the_same_result() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    small_scan(&scan);
    let config = dir.path().join("c.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let args = |out: &Path| {
        vec![
            "reconstruct".to_string(),
            scan.to_str().unwrap().to_string(),
            "-o".into(),
            out.to_str().unwrap().to_string(),
            "--config".into(),
            config.to_str().unwrap().to_string(),
            "--seed".into(),
            "7".into(),
        ]
    };
    let whole = dir.path().join("whole");
    let o = Command::new(env!("CARGO_BIN_EXE_glasscan"))
        .args(args(&whole))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // Kill the second run as soon as its first stage is saved (it is then in stage 2).
    let killed = dir.path().join("killed");
    let mut child = Command::new(env!("CARGO_BIN_EXE_glasscan"))
        .args(args(&killed))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !killed.join("stage_00.ply").is_file() {
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "stage 1 never finished"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(
        !killed.join("result.ply").exists(),
        "the run finished before it was killed"
    );
    // Without --resume the folder is refused; with it the run completes.
    let o = Command::new(env!("CARGO_BIN_EXE_glasscan"))
        .args(args(&killed))
        .output()
        .unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--resume"));
    let mut resume = args(&killed);
    resume.push("--resume".into());
    let o = Command::new(env!("CARGO_BIN_EXE_glasscan"))
        .args(&resume)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        std::fs::read(whole.join("result.ply")).unwrap(),
        std::fs::read(killed.join("result.ply")).unwrap(),
        "resumed result differs from the uninterrupted one"
    );
    for f in ["report.json", "loss.png", "hull.ply", "stage_02.ply"] {
        assert!(whole.join(f).is_file(), "{f}");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(whole.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["settings"]["seed"], 7);
    assert_eq!(report["stages"].as_array().unwrap().len(), 3);
}

#[test]
fn bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    small_scan(&scan);
    let (scan_arg, out) = (scan.to_str().unwrap(), dir.path().join("out"));
    let config = dir.path().join("c.toml");
    // Runs reconstruct with `extra` arguments and checks for a one-line error containing `needle`.
    let fails_with = |extra: &[&str], needle: &str| {
        let mut args = vec!["reconstruct", scan_arg, "-o", out.to_str().unwrap()];
        args.extend_from_slice(extra);
        let o = glasscan(&args);
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        assert!(
            o.status.code() == Some(1) && err.contains(needle),
            "{args:?}: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
    };
    let with_config = ["--config", config.to_str().unwrap()];
    std::fs::write(&config, "iterationz = 3\n").unwrap();
    fails_with(&with_config, "unknown setting 'iterationz'");
    std::fs::write(&config, "stages = 0\n").unwrap();
    fails_with(&with_config, "stages");
    fails_with(&["--preset", "fastest"], "--preset fastest");
    // A scan without decoded data.
    std::fs::remove_dir_all(scan.join("decoded")).unwrap();
    fails_with(&[], "glasscan decode");
}
