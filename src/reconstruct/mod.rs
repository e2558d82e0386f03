//! `glasscan reconstruct`: from a decoded scan and an initial mesh (the visual hull) to the mesh
//! the data supports. Coarse to fine: each stage remeshes to its edge length, then iterates
//! loss + gradient + optimiser step with the three terms weighted. After every stage the mesh
//! is checked (watertight, manifold, outward, finite), written, and committed by a checkpoint
//! ([`output`]), from which `--resume` continues with the same result as an uninterrupted run.

pub mod checkpoint;
pub mod confidence;
pub mod config;
pub mod coverage;
pub mod fingerprint;
pub mod flatness;
pub mod index;
pub mod inputs;
mod judges;
pub mod optim;
pub mod output;
pub mod pipeline;
pub mod plot;
pub mod pull;
mod stages;
mod terms;
pub mod validation;

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{bail, Context, Result};
use nalgebra::Point3;

use crate::hull::{visual_hull, HullOptions};
use crate::loss::refraction::ViewTargets;
use crate::mesh::io::{read_mesh, write_mesh};
use crate::mesh::TriMesh;
use crate::scan::silhouette::Silhouette;
use crate::trace::thickness::thickness_quantile;
pub use checkpoint::{
    Checkpoint, CostProfile, IterationRecord, MembraneVerdict, StageReport, WarmUpVerdict,
    MEMBRANE_MIN_SHARE, MEMBRANE_SILHOUETTE_RATIO,
};
use config::Settings;
pub use inputs::{load_inputs, Inputs};
use judges::*;
use output::commit;
pub use output::{checkpoint_path, stage_path, Existing};
pub use stages::remesh_options;
use stages::*;
use validation::Split;

/// Where a fresh run starts.
pub enum Start<'a> {
    /// The visual hull of the inputs' silhouettes, computed with these options (`hull.ply`).
    Hull(HullOptions),
    /// A given mesh, world frame, mm (`start.ply`).
    Mesh(&'a TriMesh),
}

/// A fresh run's start mesh (world frame, mm) and the name of the file it is written to.
#[derive(Clone)]
pub struct StartMesh {
    pub mesh: TriMesh,
    pub name: &'static str,
    /// A visual hull's voxel, mm.
    pub hull_voxel_mm: Option<f64>,
}

impl Start<'_> {
    /// The start mesh: the visual hull of `silhouettes`, or the given mesh.
    pub fn mesh(self, silhouettes: &[Silhouette]) -> Result<StartMesh> {
        Ok(match self {
            Start::Hull(o) => {
                let (mesh, report) = visual_hull(silhouettes, &o, &crate::util::progress::Silent)?;
                StartMesh {
                    mesh,
                    name: "hull.ply",
                    hull_voxel_mm: Some(report.carve.voxel_mm),
                }
            }
            Start::Mesh(m) => StartMesh {
                mesh: m.clone(),
                name: "start.ply",
                hull_voxel_mm: None,
            },
        })
    }
}

/// Progress callbacks of [`run`].
pub trait Progress {
    fn stage_start(
        &self,
        stage: usize,
        stages: usize,
        edge_mm: f64,
        faces: usize,
        iterations: usize,
    );
    fn iteration(&self, record: &IterationRecord);
    fn stage_end(&self, report: &StageReport);
    /// A line for the user (a warning, a step starting).
    fn note(&self, text: &str);
}

/// What [`run`] hands back: the last committed checkpoint and its mesh.
struct Finished {
    checkpoint: Checkpoint,
    mesh: TriMesh,
    /// False when `stop` ended the run before its last stage (continue with `--resume`).
    complete: bool,
}

