//! The full-screen pattern window on the rig's monitor (OpenCV highgui).

use std::time::Duration;

use anyhow::{bail, Context, Result};
use opencv::core::Mat;
use opencv::highgui;

const NAME: &str = "glasscan patterns";

/// A borderless full-screen window showing one pattern at a time.
pub struct PatternWindow {
    /// The patterns' size, monitor pixels.
    size: (u32, u32),
}

impl PatternWindow {
    /// Opens the window at `origin` (the monitor's top-left on the desktop) and makes it
    /// full-screen there.
    pub fn open(origin: (i32, i32), size: (u32, u32)) -> Result<Self> {
        let has_display = ["DISPLAY", "WAYLAND_DISPLAY"]
            .iter()
            .any(|v| std::env::var_os(v).is_some_and(|s| !s.is_empty()));
        if !has_display {
            bail!("no display to show the patterns on (DISPLAY is not set): run the capture in the rig's desktop session");
        }
        highgui::named_window(NAME, highgui::WINDOW_NORMAL)
            .context("cannot open a window for the patterns (OpenCV highgui)")?;
        highgui::move_window(NAME, origin.0, origin.1)?;
        highgui::set_window_property(
            NAME,
            highgui::WND_PROP_FULLSCREEN,
            highgui::WINDOW_FULLSCREEN as f64,
        )?;
        highgui::wait_key(50)?;
        Ok(PatternWindow { size })
    }

    /// A warning when the window does not cover exactly the patterns' size (the monitor is not
    /// at its native resolution, or the window manager refused full screen): stretched
    /// patterns shift every decoded monitor point.
    pub fn size_warning(&self) -> Option<String> {
        let rect = highgui::get_window_image_rect(NAME).ok()?;
        let got = (rect.width as u32, rect.height as u32);
        (got != self.size).then(|| {
            format!(
                "the pattern window is {}×{} pixels, the patterns {}×{}: run the monitor at its native resolution and check --monitor-origin",
                got.0, got.1, self.size.0, self.size.1
            )
        })
    }

    /// Shows `img` and waits `settle` (at least a millisecond, which lets the window draw).
    pub fn show(&mut self, img: &Mat, settle: Duration) -> Result<()> {
        highgui::imshow(NAME, img).context("cannot show a pattern")?;
        let ms = settle.as_millis().clamp(1, i32::MAX as u128) as i32;
        highgui::wait_key(ms)?;
        Ok(())
    }
}

impl Drop for PatternWindow {
    fn drop(&mut self) {
        let _ = highgui::destroy_window(NAME);
        let _ = highgui::wait_key(1);
    }
}
