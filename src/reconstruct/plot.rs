//! The plots of a reconstruction, drawn with `plotters` (axes, ticks, legends) and written as a
//! PNG and, beside it, an SVG of the same drawing: the loss curves of a run and the
//! time–accuracy trade of `bench reconstruct`.

use std::path::Path;
use std::sync::Once;

use anyhow::{anyhow, Result};
use opencv::core::{Mat, CV_8UC3};
use opencv::prelude::*;
use plotters::coord::Shift;
use plotters::prelude::*;

use super::{Checkpoint, IterationRecord};
use crate::util::atomic::write_atomic;
use crate::util::image::write_png;

/// DejaVu Sans, compiled in (build.rs), so that plots need no font at run time.
static FONT: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/plot_font.ttf"));

/// Registers [`FONT`] as plotters' "sans-serif" (once per process).
fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is compiled in and known to parse; a failure would only lose the text.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// Plot size, pixels.
const SIZE: (u32, u32) = (1000, 560);

/// Draws with `draw` into `png` (atomically) and into the SVG beside it.
fn png_and_svg(
    png: &Path,
    draw_png: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
    draw_svg: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> Result<()>,
) -> Result<()> {
    register_font();
    let mut rgb = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        draw_png(&root)?;
        root.present().map_err(plot_err)?;
    }
    // OpenCV writes BGR: swap the channels of plotters' RGB.
    for px in rgb.chunks_exact_mut(3) {
        px.swap(0, 2);
    }
    let mat = Mat::new_rows_cols_with_data(SIZE.1 as i32, (SIZE.0 * 3) as i32, &rgb)?
        .reshape(3, SIZE.1 as i32)?
        .try_clone()?;
    debug_assert_eq!(mat.typ(), CV_8UC3);
    write_png(png, &mat)?;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        draw_svg(&root)?;
        root.present().map_err(plot_err)?;
    }
    let svg_path = png.with_extension("svg");
    write_atomic(&svg_path, |w| w.write_all(svg.as_bytes()))
        .map_err(|e| anyhow!("cannot write {}: {e}", svg_path.display()))
}

/// plotters' errors as anyhow's.
fn plot_err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("plotting: {e}")
}

/// A plotted term of the loss: name, value, colour.
type Term = (&'static str, fn(&IterationRecord) -> f64, RGBColor);

/// The plotted terms.
const TERMS: [Term; 5] = [
    ("total", |r| r.total, BLACK),
    ("refraction", |r| r.refraction, RGBColor(0, 80, 200)),
    ("silhouette", |r| r.silhouette, RGBColor(0, 140, 0)),
    ("smoothness", |r| r.smoothness, RGBColor(200, 0, 0)),
    ("membrane", |r| r.membrane, RGBColor(140, 0, 160)),
];

/// Draws the weighted term means of a run's history (one point per iteration, stage boundaries
/// as grey lines): the warm-up stages (DRT's terms and weights, whose total can be negative) on
/// a linear scale in a panel of their own, the other stages on a log scale with the fit to the
/// held-out views after each stage (when the run holds views out).
pub fn loss_plot(path: &Path, checkpoint: &Checkpoint) -> Result<()> {
    let history = &checkpoint.history;
    let split = history
        .iter()
        .position(|r| r.stage >= checkpoint.settings.warmup_stages)
        .unwrap_or(history.len());
    let (warmup, main) = history.split_at(split);
    let validation = validation_points(checkpoint);
    let panels = Panels {
        warmup,
        main,
        offset: split,
        validation: &validation,
    };
    png_and_svg(
        path,
        |root| loss_panels(root, &panels),
        |root| loss_panels(root, &panels),
    )
}

/// The fit to the held-out views at the end of a stage: its iteration, the total and the
/// refraction term (which decides between stages,
/// docs/decisions.md#the-result-stage-a-finer-stage-earns-its-place-view-by-view).
#[derive(Clone, Copy)]
struct HeldOutPoint {
    iteration: f64,
    total: f64,
    refraction: f64,
}

/// A series of held-out points: its legend, the value it shows and its marker.
type HeldOutSeries = (&'static str, fn(&HeldOutPoint) -> f64, ShapeStyle);

/// The held-out fit at the end of each stage after the warm-up.
fn validation_points(checkpoint: &Checkpoint) -> Vec<HeldOutPoint> {
    let mut end = 0;
    let mut points = Vec::new();
    for st in &checkpoint.stages {
        end += checkpoint
            .history
            .iter()
            .filter(|r| r.stage == st.stage)
            .count();
        if let (true, Some(v)) = (
            st.stage >= checkpoint.settings.warmup_stages,
            st.validation.as_ref(),
        ) {
            points.push(HeldOutPoint {
                iteration: (end.max(1) - 1) as f64,
                total: v.total,
                refraction: v.refraction,
            });
        }
    }
    points
}

/// What the loss plot shows.
struct Panels<'a> {
    warmup: &'a [IterationRecord],
    main: &'a [IterationRecord],
    /// Iteration index of `main`'s first record.
    offset: usize,
    validation: &'a [HeldOutPoint],
}

/// The warm-up panel (if any) beside the main one.
fn loss_panels<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, p: &Panels) -> Result<()> {
    if p.warmup.is_empty() {
        return loss_panel(
            root,
            (p.main, 0),
            p.validation,
            "loss terms (weighted means), log scale",
            true,
        );
    }
    let (left, right) = root.split_horizontally(SIZE.0 * 2 / 5);
    loss_panel(
        &left,
        (p.warmup, 0),
        &[],
        "warm-up (DRT's terms and weights), linear",
        false,
    )?;
    loss_panel(
        &right,
        (p.main, p.offset),
        p.validation,
        "stages, log scale",
        true,
    )
}

