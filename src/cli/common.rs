//! What several subcommands share: argument parsers that range-check at parse time, view lists,
//! and progress bars.

use anyhow::{bail, Result};
use glasscan::util::progress::StepProgress;
use indicatif::{ProgressBar, ProgressStyle};

use glasscan::loss::Robust;
use glasscan::reconstruct::{IterationRecord, Progress, StageReport};
use glasscan::util::fixed::MAX_SIDE_PX;

/// Parses "0-9,12" (or "all", or nothing) into sorted view indices below `count`.
pub fn parse_views(spec: Option<&str>, count: usize) -> Result<Vec<usize>> {
    let Some(spec) = spec.filter(|s| *s != "all") else {
        return Ok((0..count).collect());
    };
    let mut views = Vec::new();
    for part in spec.split(',') {
        let (a, b) = part.split_once('-').unwrap_or((part, part));
        let (a, b): (usize, usize) = match (a.trim().parse(), b.trim().parse()) {
            (Ok(a), Ok(b)) if a <= b => (a, b),
            _ => bail!("--views '{spec}': '{part}' is not an index or a range like 3-7"),
        };
        if b >= count {
            bail!(
                "--views '{spec}': the scan has views 0-{}",
                count.saturating_sub(1)
            );
        }
        views.extend(a..=b);
    }
    views.sort_unstable();
    views.dedup();
    Ok(views)
}

/// Parses WIDTHxHEIGHT, both from 1 to [`MAX_SIDE_PX`].
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{s}': expected WIDTHxHEIGHT, e.g. 1280x960"))?;
    let p = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("'{s}': '{v}' is not a whole number"))
    };
    let (w, h) = (p(w)?, p(h)?);
    if w == 0 || h == 0 || w > MAX_SIDE_PX || h > MAX_SIDE_PX {
        return Err(format!(
            "'{s}': both sizes must lie between 1 and {MAX_SIDE_PX} pixels"
        ));
    }
    Ok((w, h))
}

/// Opens a scan folder and prints the rig's plausibility warnings.
pub fn open_scan(dir: &std::path::Path) -> Result<glasscan::scan::Scan> {
    let scan = glasscan::scan::Scan::open(dir)?;
    for w in scan.plausibility_warnings() {
        eprintln!("warning: {w}");
    }
    Ok(scan)
}

/// A finite number parsed from `s`.
fn finite(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(format!("'{s}' is not a finite number")),
    }
}

/// A positive, finite number.
pub fn positive(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v > 0.0 {
        Ok(v)
    } else {
        Err(format!(
            "{}: it must be positive",
            glasscan::util::short_number(v)
        ))
    }
}

/// A finite number ≥ 0.
pub fn non_negative(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v >= 0.0 {
        Ok(v)
    } else {
        Err(format!(
            "{}: it must not be negative",
            glasscan::util::short_number(v)
        ))
    }
}

/// A share in [0, 1].
pub fn share(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if (0.0..=1.0).contains(&v) {
        Ok(v)
    } else {
        Err(format!(
            "{}: it must lie in [0, 1]",
            glasscan::util::short_number(v)
        ))
    }
}

/// A robust loss: `l2`, `huber:δ` or `cauchy:δ` with δ > 0.
pub fn parse_robust(s: &str) -> Result<Robust, String> {
    let scale = |d: &str| match d.parse::<f64>() {
        Ok(v) if v > 0.0 && v.is_finite() => Ok(v),
        _ => Err(format!("'{d}': the scale δ must be a positive number")),
    };
    match s.split_once(':') {
        None if s.eq_ignore_ascii_case("l2") => Ok(Robust::L2),
        Some((k, d)) if k.eq_ignore_ascii_case("huber") => scale(d).map(Robust::Huber),
        Some((k, d)) if k.eq_ignore_ascii_case("cauchy") => scale(d).map(Robust::Cauchy),
        _ => Err(format!("'{s}': use l2, huber:δ or cauchy:δ")),
    }
}

/// A share in (0, 1].
pub fn positive_share(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v > 0.0 && v <= 1.0 {
        Ok(v)
    } else {
        Err(format!(
            "{}: it must lie in (0, 1]",
            glasscan::util::short_number(v)
        ))
    }
}

/// A solid object's refractive index: above 1 (air), at most [`glasscan::scan::MAX_IOR`].
pub fn ior(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    glasscan::scan::Ior::known(v).map(|_| v)
}

/// A share in [0, 1] as f32 (decoder thresholds).
pub fn share_f32(s: &str) -> Result<f32, String> {
    share(s).map(|v| v as f32)
}

/// A positive, finite number as f32.
pub fn positive_f32(s: &str) -> Result<f32, String> {
    positive(s).map(|v| v as f32)
}

/// A threshold that is either chosen by glasscan (`auto`) or a share in (0, 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AutoShare(pub Option<f32>);

/// Parses `auto` (any case) or a share in (0, 1).
pub fn auto_or_open_share(s: &str) -> Result<AutoShare, String> {
    if s.trim().eq_ignore_ascii_case("auto") {
        return Ok(AutoShare(None));
    }
    let v = finite(s).map_err(|_| format!("'{s}': expected auto or a number in (0, 1)"))?;
    if v > 0.0 && v < 1.0 {
        Ok(AutoShare(Some(v as f32)))
    } else {
        Err(format!(
            "{}: it must lie in (0, 1), or be auto",
            glasscan::util::short_number(v)
        ))
    }
}

