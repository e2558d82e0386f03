//! Settings of a reconstruction: presets, and a TOML file that overrides any single key.

use serde::{Deserialize, Serialize};

use crate::loss::refraction::{ResidualForm, MAX_FOOTPRINT};
use crate::loss::silhouette::SilhouetteForm;
use crate::loss::smoothness::Smoothness;
use crate::loss::targets::TargetWeights;
use crate::loss::Robust;
use crate::trace::path::NormalModel;

/// The built-in settings, from quickest to most accurate, and DRT's own schedule.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    Fast,
    Balanced,
    Accurate,
    Drt,
}

impl Preset {
    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Fast => "fast",
            Preset::Balanced => "balanced",
            Preset::Accurate => "accurate",
            Preset::Drt => "drt",
        }
    }
}

impl std::fmt::Display for Preset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The optimiser.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Optimizer {
    /// DRT's: per-vertex offsets, SGD with Nesterov momentum; the learning rate (mm per unit of
    /// clamped gradient) goes from `lr_start` to `lr_end` with 1/lr linear over the stages;
    /// gradient components clamped to [−1, 1].
    Sgd {
        lr_start: f64,
        lr_end: f64,
        momentum: f64,
    },
    /// Nicolet et al. 2021: u = (I + λL)x with the uniform Laplacian L, the gradient mapped by a
    /// cached sparse Cholesky solve, Adam with one second moment for all vertices (their
    /// root-mean-square here, where the paper takes the maximum; each step clamped to 3 learning
    /// rates); the learning rate is `lr_edge` edge lengths of the stage. With `clip` > 0 each
    /// vertex's gradient ∂E/∂x is first cut to at most `clip` times the 99th percentile of the
    /// non-zero lengths, so that one outlying ray cannot fill the shared second moment and freeze
    /// every other vertex (0, also when a config omits it: no cut). The
    /// learning rate falls geometrically over each stage's iterations to `lr_end_share` of itself
    /// (1, also when omitted: constant), so that a stage ends near its minimum rather than at the
    /// noise of its sampled views. The edges at a crease vertex — one whose faces turn more than
    /// `crease_deg` degrees from its normal ([`crate::mesh::TriMesh::normal_spread`], measured on
    /// the stage's start mesh) — weigh `crease_share` of λ, so that a sharp edge the data ask
    /// for can form rather than spread over the faces beside it (0, also when omitted: no
    /// crease vertices).
    LargeSteps {
        lambda: f64,
        lr_edge: f64,
        beta1: f64,
        beta2: f64,
        #[serde(default)]
        clip: f64,
        #[serde(default = "one_f64")]
        lr_end_share: f64,
        #[serde(default)]
        crease_deg: f64,
        #[serde(default = "one_f64")]
        crease_share: f64,
    },
}

