//! The scan folder (documented in the README):
//!
//! ```text
//! SCAN/scan.toml                  rig description (below)
//! SCAN/camera.yml, screen.yml, turntable.yml   calibration (OpenCV FileStorage YAML)
//! SCAN/captures/view_NNN/{00..,white,black}.png   raw captures, OpenCV GrayCodePattern order
//! SCAN/captures/background/…      the same patterns without the object (optional)
//! ```
//!
//! `scan.toml`:
//! ```toml
//! ior = 1.4723                  # refractive index of the object; "auto" (estimated within
//!                               # 1.40–1.70) or { auto = [1.45, 1.60] } when unknown
//! blur_px = 0.7                 # optional: the camera's blur, a Gaussian's σ in camera pixels
//! [calibration]
//! camera = "camera.yml"         # paths relative to the scan folder
//! screen = "screen.yml"
//! turntable = "turntable.yml"
//! # poses = "poses.yml"       # optional: per-view poses replacing the turntable's
//! [views]
//! angles_deg = [0.0, 5.0]       # turntable angle of each view, degrees
//! [patterns]
//! kind = "graycode"             # OpenCV's GrayCodePattern order
//! width = 1920                  # monitor pixels the patterns span (= the screen's)
//! height = 1080
//! # phase_shift = { steps = 8, period_px = 64 }   # optional sinusoidal patterns
//! ```

pub mod decoded;
pub mod outline;
pub mod silhouette;

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Point3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use crate::patterns::{GrayCode, PhaseShift};
use crate::rig::{calib_io, Camera, Screen, Turntable};
use crate::util::atomic::write_atomic;

/// The widest camera blur `scan.toml` may give (σ, camera pixels): a capture blurred more
/// than this resolves no Gray bit finer than a dozen camera pixels.
pub const MAX_BLUR_PX: f64 = 5.0;

/// The contents of `scan.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanConfig {
    pub ior: Ior,
    /// The camera's blur as the captures show it (focus, optics, the sensor's spread): the σ of
    /// a Gaussian point-spread function, camera pixels; absent or 0: sharp. A reconstruction
    /// with `blur_correction` corrects the decoded points for it (docs/architecture.md §4, a
    /// blurred camera).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blur_px: Option<f64>,
    pub calibration: CalibrationFiles,
    pub views: Views,
    pub patterns: Patterns,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFiles {
    pub camera: PathBuf,
    pub screen: PathBuf,
    pub turntable: PathBuf,
    /// Per-view world → camera poses that replace the turntable's (imported scans).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub poses: Option<PathBuf>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Views {
    pub angles_deg: Vec<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Patterns {
    pub kind: PatternKind,
    pub width: u32,
    pub height: u32,
    /// Optional phase-shift images after the Gray code.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase_shift: Option<PhaseShift>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PatternKind {
    Graycode,
}

/// A scan folder with its configuration and calibration loaded and checked.
#[derive(Clone, Debug)]
// A private field rather than #[non_exhaustive]: it also keeps the rest of the crate from
// building a scan without its checks.
#[allow(clippy::manual_non_exhaustive)]
pub struct Scan {
    pub dir: PathBuf,
    pub config: ScanConfig,
    pub camera: Camera,
    pub screen: Screen,
    pub turntable: Turntable,
    /// The views' poses when `calibration.poses` names a file (else the turntable's).
    pub poses: Option<Vec<Isometry3<f64>>>,
    /// Only [`Scan::open`] and [`Scan::new`] make a scan: they check that its parts agree.
    _checked: (),
}

/// Why a scan folder cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    #[error("cannot read {path}: {cause}")]
    Read {
        path: PathBuf,
        cause: std::io::Error,
    },
    #[error("{path}: {msg}")]
    Config { path: PathBuf, msg: String },
    #[error(
        "{dir} is not a scan folder: it has no scan.toml (a scan folder comes from `glasscan \
         capture`, `simulate` or `import-drt`; the README's scan format describes it)"
    )]
    NotAScan { dir: PathBuf },
    #[error(transparent)]
    Calibration(#[from] calib_io::CalibError),
    #[error("cannot write {path}: {cause}")]
    Write {
        path: PathBuf,
        cause: std::io::Error,
    },
}

