//! Plots a person can open: `loss.png` (the loss terms over the iterations, log scale, stage
//! boundaries in grey) and the benchmark's time against accuracy.

use std::path::Path;

use anyhow::Result;
use opencv::core::{Mat, Point, Scalar, CV_8UC3};
use opencv::imgproc::{circle, line, FILLED, LINE_AA};

use super::IterationRecord;
use crate::util::image::{label, write_png};

/// A plotted term: name, value, colour (BGR).
type Term = (&'static str, fn(&IterationRecord) -> f64, Scalar);

/// Draws the weighted term means of `history` (one point per iteration) into a PNG; the first
/// `warmup_stages` stages (DRT's weights, so on another scale) are labelled as such.
pub fn loss_plot(path: &Path, history: &[IterationRecord], warmup_stages: usize) -> Result<()> {
    let (w, h, margin) = (900, 520, 60);
    let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC3, Scalar::all(255.0))?;
    let terms: [Term; 4] = [
        ("total", |r| r.total, Scalar::new(0.0, 0.0, 0.0, 0.0)),
        (
            "refraction",
            |r| r.refraction,
            Scalar::new(200.0, 80.0, 0.0, 0.0),
        ),
        (
            "silhouette",
            |r| r.silhouette,
            Scalar::new(0.0, 140.0, 0.0, 0.0),
        ),
        (
            "smoothness",
            |r| r.smoothness,
            Scalar::new(0.0, 0.0, 200.0, 0.0),
        ),
    ];
    let logs: Vec<f64> = history
        .iter()
        .flat_map(|r| terms.iter().map(move |t| (t.1)(r)))
        .filter(|v| *v > 0.0 && v.is_finite())
        .map(f64::log10)
        .collect();
    let (lo, hi) = logs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let (lo, hi) = if lo.is_finite() {
        (lo.floor(), hi.ceil().max(lo.floor() + 1.0))
    } else {
        (0.0, 1.0)
    };
    let n = history.len().max(2) as f64;
    let x = |i: usize| margin + ((w - 2 * margin) as f64 * i as f64 / (n - 1.0)) as i32;
    let y = |v: f64| h - margin - ((h - 2 * margin) as f64 * (v.log10() - lo) / (hi - lo)) as i32;
    let grey = Scalar::all(190.0);
    for (i, r) in history.iter().enumerate() {
        if i > 0 && r.stage != history[i - 1].stage {
            line(
                &mut img,
                Point::new(x(i), margin),
                Point::new(x(i), h - margin),
                grey,
                1,
                LINE_AA,
                0,
            )?;
        }
    }
    axes(&mut img, w, h, margin)?;
    let mut decade = lo;
    while decade <= hi {
        let yy = y(10f64.powf(decade));
        label(
            &mut img,
            &format!("1e{decade}"),
            Point::new(5, yy + 4),
            0.4,
            Scalar::all(0.0),
        )?;
        decade += 1.0;
    }
    for (k, (name, f, colour)) in terms.iter().enumerate() {
        for i in 1..history.len() {
            let (a, b) = (f(&history[i - 1]), f(&history[i]));
            if a > 0.0 && b > 0.0 && a.is_finite() && b.is_finite() {
                line(
                    &mut img,
                    Point::new(x(i - 1), y(a)),
                    Point::new(x(i), y(b)),
                    *colour,
                    1,
                    LINE_AA,
                    0,
                )?;
            }
        }
        label(
            &mut img,
            name,
            Point::new(margin + 130 * k as i32, margin - 20),
            0.5,
            *colour,
        )?;
    }
    if warmup_stages > 0 {
        let end = history
            .iter()
            .position(|r| r.stage >= warmup_stages)
            .unwrap_or(history.len());
        let dark = Scalar::all(90.0);
        label(
            &mut img,
            "warm-up (DRT's weights)",
            Point::new(x(0) + 6, margin + 16),
            0.45,
            dark,
        )?;
        if end < history.len() {
            label(
                &mut img,
                "refinement",
                Point::new(x(end) + 6, margin + 16),
                0.45,
                dark,
            )?;
        }
    }
    label(
        &mut img,
        "iteration (grey: new stage)",
        Point::new(w / 2 - 100, h - 20),
        0.5,
        Scalar::all(0.0),
    )?;
    write_png(path, &img)
}

