//! The pipeline's entry point, which the CLI, the demo and the benchmarks call: from a decoded
//! scan to `result.ply` (with its confidence as a vertex property), with `report.json`, the loss
//! plot, `confidence.png`, and the evaluation against the scan's ground truth where it has one;
//! with an unknown refractive index, after a first pass that finds where to start it
//! ([`super::index`]).

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{bail, Result};

use super::confidence::{self, Confidence, ConfidenceSummary};
use super::config::Settings;
use super::index::{self, IndexReport};
use super::output::{committed_run, INDEX_FIT, INDEX_PASS};
use super::plot::loss_plot;
use super::validation::{best_stage, Split};
use super::{
    load_inputs, run, stage_path, Checkpoint, Existing, Finished, Inputs, Progress, StageReport,
    Start, StartMesh,
};
use crate::eval::confidence::{error_by_confidence, ErrorByConfidence};
use crate::eval::error_map::{confidence_legend, write_support_map};
use crate::eval::{evaluate_on, EvalOptions, EvalReport};
use crate::mesh::io::{read_mesh, write_mesh_with_quality};
use crate::mesh::stats;
use crate::mesh::TriMesh;
use crate::scan::silhouette::Silhouette;
use crate::scan::{Ior, Scan};
use crate::trace::path::MeshSurface;
use crate::trace::BuildMode;
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
    /// The index the result was made at and the held-out fit about it (a complete run).
    pub index: Option<IndexReport>,
    /// What constrains the result's surface, by area (a complete run).
    pub confidence: Option<ConfidenceSummary>,
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
            let start = start_mesh(start, &silhouettes.0, progress)?;
            let diagonal_mm = start.mesh.bbox_diagonal();
            (Some(start), diagonal_mm)
        }
    };
    let (mut inputs, mut warnings) =
        load_inputs(scan, &views, &settings, silhouettes, diagonal_mm)?;
    for w in &warnings {
        progress.note(&format!("warning: {w}"));
    }
    note_the_blur(&inputs, &settings, progress);
    let given = inputs.ior;
    let mut fit = None;
    if given.is_auto() {
        let main_committed = matches!(existing, Existing::Run(_));
        let passes = (start.clone(), main_committed);
        match estimate_index(&mut inputs, &settings, passes, out, progress, stop)? {
            Ok(stages) => fit = stages,
            Err(stopped) => return Ok(stopped_outcome(stopped, warnings)),
        }
    }
    let finished = run(&inputs, start, &settings, out, existing, progress, stop)?;
    if !finished.complete {
        return Ok(stopped_outcome(finished, warnings));
    }
    let (result_stage, result) = choose_result(out, &finished, progress)?;
    // One ray-tracing structure of the result serves the index search, the confidence and its map.
    let settings = &finished.checkpoint.settings;
    let surface = MeshSurface::with_mode(&result, settings.normals, BuildMode::Static)?;
    let used = used_index(&inputs, &finished, result_stage);
    let estimated = fit.as_deref().unwrap_or(&finished.checkpoint.stages);
    let index = index_report(&inputs, (given, estimated), (&finished, used, &surface))?;
    if let Some(w) = index.warning() {
        progress.note(&format!("warning: {w}"));
        warnings.push(w);
    }
    let confidence = confidence::measure(&inputs, &surface, settings, index.used)?;
    let quality = confidence.quality();
    let evaluation = evaluate_against_truth(scan, (&result, surface.scene()), &quality)?;
    let report = Report {
        views: views.len(),
        result_stage,
        index: &index,
        confidence: &confidence,
        quality: &quality,
        evaluation: evaluation.as_ref().map(|e| &e.0),
        error_by_confidence: evaluation.as_ref().map(|e| e.1),
        warnings: &warnings,
        t0,
    };
    write_results(out, &finished, &surface, &report)?;
    Ok(Outcome {
        checkpoint: finished.checkpoint,
        complete: true,
        result_stage,
        result,
        evaluation: evaluation.map(|e| e.0),
        index: Some(index),
        confidence: Some(confidence.summary()),
        warnings,
    })
}

/// A new run's start mesh (the visual hull of `silhouettes`, or the given mesh), saying what it
/// made.
fn start_mesh(
    start: Start,
    silhouettes: &[Silhouette],
    progress: &dyn Progress,
) -> Result<StartMesh> {
    if matches!(start, Start::Hull(_)) {
        progress.note(&format!("visual hull of {} views ...", silhouettes.len()));
    }
    let start = start.mesh(silhouettes)?;
    if let Some(v) = start.hull_voxel_mm {
        progress.note(&format!(
            "  voxels of {} mm, remeshed to {} faces",
            crate::util::short_number(v),
            start.mesh.faces.len()
        ));
    }
    Ok(start)
}

