//! Image files through OpenCV: read with glasscan's messages, written atomically like every
//! output.

use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use opencv::core::{Mat, MatTraitConst, Point, Scalar, Vector};
use opencv::imgproc::{put_text, FONT_HERSHEY_SIMPLEX, LINE_AA};

use super::atomic::write_atomic;

/// The first 8 bytes of every PNG file.
const PNG_SIGNATURE: &[u8; 8] = b"\x89PNG\r\n\x1a\n";

/// The last 12 bytes of every whole PNG file: its IEND chunk (no data, then its CRC).
const PNG_END: &[u8; 12] = b"\0\0\0\0IEND\xae\x42\x60\x82";

/// Reads an image file with OpenCV's `imread` and `flags`; when it cannot, the error names the
/// file and what is wrong: missing, a PNG cut short (a copy or a capture interrupted; checked
/// first, so that libpng prints none of its own lines), or not an image OpenCV reads.
pub fn read_image(path: &Path, flags: i32) -> Result<Mat> {
    check_png_whole(path)?;
    let m = opencv::imgcodecs::imread(path, flags)
        .with_context(|| format!("cannot read {}", path.display()))?;
    if m.empty() {
        bail!("{}: not a readable image", path.display());
    }
    Ok(m)
}

/// Refuses a missing file and a PNG file that ends before its IEND chunk; anything else is left
/// to the decoder.
fn check_png_whole(path: &Path) -> Result<()> {
    let mut f = std::fs::File::open(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => anyhow!("{}: missing", path.display()),
        _ => anyhow!("cannot read {}: {}", path.display(), e.kind()),
    })?;
    let mut head = [0u8; 8];
    if f.read_exact(&mut head).is_err() || &head != PNG_SIGNATURE {
        return Ok(());
    }
    let mut tail = [0u8; 12];
    let whole =
        f.seek(SeekFrom::End(-12)).is_ok() && f.read_exact(&mut tail).is_ok() && &tail == PNG_END;
    if !whole {
        bail!(
            "{}: a PNG cut short (it ends before its last chunk): copy or capture it again",
            path.display()
        );
    }
    Ok(())
}

/// The width and height a PNG file's header declares; `None` for anything else.
pub fn png_size(path: &Path) -> Option<(u32, u32)> {
    let mut head = [0u8; 24];
    std::fs::File::open(path).ok()?.read_exact(&mut head).ok()?;
    if &head[..8] != PNG_SIGNATURE || &head[12..16] != b"IHDR" {
        return None;
    }
    let be = |b: &[u8]| u32::from_be_bytes(b.try_into().expect("4 bytes"));
    Some((be(&head[16..20]), be(&head[20..24])))
}

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