/// Runs a reconstruction into `out`, or continues the committed run `existing` found there
/// ([`output::prepare`] decides which, before any work). `stop` set (Ctrl-C, a time budget)
/// ends the run after the current stage's commit.
fn run(
    inputs: &Inputs,
    start: Option<StartMesh>,
    settings: &Settings,
    out: &Path,
    existing: Existing,
    progress: &dyn Progress,
    stop: &AtomicBool,
) -> Result<Finished> {
    settings.check().map_err(anyhow::Error::msg)?;
    let (mut checkpoint, mut mesh) = match existing {
        Existing::Run(checkpoint) => continue_run(*checkpoint, inputs, settings, out)?,
        Existing::Nothing => {
            let start = start.context("internal error: a fresh run without a start mesh")?;
            begin_run(inputs, start, settings, out, progress)?
        }
    };
    let stages = settings.total_stages();
    let split = Split::new(inputs, settings.validation_share);
    while checkpoint.stages_done < stages {
        if stop.load(Ordering::SeqCst) {
            return Ok(Finished {
                checkpoint,
                mesh,
                complete: false,
            });
        }
        let judged =
            checkpoint.stages_done == settings.warmup_stages && settings.weight_membrane > 0.0;
        let before = judged.then(|| mesh.clone());
        let mut stage_inputs = StageInputs::prepare(inputs, &checkpoint, &mesh)?;
        mesh = run_next_stage(&mut stage_inputs, &split, &mut checkpoint, &mesh, progress)?;
        if let Some(before) = before {
            let judged = (&split, &before, mesh);
            mesh = judge_membrane(&mut stage_inputs, judged, &mut checkpoint, progress)?;
        }
        write_mesh(&stage_path(out, checkpoint.stages_done - 1), &mesh)?;
        if checkpoint.stages_done <= settings.warmup_stages {
            mesh = judge_warm_up(inputs, &split, &mut checkpoint, mesh, out, progress)?;
        }
        if inputs.ior.is_auto() {
            record_index(&mut checkpoint, inputs, progress);
        }
        commit(out, &checkpoint)?;
    }
    Ok(Finished {
        checkpoint,
        mesh,
        complete: true,
    })
}

/// After a stage of a run with an unknown index: the index it ended at (its estimate), which the
/// next stage starts from ([`index`]).
fn record_index(checkpoint: &mut Checkpoint, inputs: &Inputs, progress: &dyn Progress) {
    let from = checkpoint.index(inputs);
    let Some(estimate) = checkpoint.stages.last().and_then(|r| r.ior) else {
        return;
    };
    if estimate != from {
        progress.note(&format!(
            "refractive index: {estimate:.4} with the shape (the stage started at {from:.4})"
        ));
    }
    checkpoint.ior_fits.push([from, estimate]);
    checkpoint.ior_estimate = Some(estimate);
}

/// The start mesh of a fresh run, written to `out` and committed as a checkpoint with no stage
/// done, with the settings' footprint resolved.
fn begin_run(
    inputs: &Inputs,
    StartMesh { mesh, name, .. }: StartMesh,
    settings: &Settings,
    out: &Path,
    progress: &dyn Progress,
) -> Result<(Checkpoint, TriMesh)> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    write_mesh(&out.join(name), &mesh)?;
    let checkpoint = Checkpoint {
        settings: resolve_footprint(inputs, &mesh, settings, progress),
        diagonal_mm: mesh.bbox_diagonal(),
        thin_part_mm: thickness_quantile(&mesh, THIN_SHARE)?,
        start_mesh: name.into(),
        stages_done: 0,
        history: Vec::new(),
        stages: Vec::new(),
        warm_up: None,
        membrane: None,
        surface: None,
        inputs: inputs.fingerprint.clone(),
        ior: Some(inputs.ior),
        ior_estimate: None,
        ior_fits: Vec::new(),
    };
    commit(out, &checkpoint)?;
    Ok((checkpoint, mesh))
}

