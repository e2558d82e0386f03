//! Calibration files in OpenCV's FileStorage YAML (`%YAML:1.0`, `!!opencv-matrix`), read and
//! written through OpenCV itself (the `opencv` crate), so that OpenCV's tools read ours and ours
//! read theirs.
//!
//! - `camera.yml`: the keys of OpenCV's calibration sample: `image_width`, `image_height`,
//!   `camera_matrix` (3×3), `distortion_coefficients` (4 or 5 × 1: k1 k2 p1 p2 [k3]),
//!   `avg_reprojection_error` (other keys are ignored).
//! - `screen.yml`: `screen_width`, `screen_height` (pixels), `pitch_mm`, `rotation` (3×3) and
//!   `translation_mm` (3×1): monitor frame → camera frame (see [`super::screen`]).
//! - `turntable.yml`: `axis_point_mm` (3×1) and `axis_direction` (3×1), camera frame.
//! - `poses.yml` (optional, for scans whose views are not turntable angles, e.g. imported ones):
//!   `view_poses`, N×12: per view the world → camera rotation (row-major) and translation (mm).

use std::path::Path;

use nalgebra::{
    Isometry3, Matrix3, Point3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3,
};
use opencv::core::{
    FileNodeTraitConst, FileStorage, FileStorageTrait, FileStorageTraitConst, Mat, MatTraitConst,
    MatTraitConstManual,
};

use super::{Camera, Screen};
use crate::util::atomic::write_atomic;
use crate::util::fixed::MAX_SIDE_PX;

/// A calibration file that cannot be read or written, or whose content is inconsistent.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {msg}")]
pub struct CalibError {
    pub path: String,
    pub msg: String,
}

fn err(path: &Path, msg: impl Into<String>) -> CalibError {
    CalibError {
        path: path.display().to_string(),
        msg: msg.into(),
    }
}

fn cv(path: &Path) -> impl Fn(opencv::Error) -> CalibError + '_ {
    move |e| err(path, format!("OpenCV: {}", e.message))
}

