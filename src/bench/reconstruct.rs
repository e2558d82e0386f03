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

use super::ObjectMesh;
use crate::eval::{evaluate, EvalOptions, EvalReport};
use crate::hull::{visual_hull, HullOptions};
use crate::mesh::io::read_mesh;
use crate::mesh::TriMesh;
use crate::reconstruct::config::{Preset, Settings};
use crate::reconstruct::pipeline::{reconstruct_scan, Job};
use crate::reconstruct::plot::time_accuracy_plot;
use crate::reconstruct::validation::best_stage;
use crate::reconstruct::{self, stage_path, CostProfile, Existing, Progress, Start};
use crate::scan::Scan;
use crate::simulate::{monitor_covers, simulated_scan, SimulateOptions, Transport};

/// The scans the benchmark simulates, 72 views each.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum ScanKind {
    /// Decoded-only: exact correspondences from the simulator, no captures.
    Exact,
    /// Captures with sensor noise (σ = 2 grey levels), 0.7 px blur and 4 samples per pixel,
    /// decoded by `glasscan decode`.
    Noisy,
    /// As `noisy`, with the physical light transport (Fresnel reflections, internal reflections
    /// and their ghosts).
    Physical,
    /// A diagnostic: the `physical` scan decoded, then every view's decoded silhouette replaced
    /// by the simulator's true one (the pixels whose centre ray meets the object, and its
    /// outline's coverage by the true coverage blurred as the captures are). Against `physical`
    /// it measures how much of the error the decoded silhouettes cause.
    PhysicalTrueMasks,
}

impl ScanKind {
    /// The name used on the command line, in folder names and in the tables.
    pub fn name(self) -> &'static str {
        match self {
            ScanKind::Exact => "exact",
            ScanKind::Noisy => "noisy",
            ScanKind::Physical => "physical",
            ScanKind::PhysicalTrueMasks => "physical-true-masks",
        }
    }

    /// The simulator's options for this kind of scan on `rig` (a smooth object's normals).
    pub fn simulate_options(self, rig: &Rig) -> SimulateOptions {
        let noisy = self != ScanKind::Exact;
        let d = SimulateOptions::default();
        let (screen_width, screen_height, pitch_mm) = if rig.large_monitor {
            LARGE_MONITOR
        } else {
            (d.screen_width, d.screen_height, d.pitch_mm)
        };
        SimulateOptions {
            views: SCAN_VIEWS,
            width: rig.width,
            height: rig.height,
            fill: rig.fill,
            screen_width,
            screen_height,
            pitch_mm,
            decoded_only: !noisy,
            spp: if noisy { 4 } else { 1 },
            noise: if noisy { 2.0 } else { 0.0 },
            blur_px: if noisy { 0.7 } else { 0.0 },
            transport: match self {
                ScanKind::Physical | ScanKind::PhysicalTrueMasks => Transport::Physical,
                ScanKind::Exact | ScanKind::Noisy => Transport::Simple,
            },
            // The bench's own work folder: a scan left half made (decode interrupted) is replaced.
            force: true,
            ..d
        }
    }
}

impl std::fmt::Display for ScanKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The simulated camera: image size (px) and the share of the image height the object fills;
/// and whether the rig's monitor is the simulator's default or [`LARGE_MONITOR`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rig {
    pub width: u32,
    pub height: u32,
    pub fill: f64,
    /// [`LARGE_MONITOR`] instead of the default one, which does not cover the object.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub large_monitor: bool,
}

/// A 32-inch 4K monitor (3840 × 2160 pixels of 0.1845 mm, 398 mm tall): the bench's monitor
/// for objects the default 24-inch one (293 mm tall) does not cover, such as the horse.
pub const LARGE_MONITOR: (u32, u32, f64) = (3840, 2160, 0.1845);

impl Default for Rig {
    /// The simulator's defaults (1280×960, fill 0.6); results written before the rig was
    /// recorded were made with it.
    fn default() -> Self {
        let s = SimulateOptions::default();
        Self {
            width: s.width,
            height: s.height,
            fill: s.fill,
            large_monitor: false,
        }
    }
}