/// `settings` with their footprint resolved for the camera pixel at the centre of the start
/// `mesh` (the median over the views), when the decoded points measure whole pixels: decoded
/// from captures, they carry measured Gray bits; exact correspondences do not. A note says what
/// the run chose when it chose.
fn resolve_footprint(
    inputs: &Inputs,
    mesh: &TriMesh,
    settings: &Settings,
    progress: &dyn Progress,
) -> Settings {
    let centre = mesh
        .bbox()
        .map_or(Point3::origin(), |(lo, hi)| nalgebra::center(&lo, &hi));
    let pixels = inputs.targets.iter().filter_map(|t| t.pixel_mm_at(&centre));
    let pixel_mm = crate::util::median(pixels.collect());
    let measured = inputs.targets.iter().any(ViewTargets::has_measured_bits);
    let diagonal = mesh.bbox_diagonal();
    let footprint = settings.resolve_footprint(measured.then_some(pixel_mm), diagonal);
    if settings.footprint == config::AUTO_FOOTPRINT {
        let why = if measured {
            ""
        } else {
            "; the decoded points are exact centre-ray correspondences (no measured Gray bits)"
        };
        progress.note(&format!(
            "footprint: {footprint}×{footprint} rays per pixel (a camera pixel spans {pixel_mm:.2} mm at the object, the last stage's edges {:.2} mm{why})",
            settings.last_edge_mm(diagonal)
        ));
    }
    Settings {
        footprint,
        ..settings.clone()
    }
}

/// The committed state of the run in `out`, checked against `inputs` and `settings`.
fn continue_run(
    checkpoint: Checkpoint,
    inputs: &Inputs,
    settings: &Settings,
    out: &Path,
) -> Result<(Checkpoint, TriMesh)> {
    let changed = fingerprint::changes(&checkpoint.inputs, &inputs.fingerprint);
    if !changed.is_empty() {
        bail!(
            "--resume: the run in {} was made from other inputs ({} changed since): give the scan and views it was made from, or start over with --force",
            out.display(),
            changed.join(", ")
        );
    }
    if checkpoint.ior.is_some_and(|i| i != inputs.ior) {
        bail!(
            "--resume: the run in {} was given another refractive index ({}); give the same (scan.toml or --ior), or start over with --force",
            out.display(),
            checkpoint.ior.map_or(String::new(), |i| format!("{i:?}"))
        );
    }
    if !settings.continues(&checkpoint.settings) {
        bail!(
            "--resume: the settings differ from the run in {} (its settings are in checkpoint.json)",
            out.display()
        );
    }
    let discarded = checkpoint.warm_up.as_ref().is_some_and(|w| w.discarded);
    let path = match checkpoint.stages_done {
        0 => out.join(&checkpoint.start_mesh),
        n if discarded && n == checkpoint.settings.warmup_stages => {
            out.join(&checkpoint.start_mesh)
        }
        n => stage_path(out, n - 1),
    };
    let mesh = read_mesh(&path).context(
        "--resume: the mesh the checkpoint names is unreadable; start over with --force",
    )?;
    Ok((checkpoint, mesh))
}

#[cfg(test)]
mod tests {
    use super::*;
    use config::Preset;

    #[test]
    fn a_resumed_run_starts_after_a_discarded_warm_up_from_the_start_mesh() {
        let dir = tempfile::tempdir().unwrap();
        let start = crate::mesh::shapes::icosphere(10.0, 1);
        let warmed = crate::mesh::shapes::icosphere(12.0, 1);
        write_mesh(&dir.path().join("start.ply"), &start).unwrap();
        let mut checkpoint = Checkpoint::example(None);
        let inputs = Inputs {
            ior: crate::scan::Ior::Known(1.5),
            ior_start: None,
            targets: Vec::new(),
            kept_shares: Vec::new(),
            silhouettes: Default::default(),
            blur: None,
            blur_source: Default::default(),
            skew_marks: false,
            curved_captures: false,
            fingerprint: Default::default(),
        };
        checkpoint.stages_done = checkpoint.settings.warmup_stages;
        for s in 0..checkpoint.stages_done {
            write_mesh(&stage_path(dir.path(), s), &warmed).unwrap();
        }
        for (discarded, want) in [(true, &start), (false, &warmed)] {
            checkpoint.warm_up = Some(WarmUpVerdict {
                start_refraction: 1.0,
                warm_up_refraction: if discarded { 2.0 } else { 0.5 },
                discarded,
            });
            let settings = checkpoint.settings.clone();
            let (_, mesh) =
                continue_run(checkpoint.clone(), &inputs, &settings, dir.path()).unwrap();
            assert_eq!(mesh.positions, want.positions, "discarded: {discarded}");
        }
        // Inputs other than the run's are refused, naming what changed.
        let other = Inputs {
            fingerprint: [("decoded".to_string(), "1".to_string())].into(),
            ..inputs
        };
        let e =
            continue_run(checkpoint.clone(), &other, &checkpoint.settings, dir.path()).unwrap_err();
        assert!(e.to_string().contains("(decoded changed since)"), "{e}");
    }