/// Everything that decides a reconstruction (recorded in the report and the checkpoint).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    pub preset: Preset,
    pub seed: u64,
    /// Remeshing stages; edge lengths from `start_edge` to `final_edge` with 1/length linear in
    /// the stage index, both as a share of the initial mesh's bounding-box diagonal.
    pub stages: usize,
    pub start_edge: f64,
    pub final_edge: f64,
    pub iterations: usize,
    /// Split–collapse–flip–relax rounds of each stage's remesh ([`crate::remesh`]).
    pub remesh_iterations: usize,
    pub optimizer: Optimizer,
    /// Term weights (each term is a weighted mean over its rays or edges).
    pub weight_refraction: f64,
    pub weight_silhouette: f64,
    pub weight_smoothness: f64,
    /// Views per iteration for the refraction and silhouette terms.
    pub refraction_views: usize,
    pub silhouette_views: usize,
    /// How far apart (share of the current mesh's bounding-box diagonal) the refraction rays
    /// of a view lie at the object at most: each iteration draws that share of a view's
    /// decoded pixels that puts them so far apart, (pixel / spacing)² at the depth of the mesh's
    /// centre (all where the pixels are coarser), systematically from a random offset, each
    /// weighted by the inverse of the share (unbiased sums). The ray count then follows the
    /// scene, not the camera's pixel count (docs/decisions.md#rays-that-follow-the-scene).
    pub ray_spacing: f64,
    /// Where the current mesh's edges are finer than `ray_spacing`, an iteration's rays lie this
    /// many of its mean edge lengths apart instead (0: `ray_spacing` alone); never closer than
    /// the kept sample ([`Settings::kept_spacing_share`]). Fine stages then get more of the rays
    /// their edges can resolve, coarse ones no fewer than before
    /// (docs/decisions.md#rays-that-follow-the-mesh; absent in reports written before it
    /// existed).
    #[serde(default)]
    pub ray_edge_spacing: f64,
    pub normals: NormalModel,
    pub residual: ResidualForm,
    pub robust: Robust,
    pub max_refractions: u32,
    pub silhouette: SilhouetteForm,
    pub smoothness: Smoothness,
    /// Weights of the decoded monitor points (absent in reports written before it existed).
    #[serde(default)]
    pub target_weights: TargetWeights,
    /// Refraction rays meeting an interface with cos θi or cos θt below this are dropped
    /// (bounded per-ray influence; 0: only those without a usable derivative).
    pub min_cos: f64,
    /// Pixels whose decoded cell is at most this many direct footprints wide (a camera pixel's
    /// footprint on the monitor seen without the object), or one monitor pixel, keep their rays
    /// below `min_cos` (0: none do; absent in reports written before it existed).
    #[serde(default)]
    pub grazing_cell_footprints: f64,
    /// Refraction rays per pixel side: a pixel is modelled by the mean residual of an n×n grid
    /// of rays over its area (1: its centre ray; the cost grows as n²). 0 ([`AUTO_FOOTPRINT`]):
    /// chosen by the run from the camera pixel at the object ([`Settings::resolve_footprint`]).
    #[serde(default = "one")]
    pub footprint: u32,
    /// Weight of the per-bit term: per pixel, the measured contrasts of the Gray bits around its
    /// decoded cell against the share of its modelled footprint each pattern lights, relative
    /// to the refraction residual's penalty (0: off; scans decoded before it existed have no
    /// contrasts).
    #[serde(default)]
    pub weight_bits: f64,
    /// Correct the decoded points for the camera's blur (`blur_px` in scan.toml): at the start
    /// of every stage after the warm-up, and for the result's held-out fit, each pixel's point
    /// moves by where its blurred neighbourhood's vote lands off its centre ray's
    /// ([`crate::loss::blur`]). Off in the presets: it costs about 6 s a stage on a 640×480
    /// scan (docs/decisions.md#decoded-points-corrected-for-the-cameras-blur). Idle for a sharp
    /// camera.
    #[serde(default)]
    pub blur_correction: bool,
    /// The robust penalty's scale in the first stage after the warm-up, as a multiple of
    /// `robust`'s; it shrinks geometrically to `robust`'s at the last stage (graduated
    /// non-convexity: far from the shape every residual is large, and a small scale would
    /// hold back the very rays that must move it). 1: the same scale throughout.
    #[serde(default = "one_f64")]
    pub robust_anneal: f64,
    /// Share of the views held out of the optimisation to validate every stage on (0: none);
    /// the stage that fits them best is the result.
    pub validation_share: f64,
    /// Warm-up stages run before `stages`: the first `warmup_stages` stages of the `drt` preset
    /// (its optimiser, learning rates, terms, weights and iterations; seed, target weights and
    /// footprint from here), all at this schedule's `start_edge`. DRT's clamped SGD carves what the visual
    /// hull filled in (a concavity no silhouette shows) within a few stages, where Large Steps
    /// from the hull does not; Large Steps then refines without SGD's plateau.
    #[serde(default)]
    pub warmup_stages: usize,
    /// Share of each stage's last iterations whose vertex positions are averaged (Polyak–Ruppert
    /// tail averaging: with a constant learning rate the iterates scatter about the minimum by
    /// the noise of the sampled views, and their mean scatters less); the stage keeps the mean
    /// or its last iterate, whichever fits the held-out views better. 0: the last iterate. The
    /// warm-up's stages take `drt`'s (0).
    #[serde(default)]
    pub average_share: f64,
    /// Weight of the membrane term ([`crate::loss::membrane`]) on the vertices no compared
    /// refraction ray's path has touched in the stage so far (faces seen only edge-on), relative
    /// to the other terms; it starts once every fitted view has had about one sample. The run
    /// judges it on its first stage after the warm-up, which runs again without it, and keeps
    /// it only if it acted there on a large share of the vertices and left the held-out outlines
    /// within a factor of the run without it ([`crate::reconstruct::MembraneVerdict`]). 0: off.
    #[serde(default, alias = "weight_unseen")]
    pub weight_membrane: f64,
    /// In the stages whose target edge is shorter than this share of the diagonal, Large Steps'
    /// λ and the smoothness weight are raised by (this / the stage's edge)², so that both hold
    /// the surface over as many millimetres as at this edge: λ acts on the combinatorial
    /// Laplacian, whose reach is about √λ edges, and the smoothness term is a mean over edges
    /// whose dihedral angles on a given bend shrink with the edge. 0: the same in every stage.
    #[serde(default)]
    pub smoothing_edge: f64,
    /// `smoothing_edge` for a curved surface: before the first stage `smoothing_edge` raises,
    /// a surface less than a quarter of whose area is flat at that stage's edge smooths to this
    /// share of the diagonal instead ([`crate::reconstruct::flatness`]). 0: `smoothing_edge`
    /// on every surface.
    #[serde(default)]
    pub smoothing_edge_curved: f64,
    /// Edges that follow the surface: in the stages after the warm-up, the remesh gives each
    /// place the edge whose chord deviates from the current surface's curvature by this share
    /// of the stage's edge, between the stage's edge (where the surface bends) and
    /// `sizing_max_edge` times it (where it is flat) ([`crate::remesh::AdaptiveSizing`]). 0:
    /// every edge the stage's.
    #[serde(default)]
    pub sizing_error: f64,
    /// The longest edge of a stage with `sizing_error`, as a multiple of its edge.
    #[serde(default = "one_f64")]
    pub sizing_max_edge: f64,
    /// Edges where the data keeps pulling: before a stage with `sizing_error` remeshes, where
    /// the refraction rays' mean penalty at a vertex exceeds this multiple of the area median,
    /// its edges shrink by the excess (its mean edge × this multiple of the median over its mean
    /// penalty), never below the stage's edge (`crate::reconstruct::pull`). 0: curvature alone.
    #[serde(default)]
    pub sizing_pull: f64,
    /// The silhouette term's unit of distance at the object, as a share of the current mesh's
    /// bounding-box diagonal: its loss is squared within one unit of the outline and linear
    /// beyond ([`crate::loss::silhouette`]), the same at every camera resolution. The presets'
    /// 1/250 is a camera pixel of a 640×480 view of an object filling a quarter of its height.
    pub silhouette_scale: f64,
    /// How far (outline units, `silhouette_scale`) beside a contour edge's projected midpoint
    /// its two probe rays look: the edge counts only if the mesh is hit on one side and missed
    /// on the other, so only edges within this distance of the mesh's own outline pull on the
    /// silhouettes. An edge hidden just inside the outline (the contour of a mesh zigzags)
    /// would pull outward with nothing to balance it
    /// (docs/decisions.md#the-silhouettes-probes-and-the-holes-the-decoder-filled). DRT's: 1.
    pub silhouette_probe: f64,
}

