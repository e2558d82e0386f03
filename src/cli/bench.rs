//! `glasscan bench …`.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Subcommand};

use crate::bench::trace::{self, TraceBenchOptions, TraceBenchReport};
use crate::mesh::io::read_mesh;
use crate::mesh::shapes;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Embree throughput (coherent and incoherent rays, 1 and all threads) and BVH update cost.
    Trace(TraceArgs),
}

#[derive(Args, Debug)]
pub struct TraceArgs {
    /// Mesh to trace (.ply or .obj); default: a built-in sphere of 81,920 faces.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Width of the camera view, pixels.
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    /// Height of the camera view, pixels.
    #[arg(long, default_value_t = 960)]
    pub height: u32,
    /// Minimum duration of each throughput measurement, seconds.
    #[arg(long, default_value_t = 1.0)]
    pub seconds: f64,
    /// Seed of the random rays and vertex moves.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write the figures as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn run(cmd: &BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Trace(a) => run_trace(a),
    }
}

fn run_trace(a: &TraceArgs) -> Result<()> {
    let (name, mesh) = match &a.mesh {
        Some(p) => (p.display().to_string(), read_mesh(p)?),
        None => (
            "built-in sphere (r = 50 mm)".to_string(),
            shapes::icosphere(50.0, 6),
        ),
    };
    let opts = TraceBenchOptions {
        width: a.width,
        height: a.height,
        min_seconds: a.seconds,
        seed: a.seed,
        ..Default::default()
    };
    eprintln!("bench trace: {name}, {} faces ...", mesh.faces.len());
    let report = trace::run(&mesh, &opts)?;
    print!("{}", table(&report, a.width, a.height));
    if let Some(path) = &a.json {
        super::write_json(path, &serde_json::to_value(&report)?)?;
    }
    Ok(())
}

/// The figures as a table, with the ratios that matter.
pub fn table(r: &TraceBenchReport, width: u32, height: u32) -> String {
    let mut s = format!(
        "Embree {} · {} faces · {width}×{height} view\n",
        crate::trace::embree_version(),
        r.faces
    );
    s += &format!(
        "{:<32} {:>8} {:>10} {:>8}\n",
        "workload", "threads", "Mrays/s", "hits"
    );
    for t in &r.throughput {
        s += &format!(
            "{:<32} {:>8} {:>10.2} {:>7.1}%\n",
            t.workload,
            t.threads,
            t.mrays_per_s,
            100.0 * t.hit_share
        );
    }
    let find = |w: &str, th: usize| {
        r.throughput
            .iter()
            .find(|t| t.workload.starts_with(w) && t.threads == th)
            .map(|t| t.mrays_per_s)
    };
    if let (Some(p), Some(o)) = (
        find("camera rays, packets", r.threads),
        find("camera rays, one", r.threads),
    ) {
        s += &format!(
            "ratio packets / one by one ({} threads): {:.2}\n",
            r.threads,
            p / o
        );
    }
    if let (Some(m), Some(one)) = (
        find("camera rays, packets", r.threads),
        find("camera rays, packets", 1),
    ) {
        s += &format!(
            "ratio {} threads / 1 thread (packets): {:.2}\n",
            r.threads,
            m / one
        );
    }
    s += &format!(
        "{:<28} {:>10} {:>12} {:>16}\n",
        "BVH mode", "build ms", "update ms", "Mrays/s after"
    );
    for u in &r.updates {
        s += &format!(
            "{:<28} {:>10.2} {:>12.2} {:>16.2}\n",
            u.mode, u.build_ms, u.update_ms, u.mrays_per_s_after
        );
    }
    if let [rebuild, refit] = &r.updates[..] {
        s += &format!(
            "ratio rebuild / refit update time: {:.1}; refit / rebuild ray speed: {:.2}\n",
            rebuild.update_ms / refit.update_ms,
            refit.mrays_per_s_after / rebuild.mrays_per_s_after
        );
    }
    s
}
