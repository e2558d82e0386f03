//! `loss.png`: the loss terms over the iterations (log scale), stage boundaries in grey.

use std::path::Path;

use anyhow::Result;
use opencv::core::{Mat, Point, Scalar, CV_8UC3};
use opencv::imgproc::{line, put_text, FONT_HERSHEY_SIMPLEX, LINE_AA};

use super::IterationRecord;
use crate::util::image::write_png;

/// A plotted term: name, value, colour (BGR).
type Term = (&'static str, fn(&IterationRecord) -> f64, Scalar);

/// Draws the weighted term means of `history` (one point per iteration) into a PNG.
pub fn loss_plot(path: &Path, history: &[IterationRecord]) -> Result<()> {
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
    line(
        &mut img,
        Point::new(margin, h - margin),
        Point::new(w - margin, h - margin),
        Scalar::all(0.0),
        1,
        LINE_AA,
        0,
    )?;
    line(
        &mut img,
        Point::new(margin, margin),
        Point::new(margin, h - margin),
        Scalar::all(0.0),
        1,
        LINE_AA,
        0,
    )?;
    let mut decade = lo;
    while decade <= hi {
        let yy = y(10f64.powf(decade));
        put_text(
            &mut img,
            &format!("1e{decade}"),
            Point::new(5, yy + 4),
            FONT_HERSHEY_SIMPLEX,
            0.4,
            Scalar::all(0.0),
            1,
            LINE_AA,
            false,
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
        put_text(
            &mut img,
            name,
            Point::new(margin + 130 * k as i32, margin - 20),
            FONT_HERSHEY_SIMPLEX,
            0.5,
            *colour,
            1,
            LINE_AA,
            false,
        )?;
    }
    put_text(
        &mut img,
        "iteration (grey: new stage)",
        Point::new(w / 2 - 100, h - 20),
        FONT_HERSHEY_SIMPLEX,
        0.5,
        Scalar::all(0.0),
        1,
        LINE_AA,
        false,
    )?;
    write_png(path, &img)
}
