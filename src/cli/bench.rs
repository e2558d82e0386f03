//! `glasscan bench …`.

use std::path::{Path, PathBuf};

use glasscan::util::paths::{ensure_extension, ensure_output_spares_inputs};

use anyhow::{Context, Result};
use clap::{Args, Subcommand};

use glasscan::bench::reconstruct::ScanKind;
use glasscan::bench::trace::{self, TraceBenchOptions, TraceBenchReport};
use glasscan::loss::refraction::{ResidualForm, MAX_FOOTPRINT};
use glasscan::loss::Robust;
use glasscan::mesh::io::read_mesh;
use glasscan::mesh::shapes;
use glasscan::reconstruct::config::Preset;
use glasscan::trace::path::NormalModel;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Embree throughput (coherent and incoherent rays, 1 and all threads) and BVH update cost.
    Trace(TraceArgs),
    /// glasscan's remesher against pymeshlab's on the shared meshes and DRT's schedule.
    Remesh(RemeshBenchArgs),
    /// Loss + gradient of the refraction term over a decoded scan against bare Embree queries.
    Gradient(GradientArgs),
    /// The presets' speed/accuracy trade on simulated scans of the shared meshes.
    Reconstruct(ReconstructBenchArgs),
    /// Reconstructions with the rig calibrated from simulated images beside the same with the
    /// simulator's true calibration (noisy 72-view scans, a distorting lens).
    Calibrated(CalibratedBenchArgs),
}

#[derive(Args, Debug)]
pub struct CalibratedBenchArgs {
    /// Folder with the {object}_scan.ply meshes.
    #[arg(long)]
    pub meshes: PathBuf,
    /// Scans, runs, calibrated.json and calibrated.md go here; a rerun skips the objects
    /// calibrated.json already holds.
    #[arg(long, default_value = "target/bench-calibrated")]
    pub work: PathBuf,
    /// Objects, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "pig,horse,dog")]
    pub objects: Vec<String>,
    /// The preset of both reconstructions.
    #[arg(long, value_enum, default_value_t = Preset::Balanced)]
    pub preset: Preset,
    /// Camera image size, WIDTHxHEIGHT pixels.
    #[arg(long, default_value = "1280x960", value_parser = super::common::parse_size)]
    pub size: (u32, u32),
    /// Share of the image height the object fills.
    #[arg(long, default_value_t = 0.6, value_parser = super::common::positive_share)]
    pub fill: f64,
    /// Square side of the printed camera board, mm (default: sized with the rig).
    #[arg(long = "square-mm", value_parser = super::common::positive)]
    pub square_mm: Option<f64>,
    /// Square side of the board standing on the turntable, mm (default: --square-mm).
    #[arg(long = "turntable-square-mm", value_parser = super::common::positive)]
    pub turntable_square_mm: Option<f64>,
}

#[derive(Args, Debug)]
pub struct ReconstructBenchArgs {
    /// Folder with the {object}_scan.ply meshes (not needed for the built-in objects).
    #[arg(long)]
    pub meshes: Option<PathBuf>,
    /// Scans, runs, results.json, results.md and time_vs_accuracy.png go here; a rerun skips
    /// the runs results.json already holds.
    #[arg(long, default_value = "target/bench-reconstruct")]
    pub work: PathBuf,
    /// Objects, comma-separated: {object}_scan.ply in --meshes, `block` (a glass block with
    /// flat, parallel faces and rounded edges on a plinth) or `prism` (a cut prism, sharp edges),
    /// both built in.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "pig,horse,dog,block,prism"
    )]
    pub objects: Vec<String>,
    /// Presets, comma-separated (drt gets the time of the slowest other preset).
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "fast,balanced,accurate,drt"
    )]
    pub presets: Vec<Preset>,
    /// View counts, comma-separated, taken evenly from the scan's 72.
    #[arg(long, value_delimiter = ',', default_value = "72,36,18,9")]
    pub views: Vec<usize>,
    /// Scans: exact (decoded-only correspondences), noisy (noise 2, blur 0.7, 4 samples per
    /// pixel, decoded) and/or physical (as noisy, with Fresnel and internal reflections).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "exact,noisy")]
    pub scans: Vec<ScanKind>,
    /// Image size of the simulated camera, WxH.
    #[arg(long, default_value = "1280x960", value_parser = super::common::parse_size)]
    pub size: (u32, u32),
    /// Share of the image height the object fills.
    #[arg(long, default_value_t = 0.6, value_parser = super::common::positive_share)]
    pub fill: f64,
}