impl Optimizer {
    /// This optimiser with Large Steps' λ multiplied by `gain` (SGD has none).
    fn with_lambda_gain(mut self, gain: f64) -> Self {
        if let Optimizer::LargeSteps { lambda, .. } = &mut self {
            *lambda *= gain;
        }
        self
    }
}

/// Settings of earlier versions, in camera pixels, and what replaced them.
const RETIRED: [(&str, &str); 1] = [(
    "pixel_stride",
    "use ray_spacing (how far apart the rays lie at the object, a share of the diagonal)",
)];

/// How many times as dense (per area) as `ray_spacing`'s rays the run's kept sample of each view
/// is: an iteration on a coarse mesh draws a quarter of it where the camera's pixels are finer
/// than the kept spacing.
pub const KEPT_DENSITY: f64 = 4.0;

/// The largest `ray_edge_spacing`, mean edges: coarser rays would leave faces unseen.
const MAX_RAY_EDGE_SPACING: f64 = 10.0;

/// `footprint = 0`: rays per pixel side chosen by the run ([`Settings::resolve_footprint`]).
pub const AUTO_FOOTPRINT: u32 = 0;

fn one() -> u32 {
    1
}

fn one_f64() -> f64 {
    1.0
}

/// The most stages of a schedule.
pub const MAX_STAGES: usize = 100;
/// The most iterations of a stage (and remesh iterations).
pub const MAX_ITERATIONS: usize = 100_000;

/// Checks the optimiser's settings.
fn check_optimizer(o: &Optimizer) -> Result<(), String> {
    let positive = |v: f64| v > 0.0 && v.is_finite();
    let moment = |v: f64| (0.0..1.0).contains(&v);
    match *o {
        Optimizer::Sgd {
            lr_start,
            lr_end,
            momentum,
        } => {
            if !(positive(lr_start) && positive(lr_end)) {
                return Err("setting optimizer.sgd: lr_start and lr_end must be positive".into());
            }
            if !moment(momentum) {
                return Err("setting optimizer.sgd: momentum must lie in [0, 1)".into());
            }
        }
        Optimizer::LargeSteps {
            lambda,
            lr_edge,
            beta1,
            beta2,
            clip,
            lr_end_share,
            crease_deg,
            crease_share,
        } => {
            if !(0.0..=90.0).contains(&crease_deg) {
                return Err(
                    "setting optimizer.large_steps: crease_deg must lie in [0, 90] degrees (0: off)"
                        .into(),
                );
            }
            if !(crease_share > 0.0 && crease_share <= 1.0) {
                return Err(
                    "setting optimizer.large_steps: crease_share must lie in (0, 1]".into(),
                );
            }
            if !(clip.is_finite() && clip >= 0.0) {
                return Err(
                    "setting optimizer.large_steps: clip must be 0 (off) or positive".into(),
                );
            }
            if !(lr_end_share > 0.0 && lr_end_share <= 1.0) {
                return Err(
                    "setting optimizer.large_steps: lr_end_share must lie in (0, 1]".into(),
                );
            }
            if !(positive(lambda) && positive(lr_edge)) {
                return Err(
                    "setting optimizer.large_steps: lambda and lr_edge must be positive".into(),
                );
            }
            if !(moment(beta1) && moment(beta2)) {
                return Err(
                    "setting optimizer.large_steps: beta1 and beta2 must lie in [0, 1)".into(),
                );
            }
        }
    }
    Ok(())
}

/// `balanced`'s and `accurate`'s edges that follow the surface: a chord within a fiftieth of
/// the stage's edge from the surface, and at most three times the stage's edge where it is flat
/// (docs/decisions.md#edges-that-follow-the-surface).
const SIZING_ERROR: f64 = 0.02;
const SIZING_MAX_EDGE: f64 = 3.0;
/// `balanced`'s and `accurate`'s edges where the data keeps pulling: at vertices whose rays'
/// mean penalty exceeds 1.5 times the area median
/// (docs/decisions.md#edges-where-the-data-keeps-pulling).
const SIZING_PULL: f64 = 1.5;

