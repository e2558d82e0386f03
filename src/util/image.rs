//! Image output through OpenCV, atomic like every output.

use std::path::Path;

use anyhow::{bail, Context, Result};
use opencv::core::{Mat, Point, Scalar, Vector};
use opencv::imgproc::{put_text, FONT_HERSHEY_SIMPLEX, LINE_AA};

use super::atomic::write_atomic;

/// Writes an image (8- or 16-bit PNG, fast compression) atomically: OpenCV encodes it in
/// memory, and the bytes go through [`write_atomic`] (a temporary file beside `path`, renamed).
pub fn write_png(path: &Path, img: &impl opencv::core::ToInputArray) -> Result<()> {
    super::paths::ensure_extension(path, "output", &["png"])?;
    let params = Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_PNG_COMPRESSION, 1]);
    let mut bytes = Vector::<u8>::new();
    if !opencv::imgcodecs::imencode(".png", img, &mut bytes, &params)
        .with_context(|| format!("cannot encode {}", path.display()))?
    {
        bail!("OpenCV could not encode {}", path.display());
    }
    write_atomic(path, |w| w.write_all(bytes.as_slice()))
        .with_context(|| format!("cannot write {}", path.display()))
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
