//! `glasscan bench reconstruct`: the speed/accuracy trade of the presets, measured. For each
//! object it simulates a scan (72 views, decoded-only with exact correspondences, and, with
//! `noisy`, captures with sensor noise and blur decoded by `glasscan decode`), reconstructs it
//! with each preset and view count (hull included in the time), and evaluates every stage's
//! mesh against the truth. The `drt` preset gets the time of the slowest other preset on the
//! same scan and views ("equal time"): it stops after the first stage past it, and its accuracy is
//! read off at that budget from its stage meshes.
//!
//! Results accumulate in `WORK/results.json` (a rerun skips the runs already there), with
//! `WORK/results.md` (the table) and `WORK/time_vs_accuracy.png` rewritten after every run.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::decode::{decode_scan, DecodeOptions};
use crate::eval::{evaluate, EvalOptions, EvalReport};
use crate::hull::{visual_hull, HullOptions};
use crate::mesh::io::read_mesh;
use crate::reconstruct::config::Settings;
use crate::reconstruct::plot::time_accuracy_plot;
use crate::reconstruct::{self, stage_path, Existing, Progress, Start};
use crate::scan::Scan;
use crate::simulate::{simulate, SimulateOptions};
use crate::util::atomic::write_atomic;

/// What to run.
#[derive(Clone, Debug)]
pub struct BenchOptions {
    /// Folder with `{object}_scan.ply`.
    pub meshes: PathBuf,
    /// Scans, runs and results go here.
    pub work: PathBuf,
    pub objects: Vec<String>,
    pub presets: Vec<String>,
    /// View counts, each taken evenly from the 72.
    pub views: Vec<usize>,
    /// Which scans: "exact" (decoded-only) and/or "noisy" (noise 2, blur 0.7, decoded).
    pub scans: Vec<String>,
}

/// One reconstruction, evaluated.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BenchRun {
    pub object: String,
    pub scan: String,
    pub preset: String,
    pub views: usize,
    /// Hull + stages, seconds (for `drt`: up to the budget).
    pub seconds: f64,
    pub seconds_hull: f64,
    /// Stages run of the preset's; fewer for a `drt` run cut at the budget.
    pub stages_done: usize,
    pub stages: usize,
    pub accuracy_mm: f64,
    pub completeness_mm: f64,
    pub fscore_05: f64,
    pub fscore_1: f64,
    pub faces: usize,
    /// (seconds since the start, accuracy mm) after the hull and after each stage.
    pub curve: Vec<(f64, f64)>,
}

/// Object views of the scans.
pub const SCAN_VIEWS: usize = 72;

