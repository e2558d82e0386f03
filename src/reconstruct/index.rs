//! The object's refractive index: how a run estimates an unknown one (`ior = "auto"`), and the
//! index the held-out views fit best with the result, which gives the estimate's spread and a
//! warning when a given index fits worse than a nearby one
//! (docs/decisions.md#glass-of-unknown-index).
//!
//! An unknown index is a parameter of the optimisation beside the vertex positions: in every
//! stage after the warm-up the refraction term's derivative with respect to the index
//! ([`crate::loss::diff::snell_eta_adjoint`]) steps it with the shape
//! ([`super::optim::IndexStepper`]); the stage's estimate, the mean over its averaged
//! iterations, starts the next stage. The warm-up's DRT steps hold the index, and carve the
//! start mesh differently at a wrong one; so a first pass, the warm-up and the schedule's first
//! stage from the range's middle, finds where the run starts the index, and the run starts
//! over from the start mesh at it.
//!
//! With the shape held fixed, the held-out views' refraction term is a smooth function of the
//! index; its minimum is the root of its derivative, found by the secant method.

use anyhow::Result;
use serde::Serialize;

use super::checkpoint::StageReport;
use super::config::{Settings, AUTO_FOOTPRINT};
use super::terms::{refraction_over, IndexSlope, Sample};
use super::validation::Split;
use super::Inputs;
use crate::mesh::TriMesh;
use crate::scan::{Ior, MAX_IOR};
use crate::trace::path::MeshSurface;

/// The settings of the index pass: `settings`' warm-up and the first stage of its schedule, no
/// blur correction.
pub fn pass_settings(settings: &Settings) -> Settings {
    Settings {
        stages: 1,
        final_edge: settings.start_edge,
        // Its coarse mesh is too far from the object to correct the points on.
        blur_correction: false,
        ..settings.clone()
    }
}

/// Rays per side of the footprint by which a run that estimates the index of curved glass
/// models each pixel decoded from captures (at least; the settings' own when larger).
pub const FIT_FOOTPRINT: u32 = 2;

/// How many times its settings' iterations a run that estimates the index of curved glass
/// decoded from captures runs each stage.
pub const FIT_ITERATIONS: usize = 2;

/// The settings of a run that estimates the index: `settings`, but through curved glass decoded
/// from captures (`curved_captures`, [`Inputs::curved_captures`]) each pixel modelled by at
/// least [`FIT_FOOTPRINT`]² rays over [`FIT_ITERATIONS`] times the iterations. A pixel's decoded
/// point is its footprint's vote, which the centre ray misses where the glass bends the
/// footprint unevenly, most where it magnifies; and shape and index walk on together for as
/// long as the stages run (docs/decisions.md#glass-of-unknown-index).
pub fn estimating_settings(settings: &Settings, curved_captures: bool) -> Settings {
    if !curved_captures {
        return settings.clone();
    }
    let footprint = match settings.footprint {
        AUTO_FOOTPRINT => FIT_FOOTPRINT,
        n => n.max(FIT_FOOTPRINT),
    };
    Settings {
        footprint,
        iterations: settings.iterations * FIT_ITERATIONS,
        ..settings.clone()
    }
}

/// The secant method's first step (index units).
const FIRST_STEP: f64 = 0.01;
/// The secant method stops when a step is shorter than this (index units).
const TOLERANCE: f64 = 1e-4;
/// The most evaluations of the held-out term the search makes.
const MAX_EVALUATIONS: usize = 12;
/// The longest step of the search (index units): where the term curves downward, or a secant
/// step would leap, it steps this far downhill instead.
const MAX_STEP: f64 = 0.03;
/// How far from a given index (index units) the search for the best-fitting one looks.
const GIVEN_REACH: f64 = 0.2;

/// How much (share of its minimum) the held-out refraction term may rise over the index's
/// spread: the spread is the half-width of the range where the term, as a parabola of the curvature
/// the search measured, stays below (1 + this) × its minimum.
pub const SPREAD_RISE: f64 = 0.01;

/// How far (index units) the best-fitting index may lie from a given one before the run warns:
/// the best fit is biased where the mesh is too coarse to take the shape (the test pebble at
/// 4.5 mm edges, given its true index 1.4723, fits 1.496 best), by less than this; an index 3 %
/// off is 0.045 off.
pub const WARN_OFFSET: f64 = 0.03;