/// The object's refractive index as `scan.toml` (or `reconstruct --ior`) gives it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "IorToml", into = "IorToml")]
pub enum Ior {
    Known(f64),
    /// Unknown: `reconstruct` estimates it with the shape, within [lo, hi].
    Auto {
        lo: f64,
        hi: f64,
    },
}

/// The range `ior = "auto"` searches: crown and borosilicate glasses, quartz, acrylic and most
/// casting resins (1.45–1.60), with a margin.
pub const AUTO_IOR_RANGE: (f64, f64) = (1.40, 1.70);

/// How `ior` is written in TOML: a number, "auto", or { auto = [lo, hi] }.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum IorToml {
    Number(f64),
    Word(String),
    Range { auto: [f64; 2] },
}

impl TryFrom<IorToml> for Ior {
    type Error = String;
    fn try_from(t: IorToml) -> Result<Self, String> {
        match t {
            IorToml::Number(v) => Ior::known(v),
            IorToml::Word(w) if w == "auto" => Ok(Ior::Auto {
                lo: AUTO_IOR_RANGE.0,
                hi: AUTO_IOR_RANGE.1,
            }),
            IorToml::Word(w) => Err(format!(
                "ior = \"{w}\": give the refractive index (glass ≈ 1.5), \"auto\", or {{ auto = [lo, hi] }}"
            )),
            IorToml::Range { auto: [lo, hi] } => Ior::auto(lo, hi),
        }
    }
}

impl From<Ior> for IorToml {
    fn from(i: Ior) -> Self {
        match i {
            Ior::Known(v) => IorToml::Number(v),
            Ior::Auto { lo, hi } => IorToml::Range { auto: [lo, hi] },
        }
    }
}

impl Ior {
    /// A known index, checked: above 1 (air), at most [`MAX_IOR`].
    pub fn known(v: f64) -> Result<Self, String> {
        if v > 1.0 && v <= MAX_IOR {
            Ok(Ior::Known(v))
        } else {
            Err(format!(
                "ior = {}: a solid transparent object's refractive index lies in (1, {MAX_IOR}] (glass ≈ 1.5)",
                crate::util::short_number(v)
            ))
        }
    }

    /// An index to estimate within [lo, hi], checked.
    pub fn auto(lo: f64, hi: f64) -> Result<Self, String> {
        let (Ok(_), Ok(_)) = (Ior::known(lo), Ior::known(hi)) else {
            return Err(format!(
                "ior = {{ auto = [{}, {}] }}: both ends must lie in (1, {MAX_IOR}]",
                crate::util::short_number(lo),
                crate::util::short_number(hi)
            ));
        };
        if lo < hi {
            Ok(Ior::Auto { lo, hi })
        } else {
            Err(format!(
                "ior = {{ auto = [{}, {}] }}: give the range's lower end first",
                crate::util::short_number(lo),
                crate::util::short_number(hi)
            ))
        }
    }

    /// The index a run starts from, and the one steps that need a single value (the decoder's
    /// Fresnel loss) use: the known one, or the middle of the range.
    pub fn nominal(&self) -> f64 {
        match *self {
            Ior::Known(v) => v,
            Ior::Auto { lo, hi } => 0.5 * (lo + hi),
        }
    }

    /// The range the index may take: [v, v] when known.
    pub fn range(&self) -> (f64, f64) {
        match *self {
            Ior::Known(v) => (v, v),
            Ior::Auto { lo, hi } => (lo, hi),
        }
    }

    /// Whether the run estimates it.
    pub fn is_auto(&self) -> bool {
        matches!(self, Ior::Auto { .. })
    }
}

