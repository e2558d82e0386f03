//! `glasscan decode SCAN`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use super::common::{
    auto_or_open_share, bar, parse_views, positive_f32, share, share_f32, AutoShare,
};
use glasscan::decode::blur::Unmeasured;
use glasscan::decode::compare::{compare_view, Comparison};
use glasscan::decode::mask::MaskOptions;
use glasscan::decode::{decode_scan, DecodeOptions};
use glasscan::scan::decoded::{MeasuredBlur, ViewSummary};

#[derive(Args, Debug)]
pub struct DecodeArgs {
    /// The scan folder.
    pub scan: PathBuf,
    /// Views to decode: all (default), or a list of indices and ranges such as 0-9,12.
    #[arg(long)]
    pub views: Option<String>,
    /// Compare with `simulate`'s ground truth (truth/ in the scan folder) and print the figures.
    #[arg(long = "compare-ground-truth")]
    pub compare: bool,
    /// Smallest pattern–inverse difference of a reliable bit, grey levels (OpenCV: 5).
    #[arg(long = "white-threshold", default_value_t = 5)]
    pub white_threshold: u8,
    /// Smallest white–black difference of a lit pixel, grey levels (OpenCV: 40).
    #[arg(long = "black-threshold", default_value_t = 40)]
    pub black_threshold: u8,
    /// Smallest bit contrast as a share of the pixel's white − black range (0: OpenCV's test).
    #[arg(long = "min-contrast", default_value_t = 0.3, value_parser = share_f32)]
    pub min_contrast: f32,
    /// Ignore the scan's phase-shift images (Gray code alone).
    #[arg(long = "no-phase")]
    pub no_phase: bool,
    /// Smallest phase modulation (B/A) for a phase-refined point.
    #[arg(long = "min-modulation", default_value_t = 0.3, value_parser = share)]
    pub min_modulation: f64,
    /// Mask rule 1: decoded shift from the background beyond the cells, monitor pixels.
    #[arg(long = "shift-px", default_value_t = 2.0, value_parser = positive_f32)]
    pub shift_px: f32,
    /// Mask rule 3: relative drop of the white image against the background's (default: half
    /// the normal-incidence Fresnel loss of the scan's IOR, or 5 × the view's white-ratio noise):
    /// auto, or a share in (0, 1)
    #[arg(long = "white-drop", default_value = "auto", value_parser = auto_or_open_share)]
    pub white_drop: AutoShare,
    /// Object regions smaller than this share of the image's area are dropped (1.6e-4: 49 pixels
    /// of a 640 × 480 image).
    #[arg(long = "min-component", default_value_t = MaskOptions::default().min_component, value_parser = share)]
    pub min_component: f64,
    /// Bits per sample of 16-bit captures, 9 to 16 (default: each view's, the smallest of 10, 12,
    /// 14 and 16 that holds its white image).
    #[arg(long = "bit-depth", value_parser = clap::value_parser!(u32).range(9..=16))]
    pub bit_depth: Option<u32>,
    /// Holes smaller than this share of the image's area are filled (1.6e-4: 49 pixels of a
    /// 640 × 480 image).
    #[arg(long = "max-hole", default_value_t = MaskOptions::default().max_hole, value_parser = share)]
    pub max_hole: f64,
    /// The object has flat faces through which the monitor shows barely shifted (a block, a
    /// slab): judge the outline's pixels by how much of the background's code they show beyond
    /// what the glass beside them shows. Not for sharp-edged cut glass (docs/decisions.md).
    #[arg(long = "flat-faces")]
    pub flat_faces: bool,
    /// Object pixels whose white image shows less than this share of the light two air–glass
    /// interfaces pass at normal incidence (against the background's white) get no monitor
    /// point: their light split on its way (total internal reflection, ghosts), and the code
    /// decodes to a point no refracted path reaches. 0: every decoded pixel keeps its point.
    /// Needs a captured background
    #[arg(long = "min-light", default_value_t = DecodeOptions::default().min_light, value_parser = share_f32)]
    pub min_light: f32,
}

