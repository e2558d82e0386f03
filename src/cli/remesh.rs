//! `glasscan remesh IN -o OUT --edge-mm H`.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use clap::Args;

use glasscan::bench::remesh::{figures, RemeshFigures};
use glasscan::eval::fidelity::remesh_checked;
use glasscan::mesh::io::{read_mesh, write_mesh};
use glasscan::mesh::stats::{quality, MeshQuality};
use glasscan::remesh::{AdaptiveSizing, RemeshOptions};
use glasscan::util::paths::ensure_output_spares_inputs;

#[derive(Args, Debug)]
pub struct RemeshArgs {
    /// Input mesh (.ply or .obj): closed, manifold, consistently oriented.
    pub input: PathBuf,
    /// Output mesh (.ply or .obj).
    #[arg(short, long, visible_alias = "out")]
    pub output: PathBuf,
    /// Target edge length, mm (the largest one with --adaptive).
    #[arg(long = "edge-mm")]
    pub edge_mm: f64,
    /// Split–collapse–flip–relax iterations.
    #[arg(long, default_value_t = 10)]
    pub iterations: usize,
    /// Tangential relaxation passes per iteration.
    #[arg(long, default_value_t = 3)]
    pub relax_passes: usize,
    /// Adapt edge lengths to the curvature (between --min-edge-mm and --edge-mm).
    #[arg(long)]
    pub adaptive: bool,
    /// Smallest edge length with --adaptive, mm; default edge-mm / 5.
    #[arg(long = "min-edge-mm", requires = "adaptive")]
    pub min_edge_mm: Option<f64>,
    /// Largest chord deviation from the input with --adaptive, mm; default edge-mm / 50.
    #[arg(long = "max-error-mm", requires = "adaptive")]
    pub max_error_mm: Option<f64>,
    /// Keep sharp edges whose faces meet at more than this dihedral angle, degrees (off by
    /// default).
    #[arg(long = "feature-angle")]
    pub feature_angle_deg: Option<f64>,
    /// Seed of the surface sampling that measures the distance to the input.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn run(a: &RemeshArgs) -> Result<()> {
    ensure_output_spares_inputs(&a.output, "--output", &[&a.input])?;
    let input = read_mesh(&a.input)?;
    let adaptive = a.adaptive.then(|| AdaptiveSizing {
        min_edge_mm: a.min_edge_mm.unwrap_or(a.edge_mm / 5.0),
        max_error_mm: a.max_error_mm.unwrap_or(a.edge_mm / 50.0),
    });
    let opts = RemeshOptions {
        edge_mm: a.edge_mm,
        iterations: a.iterations,
        relax_passes: a.relax_passes,
        adaptive,
        feature_angle_deg: a.feature_angle_deg,
        edge_bound_mm: None,
    };
    let t0 = Instant::now();
    let (output, _) = remesh_checked(&input, &opts, a.seed)?;
    let seconds = t0.elapsed().as_secs_f64();
    write_mesh(&a.output, &output)?;
    let fig = figures(&input, &output, seconds, a.seed)?;
    outln!(
        "remeshed {} -> {} (h = {} mm{}, {} iterations) in {seconds:.2} s",
        a.input.display(),
        a.output.display(),
        a.edge_mm,
        if a.adaptive { ", adaptive" } else { "" },
        a.iterations
    );
    out!(
        "{}{}{}",
        header(""),
        row("input", &quality(&input), None),
        row("output", &fig.quality, Some(&fig))
    );
    Ok(())
}

/// Column titles of [`row`], after a first column titled `first`.
pub fn header(first: &str) -> String {
    format!(
        "{first:<28} {:>8} {:>9} {:>6} {:>8} {:>7} {:>6} {:>9} {:>8} {:>8}\n",
        "faces", "edge mm", "CV", "min ang", "<30° %", "val6 %", "dist mean", "dist max", "time s"
    )
}

/// One line of statistics; distances and time when `fig` is given.
pub fn row(label: &str, q: &MeshQuality, fig: Option<&RemeshFigures>) -> String {
    let tail = match fig {
        Some(f) => format!(
            "{:>9.4} {:>8.4} {:>8.2}",
            f.distance_mean_mm, f.distance_max_mm, f.seconds
        ),
        None => format!("{:>9} {:>8} {:>8}", "-", "-", "-"),
    };
    format!(
        "{label:<28} {:>8} {:>9.4} {:>6.3} {:>8.2} {:>7.3} {:>6.1} {tail}\n",
        q.faces,
        q.edges.mean_mm,
        q.edges.cv,
        q.angles.min_deg,
        100.0 * q.angles.below_30_share,
        100.0 * q.valence6_share
    )
}