impl Rig {
    /// Suffix of the scan folders: none for the default rig.
    pub(super) fn folder_suffix(&self) -> String {
        let camera = Rig {
            large_monitor: false,
            ..*self
        };
        let mut suffix = if camera == Rig::default() {
            String::new()
        } else {
            format!("_{}x{}_fill{}", self.width, self.height, self.fill)
        };
        if self.large_monitor {
            let (w, h, _) = LARGE_MONITOR;
            suffix += &format!("_monitor{w}x{h}");
        }
        suffix
    }

    /// This rig for `mesh`: with [`LARGE_MONITOR`] if the default monitor does not cover it.
    pub(super) fn for_object(&self, mesh: &TriMesh) -> Result<Rig> {
        let default = ScanKind::Exact.simulate_options(self);
        Ok(Rig {
            large_monitor: !monitor_covers(mesh, &default)?,
            ..*self
        })
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct BenchOptions {
    /// Folder with `{object}_scan.ply`.
    pub meshes: PathBuf,
    /// Scans, runs and results go here.
    pub work: PathBuf,
    pub objects: Vec<String>,
    pub presets: Vec<Preset>,
    /// View counts, each taken evenly from the 72.
    pub views: Vec<usize>,
    pub scans: Vec<ScanKind>,
    pub rig: Rig,
}

/// One reconstruction, evaluated.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BenchRun {
    pub object: String,
    pub scan: ScanKind,
    #[serde(default)]
    pub rig: Rig,
    pub preset: Preset,
    pub views: usize,
    /// Hull + stages, seconds (for `drt`: up to the budget).
    pub seconds: f64,
    pub seconds_hull: f64,
    /// Stages run of the preset's; fewer for a `drt` run cut at the budget.
    pub stages_done: usize,
    /// The stage evaluated: the one within the budget that fits the held-out views best (the
    /// last when none are held out), counted from 1.
    #[serde(default)]
    pub result_stage: usize,
    pub stages: usize,
    pub accuracy_mm: f64,
    /// The accuracy with distances inside the true mesh counted negative (mm, > 0: the result
    /// is too large); absent from runs recorded before it existed.
    #[serde(default)]
    pub signed_accuracy_mm: Option<f64>,
    pub completeness_mm: f64,
    pub fscore_05: f64,
    pub fscore_1: f64,
    pub faces: usize,
    /// (seconds since the start, accuracy mm) after the hull and after each stage.
    pub curve: Vec<(f64, f64)>,
    /// Where the stages' time went, summed over the stages run.
    #[serde(default)]
    pub profile: CostProfile,
}

/// Object views of the scans.
pub const SCAN_VIEWS: usize = 72;

/// Runs everything `o` asks for that `WORK/results.json` does not hold yet.
pub fn run_bench(
    o: &BenchOptions,
    progress: &dyn Progress,
    log: &dyn Fn(&str),
) -> Result<Vec<BenchRun>> {
    check_options(o)?;
    std::fs::create_dir_all(&o.work)
        .with_context(|| format!("cannot create {}", o.work.display()))?;
    let mut results: Vec<BenchRun> = super::read_runs(&o.work.join("results.json"))?;
    // drt last, so that the other presets set its budget.
    let mut presets = o.presets.clone();
    presets.sort_by_key(|p| *p == Preset::Drt);
    for object in &o.objects {
        let object_mesh = ObjectMesh::locate(&o.meshes, object)?;
        let rig = o.rig.for_object(&object_mesh.read()?)?;
        for &kind in &o.scans {
            let scan_dir =
                (o.work.join("scans")).join(format!("{object}_{kind}{}", rig.folder_suffix()));
            ensure_scan(&object_mesh, &scan_dir, kind, &rig, log)?;
            let scan = Scan::open(&scan_dir)?;
            let truth = read_mesh(&scan_dir.join("ground_truth.ply"))?;
            for &views in &o.views {
                for &preset in &presets {
                    let case = Case {
                        object,
                        kind,
                        rig,
                        preset,
                        views,
                    };
                    if results.iter().any(|r| case.is(r)) {
                        continue;
                    }
                    let budget = (preset == Preset::Drt)
                        .then(|| case.slowest_other(&results))
                        .flatten();
                    let r = run_case(&case, &scan, &truth, budget, &o.work, progress, log)?;
                    results.push(r);
                    write_results(&o.work, &results)?;
                }
            }
        }
    }
    write_results(&o.work, &results)?;
    Ok(results)
}

/// View counts in range and every object's mesh present, before any work.
fn check_options(o: &BenchOptions) -> Result<()> {
    for n in &o.views {
        if *n == 0 || *n > SCAN_VIEWS {
            bail!("view count {n}: choose 1..={SCAN_VIEWS}");
        }
    }
    for object in &o.objects {
        ObjectMesh::locate(&o.meshes, object)?;
    }
    Ok(())
}

/// One reconstruction of the benchmark.
struct Case<'a> {
    object: &'a str,
    kind: ScanKind,
    rig: Rig,
    preset: Preset,
    views: usize,
}

