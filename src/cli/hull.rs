//! `glasscan hull SCAN -o hull.ply`.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use clap::Args;

use super::common::{bar, parse_views, positive, voxel_size};
use glasscan::hull::{silhouettes, visual_hull, HullOptions, HullRemesh, VoxelSize};
use glasscan::mesh::io::write_mesh;
use glasscan::util::paths::{ensure_extension, ensure_output_spares_inputs};

#[derive(Args, Debug)]
pub struct HullArgs {
    /// The scan folder (decoded: `glasscan decode`, or `simulate --decoded-only`).
    pub scan: PathBuf,
    /// Output mesh (.ply or .obj), world (turntable) frame, mm.
    #[arg(short, long, visible_alias = "out")]
    pub output: PathBuf,
    /// Voxel size of the fine grid, mm, or auto: 1 mm for objects of 50 to 500 mm across
    /// (the diagonal of a first coarse box), a fiftieth of the diagonal below, a
    /// five-hundredth above.
    #[arg(long = "voxel-mm", default_value = "auto", value_parser = voxel_size)]
    pub voxel_mm: VoxelSize,
    /// Views to carve with: all (default), or indices and ranges such as 0-35,40.
    #[arg(long)]
    pub views: Option<String>,
    /// Keep points that fall outside the mask in at most this many views (mask errors).
    #[arg(long, default_value_t = 0)]
    pub tolerance: usize,
    /// Remesh the surface to this edge length, mm (default: the voxel size).
    #[arg(long = "edge-mm", conflicts_with = "raw", value_parser = positive)]
    pub edge_mm: Option<f64>,
    /// Keep the marching-cubes surface as it is (no remesh).
    #[arg(long)]
    pub raw: bool,
    /// Also write the figures as JSON here.
    #[arg(long)]
    pub report: Option<PathBuf>,
}

pub fn run(a: &HullArgs) -> Result<()> {
    let t0 = Instant::now();
    let scan = super::common::open_scan(&a.scan)?;
    let inputs = scan.input_paths();
    ensure_output_spares_inputs(&a.output, "--output", &inputs)?;
    if let Some(r) = &a.report {
        ensure_extension(r, "--report", &["json"])?;
        ensure_output_spares_inputs(r, "--report", &inputs)?;
        ensure_output_spares_inputs(r, "--report", &[&a.output])?;
    }
    let views = parse_views(a.views.as_deref(), scan.config.views.angles_deg.len())?;
    let (sils, warnings) = silhouettes(&scan, &views)?;
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    let seconds_silhouettes = t0.elapsed().as_secs_f64();
    let o = HullOptions {
        voxel: a.voxel_mm,
        tolerance: a.tolerance,
        remesh: match (a.raw, a.edge_mm) {
            (true, _) => HullRemesh::Raw,
            (false, Some(h)) => HullRemesh::EdgeMm(h),
            (false, None) => HullRemesh::AtVoxel,
        },
        ..HullOptions::default()
    };
    let bar = bar("hull", 0);
    let (mesh, mut report) = visual_hull(&sils, &o, &super::common::Bar(bar.clone()))?;
    bar.finish_and_clear();
    report.seconds_silhouettes = seconds_silhouettes;
    report.warnings = warnings;
    write_mesh(&a.output, &mesh)?;
    let c = &report.carve;
    outln!(
        "hull of {} views -> {}: {} faces, genus {}, volume {:.0} mm³ in {:.1} s",
        report.views,
        a.output.display(),
        report.faces,
        report.genus,
        report.volume_mm3,
        t0.elapsed().as_secs_f64()
    );
    outln!(
        "  grid {}×{}×{} voxels of {} mm: {} blocks, {} inside, {} on the surface ({} added by the consistency check); {} field points",
        c.dims[0], c.dims[1], c.dims[2], glasscan::util::short_number(c.voxel_mm), c.blocks, c.inside_blocks, c.surface_blocks, c.promoted_blocks, c.evaluated_points
    );
    outln!(
        "  time: masks {:.2} s, carve {:.2} s, marching cubes {:.2} s ({} faces, {} speck component(s) dropped), remesh {:.2} s",
        report.seconds_silhouettes,
        report.seconds_carve,
        report.seconds_marching_cubes,
        report.marching_cubes_faces,
        report.dropped_components,
        report.seconds_remesh
    );
    if let Some(path) = &a.report {
        super::write_json(path, &serde_json::to_value(&report)?)?;
    }
    Ok(())
}
