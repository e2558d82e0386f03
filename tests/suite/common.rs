//! Helpers every test module shares: running the glasscan binary, judging its failures, small
//! simulated scans.
//!
//! Every child process of this test binary is spawned through [`spawn`] or [`run`]: HDF5 opens
//! files without close-on-exec and locks them, so a child spawned while another test holds an
//! HDF5 file open would inherit the lock. [`hdf5_open`] is held while a test has one open.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;

use glasscan::mesh::TriMesh;
use glasscan::simulate::{simulate, SimulateOptions};
use glasscan::trace::path::NormalModel;

static SPAWN: Mutex<()> = Mutex::new(());

/// Held while this process spawns a child or has an HDF5 file open.
pub fn hdf5_open() -> MutexGuard<'static, ()> {
    SPAWN.lock().unwrap_or_else(|e| e.into_inner())
}

/// Starts `cmd` while no HDF5 file is open in this process.
pub fn spawn(cmd: &mut Command) -> Child {
    let _open = hdf5_open();
    cmd.spawn()
        .unwrap_or_else(|e| panic!("cannot start {cmd:?}: {e}"))
}

/// Runs `cmd` to its end and returns its output.
pub fn run(cmd: &mut Command) -> Output {
    spawn(cmd.stdout(Stdio::piped()).stderr(Stdio::piped()))
        .wait_with_output()
        .expect("wait for a child")
}

/// Folders of fixtures several tests share, removed when this test binary exits.
static SHARED_DIRS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// A fresh folder for a fixture that several tests share and a `static` holds (a `static` is
/// never dropped, so a `TempDir` in one would stay behind in the system's temporary folder after
/// every run): removed, with what it holds, when this test binary exits.
pub fn shared_dir() -> PathBuf {
    static REGISTER: std::sync::Once = std::sync::Once::new();
    REGISTER.call_once(|| {
        // SAFETY: `remove_shared_dirs` is an `extern "C"` function that does not unwind.
        let registered = unsafe { libc::atexit(remove_shared_dirs) };
        assert_eq!(registered, 0, "cannot register the shared folders' removal");
    });
    let dir = tempfile::tempdir().expect("a temporary folder").keep();
    lock_shared_dirs().push(dir.clone());
    dir
}

fn lock_shared_dirs() -> MutexGuard<'static, Vec<PathBuf>> {
    SHARED_DIRS.lock().unwrap_or_else(|e| e.into_inner())
}

/// Removes the folders [`shared_dir`] made (at the test binary's exit).
extern "C" fn remove_shared_dirs() {
    let dirs = std::mem::take(&mut *lock_shared_dirs());
    for dir in dirs {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// The glasscan binary, ready for arguments.
pub fn glasscan_cmd() -> Command {
    Command::new(env!("CARGO_BIN_EXE_glasscan"))
}

/// Runs the glasscan binary with `args`.
pub fn glasscan<S: AsRef<OsStr>>(args: &[S]) -> Output {
    run(glasscan_cmd().args(args))
}

pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Asserts success and returns standard output.
pub fn ok(o: &Output) -> String {
    assert!(o.status.success(), "{}", stderr(o));
    stdout(o)
}

/// Asserts a refusal in glasscan's words: exit status `code` (1 for glasscan's errors, 2 for the
/// argument parser's), no panic, no OpenCV assertion, and `needle` in an error line.
pub fn refused_with(o: &Output, code: i32, needle: &str) {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(code), "stderr: {err}");
    for bad in ["panicked", "RUST_BACKTRACE", "Assertion failed", "OpenCV("] {
        assert!(!err.contains(bad), "{err}");
    }
    let prefix = if code == 1 { "error: " } else { "error" };
    assert!(
        err.lines()
            .any(|l| l.starts_with(prefix) && l.contains(needle))
            || (code != 1 && err.contains(needle)),
        "expected '{needle}' in an error line of: {err}"
    );
}

/// [`refused_with`] for glasscan's own errors (exit status 1).
pub fn refused(o: &Output, needle: &str) {
    refused_with(o, 1, needle);
}

/// [`refused`], and the whole of standard error is that one line.
pub fn refused_in_one_line(o: &Output, needle: &str) {
    refused(o, needle);
    let err = stderr(o);
    assert_eq!(err.lines().count(), 1, "one line expected: {err}");
}

/// A path as an argument.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 path")
}

