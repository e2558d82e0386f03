//! `glasscan demo`: the main job end to end on a built-in glass object: simulate a scan with
//! captures, decode it, carve the visual hull, reconstruct with the `fast` preset, and evaluate
//! both against the truth.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;

use super::common::StageBars;
use glasscan::eval::{evaluate, EvalOptions, EvalReport};
use glasscan::hull::HullOptions;
use glasscan::mesh::io::{read_mesh, write_mesh};
use glasscan::mesh::shapes::pebble;
use glasscan::reconstruct::config::{Preset, Settings};
use glasscan::reconstruct::pipeline::{reconstruct_scan, Job, Outcome};
use glasscan::reconstruct::{Existing, Start};
use glasscan::scan::Scan;
use glasscan::simulate::{simulated_scan, SimulateOptions};
use glasscan::util::folder::StagedFolder;

/// The file that marks a folder as the demo's own (the next demo may replace it).
const DEMO_MARKER: &str = ".glasscan-demo";

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Folder for the demo's files.
    #[arg(
        short = 'o',
        long,
        visible_alias = "output",
        default_value = "demo-out"
    )]
    pub out: PathBuf,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

fn line(name: &str, e: &EvalReport) -> String {
    let f = |t: f64| {
        e.fscores
            .iter()
            .find(|f| f.threshold_mm == t)
            .map_or(f64::NAN, |f| f.fscore)
    };
    format!(
        "{name:<16} accuracy {:.3} mm  completeness {:.3} mm  F@0.5mm {:.3}  F@1mm {:.3}",
        e.accuracy_mm,
        e.completeness_mm,
        f(0.5),
        f(1.0)
    )
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let t0 = Instant::now();
    // Written into a temporary sibling, put in place at the end; only an earlier demo's folder
    // (it has the marker file) is replaced.
    let previous_demo = args.out.join(DEMO_MARKER).is_file();
    let hint = "choose another --out (the demo replaces only a folder an earlier demo wrote)";
    let staged = StagedFolder::new(&args.out, previous_demo, hint)?;
    let out = staged.path().to_path_buf();
    std::fs::write(
        out.join(DEMO_MARKER),
        "written by `glasscan demo`; the next demo replaces this folder\n",
    )
    .with_context(|| format!("cannot write into {}", out.display()))?;

    outln!("== 1. a built-in glass object: a three-lobed pebble with a dimple no silhouette shows, about 85 × 60 × 55 mm, IOR 1.4723");
    let object = pebble();
    write_mesh(&out.join("object.ply"), &object)?;

    outln!("== 2. simulate a scan (24 views, 640×480, 4 samples per pixel, Gray-code captures)");
    outln!("== 3. and decode its captures");
    let t = Instant::now();
    let scan_dir = out.join("scan");
    let sim = SimulateOptions {
        views: 24,
        width: 640,
        height: 480,
        spp: 4,
        seed: args.seed,
        ..Default::default()
    };
    let scan = simulated_scan(&object, &scan_dir, &sim, |_| ())?;
    let views: Vec<usize> = (0..sim.views).collect();
    outln!("   {:.1} s", t.elapsed().as_secs_f64());

    outln!("== 4. reconstruct: visual hull (1 mm voxels), then the fast preset");
    let t = Instant::now();
    let rec = out.join("reconstruction");
    let outcome = reconstruct(&scan, views, args.seed, &rec)?;
    outln!("   {:.1} s", t.elapsed().as_secs_f64());

    outln!("== 5. evaluate against the object as placed in the scan");
    evaluate_hull_and_result(&scan_dir, &rec, &outcome, &out)?;
    outln!(
        "\ndemo done in {:.1} s; in {}: object.ply, scan/ (captures, decoded/), reconstruction/ (hull.ply, result.ply, stage meshes, loss.png, report.json), eval.json",
        t0.elapsed().as_secs_f64(),
        args.out.display()
    );
    staged.commit()
}

/// The pipeline's entry point with the fast preset, from the visual hull.
fn reconstruct(scan: &Scan, views: Vec<usize>, seed: u64, rec: &Path) -> Result<Outcome> {
    let mut settings = Settings::preset(Preset::Fast);
    settings.seed = seed;
    let job = Job {
        scan,
        views,
        settings,
        start: Start::Hull(HullOptions::default()),
        out: rec,
        existing: Existing::Nothing,
    };
    let bars = StageBars::new();
    let outcome = reconstruct_scan(job, &bars, &AtomicBool::new(false))?;
    bars.bar.finish_and_clear();
    Ok(outcome)
}

/// The hull and the result against the scan's ground truth, printed and written to eval.json.
fn evaluate_hull_and_result(
    scan_dir: &Path,
    rec: &Path,
    outcome: &Outcome,
    out: &Path,
) -> Result<()> {
    let truth = read_mesh(&scan_dir.join("ground_truth.ply"))?;
    let hull = read_mesh(&rec.join("hull.ply"))?;
    let eh = evaluate(&hull, &truth, &EvalOptions::default())?;
    let er = outcome
        .evaluation
        .clone()
        .context("internal error: the demo's scan has a ground truth")?;
    outln!("{}", line("visual hull", &eh));
    outln!("{}", line("reconstruction", &er));
    super::write_json(
        &out.join("eval.json"),
        &serde_json::json!({ "hull": eh.to_json(), "reconstruction": er.to_json() }),
    )
}
