//! The pipeline's entry point, which the CLI, the demo and the benchmarks call: from a decoded
//! scan to `result.ply`, with `report.json`, the loss plot, and the evaluation against the
//! scan's ground truth where it has one.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::Result;

use super::config::Settings;
use super::plot::loss_plot;
use super::validation::best_stage;
use super::{load_inputs, run, stage_path, Checkpoint, Existing, Finished, Progress, Start};
use crate::eval::{evaluate, EvalOptions, EvalReport};
use crate::mesh::io::{read_mesh, write_mesh};
use crate::mesh::stats::quality;
use crate::mesh::TriMesh;
use crate::scan::Scan;
use crate::util::atomic::write_json;

/// One reconstruction to run.
pub struct Job<'a> {
    pub scan: &'a Scan,
    /// The views to use (indices into the scan's).
    pub views: Vec<usize>,
    pub settings: Settings,
    /// Where a fresh run starts (ignored when `existing` is a run to continue).
    pub start: Start<'a>,
    /// The output folder, checked by [`super::output::prepare`] into `existing`.
    pub out: &'a Path,
    pub existing: Existing,
}

/// What [`reconstruct_scan`] hands back: the run's last committed checkpoint and its result.
pub struct Outcome {
    pub checkpoint: Checkpoint,
    /// False when `stop` ended the run before its last stage (continue with `--resume`).
    pub complete: bool,
    /// The result: the stage whose mesh fits the held-out views best (the last stage when none
    /// are held out, or when the run was stopped), and its mesh.
    pub result_stage: usize,
    pub result: TriMesh,
    /// Against `SCAN/ground_truth.ply`, when the scan has one and the run is complete.
    pub evaluation: Option<EvalReport>,
    pub warnings: Vec<String>,
}

/// Runs `job` (warnings and stage progress go to `progress`); `stop` ends it after a stage's
/// commit, in which case nothing but the checkpoint and stage meshes is written.
pub fn reconstruct_scan(job: Job, progress: &dyn Progress, stop: &AtomicBool) -> Result<Outcome> {
    let t0 = Instant::now();
    let Job {
        scan,
        views,
        settings,
        start,
        out,
        existing,
    } = job;
    let silhouettes = crate::hull::silhouettes(scan, &views)?;
    let (start, diagonal_mm) = match &existing {
        Existing::Run(checkpoint) => (None, checkpoint.diagonal_mm),
        Existing::Nothing => {
            if matches!(start, Start::Hull(_)) {
                progress.note(&format!("visual hull of {} views ...", silhouettes.0.len()));
            }
            let start = start.mesh(&silhouettes.0)?;
            let diagonal_mm = start.mesh.bbox_diagonal();
            (Some(start), diagonal_mm)
        }
    };
    let (inputs, warnings) = load_inputs(scan, &views, &settings, silhouettes, diagonal_mm)?;
    for w in &warnings {
        progress.note(&format!("warning: {w}"));
    }
    let finished = run(&inputs, start, &settings, out, existing, progress, stop)?;
    if !finished.complete {
        // A stopped run has no result yet: its last stage stands in.
        return Ok(Outcome {
            result_stage: finished.checkpoint.stages_done.saturating_sub(1),
            result: finished.mesh,
            checkpoint: finished.checkpoint,
            complete: false,
            evaluation: None,
            warnings,
        });
    }
    let (result_stage, result) = choose_result(out, &finished, progress)?;
    let evaluation = evaluate_against_truth(scan, &result)?;
    let report = Report {
        views: views.len(),
        result_stage,
        evaluation: evaluation.as_ref(),
        warnings: &warnings,
        t0,
    };
    write_results(out, &finished, &result, &report)?;
    Ok(Outcome {
        checkpoint: finished.checkpoint,
        complete: true,
        result_stage,
        result,
        evaluation,
        warnings,
    })
}

/// The stage whose mesh fits the held-out views best ([`best_stage`]), and that mesh; says so
/// when it is not the last stage.
fn choose_result(
    out: &Path,
    finished: &Finished,
    progress: &dyn Progress,
) -> Result<(usize, TriMesh)> {
    let stages = &finished.checkpoint.stages;
    let last = stages.len().saturating_sub(1);
    let first = finished.checkpoint.settings.warmup_stages;
    let best = best_stage(stages, first, stages.len()).unwrap_or(last);
    if best == last {
        return Ok((last, finished.mesh.clone()));
    }
    let fit = |s: usize| {
        stages[s].validation.as_ref().map_or("-".into(), |v| {
            let outline = (v.outline_px()).map_or(String::new(), |px| {
                format!(", outline off by {px:.1} px a view")
            });
            format!(
                "refraction {:.4e}, silhouette {:.4e}{outline}",
                v.refraction, v.silhouette
            )
        })
    };
    progress.note(&format!(
        "result: stage {} of {}, whose mesh fits the held-out views best ({}; after the last stage {})",
        best + 1,
        stages.len(),
        fit(best),
        fit(last)
    ));
    Ok((best, read_mesh(&stage_path(out, best))?))
}

/// The result against the scan's `ground_truth.ply`, if it has one.
fn evaluate_against_truth(scan: &Scan, result: &TriMesh) -> Result<Option<EvalReport>> {
    let truth = scan.dir.join("ground_truth.ply");
    if !truth.is_file() {
        return Ok(None);
    }
    let reference = read_mesh(&truth)?;
    Ok(Some(evaluate(result, &reference, &EvalOptions::default())?))
}

/// What `report.json` says beside the checkpoint's figures.
struct Report<'a> {
    views: usize,
    result_stage: usize,
    evaluation: Option<&'a EvalReport>,
    warnings: &'a [String],
    t0: Instant,
}

/// `result.ply`, `loss.png` and `report.json` of a complete run in `out`.
fn write_results(out: &Path, finished: &Finished, result: &TriMesh, r: &Report) -> Result<()> {
    let checkpoint = &finished.checkpoint;
    write_mesh(&out.join("result.ply"), result)?;
    loss_plot(&out.join("loss.png"), checkpoint)?;
    let report = serde_json::json!({
        "settings": checkpoint.settings,
        "views": r.views,
        "seconds_total": r.t0.elapsed().as_secs_f64(),
        "seconds_stages": checkpoint.stages.iter().map(|s| s.seconds).sum::<f64>(),
        "stages": checkpoint.stages,
        "warm_up": checkpoint.warm_up,
        "membrane": checkpoint.membrane,
        "result_stage": r.result_stage + 1,
        "result_mesh": quality(result),
        "evaluation_against_ground_truth": r.evaluation.map(|e| e.to_json()),
        "warnings": r.warnings,
    });
    write_json(&out.join("report.json"), &report)
}