/// One panel of loss curves over iterations `offset..offset + records.len()`, with the
/// held-out fit `validation` as points.
fn loss_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    (records, offset): (&[IterationRecord], usize),
    validation: &[HeldOutPoint],
    title: &str,
    log: bool,
) -> Result<()> {
    let values = records
        .iter()
        .flat_map(|r| TERMS.iter().map(move |t| (t.1)(r)))
        .chain(validation.iter().flat_map(|p| [p.total, p.refraction]))
        .filter(|v| v.is_finite() && (!log || *v > 0.0));
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let (lo, hi) = if lo.is_finite() {
        (lo, hi)
    } else {
        (1e-3, 1.0)
    };
    let x = offset as f64..(offset + records.len().max(2) - 1) as f64;
    let mut b = ChartBuilder::on(area);
    b.caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70);
    if log {
        let y = (lo * 0.8..hi * 1.25).log_scale();
        let mut chart = b.build_cartesian_2d(x, y).map_err(plot_err)?;
        draw_loss_series(&mut chart, (records, offset), validation, |v| v > 0.0)
    } else {
        let pad = 0.05 * (hi - lo).abs().max(1e-12);
        let mut chart = b
            .build_cartesian_2d(x, lo - pad..hi + pad)
            .map_err(plot_err)?;
        draw_loss_series(&mut chart, (records, offset), validation, |_| true)
    }
}

