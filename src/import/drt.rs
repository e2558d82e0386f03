//! `glasscan import-drt`: DRT's published captures (one HDF5 file per object, 72 views) as a
//! glasscan scan folder in decoded form.
//!
//! DRT's layout (read through libhdf5, view by view — the files are 2–3 GB):
//! - `cam_proj` [72, 4, 4]: world → camera per view; `cam_k` [3, 3]: intrinsics;
//! - `mask` [72, H, W]: 0/1 or 0/255;
//! - `screen_position` [72, H·W, 3] or [72, H, W, 3]: per pixel the decoded monitor point, world
//!   frame (mm); a row of zeros decoded nothing;
//! - Point Grey files (1280×960) also hold `ray_origin` and `ray_dir` [72, H·W, 3] (world frame);
//!   Redmi files (1920×1080) do not: rays go through integer pixel coordinates of `cam_k`.
//!
//! Written: `camera.yml` (`cam_k`, no distortion), `poses.yml` (the views' poses),
//! `turntable.yml` (the axis the poses turn about, for reference), `screen.yml` (a virtual monitor
//! on the plane fitted to the monitor points, 0.25 mm pixels), `scan.toml`, and in `decoded/` per
//! view the mask and a rays file: each object pixel's ray and 3D target in the camera frame, read
//! directly by the losses.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};

use crate::calibrate::turntable::axis_of_motions;
use crate::rig::{Camera, Screen};
use crate::scan::decoded::ViewSummary;
use crate::scan::decoded::{mask_path, rays_path, write_rays, write_summary, PixelRay};
use crate::scan::{CalibrationFiles, PatternKind, Patterns, Scan, ScanConfig, Views};
use crate::util::fixed::{FixedPoint, MAX_SIDE_PX};
use crate::util::folder::{StagedFolder, FORCE_HINT};
use crate::util::image::write_pixels;

/// DRT's view count.
pub const DRT_VIEWS: usize = 72;
/// Pixel pitch of the virtual monitor, mm, where its sides fit in [`MAX_SIDE_PX`] pixels; a wider
/// spread of targets gets the smallest pitch (in steps of 0.05 mm) that fits.
const VIRTUAL_PITCH_MM: f64 = 0.25;

/// Which of DRT's cameras made the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DrtCamera {
    /// 1280×960, per-pixel rays in the file.
    PointGrey,
    /// 1920×1080, rays from `cam_k` and `cam_proj`.
    Redmi,
}

/// What an import found.
#[derive(Clone, Debug)]
pub struct ImportReport {
    pub camera: DrtCamera,
    pub width: u32,
    pub height: u32,
    /// Object pixels and those with a monitor point, over all views.
    pub object_pixels: usize,
    pub rays: usize,
    /// RMS distance of the monitor points from their fitted plane, mm.
    pub plane_rms_mm: f64,
    /// Largest distance of a file's ray origin from its view's camera centre, mm (Point Grey).
    pub max_origin_offset_mm: f64,
    /// The virtual monitor's pixel pitch, mm.
    pub pitch_mm: f64,
    /// What looks wrong in the file but does not stop the import.
    pub warnings: Vec<String>,
}

/// The file's datasets, checked.
struct DrtFile {
    file: hdf5::File,
    path: PathBuf,
    width: usize,
    height: usize,
    /// `screen_position` is [72, H, W, 3] rather than [72, H·W, 3].
    grid_positions: bool,
}

/// Memory per pixel of a view being imported: the mask, three rows of f64 triples read from the
/// file, and the ray kept.
const BYTES_PER_PIXEL: u128 = 8 + 3 * 24 + 56;

