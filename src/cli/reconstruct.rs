//! `glasscan reconstruct SCAN -o OUT`.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use super::common::parse_views;
use crate::eval::{evaluate, EvalOptions};
use crate::hull::HullOptions;
use crate::mesh::io::{read_mesh, write_mesh};
use crate::mesh::stats::quality;
use crate::reconstruct::config::Settings;
use crate::reconstruct::plot::loss_plot;
use crate::reconstruct::{self, output, Existing, IterationRecord, Progress, StageReport, Start};
use crate::scan::Scan;

#[derive(Args, Debug)]
pub struct ReconstructArgs {
    /// The scan folder, decoded (`glasscan decode`, or `simulate --decoded-only`).
    pub scan: PathBuf,
    /// Output folder: result.ply, stage_NN.ply, report.json, loss.png, checkpoint.json.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Settings: fast, balanced (the default: beats DRT's schedule at equal time on every
    /// benchmark scan), accurate, or drt (DRT's schedule and optimiser).
    #[arg(long, default_value = "balanced")]
    pub preset: String,
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
    /// Voxel size of the visual hull, mm.
    #[arg(long = "hull-voxel-mm", default_value_t = 1.0, value_parser = super::common::positive)]
    pub hull_voxel_mm: f64,
}

/// A progress bar per stage and a line per finished stage.
pub(super) struct Bars {
    pub bar: ProgressBar,
}

impl Bars {
    pub fn new() -> Self {
        Self {
            bar: ProgressBar::new(0).with_style(
                ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} ({eta})")
                    .expect("static template"),
            ),
        }
    }
}

impl Progress for Bars {
    fn stage_start(
        &self,
        stage: usize,
        stages: usize,
        edge_mm: f64,
        faces: usize,
        iterations: usize,
    ) {
        self.bar.reset();
        self.bar.set_length(iterations as u64);
        self.bar.set_prefix(format!(
            "stage {}/{stages} ({edge_mm:.2} mm, {faces} faces)",
            stage + 1
        ));
    }
    fn iteration(&self, r: &IterationRecord) {
        self.bar.set_message(format!("loss {:.3e}", r.total));
        self.bar.inc(1);
    }
    fn stage_end(&self, r: &StageReport) {
        self.bar.suspend(|| {
            eprintln!(
                "stage {:>2}: edge {:.2} mm, {} faces, {:.1} s, loss {:.3e} (refraction {:.3e}, silhouette {:.3e}, smoothness {:.3e}), rays used {}, dropped {}",
                r.stage + 1,
                r.edge_mm,
                r.faces,
                r.seconds,
                r.last.total,
                r.last.refraction,
                r.last.silhouette,
                r.last.smoothness,
                r.refraction_rays_used,
                r.refraction_drops.total()
            )
        });
    }
}

pub fn run(a: &ReconstructArgs) -> Result<()> {
    let t0 = Instant::now();
    let scan = Scan::open(&a.scan)?;
    let views = parse_views(a.views.as_deref(), scan.config.views.angles_deg.len())?;
    let mut settings = Settings::preset(&a.preset).with_context(|| {
        format!(
            "--preset {}: choose fast, balanced, accurate or drt",
            a.preset
        )
    })?;
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
    settings.check().map_err(|e| anyhow::anyhow!("{e}"))?;
    let existing = output::prepare(&a.output, a.resume, a.force)?;
    let (inputs, warnings) = reconstruct::load_inputs(&scan, &views, settings.target_weights)?;
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    let start = match &a.init {
        Some(p) => {
            let m = read_mesh(p)?;
            crate::mesh::validate::ensure_valid(&m)
                .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
            Some(m)
        }
        None => None,
    };
    let start = match &start {
        Some(m) => Start::Mesh(m),
        None => Start::Hull(HullOptions {
            voxel_mm: a.hull_voxel_mm,
            ..HullOptions::default()
        }),
    };
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        // First Ctrl-C: finish the stage and save its checkpoint; second: quit at once.
        let _ = ctrlc::set_handler(move || {
            if stop.swap(true, Ordering::SeqCst) {
                std::process::exit(130);
            }
            eprintln!("\nstopping after this stage's checkpoint (Ctrl-C again to quit now)");
        });
    }
    if matches!(existing, Existing::Nothing) && matches!(start, Start::Hull(_)) {
        eprintln!(
            "visual hull ({} views, {} mm voxels) ...",
            inputs.silhouettes.len(),
            a.hull_voxel_mm
        );
    }
    let bars = Bars::new();
    let finished = reconstruct::run(&inputs, start, &settings, &a.output, existing, &bars, &stop)?;
    bars.bar.finish_and_clear();
    let (ck, mesh) = (finished.checkpoint, finished.mesh);
    if !finished.complete {
        bail!(
            "stopped after stage {} of {} (checkpoint saved): continue with --resume",
            ck.stages_done,
            settings.total_stages()
        );
    }
    write_mesh(&a.output.join("result.ply"), &mesh)?;
    loss_plot(
        &a.output.join("loss.png"),
        &ck.history,
        settings.warmup_stages,
    )?;
    let truth = a.scan.join("ground_truth.ply");
    let evaluation = if truth.is_file() {
        let reference = read_mesh(&truth)?;
        let e = evaluate(&mesh, &reference, &EvalOptions::default())?;
        Some(e)
    } else {
        None
    };
    let report = serde_json::json!({
        "settings": ck.settings,
        "views": views.len(),
        "seconds_total": t0.elapsed().as_secs_f64(),
        "seconds_stages": ck.stages.iter().map(|s| s.seconds).sum::<f64>(),
        "stages": ck.stages,
        "final_mesh": quality(&mesh),
        "evaluation_against_ground_truth": evaluation.as_ref().map(|e| e.to_json()),
        "warnings": warnings,
    });
    super::write_json(&a.output.join("report.json"), &report)?;
    outln!(
        "reconstructed {} ({} preset, {} stages) -> {}: {} faces in {:.1} s of stages",
        a.scan.display(),
        settings.preset,
        settings.total_stages(),
        a.output.join("result.ply").display(),
        mesh.faces.len(),
        ck.stages.iter().map(|s| s.seconds).sum::<f64>()
    );
    if let Some(e) = &evaluation {
        outln!(
            "against the scan's ground truth: accuracy {:.3} mm, completeness {:.3} mm",
            e.accuracy_mm,
            e.completeness_mm
        );
    }
    outln!(
        "report: {}, loss curves: {}",
        a.output.join("report.json").display(),
        a.output.join("loss.png").display()
    );
    Ok(())
}
