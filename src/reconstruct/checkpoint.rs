//! What a run commits after every stage: the checkpoint (settings, schedule, history, stage
//! reports, the judges' verdicts, the inputs' fingerprint) and the records it holds.

use super::config::Settings;
use super::validation::ValidationRecord;
use crate::loss::Drops;
use serde::{Deserialize, Serialize};

/// The weighted means of the terms at one iteration (before its step).
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct IterationRecord {
    pub stage: usize,
    pub iteration: usize,
    pub refraction: f64,
    pub silhouette: f64,
    pub smoothness: f64,
    /// The membrane term on what the refraction data cannot see (0 when off).
    #[serde(default, alias = "unseen")]
    pub membrane: f64,
    pub total: f64,
}

/// Figures of one stage (the default: a stage that ran nothing).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct StageReport {
    pub stage: usize,
    pub edge_mm: f64,
    pub vertices: usize,
    pub faces: usize,
    /// Wall time of the stage, s (the stage that judges the membrane term: both its runs).
    pub seconds: f64,
    pub refraction_rays_used: usize,
    pub refraction_drops: Drops,
    pub contour_edges_used: usize,
    /// Faces of (numerically) zero area at the end of the stage (the next remesh removes them).
    pub degenerate_faces: usize,
    pub last: IterationRecord,
    /// The stage mesh's fit to the held-out views (none held out: `None`).
    #[serde(default)]
    pub validation: Option<ValidationRecord>,
    /// The stage's mesh is the mean of its last iterates (`average_share`), not its last.
    #[serde(default)]
    pub averaged: bool,
    /// Share of the stage mesh's vertices that no compared refraction ray touched during the
    /// stage (faces seen only edge-on, or hidden; the membrane term acts there, `weight_membrane`).
    #[serde(default)]
    pub unseen_share: f64,
    /// The largest share of the stage mesh's vertices the membrane term acted on in one
    /// iteration (0: no unseen patch, or the term off).
    #[serde(default)]
    pub membrane_share: f64,
    /// Where the stage's time went.
    #[serde(default)]
    pub profile: CostProfile,
    /// The refractive index the stage was run at (`None` in checkpoints that predate it: the
    /// scan's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ior: Option<f64>,
    /// A warm-up stage not run: an earlier one fit the held-out views worse than the start mesh
    /// ([`WarmUpVerdict`]); its mesh is the start mesh.
    #[serde(default)]
    pub skipped: bool,
    /// How far the stage's decoded points were moved for the camera's blur, on its start mesh
    /// (`None`: no blur corrected for, or a warm-up stage).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blur: Option<crate::loss::blur::CorrectionSummary>,
}

/// Where a stage's wall time went, seconds, and how fast it traced.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CostProfile {
    /// Correcting the decoded points for the camera's blur on the stage's start mesh.
    #[serde(default)]
    pub blur: f64,
    /// Remeshing to the stage's edge length, with its sizing field (the rays that measure
    /// where the data pulls, `sizing_pull`, included).
    pub remesh: f64,
    /// Every term of every iteration, wall time. The terms run at the same time, so their own
    /// times below overlap and add up to more (absent in reports written before they ran
    /// together).
    #[serde(default)]
    pub terms: f64,
    /// The refraction term: tracing the sampled pixels' paths and their gradients.
    pub refraction: f64,
    /// The silhouette term: contour edges, their probe rays and gradients.
    pub silhouette: f64,
    /// The smoothness and membrane terms.
    pub regularisers: f64,
    /// The optimiser's steps, Large Steps' linear solves included.
    pub step: f64,
    /// Refitting the ray-tracing structure to the moved vertices.
    pub refit: f64,
    /// Fitting the held-out views (the stage's end; the judges' runs not included).
    pub validation: f64,
    /// Refraction rays used per second of the refraction term.
    pub refraction_rays_per_s: f64,
}

impl CostProfile {
    /// The sum of `profiles`, field by field; the ray rate over their summed refraction time.
    pub fn total<'a>(profiles: impl IntoIterator<Item = (&'a CostProfile, usize)>) -> Self {
        let mut t = CostProfile::default();
        let mut rays = 0.0;
        for (p, used) in profiles {
            t.remesh += p.remesh;
            t.terms += p.terms;
            t.refraction += p.refraction;
            t.silhouette += p.silhouette;
            t.regularisers += p.regularisers;
            t.step += p.step;
            t.refit += p.refit;
            t.validation += p.validation;
            rays += used as f64;
        }
        t.refraction_rays_per_s = if t.refraction > 0.0 {
            rays / t.refraction
        } else {
            0.0
        };
        t
    }
}