/// An OpenCV file opened for reading, with typed accessors that name the missing key.
struct Reader<'a> {
    fs: FileStorage,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn open(path: &'a Path) -> Result<Self, CalibError> {
        if !path.is_file() {
            return Err(err(path, "no such file"));
        }
        // OpenCV asserts on an empty or foreign file: look at the first bytes first.
        let head = read_head(path).map_err(|e| err(path, format!("cannot read it: {e}")))?;
        if !head.starts_with(b"%YAML") {
            return Err(err(
                path,
                "not an OpenCV FileStorage YAML file: it must start with %YAML:1.0 (see the \
                 calibration files in the README)",
            ));
        }
        // Parsed from memory: OpenCV reads a '?' in a file name as the start of options.
        let meta =
            std::fs::metadata(path).map_err(|e| err(path, format!("cannot read it: {e}")))?;
        if meta.len() > MAX_FILE_BYTES {
            return Err(err(
                path,
                format!(
                    "{} bytes: a calibration file is at most {MAX_FILE_BYTES} bytes",
                    meta.len()
                ),
            ));
        }
        let text = std::fs::read_to_string(path)
            .map_err(|e| err(path, format!("cannot read it as text: {e}")))?;
        let flags = opencv::core::FileStorage_READ | opencv::core::FileStorage_MEMORY;
        let fs = FileStorage::new(&text, flags, "").map_err(|_| {
            err(
                path,
                "its YAML cannot be parsed (check indentation, colons and the !!opencv-matrix \
                 blocks against the README)",
            )
        })?;
        if !fs.is_opened().map_err(cv(path))? {
            return Err(err(path, "not an OpenCV FileStorage file"));
        }
        Ok(Self { fs, path })
    }

    fn node(&self, key: &str) -> Result<opencv::core::FileNode, CalibError> {
        let n = self.fs.get(key).map_err(cv(self.path))?;
        if n.empty().map_err(cv(self.path))? || n.is_none().map_err(cv(self.path))? {
            return Err(err(self.path, format!("missing key '{key}'")));
        }
        Ok(n)
    }

    fn real(&self, key: &str) -> Result<f64, CalibError> {
        let n = self.node(key)?;
        if !(n.is_real().map_err(cv(self.path))? || n.is_int().map_err(cv(self.path))?) {
            return Err(err(self.path, format!("'{key}' must be a number")));
        }
        let v = n.real().map_err(cv(self.path))?;
        if !v.is_finite() {
            return Err(err(self.path, format!("'{key}' is not a finite number")));
        }
        Ok(v)
    }

    fn positive_int(&self, key: &str) -> Result<u32, CalibError> {
        let v = self.real(key)?;
        if v < 1.0 || v.fract() != 0.0 || v > u32::MAX as f64 {
            return Err(err(
                self.path,
                format!("'{key}' = {v}: expected a positive whole number"),
            ));
        }
        Ok(v as u32)
    }

    /// An image or monitor side in pixels: a whole number from 1 to [`MAX_SIDE_PX`].
    fn side(&self, key: &str) -> Result<u32, CalibError> {
        let v = self.positive_int(key)?;
        if v > MAX_SIDE_PX {
            return Err(err(
                self.path,
                format!("'{key}' = {v}: at most {MAX_SIDE_PX} pixels"),
            ));
        }
        Ok(v)
    }

    /// A matrix with `rows` × `cols` entries (in either orientation for vectors), row-major.
    fn matrix(&self, key: &str, sizes: &[(i32, i32)]) -> Result<Vec<f64>, CalibError> {
        let node = self.node(key)?;
        let (r, c) = self.matrix_shape(key, &node)?;
        if !sizes.contains(&(r, c)) {
            return Err(err(
                self.path,
                format!("'{key}' is {r}×{c}, expected one of {sizes:?}"),
            ));
        }
        let m = node.mat().map_err(cv(self.path))?;
        let mut f = Mat::default();
        m.convert_to(&mut f, opencv::core::CV_64F, 1.0, 0.0)
            .map_err(cv(self.path))?;
        let v: Vec<f64> = f.data_typed::<f64>().map_err(cv(self.path))?.to_vec();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(err(self.path, format!("'{key}' has a non-finite entry")));
        }
        Ok(v)
    }

    /// Rows and columns of an `!!opencv-matrix` node, checked against its `dt` and `data`
    /// before OpenCV reads it (OpenCV asserts on a mismatch).
    fn matrix_shape(
        &self,
        key: &str,
        node: &opencv::core::FileNode,
    ) -> Result<(i32, i32), CalibError> {
        let cv = cv(self.path);
        let form = || {
            err(
                self.path,
                format!(
                    "'{key}' must be an !!opencv-matrix with rows, cols, dt: d and data (rows × \
                     cols numbers)"
                ),
            )
        };
        if !node.is_map().map_err(&cv)? {
            return Err(form());
        }
        let int = |k: &str| -> Result<i32, CalibError> {
            let n = node.get(k).map_err(&cv)?;
            if !n.is_int().map_err(&cv)? {
                return Err(form());
            }
            n.to_i32().map_err(&cv)
        };
        let (r, c) = (int("rows")?, int("cols")?);
        let dt = node.get("dt").map_err(&cv)?;
        let data = node.get("data").map_err(&cv)?;
        let dt_ok = dt.is_string().map_err(&cv)? && !dt.to_string().map_err(&cv)?.is_empty();
        let numbers = data.is_seq().map_err(&cv)?
            && (0..data.size().map_err(&cv)?).all(|i| {
                data.at(i as i32)
                    .and_then(|e| Ok(e.is_real()? || e.is_int()?))
                    .unwrap_or(false)
            });
        if r < 1 || c < 1 || !dt_ok || !numbers {
            return Err(form());
        }
        if data.size().map_err(&cv)? != (r as usize) * (c as usize) {
            return Err(err(
                self.path,
                format!(
                    "'{key}' declares {r}×{c} but its data holds {} number(s)",
                    data.size().map_err(&cv)?
                ),
            ));
        }
        Ok((r, c))
    }
}

/// The largest calibration file read, bytes (a view-pose file of 3600 views is about 1 MB).
const MAX_FILE_BYTES: u64 = 64 << 20;

/// The first bytes of a file (up to 16).
fn read_head(path: &Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let mut head = Vec::with_capacity(16);
    std::fs::File::open(path)?.take(16).read_to_end(&mut head)?;
    Ok(head)
}

/// An OpenCV file being written in memory, then stored atomically.
struct Writer<'a> {
    fs: FileStorage,
    path: &'a Path,
}

impl<'a> Writer<'a> {
    fn new(path: &'a Path) -> Result<Self, CalibError> {
        let flags = opencv::core::FileStorage_WRITE | opencv::core::FileStorage_MEMORY;
        let fs = FileStorage::new(".yml", flags, "").map_err(cv(path))?;
        Ok(Self { fs, path })
    }

