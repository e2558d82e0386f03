//! The pipeline's entry point, which the CLI, the demo and the benchmarks call: from a decoded
//! scan to `result.ply`, with `report.json`, the loss plot, and the evaluation against the
//! scan's ground truth where it has one.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::Result;

use super::config::Settings;
use super::plot::loss_plot;
use super::{load_inputs, run, Existing, Finished, Progress, Start};
use crate::eval::{evaluate, EvalOptions, EvalReport};
use crate::mesh::io::{read_mesh, write_mesh};
use crate::mesh::stats::quality;
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

/// What [`reconstruct_scan`] hands back.
pub struct Outcome {
    pub finished: Finished,
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
    let (inputs, warnings) = load_inputs(scan, &views, settings.target_weights)?;
    for w in &warnings {
        progress.note(&format!("warning: {w}"));
    }
    if matches!(existing, Existing::Nothing) && matches!(start, Start::Hull(_)) {
        progress.note(&format!(
            "visual hull of {} views ...",
            inputs.silhouettes.len()
        ));
    }
    let finished = run(&inputs, start, &settings, out, existing, progress, stop)?;
    if !finished.complete {
        return Ok(Outcome {
            finished,
            evaluation: None,
            warnings,
        });
    }
    let evaluation = evaluate_against_truth(scan, &finished)?;
    let report = Report {
        views: views.len(),
        evaluation: evaluation.as_ref(),
        warnings: &warnings,
        t0,
    };
    write_results(out, &finished, &report)?;
    Ok(Outcome {
        finished,
        evaluation,
        warnings,
    })
}

/// The result against the scan's `ground_truth.ply`, if it has one.
fn evaluate_against_truth(scan: &Scan, finished: &Finished) -> Result<Option<EvalReport>> {
    let truth = scan.dir.join("ground_truth.ply");
    if !truth.is_file() {
        return Ok(None);
    }
    let reference = read_mesh(&truth)?;
    Ok(Some(evaluate(
        &finished.mesh,
        &reference,
        &EvalOptions::default(),
    )?))
}

/// What `report.json` says beside the checkpoint's figures.
struct Report<'a> {
    views: usize,
    evaluation: Option<&'a EvalReport>,
    warnings: &'a [String],
    t0: Instant,
}

/// `result.ply`, `loss.png` and `report.json` of a complete run in `out`.
fn write_results(out: &Path, finished: &Finished, r: &Report) -> Result<()> {
    let ck = &finished.checkpoint;
    write_mesh(&out.join("result.ply"), &finished.mesh)?;
    loss_plot(
        &out.join("loss.png"),
        &ck.history,
        ck.settings.warmup_stages,
    )?;
    let report = serde_json::json!({
        "settings": ck.settings,
        "views": r.views,
        "seconds_total": r.t0.elapsed().as_secs_f64(),
        "seconds_stages": ck.stages.iter().map(|s| s.seconds).sum::<f64>(),
        "stages": ck.stages,
        "final_mesh": quality(&finished.mesh),
        "evaluation_against_ground_truth": r.evaluation.map(|e| e.to_json()),
        "warnings": r.warnings,
    });
    write_json(&out.join("report.json"), &report)
}