impl DrtFile {
    fn open(path: &Path) -> Result<Self> {
        if !path.is_file() {
            bail!("{}: no such file", path.display());
        }
        let file = hdf5::File::open(path)
            .with_context(|| format!("{}: not an HDF5 file", path.display()))?;
        let mut f = Self {
            file,
            path: path.to_path_buf(),
            width: 0,
            height: 0,
            grid_positions: false,
        };
        f.expect("cam_proj", &[&[DRT_VIEWS, 4, 4]])?;
        f.expect("cam_k", &[&[3, 3]])?;
        let mask = f.shape("mask")?;
        if mask.len() != 3 || mask[0] != DRT_VIEWS || mask[1] == 0 || mask[2] == 0 {
            bail!(
                "{}: dataset 'mask' has shape {mask:?}, expected [{DRT_VIEWS}, H, W]",
                path.display()
            );
        }
        (f.height, f.width) = (mask[1], mask[2]);
        // A view is read whole: the mask, three per-pixel rows, and the rays kept.
        crate::util::budget::check(
            &format!(
                "{}: one view of {}×{} pixels ('mask')",
                path.display(),
                mask[2],
                mask[1]
            ),
            (mask[1] as u128) * (mask[2] as u128),
            BYTES_PER_PIXEL,
            "is the file damaged? DRT's cameras are 1280×960 and 1920×1080",
        )?;
        let (n, h, w) = (f.width * f.height, f.height, f.width);
        let found = f.expect(
            "screen_position",
            &[&[DRT_VIEWS, n, 3], &[DRT_VIEWS, h, w, 3]],
        )?;
        f.grid_positions = found.len() == 4;
        Ok(f)
    }

    fn shape(&self, key: &str) -> Result<Vec<usize>> {
        let ds = self.file.dataset(key).map_err(|_| {
            anyhow::anyhow!(
                "{}: no dataset '{key}' (not a DRT capture file?)",
                self.path.display()
            )
        })?;
        Ok(ds.shape())
    }

    /// The shape of `key`, which must be one of `allowed`.
    fn expect(&self, key: &str, allowed: &[&[usize]]) -> Result<Vec<usize>> {
        let s = self.shape(key)?;
        if !allowed.contains(&s.as_slice()) {
            let want: Vec<String> = allowed.iter().map(|a| format!("{a:?}")).collect();
            if s.first().is_some_and(|&v| v != DRT_VIEWS) && allowed[0].len() > 2 {
                bail!(
                    "{}: dataset '{key}' has shape {s:?}: {} views, but DRT's captures have {DRT_VIEWS} (expected {})",
                    self.path.display(),
                    s[0],
                    want.join(" or ")
                );
            }
            bail!(
                "{}: dataset '{key}' has shape {s:?}, expected {}",
                self.path.display(),
                want.join(" or ")
            );
        }
        Ok(s)
    }

    /// View `k`'s rows of a per-pixel [72, H·W, 3] (or [72, H, W, 3]) dataset, as f64 triples.
    fn pixel_rows(&self, key: &str, k: usize) -> Result<Vec<[f64; 3]>> {
        let ds = self.file.dataset(key)?;
        let flat: Vec<f64> = if ds.ndim() == 4 {
            ds.read_slice::<f64, _, ndarray::Ix3>(ndarray::s![k, .., .., ..])?
                .iter()
                .copied()
                .collect()
        } else {
            ds.read_slice_2d::<f64, _>(ndarray::s![k, .., ..])?
                .iter()
                .copied()
                .collect()
        };
        Ok(flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }

    fn matrix4(&self, k: usize) -> Result<Matrix4<f64>> {
        let m = self
            .file
            .dataset("cam_proj")?
            .read_slice_2d::<f64, _>(ndarray::s![k, .., ..])?;
        let v: Vec<f64> = m.iter().copied().collect();
        Ok(Matrix4::from_row_slice(&v))
    }
}

/// The rigid transform of a 4×4 world → camera matrix; `None` unless it is one.
fn rigid(m: &Matrix4<f64>) -> Option<Isometry3<f64>> {
    let r = m.fixed_view::<3, 3>(0, 0).into_owned();
    let ok = (r.transpose() * r - Matrix3::identity()).amax() < 1e-4
        && r.determinant() > 0.0
        && (m.row(3) - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0)).amax() < 1e-9;
    ok.then(|| {
        Isometry3::from_parts(
            Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)),
        )
    })
}

/// Imports `path` into the scan folder `out`; `camera` overrides the inference from the image
/// size; `progress(k)` after each view. The scan is written into a temporary sibling that
/// replaces `out` whole on success; a non-empty `out` is refused unless `force`.
pub fn import_drt(
    path: &Path,
    out: &Path,
    camera: Option<DrtCamera>,
    ior: f64,
    force: bool,
    progress: impl FnMut(usize),
) -> Result<ImportReport> {
    let staged = StagedFolder::new(out, force, FORCE_HINT)?;
    let report = import_into(path, staged.path(), camera, ior, progress)?;
    staged.commit()?;
    Ok(report)
}

