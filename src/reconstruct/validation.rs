//! Held-out views: a share of the scan's views, spread evenly over the turntable, that the
//! optimisation never sees. After every stage the mesh's fit to them is measured (the refraction
//! and silhouette terms with the run's own residual forms and weights, over every pixel the run
//! keeps of them, and the pixels where the mesh's own outline and the held-out mask
//! disagree), so a run knows without ground truth when a stage made it worse; the stage that
//! fits them best becomes the result.

use std::collections::BTreeMap;

use anyhow::Result;

use super::terms::Sample;
use serde::{Deserialize, Serialize};

use super::config::Settings;
use super::Inputs;
use crate::loss::silhouette::{outline_disagreement, pixels_per_unit};
use crate::mesh::TriMesh;
use crate::scan::silhouette::Silhouette;
use crate::trace::path::MeshSurface;
use crate::trace::BuildMode;

/// Which views fit and which validate, as indices into [`Inputs`]' targets and silhouettes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Split {
    pub fit_targets: Vec<usize>,
    pub fit_silhouettes: Vec<usize>,
    pub held_targets: Vec<usize>,
    pub held_silhouettes: Vec<usize>,
}

impl Split {
    /// Holds out ⌊share · views⌋ of the views (none for a share of 0), evenly spaced, the first
    /// half a spacing in.
    pub fn new(inputs: &Inputs, share: f64) -> Self {
        let mut views: Vec<usize> = inputs
            .silhouettes
            .iter()
            .map(|s| s.view)
            .chain(inputs.targets.iter().map(|t| t.view))
            .collect();
        views.sort_unstable();
        views.dedup();
        let held_count = (share * views.len() as f64).floor() as usize;
        let held: Vec<usize> = (0..held_count)
            .map(|k| views[(2 * k + 1) * views.len() / (2 * held_count)])
            .collect();
        let (held_targets, fit_targets) =
            partition(inputs.targets.iter().map(|t| held.contains(&t.view)));
        let (held_silhouettes, fit_silhouettes) =
            partition(inputs.silhouettes.iter().map(|s| held.contains(&s.view)));
        Split {
            fit_targets,
            fit_silhouettes,
            held_targets,
            held_silhouettes,
        }
    }

    /// Whether any view is held out.
    pub fn validates(&self) -> bool {
        !self.held_targets.is_empty() || !self.held_silhouettes.is_empty()
    }
}

/// Indices where `held` is true, and where it is false.
fn partition(held: impl Iterator<Item = bool>) -> (Vec<usize>, Vec<usize>) {
    let (mut yes, mut no) = (Vec::new(), Vec::new());
    for (i, h) in held.enumerate() {
        if h {
            yes.push(i);
        } else {
            no.push(i);
        }
    }
    (yes, no)
}

/// A mesh's fit to the held-out views: the weighted means of the two data terms (as the run
/// weighs them) and their sum, pooled over the views and view by view.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ValidationRecord {
    pub refraction: f64,
    pub silhouette: f64,
    pub total: f64,
    /// Held-out views.
    pub views: usize,
    /// Each held-out view's fit, in view order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub per_view: Vec<ViewFit>,
}

impl ValidationRecord {
    /// The mean over the held-out views of the pixels where the mesh's outline and the mask
    /// disagree, when every view counted them.
    pub fn outline_px(&self) -> Option<f64> {
        let counts: Option<Vec<f64>> = self.per_view.iter().map(|v| v.outline_px).collect();
        counts
            .filter(|c| !c.is_empty())
            .map(|c| crate::util::mean(&c))
    }
}

/// One held-out view's fit: the weighted means of the two data terms over its pixels and its
/// outline, times the run's weights (0 for a term the view has no data for), and how many
/// pixels the mesh's outline and the mask disagree on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ViewFit {
    /// The view's index in the scan.
    pub view: usize,
    pub refraction: f64,
    pub silhouette: f64,
    /// Camera pixels covered by the mesh and outside the mask or the other way round
    /// ([`crate::loss::silhouette::outline_disagreement`]); absent for a view without a mask and
    /// from the reports of versions before it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outline_px: Option<f64>,
}

/// A term's loss and weight over one view.
#[derive(Clone, Copy, Default)]
struct Sums {
    loss: f64,
    weight: f64,
}

impl Sums {
    fn mean(self, factor: f64) -> f64 {
        if self.weight > 0.0 {
            factor * self.loss / self.weight
        } else {
            0.0
        }
    }

    fn of(term: &super::terms::TermValue) -> Sums {
        Sums {
            loss: term.loss,
            weight: term.weight,
        }
    }

