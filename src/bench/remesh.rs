//! `glasscan bench remesh`: glasscan's remesher against pymeshlab's
//! `meshing_isotropic_explicit_remeshing` on the same inputs and settings, timed and judged by
//! the same statistics.
//!
//! pymeshlab runs in a Python interpreter given by the caller (`make bench-remesh` sets up a venv
//! with it); its filter call alone is timed, in Python, so file I/O is excluded on both sides.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::eval::sampled_distances;
use crate::mesh::io::{read_mesh, write_mesh};
use crate::mesh::stats::{quality, MeshQuality};
use crate::mesh::TriMesh;
use crate::remesh::{remesh, RemeshOptions};
use crate::trace::{BuildMode, Device, Scene};

/// Surface samples used for the distance of a remeshed mesh to its input.
const DISTANCE_SAMPLES: usize = 200_000;

/// What one remeshing produced, and how long it took.
#[derive(Clone, Debug, Serialize)]
pub struct RemeshFigures {
    pub seconds: f64,
    pub quality: MeshQuality,
    /// Face-sampled distances from the output to the input surface, mm.
    pub distance_mean_mm: f64,
    pub distance_max_mm: f64,
}

/// Quality of `output` and its face-sampled distance to `input` (seeded).
pub fn figures(
    input: &TriMesh,
    output: &TriMesh,
    seconds: f64,
    seed: u64,
) -> Result<RemeshFigures> {
    let device = Device::new()?;
    let scene = Scene::new(&device, input, BuildMode::Static)?;
    let d = sampled_distances(output, &scene, DISTANCE_SAMPLES, seed)?;
    Ok(RemeshFigures {
        seconds,
        quality: quality(output),
        distance_mean_mm: d.iter().sum::<f64>() / d.len().max(1) as f64,
        distance_max_mm: d.iter().copied().fold(0.0, f64::max),
    })
}

/// One benchmark case: an input, a schedule of target edge lengths (each stage remeshes the
/// previous stage's output) and the iterations per stage.
#[derive(Clone, Debug, Serialize)]
pub struct Case {
    pub name: String,
    pub input: PathBuf,
    pub schedule_mm: Vec<f64>,
    pub iterations: usize,
}

/// The results of one case.
#[derive(Clone, Debug, Serialize)]
pub struct CaseResult {
    pub case: Case,
    pub glasscan: RemeshFigures,
    /// Time of the last stage alone, seconds.
    pub glasscan_last_stage_s: f64,
    pub pymeshlab: Option<RemeshFigures>,
    pub pymeshlab_last_stage_s: Option<f64>,
}

/// The cases of the benchmark: every `*_scan.ply` and `*_vh.ply` in `dir` at each of `edges_mm`
/// (10 iterations), and DRT's schedule from `pig_vh.ply` (20 stages from 10 mm to 1 mm, 1/h linear
/// in the stage index, 3 iterations each).
pub fn cases(dir: &Path, edges_mm: &[f64]) -> Result<Vec<Case>> {
    let mut inputs: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot list {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let n = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            n.ends_with("_scan.ply") || n.ends_with("_vh.ply")
        })
        .collect();
    inputs.sort();
    if inputs.is_empty() {
        bail!("no *_scan.ply or *_vh.ply meshes in {}", dir.display());
    }
    let mut cases = Vec::new();
    for input in &inputs {
        let stem = input
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("mesh")
            .to_string();
        for &h in edges_mm {
            cases.push(Case {
                name: format!("{stem} h={h}"),
                input: input.clone(),
                schedule_mm: vec![h],
                iterations: 10,
            });
        }
    }
    let pig_vh = dir.join("pig_vh.ply");
    if pig_vh.is_file() {
        let schedule = (0..20)
            .map(|k| 1.0 / (0.1 + 0.9 * k as f64 / 19.0))
            .collect();
        cases.push(Case {
            name: "DRT schedule from pig_vh".into(),
            input: pig_vh,
            schedule_mm: schedule,
            iterations: 3,
        });
    }
    Ok(cases)
}