/// [`import_drt`]'s work, into the folder `out` (the staging folder).
fn import_into(
    path: &Path,
    out: &Path,
    camera: Option<DrtCamera>,
    ior: f64,
    mut progress: impl FnMut(usize),
) -> Result<ImportReport> {
    let f = DrtFile::open(path)?;
    let kind = camera.unwrap_or_else(|| infer_camera(&f));
    if kind == DrtCamera::PointGrey {
        let (w, h) = (f.width, f.height);
        for key in ["ray_origin", "ray_dir"] {
            f.expect(key, &[&[DRT_VIEWS, w * h, 3], &[DRT_VIEWS, h, w, 3]])?;
        }
    }
    let cam = read_intrinsics(&f)?;
    let decoded = out.join("decoded");
    std::fs::create_dir_all(&decoded)
        .with_context(|| format!("cannot create {}", decoded.display()))?;
    let mut fit = PlaneSums::default();
    let mut views = Vec::with_capacity(DRT_VIEWS);
    for v in 0..DRT_VIEWS {
        views.push(import_view(&f, v, kind, &cam, &decoded, &mut fit)?);
        progress(v);
    }
    if fit.n < 3.0 {
        bail!("{}: no object pixel has a monitor point (screen_position is all zero inside the masks)", path.display());
    }
    let screen = virtual_screen(&decoded, fit.n, &fit.sum, &fit.outer)?;
    let plane_rms_mm = plane_rms(&decoded, &screen)?;
    let poses = views.iter().map(|v| v.pose).collect();
    let scan = imported_scan(out, ior, cam, screen.clone(), poses)?;
    let warnings = monitor_in_front(&scan).into_iter().collect();
    scan.save()?;
    let summaries: Vec<ViewSummary> = views.iter().map(|v| v.summary.clone()).collect();
    write_summary(
        &decoded,
        &FixedPoint::for_screen(screen.width_px, screen.height_px),
        &summaries,
        None,
    )?;
    Ok(ImportReport {
        camera: kind,
        width: f.width as u32,
        height: f.height as u32,
        object_pixels: summaries.iter().map(|s| s.object_pixels).sum(),
        rays: views.iter().map(|v| v.rays).sum(),
        plane_rms_mm,
        max_origin_offset_mm: views.iter().map(|v| v.max_origin).fold(0.0, f64::max),
        pitch_mm: screen.pitch_mm,
        warnings,
    })
}

/// A warning when the monitor plane fitted to the targets passes between the camera and the
/// turntable axis: the rays would meet their targets before the object, so the file's targets
/// are likely not on the monitor behind it (another frame or unit).
fn monitor_in_front(scan: &Scan) -> Option<String> {
    let s = &scan.screen;
    let n = s.pose.rotation * Vector3::z();
    let depth = n.dot(&(scan.turntable.axis_point.coords - s.pose.translation.vector));
    (depth > 0.0).then(|| {
        format!(
            "the monitor plane fitted to the file's targets lies {depth:.0} mm in front of the turntable axis (between the camera and the object): check that screen_position holds points on the monitor behind the object, camera frame, mm"
        )
    })
}

/// The camera of a file without `--camera`: the Redmi's size, or no per-pixel rays, means Redmi.
fn infer_camera(f: &DrtFile) -> DrtCamera {
    if (f.width, f.height) == (1920, 1080) || !f.file.link_exists("ray_dir") {
        DrtCamera::Redmi
    } else {
        DrtCamera::PointGrey
    }
}

/// The pinhole camera of `cam_k` (no distortion), checked to be of the form [fx 0 cx; 0 fy cy;
/// 0 0 1].
fn read_intrinsics(f: &DrtFile) -> Result<Camera> {
    let k: Vec<f64> = f
        .file
        .dataset("cam_k")?
        .read_2d::<f64>()?
        .iter()
        .copied()
        .collect();
    let cam = Camera {
        width: f.width as u32,
        height: f.height as u32,
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        dist: [0.0; 5],
    };
    if !(cam.fx > 0.0 && cam.fy > 0.0 && k[1] == 0.0 && k[3] == 0.0 && k[6..] == [0.0, 0.0, 1.0]) {
        bail!(
            "{}: 'cam_k' is not of the form [fx 0 cx; 0 fy cy; 0 0 1]: {k:?}",
            f.path.display()
        );
    }
    Ok(cam)
}

