//! Whether a surface has flat faces, for `accurate`'s fine stages: the stages finer than
//! `smoothing_edge` raise the smoothing so that it reaches as far in millimetres as at that
//! edge. Flat glass (a block, a prism) gains from the reach: the data on a flat face is noise
//! about a plane. A curved surface (a figurine) loses detail to it, and smooths to the shorter
//! `smoothing_edge_curved` instead (docs/decisions.md#accurates-fine-stages-smoothing-that-follows-the-surface).
//!
//! The rule is in shares of the surface, not camera pixels: a surface is flat-faced when at least
//! [`FLAT_FACED_SHARE`] of its area is flat at the first raised stage's edge, "flat" meaning that
//! the remesher's curvature rule ([`crate::remesh::curvature_edges`], with the stage's sizing)
//! gives it at least twice that edge.

use serde::{Deserialize, Serialize};

use super::config::Settings;
use crate::mesh::TriMesh;
use crate::remesh::{curvature_edges, AdaptiveSizing};

/// The share of the area that must be flat for a surface to count as flat-faced: measured on
/// `accurate`'s meshes before its first raised stage (the shared objects' physical 640×480
/// scans, seeds 0–2), 0.65 on the block and 0.79 on the prism, under 0.01 on the pig, the dog
/// and the horse.
pub const FLAT_FACED_SHARE: f64 = 0.25;

/// How far a point's curvature edge must reach, in stage edges, for it to count as flat.
const FLAT_EDGES: f64 = 2.0;

/// The surface as the run found it before its first raised stage, and the smoothing it chose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceVerdict {
    /// The stage (index) the verdict was made before.
    pub stage: usize,
    /// The share of the mesh's area that is flat at that stage's edge.
    pub flat_share: f64,
    /// True: the surface is curved, and the raised stages smooth to `smoothing_edge_curved`.
    pub curved: bool,
}

/// The share of `mesh`'s area (world frame, mm) whose curvature edge, with `settings`' sizing at
/// a stage edge of `edge_mm`, is at least [`FLAT_EDGES`] times that edge; 0 for a mesh without
/// area or a schedule without sizing.
pub fn flat_share(mesh: &TriMesh, edge_mm: f64, settings: &Settings) -> f64 {
    if settings.sizing_error <= 0.0 {
        return 0.0;
    }
    let sizing = AdaptiveSizing {
        min_edge_mm: edge_mm,
        max_error_mm: settings.sizing_error * edge_mm,
    };
    let h_max = edge_mm * settings.sizing_max_edge.max(FLAT_EDGES);
    let edges = curvature_edges(mesh, h_max, sizing);
    let areas = mesh.vertex_areas();
    let total = areas.iter().fold(0.0, |sum, a| sum + a);
    let flat: f64 = (edges.iter().zip(&areas))
        .filter(|(&h, _)| h >= FLAT_EDGES * edge_mm)
        .fold(0.0, |sum, (_, a)| sum + a);
    if total > 0.0 {
        flat / total
    } else {
        0.0
    }
}

/// The verdict on `mesh` before stage `stage` (edge `edge_mm`).
pub fn judge_surface(
    mesh: &TriMesh,
    stage: usize,
    edge_mm: f64,
    settings: &Settings,
) -> SurfaceVerdict {
    let flat_share = flat_share(mesh, edge_mm, settings);
    SurfaceVerdict {
        stage,
        flat_share,
        curved: flat_share < FLAT_FACED_SHARE,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::shapes::{glass_block, icosphere};
    use crate::reconstruct::config::Preset;

    #[test]
    fn a_block_is_flat_faced_and_a_sphere_is_curved() {
        let settings = Settings::preset(Preset::Accurate);
        let edge = 1.5;
        let block = crate::remesh::remesh(
            &glass_block(1.0),
            &crate::reconstruct::remesh_options(&settings, edge),
        )
        .unwrap();
        let sphere = icosphere(25.0, 5);
        let (b, s) = (
            judge_surface(&block, 5, edge, &settings),
            judge_surface(&sphere, 5, edge, &settings),
        );
        eprintln!(
            "flat shares: block {:.3}, sphere {:.3}",
            b.flat_share, s.flat_share
        );
        assert!(!b.curved && b.flat_share > 2.0 * FLAT_FACED_SHARE, "{b:?}");
        assert!(s.curved && s.flat_share < 0.2 * FLAT_FACED_SHARE, "{s:?}");
        let uniform = Settings {
            sizing_error: 0.0,
            ..settings
        };
        assert_eq!(flat_share(&block, edge, &uniform), 0.0);
    }

    #[test]
    fn a_curved_verdict_smooths_only_the_raised_stages_less() {
        let mut checkpoint = crate::reconstruct::Checkpoint::example(None);
        checkpoint.settings = Settings::preset(Preset::Accurate);
        let total = checkpoint.settings.total_stages();
        let first = (0..total)
            .find(|&g| checkpoint.settings.judges_surface_before(g))
            .expect("accurate judges the surface");
        let smoothing = |c: &crate::reconstruct::Checkpoint| -> Vec<f64> {
            (0..total)
                .map(|g| c.stage_settings(g).0.weight_smoothness)
                .collect()
        };
        let flat = smoothing(&checkpoint);
        checkpoint.surface = Some(SurfaceVerdict {
            stage: first,
            flat_share: 0.0,
            curved: true,
        });
        let curved = smoothing(&checkpoint);
        for g in 0..total {
            match g >= first {
                true => assert!(curved[g] < flat[g], "stage {g}: {curved:?} {flat:?}"),
                false => assert_eq!(curved[g], flat[g], "stage {g}"),
            }
        }
    }
}