/// A stopped run's outcome: it has no result yet, its last stage stands in.
fn stopped_outcome(finished: Finished, warnings: Vec<String>) -> Outcome {
    Outcome {
        result_stage: finished.checkpoint.stages_done.saturating_sub(1),
        result: finished.mesh,
        checkpoint: finished.checkpoint,
        complete: false,
        evaluation: None,
        index: None,
        confidence: None,
        warnings,
    }
}

/// The settings that estimate the index ([`index::estimating_settings`]), saying how they differ
/// from the run's `settings`.
fn settings_to_estimate(settings: &Settings, inputs: &Inputs, progress: &dyn Progress) -> Settings {
    let estimating = index::estimating_settings(settings, inputs.curved_captures);
    if estimating != *settings {
        progress.note(&format!(
            "curved glass decoded from captures: to estimate the index, each pixel is modelled by {0}×{0} rays over its area, {1} iterations a stage",
            estimating.footprint, estimating.iterations
        ));
    }
    estimating
}

/// The passes of a run given `ior = "auto"` before it ([`index`]), with `settings` the run's: the
/// first pass finds where to start the index (`inputs.ior_start`). With the same settings
/// ([`index::estimating_settings`]) the run then estimates the index with the shape itself;
/// otherwise a second pass, with the estimating settings, does, and the run is given its
/// estimate (`inputs.ior`). `start` is the run's start mesh (`None` when the main run is
/// committed, which it is only once the passes are complete). The second pass's stages, which
/// hold the estimate, or the stopped pass.
fn estimate_index(
    inputs: &mut Inputs,
    settings: &Settings,
    (start, main_committed): (Option<StartMesh>, bool),
    out: &Path,
    progress: &dyn Progress,
    stop: &AtomicBool,
) -> Result<Result<Option<Vec<StageReport>>, Finished>> {
    let estimating = settings_to_estimate(settings, inputs, progress);
    let (lo, hi) = inputs.ior.range();
    let first = index::pass_settings(&estimating);
    progress.note(&format!(
        "the refractive index is unknown ({lo}–{hi}): a first pass of {} stages finds where to start it, in {}",
        first.total_stages(),
        out.join(INDEX_PASS).display()
    ));
    let passes = (start.clone(), main_committed, out);
    let first = match pass(inputs, passes.clone(), (INDEX_PASS, &first), progress, stop)? {
        Ok(first) => first,
        Err(stopped) => return Ok(Err(stopped)),
    };
    let start_at = first.checkpoint.index(inputs);
    inputs.ior_start = Some(start_at);
    if estimating == *settings {
        progress.note(&format!(
            "refractive index {start_at:.4} after the first pass: the run starts again from the start mesh at it, and estimates it with the shape from stage {} on",
            settings.warmup_stages + 1
        ));
        return Ok(Ok(None));
    }
    progress.note(&format!(
        "refractive index {start_at:.4} after the first pass: a second pass, in {}, starts again from the start mesh at it and estimates it with the shape; the run is then given its estimate, with its own settings",
        out.join(INDEX_FIT).display()
    ));
    let fit = match pass(inputs, passes, (INDEX_FIT, &estimating), progress, stop)? {
        Ok(fit) => fit,
        Err(stopped) => return Ok(Err(stopped)),
    };
    let estimate = fit.checkpoint.index(inputs);
    progress.note(&format!(
        "refractive index {estimate:.4} estimated with the shape: the run starts again from the start mesh, given it"
    ));
    (inputs.ior, inputs.ior_start) = (Ior::Known(estimate), None);
    Ok(Ok(Some(fit.checkpoint.stages)))
}

/// A pass of a run given `ior = "auto"` with `settings`, in `out/name` (continued when committed
/// there; `start` is the run's start mesh, `None` when the main run is committed, which it is
/// only once the passes are complete): the complete pass, or the stopped one.
fn pass(
    inputs: &Inputs,
    (start, main_committed, out): (Option<StartMesh>, bool, &Path),
    (name, settings): (&str, &Settings),
    progress: &dyn Progress,
    stop: &AtomicBool,
) -> Result<Result<Finished, Finished>> {
    let dir = out.join(name);
    let existing = committed_run(&dir)?;
    if main_committed && matches!(existing, Existing::Nothing) {
        bail!(
            "--resume: {} (a pass that estimated the refractive index) is missing or has no checkpoint; start the run over with --force",
            dir.display()
        );
    }
    let finished = run(inputs, start, settings, &dir, existing, progress, stop)?;
    Ok(if finished.complete {
        Ok(finished)
    } else {
        Err(finished)
    })
}