/// The state saved after every stage.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Checkpoint {
    pub settings: Settings,
    /// Bounding-box diagonal of the initial mesh (mm): the unit of the edge schedule.
    pub diagonal_mm: f64,
    /// Thickness of the initial mesh's thinnest parts (mm): the thinnest 2 % of its area
    /// ([`THIN_SHARE`]) is thinner; it bounds the warm-up's edge ([`stage_edge_mm`]).
    #[serde(default)]
    pub thin_part_mm: Option<f64>,
    /// The file (in the output folder) of the mesh the run started from.
    pub start_mesh: String,
    pub stages_done: usize,
    pub history: Vec<IterationRecord>,
    pub stages: Vec<StageReport>,
    /// The warm-up judged against the start mesh on the held-out views, once it has ended.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warm_up: Option<WarmUpVerdict>,
    /// The membrane term judged on the first stage after the warm-up, once it has ended.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub membrane: Option<MembraneVerdict>,
    /// Whether the surface is flat-faced or curved, judged before the first stage whose
    /// smoothing is raised (with `smoothing_edge_curved` set).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub surface: Option<super::flatness::SurfaceVerdict>,
    /// What the run's inputs were read from ([`fingerprint`]).
    #[serde(default)]
    pub inputs: super::fingerprint::Fingerprint,
    /// The refractive index the run was given (known, or a range to estimate it in; `None` in
    /// checkpoints that predate it: the scan's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ior: Option<crate::scan::Ior>,
    /// A run with an unknown index: the last stage's estimate, which the next stage starts from
    /// ([`super::index`]); `None`: the given index (before the first stage of an unknown one,
    /// [`super::Inputs::ior_start`] or the range's middle).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ior_estimate: Option<f64>,
    /// A run with an unknown index: per stage so far, the index it started from and its
    /// estimate.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ior_fits: Vec<[f64; 2]>,
}

impl Checkpoint {
    /// Stage `s`'s settings and its index in its schedule ([`Settings::stage`]), with the
    /// smoothing the surface verdict chose.
    pub fn stage_settings(&self, s: usize) -> (super::config::Settings, usize) {
        match &self.surface {
            Some(v) if v.curved => self.settings.with_curved_smoothing().stage(s),
            _ => self.settings.stage(s),
        }
    }

    /// The refractive index the next stage runs at.
    pub fn index(&self, inputs: &super::Inputs) -> f64 {
        (self.ior_estimate.or(inputs.ior_start)).unwrap_or_else(|| inputs.ior.nominal())
    }
}

/// Whether the warm-up made the mesh fit the held-out views better: DRT's steps carve what the
/// hull left (a wedge between legs) but on flat faces, where the hull is already close, they
/// can leave the mesh worse than it started; the first warm-up stage that fits worse ends the
/// warm-up, and the stages after it start from the start mesh instead.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WarmUpVerdict {
    /// Held-out refraction term of the start mesh and of the last warm-up stage's mesh judged.
    pub start_refraction: f64,
    pub warm_up_refraction: f64,
    /// True: the next stages start from the start mesh.
    pub discarded: bool,
}

/// Whether the membrane term ([`Settings::weight_membrane`]) acts after the first stage that
/// follows the warm-up (the judged stage). A face seen only edge-on (a block's top) is unseen at
/// that stage's coarse edges already, and flattening it is right; a rounded cap seen edge-on is
/// unseen too, and flattening it makes the held-out outlines, which show its profile, fit
/// several times worse than the same stage without the term. A face seen edge-on is a large part
/// of the surface at those edges; patches that are a few percent there, or appear only at finer
/// edges, are a cap's pole or curved detail no ray happened to touch: the term stays off when
/// it acted on less than [`MEMBRANE_MIN_SHARE`] of the judged stage's vertices.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MembraneVerdict {
    /// The largest share of the judged stage's vertices the term acted on in one iteration.
    pub share: f64,
    /// Held-out silhouette term of the judged stage's mesh with the term and of the same stage
    /// run without it (`None`: not run, as no patch formed or no views are held out).
    pub silhouette_with: Option<f64>,
    pub silhouette_without: Option<f64>,
    /// True: the judged stage's mesh is the one with the term, and the term acts in the later
    /// stages; false: the stage without it stands (when the term acted) and the term is off.
    pub kept: bool,
}

/// The judged stage's held-out silhouette term with the membrane over without it above which
/// the term is rejected: measured 0.98–1.44 on the block's and the prism's scans, where
/// flattening was right, and 4.75 on the demo's pebble, where it was wrong
/// (docs/decisions.md#faces-no-ray-sees-the-membrane-term).
pub const MEMBRANE_SILHOUETTE_RATIO: f64 = 2.0;

/// The smallest share of the judged stage's vertices the membrane term must have acted on to be
/// kept: the block's top and bottom are 21 % of its vertices at its first Large Steps stage, the
/// prism's 27 %; a small pebble's poles at coarse edges 3 % (the term then flattened them in the
/// later stages), the dog's at 1280×960 2 %
/// (docs/decisions.md#faces-no-ray-sees-the-membrane-term).
pub const MEMBRANE_MIN_SHARE: f64 = 0.05;

#[cfg(test)]
impl Checkpoint {
    /// A fresh run's checkpoint with `balanced`'s settings, a 240 mm start mesh whose thin parts
    /// are `thin_part_mm` thick, and no inputs.
    pub(crate) fn example(thin_part_mm: Option<f64>) -> Self {
        Checkpoint {
            settings: super::config::Settings::preset(super::config::Preset::Balanced),
            diagonal_mm: 240.0,
            thin_part_mm,
            start_mesh: "start.ply".into(),
            stages_done: 0,
            history: Vec::new(),
            stages: Vec::new(),
            warm_up: None,
            membrane: None,
            surface: None,
            inputs: Default::default(),
            ior: None,
            ior_estimate: None,
            ior_fits: Vec::new(),
        }
    }
}