    fn add(self, other: Sums) -> Sums {
        Sums {
            loss: self.loss + other.loss,
            weight: self.weight + other.weight,
        }
    }
}

/// The fit of `mesh` at refractive index `ior` to the held-out views of `split`; `None` when
/// none are held out.
pub fn validate_mesh(
    (inputs, ior): (&Inputs, f64),
    split: &Split,
    mesh: &TriMesh,
    settings: &Settings,
) -> Result<Option<ValidationRecord>> {
    if !split.validates() {
        return Ok(None);
    }
    let surface = MeshSurface::with_mode(mesh, settings.normals, BuildMode::Static)?;
    let edges = mesh.interior_edges();
    // Per view (sorted): the refraction and the silhouette term's sums, the outline's pixels.
    let mut views: BTreeMap<usize, ViewSums> = BTreeMap::new();
    for &t in &split.held_targets {
        let all = [(t, Sample::AllKept)];
        let slope = super::terms::IndexSlope::Unneeded;
        let term =
            super::terms::refraction_over((inputs, ior), &surface, mesh, settings, &all, slope)?;
        let sums = &mut views.entry(inputs.targets[t].view).or_default().0;
        *sums = sums.add(Sums::of(&term));
    }
    for &k in &split.held_silhouettes {
        let sil = &inputs.silhouettes[k];
        let term = super::terms::silhouette_over(inputs, &surface, mesh, &edges, settings, &[k])?;
        let stride = outline_stride(mesh, sil, settings);
        let outline = outline_disagreement(mesh, sil, surface.scene(), stride)?;
        let entry = views.entry(sil.view).or_default();
        entry.1 = entry.1.add(Sums::of(&term));
        entry.2 = Some(outline as f64);
    }
    Ok(Some(record(&views, settings)))
}

/// The pixel stride of view `sil`'s outline test: the camera pixels in the kept rays' spacing
/// ([`Settings::kept_spacing_share`] of `mesh`'s diagonal) at the object, so that the
/// rays it traces follow the object, not the camera's pixel count; 1 where a pixel is coarser.
fn outline_stride(mesh: &TriMesh, sil: &Silhouette, settings: &Settings) -> usize {
    let Some((lo, hi)) = mesh.bbox() else {
        return 1;
    };
    let spacing_mm = settings.kept_spacing_share() * (hi - lo).norm();
    let pixels = spacing_mm * pixels_per_unit(mesh, sil, 1.0);
    if pixels.is_finite() {
        (pixels.floor() as usize).max(1)
    } else {
        1
    }
}

/// One held-out view's refraction and silhouette sums and its outline's disagreeing pixels.
type ViewSums = (Sums, Sums, Option<f64>);

/// The pooled and per-view record of each view's sums.
fn record(views: &BTreeMap<usize, ViewSums>, settings: &Settings) -> ValidationRecord {
    let (wr, ws) = (settings.weight_refraction, settings.weight_silhouette);
    let pooled = (views.values()).fold((Sums::default(), Sums::default()), |a, e| {
        (a.0.add(e.0), a.1.add(e.1))
    });
    let (r, s) = (pooled.0.mean(wr), pooled.1.mean(ws));
    ValidationRecord {
        refraction: r,
        silhouette: s,
        total: r + s,
        views: views.len(),
        per_view: (views.iter())
            .map(|(&view, &(rs, ss, outline_px))| ViewFit {
                view,
                refraction: rs.mean(wr),
                silhouette: ss.mean(ws),
                outline_px,
            })
            .collect(),
    }
}

/// Student's t one-sided 5 % critical values for 1–30 degrees of freedom.
const T_CRITICAL_5: [f64; 30] = [
    6.314, 2.920, 2.353, 2.132, 2.015, 1.943, 1.895, 1.860, 1.833, 1.812, 1.796, 1.782, 1.771,
    1.761, 1.753, 1.746, 1.740, 1.734, 1.729, 1.725, 1.721, 1.717, 1.714, 1.711, 1.708, 1.706,
    1.703, 1.701, 1.699, 1.697,
];

/// How many standard errors of the per-view differences a later stage's gain over `views`
/// held-out views must exceed to replace the chosen stage: the t distribution's one-sided 5 %
/// quantile with `views − 1` degrees of freedom (1.94 for 7 views, 6.31 for 2; beyond 30 by the
/// Cornish–Fisher expansion about the normal's 1.645); infinite for fewer than two views, which
/// cannot be tested.
pub fn significant_t(views: usize) -> f64 {
    let df = views.saturating_sub(1);
    if df == 0 {
        return f64::INFINITY;
    }
    if let Some(&t) = T_CRITICAL_5.get(df - 1) {
        return t;
    }
    let (z, n) = (1.644_853_626_951_472_f64, df as f64);
    z + (z.powi(3) + z) / (4.0 * n)
        + (5.0 * z.powi(5) + 16.0 * z.powi(3) + 3.0 * z) / (96.0 * n * n)
}