impl Settings {
    /// The preset's settings.
    pub fn preset(preset: Preset) -> Self {
        let fast = Self::fast();
        let settings = match preset {
            Preset::Fast => fast,
            Preset::Balanced => Self::balanced(fast),
            Preset::Accurate => Self::accurate(fast),
            Preset::Drt => Self::drt(fast),
        };
        Settings { preset, ..settings }
    }

    /// `fast`'s settings, from which the other presets start.
    fn fast() -> Self {
        let large_steps = Optimizer::LargeSteps {
            lambda: 20.0,
            lr_edge: 0.3,
            beta1: 0.9,
            beta2: 0.999,
            clip: 10.0,
            lr_end_share: 1.0,
            // No crease vertices: the block loses with them
            // (docs/decisions.md#creases-under-large-steps).
            crease_deg: 0.0,
            crease_share: 1.0,
        };
        Settings {
            preset: Preset::Fast,
            seed: 0,
            stages: 3,
            start_edge: 1.0 / 60.0,
            final_edge: 1.0 / 150.0,
            iterations: 80,
            remesh_iterations: 5,
            optimizer: large_steps,
            weight_refraction: 1.0,
            weight_silhouette: 0.1,
            weight_smoothness: 0.05,
            refraction_views: 2,
            silhouette_views: 4,
            ray_spacing: 1.0 / 180.0,
            ray_edge_spacing: 0.4,
            normals: NormalModel::Vertex,
            residual: ResidualForm::Direction,
            robust: Robust::Cauchy(0.2),
            max_refractions: 2,
            silhouette: SilhouetteForm::Distance,
            smoothness: Smoothness::LogTwoMinusCos,
            target_weights: TargetWeights::Uniform,
            warmup_stages: 3,
            validation_share: 0.1,
            // Grazing and near-critical rays are dropped: their decoded points lie off the
            // centre ray's, outward; not where the decoded cell is fine, as on flat faces seen
            // edge-on (docs/decisions.md#faces-no-ray-sees-the-membrane-term).
            min_cos: 0.3,
            grazing_cell_footprints: 3.0,
            footprint: 1,
            weight_bits: 0.01,
            blur_correction: false,
            robust_anneal: 1.0,
            average_share: 0.5,
            weight_membrane: 10.0,
            smoothing_edge: 0.0,
            smoothing_edge_curved: 0.0,
            sizing_error: 0.0,
            sizing_max_edge: 1.0,
            sizing_pull: 0.0,
            silhouette_scale: 1.0 / 250.0,
            silhouette_probe: 0.03,
        }
    }

    /// `balanced`'s settings: `fast`'s (`base`) with finer last edges, more iterations and views
    /// per iteration, and edges that follow the surface.
    fn balanced(base: Self) -> Self {
        Settings {
            final_edge: 1.0 / 250.0,
            iterations: 150,
            refraction_views: 4,
            silhouette_views: 8,
            sizing_error: SIZING_ERROR,
            sizing_max_edge: SIZING_MAX_EDGE,
            sizing_pull: SIZING_PULL,
            ..base
        }
    }

    /// `accurate`'s settings: `fast`'s (`base`) with more and finer stages, longer ones, and its
    /// footprint and smoothing chosen from the scene.
    fn accurate(base: Self) -> Self {
        Settings {
            stages: 5,
            final_edge: 1.0 / 350.0,
            iterations: 300,
            refraction_views: 4,
            silhouette_views: 8,
            // Rays a camera pixel's width apart at the object about as far as its finest
            // edge: 2×2 where a pixel spans 1.5 finest edges or more
            // (docs/decisions.md#accurate-chooses-its-footprint-from-the-camera-pixel-at-the-object).
            footprint: AUTO_FOOTPRINT,
            // Its stages finer than about `balanced`'s second (1/155 of the diagonal) smooth
            // as far in millimetres as that one on a flat-faced surface, as far as 1/250 on a
            // curved one
            // (docs/decisions.md#accurates-fine-stages-smoothing-that-follows-the-surface).
            smoothing_edge: 0.0065,
            smoothing_edge_curved: 0.004,
            // Its fine stages with closer rays stall at 5 MP
            // (docs/decisions.md#rays-that-follow-the-mesh).
            ray_edge_spacing: 0.0,
            sizing_error: SIZING_ERROR,
            sizing_max_edge: SIZING_MAX_EDGE,
            sizing_pull: SIZING_PULL,
            ..base
        }
    }

    /// `drt`'s settings: DRT's schedule, optimiser and terms over `fast`'s (`base`).
    fn drt(base: Self) -> Self {
        // DRT sums its terms (weights 40·217.5/H² per ray, 2e-3·217.5/H per contour edge,
        // 0.08·mean edge/10 per edge, H = 960); the weights here turn glasscan's means into
        // those sums for a 1280×960 view of a ~250 mm object (~1e5 rays, ~2e3 contour edges per
        // view, ~1.4e5 edges).
        Settings {
            stages: 20,
            start_edge: 1.0 / 30.0,
            final_edge: 1.0 / 300.0,
            iterations: 200,
            remesh_iterations: 3,
            optimizer: Optimizer::Sgd {
                lr_start: 0.1,
                lr_end: 0.05,
                momentum: 0.95,
            },
            weight_refraction: 900.0,
            weight_silhouette: 7.0,
            weight_smoothness: 1100.0,
            refraction_views: 1,
            silhouette_views: 8,
            ray_spacing: 1.0 / 250.0,
            ray_edge_spacing: 0.0,
            normals: NormalModel::Face,
            residual: ResidualForm::Direction,
            robust: Robust::L2,
            silhouette: SilhouetteForm::Drt,
            smoothness: Smoothness::NegLogOnePlusCos,
            warmup_stages: 0,
            validation_share: 0.0,
            min_cos: 0.0,
            average_share: 0.0,
            weight_bits: 0.0,
            weight_membrane: 0.0,
            silhouette_probe: 1.0,
            ..base
        }
    }

