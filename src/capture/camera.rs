//! The camera, through OpenCV videoio: a device, or a recorded sequence replayed frame by frame.

use anyhow::{bail, Context, Result};
use opencv::core::{Mat, MatTraitConst};
use opencv::prelude::*;
use opencv::videoio::{self, VideoCapture};

/// Where frames come from.
#[derive(Clone, Debug, PartialEq)]
pub enum CameraSource {
    /// A device index (0 for the first camera).
    Device(i32),
    /// An image sequence (`frames/%04d.png`) or a video file: frame k is the capture's k-th image.
    Files(String),
}

impl CameraSource {
    /// A whole number is a device index; anything else a file pattern or video.
    pub fn parse(s: &str) -> Result<Self, String> {
        if s.is_empty() {
            return Err("give a device index (0) or a file pattern such as frames/%04d.png".into());
        }
        Ok(match s.parse::<i32>() {
            Ok(i) if i >= 0 => CameraSource::Device(i),
            Ok(i) => return Err(format!("device index {i}: indices start at 0")),
            Err(_) => CameraSource::Files(s.to_string()),
        })
    }
}

/// An open camera.
pub struct Camera {
    capture: VideoCapture,
    replay: bool,
    flush_frames: u32,
    expect_size: Option<(u32, u32)>,
}

impl Camera {
    /// Opens `source`; a device is asked for `expect_size` when given.
    pub fn open(
        source: &CameraSource,
        flush_frames: u32,
        expect_size: Option<(u32, u32)>,
    ) -> Result<Self> {
        let (capture, replay) = match source {
            CameraSource::Device(i) => (VideoCapture::new(*i, videoio::CAP_ANY)?, false),
            CameraSource::Files(p) => (VideoCapture::from_file(p, videoio::CAP_ANY)?, true),
        };
        if !capture.is_opened()? {
            bail!(
                "cannot open the camera {}: {}",
                describe(source),
                match source {
                    CameraSource::Device(_) => "check that it is plugged in and not in use (ls /dev/video*)",
                    CameraSource::Files(_) => "no readable image or video there (a sequence is named like frames/%04d.png)",
                }
            );
        }
        let mut camera = Camera {
            capture,
            replay,
            flush_frames,
            expect_size,
        };
        if let (false, Some((w, h))) = (replay, expect_size) {
            camera
                .capture
                .set(videoio::CAP_PROP_FRAME_WIDTH, w as f64)?;
            camera
                .capture
                .set(videoio::CAP_PROP_FRAME_HEIGHT, h as f64)?;
        }
        Ok(camera)
    }

    /// The `k`-th image of the capture, 8-bit grey: a device's next frame after the flush, or
    /// a recording's frame `k`.
    pub fn grab(&mut self, k: usize) -> Result<Mat> {
        let mut frame = Mat::default();
        if self.replay {
            self.capture.set(videoio::CAP_PROP_POS_FRAMES, k as f64)?;
        } else {
            for _ in 0..self.flush_frames {
                self.capture.grab()?;
            }
        }
        if !self.capture.read(&mut frame)? || frame.empty() {
            bail!("the camera gave no frame");
        }
        let grey = to_grey(&frame)?;
        self.check_size(&grey)?;
        Ok(grey)
    }

    fn check_size(&self, img: &Mat) -> Result<()> {
        let got = (img.cols() as u32, img.rows() as u32);
        match self.expect_size {
            Some(want) if want != got => bail!(
                "the camera gives {}×{} images but the scan's camera file says {}×{}: set the camera's resolution, or calibrate it at this one",
                got.0,
                got.1,
                want.0,
                want.1
            ),
            _ => Ok(()),
        }
    }
}

/// 8-bit grey from whatever the camera gives (grey, BGR, BGRA; 8 or 16 bits).
fn to_grey(frame: &Mat) -> Result<Mat> {
    use opencv::imgproc::{cvt_color, COLOR_BGR2GRAY, COLOR_BGRA2GRAY};
    let mut grey = match frame.channels() {
        1 => frame.try_clone()?,
        3 | 4 => {
            let code = if frame.channels() == 3 {
                COLOR_BGR2GRAY
            } else {
                COLOR_BGRA2GRAY
            };
            let mut g = Mat::default();
            cvt_color(frame, &mut g, code, 0).context("cannot convert the frame to grey")?;
            g
        }
        c => bail!("the camera gives frames with {c} channels (1, 3 or 4 expected)"),
    };
    if grey.depth() != opencv::core::CV_8U {
        let mut g8 = Mat::default();
        grey.convert_to(&mut g8, opencv::core::CV_8U, 1.0 / 257.0, 0.0)?;
        grey = g8;
    }
    Ok(grey)
}

fn describe(source: &CameraSource) -> String {
    match source {
        CameraSource::Device(i) => format!("device {i}"),
        CameraSource::Files(p) => format!("'{p}'"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sources_parse_as_devices_or_files() {
        assert_eq!(CameraSource::parse("0"), Ok(CameraSource::Device(0)));
        assert_eq!(
            CameraSource::parse("frames/%04d.png"),
            Ok(CameraSource::Files("frames/%04d.png".into()))
        );
        assert!(CameraSource::parse("-1").is_err());
        assert!(CameraSource::parse("").is_err());
    }
}
