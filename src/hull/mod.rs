//! `glasscan hull`: the visual hull of the decoded silhouettes (docs/architecture.md §8) — the starting shape of
//! the optimisation. Space carving ([`carve`]) into a block-sparse field, marching cubes
//! ([`crate::mesh::marching_cubes`]), optionally an isotropic remesh.

pub mod carve;

use std::borrow::Cow;
use std::time::Instant;

use crate::util::progress::StepProgress;
use anyhow::{bail, Context, Result};
use rayon::prelude::*;
use serde::Serialize;

use crate::eval::fidelity::remesh_checked;
use crate::mesh::components::keep_large_components;
use crate::mesh::marching_cubes::{marching_cubes, FieldBlock, Grid};
use crate::mesh::validate::ensure_valid;
use crate::mesh::TriMesh;
use crate::remesh::RemeshOptions;
use crate::rig::camera::Camera;
use crate::scan::decoded::DecodedScan;
use crate::scan::silhouette::Silhouette;
use crate::scan::Scan;
pub use carve::VoxelSize;
use carve::{carve, CarveStats, Field};

/// Components of the carved surface with less than this share of the largest one's volume are
/// dropped: specks left where thin parts break up at the voxel size, and cavities carved by holes
/// in a mask (their volume is negative).
pub const SPECK_SHARE: f64 = 0.01;

/// Settings of a hull.
#[derive(Clone, Copy, Debug)]
pub struct HullOptions {
    /// Fine voxel size.
    pub voxel: VoxelSize,
    /// A point survives if it projects inside the mask in all views but this many.
    pub tolerance: usize,
    /// Voxels per block side of the sparse fine grid.
    pub block: usize,
    /// What is done with the marching-cubes surface.
    pub remesh: HullRemesh,
}

/// The marching-cubes surface kept as it is, or remeshed isotropically.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HullRemesh {
    Raw,
    /// To edges as long as the voxel.
    AtVoxel,
    /// To edges of this length, mm.
    EdgeMm(f64),
}

impl Default for HullOptions {
    fn default() -> Self {
        Self {
            voxel: VoxelSize::Auto,
            tolerance: 0,
            block: 4,
            remesh: HullRemesh::AtVoxel,
        }
    }
}

/// Figures of a hull.
#[derive(Clone, Debug, Serialize)]
pub struct HullReport {
    pub views: usize,
    pub carve: CarveStats,
    pub marching_cubes_faces: usize,
    /// Components dropped as specks (see [`SPECK_SHARE`]).
    pub dropped_components: usize,
    pub faces: usize,
    pub genus: i64,
    pub volume_mm3: f64,
    pub seconds_silhouettes: f64,
    pub seconds_carve: f64,
    pub seconds_marching_cubes: f64,
    pub seconds_remesh: f64,
    pub warnings: Vec<String>,
}

/// Reads the masks of `views` from the decoded scan; views decode skipped are left out with a
/// warning. Errors for empty masks (they would carve everything away) and when no view is left.
pub fn silhouettes(scan: &Scan, views: &[usize]) -> Result<(Vec<Silhouette>, Vec<String>)> {
    let decoded = DecodedScan::open(&scan.dir, (scan.camera.width, scan.camera.height))?;
    let poses = scan.view_poses();
    let mut warnings = Vec::new();
    let loaded: Vec<Result<Option<Silhouette>>> = views
        .par_iter()
        .map(|&k| {
            let Some(mask) = decoded.mask(k)? else {
                return Ok(None);
            };
            let sil = Silhouette::from_mask(k, &mask, &scan.camera, poses[k])?;
            match decoded.coverage(k)? {
                Some(coverage) => sil.with_coverage(coverage).map(Some),
                None => Ok(Some(sil)),
            }
        })
        .collect();
    let mut sils = Vec::new();
    for (&k, s) in views.iter().zip(loaded) {
        match s? {
            None => warnings.push(format!(
                "view {k} left out: {}",
                decoded.warning(k).unwrap_or("not decoded")
            )),
            Some(s) if s.area_px == 0 => bail!(
                "view {k}: the mask is empty, which would carve the whole object away; check its decode (decoded/preview/view_{k:03}.png) or leave the view out with --views"
            ),
            Some(s) => {
                if s.touches_border {
                    warnings.push(format!(
                        "view {k}: the mask touches the image border; the object may be cut off there and the hull too small"
                    ));
                }
                sils.push(s);
            }
        }
    }
    if sils.is_empty() {
        bail!(
            "no decoded view with a silhouette among the {} requested",
            views.len()
        );
    }
    Ok((sils, warnings))
}