#[derive(Args, Debug)]
pub struct GradientArgs {
    /// A decoded scan folder (e.g. from `glasscan simulate --decoded-only`).
    #[arg(long)]
    pub scan: PathBuf,
    /// The mesh to evaluate (world frame); default: the scan's ground_truth.ply.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Views: all (default), or indices and ranges such as 0-35.
    #[arg(long)]
    pub views: Option<String>,
    /// Normal model of the refraction term.
    #[arg(long, value_enum, default_value = "face")]
    pub normals: NormalModel,
    /// Residual form: screen (mm on the monitor) or direction (DRT's code).
    #[arg(long, value_enum, default_value = "screen")]
    pub form: ResidualForm,
    /// Paths with up to this many refractions (even) are used.
    #[arg(long = "max-refractions", default_value_t = 2)]
    pub max_refractions: u32,
    /// Robust loss: l2, huber:δ or cauchy:δ (δ in the residual's unit).
    #[arg(long, default_value = "l2", value_parser = super::common::parse_robust)]
    pub robust: Robust,
    /// Rays per pixel side (a pixel modelled by the mean of an n×n grid of rays), 1..=4.
    #[arg(long, default_value_t = 1,
          value_parser = clap::value_parser!(u32).range(1..=MAX_FOOTPRINT as i64))]
    pub footprint: u32,
    /// Timed evaluations (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Also write the figures as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct RemeshBenchArgs {
    /// Folder with the *_scan.ply and *_vh.ply meshes.
    #[arg(long)]
    pub meshes: PathBuf,
    /// Target edge lengths, mm, comma-separated.
    #[arg(long = "edge-mm", value_delimiter = ',', default_value = "1,2,5")]
    pub edges_mm: Vec<f64>,
    /// A Python interpreter with pymeshlab, to run the same cases through it (`make bench-remesh`
    /// sets one up); without it only glasscan runs.
    #[arg(long)]
    pub python: Option<PathBuf>,
    /// Folder for both sides' output meshes.
    #[arg(long, default_value = "target/bench-remesh")]
    pub work: PathBuf,
    /// Also write every figure as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct TraceArgs {
    /// Mesh to trace (.ply or .obj); default: a built-in sphere of 81,920 faces.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Width of the camera view, pixels.
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    /// Height of the camera view, pixels.
    #[arg(long, default_value_t = 960)]
    pub height: u32,
    /// Minimum duration of each throughput measurement, seconds.
    #[arg(long, default_value_t = 1.0)]
    pub seconds: f64,
    /// Seed of the random rays and vertex moves.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write the figures as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn run(cmd: &BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Trace(a) => run_trace(a),
        BenchCommand::Remesh(a) => run_remesh(a),
        BenchCommand::Gradient(a) => run_gradient(a),
        BenchCommand::Reconstruct(a) => run_reconstruct(a),
        BenchCommand::Calibrated(a) => run_calibrated(a),
    }
}

/// Refuses a benchmark's output folder `work` or JSON file `json` that is, holds or lies in one
/// of its `inputs`, and a JSON file without its extension.
fn guard_outputs(work: Option<&Path>, json: Option<&Path>, inputs: &[&Path]) -> Result<()> {
    let inputs: Vec<&Path> = inputs
        .iter()
        .copied()
        .filter(|p| !p.as_os_str().is_empty())
        .collect();
    if let Some(w) = work {
        ensure_output_spares_inputs(w, "--work", &inputs)?;
    }
    if let Some(j) = json {
        ensure_extension(j, "--json", &["json"])?;
        ensure_output_spares_inputs(j, "--json", &inputs)?;
    }
    Ok(())
}