    /// The preset's settings with the keys of a TOML file (any subset of [`Settings`]'s)
    /// overriding them; unknown keys and wrong types are errors naming them.
    pub fn with_overrides(self, toml_text: &str) -> Result<Self, String> {
        let mut value = toml::Value::try_from(&self).map_err(|e| e.to_string())?;
        let over: toml::Table = toml::from_str(toml_text).map_err(|e| e.message().to_string())?;
        let table = value.as_table_mut().expect("settings serialise to a table");
        for (k, v) in over {
            if let Some((_, instead)) = RETIRED.iter().find(|(old, _)| *old == k) {
                return Err(format!("setting '{k}' was retired: {instead}"));
            }
            if !table.contains_key(&k) {
                return Err(format!(
                    "unknown setting '{k}' (settings: {})",
                    table.keys().cloned().collect::<Vec<_>>().join(", ")
                ));
            }
            table.insert(k, v);
        }
        value
            .try_into()
            .map_err(|e: toml::de::Error| e.message().to_string())
    }

    /// Checks ranges; the message names the setting.
    pub fn check(&self) -> Result<(), String> {
        self.check_schedule()?;
        self.check_sizing()?;
        self.check_terms()?;
        check_optimizer(&self.optimizer)
    }

    /// Stages, iterations, edge lengths, sampling.
    fn check_schedule(&self) -> Result<(), String> {
        let bad = |k: &str, why: &str| Err(format!("setting {k}: {why}"));
        for (k, v, max) in [
            ("stages", self.stages, MAX_STAGES),
            ("iterations", self.iterations, MAX_ITERATIONS),
            (
                "remesh_iterations",
                self.remesh_iterations.max(1),
                MAX_ITERATIONS,
            ),
        ] {
            if v == 0 || v > max {
                return bad(k, &format!("must lie in 1..={max}"));
            }
        }
        let drt_stages = Settings::preset(Preset::Drt).stages;
        if self.warmup_stages > drt_stages {
            return bad(
                "warmup_stages",
                &format!("DRT's schedule has {drt_stages} stages"),
            );
        }
        if !(self.start_edge > 0.0 && self.final_edge > 0.0 && self.final_edge <= self.start_edge)
            || self.start_edge > 1.0
        {
            return bad(
                "start_edge/final_edge",
                "need 0 < final_edge ≤ start_edge ≤ 1 (shares of the diagonal)",
            );
        }
        if self.refraction_views == 0 {
            return bad("refraction_views", "must be at least 1");
        }
        if !(self.ray_spacing > 0.0 && self.ray_spacing <= 0.1) {
            return bad(
                "ray_spacing",
                "must lie in (0, 0.1] (a share of the diagonal)",
            );
        }
        if !(0.0..=MAX_RAY_EDGE_SPACING).contains(&self.ray_edge_spacing) {
            return bad(
                "ray_edge_spacing",
                &format!("must lie in [0, {MAX_RAY_EDGE_SPACING}] (mean edges; 0: ray_spacing)"),
            );
        }
        if !(0.0..0.5).contains(&self.min_cos) {
            return bad("min_cos", "must lie in [0, 0.5)");
        }
        if !(self.grazing_cell_footprints >= 0.0 && self.grazing_cell_footprints.is_finite()) {
            return bad("grazing_cell_footprints", "must be 0 or more");
        }
        if !(0.0..=0.5).contains(&self.validation_share) {
            return bad("validation_share", "must lie in [0, 0.5]");
        }
        if !(0.0..1.0).contains(&self.average_share) {
            return bad("average_share", "must lie in [0, 1)");
        }
        Ok(())
    }

    /// The graded stages' sizing field and `accurate`'s raised smoothing.
    fn check_sizing(&self) -> Result<(), String> {
        let bad = |k: &str, why: &str| Err(format!("setting {k}: {why}"));
        if !(0.0..=1.0).contains(&self.sizing_error) {
            return bad(
                "sizing_error",
                "must lie in [0, 1] (a share of the stage's edge; 0: off)",
            );
        }
        if !(self.sizing_pull == 0.0 || (1.0..=100.0).contains(&self.sizing_pull)) {
            return bad(
                "sizing_pull",
                "must be 0 (off) or lie in [1, 100] (a multiple of the median penalty)",
            );
        }
        if !(1.0..=10.0).contains(&self.sizing_max_edge) {
            return bad(
                "sizing_max_edge",
                "must lie in [1, 10] (a multiple of the stage's edge)",
            );
        }
        if !(0.0..=1.0).contains(&self.smoothing_edge) {
            return bad(
                "smoothing_edge",
                "must lie in [0, 1] (a share of the diagonal; 0: off)",
            );
        }
        if !(0.0..=1.0).contains(&self.smoothing_edge_curved) {
            return bad(
                "smoothing_edge_curved",
                "must lie in [0, 1] (a share of the diagonal; 0: smoothing_edge)",
            );
        }
        Ok(())
    }

