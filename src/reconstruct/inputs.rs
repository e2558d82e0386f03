//! What a run reads from the scan, loaded once: refraction targets, silhouettes, and the
//! fingerprint of the files they came from.

use super::config::Settings;
use crate::loss::refraction::ViewTargets;
use crate::scan::silhouette::Silhouette;
use anyhow::{bail, Result};

/// What the optimisation reads from the scan, loaded once.
pub struct Inputs {
    pub ior: f64,
    pub targets: Vec<ViewTargets>,
    pub silhouettes: Vec<Silhouette>,
    /// What the inputs were read from ([`fingerprint`]); a run resumes only from the same.
    pub fingerprint: super::fingerprint::Fingerprint,
}

/// Loads the decoded targets (weighted by `settings.target_weights`) and silhouettes of `views`,
/// with warnings: views without refraction data, a per-bit term without contrasts to read.
pub fn load_inputs(
    scan: &crate::scan::Scan,
    views: &[usize],
    settings: &Settings,
) -> Result<(Inputs, Vec<String>)> {
    let weights = settings.target_weights;
    let (silhouettes, mut warnings) = crate::hull::silhouettes(scan, views)?;
    let (targets, skipped) = crate::loss::targets::scan_targets(scan, views, weights)?;
    if targets.is_empty() {
        bail!("no decoded view to reconstruct from");
    }
    let decoded: usize = targets.iter().map(|t| t.pixels.len()).sum();
    if decoded == 0 {
        bail!("no object pixel has a decoded monitor point: check the decode (decoded/preview/)");
    }
    warnings.extend(
        skipped
            .iter()
            .map(|k| format!("view {k}: no refraction data (decode skipped it)")),
    );
    let has_bits = targets.iter().any(ViewTargets::has_measured_bits);
    if settings.weight_bits > 0.0 && !has_bits && scan.dir.join("captures").is_dir() {
        warnings.push(format!(
            "the decoded data has no Gray-bit contrasts (decoded by an earlier glasscan): the per-bit term is idle; run `glasscan decode {}` again to use it",
            scan.dir.display()
        ));
    }
    Ok((
        Inputs {
            ior: scan.config.ior,
            targets,
            silhouettes,
            fingerprint: super::fingerprint::of_scan(scan, views)?,
        },
        warnings,
    ))
}