fn run_calibrated(a: &CalibratedBenchArgs) -> Result<()> {
    use glasscan::bench::calibrated::{run_calibrated_bench, CalibratedBenchOptions};
    guard_outputs(Some(&a.work), None, &[&a.meshes])?;
    let o = CalibratedBenchOptions {
        meshes: a.meshes.clone(),
        work: a.work.clone(),
        objects: a.objects.clone(),
        preset: a.preset,
        rig: glasscan::bench::reconstruct::Rig {
            width: a.size.0,
            height: a.size.1,
            fill: a.fill,
            large_monitor: false,
        },
        boards: glasscan::simulate::calibration::CalibrationBoards {
            camera_square_mm: a.square_mm,
            turntable_square_mm: a.turntable_square_mm,
            ..Default::default()
        },
    };
    let bars = super::common::StageBars::new();
    let log = |s: &str| bars.bar.suspend(|| eprintln!("{s}"));
    let results = run_calibrated_bench(&o, &bars, &log)?;
    bars.bar.finish_and_clear();
    let table = a.work.join("calibrated.md");
    let text = std::fs::read_to_string(&table)
        .with_context(|| format!("cannot read the results table {}", table.display()))?;
    outln!("{text}");
    outln!("{} objects", results.len());
    Ok(())
}

fn run_reconstruct(a: &ReconstructBenchArgs) -> Result<()> {
    use glasscan::bench::reconstruct::{run_bench, BenchOptions, Rig};
    let meshes = a.meshes.clone().unwrap_or_default();
    guard_outputs(Some(&a.work), None, &[&meshes])?;
    let o = BenchOptions {
        meshes,
        work: a.work.clone(),
        objects: a.objects.clone(),
        presets: a.presets.clone(),
        views: a.views.clone(),
        scans: a.scans.clone(),
        rig: Rig {
            width: a.size.0,
            height: a.size.1,
            fill: a.fill,
            large_monitor: false,
        },
    };
    let bars = super::common::StageBars::new();
    let log = |s: &str| bars.bar.suspend(|| eprintln!("{s}"));
    let results = run_bench(&o, &bars, &log)?;
    bars.bar.finish_and_clear();
    let table = a.work.join("results.md");
    let text = std::fs::read_to_string(&table)
        .with_context(|| format!("cannot read the results table {}", table.display()))?;
    outln!("{text}");
    outln!(
        "{} runs; plot: {}",
        results.len(),
        a.work.join("time_vs_accuracy.png").display()
    );
    Ok(())
}

fn run_gradient(a: &GradientArgs) -> Result<()> {
    use glasscan::loss::refraction::RefractionSettings;
    let mut inputs = vec![a.scan.as_path()];
    inputs.extend(a.mesh.as_deref());
    guard_outputs(None, a.json.as_deref(), &inputs)?;
    if !(2..=glasscan::trace::path::MAX_TRAIL as u32).contains(&a.max_refractions) {
        anyhow::bail!(
            "--max-refractions {}: it must lie in 2..={}",
            a.max_refractions,
            glasscan::trace::path::MAX_TRAIL
        );
    }
    let scan = super::common::open_scan(&a.scan)?;
    let views = super::common::parse_views(a.views.as_deref(), scan.config.views.angles_deg.len())?;
    let mesh_path = a
        .mesh
        .clone()
        .unwrap_or_else(|| a.scan.join("ground_truth.ply"));
    let mesh = read_mesh(&mesh_path)?;
    glasscan::mesh::validate::ensure_valid(&mesh)
        .map_err(|e| anyhow::anyhow!("{}: {e}", mesh_path.display()))?;
    let t0 = std::time::Instant::now();
    let (targets, skipped) =
        glasscan::loss::targets::scan_targets(&scan, &views, Default::default())?;
    let load_s = t0.elapsed().as_secs_f64();
    let s = RefractionSettings {
        ior: scan.config.ior.nominal(),
        ior_air: glasscan::trace::refract::IOR_AIR,
        max_refractions: a.max_refractions,
        normals: a.normals,
        form: a.form,
        robust: a.robust,
        min_cos: 0.0,
        grazing_cell_footprints: 0.0,
        footprint: a.footprint,
        bit_weight: 0.0,
        index_gradient: false,
    };
    eprintln!(
        "bench gradient: {} ({} faces), {} views of {} ({} left out by decode), targets loaded in {load_s:.1} s",
        mesh_path.display(),
        mesh.faces.len(),
        targets.len(),
        a.scan.display(),
        skipped.len()
    );
    let bar = super::common::bar("bench gradient", a.repeats.max(1));
    let r = glasscan::bench::gradient::run(&mesh, &targets, &s, a.repeats, |i| {
        bar.set_position(i as u64)
    })?;
    bar.finish_and_clear();
    print_gradient(a, &s, &r)?;
    if let Some(path) = &a.json {
        super::write_json(path, &serde_json::to_value(&r)?)?;
    }
    Ok(())
}