/// Parses `auto` (any case) or a positive size in mm: a hull's voxel.
pub fn voxel_size(s: &str) -> Result<glasscan::hull::VoxelSize, String> {
    if s.trim().eq_ignore_ascii_case("auto") {
        return Ok(glasscan::hull::VoxelSize::Auto);
    }
    let v = finite(s).map_err(|_| format!("'{s}': expected auto or a size in mm"))?;
    if v > 0.0 {
        Ok(glasscan::hull::VoxelSize::Mm(v))
    } else {
        Err(format!(
            "{}: it must be a positive size, or auto",
            glasscan::util::short_number(v)
        ))
    }
}

/// A progress bar of `len` steps whose line starts with `what`.
pub fn bar(what: &str, len: usize) -> ProgressBar {
    ProgressBar::new(len as u64).with_style(
        ProgressStyle::with_template(&format!(
            "{what} {{msg}} [{{bar:40}}] {{pos}}/{{len}} ({{eta}})"
        ))
        .expect("a valid template"),
    )
}

/// A progress bar that draws the library's [`StepProgress`] reports: the phase as its message.
pub struct Bar(pub ProgressBar);

impl StepProgress for Bar {
    fn phase(&self, name: &str, total: u64) {
        self.0.set_message(name.to_string());
        self.0.set_length(total);
        self.0.set_position(0);
    }
    fn advance(&self, n: u64) {
        self.0.inc(n);
    }
    fn grow(&self, more: u64) {
        self.0.inc_length(more);
    }
}

/// The progress of a reconstruction: a bar per stage (loss, ETA) and a line per finished stage.
pub struct StageBars {
    pub bar: ProgressBar,
}

impl StageBars {
    pub fn new() -> Self {
        Self {
            bar: ProgressBar::new(0).with_style(
                ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} ({eta})")
                    .expect("static template"),
            ),
        }
    }
}

impl Progress for StageBars {
    fn stage_start(
        &self,
        stage: usize,
        stages: usize,
        edge_mm: f64,
        faces: usize,
        iterations: usize,
    ) {
        self.bar.reset();
        self.bar.set_length(iterations as u64);
        self.bar.set_prefix(format!(
            "stage {}/{stages} ({edge_mm:.2} mm, {faces} faces)",
            stage + 1
        ));
    }
    fn iteration(&self, r: &IterationRecord) {
        self.bar.set_message(format!("loss {:.3e}", r.total));
        self.bar.inc(1);
    }
    fn note(&self, text: &str) {
        self.bar.suspend(|| eprintln!("{text}"));
    }
    fn stage_end(&self, r: &StageReport) {
        self.bar.suspend(|| {
            eprintln!(
                "stage {:>2}: edge {} mm, {} faces, {:.1} s, loss {:.3e} (refraction {:.3e}, silhouette {:.3e}, smoothness {:.3e}{}), rays used {}, dropped {}{}",
                r.stage + 1,
                glasscan::util::mm(r.edge_mm, 2),
                r.faces,
                r.seconds,
                r.last.total,
                r.last.refraction,
                r.last.silhouette,
                r.last.smoothness,
                if r.last.membrane > 0.0 {
                    format!(", membrane {:.3e} on the {:.0} % of the vertices no ray saw", r.last.membrane, 100.0 * r.unseen_share)
                } else {
                    String::new()
                },
                r.refraction_rays_used,
                r.refraction_drops.total(),
                if r.averaged {
                    ", mesh: the mean of the last iterates"
                } else {
                    ""
                }
            )
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_lists() {
        assert_eq!(parse_views(None, 3).unwrap(), vec![0, 1, 2]);
        assert_eq!(parse_views(Some("2,0-1,1"), 3).unwrap(), vec![0, 1, 2]);
        assert!(parse_views(Some("3"), 3).is_err());
        assert!(parse_views(Some("2-1"), 3).is_err());
        assert!(parse_views(Some("0"), 0).is_err());
    }

    #[test]
    fn numbers_are_range_checked() {
        assert!(positive("nan").is_err() && positive("0").is_err() && positive("1e-3").is_ok());
        assert!(non_negative("-0.5").is_err() && non_negative("0").is_ok());
        assert!(share("2").is_err() && share("1").is_ok() && share("inf").is_err());
        assert_eq!(auto_or_open_share("AUTO").unwrap(), AutoShare(None));
        assert!(auto_or_open_share("-0.5").is_err() && auto_or_open_share("1").is_err());
        assert_eq!(parse_size("640x480").unwrap(), (640, 480));
        assert_eq!(parse_robust("L2"), Ok(Robust::L2));
        assert_eq!(parse_robust("cauchy:0.5"), Ok(Robust::Cauchy(0.5)));
        assert_eq!(parse_robust("huber:2"), Ok(Robust::Huber(2.0)));
        for bad in [
            "cauchy",
            "cauchy:0",
            "huber:-1",
            "huber:nan",
            "tukey:1",
            "l2:1",
        ] {
            assert!(parse_robust(bad).is_err(), "{bad}");
        }
        assert!(parse_size("100000x100000").is_err() && parse_size("0x4").is_err());
    }
}