impl Case<'_> {
    /// Whether `r` is this case's result.
    fn is(&self, r: &BenchRun) -> bool {
        r.object == self.object
            && r.scan == self.kind
            && r.rig == self.rig
            && r.preset == self.preset
            && r.views == self.views
    }

    /// The longest time of another preset on the same scan and views (drt's budget).
    fn slowest_other(&self, results: &[BenchRun]) -> Option<f64> {
        results
            .iter()
            .filter(|r| {
                r.object == self.object
                    && r.scan == self.kind
                    && r.rig == self.rig
                    && r.views == self.views
                    && r.preset != Preset::Drt
            })
            .map(|r| r.seconds)
            .reduce(f64::max)
    }

    fn label(&self) -> String {
        format!(
            "{}_{}{}_{}_v{}",
            self.object,
            self.kind,
            self.rig.folder_suffix(),
            self.preset,
            self.views
        )
    }
}

/// Marks a `physical-true-masks` scan whose silhouettes have all been replaced.
const TRUE_MASKS_MARK: &str = "true_masks_done";

/// Simulates (and unless `exact`, decodes) the scan unless `dir` already holds it.
fn ensure_scan(
    object: &ObjectMesh,
    dir: &Path,
    kind: ScanKind,
    rig: &Rig,
    log: &dyn Fn(&str),
) -> Result<()> {
    let done = match kind {
        ScanKind::PhysicalTrueMasks => dir.join("decoded").join(TRUE_MASKS_MARK),
        _ => dir.join("decoded").join("summary.json"),
    };
    if done.is_file() {
        return Ok(());
    }
    let mesh = object.read()?;
    log(&format!(
        "simulating {} into {}",
        object.describe(),
        dir.display()
    ));
    let t0 = Instant::now();
    let opts = SimulateOptions {
        normals: object.normals(),
        ..kind.simulate_options(rig)
    };
    simulated_scan(&mesh, dir, &opts, |_| ())?;
    if kind == ScanKind::PhysicalTrueMasks {
        use_true_masks(dir, opts.blur_px)?;
    }
    log(&format!("  {:.1} s", t0.elapsed().as_secs_f64()));
    Ok(())
}

/// Replaces every decoded silhouette of the simulated scan in `dir` by the simulator's true one,
/// its outline's coverage by the true coverage blurred as the captures were (a Gaussian of σ
/// `blur_px` camera pixels: what a decoder that measured each pixel's share exactly would
/// give), views decode left out staying out; then marks the scan done.
fn use_true_masks(dir: &Path, blur_px: f64) -> Result<()> {
    let (decoded, truth) = (dir.join("decoded"), dir.join("truth"));
    for k in 0..SCAN_VIEWS {
        let name = format!("view_{k:03}_mask.png");
        if !decoded.join(&name).is_file() {
            continue;
        }
        let bytes = std::fs::read(truth.join(&name))
            .with_context(|| format!("cannot read {}", truth.join(&name).display()))?;
        let path = decoded.join(&name);
        crate::util::atomic::write_atomic(&path, |w| w.write_all(&bytes))
            .with_context(|| format!("cannot write {}", path.display()))?;
        write_true_coverage(dir, k, blur_px)?;
    }
    let mark = decoded.join(TRUE_MASKS_MARK);
    std::fs::write(
        &mark,
        "decoded silhouettes replaced by the simulator's true ones\n",
    )
    .with_context(|| format!("cannot write {}", mark.display()))
}