/// Runs everything `o` asks for that `WORK/results.json` does not hold yet.
pub fn run_bench(
    o: &BenchOptions,
    progress: &dyn Progress,
    log: &dyn Fn(&str),
) -> Result<Vec<BenchRun>> {
    for n in &o.views {
        if *n == 0 || *n > SCAN_VIEWS {
            bail!("view count {n}: choose 1..={SCAN_VIEWS}");
        }
    }
    for p in &o.presets {
        Settings::preset(p).with_context(|| format!("unknown preset '{p}'"))?;
    }
    for s in &o.scans {
        if s != "exact" && s != "noisy" {
            bail!("scan kind '{s}': choose exact or noisy");
        }
    }
    std::fs::create_dir_all(&o.work)
        .with_context(|| format!("cannot create {}", o.work.display()))?;
    let results_path = o.work.join("results.json");
    let mut results: Vec<BenchRun> = if results_path.is_file() {
        serde_json::from_str(&std::fs::read_to_string(&results_path)?)
            .with_context(|| format!("{}: not a bench results file", results_path.display()))?
    } else {
        Vec::new()
    };
    // drt last, so that the other presets set its budget.
    let mut presets = o.presets.clone();
    presets.sort_by_key(|p| p == "drt");
    for object in &o.objects {
        let mesh_path = o.meshes.join(format!("{object}_scan.ply"));
        if !mesh_path.is_file() {
            bail!(
                "{}: no such mesh (--meshes names the folder of {{object}}_scan.ply)",
                mesh_path.display()
            );
        }
        for kind in &o.scans {
            let scan_dir = o.work.join("scans").join(format!("{object}_{kind}"));
            ensure_scan(&mesh_path, &scan_dir, kind == "noisy", log)?;
            let scan = Scan::open(&scan_dir)?;
            let truth = read_mesh(&scan_dir.join("ground_truth.ply"))?;
            for &n in &o.views {
                for preset in &presets {
                    let done = |r: &BenchRun| {
                        r.object == *object
                            && r.scan == *kind
                            && r.preset == *preset
                            && r.views == n
                    };
                    if results.iter().any(done) {
                        continue;
                    }
                    let budget = (preset == "drt")
                        .then(|| {
                            results
                                .iter()
                                .filter(|r| {
                                    r.object == *object
                                        && r.scan == *kind
                                        && r.views == n
                                        && r.preset != "drt"
                                })
                                .map(|r| r.seconds)
                                .fold(None, |m: Option<f64>, s| Some(m.map_or(s, |m| m.max(s))))
                        })
                        .flatten();
                    log(&format!(
                        "{object} ({kind}), {preset}, {n} views{}",
                        budget.map_or(String::new(), |b| format!(", budget {b:.0} s"))
                    ));
                    let run_dir = o
                        .work
                        .join("runs")
                        .join(format!("{object}_{kind}_{preset}_v{n}"));
                    let r = run_one(
                        &scan, &truth, object, kind, preset, n, budget, &run_dir, progress,
                    )?;
                    log(&format!(
                        "  {:.1} s, accuracy {:.3} mm, completeness {:.3} mm, F@0.5 {:.3}, F@1 {:.3}",
                        r.seconds, r.accuracy_mm, r.completeness_mm, r.fscore_05, r.fscore_1
                    ));
                    results.push(r);
                    write_results(&o.work, &results)?;
                }
            }
        }
    }
    write_results(&o.work, &results)?;
    Ok(results)
}

/// Simulates (and for `noisy`, decodes) the scan unless `dir` already holds it.
fn ensure_scan(mesh_path: &Path, dir: &Path, noisy: bool, log: &dyn Fn(&str)) -> Result<()> {
    if dir.join("decoded").join("summary.json").is_file() {
        return Ok(());
    }
    let mesh = read_mesh(mesh_path)?;
    let o = SimulateOptions {
        views: SCAN_VIEWS,
        decoded_only: !noisy,
        spp: if noisy { 4 } else { 1 },
        noise: if noisy { 2.0 } else { 0.0 },
        blur_px: if noisy { 0.7 } else { 0.0 },
        // The bench's own work folder: a scan left half made (decode interrupted) is replaced.
        force: true,
        ..Default::default()
    };
    log(&format!(
        "simulating {} into {}",
        mesh_path.display(),
        dir.display()
    ));
    let t0 = Instant::now();
    simulate(&mesh, dir, &o, |_| ())?;
    if noisy {
        let scan = Scan::open(dir)?;
        let views: Vec<usize> = (0..SCAN_VIEWS).collect();
        decode_scan(&scan, &views, &DecodeOptions::default(), |_| ())?;
    }
    log(&format!("  {:.1} s", t0.elapsed().as_secs_f64()));
    Ok(())
}

/// `n` views spread evenly over the scan's.
fn spread_views(n: usize, total: usize) -> Vec<usize> {
    (0..n).map(|k| k * total / n).collect()
}