/// Runs `cases` with glasscan and, if `python` is given, with pymeshlab; `work` receives both
/// sides' outputs (`glasscan_N.ply`, `pymeshlab_N.ply`). `progress` is told each finished case.
pub fn run(
    cases: &[Case],
    python: Option<&Path>,
    work: &Path,
    mut progress: impl FnMut(&CaseResult) -> Result<()>,
) -> Result<Vec<CaseResult>> {
    let pml = match python {
        Some(py) => Some(run_pymeshlab(py, cases, work)?),
        None => None,
    };
    let mut results = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        let input = read_mesh(&case.input)?;
        let mut mesh = input.clone();
        let mut total = 0.0;
        let mut last = 0.0;
        for &h in &case.schedule_mm {
            let opts = RemeshOptions {
                iterations: case.iterations,
                ..RemeshOptions::uniform(h)
            };
            let t0 = Instant::now();
            mesh = remesh(&mesh, &opts)
                .with_context(|| format!("{}: remeshing at {h} mm", case.name))?;
            last = t0.elapsed().as_secs_f64();
            total += last;
        }
        std::fs::create_dir_all(work)
            .with_context(|| format!("cannot create {}", work.display()))?;
        write_mesh(&work.join(format!("glasscan_{i}.ply")), &mesh)?;
        let glasscan = figures(&input, &mesh, total, i as u64)?;
        let (pymeshlab, pymeshlab_last_stage_s) = match &pml {
            Some(runs) => {
                let run = &runs[i];
                let out = read_mesh(&run.output)?;
                (
                    Some(figures(
                        &input,
                        &out,
                        run.stage_seconds.iter().sum(),
                        i as u64,
                    )?),
                    run.stage_seconds.last().copied(),
                )
            }
            None => (None, None),
        };
        let result = CaseResult {
            case: case.clone(),
            glasscan,
            glasscan_last_stage_s: last,
            pymeshlab,
            pymeshlab_last_stage_s,
        };
        progress(&result)?;
        results.push(result);
    }
    Ok(results)
}

#[derive(Serialize)]
struct PmlJob<'a> {
    input: &'a Path,
    output: PathBuf,
    schedule: &'a [f64],
    iterations: usize,
}

#[derive(Deserialize)]
struct PmlRun {
    output: PathBuf,
    stage_seconds: Vec<f64>,
}

/// The pymeshlab side: one process runs every job and reports the filter times.
const PYMESHLAB_SCRIPT: &str = r#"
import json, sys, time
import pymeshlab
value = getattr(pymeshlab, "PureValue", None) or getattr(pymeshlab, "AbsoluteValue")
jobs = json.load(open(sys.argv[1]))
runs = []
for job in jobs:
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(job["input"])
    secs = []
    for h in job["schedule"]:
        t0 = time.perf_counter()
        # featuredeg=180: no feature preservation, as glasscan's default.
        ms.meshing_isotropic_explicit_remeshing(iterations=job["iterations"], targetlen=value(h), featuredeg=180)
        secs.append(time.perf_counter() - t0)
    ms.save_current_mesh(job["output"], binary=True)
    runs.append({"output": job["output"], "stage_seconds": secs})
    print(f"pymeshlab: {job['input']} done in {sum(secs):.2f} s", file=sys.stderr, flush=True)
json.dump(runs, open(sys.argv[2], "w"))
"#;

fn run_pymeshlab(python: &Path, cases: &[Case], work: &Path) -> Result<Vec<PmlRun>> {
    std::fs::create_dir_all(work).with_context(|| format!("cannot create {}", work.display()))?;
    let jobs: Vec<PmlJob> = cases
        .iter()
        .enumerate()
        .map(|(i, c)| PmlJob {
            input: &c.input,
            output: work.join(format!("pymeshlab_{i}.ply")),
            schedule: &c.schedule_mm,
            iterations: c.iterations,
        })
        .collect();
    let (script, jobs_file, runs_file) = (
        work.join("pymeshlab_bench.py"),
        work.join("jobs.json"),
        work.join("runs.json"),
    );
    std::fs::write(&script, PYMESHLAB_SCRIPT)
        .with_context(|| format!("cannot write {}", script.display()))?;
    std::fs::write(&jobs_file, serde_json::to_vec(&jobs)?)
        .with_context(|| format!("cannot write {}", jobs_file.display()))?;
    let status = Command::new(python)
        .arg(&script)
        .arg(&jobs_file)
        .arg(&runs_file)
        .status()
        .with_context(|| format!("cannot run {}", python.display()))?;
    if !status.success() {
        bail!("pymeshlab run failed ({status}); is pymeshlab installed for {}? (make bench-remesh sets up a venv with it)", python.display());
    }
    let bytes = std::fs::read(&runs_file).with_context(|| {
        format!(
            "pymeshlab wrote no runs: cannot read {}",
            runs_file.display()
        )
    })?;
    let runs: Vec<PmlRun> = serde_json::from_slice(&bytes).with_context(|| {
        format!(
            "pymeshlab's runs in {} are not readable",
            runs_file.display()
        )
    })?;
    if runs.len() != cases.len() {
        bail!(
            "pymeshlab reported {} runs for {} cases",
            runs.len(),
            cases.len()
        );
    }
    Ok(runs)
}