impl std::str::FromStr for Ior {
    type Err = String;
    /// `1.52`, `auto`, or `auto:1.45:1.60` (the command line's form).
    fn from_str(s: &str) -> Result<Self, String> {
        let s = s.trim();
        if s == "auto" {
            return IorToml::Word(s.into()).try_into();
        }
        if let Some(range) = s.strip_prefix("auto:") {
            let ends: Vec<f64> = range
                .split(':')
                .filter_map(|x| x.trim().parse().ok())
                .collect();
            return match ends[..] {
                [lo, hi] => Ior::auto(lo, hi),
                _ => Err(format!(
                    "--ior {s}: give auto:LO:HI, such as auto:1.45:1.60"
                )),
            };
        }
        match s.parse::<f64>() {
            Ok(v) => Ior::known(v),
            Err(_) => Err(format!(
                "--ior {s}: give the refractive index (glass ≈ 1.5), auto, or auto:LO:HI"
            )),
        }
    }
}

/// The largest refractive index a scan may give (the densest glasses and crystals are below 2.5;
/// diamond 2.42).
pub const MAX_IOR: f64 = 4.0;

/// The most views a scan may have.
pub const MAX_VIEWS: usize = 3600;

/// The largest turntable angle a scan may give, degrees (ten turns either way).
pub const MAX_ANGLE_DEG: f64 = 3600.0;

/// Refuses capture folders (`captures/view_NNN`) beyond the views `scan.toml` lists: a view
/// without an angle would be silently left out.
fn check_view_folders(dir: &Path, views: usize) -> Result<(), ScanError> {
    let captures = dir.join("captures");
    let Ok(entries) = std::fs::read_dir(&captures) else {
        return Ok(());
    };
    let beyond = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            name.strip_prefix("view_")?.parse::<usize>().ok()
        })
        .filter(|&k| k >= views)
        .min();
    match beyond {
        Some(k) => Err(ScanError::Config {
            path: dir.join("scan.toml"),
            msg: format!(
                "views.angles_deg lists {views} angles but {} exists: give one angle per captures/view_NNN folder",
                captures.join(format!("view_{k:03}")).display()
            ),
        }),
        None => Ok(()),
    }
}

impl ScanConfig {
    /// Reads and checks `dir/scan.toml` (not the calibration files it names).
    pub fn load(dir: &Path) -> Result<Self, ScanError> {
        let path = dir.join("scan.toml");
        let text = std::fs::read_to_string(&path).map_err(|cause| match cause.kind() {
            std::io::ErrorKind::NotFound => ScanError::NotAScan {
                dir: dir.to_path_buf(),
            },
            _ => ScanError::Read {
                path: path.clone(),
                cause,
            },
        })?;
        let config: ScanConfig = toml::from_str(&text).map_err(|e| ScanError::Config {
            path: path.clone(),
            msg: e.message().to_string()
                + &e.span()
                    .map_or(String::new(), |s| format!(" (at byte {})", s.start)),
        })?;
        let bad = |msg: String| ScanError::Config {
            path: path.clone(),
            msg,
        };
        let angles = &config.views.angles_deg;
        if angles.is_empty() || angles.len() > MAX_VIEWS {
            return Err(bad(format!(
                "views.angles_deg lists {} angles: give 1 to {MAX_VIEWS}, one per view",
                angles.len()
            )));
        }
        if let Some(a) = angles
            .iter()
            .find(|a| a.is_nan() || a.abs() > MAX_ANGLE_DEG)
        {
            return Err(bad(format!(
                "views.angles_deg holds {}: turntable angles are degrees within ±{MAX_ANGLE_DEG}",
                crate::util::short_number(*a)
            )));
        }
        if let Some(b) = config.blur_px.filter(|b| !(0.0..=MAX_BLUR_PX).contains(b)) {
            return Err(bad(format!(
                "blur_px = {}: the camera's blur is a Gaussian's σ in camera pixels, 0 to {MAX_BLUR_PX} (leave it out for a sharp camera)",
                crate::util::short_number(b)
            )));
        }
        if let Some(p) = config.patterns.phase_shift {
            if !(3..=64).contains(&p.steps) || !(4..=65_536).contains(&p.period_px) {
                return Err(bad(format!(
                    "phase_shift needs steps in 3..=64 and period_px in 4..=65536, got {} and {}",
                    p.steps, p.period_px
                )));
            }
        }
        Ok(config)
    }