/// Says when the run corrects the decoded points for the camera's blur.
fn note_the_blur(inputs: &Inputs, settings: &Settings, progress: &dyn Progress) {
    if !settings.blur_correction {
        return;
    }
    let source = inputs.blur_source.describe();
    progress.note(&match inputs.blur {
        Some(_) => format!(
            "the camera's blur ({source}): each stage after the warm-up corrects the decoded points for it on its start mesh, the held-out fit on the result"
        ),
        None if inputs.blur_source.sigma_px().is_some() => format!(
            "the camera's blur ({source}) is below what the correction resolves: nothing to correct"
        ),
        None => "blur_correction is on, but the scan gives no blur (no blur_px in scan.toml, and decode measured none: no background captures, or too few stripe edges in them): nothing is corrected".into(),
    });
}

/// The index the result (`finished`'s stage `result_stage`) was made at: the given one, or its
/// stage's estimate.
fn used_index(inputs: &Inputs, finished: &Finished, result_stage: usize) -> f64 {
    (finished.checkpoint.stages.get(result_stage))
        .and_then(|r| r.ior)
        .unwrap_or_else(|| inputs.ior.nominal())
}

/// The index the result was made at, `used` (`given`, or its stage's estimate), an unknown
/// index's estimate (the last of the `estimated` stages: the run's, or its second pass's), and
/// the held-out fit of the result (mesh `result`, of
/// `finished`) about `used`, with the held-out views' points marked for the camera's blur on the
/// result (and corrected when the run corrects) wherever a blur is known.
fn index_report(
    inputs: &Inputs,
    (given, estimated): (Ior, &[StageReport]),
    (finished, used, result): (&Finished, f64, &MeshSurface),
) -> Result<IndexReport> {
    let settings = &finished.checkpoint.settings;
    let split = Split::new(inputs, settings.validation_share);
    let held = Some(&split.held_targets[..]);
    let deblurred = if settings.blur_correction || inputs.skew_marks {
        inputs.deblurred(result, used, held, settings.blur_correction)?
    } else {
        None
    };
    let inputs = deblurred
        .as_ref()
        .map_or(inputs, |(corrected, _)| corrected);
    let from = (used, index::search_range(given));
    Ok(IndexReport {
        given,
        used,
        estimate: index::estimate(given, estimated),
        held_out_best: index::held_out_best(inputs, &split, result, settings, from)?,
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

/// The result (with its static scene) against the scan's `ground_truth.ply`, if it has one, and
/// its error by quarters of the area ordered by its confidence (`quality`, per vertex).
fn evaluate_against_truth(
    scan: &Scan,
    (result, scene): (&TriMesh, &crate::trace::Scene),
    quality: &[f64],
) -> Result<Option<(EvalReport, ErrorByConfidence)>> {
    let truth = scan.dir.join("ground_truth.ply");
    if !truth.is_file() {
        return Ok(None);
    }
    let reference = read_mesh(&truth)?;
    let device = crate::trace::Device::new()?;
    let ref_scene = crate::trace::Scene::new(&device, &reference, BuildMode::Static)?;
    Ok(Some((
        evaluate_on(
            (result, scene),
            (&reference, &ref_scene),
            &EvalOptions::default(),
        )?,
        error_by_confidence(result, quality, &ref_scene)?,
    )))
}

/// What `report.json` says beside the checkpoint's figures.
struct Report<'a> {
    views: usize,
    result_stage: usize,
    index: &'a IndexReport,
    confidence: &'a Confidence,
    /// The confidence's per-vertex quality ([`Confidence::quality`]).
    quality: &'a [f64],
    error_by_confidence: Option<ErrorByConfidence>,
    evaluation: Option<&'a EvalReport>,
    warnings: &'a [String],
    t0: Instant,
}

/// `result.ply`, `loss.png`, `confidence.png` and `report.json` of a complete run in `out`
/// (the result as `surface` holds it).
fn write_results(out: &Path, finished: &Finished, surface: &MeshSurface, r: &Report) -> Result<()> {
    let (checkpoint, result) = (&finished.checkpoint, surface.mesh());
    write_mesh_with_quality(&out.join("result.ply"), result, r.quality)?;
    loss_plot(&out.join("loss.png"), checkpoint)?;
    let summary = r.confidence.summary();
    write_support_map(
        &out.join("confidence.png"),
        (result, surface.scene()),
        r.quality,
        confidence_legend(r.quality),
    )?;
    let report = serde_json::json!({
        "settings": checkpoint.settings,
        "views": r.views,
        "seconds_total": r.t0.elapsed().as_secs_f64(),
        "seconds_stages": checkpoint.stages.iter().map(|s| s.seconds).sum::<f64>(),
        "stages": checkpoint.stages,
        "warm_up": checkpoint.warm_up,
        "membrane": checkpoint.membrane,
        "surface": checkpoint.surface,
        "result_stage": r.result_stage + 1,
        "ior": r.index,
        "confidence": summary,
        "result_mesh": stats::quality(result),
        "evaluation_against_ground_truth": r.evaluation.map(|e| e.to_json()),
        "error_by_confidence_against_ground_truth": r.error_by_confidence,
        "warnings": r.warnings,
    });
    write_json(&out.join("report.json"), &report)
}