    fn int(&mut self, key: &str, v: u32) -> Result<(), CalibError> {
        opencv::core::write_i32(&mut self.fs, key, v as i32).map_err(cv(self.path))
    }

    fn real(&mut self, key: &str, v: f64) -> Result<(), CalibError> {
        opencv::core::write_f64(&mut self.fs, key, v).map_err(cv(self.path))
    }

    fn matrix(&mut self, key: &str, rows: usize, data: &[f64]) -> Result<(), CalibError> {
        let cols = data.len() / rows;
        let nested: Vec<&[f64]> = data.chunks(cols).collect();
        let m = Mat::from_slice_2d(&nested).map_err(cv(self.path))?;
        opencv::core::write_mat(&mut self.fs, key, &m).map_err(cv(self.path))
    }

    fn finish(mut self) -> Result<(), CalibError> {
        let text = self.fs.release_and_get_string().map_err(cv(self.path))?;
        write_atomic(self.path, |w| w.write_all(text.as_bytes()))
            .map_err(|e| err(self.path, format!("cannot write: {e}")))
    }
}

/// Reads a camera file (OpenCV calibration sample keys).
pub fn read_camera(path: &Path) -> Result<Camera, CalibError> {
    let r = Reader::open(path)?;
    let (width, height) = (r.side("image_width")?, r.side("image_height")?);
    let k = r.matrix("camera_matrix", &[(3, 3)])?;
    let d = r.matrix("distortion_coefficients", &[(4, 1), (1, 4), (5, 1), (1, 5)])?;
    if k[1] != 0.0 || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || k[8] != 1.0 {
        return Err(err(
            path,
            "camera_matrix is not of the form [fx 0 cx; 0 fy cy; 0 0 1]",
        ));
    }
    if !(k[0] > 0.0 && k[4] > 0.0) {
        return Err(err(
            path,
            format!(
                "focal lengths must be positive (fx = {}, fy = {})",
                k[0], k[4]
            ),
        ));
    }
    let mut dist = [0.0; 5];
    dist[..d.len()].copy_from_slice(&d);
    Ok(Camera {
        width,
        height,
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        dist,
    })
}

/// What OpenCV's calibration sample records about a calibration beyond the camera itself.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraRecord {
    /// Images used.
    pub nframes: usize,
    /// Inner corners per board row and column.
    pub board_width: u32,
    pub board_height: u32,
    /// Board square size (the unit of the extrinsic translations; glasscan uses mm).
    pub square_size: f64,
    /// fx/fy when it was held fixed.
    pub aspect_ratio: Option<f64>,
    /// OpenCV's calibration flags.
    pub flags: i32,
    /// RMS reprojection error per image, pixels.
    pub per_view_errors: Vec<f64>,
    /// Per image: rotation vector (3) and translation (3) of the board in the camera frame.
    pub extrinsics: Vec<[f64; 6]>,
}

/// Writes a camera file with the keys of OpenCV's calibration sample (in its order), the
/// calibration's record included when given.
pub fn write_camera(
    path: &Path,
    c: &Camera,
    avg_reprojection_error: f64,
    record: Option<&CameraRecord>,
) -> Result<(), CalibError> {
    let mut w = Writer::new(path)?;
    if let Some(r) = record {
        w.int("nframes", r.nframes as u32)?;
    }
    w.int("image_width", c.width)?;
    w.int("image_height", c.height)?;
    if let Some(r) = record {
        w.int("board_width", r.board_width)?;
        w.int("board_height", r.board_height)?;
        w.real("square_size", r.square_size)?;
        if let Some(a) = r.aspect_ratio {
            w.real("aspectRatio", a)?;
        }
        w.int("flags", r.flags as u32)?;
    }
    w.matrix(
        "camera_matrix",
        3,
        &[c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0],
    )?;
    w.matrix("distortion_coefficients", 5, &c.dist)?;
    w.real("avg_reprojection_error", avg_reprojection_error)?;
    if let Some(r) = record {
        w.matrix(
            "per_view_reprojection_errors",
            r.per_view_errors.len(),
            &r.per_view_errors,
        )?;
        let ex: Vec<f64> = r.extrinsics.iter().flatten().copied().collect();
        w.matrix("extrinsic_parameters", r.extrinsics.len(), &ex)?;
    }
    w.finish()
}

