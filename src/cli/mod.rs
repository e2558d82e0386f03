//! The command line: argument definitions (clap) and one small module per subcommand, each a
//! thin layer over the library.

/// `print!` that reports a failed write (a closed pipe, a full disk) as an error instead of
/// panicking.
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        write!(std::io::stdout().lock(), $($arg)*)?;
    }};
}

/// `println!` counterpart of [`out!`].
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*)?;
    }};
}

mod bench;
mod calibrate;
#[cfg(feature = "capture")]
mod capture;
mod common;
mod decode;
mod demo;
mod eval;
mod hull;
#[cfg(feature = "hdf5")]
mod import;
mod info;
mod patterns;
mod reconstruct;
mod remesh;
mod simulate;

use anyhow::Result;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use glasscan::util::atomic::write_json;

/// Reconstruct the mesh of a solid transparent object from a turntable Gray-code scan.
#[derive(Parser, Debug)]
#[command(name = "glasscan", version, about, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Memory limit, GiB: sizes from files and arguments that would need more are refused
    /// before anything is allocated (default: 3/4 of the machine's memory).
    #[arg(long = "max-memory-gb", global = true, value_parser = common::positive)]
    max_memory_gb: Option<f64>,
    /// Also show OpenCV's own log lines (warnings, information), silenced otherwise.
    #[arg(long, global = true)]
    verbose: bool,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Counts, bounding box, genus, edge lengths and the validation verdict of a mesh
    /// (exit code 1 if the mesh is not a closed, manifold, outward-oriented surface).
    Info(info::InfoArgs),
    /// Accuracy, completeness, F-scores, DRT's figure and Hausdorff distance against a reference.
    Eval(eval::EvalArgs),
    /// Decode a scan's captures: silhouettes and monitor points per view.
    Decode(decode::DecodeArgs),
    /// Calibrate the rig: camera, monitor pose, turntable axis.
    #[command(subcommand)]
    Calibrate(calibrate::CalibrateCommand),
    #[cfg(feature = "capture")]
    /// Show the patterns on the monitor and grab them with the camera, view by view.
    Capture(capture::CaptureArgs),
    /// The Gray-code images to show on the monitor, in OpenCV's order.
    Patterns(patterns::PatternsArgs),
    /// A synthetic scan of a mesh: calibration, captures and ground truth.
    Simulate(simulate::SimulateArgs),
    /// Isotropic remeshing to a target edge length.
    Remesh(remesh::RemeshArgs),
    #[cfg(feature = "hdf5")]
    /// A scan folder from DRT's published HDF5 captures.
    ImportDrt(import::ImportDrtArgs),
    /// The visual hull of a decoded scan's silhouettes.
    Hull(hull::HullArgs),
    /// The main job: optimise the mesh against a decoded scan, coarse to fine.
    Reconstruct(reconstruct::ReconstructArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Zero-setup first run on a built-in object.
    Demo(demo::DemoArgs),
}

/// Versions of glasscan and of the native libraries it was built against.
fn long_version() -> String {
    format!(
        "{} (Embree {}, OpenCV {})",
        env!("CARGO_PKG_VERSION"),
        glasscan::trace::embree_version(),
        opencv::core::get_version_string().unwrap_or_else(|_| "unknown".into())
    )
}

/// True when `e` is a write to a closed pipe (`glasscan … | head`): not worth reporting.
pub fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
    })
}

/// Parses the command line and runs the chosen subcommand.
pub fn run() -> Result<()> {
    let matches = Cli::command().long_version(long_version()).get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    // glasscan's own words only: OpenCV's `[ WARN:…]` lines would stand before its errors.
    if !cli.verbose {
        opencv::core::set_log_level(opencv::core::LogLevel::LOG_LEVEL_SILENT)?;
    }
    if let Some(gb) = cli.max_memory_gb {
        glasscan::util::budget::set_limit_gb(gb).map_err(anyhow::Error::msg)?;
    }
    match cli.command {
        Command::Info(a) => info::run(&a),
        Command::Eval(a) => eval::run(&a),
        Command::Decode(a) => decode::run(&a),
        Command::Calibrate(c) => calibrate::run(&c),
        #[cfg(feature = "capture")]
        Command::Capture(a) => capture::run(&a),
        Command::Patterns(a) => patterns::run(&a),
        Command::Simulate(a) => simulate::run(&a),
        Command::Remesh(a) => remesh::run(&a),
        #[cfg(feature = "hdf5")]
        Command::ImportDrt(a) => import::run(&a),
        Command::Hull(a) => hull::run(&a),
        Command::Reconstruct(a) => reconstruct::run(&a),
        Command::Bench(b) => bench::run(&b),
        Command::Demo(a) => demo::run(&a),
    }
}
