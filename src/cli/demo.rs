//! `glasscan demo`: the zero-setup first run on a built-in object. For now it exercises what is
//! built end to end: make a pebble-like glass object, write and re-read it, validate it, evaluate
//! a coarser tessellation of it against it, benchmark ray tracing on it, and simulate a scan of it.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use nalgebra::Vector3;

use crate::bench::trace::{self as trace_bench, TraceBenchOptions};
use crate::eval::{evaluate, EvalOptions};
use crate::mesh::io::{read_mesh, write_mesh};
use crate::mesh::shapes::ellipsoid;
use crate::mesh::validate::{ensure_valid, validate};
use crate::simulate::{simulate, SimulateOptions};

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Folder for the demo's files.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let t0 = Instant::now();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create the output folder {}", args.out.display()))?;
    let radii = Vector3::new(40.0, 30.0, 25.0);

    outln!("== 1. a built-in object: an ellipsoidal pebble, semi-axes 40 × 30 × 25 mm");
    let object_path = args.out.join("object.ply");
    write_mesh(&object_path, &ellipsoid(radii, 6))?;
    let object = read_mesh(&object_path)?;
    let report = ensure_valid(&object).context("the built-in object is invalid")?;
    out!("{}", super::info::describe(&object_path, &object, &report));

    outln!("\n== 2. evaluation: a 16× coarser tessellation of the same pebble against it");
    let coarse_path = args.out.join("coarse.obj");
    write_mesh(&coarse_path, &ellipsoid(radii, 4))?;
    let coarse = read_mesh(&coarse_path)?;
    outln!(
        "coarse           {} ({} faces, {})",
        coarse_path.display(),
        coarse.faces.len(),
        if validate(&coarse).is_valid() {
            "valid"
        } else {
            "INVALID"
        }
    );
    let eval_opts = EvalOptions {
        samples: 200_000,
        seed: args.seed,
        ..Default::default()
    };
    let metrics = evaluate(&coarse, &object, &eval_opts)?;
    out!("{}", super::eval::table(&metrics, args.seed));
    super::write_json(&args.out.join("eval.json"), &metrics.to_json())?;

    outln!("\n== 3. ray tracing throughput on the pebble");
    let bench_opts = TraceBenchOptions {
        min_seconds: 0.5,
        seed: args.seed,
        ..Default::default()
    };
    let bench = trace_bench::run(&object, &bench_opts)?;
    out!(
        "{}",
        super::bench::table(&bench, bench_opts.width, bench_opts.height)
    );

    outln!("\n== 4. a simulated scan of the pebble: 8 views, 640×480, captures and ground truth");
    let sim = SimulateOptions {
        views: 8,
        width: 640,
        height: 480,
        seed: args.seed,
        ..Default::default()
    };
    let scan_dir = args.out.join("scan");
    let r = simulate(&object, &scan_dir, &sim, |_| ())?;
    outln!(
        "object pixels {}: {:.1} % reach the monitor through exactly 2 refractions, {:.1} % through 4+, {:.1} % end in total internal reflection, {:.1} % miss the monitor",
        r.object_pixels,
        100.0 * r.two_refractions,
        100.0 * r.more_refractions,
        100.0 * r.total_internal_reflection,
        100.0 * r.missed_monitor
    );
    outln!(
        "a camera pixel sees {:.1} monitor pixels through the glass (median), {:.1} directly",
        r.median_footprint_px,
        r.direct_footprint_px
    );

    outln!(
        "\ndemo done in {:.1} s; files in {}: object.ply, coarse.obj, eval.json, scan/",
        t0.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(())
}