/// Running sums of a least-squares plane fit of the monitor points (camera frame, mm).
#[derive(Default)]
struct PlaneSums {
    n: f64,
    sum: Vector3<f64>,
    outer: Matrix3<f64>,
}

impl PlaneSums {
    fn add(&mut self, p: &Point3<f64>) {
        self.n += 1.0;
        self.sum += p.coords;
        self.outer += p.coords * p.coords.transpose();
    }
}

/// One view as imported.
struct ImportedView {
    /// World → camera.
    pose: Isometry3<f64>,
    summary: ViewSummary,
    rays: usize,
    /// Largest distance of a ray origin from the camera centre, mm (Point Grey files).
    max_origin: f64,
}

/// Reads view `v`, writes its mask and rays into `decoded`, and adds its monitor points to `fit`.
fn import_view(
    f: &DrtFile,
    v: usize,
    kind: DrtCamera,
    cam: &Camera,
    decoded: &Path,
    fit: &mut PlaneSums,
) -> Result<ImportedView> {
    let pose = rigid(&f.matrix4(v)?).with_context(|| {
        format!(
            "{}: cam_proj[{v}] is not a rigid world → camera transform",
            f.path.display()
        )
    })?;
    let mask: Vec<u8> = f
        .file
        .dataset("mask")?
        .read_slice_2d::<f64, _>(ndarray::s![v, .., ..])?
        .iter()
        .map(|&m| if m > 0.0 { 255 } else { 0 })
        .collect();
    let targets = f.pixel_rows("screen_position", v)?;
    let given = if kind == DrtCamera::PointGrey {
        Some((f.pixel_rows("ray_origin", v)?, f.pixel_rows("ray_dir", v)?))
    } else {
        None
    };
    let eye = pose.inverse() * Point3::origin();
    let (mut rays, mut objects, mut max_origin) = (Vec::new(), 0, 0.0f64);
    for (i, t) in targets.iter().enumerate() {
        if mask[i] == 0 {
            continue;
        }
        objects += 1;
        if t.iter().all(|&c| c == 0.0) || t.iter().any(|c| !c.is_finite()) {
            continue;
        }
        let dir = match &given {
            Some((origins, dirs)) => {
                max_origin = max_origin.max((Point3::from(origins[i]) - eye).norm());
                pose.rotation * Vector3::from(dirs[i])
            }
            None => cam
                .pixel_ray((i % f.width) as f64, (i / f.width) as f64)
                .context("pixel ray")?,
        };
        let Some(dir) = dir.try_normalize(1e-12) else {
            continue;
        };
        let target = pose * Point3::from(*t);
        fit.add(&target);
        rays.push(PixelRay {
            pixel: i as u32,
            dir,
            target,
        });
    }
    write_pixels(&mask_path(decoded, v), cam.width, cam.height, &mask)?;
    write_rays(decoded, v, &rays)?;
    let summary = ViewSummary {
        view: v,
        object_pixels: objects,
        decoded_share: rays.len() as f64 / objects.max(1) as f64,
        complete_share: 1.0,
        dim_share: None,
        white_drop: None,
        monitor_edge_px: 0,
        warning: None,
        flat_glass: None,
    };
    Ok(ImportedView {
        pose,
        summary,
        rays: rays.len(),
        max_origin,
    })
}