/// The stage (index) among the first `upto` that fits the held-out views best, from stage
/// `first` on (the warm-up's stages carve at the coarsest edge length and are candidates only
/// when no later stage is done): the stage of lowest total, then each later stage that
/// [`fits_significantly_better`] than the one chosen so far. The last of them when the run
/// holds out nothing. `None` when no stage is done.
pub fn best_stage(stages: &[super::StageReport], first: usize, upto: usize) -> Option<usize> {
    let done = &stages[..upto.min(stages.len())];
    let from = if done.len() > first { first } else { 0 };
    let Some(lowest) = lowest_total(done, from) else {
        return done.len().checked_sub(1);
    };
    let fit = |s: usize| done[s].validation.as_ref();
    Some(
        (lowest + 1..done.len()).fold(lowest, |chosen, later| match (fit(chosen), fit(later)) {
            (Some(c), Some(l)) if fits_significantly_better(c, l) => later,
            _ => chosen,
        }),
    )
}

/// The stage from `from` on whose held-out total is lowest (finite), if any is validated.
fn lowest_total(done: &[super::StageReport], from: usize) -> Option<usize> {
    (done.iter().enumerate().skip(from))
        .filter_map(|(i, s)| s.validation.as_ref().map(|v| (i, v.total)))
        .filter(|(_, t)| t.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Whether `later` fits the same held-out views better than `earlier` beyond the noise between
/// views, by paired comparisons (the per-view differences' mean over their standard error) of
/// two measures: the refraction term and the pixels where the mesh's outline and the mask
/// disagree. One must be lower by more than [`significant_t`] standard errors (a one-sided test
/// at 5 %) and the other not higher by as much. The pooled total can prefer a coarser stage
/// because the held-out masks' outlines, not the shape, dominate its silhouette term, and that
/// term's mean over contour edges changes with their number and zigzag at every edge length
/// (docs/decisions.md#the-result-stage-a-finer-stage-earns-its-place-view-by-view):
/// a finer stage must earn its place view by view. Where a record has no
/// outline counts (an older checkpoint), the silhouette term stands in for them. False without
/// per-view figures for the same views.
pub fn fits_significantly_better(earlier: &ValidationRecord, later: &ValidationRecord) -> bool {
    let (e, l) = (&earlier.per_view, &later.per_view);
    let same_views = e.len() == l.len() && e.iter().zip(l).all(|(a, b)| a.view == b.view);
    if !same_views {
        return false;
    }
    let gain = |term: fn(&ViewFit) -> f64| -> Vec<f64> {
        e.iter().zip(l).map(|(a, b)| term(a) - term(b)).collect()
    };
    let refraction = paired_t(&gain(|v| v.refraction));
    let counted = e.iter().chain(l).all(|v| v.outline_px.is_some());
    let outline = if counted {
        paired_t(&gain(|v| v.outline_px.unwrap_or(0.0)))
    } else {
        paired_t(&gain(|v| v.silhouette))
    };
    let t = significant_t(e.len());
    let better = |a: f64, b: f64| a > t && b > -t;
    better(refraction, outline) || better(outline, refraction)
}

/// The paired t statistic of `differences`: their mean over its standard error (±∞ when they
/// agree exactly and are not all 0; 0 for fewer than two, or any that is not finite).
fn paired_t(differences: &[f64]) -> f64 {
    let n = differences.len();
    if n < 2 || differences.iter().any(|d| !d.is_finite()) {
        return 0.0;
    }
    let mean = differences.iter().sum::<f64>() / n as f64;
    let variance = differences.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let standard_error = (variance / n as f64).sqrt();
    if standard_error > 0.0 {
        mean / standard_error
    } else if mean == 0.0 {
        0.0
    } else {
        mean.signum() * f64::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reconstruct::StageReport;

    fn stage(stage: usize, total: Option<f64>) -> StageReport {
        StageReport {
            stage,
            edge_mm: 1.0,
            validation: total.map(|total| ValidationRecord {
                total,
                ..Default::default()
            }),
            ..Default::default()
        }
    }

    #[test]
    fn the_best_stage_is_the_lowest_held_out_fit_after_the_warm_up_within_the_stages_done() {
        let stages: Vec<StageReport> = [0.5, 0.2, 0.3, 0.1]
            .iter()
            .enumerate()
            .map(|(i, &t)| stage(i, Some(t)))
            .collect();
        assert_eq!(best_stage(&stages, 0, 4), Some(3));
        assert_eq!(best_stage(&stages, 0, 3), Some(1));
        assert_eq!(best_stage(&stages, 0, 0), None);
        // Stages before `first` (the warm-up) are candidates only when no later one is done.
        assert_eq!(best_stage(&stages, 2, 3), Some(2));
        assert_eq!(best_stage(&stages, 2, 4), Some(3));
        assert_eq!(best_stage(&stages, 3, 3), Some(1));
        let unvalidated: Vec<StageReport> = (0..3).map(|i| stage(i, None)).collect();
        assert_eq!(best_stage(&unvalidated, 0, 3), Some(2));
        let with_nan = vec![stage(0, Some(f64::NAN)), stage(1, Some(0.4))];
        assert_eq!(best_stage(&with_nan, 0, 2), Some(1));
    }

    /// A record of seven held-out views with these per-view refraction and silhouette terms and
    /// outline pixels (none: not counted).
    fn seven_views_outlined(
        refraction: [f64; 7],
        silhouette: [f64; 7],
        outline: Option<[f64; 7]>,
    ) -> ValidationRecord {
        let views: BTreeMap<usize, ViewSums> = (0..7)
            .map(|v| {
                let sums = |x: f64| Sums {
                    loss: x,
                    weight: 1.0,
                };
                let px = outline.map(|o| o[v]);
                (5 + 10 * v, (sums(refraction[v]), sums(silhouette[v]), px))
            })
            .collect();
        let mut settings = Settings::preset(super::super::config::Preset::Balanced);
        (settings.weight_refraction, settings.weight_silhouette) = (1.0, 1.0);
        record(&views, &settings)
    }

    /// [`seven_views_outlined`] with the same outline in every view.
    fn seven_views(refraction: [f64; 7], silhouette: [f64; 7]) -> ValidationRecord {
        seven_views_outlined(refraction, silhouette, Some([100.0; 7]))
    }

    /// Stages 0, 1, … with these held-out fits.
    fn validated_stages<const N: usize>(fits: [ValidationRecord; N]) -> Vec<StageReport> {
        (fits.into_iter().enumerate())
            .map(|(i, v)| StageReport {
                validation: Some(v),
                ..stage(i, None)
            })
            .collect()
    }

    #[test]
    fn the_record_pools_the_views_and_keeps_each() {
        let r = seven_views([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0], [0.5; 7]);
        assert_eq!(r.views, 7);
        assert!((r.refraction - 4.0).abs() < 1e-12);
        assert!((r.total - 4.5).abs() < 1e-12);
        assert_eq!(r.per_view[2].view, 25);
        assert_eq!(r.per_view[2].refraction, 3.0);
        let outlined = seven_views_outlined(
            [1.0; 7],
            [0.5; 7],
            Some([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]),
        );
        assert_eq!(outlined.outline_px(), Some(4.0));
        assert_eq!(
            seven_views_outlined([1.0; 7], [0.5; 7], None).outline_px(),
            None
        );
    }

    #[test]
    fn the_paired_t_is_the_mean_difference_over_its_standard_error() {
        // Mean 2, sample standard deviation 1, three differences: t = 2 / (1 / √3).
        assert!((paired_t(&[1.0, 2.0, 3.0]) - 2.0 * 3f64.sqrt()).abs() < 1e-12);
        assert_eq!(paired_t(&[0.5, 0.5]), f64::INFINITY);
        assert_eq!(paired_t(&[0.0, 0.0]), 0.0);
        assert_eq!(paired_t(&[1.0]), 0.0);
        assert_eq!(paired_t(&[1.0, f64::NAN, 2.0]), 0.0);
    }

    #[test]
    fn the_threshold_is_the_t_distributions_one_sided_5_percent_quantile() {
        assert_eq!(significant_t(7), 1.943);
        assert_eq!(significant_t(2), 6.314);
        assert_eq!(significant_t(1), f64::INFINITY);
        assert_eq!(significant_t(0), f64::INFINITY);
        // Beyond the table the expansion continues it and falls towards the normal's 1.645.
        assert!((significant_t(32) - 1.696).abs() < 1e-3);
        assert!((significant_t(61) - 1.671).abs() < 1e-3);
        assert!((significant_t(100_000) - 1.645).abs() < 1e-3);
        let t: Vec<f64> = (2..200).map(significant_t).collect();
        assert!(t.windows(2).all(|w| w[1] < w[0]));
    }

    #[test]
    fn a_gain_of_about_two_and_a_half_standard_errors_counts_over_7_views_not_over_3() {
        // Refraction misfit lower by 0–0.002 a view (mean 0.0013): t = 2.65 over 7 views.
        let base_r = [0.020, 0.030, 0.025, 0.018, 0.022, 0.028, 0.021];
        let gain = [0.002, 0.0, 0.002, 0.0, 0.002, 0.0, 0.001];
        let earlier = seven_views(base_r, [0.04; 7]);
        let later = seven_views(std::array::from_fn(|v| base_r[v] - gain[v]), [0.04; 7]);
        let t = paired_t(&gain);
        assert!(t > significant_t(7) && t < 3.0, "t = {t}");
        assert!(fits_significantly_better(&earlier, &later));
        // The same three views' gains are not enough (t = 2 against 2.92).
        let first3 = |r: &ValidationRecord| ValidationRecord {
            per_view: r.per_view[..3].to_vec(),
            ..r.clone()
        };
        assert!(paired_t(&gain[..3]) < significant_t(3));
        assert!(!fits_significantly_better(
            &first3(&earlier),
            &first3(&later)
        ));
    }

    #[test]
    fn a_finer_stage_replaces_a_lower_total_only_with_a_gain_consistent_over_the_views() {
        let base_r = [0.020, 0.030, 0.025, 0.018, 0.022, 0.028, 0.021];
        let base_s = [0.03, 0.05, 0.04, 0.30, 0.04, 0.09, 0.20];
        let earlier = seven_views(base_r, base_s);
        // 20 % less refraction misfit in every view, the outlines a little worse: the pooled
        // total is higher, yet the gain is far beyond the noise between views.
        let consistent = seven_views(base_r.map(|r| 0.8 * r), base_s.map(|s| s * 1.08));
        assert!(consistent.total > earlier.total);
        assert!(fits_significantly_better(&earlier, &consistent));
        // A lower pooled refraction term from one view only is noise.
        let mut one_view = base_r.map(|r| 1.01 * r);
        one_view[1] = 0.010;
        let one_view = seven_views(one_view, base_s);
        assert!(one_view.refraction < earlier.refraction);
        assert!(!fits_significantly_better(&earlier, &one_view));
        // Consistently worse outlines in every view veto a refraction gain; a higher contour
        // term alone does not.
        let outline = [100.0, 120.0, 90.0, 140.0, 110.0, 95.0, 130.0];
        let earlier = seven_views_outlined(base_r, base_s, Some(outline));
        let bulged = seven_views_outlined(
            base_r.map(|r| 0.8 * r),
            base_s,
            Some(outline.map(|o| o + 12.0)),
        );
        assert!(!fits_significantly_better(&earlier, &bulged));
        let finer_contour = seven_views_outlined(
            base_r.map(|r| 0.8 * r),
            base_s.map(|s| s + 0.05),
            Some(outline),
        );
        assert!(fits_significantly_better(&earlier, &finer_contour));
        // Fewer disagreeing pixels in every view earn a finer stage its place when the
        // refraction term is no better; the pooled total may still be higher.
        let jitter = [1.02, 0.99, 1.01, 0.98, 1.0, 1.01, 0.99];
        let sharper = seven_views_outlined(
            std::array::from_fn(|v| base_r[v] * jitter[v]),
            base_s.map(|s| s * 1.3),
            Some(outline.map(|o| o - 9.0 - o / 50.0)),
        );
        assert!(sharper.total > earlier.total);
        assert!(fits_significantly_better(&earlier, &sharper));
        // Without outline counts (an older checkpoint) the contour term stands in.
        let older = |r: [f64; 7], s: [f64; 7]| seven_views_outlined(r, s, None);
        let (older_earlier, older_bulged) = (
            older(base_r, base_s),
            older(base_r.map(|r| 0.8 * r), base_s.map(|s| s + 0.05)),
        );
        assert!(!fits_significantly_better(&older_earlier, &older_bulged));
        let earlier = seven_views(base_r, base_s);
        // Different views (or none per view: an older checkpoint) are never compared.
        let mut other = consistent.clone();
        other.per_view[0].view = 1;
        assert!(!fits_significantly_better(&earlier, &other));
        let pooled_only = ValidationRecord {
            per_view: Vec::new(),
            ..consistent.clone()
        };
        assert!(!fits_significantly_better(&earlier, &pooled_only));

        // In a run: the lowest total (stage 1), then stage 2's consistent gain over it.
        let stages = validated_stages([earlier.clone(), earlier, consistent]);
        assert_eq!(best_stage(&stages, 1, 3), Some(2));
        assert_eq!(best_stage(&stages, 1, 2), Some(1));
    }
}
