//! The error map: a PNG of the result mesh seen from six sides (orthographic: four around the
//! turntable's +y axis, then from above and below), every visible point coloured by its distance
//! to the reference surface (mm; blue 0 → green → yellow → red at `max_mm` and beyond) or, signed,
//! by which side of it the point lies (blue inside at −`max_mm` → grey on it → red outside at
//! +`max_mm`), and shaded by how squarely it faces the viewer; a colour bar below. The support
//! map draws a per-vertex measure of support (a result's confidence) the same way, red where
//! nothing supports the surface.

use std::path::Path;

use anyhow::Result;
use nalgebra::{Point3, Vector3};
use opencv::core::{Mat, MatTrait, Point, Rect, Scalar, Vec3b, CV_8UC3};
use opencv::imgproc::{rectangle, LINE_8};

use super::signed_distance;
use crate::mesh::TriMesh;
use crate::trace::{ClosestPoint, Ray, Scene};
use crate::util::image::{label, write_png};
use crate::util::mm;

/// Side of one panel, pixels.
const PANEL: i32 = 420;
/// Height of the colour-bar strip, pixels.
const BAR: i32 = 70;

/// The six viewing directions (unit, world frame) with each panel's up vector and title.
fn views() -> [(Vector3<f64>, Vector3<f64>, &'static str); 6] {
    let (x, y, z) = (Vector3::x(), Vector3::y(), Vector3::z());
    [
        (-z, y, "front (-z)"),
        (-x, y, "side (-x)"),
        (z, y, "back (+z)"),
        (x, y, "side (+x)"),
        (-y, -z, "top (-y)"),
        (y, z, "bottom (+y)"),
    ]
}

/// Blue → cyan → green → yellow → red for `s` in [0, 1] (BGR).
fn colour(s: f64) -> [f64; 3] {
    const STOPS: [[f64; 3]; 5] = [
        [255.0, 40.0, 20.0],
        [230.0, 200.0, 0.0],
        [40.0, 200.0, 40.0],
        [0.0, 220.0, 240.0],
        [20.0, 20.0, 230.0],
    ];
    let t = s.clamp(0.0, 1.0) * (STOPS.len() - 1) as f64;
    let i = (t.floor() as usize).min(STOPS.len() - 2);
    let f = t - i as f64;
    std::array::from_fn(|c| STOPS[i][c] * (1.0 - f) + STOPS[i + 1][c] * f)
}

/// Blue (−1, inside) → grey (0) → red (+1, outside) for `s` in [−1, 1] (BGR).
fn signed_colour(s: f64) -> [f64; 3] {
    const INSIDE: [f64; 3] = [220.0, 70.0, 20.0];
    const ON: [f64; 3] = [225.0, 225.0, 225.0];
    const OUTSIDE: [f64; 3] = [20.0, 20.0, 220.0];
    let s = s.clamp(-1.0, 1.0);
    let (end, f) = if s < 0.0 { (INSIDE, -s) } else { (OUTSIDE, s) };
    std::array::from_fn(|c| ON[c] * (1.0 - f) + end[c] * f)
}

/// What an error map shows: the distance to the reference, or the signed distance to the
/// reference mesh (negative inside it).
#[derive(Clone, Copy)]
pub enum ErrorScale<'a> {
    Distance,
    Signed(&'a TriMesh),
}

impl ErrorScale<'_> {
    /// The distance (mm) this scale shows for point `q` with its closest reference point `c`.
    fn distance(&self, q: &Point3<f64>, c: &ClosestPoint) -> f64 {
        match self {
            ErrorScale::Distance => c.dist,
            ErrorScale::Signed(mesh) => signed_distance(q, c, mesh),
        }
    }

    /// Where distance `d` (mm) lies along the colour bar, 0 at its left end and 1 at its right
    /// (`max_mm` at the right end; for the signed scale −`max_mm` at the left).
    fn position(&self, d: f64, max_mm: f64) -> f64 {
        match self {
            ErrorScale::Distance => d / max_mm,
            ErrorScale::Signed(_) => 0.5 + 0.5 * d / max_mm,
        }
    }

    /// The colour at `f` along the bar (clamped to its ends).
    fn bar_colour(&self, f: f64) -> [f64; 3] {
        match self {
            ErrorScale::Distance => colour(f),
            ErrorScale::Signed(_) => signed_colour(2.0 * f - 1.0),
        }
    }

    /// The colour bar's title and its labels at its left end, middle and right end.
    fn legend(&self, max_mm: f64) -> (&'static str, [String; 3]) {
        match self {
            ErrorScale::Distance => (
                "distance to the reference",
                [
                    "0 mm".into(),
                    format!("{} mm", mm(0.5 * max_mm, 3)),
                    format!(">= {} mm", mm(max_mm, 3)),
                ],
            ),
            ErrorScale::Signed(_) => (
                "signed distance to the reference (< 0: inside it)",
                [
                    format!("<= -{} mm", mm(max_mm, 3)),
                    "0 mm".into(),
                    format!(">= +{} mm", mm(max_mm, 3)),
                ],
            ),
        }
    }
}