/// View `k`'s decoded outline coverage from the scan's true mask and true coverage (in `dir`),
/// the coverage blurred by a Gaussian of σ `blur_px` camera pixels.
fn write_true_coverage(dir: &Path, k: usize, blur_px: f64) -> Result<()> {
    use opencv::core::{MatTraitConst, MatTraitConstManual};
    let read = |name: &str| {
        crate::decode::compare::load(&dir.join("truth").join(format!("view_{k:03}_{name}.png")))
    };
    let (mask, coverage) = (read("mask")?, read("coverage")?);
    let mut sharp = opencv::core::Mat::default();
    coverage.convert_to(&mut sharp, opencv::core::CV_32F, 1.0 / 65535.0, 0.0)?;
    let share = crate::simulate::camera_blur(&sharp, blur_px)?;
    let background: Vec<f32> = share.data_typed::<f32>()?.iter().map(|c| 1.0 - c).collect();
    let width = mask.cols() as usize;
    let outline = crate::decode::mask::outline_coverage(mask.data_bytes()?, &background, width);
    let path = crate::scan::decoded::coverage_path(&dir.join("decoded"), k);
    crate::util::image::write_pixels(&path, width as u32, mask.rows() as u32, &outline)
}

/// `n` views spread evenly over the scan's.
fn spread_views(n: usize, total: usize) -> Vec<usize> {
    (0..n).map(|k| k * total / n).collect()
}

/// Runs and evaluates one case, with its log lines.
fn run_case(
    case: &Case,
    scan: &Scan,
    truth: &TriMesh,
    budget: Option<f64>,
    work: &Path,
    progress: &dyn Progress,
    log: &dyn Fn(&str),
) -> Result<BenchRun> {
    log(&format!(
        "{} ({}), {}, {} views{}",
        case.object,
        case.kind,
        case.preset,
        case.views,
        budget.map_or(String::new(), |b| format!(", budget {b:.0} s"))
    ));
    let dir = work.join("runs").join(case.label());
    let r = run_one(case, scan, truth, budget, &dir, progress)?;
    log(&format!(
        "  {:.1} s, accuracy {:.3} mm (signed {:+.3}), completeness {:.3} mm, F@0.5 {:.3}, F@1 {:.3}",
        r.seconds,
        r.accuracy_mm,
        r.signed_accuracy_mm.unwrap_or(f64::NAN),
        r.completeness_mm,
        r.fscore_05,
        r.fscore_1
    ));
    Ok(r)
}

/// A reconstruction from the visual hull through the pipeline's entry point, stopped at
/// `budget` seconds (after the stage that passes it) when one is given.
fn run_one(
    case: &Case,
    scan: &Scan,
    truth: &TriMesh,
    budget: Option<f64>,
    dir: &Path,
    progress: &dyn Progress,
) -> Result<BenchRun> {
    let settings = Settings::preset(case.preset);
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("cannot clear {}", dir.display()))?;
    }
    let views = spread_views(case.views, scan.config.views.angles_deg.len());
    let t0 = Instant::now();
    // The silhouettes alone: the run loads its targets itself.
    let (silhouettes, _) = crate::hull::silhouettes(scan, &views)?;
    let (hull, _) = visual_hull(
        &silhouettes,
        &HullOptions::default(),
        &crate::util::progress::Silent,
    )?;
    let seconds_hull = t0.elapsed().as_secs_f64();
    let stop = stop_after(budget.map(|b| b - seconds_hull));
    let job = Job {
        scan,
        views,
        settings: settings.clone(),
        start: Start::Mesh(&hull),
        out: dir,
        existing: Existing::Nothing,
    };
    // A run cut at the budget ends after a stage's commit; the stages it finished are read back.
    let checkpoint = reconstruct_scan(job, progress, &stop)?.checkpoint;
    let (curve, within, seconds) =
        stage_curve(&hull, truth, seconds_hull, &checkpoint.stages, budget, dir)?;
    // The result is the stage within the budget that fits the held-out views best.
    let s = best_stage(&checkpoint.stages, settings.warmup_stages, within)
        .context("the run finished no stage")?;
    let mesh = read_mesh(&stage_path(dir, s))?;
    let e: EvalReport = evaluate(&mesh, truth, &EvalOptions::default())?;
    let f = |t: f64| {
        e.fscores
            .iter()
            .find(|f| (f.threshold_mm - t).abs() < 1e-9)
            .map_or(f64::NAN, |f| f.fscore)
    };
    Ok(BenchRun {
        object: case.object.into(),
        scan: case.kind,
        rig: case.rig,
        preset: case.preset,
        views: case.views,
        seconds,
        seconds_hull,
        stages_done: within,
        result_stage: s + 1,
        stages: settings.total_stages(),
        accuracy_mm: e.accuracy_mm,
        signed_accuracy_mm: Some(e.signed_accuracy_mm),
        completeness_mm: e.completeness_mm,
        fscore_05: f(0.5),
        fscore_1: f(1.0),
        faces: mesh.faces.len(),
        curve,
        profile: CostProfile::total(
            checkpoint.stages[..within]
                .iter()
                .map(|st| (&st.profile, st.refraction_rays_used)),
        ),
    })
}