pub fn run(a: &DecodeArgs) -> Result<()> {
    let scan = super::common::open_scan(&a.scan)?;
    let views = parse_views(a.views.as_deref(), scan.config.views.angles_deg.len())?;
    let o = options(a);
    let bar = bar("decode", views.len());
    let t0 = std::time::Instant::now();
    let outcome = decode_scan(&scan, &views, &o, |s| {
        if let Some(w) = &s.warning {
            bar.suspend(|| eprintln!("warning: view {}: {w}", s.view));
        }
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    let flat_faces_hint = outcome.flat_faces_suggested(a.flat_faces);
    let min_light_hint = outcome.min_light_suggested(a.min_light, scan.config.ior.is_auto());
    let summaries = outcome.views;
    let object: usize = summaries.iter().map(|s| s.object_pixels).sum();
    let of_object = |share: fn(&ViewSummary) -> f64| -> f64 {
        let n: f64 = summaries
            .iter()
            .map(|s| share(s) * s.object_pixels as f64)
            .sum();
        100.0 * n / object.max(1) as f64
    };
    let dim = summaries.iter().any(|s| s.dim_share.is_some()).then(|| {
        let share = of_object(|s| s.dim_share.unwrap_or(0.0));
        format!(" ({share:.1} % left without one for too little light)")
    });
    outln!(
        "decoded {} views in {:.1} s into {}: {object} object pixels, {:.1} % with a monitor point{}; {} view(s) with warnings",
        summaries.len(),
        t0.elapsed().as_secs_f64(),
        scan.dir.join("decoded").display(),
        of_object(|s| s.decoded_share),
        dim.unwrap_or_default(),
        summaries.iter().filter(|s| s.warning.is_some()).count()
    );
    if let Some(share) = flat_faces_hint {
        outln!(
            "hint: through {:.0} % of the object's inside the monitor shows barely shifted (flat, nearly parallel faces): if the object has no sharp edges (a block, a slab), decode again with --flat-faces, whose outlines lie closer to the truth there (docs/decisions.md#outlines-beside-flat-glass)",
            100.0 * share
        );
    }
    if min_light_hint {
        outln!(
            "hint: the index is to be estimated (ior = \"auto\") and the glass is curved: points decoded from light that split on its way bias the estimate low; decode again with --min-light 0.7 (glasscan's simulated pig, dog and horse at 1.50: estimates 0.003–0.018 nearer, `accurate` 14–32 % more accurate; docs/decisions.md#points-from-light-that-split)"
        );
    }
    print_blur(&scan, outcome.blur)?;
    if a.compare {
        print_comparison(&scan, &summaries)?;
    }
    Ok(())
}

/// The decoder's options from the command line's.
fn options(a: &DecodeArgs) -> DecodeOptions {
    DecodeOptions {
        white_threshold: a.white_threshold,
        black_threshold: a.black_threshold,
        min_contrast: a.min_contrast,
        use_phase: !a.no_phase,
        min_modulation: a.min_modulation,
        mask: MaskOptions {
            shift_px: a.shift_px,
            white_drop: a.white_drop.0,
            min_component: a.min_component,
            max_hole: a.max_hole,
            flat_faces: a.flat_faces,
        },
        bit_depth: a.bit_depth,
        min_light: a.min_light,
    }
}

/// `--compare-ground-truth`: each decoded view (those without a warning) against the
/// simulator's truth, a row each, then the whole scan.
fn print_comparison(scan: &glasscan::scan::Scan, summaries: &[ViewSummary]) -> Result<()> {
    let fixed =
        glasscan::util::fixed::FixedPoint::for_screen(scan.screen.width_px, scan.screen.height_px);
    let rows: Vec<Comparison> = summaries
        .iter()
        .filter(|s| s.warning.is_none())
        .map(|s| compare_view(&scan.dir, s.view, &fixed))
        .collect::<Result<_>>()?;
    outln!(
        "{:>5} {:>8} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>12} {:>12} {:>9} {:>11}",
        "view",
        "mask IoU",
        "extra",
        "missing",
        "edge px",
        "area px",
        "valid",
        "decoded %",
        "med err foot",
        "med err ctr",
        "≤1 px %",
        "≤ uncert. %"
    );
    for c in &rows {
        outln!(
            "{:>5} {:>8.4} {:>9} {:>9} {:>9.3} {:>9} {:>9} {:>9.1} {:>12.2} {:>12.2} {:>9.1} {:>11.1}",
            c.view,
            c.mask_iou,
            c.mask_extra,
            c.mask_missing,
            c.edge_offset_px(),
            c.coverage_offset_px()
                .map_or("—".to_string(), |v| format!("{v:.3}")),
            c.valid,
            100.0 * c.decoded_share,
            c.median_error_footprint_px,
            c.median_error_centre_px,
            100.0 * c.within_1px_footprint,
            100.0 * c.within_uncertainty_footprint
        );
    }
    let n: usize = rows.iter().map(|c| c.compared).sum();
    let valid: usize = rows.iter().map(|c| c.valid).sum();
    let direct_offset = Comparison::overall_direct_offset_px(&rows);
    let direct: usize = rows.iter().map(|c| c.direct_compared).sum();
    let w = |f: fn(&Comparison) -> f64| {
        rows.iter().map(|c| f(c) * c.compared as f64).sum::<f64>() / n.max(1) as f64
    };
    let by_area = match Comparison::overall_coverage_offset_px(&rows) {
        Some(v) => format!("{v:+.3} px"),
        None => "not measured (the truth has no coverage: simulated before 0.15.0)".to_string(),
    };
    outln!(
        "overall: mean mask IoU {:.4}; decoded outline {:+.3} px from the true one (> 0: outside), by area against the true coverage {by_area}; the monitor seen directly decoded at ({:+.3}, {:+.3}) camera px from the truth (x, y; {direct} px); {:.1} % of {valid} valid object pixels decoded; of those {:.1} % within 1 monitor pixel of the footprint centroid, {:.1} % within their uncertainty; median error against the footprint centroid {:.3} px",
        rows.iter().map(|c| c.mask_iou).sum::<f64>() / rows.len().max(1) as f64,
        Comparison::overall_edge_offset_px(&rows),
        direct_offset[0],
        direct_offset[1],
        100.0 * n as f64 / valid.max(1) as f64,
        100.0 * w(|c| c.within_1px_footprint),
        100.0 * w(|c| c.within_uncertainty_footprint),
        glasscan::util::median(rows.iter().map(|c| c.median_error_footprint_px).collect())
    );
    Ok(())
}

/// What decode measured of the camera's blur, beside scan.toml's.
fn print_blur(
    scan: &glasscan::scan::Scan,
    blur: Option<Result<MeasuredBlur, Unmeasured>>,
) -> Result<()> {
    let given = scan.config.blur_px;
    match (blur, given) {
        (Some(Ok(m)), Some(g)) => outln!(
            "camera blur on the background captures: σ {:.2} px ({} stripe edges); scan.toml gives blur_px = {g}, which runs use",
            m.sigma_px,
            m.edges
        ),
        (Some(Ok(m)), None) => outln!(
            "camera blur on the background captures: σ {:.2} px ({} stripe edges); a run with blur_correction uses it (blur_px in scan.toml overrides it)",
            m.sigma_px,
            m.edges
        ),
        (Some(Err(why)), _) => outln!("camera blur: not measured, {why}"),
        (None, _) => {}
    }
    Ok(())
}