/// Renders `result` coloured by the distance of each visible point to the surface in `reference`
/// (as `scale` says) and writes the PNG to `path` (atomically). `max_mm`: the distance shown red.
pub fn write_error_map(
    path: &Path,
    result: &TriMesh,
    result_scene: &Scene,
    reference: &Scene,
    scale: ErrorScale,
    max_mm: f64,
) -> Result<()> {
    let colours = |seen: &[(u32, Point3<f64>)]| -> Result<Vec<[f64; 3]>> {
        let points: Vec<Point3<f64>> = seen.iter().map(|s| s.1).collect();
        let dist = reference.closest_points(&points)?;
        Ok((points.iter().zip(&dist))
            .map(|(q, c)| scale.bar_colour(scale.position(scale.distance(q, c), max_mm)))
            .collect())
    };
    let (title, labels) = scale.legend(max_mm);
    let bar = |f: f64| scale.bar_colour(f);
    write_panels(
        path,
        (result, result_scene),
        &colours,
        (&bar, title, labels),
    )
}

/// Renders `result` coloured by a per-vertex measure of support (`per_vertex`, in `unit`; each
/// face shows its vertices' mean) with the error map's conventions: red where it is 0 (nothing
/// supports the surface), blue at `max` and beyond; writes the PNG to `path` (atomically).
pub fn write_support_map(
    path: &Path,
    (result, result_scene): (&TriMesh, &Scene),
    per_vertex: &[f64],
    (title, unit, max): (&str, &str, f64),
) -> Result<()> {
    let colours = |seen: &[(u32, Point3<f64>)]| -> Result<Vec<[f64; 3]>> {
        Ok(seen
            .iter()
            .map(|&(prim, _)| {
                let face = result.faces[prim as usize];
                let v = face.iter().map(|&k| per_vertex[k as usize]).sum::<f64>() / 3.0;
                colour(1.0 - v / max)
            })
            .collect())
    };
    let labels = [
        format!(">= {max:.3} {unit}"),
        format!("{:.3} {unit}", 0.5 * max),
        format!("0 {unit}"),
    ];
    let bar = |f: f64| colour(f);
    write_panels(
        path,
        (result, result_scene),
        &colours,
        (&bar, title, labels),
    )
}

/// The legend of a map of a result's confidence (`per_vertex`, its `quality`: refraction rays
/// per mm² over their mean penalty): its title, unit, and the value shown blue, twice the
/// median over the vertices (at least 1).
pub fn confidence_legend(per_vertex: &[f64]) -> (&'static str, &'static str, f64) {
    let median = crate::util::median(per_vertex.to_vec());
    (
        "refraction rays per mm^2 over their mean penalty (red: none; the mesh's vertex quality)",
        "/mm^2",
        (2.0 * median).max(1.0),
    )
}

/// Colours of the visible points (triangle, point) of one panel, before shading.
type PanelColours<'a> = &'a dyn Fn(&[(u32, Point3<f64>)]) -> Result<Vec<[f64; 3]>>;

