//! `glasscan patterns --screen 1920x1080 --out DIR`.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

use glasscan::patterns::{GrayCode, PhaseShift};
use glasscan::util::folder::{StagedFolder, FORCE_HINT};

#[derive(Args, Debug)]
pub struct PatternsArgs {
    /// Monitor resolution, WIDTHxHEIGHT pixels.
    #[arg(long, value_parser = super::common::parse_size)]
    pub screen: (u32, u32),
    /// Folder for the images.
    #[arg(short = 'o', long, visible_alias = "output")]
    pub out: PathBuf,
    /// Also write N-step phase-shift images (per axis) after the Gray code.
    #[arg(long = "phase-shift")]
    pub phase_steps: Option<u32>,
    /// Period of the phase-shift sinusoid, monitor pixels.
    #[arg(long = "period-px", default_value_t = 64, requires = "phase_steps")]
    pub period_px: u32,
    /// Replace a non-empty output folder (whole, once the new images are written).
    #[arg(long)]
    pub force: bool,
}

pub fn run(a: &PatternsArgs) -> Result<()> {
    let code = GrayCode {
        width: a.screen.0,
        height: a.screen.1,
    };
    if code.width < 2 || code.height < 2 {
        bail!(
            "--screen {}x{}: a Gray code needs at least 2 pixels each way",
            code.width,
            code.height
        );
    }
    let phase = a.phase_steps.map(|steps| PhaseShift {
        steps,
        period_px: a.period_px,
    });
    if let Some(p) = phase.filter(|p| p.steps < 3 || p.period_px < 4) {
        bail!(
            "--phase-shift {} --period-px {}: need at least 3 steps and a period of 4 pixels",
            p.steps,
            p.period_px
        );
    }
    // Written whole: no image of an earlier set is left beside the new one.
    let staged = StagedFolder::new(&a.out, a.force, FORCE_HINT)?;
    code.write_images(staged.path())?;
    if let Some(p) = phase {
        p.write_images(staged.path(), code.width, code.height)?;
    }
    staged.commit()?;
    if let Some(p) = phase {
        outln!(
            "wrote {} phase-shift images (phase_u_*, phase_v_*: {} steps, period {} monitor pixels)",
            p.file_names().len(),
            p.steps,
            p.period_px
        );
    }
    outln!(
        "wrote {} Gray-code images + white + black for a {}x{} monitor into {} (order in ORDER.txt)",
        code.pattern_count(),
        code.width,
        code.height,
        a.out.display()
    );
    Ok(())
}