/// Reads a screen file.
pub fn read_screen(path: &Path) -> Result<Screen, CalibError> {
    let r = Reader::open(path)?;
    let (width_px, height_px) = (r.side("screen_width")?, r.side("screen_height")?);
    let pitch_mm = r.real("pitch_mm")?;
    if pitch_mm <= 0.0 {
        return Err(err(
            path,
            format!("pitch_mm = {pitch_mm}: it must be positive"),
        ));
    }
    let rm = Matrix3::from_row_slice(&r.matrix("rotation", &[(3, 3)])?);
    if (rm.transpose() * rm - Matrix3::identity()).amax() > 1e-6 || rm.determinant() < 0.0 {
        return Err(err(
            path,
            "rotation is not a rotation matrix (orthonormal, determinant +1)",
        ));
    }
    let t = r.matrix("translation_mm", &[(3, 1), (1, 3)])?;
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rm));
    Ok(Screen {
        width_px,
        height_px,
        pitch_mm,
        pose: Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), rot),
    })
}

/// Writes a screen file.
pub fn write_screen(path: &Path, s: &Screen) -> Result<(), CalibError> {
    let mut w = Writer::new(path)?;
    w.int("screen_width", s.width_px)?;
    w.int("screen_height", s.height_px)?;
    w.real("pitch_mm", s.pitch_mm)?;
    let r = s.pose.rotation.to_rotation_matrix().into_inner();
    let row_major: Vec<f64> = (0..3)
        .flat_map(|i| (0..3).map(move |j| r[(i, j)]))
        .collect();
    w.matrix("rotation", 3, &row_major)?;
    w.matrix("translation_mm", 3, s.pose.translation.vector.as_slice())?;
    w.finish()
}

/// Reads a turntable file: the axis point and unit direction (camera frame).
pub fn read_turntable_axis(path: &Path) -> Result<(Point3<f64>, Unit<Vector3<f64>>), CalibError> {
    let r = Reader::open(path)?;
    let p = r.matrix("axis_point_mm", &[(3, 1), (1, 3)])?;
    let d = r.matrix("axis_direction", &[(3, 1), (1, 3)])?;
    let dir = Unit::try_new(Vector3::new(d[0], d[1], d[2]), 1e-12)
        .ok_or_else(|| err(path, "axis_direction is zero"))?;
    Ok((Point3::new(p[0], p[1], p[2]), dir))
}

/// Writes a turntable file.
pub fn write_turntable_axis(
    path: &Path,
    point: &Point3<f64>,
    dir: &Unit<Vector3<f64>>,
) -> Result<(), CalibError> {
    let mut w = Writer::new(path)?;
    w.matrix("axis_point_mm", 3, point.coords.as_slice())?;
    w.matrix("axis_direction", 3, dir.as_slice())?;
    w.finish()
}

/// Reads a per-view poses file (world → camera of each view).
pub fn read_view_poses(path: &Path) -> Result<Vec<Isometry3<f64>>, CalibError> {
    let r = Reader::open(path)?;
    let m = r.node("view_poses")?.mat().map_err(cv(path))?;
    if m.cols() != 12 || m.rows() < 1 {
        return Err(err(
            path,
            format!("'view_poses' is {}×{}, expected N×12", m.rows(), m.cols()),
        ));
    }
    let rows = m.rows();
    let v = r.matrix("view_poses", &[(rows, 12)])?;
    v.chunks(12)
        .enumerate()
        .map(|(k, p)| {
            let rm = Matrix3::from_row_slice(&p[..9]);
            if (rm.transpose() * rm - Matrix3::identity()).amax() > 1e-6 || rm.determinant() < 0.0 {
                return Err(err(path, format!("view {k}: not a rotation matrix")));
            }
            Ok(Isometry3::from_parts(
                Translation3::new(p[9], p[10], p[11]),
                UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rm)),
            ))
        })
        .collect()
}

/// Writes a per-view poses file.
pub fn write_view_poses(path: &Path, poses: &[Isometry3<f64>]) -> Result<(), CalibError> {
    let mut w = Writer::new(path)?;
    let data: Vec<f64> = poses
        .iter()
        .flat_map(|p| {
            let r = p.rotation.to_rotation_matrix().into_inner();
            let t = p.translation.vector;
            let mut row: Vec<f64> = (0..3)
                .flat_map(|i| (0..3).map(move |j| r[(i, j)]))
                .collect();
            row.extend_from_slice(t.as_slice());
            row
        })
        .collect();
    w.matrix("view_poses", poses.len(), &data)?;
    w.finish()
}