#[allow(clippy::too_many_arguments)]
fn run_one(
    scan: &Scan,
    truth: &crate::mesh::TriMesh,
    object: &str,
    kind: &str,
    preset: &str,
    n: usize,
    budget: Option<f64>,
    dir: &Path,
    progress: &dyn Progress,
) -> Result<BenchRun> {
    let settings = Settings::preset(preset).expect("checked");
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("cannot clear {}", dir.display()))?;
    }
    let views = spread_views(n, scan.config.views.angles_deg.len());
    let t0 = Instant::now();
    let (inputs, _) = reconstruct::load_inputs(scan, &views, settings.target_weights)?;
    let (hull, _) = visual_hull(
        &inputs.silhouettes,
        &HullOptions::default(),
        &indicatif::ProgressBar::hidden(),
    )?;
    let seconds_hull = t0.elapsed().as_secs_f64();
    let stop = Arc::new(AtomicBool::new(false));
    if let Some(b) = budget {
        let stop = stop.clone();
        let left = (b - seconds_hull).max(0.0);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs_f64(left));
            stop.store(true, Ordering::SeqCst);
        });
    }
    // A run cut at the budget ends after a stage's commit; the stages it finished are read back.
    let ck = reconstruct::run(
        &inputs,
        Start::Mesh(&hull),
        &settings,
        dir,
        Existing::Nothing,
        progress,
        &stop,
    )?
    .checkpoint;
    let quick = EvalOptions {
        samples: 200_000,
        ..EvalOptions::default()
    };
    let mut curve = vec![(seconds_hull, evaluate(&hull, truth, &quick)?.accuracy_mm)];
    let mut elapsed = seconds_hull;
    let mut last = None;
    for (s, st) in ck.stages.iter().enumerate() {
        elapsed += st.seconds;
        if budget.is_some_and(|b| elapsed > b) && last.is_some() {
            break;
        }
        let mesh = read_mesh(&stage_path(dir, s))?;
        curve.push((elapsed, evaluate(&mesh, truth, &quick)?.accuracy_mm));
        last = Some((s, elapsed, mesh));
    }
    let (s, seconds, mesh) = last.context("the run finished no stage")?;
    let e: EvalReport = evaluate(&mesh, truth, &EvalOptions::default())?;
    let f = |t: f64| {
        e.fscores
            .iter()
            .find(|f| (f.threshold_mm - t).abs() < 1e-9)
            .map_or(f64::NAN, |f| f.fscore)
    };
    Ok(BenchRun {
        object: object.into(),
        scan: kind.into(),
        preset: preset.into(),
        views: n,
        seconds,
        seconds_hull,
        stages_done: s + 1,
        stages: settings.total_stages(),
        accuracy_mm: e.accuracy_mm,
        completeness_mm: e.completeness_mm,
        fscore_05: f(0.5),
        fscore_1: f(1.0),
        faces: mesh.faces.len(),
        curve,
    })
}

/// Writes results.json, results.md and time_vs_accuracy.png.
fn write_results(work: &Path, results: &[BenchRun]) -> Result<()> {
    write_atomic(&work.join("results.json"), |w| {
        serde_json::to_writer_pretty(&mut *w, results)?;
        Ok(())
    })?;
    let mut md = String::from(
        "| object | scan | preset | views | time (s) | accuracy (mm) | completeness (mm) | F@0.5 mm | F@1 mm | stages |\n|---|---|---|---:|---:|---:|---:|---:|---:|---|\n",
    );
    for r in results {
        md += &format!(
            "| {} | {} | {} | {} | {:.0} | {:.3} | {:.3} | {:.3} | {:.3} | {}/{} |\n",
            r.object,
            r.scan,
            r.preset,
            r.views,
            r.seconds,
            r.accuracy_mm,
            r.completeness_mm,
            r.fscore_05,
            r.fscore_1,
            r.stages_done,
            r.stages
        );
    }
    write_atomic(&work.join("results.md"), |w| w.write_all(md.as_bytes()))?;
    let series: Vec<(String, Vec<(f64, f64)>)> = results
        .iter()
        .map(|r| {
            (
                format!("{} {} {} {}v", r.object, r.scan, r.preset, r.views),
                r.curve.clone(),
            )
        })
        .collect();
    time_accuracy_plot(&work.join("time_vs_accuracy.png"), &series)
}
