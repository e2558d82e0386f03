//! `glasscan reconstruct SCAN -o OUT`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;

use super::common::{parse_views, StageBars};
use glasscan::hull::HullOptions;
use glasscan::mesh::io::read_mesh;
use glasscan::mesh::validate::ensure_valid;
use glasscan::mesh::TriMesh;
use glasscan::reconstruct::config::{Preset, Settings};
use glasscan::reconstruct::output;
use glasscan::reconstruct::pipeline::{reconstruct_scan, Job, Outcome};
use glasscan::reconstruct::Start;
use glasscan::util::paths::ensure_output_spares_inputs;

#[derive(Args, Debug)]
pub struct ReconstructArgs {
    /// The scan folder, decoded (`glasscan decode`, or `simulate --decoded-only`).
    pub scan: PathBuf,
    /// Output folder: result.ply, stage_NN.ply, report.json, loss.png, checkpoint.json.
    #[arg(short, long, visible_alias = "out")]
    pub output: PathBuf,
    /// Settings: fast, balanced (the default: beats DRT's schedule at equal time on every
    /// benchmark scan), accurate, or drt (DRT's schedule and optimiser).
    #[arg(long, value_enum, default_value_t = Preset::Balanced)]
    pub preset: Preset,
    /// A TOML file overriding any of the preset's settings (see the README).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Continue the run in the output folder from its last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Start over in an output folder that holds a run (its glasscan files are removed first;
    /// other files are never touched, and refuse the folder).
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
    /// Views to use: all (default), or indices and ranges such as 0-35.
    #[arg(long)]
    pub views: Option<String>,
    /// Seed of every random choice (views, pixels); overrides the config's.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Start from this mesh (world frame) instead of the visual hull.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// The object's refractive index, overriding scan.toml's: a number (glass ≈ 1.5), auto
    /// (estimated with the shape within 1.40–1.70), or auto:LO:HI.
    #[arg(long)]
    pub ior: Option<glasscan::scan::Ior>,
    /// Voxel size of the visual hull, mm (also the edge length it is remeshed to), or auto (as
    /// `hull --voxel-mm`).
    #[arg(long = "hull-voxel-mm", default_value = "auto", value_parser = super::common::voxel_size)]
    pub hull_voxel_mm: glasscan::hull::VoxelSize,
}

pub fn run(a: &ReconstructArgs) -> Result<()> {
    let mut scan = super::common::open_scan(&a.scan)?;
    if let Some(ior) = a.ior {
        scan.config.ior = ior;
    }
    let views = parse_views(a.views.as_deref(), scan.config.views.angles_deg.len())?;
    let settings = settings(a)?;
    let mut inputs = scan.input_paths();
    inputs.extend(a.config.iter().chain(&a.init).cloned());
    ensure_output_spares_inputs(&a.output, "--output", &inputs)?;
    // Held until the run ends: a second run, --resume or --force on this folder is refused.
    let (existing, _lock) = output::prepare(&a.output, a.resume, a.force)?;
    let init = a.init.as_deref().map(read_init).transpose()?;
    let start = match &init {
        Some(m) => Start::Mesh(m),
        // The hull is remeshed at its voxel size, as `glasscan hull` does by default.
        None => Start::Hull(HullOptions {
            voxel: a.hull_voxel_mm,
            ..HullOptions::default()
        }),
    };
    let job = Job {
        scan: &scan,
        views,
        settings,
        start,
        out: &a.output,
        existing,
    };
    let stop = stop_on_ctrl_c();
    let bars = StageBars::new();
    let outcome = reconstruct_scan(job, &bars, &stop)?;
    bars.bar.finish_and_clear();
    print_summary(a, &outcome)
}

/// The preset, with the config file's keys and the seed applied, range-checked.
fn settings(a: &ReconstructArgs) -> Result<Settings> {
    let mut settings = Settings::preset(a.preset);
    if let Some(path) = &a.config {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        settings = settings
            .with_overrides(&text)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    }
    if let Some(seed) = a.seed {
        settings.seed = seed;
    }
    settings.check().map_err(anyhow::Error::msg)?;
    Ok(settings)
}

/// The `--init` mesh, which must be a valid closed surface.
fn read_init(path: &Path) -> Result<TriMesh> {
    let m = read_mesh(path)?;
    ensure_valid(&m).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(m)
}

/// A flag the first Ctrl-C sets (the run stops after the stage's commit); a second quits.
fn stop_on_ctrl_c() -> Arc<AtomicBool> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let _ = ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
        eprintln!("\nstopping after this stage's checkpoint (Ctrl-C again to quit now)");
    });
    stop
}

/// The closing lines: where the result is, its figures, or how to continue a stopped run.
fn print_summary(a: &ReconstructArgs, outcome: &Outcome) -> Result<()> {
    let checkpoint = &outcome.checkpoint;
    if !outcome.complete {
        bail!(
            "stopped after stage {} of {} (checkpoint saved): continue with --resume",
            checkpoint.stages_done,
            checkpoint.settings.total_stages()
        );
    }
    outln!(
        "reconstructed {} ({} preset, {} stages) -> {}: stage {}, {} faces, in {:.1} s of stages",
        a.scan.display(),
        checkpoint.settings.preset,
        checkpoint.settings.total_stages(),
        a.output.join("result.ply").display(),
        outcome.result_stage + 1,
        outcome.result.faces.len(),
        checkpoint.stages.iter().map(|s| s.seconds).sum::<f64>()
    );
    if let Some(i) = &outcome.index {
        let (index, used) = (i.estimate.unwrap_or(i.used), format!("{:.4}", i.used));
        let how = if !i.given.is_auto() {
            "given".into()
        } else if format!("{index:.4}") == used {
            "estimated".into()
        } else {
            format!(
                "estimated by the last stage; the result, stage {}, was made at {used}",
                outcome.result_stage + 1
            )
        };
        let fit = i.held_out_best.map_or(String::new(), |b| {
            format!(
                "; the held-out views fit {:.4} ± {:.4} best with the result",
                b.ior, b.spread
            )
        });
        outln!("refractive index {index:.4} ({how}){fit}");
    }
    if let Some(c) = &outcome.confidence {
        outln!(
            "support: {:.1} % of the area by refraction rays, {:.1} % by silhouettes only, {:.1} % by neither (confidence.png; result.ply's quality: rays per mm² over their mean penalty)",
            100.0 * c.refraction_share,
            100.0 * c.silhouette_only_share,
            100.0 * c.unconstrained_share
        );
    }
    if let Some(e) = &outcome.evaluation {
        outln!(
            "against the scan's ground truth: accuracy {} mm, completeness {} mm",
            glasscan::util::mm(e.accuracy_mm, 3),
            glasscan::util::mm(e.completeness_mm, 3)
        );
    }
    outln!(
        "report: {}, loss curves: {}",
        a.output.join("report.json").display(),
        a.output.join("loss.png").display()
    );
    Ok(())
}