    /// The pattern set.
    pub fn graycode(&self) -> GrayCode {
        GrayCode {
            width: self.patterns.width,
            height: self.patterns.height,
        }
    }
}

/// Refuses a monitor the camera cannot see the patterns on: behind the camera, or showing the
/// camera its back (its z axis, x right × y down, must point away from the camera).
fn check_monitor_placement(screen: &Screen) -> Result<(), String> {
    let centre = screen.point(
        (screen.width_px as f64 - 1.0) / 2.0,
        (screen.height_px as f64 - 1.0) / 2.0,
    );
    if centre.z <= 0.0 {
        return Err(format!(
            "the monitor lies behind the camera (its centre at z = {:.1} mm in the camera frame): \
             check translation_mm (camera frame, mm)",
            centre.z
        ));
    }
    let normal = screen.pose.rotation * nalgebra::Vector3::z();
    if normal.dot(&centre.coords) <= 0.0 {
        return Err(
            "the monitor shows the camera its back (its z axis points towards the camera): check \
             rotation (monitor frame → camera frame; monitor x right, y down)"
                .into(),
        );
    }
    Ok(())
}

impl Scan {
    /// Loads `dir/scan.toml` and the calibration files it names, and checks that they agree.
    pub fn open(dir: &Path) -> Result<Self, ScanError> {
        let config = ScanConfig::load(dir)?;
        check_view_folders(dir, config.views.angles_deg.len())?;
        let c = &config.calibration;
        let camera = calib_io::read_camera(&dir.join(&c.camera))?;
        let screen = calib_io::read_screen(&dir.join(&c.screen))?;
        let axis = calib_io::read_turntable_axis(&dir.join(&c.turntable))?;
        let poses = match &c.poses {
            Some(p) => Some(calib_io::read_view_poses(&dir.join(p))?),
            None => None,
        };
        Self::new(dir, config, camera, screen, axis, poses)
    }

    /// A scan in `dir` from its parts (the turntable's axis point, mm, and direction, camera
    /// frame), checked as [`Scan::open`] checks a folder: patterns the size of the screen, a
    /// monitor in front of the camera facing it, an axis in front of the camera and not through
    /// it, and a pose per view.
    pub fn new(
        dir: &Path,
        config: ScanConfig,
        camera: Camera,
        screen: Screen,
        (axis_point, axis_dir): (Point3<f64>, Unit<Vector3<f64>>),
        poses: Option<Vec<Isometry3<f64>>>,
    ) -> Result<Self, ScanError> {
        let c = &config.calibration;
        let bad = |file: &Path, msg: String| ScanError::Config {
            path: dir.join(file),
            msg,
        };
        if (config.patterns.width, config.patterns.height) != (screen.width_px, screen.height_px) {
            return Err(bad(
                Path::new("scan.toml"),
                format!(
                    "patterns are {}×{} but the screen ({}) is {}×{}",
                    config.patterns.width,
                    config.patterns.height,
                    c.screen.display(),
                    screen.width_px,
                    screen.height_px
                ),
            ));
        }
        check_monitor_placement(&screen).map_err(|msg| bad(&c.screen, msg))?;
        if axis_point.z <= 0.0 {
            return Err(bad(
                &c.turntable,
                format!(
                    "the turntable axis point lies behind the camera (z = {:.1} mm in the camera \
                     frame): check axis_point_mm",
                    axis_point.z
                ),
            ));
        }
        let turntable = Turntable {
            axis_point,
            axis_dir,
            angles_deg: config.views.angles_deg.clone(),
        };
        if turntable.base_pose().is_none() {
            return Err(bad(
                Path::new("scan.toml"),
                "inconsistent calibration: the camera lies on the turntable axis".into(),
            ));
        }
        if let (Some(p), Some(poses)) = (&c.poses, &poses) {
            if poses.len() != config.views.angles_deg.len() {
                return Err(bad(
                    Path::new("scan.toml"),
                    format!(
                        "{} holds {} view poses for {} views",
                        p.display(),
                        poses.len(),
                        config.views.angles_deg.len()
                    ),
                ));
            }
        }
        let poses = poses.filter(|_| c.poses.is_some());
        Ok(Self {
            dir: dir.to_path_buf(),
            config,
            camera,
            screen,
            turntable,
            poses,
            _checked: (),
        })
    }

