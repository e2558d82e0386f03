//! The judges of a run, each deciding once on the held-out views: whether the warm-up stands
//! (against the start mesh) and whether the membrane term acts (its judged stage run again
//! without it).

use super::output::stage_path;
use super::validation::{validate_mesh, Split};
use crate::mesh::io::{read_mesh, write_mesh};
use crate::mesh::TriMesh;
use anyhow::{Context, Result};
use std::path::Path;

use super::stages::*;
use super::{
    Checkpoint, Inputs, IterationRecord, MembraneVerdict, Progress, StageReport, WarmUpVerdict,
    MEMBRANE_MIN_SHARE, MEMBRANE_SILHOUETTE_RATIO,
};

/// Judges the warm-up stage that just ended (its mesh `warmed`) against the run's start mesh on
/// the held-out views: returns the mesh the next stage starts from, the verdict recorded in
/// `checkpoint`. The first warm-up stage that fits worse than the start mesh ends the warm-up:
/// its remaining stages are skipped ([`skip_warm_up_rest`]) and the stages after it start from
/// the start mesh. Without held-out views the warm-up is kept unjudged.
pub(super) fn judge_warm_up(
    inputs: &Inputs,
    split: &Split,
    checkpoint: &mut Checkpoint,
    warmed: TriMesh,
    out: &Path,
    progress: &dyn Progress,
) -> Result<TriMesh> {
    let warm_fit = checkpoint.stages.last().and_then(|r| r.validation.as_ref());
    let Some(warm_up_refraction) = warm_fit.map(|v| v.refraction) else {
        return Ok(warmed);
    };
    let start = read_mesh(&out.join(&checkpoint.start_mesh))
        .context("the start mesh of this run is unreadable; start over with --force")?;
    let start_refraction = match &checkpoint.warm_up {
        Some(verdict) => verdict.start_refraction,
        None => {
            let index = (inputs, checkpoint.index(inputs));
            match validate_mesh(index, split, &start, &checkpoint.settings)? {
                Some(fit) => fit.refraction,
                None => return Ok(warmed),
            }
        }
    };
    let discarded = warm_up_refraction > start_refraction;
    checkpoint.warm_up = Some(WarmUpVerdict {
        start_refraction,
        warm_up_refraction,
        discarded,
    });
    if !discarded {
        return Ok(warmed);
    }
    let skipped = checkpoint.settings.warmup_stages - checkpoint.stages_done;
    progress.note(&format!(
        "the warm-up fits the held-out views worse than the start mesh (refraction {warm_up_refraction:.4e} \
         against {start_refraction:.4e}): the next stages start from the start mesh{}",
        if skipped > 0 {
            format!(", and the warm-up's last {skipped} stage(s) are skipped")
        } else {
            String::new()
        }
    ));
    skip_warm_up_rest(checkpoint, &start, out)?;
    Ok(start)
}

/// Records the warm-up stages not yet run as skipped: each with the start mesh `start` as its
/// mesh, no time and no fit to the held-out views (so never the result).
fn skip_warm_up_rest(checkpoint: &mut Checkpoint, start: &TriMesh, out: &Path) -> Result<()> {
    let Some((edge_mm, ior)) = checkpoint.stages.last().map(|s| (s.edge_mm, s.ior)) else {
        return Ok(());
    };
    while checkpoint.stages_done < checkpoint.settings.warmup_stages {
        let stage = checkpoint.stages_done;
        write_mesh(&stage_path(out, stage), start)?;
        checkpoint.stages.push(StageReport {
            stage,
            edge_mm,
            vertices: start.positions.len(),
            faces: start.faces.len(),
            ior,
            skipped: true,
            ..Default::default()
        });
        checkpoint.stages_done += 1;
    }
    Ok(())
}

