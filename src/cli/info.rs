//! `glasscan info MESH`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;

use glasscan::mesh::io::read_mesh;
use glasscan::mesh::validate::{validate, InvalidMesh, Report};
use glasscan::mesh::{stats, TriMesh};
use glasscan::trace::thickness::thickness_quantiles;

#[derive(Args, Debug)]
pub struct InfoArgs {
    /// Mesh file (.ply or .obj).
    pub mesh: PathBuf,
}

pub fn run(args: &InfoArgs) -> Result<()> {
    let mesh = read_mesh(&args.mesh)?;
    let report = validate(&mesh);
    out!("{}", describe(&args.mesh, &mesh, &report));
    if report.is_valid() {
        outln!("{}", describe_thickness(&mesh)?);
        Ok(())
    } else {
        Err(InvalidMesh(report.defects))
            .with_context(|| format!("{} is not a valid mesh", args.mesh.display()))
    }
}

/// The local thickness line of a valid mesh (see [`glasscan::trace::thickness`]).
fn describe_thickness(mesh: &TriMesh) -> Result<String> {
    let q = thickness_quantiles(mesh, &[0.02, 0.5])?;
    let mm = |t: Option<f64>| t.unwrap_or(f64::NAN);
    Ok(format!(
        "{:<16} thinnest 2 % of the area under {:.4}, median {:.4}",
        "thickness (mm)",
        mm(q[0]),
        mm(q[1])
    ))
}

/// The human-readable summary `info` prints.
pub fn describe(path: &Path, mesh: &TriMesh, report: &Report) -> String {
    let mut s = String::new();
    let mut line = |k: &str, v: String| s.push_str(&format!("{k:<16} {v}\n"));
    line("mesh", path.display().to_string());
    line(
        "vertices",
        format!(
            "{} ({} unreferenced)",
            mesh.positions.len(),
            report.unreferenced_vertices
        ),
    );
    line("faces", mesh.faces.len().to_string());
    line("edges", report.edges.to_string());
    line("components", report.components.to_string());
    if let Some((lo, hi)) = mesh.bbox() {
        let d = hi - lo;
        line(
            "bbox min (mm)",
            format!("{:.4} {:.4} {:.4}", lo.x, lo.y, lo.z),
        );
        line(
            "bbox max (mm)",
            format!("{:.4} {:.4} {:.4}", hi.x, hi.y, hi.z),
        );
        line(
            "bbox size (mm)",
            format!(
                "{:.4} x {:.4} x {:.4} (diagonal {:.4})",
                d.x,
                d.y,
                d.z,
                d.norm()
            ),
        );
    }
    line("area (mm²)", format!("{:.4}", mesh.area()));
    line("volume (mm³)", format!("{:.4}", mesh.signed_volume()));
    let e = stats::edge_lengths(mesh);
    line(
        "edge length (mm)",
        format!(
            "mean {:.4}, min {:.4}, max {:.4}, CV {:.3}",
            e.mean_mm, e.min_mm, e.max_mm, e.cv
        ),
    );
    let a = stats::angles(mesh);
    line(
        "angles",
        format!(
            "min {:.2}°, {:.2} % of triangles with an angle < 30°",
            a.min_deg,
            100.0 * a.below_30_share
        ),
    );
    line(
        "genus",
        report
            .genus
            .map_or("undefined (not a closed manifold)".into(), |g| {
                g.to_string()
            }),
    );
    if report.is_valid() {
        line(
            "verdict",
            "valid: watertight, manifold, consistently oriented, outward".into(),
        );
    } else {
        line(
            "verdict",
            format!("INVALID ({} defect kind(s))", report.defects.len()),
        );
        for d in &report.defects {
            line("  defect", d.to_string());
        }
    }
    s
}