/// The scan of an import: the views' poses, the turntable axis they turn about, and the angles
/// about it.
fn imported_scan(
    out: &Path,
    ior: f64,
    camera: Camera,
    screen: Screen,
    poses: Vec<Isometry3<f64>>,
) -> Result<Scan> {
    let (axis_dir, axis_point) = axis_of_motions(&poses, None)?;
    let angles_deg: Vec<f64> = poses
        .iter()
        .map(|p| {
            let v = (p.rotation * poses[0].rotation.inverse()).scaled_axis();
            (v.norm() * v.dot(&axis_dir).signum())
                .to_degrees()
                .rem_euclid(360.0)
        })
        .collect();
    let config = ScanConfig {
        ior: crate::scan::Ior::Known(ior),
        blur_px: None,
        calibration: CalibrationFiles {
            camera: "camera.yml".into(),
            screen: "screen.yml".into(),
            turntable: "turntable.yml".into(),
            poses: Some("poses.yml".into()),
        },
        views: Views { angles_deg },
        patterns: Patterns {
            kind: PatternKind::Graycode,
            width: screen.width_px,
            height: screen.height_px,
            phase_shift: None,
        },
    };
    Ok(Scan::new(
        out,
        config,
        camera,
        screen,
        (axis_point, axis_dir),
        Some(poses),
    )?)
}

/// A monitor on the least-squares plane of the targets, facing away from the camera, its
/// columns along the camera's x, covering every target (one pass over the written rays files).
fn virtual_screen(
    decoded: &Path,
    n: f64,
    sum: &Vector3<f64>,
    outer: &Matrix3<f64>,
) -> Result<Screen> {
    let centroid = sum / n;
    let cov = outer / n - centroid * centroid.transpose();
    let eig = cov.symmetric_eigen();
    let (i_min, _) = eig.eigenvalues.argmin();
    let mut z: Vector3<f64> = eig.eigenvectors.column(i_min).into_owned();
    if z.dot(&centroid) < 0.0 {
        z = -z;
    }
    let x = (Vector3::x() - z * z.x)
        .try_normalize(1e-9)
        .unwrap_or_else(Vector3::y);
    let y = z.cross(&x);
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
        Matrix3::from_columns(&[x, y, z]),
    ));
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for_each_target(decoded, |t| {
        let d = t - Point3::from(centroid);
        for (a, axis) in [x, y].iter().enumerate() {
            lo[a] = lo[a].min(d.dot(axis));
            hi[a] = hi[a].max(d.dot(axis));
        }
    })?;
    let origin = centroid + x * lo[0] + y * lo[1];
    let pitch = virtual_pitch_mm((hi[0] - lo[0]).max(hi[1] - lo[1]));
    let size = |a: usize| ((hi[a] - lo[a]) / pitch).ceil() as u32 + 1;
    Ok(Screen {
        width_px: size(0),
        height_px: size(1),
        pitch_mm: pitch,
        pose: Isometry3::from_parts(Translation3::from(origin), rot),
    })
}

/// The virtual monitor's pitch for targets spread over `extent_mm` along its longer side:
/// [`VIRTUAL_PITCH_MM`], or the smallest multiple of 0.05 mm that keeps the side within
/// [`MAX_SIDE_PX`] pixels.
fn virtual_pitch_mm(extent_mm: f64) -> f64 {
    let fits = extent_mm / f64::from(MAX_SIDE_PX - 2);
    VIRTUAL_PITCH_MM.max((fits / 0.05).ceil() * 0.05)
}

/// RMS distance of the targets from the screen's plane, mm.
fn plane_rms(decoded: &Path, screen: &Screen) -> Result<f64> {
    let inv = screen.pose.inverse();
    let (mut n, mut s) = (0.0f64, 0.0f64);
    for_each_target(decoded, |t| {
        n += 1.0;
        s += (inv * t).z.powi(2);
    })?;
    Ok((s / n.max(1.0)).sqrt())
}

/// Calls `f` with every target of the rays files in `decoded` (camera frame).
fn for_each_target(decoded: &Path, mut f: impl FnMut(Point3<f64>)) -> Result<()> {
    for v in 0..DRT_VIEWS {
        let path = rays_path(decoded, v);
        for r in crate::scan::decoded::read_rays(&path, usize::MAX)? {
            f(r.target);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_virtual_monitor_fits_its_largest_side() {
        assert_eq!(virtual_pitch_mm(400.0), VIRTUAL_PITCH_MM);
        // A sphere's grazing exits spread 5.8 m: 23,125 pixels at 0.25 mm.
        let p = virtual_pitch_mm(5781.0);
        assert!(p > VIRTUAL_PITCH_MM && ((5781.0 / p).ceil() as u32) < MAX_SIDE_PX);
        assert!(((p / 0.05).round() * 0.05 - p).abs() < 1e-12, "{p}");
    }
}