/// Judges the membrane term on the stage that just ended (the first after the warm-up; its mesh
/// `judged`, started from `before`): when the term acted, runs the stage again without it, on
/// the same `stage_inputs`; the term's run stands, and the term stays on, when it acted on at
/// least [`MEMBRANE_MIN_SHARE`] of the vertices and its held-out outlines are within
/// [`MEMBRANE_SILHOUETTE_RATIO`] of the other run's (without views held out, on the share
/// alone). Returns the mesh the next stages start from, the verdict recorded in `checkpoint`.
pub(super) fn judge_membrane(
    stage_inputs: &mut StageInputs,
    (split, before, judged): (&Split, &TriMesh, TriMesh),
    checkpoint: &mut Checkpoint,
    progress: &dyn Progress,
) -> Result<TriMesh> {
    let stage = checkpoint.stages.last().expect("a stage has just ended");
    let (s, share) = (stage.stage, stage.membrane_share);
    let silhouette_with = stage.validation.as_ref().map(|v| v.silhouette);
    let large = share >= MEMBRANE_MIN_SHARE;
    let unjudged = MembraneVerdict {
        share,
        silhouette_with,
        silhouette_without: None,
        kept: large,
    };
    if share == 0.0 || (large && silhouette_with.is_none()) {
        progress.note(if share == 0.0 {
            "no face is unseen at the first stage's edges: the membrane term stays off"
        } else {
            "no views held out: the membrane term is kept unjudged"
        });
        checkpoint.membrane = Some(unjudged);
        return Ok(judged);
    }
    progress.note(&format!(
        "the membrane term acted on {:.0} % of the vertices: stage {} again without it, to judge it",
        100.0 * share,
        s + 1
    ));
    let with = FirstRun::take(checkpoint, judged);
    // The stage's second run reads the verdict: the term off.
    checkpoint.membrane = Some(MembraneVerdict {
        kept: false,
        ..unjudged.clone()
    });
    let without = run_next_stage(stage_inputs, split, checkpoint, before, progress)?;
    let silhouette_without =
        (checkpoint.stages.last().and_then(|r| r.validation.as_ref())).map(|v| v.silhouette);
    let ratio = silhouette_with.unwrap_or(f64::NAN) / silhouette_without.unwrap_or(f64::NAN);
    let kept = large && (ratio.is_nan() || ratio <= MEMBRANE_SILHOUETTE_RATIO);
    progress.note(&membrane_verdict_line(share, ratio, kept));
    checkpoint.membrane = Some(MembraneVerdict {
        silhouette_without,
        kept,
        ..unjudged
    });
    if !kept {
        with.discard(checkpoint);
        return Ok(without);
    }
    Ok(with.restore(checkpoint))
}

/// What the run says of the membrane term's verdict.
pub(super) fn membrane_verdict_line(share: f64, ratio: f64, kept: bool) -> String {
    let outlines = if ratio.is_nan() {
        "no views held out to compare the outlines with and without the membrane term".to_string()
    } else {
        format!("held-out outlines with the membrane term {ratio:.2}× as far as without")
    };
    if kept {
        format!("{outlines}: kept (the stage with it stands)")
    } else if share < MEMBRANE_MIN_SHARE {
        format!(
            "{outlines}; it acted on under {:.0} % of the vertices, no face seen edge-on: dropped",
            100.0 * MEMBRANE_MIN_SHARE
        )
    } else {
        format!("{outlines}: dropped (a rounded face, not a flat one)")
    }
}

/// A stage's first run, held while the same stage runs again: its report, iterations and mesh.
pub(super) struct FirstRun {
    report: StageReport,
    history: Vec<IterationRecord>,
    mesh: TriMesh,
}

impl FirstRun {
    /// Takes the last stage (its mesh `mesh`) out of `checkpoint`, which then has it still to run.
    fn take(checkpoint: &mut Checkpoint, mesh: TriMesh) -> Self {
        let report = checkpoint.stages.pop().expect("a stage has just ended");
        let (earlier, history) = checkpoint
            .history
            .drain(..)
            .partition(|r| r.stage != report.stage);
        checkpoint.history = earlier;
        checkpoint.stages_done -= 1;
        Self {
            report,
            history,
            mesh,
        }
    }

    /// Puts this run back in place of the stage's other run in `checkpoint`, with both runs' time;
    /// returns its mesh.
    fn restore(self, checkpoint: &mut Checkpoint) -> TriMesh {
        let other = checkpoint.stages.pop().expect("the stage has run again");
        checkpoint.history.retain(|r| r.stage != other.stage);
        checkpoint.history.extend(self.history);
        checkpoint.stages.push(StageReport {
            seconds: self.report.seconds + other.seconds,
            ..self.report
        });
        self.mesh
    }

    /// Drops this run; its time goes to the stage's other run in `checkpoint`, which stands.
    fn discard(self, checkpoint: &mut Checkpoint) {
        if let Some(other) = checkpoint.stages.last_mut() {
            other.seconds += self.report.seconds;
            // The blur correction both runs used was made, and timed, for this one.
            other.profile.blur += self.report.profile.blur;
        }
    }
}