/// Axes, stage boundaries, the four terms and the held-out fit (points `keep` accepts) and
/// the legend.
fn draw_loss_series<'a, DB, Y>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<plotters::coord::types::RangedCoordf64, Y>>,
    (records, offset): (&[IterationRecord], usize),
    validation: &[HeldOutPoint],
    keep: impl Fn(f64) -> bool,
) -> Result<()>
where
    DB: DrawingBackend + 'a,
    Y: Ranged<ValueType = f64> + plotters::coord::ranged1d::ValueFormatter<f64>,
{
    chart
        .configure_mesh()
        .x_desc("iteration")
        .y_desc("loss")
        .x_labels(6)
        .x_label_formatter(&|x| format!("{x:.0}"))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(plot_err)?;
    let (_, y_range) = (chart.x_range(), chart.y_range());
    for (i, r) in records.iter().enumerate().skip(1) {
        if r.stage != records[i - 1].stage {
            let x = (offset + i) as f64;
            chart
                .draw_series(LineSeries::new(
                    [(x, y_range.start), (x, y_range.end)],
                    RGBColor(190, 190, 190),
                ))
                .map_err(plot_err)?;
        }
    }
    // A term that is zero throughout (switched off) gets no line and no legend entry.
    let present = |value: fn(&IterationRecord) -> f64| records.iter().any(|r| value(r) != 0.0);
    for (name, value, colour) in TERMS.into_iter().filter(|t| present(t.1)) {
        let points = records
            .iter()
            .enumerate()
            .map(|(i, r)| ((offset + i) as f64, value(r)))
            .filter(|(_, v)| v.is_finite() && keep(*v));
        chart
            .draw_series(LineSeries::new(points, colour.stroke_width(2)))
            .map_err(plot_err)?
            .label(name)
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(2)));
    }
    let colour = RGBColor(230, 130, 0);
    let held_out: [HeldOutSeries; 2] = [
        ("held-out views: total", |p| p.total, colour.filled()),
        (
            "held-out views: refraction",
            |p| p.refraction,
            colour.stroke_width(2),
        ),
    ];
    // No held-out views: no points and no legend entries.
    let held_out = if validation.is_empty() {
        &[][..]
    } else {
        &held_out[..]
    };
    for &(name, value, style) in held_out {
        let points = (validation.iter())
            .map(|p| (p.iteration, value(p)))
            .filter(|(_, v)| v.is_finite() && keep(*v));
        chart
            .draw_series(points.map(|p| Circle::new(p, 5, style)))
            .map_err(plot_err)?
            .label(name)
            .legend(move |(x, y)| Circle::new((x + 9, y), 5, style));
    }
    draw_legend(chart)
}

/// The series' legend, in the upper right corner.
fn draw_legend<'a, DB, CT>(chart: &mut ChartContext<'a, DB, CT>) -> Result<()>
where
    DB: DrawingBackend + 'a,
    CT: CoordTranslate,
{
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(plot_err)
}

/// Colours of the presets in [`time_accuracy_plot`].
const PRESET_COLOURS: [(&str, RGBColor); 4] = [
    ("fast", RGBColor(0, 140, 0)),
    ("balanced", RGBColor(0, 80, 200)),
    ("accurate", RGBColor(200, 0, 0)),
    ("drt", RGBColor(120, 120, 120)),
];

/// Accuracy (mm, linear) against wall time (s, log scale): one line per run through its
/// (time, accuracy) after the hull and each stage, coloured by the preset named in its label
/// (the label's third word), with a legend of the labels.
pub fn time_accuracy_plot(path: &Path, series: &[(String, Vec<(f64, f64)>)]) -> Result<()> {
    png_and_svg(
        path,
        |root| time_accuracy_chart(root, series),
        |root| time_accuracy_chart(root, series),
    )
}

fn time_accuracy_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<()> {
    let points = series
        .iter()
        .flat_map(|s| s.1.iter())
        .filter(|p| p.0 > 0.0 && p.1.is_finite());
    let (t_lo, t_hi, a_hi) = points.fold((f64::INFINITY, 0.0f64, 0.0f64), |(a, b, c), p| {
        (a.min(p.0), b.max(p.0), c.max(p.1))
    });
    let (t_lo, t_hi) = if t_lo.is_finite() {
        (t_lo, t_hi)
    } else {
        (1.0, 10.0)
    };
    let mut chart = ChartBuilder::on(root)
        .caption("accuracy after the hull and each stage", ("sans-serif", 20))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(64)
        .build_cartesian_2d(
            (t_lo * 0.8..t_hi * 1.25).log_scale(),
            0.0..a_hi.max(0.1) * 1.05,
        )
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc("time (s, log scale)")
        .y_desc("accuracy (mm)")
        .draw()
        .map_err(plot_err)?;
    for (label, pts) in series {
        let preset = label.split_whitespace().nth(2).unwrap_or("");
        let colour = PRESET_COLOURS
            .iter()
            .find(|(p, _)| *p == preset)
            .map_or(BLACK, |c| c.1);
        let pts: Vec<(f64, f64)> = pts.iter().copied().filter(|p| p.0 > 0.0).collect();
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))
            .map_err(plot_err)?
            .label(label.as_str())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(2)));
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))
            .map_err(plot_err)?;
    }
    draw_legend(&mut chart)
}
