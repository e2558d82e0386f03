//! `glasscan patterns --screen 1920x1080 --out DIR`.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

use crate::patterns::GrayCode;

#[derive(Args, Debug)]
pub struct PatternsArgs {
    /// Monitor resolution, WIDTHxHEIGHT pixels.
    #[arg(long, value_parser = super::simulate::parse_size)]
    pub screen: (u32, u32),
    /// Folder for the images.
    #[arg(long)]
    pub out: PathBuf,
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
    outln!(
        "wrote {} Gray-code images + white + black for a {}x{} monitor into {} (order in ORDER.txt)",
        code.pattern_count(),
        code.width,
        code.height,
        a.out.display()
    );
    Ok(())
}