    /// The terms: refraction count, robust loss, smoothness penalty, weights.
    fn check_terms(&self) -> Result<(), String> {
        let bad = |k: &str, why: &str| Err(format!("setting {k}: {why}"));
        let max = crate::trace::path::MAX_TRAIL as u32;
        if self.max_refractions < 2 || self.max_refractions > max || self.max_refractions % 2 == 1 {
            return bad(
                "max_refractions",
                &format!("must be even and lie in 2..={max} (a ray enters and leaves)"),
            );
        }
        if !(self.robust_anneal >= 1.0 && self.robust_anneal <= 1e3) {
            return bad("robust_anneal", "must lie in [1, 1000]");
        }
        if self.footprint > MAX_FOOTPRINT {
            return bad(
                "footprint",
                &format!(
                    "rays per pixel side must lie in 1..={MAX_FOOTPRINT} (0: chosen by the run)"
                ),
            );
        }
        match self.robust {
            Robust::Huber(d) | Robust::Cauchy(d) if !(d > 0.0 && d.is_finite()) => {
                return bad("robust", "the scale δ must be a positive number");
            }
            _ => {}
        }
        if !(self.silhouette_scale > 0.0 && self.silhouette_scale <= 0.1) {
            return bad(
                "silhouette_scale",
                "must lie in (0, 0.1] (a share of the diagonal)",
            );
        }
        if !(self.silhouette_probe > 0.0 && self.silhouette_probe <= 4.0) {
            return bad(
                "silhouette_probe",
                "the probe distance must lie in (0, 4] outline units (silhouette_scale)",
            );
        }
        if let Smoothness::Tolerant { tau } = self.smoothness {
            if !(tau > 0.0 && tau.is_finite()) {
                return bad("smoothness", "τ must be a positive number");
            }
        }
        for (k, w) in [
            ("weight_refraction", self.weight_refraction),
            ("weight_silhouette", self.weight_silhouette),
            ("weight_smoothness", self.weight_smoothness),
            ("weight_bits", self.weight_bits),
            ("weight_membrane", self.weight_membrane),
        ] {
            if !(w >= 0.0 && w.is_finite()) {
                return bad(k, "must be a finite weight ≥ 0");
            }
        }
        Ok(())
    }

    /// Stages in all, the warm-up included.
    pub fn total_stages(&self) -> usize {
        self.warmup_stages + self.stages
    }

    /// The settings that drive stage `g` (0-based over [`Self::total_stages`], warm-up first)
    /// and the stage's index in their own schedule.
    pub fn stage(&self, g: usize) -> (Settings, usize) {
        if g < self.warmup_stages {
            let drt = Settings {
                seed: self.seed,
                target_weights: self.target_weights,
                start_edge: self.start_edge,
                final_edge: self.start_edge,
                footprint: self.footprint,
                ..Settings::preset(Preset::Drt)
            };
            (drt, g)
        } else {
            let k = g - self.warmup_stages;
            let left = if self.stages > 1 {
                (self.stages - 1 - k) as f64 / (self.stages - 1) as f64
            } else {
                0.0
            };
            let gain = self.smoothing_gain(k);
            let stage = Settings {
                robust: self.robust.scaled(self.robust_anneal.powf(left)),
                optimizer: self.optimizer.with_lambda_gain(gain),
                weight_smoothness: self.weight_smoothness * gain,
                ..self.clone()
            };
            (stage, k)
        }
    }

    /// Rays per pixel side for a run whose decoded points measure whole camera pixels that
    /// span `pixel_mm` at the object (mm; `None`: the points are exact centre-ray
    /// correspondences, as `simulate --decoded-only` writes and imports carry) and whose start
    /// mesh's bounding-box diagonal is `diagonal_mm`: `footprint` when set, else
    /// ([`AUTO_FOOTPRINT`]) the count that spaces the rays across a pixel about one last-stage
    /// edge apart, round(pixel / edge) within 1..=[`MAX_FOOTPRINT`] (1 for centre-ray points).
    pub fn resolve_footprint(&self, pixel_mm: Option<f64>, diagonal_mm: f64) -> u32 {
        if self.footprint != AUTO_FOOTPRINT {
            return self.footprint;
        }
        let per_edge = pixel_mm.map_or(f64::NAN, |p| p / self.last_edge_mm(diagonal_mm));
        if per_edge.is_finite() {
            (per_edge.round() as u32).clamp(1, MAX_FOOTPRINT)
        } else {
            1
        }
    }

    /// Whether a run committed with `committed` (its footprint resolved) continues under these
    /// settings: equal, but for a footprint these leave to the run.
    pub fn continues(&self, committed: &Settings) -> bool {
        let footprint = match self.footprint {
            AUTO_FOOTPRINT => committed.footprint,
            n => n,
        };
        Settings {
            footprint,
            ..self.clone()
        } == *committed
    }