/// The two axis lines of a `w` × `h` plot with `margin`.
fn axes(img: &mut Mat, w: i32, h: i32, margin: i32) -> Result<()> {
    let black = Scalar::all(0.0);
    line(
        img,
        Point::new(margin, h - margin),
        Point::new(w - margin, h - margin),
        black,
        1,
        LINE_AA,
        0,
    )?;
    line(
        img,
        Point::new(margin, margin),
        Point::new(margin, h - margin),
        black,
        1,
        LINE_AA,
        0,
    )?;
    Ok(())
}

/// Colours (BGR) of the presets in [`time_accuracy_plot`].
const PRESET_COLOURS: [(&str, [f64; 3]); 4] = [
    ("fast", [0.0, 140.0, 0.0]),
    ("balanced", [200.0, 80.0, 0.0]),
    ("accurate", [0.0, 0.0, 200.0]),
    ("drt", [120.0, 120.0, 120.0]),
];

/// Accuracy (mm, linear) against wall time (s, log scale): one polyline per run through its
/// (time, accuracy) after the hull and each stage, coloured by the preset named in its label
/// (the label's third word), labelled at its end.
pub fn time_accuracy_plot(path: &Path, series: &[(String, Vec<(f64, f64)>)]) -> Result<()> {
    let (w, h, margin) = (1000, 640, 70);
    let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC3, Scalar::all(255.0))?;
    let pts = series
        .iter()
        .flat_map(|s| s.1.iter())
        .filter(|p| p.0 > 0.0 && p.1.is_finite());
    let (t_lo, t_hi, a_hi) = pts.fold((f64::INFINITY, 0.0f64, 0.0f64), |(a, b, c), p| {
        (a.min(p.0), b.max(p.0), c.max(p.1))
    });
    let (lo, hi) = if t_lo.is_finite() {
        (
            t_lo.log10().floor(),
            t_hi.log10().ceil().max(t_lo.log10().floor() + 1.0),
        )
    } else {
        (0.0, 1.0)
    };
    let a_hi = if a_hi > 0.0 {
        (a_hi * 10.0).ceil() / 10.0
    } else {
        1.0
    };
    let x = |t: f64| margin + ((w - 2 * margin) as f64 * (t.log10() - lo) / (hi - lo)) as i32;
    let y = |a: f64| h - margin - ((h - 2 * margin) as f64 * a / a_hi) as i32;
    axes(&mut img, w, h, margin)?;
    let black = Scalar::all(0.0);
    let mut decade = lo;
    while decade <= hi {
        let t = 10f64.powf(decade);
        label(
            &mut img,
            &format!("{t} s"),
            Point::new(x(t) - 15, h - margin + 18),
            0.4,
            black,
        )?;
        decade += 1.0;
    }
    for k in 0..=5 {
        let a = a_hi * k as f64 / 5.0;
        label(
            &mut img,
            &format!("{a:.2}"),
            Point::new(10, y(a) + 4),
            0.4,
            black,
        )?;
    }
    for (name, points) in series {
        let preset = name.split_whitespace().nth(2).unwrap_or("");
        let c = PRESET_COLOURS
            .iter()
            .find(|(p, _)| *p == preset)
            .map_or([0.0; 3], |(_, c)| *c);
        let colour = Scalar::new(c[0], c[1], c[2], 0.0);
        let ok: Vec<&(f64, f64)> = points
            .iter()
            .filter(|p| p.0 > 0.0 && p.1.is_finite())
            .collect();
        for pair in ok.windows(2) {
            line(
                &mut img,
                Point::new(x(pair[0].0), y(pair[0].1)),
                Point::new(x(pair[1].0), y(pair[1].1)),
                colour,
                1,
                LINE_AA,
                0,
            )?;
        }
        if let Some(end) = ok.last() {
            circle(
                &mut img,
                Point::new(x(end.0), y(end.1)),
                4,
                colour,
                FILLED,
                LINE_AA,
                0,
            )?;
            let short: String = name
                .split_whitespace()
                .filter(|w| *w != preset)
                .collect::<Vec<_>>()
                .join(" ");
            label(
                &mut img,
                &short,
                Point::new(x(end.0) + 6, y(end.1) - 4),
                0.35,
                colour,
            )?;
        }
    }
    for (k, (p, c)) in PRESET_COLOURS.iter().enumerate() {
        label(
            &mut img,
            p,
            Point::new(margin + 120 * k as i32, margin - 25),
            0.55,
            Scalar::new(c[0], c[1], c[2], 0.0),
        )?;
    }
    label(
        &mut img,
        "accuracy (mm) against wall time (hull + stages; a point per stage)",
        Point::new(w / 2 - 260, h - 20),
        0.5,
        black,
    )?;
    write_png(path, &img)
}
