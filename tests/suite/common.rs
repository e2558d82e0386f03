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