/// A flag that turns true `seconds` from now (never, for `None`).
fn stop_after(seconds: Option<f64>) -> Arc<AtomicBool> {
    let stop = Arc::new(AtomicBool::new(false));
    if let Some(left) = seconds {
        let stop = stop.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs_f64(left.max(0.0)));
            stop.store(true, Ordering::SeqCst);
        });
    }
    stop
}

/// (seconds, accuracy mm) after the hull and each stage of a run.
type Curve = Vec<(f64, f64)>;

/// The [`Curve`] up to the budget (at least one stage), the number of those stages and the
/// seconds they took with the hull.
fn stage_curve(
    hull: &TriMesh,
    truth: &TriMesh,
    seconds_hull: f64,
    stages: &[reconstruct::StageReport],
    budget: Option<f64>,
    dir: &Path,
) -> Result<(Curve, usize, f64)> {
    let quick = EvalOptions {
        samples: 200_000,
        ..EvalOptions::default()
    };
    let mut curve = vec![(seconds_hull, evaluate(hull, truth, &quick)?.accuracy_mm)];
    let (mut elapsed, mut seconds, mut within) = (seconds_hull, seconds_hull, 0);
    for (s, st) in stages.iter().enumerate() {
        elapsed += st.seconds;
        if budget.is_some_and(|b| elapsed > b) && within > 0 {
            break;
        }
        let mesh = read_mesh(&stage_path(dir, s))?;
        curve.push((elapsed, evaluate(&mesh, truth, &quick)?.accuracy_mm));
        (seconds, within) = (elapsed, s + 1);
    }
    Ok((curve, within, seconds))
}

/// Writes results.json, results.md and time_vs_accuracy.png.
fn write_results(work: &Path, results: &[BenchRun]) -> Result<()> {
    let mut md = String::from(
        "| object | scan | preset | views | time (s) | accuracy (mm) | signed (mm) | completeness (mm) | F@0.5 mm | F@1 mm | stages | result |\n|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|\n",
    );
    for r in results {
        md += &format!(
            "| {}{} | {} | {} | {} | {:.0} | {:.3} | {} | {:.3} | {:.3} | {:.3} | {}/{} | {} |\n",
            r.object,
            if r.rig.large_monitor {
                " (32\" monitor)"
            } else {
                ""
            },
            r.scan,
            r.preset,
            r.views,
            r.seconds,
            r.accuracy_mm,
            r.signed_accuracy_mm
                .map_or("–".to_string(), |v| format!("{v:+.3}")),
            r.completeness_mm,
            r.fscore_05,
            r.fscore_1,
            r.stages_done,
            r.stages,
            r.result_stage
        );
    }
    super::write_runs(
        &work.join("results.json"),
        results,
        &work.join("results.md"),
        &md,
    )?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::shapes::ellipsoid;
    use nalgebra::Vector3;

    #[test]
    fn an_object_the_default_monitor_does_not_cover_gets_the_large_one() {
        // The default monitor covers about 200 mm at the axis: a 60 mm ball fits, a 240 mm
        // tall spindle does not.
        let rig = Rig::default();
        let ball = rig
            .for_object(&ellipsoid(Vector3::new(30.0, 30.0, 30.0), 3))
            .unwrap();
        let spindle = rig
            .for_object(&ellipsoid(Vector3::new(30.0, 120.0, 30.0), 3))
            .unwrap();
        assert!(!ball.large_monitor);
        assert_eq!(ball.folder_suffix(), "");
        assert!(spindle.large_monitor);
        assert_eq!(spindle.folder_suffix(), "_monitor3840x2160");
        let o = ScanKind::Physical.simulate_options(&spindle);
        assert_eq!((o.screen_width, o.screen_height, o.pitch_mm), LARGE_MONITOR);
        assert!(monitor_covers(&ellipsoid(Vector3::new(30.0, 120.0, 30.0), 3), &o).unwrap());
    }
}