    /// The files and folders a command reading this scan reads: `scan.toml`, the calibration
    /// files, `decoded/` and `captures/` (read whole). No output may be, hold or lie in one.
    pub fn input_paths(&self) -> Vec<PathBuf> {
        let c = &self.config.calibration;
        let mut paths = vec![self.dir.join("scan.toml")];
        paths.extend(
            [
                Some(&c.camera),
                Some(&c.screen),
                Some(&c.turntable),
                c.poses.as_ref(),
            ]
            .into_iter()
            .flatten()
            .map(|f| self.dir.join(f)),
        );
        paths.push(self.dir.join("decoded"));
        paths.push(self.dir.join("captures"));
        paths
    }

    /// Named warnings about a rig that works but looks wrong: the turntable axis projects
    /// outside the image (the object is probably out of view) or far from its centre.
    pub fn plausibility_warnings(&self) -> Vec<String> {
        let c = &self.camera;
        let (w, h) = (c.width as f64, c.height as f64);
        match c.project(&self.turntable.axis_point) {
            None => vec!["the turntable axis point projects behind the camera".into()],
            Some(p) if p.x < 0.0 || p.y < 0.0 || p.x > w || p.y > h => vec![format!(
                "the turntable axis projects outside the image (at pixel ({:.0}, {:.0}) of {w}×{h}): the object is probably out of view; check turntable.yml",
                p.x, p.y
            )],
            Some(p) if (p.x - w / 2.0).abs() > 0.3 * w => vec![format!(
                "the turntable axis projects {:.0} px from the image's centre column: the object will leave the view as it turns; centre the turntable",
                (p.x - w / 2.0).abs()
            )],
            Some(_) => Vec::new(),
        }
    }

    /// Writes `scan.toml` and the calibration files into `self.dir` (atomically each).
    pub fn save(&self) -> Result<(), ScanError> {
        let c = &self.config.calibration;
        calib_io::write_camera(&self.dir.join(&c.camera), &self.camera, 0.0, None)?;
        calib_io::write_screen(&self.dir.join(&c.screen), &self.screen)?;
        calib_io::write_turntable_axis(
            &self.dir.join(&c.turntable),
            &self.turntable.axis_point,
            &self.turntable.axis_dir,
        )?;
        if let (Some(p), Some(poses)) = (&c.poses, &self.poses) {
            calib_io::write_view_poses(&self.dir.join(p), poses)?;
        }
        let path = self.dir.join("scan.toml");
        let text = toml::to_string_pretty(&self.config).expect("a scan config serialises");
        write_atomic(&path, |w| {
            w.write_all(
                format!("# glasscan scan folder (see README: scan folder)\n{text}").as_bytes(),
            )
        })
        .map_err(|cause| ScanError::Write { path, cause })
    }

    /// The pattern set.
    pub fn graycode(&self) -> GrayCode {
        self.config.graycode()
    }

    /// World → camera transform of every view.
    pub fn view_poses(&self) -> Vec<Isometry3<f64>> {
        match &self.poses {
            Some(p) => p.clone(),
            None => self.turntable.view_poses().expect("checked when opened"),
        }
    }

    /// Folder of view `k`'s captures.
    pub fn view_dir(&self, k: usize) -> PathBuf {
        self.dir.join("captures").join(format!("view_{k:03}"))
    }

    /// Folder of the background captures.
    pub fn background_dir(&self) -> PathBuf {
        background_dir(&self.dir)
    }
}

/// Folder of the background captures of the scan folder `dir`.
pub fn background_dir(dir: &Path) -> PathBuf {
    dir.join("captures").join("background")
}