/// How near (index units) the result's estimate may come to its range's bound before the run
/// warns that the index may lie beyond it: the stepper holds the index inside the range, so an
/// estimate pinned there says the data pulled further. (The coarse stages may reach a bound on
/// the way and the finer ones leave it: the test pebble's run touches 1.40 and ends at 1.467
/// for 1.4723.)
pub const BOUND_MARGIN: f64 = 0.005;

/// The held-out views' refraction term (weighted mean) and its derivative with respect to the
/// index, at one index.
#[derive(Clone, Copy, Debug, PartialEq)]
struct HeldOut {
    ior: f64,
    value: f64,
    slope: f64,
}

/// The index the held-out views fit best, with the shape fixed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct BestFit {
    pub ior: f64,
    /// See [`SPREAD_RISE`].
    pub spread: f64,
    /// The held-out refraction term there.
    pub refraction: f64,
    /// Evaluations of the held-out term the search made.
    pub evaluations: usize,
}

/// What `report.json` says of the index.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct IndexReport {
    /// As given (scan.toml or --ior).
    pub given: Ior,
    /// The index the result was made at: the given one, or its stage's estimate.
    pub used: f64,
    /// An unknown index's estimate: the last stage's, made with the finest mesh ([`estimate`]);
    /// the same as `used` unless the held-out views chose an earlier stage's mesh. `None` for a
    /// given index.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimate: Option<f64>,
    /// The index the held-out views fit best with the result's shape (`None`: no views held
    /// out, or the term has no minimum within reach).
    pub held_out_best: Option<BestFit>,
}

impl IndexReport {
    /// A warning when a given index fits the held-out views clearly worse than a nearby one, or
    /// when the result's estimate cannot be trusted: pinned at its range's bound, unconfirmed by
    /// the held-out views, or far from the index they fit best.
    pub fn warning(&self) -> Option<String> {
        match self.given {
            Ior::Known(given) => self.given_warning(given),
            Ior::Auto { lo, hi } => self.estimate_warning(lo, hi),
        }
    }

    fn given_warning(&self, given: f64) -> Option<String> {
        let best = self.held_out_best?;
        ((best.ior - given).abs() > WARN_OFFSET).then(|| {
            format!(
                "the held-out views fit a refractive index of {:.3} better than the given {given:.4}: check the index, or give ior = \"auto\"",
                best.ior
            )
        })
    }

    /// The estimate is pinned when it or the result's index lies at a bound; the held-out
    /// views judge the result's index, with the result's mesh.
    fn estimate_warning(&self, lo: f64, hi: f64) -> Option<String> {
        let used = self.used;
        let estimate = self.estimate.unwrap_or(used);
        if let Some((index, bound)) = [estimate, used]
            .into_iter()
            .flat_map(|i| [(i, lo), (i, hi)])
            .find(|(i, b)| (i - b).abs() <= BOUND_MARGIN)
        {
            return Some(format!(
                "the refractive index estimate {index:.4} lies at the range's bound {bound}: the index may lie outside {lo}–{hi}, or these captures may not settle it; give a wider range (ior = {{ auto = [lo, hi] }}) or the index"
            ));
        }
        let Some(best) = self.held_out_best else {
            return Some(format!(
                "the estimate {used:.4} the result was made at is unconfirmed: the held-out views find no best-fitting index with the result (or the run holds no views out)"
            ));
        };
        ((best.ior - used).abs() > WARN_OFFSET).then(|| {
            format!(
                "the held-out views fit a refractive index of {:.3} better than the estimate {used:.4} the result was made at: the estimate is not settled",
                best.ior
            )
        })
    }
}

/// An unknown index's estimate from a run's `stages`: the last stage's, whose mesh is the finest
/// and whose index has had every stage to settle, whichever stage's mesh the held-out views
/// choose as the result (docs/decisions.md#glass-of-unknown-index). `None` for a given index,
/// or before a stage has recorded one.
pub fn estimate(given: Ior, stages: &[StageReport]) -> Option<f64> {
    given.is_auto().then(|| stages.last()?.ior).flatten()
}

