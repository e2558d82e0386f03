//! `glasscan eval RESULT --reference GT`.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

use glasscan::eval::confidence::error_by_confidence;
use glasscan::eval::error_map::{
    confidence_legend, write_error_map, write_support_map, ErrorScale,
};
use glasscan::eval::{evaluate_on, EvalOptions, EvalReport};
use glasscan::mesh::io::{read_mesh, read_mesh_with_quality};
use glasscan::mesh::TriMesh;
use glasscan::trace::{BuildMode, Device, Scene};
use glasscan::util::paths::{ensure_extension, ensure_output_spares_inputs};

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// The reconstructed mesh (.ply or .obj).
    pub result: PathBuf,
    /// The ground-truth mesh (.ply or .obj).
    #[arg(long)]
    pub reference: PathBuf,
    /// F-score thresholds, mm, comma-separated.
    #[arg(
        long = "threshold-mm",
        value_delimiter = ',',
        default_value = "0.5,1.0",
        value_parser = super::common::positive
    )]
    pub thresholds_mm: Vec<f64>,
    /// Surface samples drawn on each mesh.
    #[arg(long, default_value_t = 1_000_000, value_parser = clap::value_parser!(u64).range(1..))]
    pub samples: u64,
    /// Seed of the surface sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write the metrics as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also write an error map: the result from six sides coloured by distance to the reference.
    #[arg(long = "error-map")]
    pub error_map: Option<PathBuf>,
    /// The distance shown red in the error map, mm (default: the largest F-score threshold).
    #[arg(long = "error-max-mm", value_parser = super::common::positive)]
    pub error_max_mm: Option<f64>,
    /// Colour the error map by the signed distance: blue where the result lies inside the
    /// reference, red where it lies outside.
    #[arg(long = "error-map-signed", requires = "error_map")]
    pub error_map_signed: bool,
    /// Also write the result's confidence (its vertex quality, as reconstruct writes it) from the
    /// error map's six sides, with its colour bar conventions (red: no support).
    #[arg(long = "confidence-map")]
    pub confidence_map: Option<PathBuf>,
}

pub fn run(args: &EvalArgs) -> Result<()> {
    let error_max_mm = check_outputs(args)?;
    let (result, quality) = read_mesh_with_quality(&args.result)?;
    if args.confidence_map.is_some() && quality.is_none() {
        bail!(
            "--confidence-map: {} has no vertex quality (reconstruct's result.ply carries its confidence there)",
            args.result.display()
        );
    }
    let reference = read_mesh(&args.reference)?;
    let options = EvalOptions {
        samples: usize::try_from(args.samples).unwrap_or(usize::MAX),
        thresholds_mm: args.thresholds_mm.clone(),
        seed: args.seed,
    };
    // One ray-tracing structure of each mesh serves the metrics and the maps.
    let device = Device::new()?;
    let res_scene = Scene::new(&device, &result, BuildMode::Static)?;
    let ref_scene = Scene::new(&device, &reference, BuildMode::Static)?;
    let report = evaluate_on((&result, &res_scene), (&reference, &ref_scene), &options)?;
    outln!(
        "result           {} ({} faces)",
        args.result.display(),
        result.faces.len()
    );
    outln!(
        "reference        {} ({} faces)",
        args.reference.display(),
        reference.faces.len()
    );
    out!("{}", table(&report, args.seed));
    let mut json = report.to_json();
    if let Some(quality) = &quality {
        json["error_by_confidence"] =
            by_confidence(args, (&result, &res_scene), &ref_scene, quality)?;
    }
    if let Some(path) = &args.json {
        super::write_json(path, &json)?;
    }
    if let Some(path) = &args.error_map {
        let scale = if args.error_map_signed {
            ErrorScale::Signed(&reference)
        } else {
            ErrorScale::Distance
        };
        write_error_map(path, &result, &res_scene, &ref_scene, scale, error_max_mm)?;
        outln!("error map        {}", path.display());
    }
    Ok(())
}

/// Checks the output paths (their extensions; none overwrites an input) and the error map's
/// scale before any work; returns that scale (mm).
fn check_outputs(args: &EvalArgs) -> Result<f64> {
    let inputs = [args.result.as_path(), args.reference.as_path()];
    if let Some(p) = &args.json {
        ensure_extension(p, "--json", &["json"])?;
        ensure_output_spares_inputs(p, "--json", &inputs)?;
    }
    for (p, flag) in [
        (&args.error_map, "--error-map"),
        (&args.confidence_map, "--confidence-map"),
    ] {
        if let Some(p) = p {
            ensure_extension(p, flag, &["png"])?;
            ensure_output_spares_inputs(p, flag, &inputs)?;
        }
    }
    let max_mm = args
        .error_max_mm
        .unwrap_or_else(|| args.thresholds_mm.iter().copied().fold(0.0, f64::max));
    if args.error_map.is_some() && !(max_mm.is_finite() && max_mm > 0.0) {
        bail!("--error-max-mm {max_mm}: it must be a positive number of mm");
    }
    Ok(max_mm)
}

/// The result's error by quarters of its area ordered by its confidence (`quality`, per
/// vertex), printed and as JSON, and the confidence map if asked for.
fn by_confidence(
    args: &EvalArgs,
    (result, res_scene): (&TriMesh, &Scene),
    ref_scene: &Scene,
    quality: &[f64],
) -> Result<serde_json::Value> {
    let by = error_by_confidence(result, quality, ref_scene)?;
    let [q1, q2, q3, q4] = by.quartiles_mm;
    let ratio = by.least_over_most.map_or(
        "no ratio: no error in the most confident".to_string(),
        |r| format!("{r:.2}×"),
    );
    outln!(
        "by confidence    {q1:.4} / {q2:.4} / {q3:.4} / {q4:.4} mm  (mean vertex error in each quarter of the area, least to most confident by the result's quality; {ratio})"
    );
    if let Some(path) = &args.confidence_map {
        write_support_map(
            path,
            (result, res_scene),
            quality,
            confidence_legend(quality),
        )?;
        outln!("confidence map   {}", path.display());
    }
    Ok(serde_json::to_value(by)?)
}

/// The metrics as the table `eval` (and the demo) print.
pub fn table(r: &EvalReport, seed: u64) -> String {
    let mut s = format!("samples          {} per mesh (seed {seed})\n", r.samples);
    s += &format!(
        "accuracy         {:.6} mm  (mean distance result → reference)\n",
        r.accuracy_mm
    );
    s += &format!(
        "signed accuracy  {:+.6} mm  (> 0: the result lies outside the reference; {:.1} % of its area does)\n",
        r.signed_accuracy_mm,
        100.0 * r.outside_share
    );
    s += &format!(
        "completeness     {:.6} mm  (mean distance reference → result)\n",
        r.completeness_mm
    );
    for f in &r.fscores {
        s += &format!(
            "F-score@{:<8} {:.4}     (precision {:.4}, recall {:.4})\n",
            format!("{}mm", f.threshold_mm),
            f.fscore,
            f.precision,
            f.recall
        );
    }
    s += &format!(
        "DRT mean         {:.6} mm  (result vertices → reference surface)\n",
        r.drt_mean_mm
    );
    s += &format!("Hausdorff        {:.6} mm\n", r.hausdorff_mm);
    s
}