/// A scan of `mesh` with decoded correspondences only (no captures): `views` views at
/// `width`×`height` pixels, one sample per pixel, the simulator's default rig.
pub fn decoded_scan(dir: &Path, mesh: &TriMesh, views: usize, size: (u32, u32)) -> PathBuf {
    decoded_scan_with_normals(dir, mesh, views, size, NormalModel::Vertex)
}

/// [`decoded_scan`] with the object refracting at `normals` (flat facets: `Face`).
pub fn decoded_scan_with_normals(
    dir: &Path,
    mesh: &TriMesh,
    views: usize,
    (width, height): (u32, u32),
    normals: NormalModel,
) -> PathBuf {
    let opts = SimulateOptions {
        views,
        width,
        height,
        spp: 1,
        decoded_only: true,
        normals,
        ..Default::default()
    };
    simulate(mesh, dir, &opts, |_| ()).expect("simulate a small scan");
    dir.to_path_buf()
}

/// The glass ellipsoid (30 × 22 × 18 mm semi-axes) captured in `dir/scan` with `capture`'s
/// settings (views, samples, noise, blur, index) by a 320×240 camera before a 1920×1200 monitor
/// of 0.2 mm pixels, a camera pixel spanning about 4 monitor pixels as in a rig; returns the
/// scan folder (not decoded).
pub fn fine_monitor_ellipsoid(dir: &Path, capture: SimulateOptions) -> PathBuf {
    let scan = dir.join("scan");
    let opts = SimulateOptions {
        width: 320,
        height: 240,
        screen_width: 1920,
        screen_height: 1200,
        pitch_mm: 0.2,
        ..capture
    };
    let shape = glasscan::mesh::shapes::ellipsoid(nalgebra::Vector3::new(30.0, 22.0, 18.0), 4);
    simulate(&shape, &scan, &opts, |_| ()).expect("simulate the ellipsoid");
    scan
}

/// Every file below `dir` with its bytes, by relative path.
pub fn snapshot(dir: &Path) -> std::collections::BTreeMap<PathBuf, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

/// Runs `args` to its end `kills` times, each time killed (SIGKILL) after a delay drawn from
/// 0..`span` by `seed`, then once uninterrupted: that run must succeed, and no temporary of the
/// output `out` (`.NAME.glasscan-*`, its lock) may be left beside it.
pub fn killed_then_rerun(args: &[&str], out: &Path, kills: usize, span: Duration, seed: u64) {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    for _ in 0..kills {
        let mut child = spawn(
            glasscan_cmd()
                .args(args)
                .stdout(Stdio::null())
                .stderr(Stdio::null()),
        );
        std::thread::sleep(span.mul_f64(rng.random_range(0.0..1.0)));
        let _ = child.kill();
        child.wait().unwrap();
    }
    let o = glasscan(args);
    assert!(o.status.success(), "rerun of {args:?}: {}", stderr(&o));
    let name = out.file_name().unwrap().to_string_lossy().into_owned();
    let left: Vec<String> = std::fs::read_dir(out.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&format!(".{name}.glasscan")))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

/// The lines of a Markdown text with whether each lies inside a fenced code block (the fence
/// lines themselves left out).
pub fn markdown_lines(text: &str) -> Vec<(&str, bool)> {
    let mut in_block = false;
    let mut out = Vec::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
        } else {
            out.push((line, in_block));
        }
    }
    out
}