/// The visual hull of `sils` (all taken with the same camera; the holes the decoder filled count
/// inside), world frame, outward, watertight.
pub fn visual_hull(
    sils: &[Silhouette],
    o: &HullOptions,
    progress: &dyn StepProgress,
) -> Result<(TriMesh, HullReport)> {
    let filled: Vec<Cow<Silhouette>> = sils
        .par_iter()
        .map(Silhouette::with_holes_filled)
        .collect::<Result<_>>()?;
    let sils: Vec<&Silhouette> = filled.iter().map(|s| s.as_ref()).collect();
    check_options(o, sils.len())?;
    let centre = sils[0].pose.inverse() * nalgebra::Point3::origin();
    let field = Field {
        silhouettes: &sils,
        tolerance: o.tolerance,
    };
    let t0 = Instant::now();
    let half_fov_tan = half_field_of_view_tan(&sils[0].camera);
    let (grid, blocks, stats) = carve(&field, centre, half_fov_tan, o.voxel, o.block, progress)?;
    let seconds_carve = t0.elapsed().as_secs_f64();
    progress.phase("marching cubes", 0);
    let t1 = Instant::now();
    let (mc, mc_faces, dropped_components) = carved_surface(&grid, &blocks, stats.voxel_mm)?;
    let seconds_marching_cubes = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let mesh = remeshed(mc, o.remesh, stats.voxel_mm, progress)?;
    let seconds_remesh = t2.elapsed().as_secs_f64();
    let report = ensure_valid(&mesh).context("the remeshed hull is not a valid surface")?;
    let report = HullReport {
        views: sils.len(),
        carve: stats,
        marching_cubes_faces: mc_faces,
        dropped_components,
        faces: mesh.faces.len(),
        genus: report.genus.unwrap_or(0),
        volume_mm3: mesh.signed_volume(),
        seconds_silhouettes: 0.0,
        seconds_carve,
        seconds_marching_cubes,
        seconds_remesh,
        warnings: Vec::new(),
    };
    Ok((mesh, report))
}

/// Refuses a voxel size or tolerance no hull of `views` views can be carved with.
fn check_options(o: &HullOptions, views: usize) -> Result<()> {
    if let VoxelSize::Mm(v) = o.voxel {
        if !(v > 0.0 && v.is_finite()) {
            bail!("--voxel-mm {v}: it must be a positive size");
        }
    }
    if o.tolerance >= views || o.tolerance > 7 {
        bail!(
            "--tolerance {}: it must be below the number of views ({views}) and at most 7",
            o.tolerance,
        );
    }
    Ok(())
}

/// The tangent of the widest angle between `cam`'s optical axis and a ray through its image's
/// corners (unitless).
fn half_field_of_view_tan(cam: &Camera) -> f64 {
    [
        (0.0, 0.0),
        (cam.width as f64 - 1.0, cam.height as f64 - 1.0),
    ]
    .iter()
    .map(|&(u, v): &(f64, f64)| ((u - cam.cx) / cam.fx).hypot((v - cam.cy) / cam.fy))
    .fold(0.0, f64::max)
}

/// The carved grid's surface by marching cubes, without the specks thin parts leave at the voxel
/// size and the closed cavities holes in the masks carve (components facing inwards, negative
/// volume): the surface, its marching-cubes face count and how many components were dropped.
fn carved_surface(
    grid: &Grid,
    blocks: &[FieldBlock],
    voxel_mm: f64,
) -> Result<(TriMesh, usize, usize)> {
    let mc = marching_cubes(grid, blocks);
    if mc.faces.is_empty() {
        bail!(
            "the hull is empty at --voxel-mm {}: the silhouettes' intersection is thinner than a voxel",
            crate::util::short_number(voxel_mm)
        );
    }
    let mc_faces = mc.faces.len();
    let (mc, dropped_components) = keep_large_components(&mc, SPECK_SHARE);
    ensure_valid(&mc).context("internal error: marching cubes gave an invalid surface")?;
    Ok((mc, mc_faces, dropped_components))
}

/// The marching-cubes surface `mc` as `remesh` asks (voxels of `voxel_mm` mm).
fn remeshed(
    mc: TriMesh,
    remesh: HullRemesh,
    voxel_mm: f64,
    progress: &dyn StepProgress,
) -> Result<TriMesh> {
    let edge_mm = match remesh {
        HullRemesh::Raw => return Ok(mc),
        HullRemesh::AtVoxel => voxel_mm,
        HullRemesh::EdgeMm(h) => h,
    };
    progress.phase("remesh", 0);
    Ok(remesh_checked(&mc, &RemeshOptions::uniform(edge_mm), 0)
        .context("remeshing the hull (hull: --edge-mm; reconstruct: --hull-voxel-mm)")?
        .0)
}