/// `bench gradient`'s figures: what was traced, what was dropped, the rates and their ratios.
fn print_gradient(
    a: &GradientArgs,
    s: &glasscan::loss::refraction::RefractionSettings,
    r: &glasscan::bench::gradient::GradientBenchReport,
) -> Result<()> {
    outln!(
        "{} threads · {} faces · {} views · {:?} normals · {:?} residual · paths with ≤ {} refractions",
        r.threads, r.faces, r.views, s.normals, s.form, s.max_refractions
    );
    outln!(
        "camera rays {}  Embree queries {}  used {} ({:.1} %)  dropped: no hit {}, TIR {}, refraction count {}, missed monitor {}, grazing {}, near critical {}, non-finite {}",
        r.camera_rays,
        r.queries,
        r.used,
        100.0 * r.used as f64 / r.camera_rays.max(1) as f64,
        r.drops.no_hit,
        r.drops.total_internal_reflection,
        r.drops.refraction_count,
        r.drops.missed_monitor,
        r.drops.grazing,
        r.drops.near_critical,
        r.drops.non_finite
    );
    outln!(
        "mean loss over the rays used: {:.4e} ({})",
        r.mean_loss,
        match a.form {
            ResidualForm::Screen => "mm² on the monitor",
            ResidualForm::Direction => "unitless",
        }
    );
    outln!(
        "loss + gradient: {:.3} s per gradient over all views, {:.1} ms per view; {:.2} M camera rays/s, {:.2} M queries/s",
        r.seconds_per_gradient,
        1e3 * r.seconds_per_view,
        r.camera_rays_per_s / 1e6,
        r.queries_per_s / 1e6
    );
    outln!(
        "Embree alone, same queries: {:.3} s, {:.2} M queries/s",
        r.seconds_embree_only,
        r.embree_queries_per_s / 1e6
    );
    outln!(
        "forward pass alone (the same trace, nothing differentiated): {:.3} s, ratio to Embree alone {:.2}; the backward pass and the sums: {:.3} s",
        r.seconds_trace_only,
        r.ratio_trace_only,
        r.seconds_per_gradient - r.seconds_trace_only
    );
    outln!("ratio loss+gradient / Embree alone: {:.2}", r.ratio);
    Ok(())
}

fn run_trace(a: &TraceArgs) -> Result<()> {
    guard_outputs(
        None,
        a.json.as_deref(),
        &a.mesh.as_deref().into_iter().collect::<Vec<_>>(),
    )?;
    let (name, mesh) = match &a.mesh {
        Some(p) => (p.display().to_string(), read_mesh(p)?),
        None => (
            "built-in sphere (r = 50 mm)".to_string(),
            shapes::icosphere(50.0, 6),
        ),
    };
    let opts = TraceBenchOptions {
        width: a.width,
        height: a.height,
        min_seconds: a.seconds,
        seed: a.seed,
        ..Default::default()
    };
    eprintln!("bench trace: {name}, {} faces ...", mesh.faces.len());
    let report = trace::run(&mesh, &opts)?;
    out!("{}", table(&report, a.width, a.height));
    if let Some(path) = &a.json {
        super::write_json(path, &serde_json::to_value(&report)?)?;
    }
    Ok(())
}