    /// Keeps the notes of a run.
    #[derive(Default)]
    struct Notes(std::sync::Mutex<Vec<String>>);

    impl Progress for Notes {
        fn stage_start(&self, _: usize, _: usize, _: f64, _: usize, _: usize) {}
        fn iteration(&self, _: &IterationRecord) {}
        fn stage_end(&self, _: &StageReport) {}
        fn note(&self, text: &str) {
            self.0.lock().unwrap().push(text.to_string());
        }
    }

    #[test]
    fn a_run_resolves_its_footprint_from_the_pixel_at_the_start_mesh_and_the_measured_bits() {
        use crate::loss::bits::{BitContrast, PixelBits};
        use crate::loss::refraction::{view_down_z, PixelTarget};
        // A sphere of radius 10 mm: diagonal 20·√3 mm, `accurate`'s last edge 1/350 of it
        // (0.099 mm); a camera 100 mm away with 500 px focal length: 0.2 mm pixels, 2.02 edges.
        let mesh = crate::mesh::shapes::icosphere(10.0, 2);
        let inputs = |bits: PixelBits| Inputs {
            ior: crate::scan::Ior::Known(1.5),
            ior_start: None,
            targets: vec![ViewTargets {
                pixels: vec![PixelTarget {
                    dir: -nalgebra::Vector3::z(),
                    target: Point3::new(0.0, 0.0, -300.0),
                    weight: 1.0,
                    bits,
                    cell_px: 1.0,
                    direct_px: 1.0,
                    index_evidence: true,
                }],
                ..view_down_z(100.0, (500.0, 500.0))
            }],
            kept_shares: vec![1.0],
            silhouettes: Default::default(),
            blur: None,
            blur_source: Default::default(),
            skew_marks: false,
            curved_captures: false,
            fingerprint: Default::default(),
        };
        let measured = PixelBits {
            u: [
                Some(BitContrast {
                    bit: 3,
                    contrast: 0.5,
                }),
                None,
            ],
            ..PixelBits::default()
        };
        let accurate = Settings::preset(Preset::Accurate);
        let notes = Notes::default();
        let resolved = resolve_footprint(&inputs(measured), &mesh, &accurate, &notes);
        assert_eq!(resolved.footprint, 2);
        assert!(accurate.continues(&resolved));
        // Exact correspondences (no measured bits) keep the centre ray.
        let exact = resolve_footprint(&inputs(PixelBits::default()), &mesh, &accurate, &notes);
        assert_eq!(exact.footprint, 1);
        let notes = notes.0.into_inner().unwrap();
        assert!(
            notes[0].starts_with("footprint: 2×2") && notes[0].contains("0.20 mm"),
            "{notes:?}"
        );
        assert!(notes[1].contains("centre-ray"), "{notes:?}");
        // A preset that sets its footprint keeps it, without a note.
        let quiet = Notes::default();
        let balanced = Settings::preset(Preset::Balanced);
        assert_eq!(
            resolve_footprint(&inputs(measured), &mesh, &balanced, &quiet),
            balanced
        );
        assert!(quiet.0.into_inner().unwrap().is_empty());
    }
}
