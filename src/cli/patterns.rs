//! `glasscan patterns --screen 1920x1080 --out DIR`.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

use crate::patterns::{GrayCode, PhaseShift};

#[derive(Args, Debug)]
pub struct PatternsArgs {
    /// Monitor resolution, WIDTHxHEIGHT pixels.
    #[arg(long, value_parser = super::common::parse_size)]
    pub screen: (u32, u32),
    /// Folder for the images.
    #[arg(long)]
    pub out: PathBuf,
    /// Also write N-step phase-shift images (per axis) after the Gray code.
    #[arg(long = "phase-shift")]
    pub phase_steps: Option<u32>,
    /// Period of the phase-shift sinusoid, monitor pixels.
    #[arg(long = "period-px", default_value_t = 64, requires = "phase_steps")]
    pub period_px: u32,
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
    code.write_images(&a.out)?;
    if let Some(steps) = a.phase_steps {
        let p = PhaseShift {
            steps,
            period_px: a.period_px,
        };
        if steps < 3 || a.period_px < 4 {
            bail!("--phase-shift {steps} --period-px {}: need at least 3 steps and a period of 4 pixels", a.period_px);
        }
        p.write_images(&a.out, code.width, code.height)?;
        outln!("wrote {} phase-shift images (phase_u_*, phase_v_*: {steps} steps, period {} monitor pixels)", p.file_names().len(), a.period_px);
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