/// The figures as a table, with the ratios that matter.
pub fn table(r: &TraceBenchReport, width: u32, height: u32) -> String {
    let mut s = format!(
        "Embree {} · {} faces · {width}×{height} view\n",
        glasscan::trace::embree_version(),
        r.faces
    );
    s += &format!(
        "{:<32} {:>8} {:>10} {:>8}\n",
        "workload", "threads", "Mrays/s", "hits"
    );
    for t in &r.throughput {
        s += &format!(
            "{:<32} {:>8} {:>10.2} {:>7.1}%\n",
            t.workload,
            t.threads,
            t.mrays_per_s,
            100.0 * t.hit_share
        );
    }
    let find = |w: &str, th: usize| {
        r.throughput
            .iter()
            .find(|t| t.workload.starts_with(w) && t.threads == th)
            .map(|t| t.mrays_per_s)
    };
    if let (Some(p), Some(o)) = (
        find("camera rays, packets", r.threads),
        find("camera rays, one", r.threads),
    ) {
        s += &format!(
            "ratio packets / one by one ({} threads): {:.2}\n",
            r.threads,
            p / o
        );
    }
    if let (Some(m), Some(one)) = (
        find("camera rays, packets", r.threads),
        find("camera rays, packets", 1),
    ) {
        s += &format!(
            "ratio {} threads / 1 thread (packets): {:.2}\n",
            r.threads,
            m / one
        );
    }
    s += &format!(
        "{:<28} {:>10} {:>12} {:>16}\n",
        "BVH mode", "build ms", "update ms", "Mrays/s after"
    );
    for u in &r.updates {
        s += &format!(
            "{:<28} {:>10.2} {:>12.2} {:>16.2}\n",
            u.mode, u.build_ms, u.update_ms, u.mrays_per_s_after
        );
    }
    if let [rebuild, refit] = &r.updates[..] {
        s += &format!(
            "ratio rebuild / refit update time: {:.1}; refit / rebuild ray speed: {:.2}\n",
            rebuild.update_ms / refit.update_ms,
            refit.mrays_per_s_after / rebuild.mrays_per_s_after
        );
    }
    s
}

fn run_remesh(a: &RemeshBenchArgs) -> Result<()> {
    use super::remesh::{header, row};
    use glasscan::bench::remesh;
    guard_outputs(Some(&a.work), a.json.as_deref(), &[&a.meshes])?;
    let cases = remesh::cases(&a.meshes, &a.edges_mm)?;
    match &a.python {
        Some(py) => eprintln!(
            "bench remesh: {} cases, glasscan and pymeshlab ({})",
            cases.len(),
            py.display()
        ),
        None => eprintln!(
            "bench remesh: {} cases, glasscan only (pymeshlab not requested: pass --python)",
            cases.len()
        ),
    }
    out!("{}", header("case / tool"));
    let mut ratios = Vec::new();
    let results = remesh::run(&cases, a.python.as_deref(), &a.work, |r| {
        out!(
            "{}",
            row(
                &format!("{} glasscan", r.case.name),
                &r.glasscan.quality,
                Some(&r.glasscan)
            )
        );
        if let Some(p) = &r.pymeshlab {
            out!(
                "{}",
                row(&format!("{} pymeshlab", r.case.name), &p.quality, Some(p))
            );
            let ratio = p.seconds / r.glasscan.seconds;
            outln!("{:<28} speed-up ×{ratio:.1}", "");
            ratios.push(ratio);
        }
        Ok(())
    })?;
    if let (Some(min), Some(max)) = (
        ratios.iter().copied().reduce(f64::min),
        ratios.iter().copied().reduce(f64::max),
    ) {
        let geo = (ratios.iter().map(|r| r.ln()).sum::<f64>() / ratios.len() as f64).exp();
        outln!("speed-up over pymeshlab: min ×{min:.1}, geometric mean ×{geo:.1}, max ×{max:.1}");
    }
    if let Some(last) = results.iter().find(|r| r.case.schedule_mm.len() > 1) {
        outln!(
            "DRT schedule, last stage alone: glasscan {:.2} s{}",
            last.glasscan_last_stage_s,
            last.pymeshlab_last_stage_s
                .map_or(String::new(), |s| format!(", pymeshlab {s:.2} s"))
        );
    }
    if let Some(path) = &a.json {
        super::write_json(path, &serde_json::to_value(&results)?)?;
    }
    Ok(())
}