/// The range the search for the best-fitting index keeps to: an unknown index's range, or
/// [`GIVEN_REACH`] about a given one.
pub fn search_range(ior: Ior) -> (f64, f64) {
    match ior {
        Ior::Auto { lo, hi } => (lo, hi),
        Ior::Known(v) => (
            (v - GIVEN_REACH).max(1.0 + 1e-3),
            (v + GIVEN_REACH).min(MAX_IOR),
        ),
    }
}

/// The index within `range` where the held-out views' refraction term of the mesh `surface`
/// holds is lowest,
/// by the secant method on its derivative from `from` (steps of at most [`MAX_STEP`], downhill
/// where the term curves downward); `None` without held-out views, or when the search has not
/// settled within [`MAX_EVALUATIONS`] or ends where the term curves downward.
pub fn held_out_best(
    inputs: &Inputs,
    split: &Split,
    surface: &MeshSurface,
    settings: &Settings,
    (from, range): (f64, (f64, f64)),
) -> Result<Option<BestFit>> {
    if !split.validates() {
        return Ok(None);
    }
    let at = |ior: f64| held_out(inputs, split, surface, surface.mesh(), settings, ior);
    let second = if from + FIRST_STEP <= range.1 {
        from + FIRST_STEP
    } else {
        from - FIRST_STEP
    };
    let (mut a, mut b) = (at(from)?, at(second)?);
    for evaluations in 3..=MAX_EVALUATIONS {
        let curvature = (b.slope - a.slope) / (b.ior - a.ior);
        let downhill = -MAX_STEP * b.slope.signum();
        let step = if curvature > 0.0 && curvature.is_finite() {
            (-b.slope / curvature).clamp(-MAX_STEP, MAX_STEP)
        } else {
            downhill
        };
        let next = (b.ior + step).clamp(range.0, range.1);
        let c = at(next)?;
        if (next - b.ior).abs() < TOLERANCE {
            if !(curvature > 0.0 && curvature.is_finite()) {
                return Ok(None);
            }
            return Ok(Some(BestFit {
                ior: next,
                spread: (2.0 * SPREAD_RISE * c.value.max(0.0) / curvature).sqrt(),
                refraction: c.value,
                evaluations,
            }));
        }
        (a, b) = (b, c);
    }
    Ok(None)
}