    /// How far apart the run's kept sample of each view puts its rays at the object, as a share
    /// of the start mesh's bounding-box diagonal: [`KEPT_DENSITY`] times as dense as
    /// `ray_spacing`'s rays. The closest an iteration's rays lie, whatever `ray_edge_spacing`
    /// asks (docs/decisions.md#rays-that-follow-the-mesh).
    pub fn kept_spacing_share(&self) -> f64 {
        self.ray_spacing / KEPT_DENSITY.sqrt()
    }

    /// Target edge length of stage `s` of this schedule (mm) for an initial bounding-box
    /// diagonal `diag`.
    pub fn edge_mm(&self, s: usize, diag: f64) -> f64 {
        diag * self.edge_share(s)
    }

    /// Target edge length of this schedule's last stage (mm) for an initial bounding-box
    /// diagonal `diag`.
    pub fn last_edge_mm(&self, diag: f64) -> f64 {
        self.edge_mm(self.stages - 1, diag)
    }

    /// Target edge length of stage `s` of this schedule as a share of the diagonal.
    fn edge_share(&self, s: usize) -> f64 {
        let t = if self.stages > 1 {
            s as f64 / (self.stages - 1) as f64
        } else {
            1.0
        };
        1.0 / ((1.0 - t) / self.start_edge + t / self.final_edge)
    }

    /// How much stage `s` raises λ and the smoothness weight: (smoothing_edge / its edge)², at
    /// least 1.
    fn smoothing_gain(&self, s: usize) -> f64 {
        (self.smoothing_edge / self.edge_share(s)).powi(2).max(1.0)
    }

    /// Whether stage `g` (counting the warm-up) is the first whose smoothing is raised and the
    /// settings choose it by the surface (`smoothing_edge_curved` set): where the run judges
    /// the surface.
    pub fn judges_surface_before(&self, g: usize) -> bool {
        let raised =
            |g: usize| g >= self.warmup_stages && self.smoothing_gain(g - self.warmup_stages) > 1.0;
        self.smoothing_edge_curved > 0.0 && raised(g) && (g == 0 || !raised(g - 1))
    }

