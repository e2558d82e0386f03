//! Image output through OpenCV, atomic like every output.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use opencv::core::{Mat, Point, Scalar, Vector};
use opencv::imgproc::{put_text, FONT_HERSHEY_SIMPLEX, LINE_AA};

/// Writes an image (8- or 16-bit PNG, fast compression) atomically: OpenCV writes a temporary
/// file beside `path`, which is then renamed.
pub fn write_png(path: &Path, img: &impl opencv::core::ToInputArray) -> Result<()> {
    let tmp: PathBuf = path.with_extension("tmp.png");
    let params = Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_PNG_COMPRESSION, 1]);
    if !opencv::imgcodecs::imwrite(&tmp, img, &params)
        .with_context(|| format!("cannot write {}", path.display()))?
    {
        bail!("OpenCV could not write {}", path.display());
    }
    std::fs::rename(&tmp, path).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// Writes `data` (row-major pixels of `width` × `height`, any OpenCV pixel type) as a PNG.
pub fn write_pixels<T: opencv::core::DataType>(
    path: &Path,
    width: u32,
    height: u32,
    data: &[T],
) -> Result<()> {
    let mat = opencv::core::Mat::new_rows_cols_with_data(height as i32, width as i32, data)?;
    write_png(path, &mat)
}

/// Draws `s` on a plot with its baseline starting at `at` (OpenCV's simplex font, `scale` × its
/// size, antialiased), in BGR `colour`.
pub fn label(img: &mut Mat, s: &str, at: Point, scale: f64, colour: Scalar) -> Result<()> {
    put_text(
        img,
        s,
        at,
        FONT_HERSHEY_SIMPLEX,
        scale,
        colour,
        1,
        LINE_AA,
        false,
    )?;
    Ok(())
}
