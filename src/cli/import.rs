//! `glasscan import-drt FILE.h5 -o SCAN`.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, ValueEnum};

use glasscan::import::drt::{import_drt, DrtCamera, DRT_VIEWS};
use glasscan::util::paths::ensure_output_spares_inputs;

#[derive(Args, Debug)]
pub struct ImportDrtArgs {
    /// DRT's HDF5 capture file of one object.
    pub file: PathBuf,
    /// The scan folder to write (decoded form with calibration).
    #[arg(short, long, visible_alias = "out")]
    pub output: PathBuf,
    /// The camera that made the file (default: from the image size and the keys present).
    #[arg(long, value_enum)]
    pub camera: Option<CameraArg>,
    /// Refractive index of the object (DRT's files do not record it).
    #[arg(long, default_value_t = 1.4723, value_parser = super::common::ior)]
    pub ior: f64,
    /// Replace a non-empty output folder (whole, once the import succeeded).
    #[arg(long)]
    pub force: bool,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum CameraArg {
    Pointgrey,
    Redmi,
}

pub fn run(a: &ImportDrtArgs) -> Result<()> {
    let bar = super::common::bar("import", DRT_VIEWS);
    let camera = a.camera.map(|c| match c {
        CameraArg::Pointgrey => DrtCamera::PointGrey,
        CameraArg::Redmi => DrtCamera::Redmi,
    });
    let t0 = std::time::Instant::now();
    ensure_output_spares_inputs(&a.output, "--output", &[&a.file])?;
    let r = import_drt(&a.file, &a.output, camera, a.ior, a.force, |_| bar.inc(1))?;
    bar.finish_and_clear();
    outln!(
        "imported {} ({:?}, {}×{}, {DRT_VIEWS} views) into {} in {:.1} s",
        a.file.display(),
        r.camera,
        r.width,
        r.height,
        a.output.display(),
        t0.elapsed().as_secs_f64()
    );
    outln!(
        "{} object pixels, {} with a monitor point ({:.1} %); monitor points within {:.3} mm (RMS) of one plane",
        r.object_pixels,
        r.rays,
        100.0 * r.rays as f64 / r.object_pixels.max(1) as f64,
        r.plane_rms_mm
    );
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    if r.camera == DrtCamera::PointGrey {
        outln!(
            "per-pixel ray origins within {:.3} mm of their view's camera centre",
            r.max_origin_offset_mm
        );
    }
    Ok(())
}