/// The held-out views' refraction term at index `ior`, on every pixel they keep.
fn held_out(
    inputs: &Inputs,
    split: &Split,
    surface: &MeshSurface,
    mesh: &TriMesh,
    settings: &Settings,
    ior: f64,
) -> Result<HeldOut> {
    let views: Vec<(usize, Sample)> = split
        .held_targets
        .iter()
        .map(|&t| (t, Sample::AllKept))
        .collect();
    let term = refraction_over(
        (inputs, ior),
        surface,
        mesh,
        settings,
        &views,
        IndexSlope::Wanted,
    )?;
    let w = if term.weight > 0.0 {
        1.0 / term.weight
    } else {
        0.0
    };
    Ok(HeldOut {
        ior,
        value: term.loss * w,
        slope: term.ior_grad * w,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report_at(given: Ior, best: f64) -> IndexReport {
        IndexReport {
            given,
            used: given.nominal(),
            estimate: given.is_auto().then(|| given.nominal()),
            held_out_best: Some(BestFit {
                ior: best,
                spread: 0.003,
                refraction: 1.0,
                evaluations: 4,
            }),
        }
    }

    #[test]
    fn a_given_index_far_from_the_best_fitting_one_warns_and_a_near_one_does_not() {
        let far = report_at(Ior::Known(1.5), 1.535);
        assert!(far.warning().unwrap().contains("1.535"), "{far:?}");
        assert_eq!(report_at(Ior::Known(1.5), 1.525).warning(), None);
        let none = IndexReport {
            held_out_best: None,
            ..far
        };
        assert_eq!(none.warning(), None);
    }

    #[test]
    fn an_estimate_pinned_at_its_bound_unconfirmed_or_far_from_the_best_fit_warns() {
        let auto = Ior::Auto { lo: 1.4, hi: 1.7 };
        // Settled: estimated 1.55, the held-out views fit 1.56 best.
        let settled = report_at(auto, 1.56);
        assert_eq!(settled.warning(), None);
        let pinned = IndexReport {
            used: 1.4,
            ..settled.clone()
        };
        let w = pinned.warning().expect("pinned at the floor");
        assert!(w.contains("bound 1.4") && w.contains("wider range"), "{w}");
        let near = IndexReport {
            used: 1.4 + 2.0 * BOUND_MARGIN,
            held_out_best: Some(BestFit {
                ior: 1.41,
                ..settled.held_out_best.unwrap()
            }),
            ..settled.clone()
        };
        assert_eq!(near.warning(), None);
        let top = IndexReport {
            used: 1.698,
            ..settled.clone()
        };
        assert!(top.warning().unwrap().contains("bound 1.7"));
        let unconfirmed = IndexReport {
            held_out_best: None,
            ..settled.clone()
        };
        assert!(unconfirmed.warning().unwrap().contains("unconfirmed"));
        let far = report_at(auto, 1.55 + 1.5 * WARN_OFFSET);
        assert!(far.warning().unwrap().contains("not settled"));
    }

    #[test]
    fn the_estimate_is_the_last_stages_and_its_bound_warns_too() {
        let auto = Ior::Auto { lo: 1.4, hi: 1.7 };
        let stage = |ior| StageReport {
            ior,
            ..StageReport::default()
        };
        let stages = [stage(Some(1.44)), stage(Some(1.58)), stage(Some(1.598))];
        assert_eq!(estimate(auto, &stages), Some(1.598));
        assert_eq!(estimate(Ior::Known(1.5), &stages), None);
        assert_eq!(estimate(auto, &[]), None);
        assert_eq!(estimate(auto, &[stage(None)]), None);
        // The result made at 1.55 (an earlier stage), the last stage's estimate at the ceiling.
        let pinned = IndexReport {
            estimate: Some(1.699),
            ..report_at(auto, 1.56)
        };
        let w = pinned
            .warning()
            .expect("the estimate pinned at the ceiling");
        assert!(w.contains("1.6990") && w.contains("bound 1.7"), "{w}");
    }

    #[test]
    fn curved_captures_estimate_the_index_with_a_footprint_over_twice_the_iterations() {
        use super::super::config::Preset;
        let balanced = Settings::preset(Preset::Balanced);
        assert_eq!(estimating_settings(&balanced, false), balanced);
        let fit = estimating_settings(&balanced, true);
        assert_eq!(fit.footprint, FIT_FOOTPRINT);
        assert_eq!(fit.iterations, FIT_ITERATIONS * balanced.iterations);
        let unchanged = Settings {
            footprint: balanced.footprint,
            iterations: balanced.iterations,
            ..fit.clone()
        };
        assert_eq!(unchanged, balanced);
        // A larger footprint is kept; a footprint left to the run becomes the fit's.
        let four = Settings {
            footprint: 4,
            ..balanced
        };
        assert_eq!(estimating_settings(&four, true).footprint, 4);
        let accurate = Settings::preset(Preset::Accurate);
        assert_eq!(accurate.footprint, AUTO_FOOTPRINT);
        assert_eq!(
            estimating_settings(&accurate, true).footprint,
            FIT_FOOTPRINT
        );
    }

    #[test]
    fn the_search_keeps_to_the_range_or_near_a_given_index() {
        assert_eq!(search_range(Ior::Auto { lo: 1.45, hi: 1.6 }), (1.45, 1.6));
        let (lo, hi) = search_range(Ior::Known(1.1));
        assert!(
            (lo - 1.001).abs() < 1e-12 && (hi - 1.3).abs() < 1e-12,
            "{lo} {hi}"
        );
    }

    #[test]
    fn the_index_pass_runs_the_warm_up_and_the_schedules_first_stage() {
        let balanced = Settings::preset(super::super::config::Preset::Balanced);
        let pass = pass_settings(&balanced);
        assert_eq!(pass.warmup_stages, balanced.warmup_stages);
        assert_eq!(pass.total_stages(), balanced.warmup_stages + 1);
        for s in 0..pass.total_stages() {
            let (a, b) = (pass.stage(s), balanced.stage(s));
            assert_eq!(a.1, b.1, "stage {s}");
            let (a, b) = (a.0.edge_mm(a.1, 100.0), b.0.edge_mm(b.1, 100.0));
            assert!((a - b).abs() < 1e-9, "stage {s}: {a} against {b}");
        }
    }
}