    /// These settings with a curved surface's smoothing (`smoothing_edge_curved`, if set).
    pub fn with_curved_smoothing(&self) -> Settings {
        Settings {
            smoothing_edge: match self.smoothing_edge_curved {
                e if e > 0.0 => e,
                _ => self.smoothing_edge,
            },
            ..self.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scan::decoded::MonitorTarget;

    #[test]
    fn target_weights_are_a_setting() {
        let s = Settings::preset(Preset::Fast);
        assert_eq!(s.target_weights, TargetWeights::Uniform);
        let s = s.with_overrides("target_weights = \"cell\"\n").unwrap();
        assert_eq!(s.target_weights, TargetWeights::Cell);
        let cell = |c: f64| MonitorTarget {
            u: 10.0,
            v: 20.0,
            cell_u: c,
            cell_v: c,
        };
        assert_eq!(TargetWeights::Cell.weight(&cell(1.0)), 1.0);
        assert_eq!(TargetWeights::Cell.weight(&cell(4.0)), 1.0 / 16.0);
        assert_eq!(TargetWeights::Uniform.weight(&cell(4.0)), 1.0);
        assert!(s.with_overrides("target_weights = \"area\"\n").is_err());
    }

    #[test]
    fn rays_follow_the_mesh_in_fast_and_balanced_but_not_in_their_warm_up() {
        for preset in [Preset::Fast, Preset::Balanced] {
            let s = Settings::preset(preset);
            assert_eq!(s.ray_edge_spacing, 0.4);
            assert_eq!(s.stage(0).0.ray_edge_spacing, 0.0, "the warm-up is DRT's");
            assert_eq!(s.kept_spacing_share(), s.ray_spacing / 2.0);
        }
        for preset in [Preset::Accurate, Preset::Drt] {
            assert_eq!(Settings::preset(preset).ray_edge_spacing, 0.0);
        }
        let s = Settings::preset(Preset::Balanced);
        for bad in ["-0.1", "10.5", "nan"] {
            let over = s
                .clone()
                .with_overrides(&format!("ray_edge_spacing = {bad}\n"));
            let err = over.and_then(|s| s.check().map(|_| s)).unwrap_err();
            assert!(err.contains("ray_edge_spacing"), "{err}");
        }
    }

    /// The crease weights are off in the presets and in a `large_steps` table that omits them
    /// (an older config's); out-of-range values are refused by name.
    #[test]
    fn crease_weights_are_an_option_checked_by_name() {
        let crease = |s: &Settings| match s.optimizer {
            Optimizer::LargeSteps {
                crease_deg,
                crease_share,
                ..
            } => (crease_deg, crease_share),
            Optimizer::Sgd { .. } => panic!("not large_steps"),
        };
        let s = Settings::preset(Preset::Balanced);
        assert_eq!(crease(&s), (0.0, 1.0));
        let table = |extra: &str| {
            format!("optimizer = {{ large_steps = {{ lambda = 20.0, lr_edge = 0.3, beta1 = 0.9, beta2 = 0.999{extra} }} }}\n")
        };
        let old = s.clone().with_overrides(&table("")).unwrap();
        assert_eq!(crease(&old), (0.0, 1.0));
        let on = (s.clone())
            .with_overrides(&table(", crease_deg = 25.0, crease_share = 0.25"))
            .unwrap();
        assert_eq!(crease(&on), (25.0, 0.25));
        assert!(on.check().is_ok());
        for (bad, key) in [
            (", crease_deg = 95.0", "crease_deg"),
            (", crease_deg = -1.0", "crease_deg"),
            (", crease_share = 0.0", "crease_share"),
            (", crease_share = 1.5", "crease_share"),
        ] {
            let err = s
                .clone()
                .with_overrides(&table(bad))
                .unwrap()
                .check()
                .unwrap_err();
            assert!(err.contains(key), "{err}");
        }
    }

    #[test]
    fn smoothing_is_raised_only_in_stages_finer_than_the_smoothing_edge() {
        let lambda_of = |s: &Settings, g: usize| match s.stage(g).0.optimizer {
            Optimizer::LargeSteps { lambda, .. } => lambda,
            Optimizer::Sgd { .. } => f64::NAN,
        };
        let raised = Settings::preset(Preset::Accurate);
        assert_eq!(raised.smoothing_edge, 0.0065);
        let plain = raised
            .clone()
            .with_overrides("smoothing_edge = 0.0\n")
            .unwrap();
        let w = plain.warmup_stages;
        for k in 0..plain.stages {
            let edge = plain.edge_share(k);
            let expected = 20.0 * (raised.smoothing_edge / edge).powi(2).max(1.0);
            assert_eq!(lambda_of(&plain, w + k), 20.0, "stage {k}");
            assert!(
                (lambda_of(&raised, w + k) - expected).abs() < 1e-9,
                "stage {k}"
            );
            let smooth = raised.stage(w + k).0.weight_smoothness;
            assert!((smooth - 0.05 * expected / 20.0).abs() < 1e-12, "stage {k}");
            assert_eq!(plain.stage(w + k).0.weight_smoothness, 0.05, "stage {k}");
        }
        // The warm-up's DRT stages keep DRT's weight.
        let drt = Settings::preset(Preset::Drt).weight_smoothness;
        assert_eq!(raised.stage(0).0.weight_smoothness, drt);
        // The last stage (1/350 of the diagonal) smooths as far in millimetres as 0.0065 does;
        // the first two (1/60, 1/132.5) as before.
        let last = lambda_of(&raised, w + plain.stages - 1);
        assert!((last - 20.0 * (350.0f64 * 0.0065).powi(2)).abs() < 1e-9);
        assert_eq!(lambda_of(&raised, w + 1), 20.0);
        assert!(plain
            .clone()
            .with_overrides("smoothing_edge = -1\n")
            .unwrap()
            .check()
            .is_err());
        // A curved surface's stages smooth to `smoothing_edge_curved`: less in every raised
        // stage, the same before; the surface is judged before the first raised stage only.
        let curved = raised.with_curved_smoothing();
        assert_eq!(curved.smoothing_edge, raised.smoothing_edge_curved);
        let first_raised = (0..raised.total_stages())
            .find(|&g| raised.judges_surface_before(g))
            .expect("accurate judges the surface");
        for g in 0..raised.total_stages() {
            let (c, r) = (lambda_of(&curved, g), lambda_of(&raised, g));
            match g >= first_raised {
                true => assert!(c < r, "stage {g}: {c} against {r}"),
                false => assert!(c == r || c.is_nan() && r.is_nan(), "stage {g}"),
            }
            assert_eq!(raised.judges_surface_before(g), g == first_raised);
            assert!(!plain.judges_surface_before(g), "no raised stage");
        }
        assert!(raised
            .with_overrides("smoothing_edge_curved = 2\n")
            .unwrap()
            .check()
            .is_err());
    }

    #[test]
    fn accurate_models_a_pixel_by_rays_about_one_last_edge_apart_at_the_object() {
        let auto = Settings::preset(Preset::Accurate);
        assert_eq!(auto.footprint, AUTO_FOOTPRINT);
        // 350 mm of diagonal: the last stage's edges are 1 mm.
        let n = |pixel_mm: f64| auto.resolve_footprint(Some(pixel_mm), 350.0);
        assert_eq!(
            [n(0.3), n(1.0), n(1.49), n(1.51), n(2.2), n(3.0), n(9.0)],
            [1, 1, 1, 2, 2, 3, 4]
        );
        assert_eq!(n(f64::NAN), 1);
        // Exact centre-ray correspondences are the centre ray's, at any pixel size.
        assert_eq!(auto.resolve_footprint(None, 350.0), 1);
        // A footprint the settings set is kept; the other presets model the centre ray.
        let two = auto.clone().with_overrides("footprint = 2\n").unwrap();
        assert_eq!(two.resolve_footprint(Some(0.1), 350.0), 2);
        assert_eq!(
            Settings::preset(Preset::Balanced).resolve_footprint(Some(5.0), 350.0),
            1
        );
        assert!(auto
            .clone()
            .with_overrides("footprint = 5\n")
            .unwrap()
            .check()
            .is_err());
        // A run committed with the resolved count continues under the preset, not under another
        // count or other settings.
        let committed = Settings {
            footprint: 3,
            ..auto.clone()
        };
        assert!(auto.continues(&committed));
        assert!(!two.continues(&committed));
        let other = auto.with_overrides("iterations = 10\n").unwrap();
        assert!(!other.continues(&committed));
    }
}