/// The six panels of `result` (through `result_scene`), each visible point coloured by
/// `colours` and shaded by how squarely it faces the viewer, and the colour bar (its colour
/// along [0, 1], title, labels at its left end, middle and right end); written to `path`.
fn write_panels(
    path: &Path,
    (result, result_scene): (&TriMesh, &Scene),
    colours: PanelColours,
    (bar_colour, title, labels): (&dyn Fn(f64) -> [f64; 3], &str, [String; 3]),
) -> Result<()> {
    let Some((lo, hi)) = result.bbox() else {
        anyhow::bail!("the mesh has no vertices: no map");
    };
    let centre = nalgebra::center(&lo, &hi);
    let radius = 0.5 * (hi - lo).norm();
    let mm_per_px = 2.0 * radius * 1.05 / PANEL as f64;
    let (cols, rows) = (3, 2);
    let mut img = Mat::new_rows_cols_with_default(
        rows * PANEL + BAR,
        cols * PANEL,
        CV_8UC3,
        Scalar::all(255.0),
    )?;
    for (k, (dir, up, panel_title)) in views().into_iter().enumerate() {
        let right = dir.cross(&up);
        let rays: Vec<Ray> = (0..PANEL * PANEL)
            .map(|p| {
                let (px, py) = ((p % PANEL) as f64 + 0.5, (p / PANEL) as f64 + 0.5);
                let offset = right * ((px - 0.5 * PANEL as f64) * mm_per_px)
                    - up * ((py - 0.5 * PANEL as f64) * mm_per_px);
                Ray::new(centre + offset - dir * (2.0 * radius), dir)
            })
            .collect();
        let hits = result_scene.intersect(&rays, true)?;
        let (pixels, seen): (Vec<usize>, Vec<(u32, Point3<f64>)>) = rays
            .iter()
            .zip(&hits)
            .enumerate()
            .filter_map(|(p, (r, h))| h.map(|h| (p, (h.prim, r.origin + r.dir * h.t))))
            .unzip();
        let (x0, y0) = ((k as i32 % cols) * PANEL, (k as i32 / cols) * PANEL);
        for ((p, (prim, _)), c) in pixels.iter().zip(&seen).zip(colours(&seen)?) {
            let n = result.face_cross(*prim as usize);
            let facing = n.dot(&dir).abs() / n.norm().max(f64::MIN_POSITIVE);
            let shade = 0.35 + 0.65 * facing;
            let c = c.map(|v| (v * shade) as u8);
            *img.at_2d_mut::<Vec3b>(y0 + *p as i32 / PANEL, x0 + *p as i32 % PANEL)? =
                Vec3b::from(c);
        }
        label(
            &mut img,
            panel_title,
            Point::new(x0 + 10, y0 + 22),
            0.6,
            Scalar::all(0.0),
        )?;
    }
    draw_bar(&mut img, (cols, rows), bar_colour, title, labels)?;
    write_png(path, &img)
}

/// The colour bar below the panels of an image `cols` × `rows` panels large.
fn draw_bar(
    img: &mut Mat,
    (cols, rows): (i32, i32),
    bar_colour: &dyn Fn(f64) -> [f64; 3],
    title: &str,
    labels: [String; 3],
) -> Result<()> {
    let (bx, by, bw, bh) = (60, rows * PANEL + 12, cols * PANEL - 120, 20);
    for i in 0..bw {
        let c = bar_colour(i as f64 / (bw - 1) as f64);
        rectangle(
            img,
            Rect::new(bx + i, by, 1, bh),
            Scalar::new(c[0], c[1], c[2], 0.0),
            -1,
            LINE_8,
            0,
        )?;
    }
    for (f, text) in [0.0, 0.5, 1.0].into_iter().zip(labels) {
        let x = bx + (f * bw as f64) as i32 - 20;
        label(
            img,
            &text,
            Point::new(x.min(cols * PANEL - 130), by + bh + 22),
            0.5,
            Scalar::all(0.0),
        )?;
    }
    label(img, title, Point::new(bx, by - 2), 0.45, Scalar::all(0.0))
}

#[cfg(test)]
mod tests {
    use super::{colour, signed_colour};

    #[test]
    fn the_colour_scale_runs_blue_to_red_and_clamps() {
        assert_eq!(colour(0.0), [255.0, 40.0, 20.0]);
        assert_eq!(colour(1.0), [20.0, 20.0, 230.0]);
        assert_eq!(colour(7.0), colour(1.0));
        assert_eq!(colour(-1.0), colour(0.0));
        let mid = colour(0.5);
        assert!(mid[1] > mid[0] && mid[1] > mid[2], "{mid:?}");
    }

    #[test]
    fn the_signed_scale_runs_blue_inside_to_red_outside_and_clamps() {
        let (inside, outside) = (signed_colour(-1.0), signed_colour(1.0));
        assert!(inside[0] > 200.0 && inside[2] < 50.0, "{inside:?}");
        assert!(outside[2] > 200.0 && outside[0] < 50.0, "{outside:?}");
        let on = signed_colour(0.0);
        assert!(
            on.iter().all(|&v| v == on[0]),
            "grey on the surface: {on:?}"
        );
        assert_eq!(signed_colour(-5.0), inside);
        assert_eq!(signed_colour(5.0), outside);
    }
}
